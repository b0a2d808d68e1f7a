//! The voxel grid's step: scripts with `grid = "voxels"` run once per
//! candidate brick and pass, reading the previous generation of the
//! brick's materials and channels with a one-voxel halo (10³) and writing
//! only its own 8³ cells. Outputs are committed in sorted brick order after
//! each pass (double buffering), so the result is bit-identical for any
//! thread count; a script whose step fails is rolled back alone.
//!
//! **Stages.** [`VoxelSim::step`] runs, for each script due this tick
//! (`every = N` runs it on every Nth), its candidates (from
//! [`super::schedule`]: the active bricks, or with `only = {…}` those
//! holding one of its materials, dilated by what its passes can reach),
//! then its parallel passes, then its validated commit; last, `settle`
//! moves quiet bricks towards sleep and wakes the neighbours of changed
//! ones.
//!
//! **Validation.** Written materials must be registered (or air), channel
//! values finite and within their declared `ranges`, and `conserved`
//! channels' totals unchanged beyond round-off; otherwise the script's step
//! is rejected with the script, brick and value named.

use std::sync::atomic::{AtomicU64, Ordering};
use std::time::Instant;

use glam::IVec3;
use rustc_hash::{FxHashMap, FxHashSet};

use super::channels::VoxelChannels;
use super::exec::{Bounds, Job, run_script};
use super::memory::growth_fits;
use super::schedule::{MatSet, presence_of};
use super::scripts::Loaded;
use crate::sim::runtime::vms::StepStamp;
use crate::sim::script::VOXEL_CELLS;
use crate::sim::{SimError, StepKey};
use crate::world::{BRICK_EDGE, BrickStore, MaterialRegistry};

/// The material kernels see outside the world's bounds (a wall).
pub const BOUNDARY: u8 = 255;

static STEP_SERIAL: AtomicU64 = AtomicU64::new(1 << 40);

/// What one voxel step did.
#[derive(Clone, Debug, Default)]
pub struct VoxelStepReport {
    /// Bricks whose kernels ran (the largest count over scripts).
    pub candidates: usize,
    /// Bricks whose materials changed (sorted), already recorded in the store.
    pub changed: Vec<IVec3>,
    /// Scripts whose step was rejected.
    pub errors: Vec<SimError>,
    /// Milliseconds each script took (script order; 0 if it did not run).
    pub script_ms: Vec<f64>,
}

/// The voxel simulation: per-voxel channels, voxel scripts, the active set.
pub struct VoxelSim {
    pub(super) channels: VoxelChannels,
    pub(super) scripts: Vec<Loaded>,
    /// Brick bounds `[min, max)`.
    pub(super) lo: IVec3,
    pub(super) hi: IVec3,
    /// The world's voxel box, within the bricks `[lo, hi)`.
    pub(super) voxels: (IVec3, IVec3),
    /// Most bytes of many-material blocks the world's brick pool may hold
    /// ([`ARENA_LIMIT`](crate::world::ARENA_LIMIT) unless lowered).
    pub(super) arena_limit: u64,
    pub(super) active: FxHashSet<IVec3>,
    pub(super) quiet: FxHashMap<IVec3, u8>,
    pub(super) presence: FxHashMap<IVec3, MatSet>,
    /// A parameter changed or a script was replaced: wake every brick that
    /// holds something at the next step. Decided from the world then, not
    /// from the presence cache, whose contents depend on the run's history
    /// (regression: after a resume, a parameter change woke fewer bricks
    /// than in a run that never stopped).
    pub(super) wake_pending: bool,
    pub(super) tick: u64,
    pub(super) seed: u64,
}

/// Brick coordinates covering the voxel box `[lo, hi)`.
fn brick_bounds(lo: IVec3, hi: IVec3) -> (IVec3, IVec3) {
    (
        lo.div_euclid(IVec3::splat(BRICK_EDGE)),
        (hi - 1).div_euclid(IVec3::splat(BRICK_EDGE)) + 1,
    )
}

impl VoxelSim {
    /// A voxel simulation over the voxel box `[lo, hi)`; every non-empty
    /// brick starts awake.
    pub fn new(store: &BrickStore, lo: IVec3, hi: IVec3, seed: u64) -> Self {
        let (blo, bhi) = brick_bounds(lo, hi);
        let inside = |b: IVec3| b.cmpge(blo).all() && b.cmplt(bhi).all();
        let active = store
            .iter()
            .map(|(b, _)| b)
            .filter(|b| inside(*b))
            .collect();
        VoxelSim {
            channels: VoxelChannels::default(),
            scripts: Vec::new(),
            lo: blo,
            hi: bhi,
            voxels: (lo, hi),
            arena_limit: crate::world::ARENA_LIMIT,
            active,
            quiet: FxHashMap::default(),
            presence: FxHashMap::default(),
            wake_pending: false,
            tick: 0,
            seed,
        }
    }

    /// Lower the bytes of many-material blocks the world may hold (from
    /// [`ARENA_LIMIT`](crate::world::ARENA_LIMIT)): a step whose changed
    /// bricks would pass it is rejected. For hosts that cap the world, and
    /// for tests of the guard.
    pub fn set_arena_limit(&mut self, bytes: u64) {
        self.arena_limit = bytes.min(crate::world::ARENA_LIMIT);
    }

    pub(super) fn inside(&self, b: IVec3) -> bool {
        b.cmpge(self.lo).all() && b.cmplt(self.hi).all()
    }

    /// The channels.
    pub fn channels(&self) -> &VoxelChannels {
        &self.channels
    }

    /// Mutable channels (initial conditions); wakes nothing by itself.
    pub fn channels_mut(&mut self) -> &mut VoxelChannels {
        &mut self.channels
    }

    /// Set channel `name` to `value` in every voxel of material `id` (and
    /// wake those bricks): initial conditions from a built world, e.g. full
    /// water where the world has water voxels.
    pub fn fill_channel_from_material(
        &mut self,
        store: &BrickStore,
        name: &str,
        id: u8,
        value: f32,
    ) {
        let ch = self.channels.channel(name);
        let mut bricks: Vec<IVec3> = store
            .iter()
            .map(|(b, _)| b)
            .filter(|b| self.inside(*b))
            .collect();
        bricks.sort_by_key(|b| (b.z, b.y, b.x));
        for b in bricks {
            let mut d = [0u8; VOXEL_CELLS];
            store.read_dense(b, &mut d);
            if !d.contains(&id) {
                continue;
            }
            let mut v = self
                .channels
                .get(ch, b)
                .copied()
                .unwrap_or([0.0; VOXEL_CELLS]);
            for (x, m) in v.iter_mut().zip(d.iter()) {
                if *m == id {
                    *x = value;
                }
            }
            self.channels.set(ch, b, &v);
            self.wake(b);
        }
    }

    /// Ticks taken.
    pub fn tick(&self) -> u64 {
        self.tick
    }

    /// Continue from `tick` (after a resume).
    pub fn set_tick(&mut self, tick: u64) {
        self.tick = tick;
    }

    /// Replace every channel (a resume); scripts find theirs again by name.
    pub fn set_channels(&mut self, channels: VoxelChannels) {
        self.channels = channels;
        for s in &mut self.scripts {
            s.channel_ids = s
                .spec
                .channels
                .iter()
                .map(|c| self.channels.channel(c))
                .collect();
        }
    }

    /// Key the scripts' random numbers with the world's seed.
    pub fn set_seed(&mut self, seed: u64) {
        self.seed = seed;
    }

    /// Apply every script's `fills` (a freshly built world's initial
    /// conditions).
    pub fn apply_fills(&mut self, store: &BrickStore, registry: &MaterialRegistry) {
        let fills: Vec<(String, String)> = self
            .scripts
            .iter()
            .flat_map(|s| s.spec.fills.clone())
            .collect();
        for (ch, m) in fills {
            if let Some(id) = registry.id(&m) {
                self.fill_channel_from_material(store, &ch, id, 1.0);
            }
        }
    }

    /// Advance every voxel script by `dt` (one run every N ticks by N·`dt`);
    /// changed materials go through `store`'s recorded edit path. A failed
    /// script is rolled back alone.
    pub fn step(
        &mut self,
        store: &mut BrickStore,
        registry: &MaterialRegistry,
        dt: f64,
    ) -> VoxelStepReport {
        let serial = STEP_SERIAL.fetch_add(1, Ordering::Relaxed);
        let mut report = VoxelStepReport {
            script_ms: vec![0.0; self.scripts.len()],
            ..Default::default()
        };
        let valid: [bool; 256] = std::array::from_fn(|m| {
            m == 0 || (m != BOUNDARY as usize && registry.get(m as u8).is_some())
        });
        if std::mem::take(&mut self.wake_pending) {
            self.wake_everything(store);
        }
        let mut changed: FxHashSet<IVec3> = FxHashSet::default();
        for si in 0..self.scripts.len() {
            let (every, suspended) = {
                let s = &self.scripts[si];
                (s.every, s.health.suspended().is_some())
            };
            if suspended || !self.tick.is_multiple_of(every) {
                continue;
            }
            let t0 = Instant::now();
            let cands = self.candidates(store, si);
            report.candidates = report.candidates.max(cands.len());
            let key = StepKey::new(self.seed, self.tick, &self.scripts[si].spec.name);
            let l = &self.scripts[si];
            let job = Job {
                uid: l.uid.get(),
                src: &l.src,
                spec: &l.spec,
                params: &l.params,
                channel_ids: &l.channel_ids,
                material_ids: &l.material_ids,
                limits: l.limits,
                kernel: &l.kernel,
            };
            let result = run_script(
                &job,
                store,
                &self.channels,
                &cands,
                Bounds {
                    bricks: (self.lo, self.hi),
                    voxels: self.voxels,
                },
                &valid,
                StepStamp {
                    // Run every N ticks: it covers N steps' time (as the
                    // column scripts do).
                    dt: dt * every as f64,
                    serial,
                    key,
                },
            );
            let result = result.and_then(|work| {
                growth_fits(job.spec, store, &work, self.arena_limit).map(|()| work)
            });
            let s = &mut self.scripts[si];
            // Bricks this script changed, woken at once so that the next
            // script's seeds include them (regression, from review: a drop
            // rain3d put into a sleeping brick was not a water3d seed in the
            // same tick, so its reach was missing and water could be lost).
            let mut now_changed = Vec::new();
            match result {
                Ok(work) => {
                    if !cands.is_empty() {
                        s.health.succeeded(self.tick);
                    }
                    for ci in work.changed_mats() {
                        let (b, mats) = (work.cands[ci], &work.mats[ci]);
                        if store.edit_brick(b, |d| *d = *mats) {
                            changed.insert(b);
                            now_changed.push(b);
                            self.presence.insert(b, presence_of(mats));
                        }
                    }
                    for (k, &ch) in s.channel_ids.iter().enumerate() {
                        for (ci, &b) in work.cands.iter().enumerate() {
                            let v = &work.chans[k][ci];
                            let same = match self.channels.get(ch, b) {
                                Some(old) => old
                                    .iter()
                                    .zip(v.iter())
                                    .all(|(a, c)| a.to_bits() == c.to_bits()),
                                None => v.iter().all(|x| x.to_bits() == 0),
                            };
                            if !same {
                                changed.insert(b);
                                now_changed.push(b);
                                self.channels.set(ch, b, v);
                            }
                        }
                    }
                }
                Err(e) => {
                    s.health.failed(self.tick, &e);
                    report.errors.push(e);
                }
            }
            for b in now_changed {
                self.wake(b);
            }
            report.script_ms[si] = t0.elapsed().as_secs_f64() * 1e3;
        }
        report.changed = self.settle(store, changed, !report.errors.is_empty());
        self.tick += 1;
        report
    }
}
