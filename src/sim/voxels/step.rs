//! The voxel grid's step: scripts with `grid = "voxels"` run once per
//! candidate brick and pass, reading the previous generation of the
//! brick's materials and channels with a one-voxel halo (10³) and writing
//! only its own 8³ cells. Outputs are committed in sorted brick order after
//! each pass (double buffering), so the result is bit-identical for any
//! thread count; a script whose step fails is rolled back alone.
//!
//! **Scheduling.** The candidates of a step are the active bricks, or with
//! `only = {…}` the active bricks holding one of those materials (found from
//! a per-brick presence bitset, never by scanning), dilated by one brick so
//! that anything can move into a neighbour. A brick unchanged for
//! [`SLEEP_AFTER`] steps sleeps; a change wakes its 26 neighbours; bricks
//! holding a `keep_awake` material never sleep. `every = N` runs a script
//! on every Nth tick.
//!
//! **Validation.** Written materials must be registered (or air), channel
//! values finite and within their declared `ranges`, and `conserved`
//! channels' totals unchanged beyond round-off; otherwise the script's step
//! is rejected with the script, brick and value named.

use std::sync::atomic::{AtomicU64, Ordering};

use super::scripts::Loaded;
use std::time::Instant;

use glam::IVec3;
use rustc_hash::{FxHashMap, FxHashSet};

use super::channels::VoxelChannels;
use super::exec::{Job, run_script};
use super::halo::{SELF, neighbour_offset};
use crate::sim::script::VOXEL_CELLS;
use crate::sim::{SimError, StepKey};
use crate::world::{BRICK_EDGE, BrickStore, MaterialRegistry};

/// Steps without change before a brick sleeps.
pub const SLEEP_AFTER: u8 = 2;
/// Failed steps in a row before a voxel script is suspended.
pub const SUSPEND_AFTER: u32 = 3;
/// The material kernels see outside the world's bounds (a wall).
pub const BOUNDARY: u8 = 255;

static STEP_SERIAL: AtomicU64 = AtomicU64::new(1 << 40);

/// A 256-bit set of material ids.
pub(super) type MatSet = [u64; 4];

pub(super) fn set_of(ids: impl IntoIterator<Item = u8>) -> MatSet {
    let mut s = [0u64; 4];
    for i in ids {
        s[i as usize >> 6] |= 1 << (i & 63);
    }
    s
}

fn presence_of(d: &[u8; VOXEL_CELLS]) -> MatSet {
    set_of(d.iter().copied())
}

fn meets(a: &MatSet, b: &MatSet) -> bool {
    a.iter().zip(b).any(|(x, y)| x & y != 0)
}

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

/// For each cell of a brick, the neighbours (bit n = neighbour n, the
/// brick itself included) that something in the cell can reach within
/// `passes` voxels: on each axis the brick itself, and the lower or upper
/// neighbour when the cell lies within `passes` of that face.
fn reach_masks(passes: usize) -> &'static [u32; VOXEL_CELLS] {
    static TABLES: std::sync::OnceLock<Vec<[u32; VOXEL_CELLS]>> = std::sync::OnceLock::new();
    let tables = TABLES.get_or_init(|| {
        (0..=BRICK_EDGE as usize)
            .map(|r| {
                let r = r as i32;
                std::array::from_fn(|i| {
                    let c = [i as i32 % 8, i as i32 / 8 % 8, i as i32 / 64];
                    let sides = |v: i32| -> Vec<i32> {
                        let mut s = vec![0];
                        if v < r {
                            s.push(-1);
                        }
                        if v >= BRICK_EDGE - r {
                            s.push(1);
                        }
                        s
                    };
                    let mut m = 0u32;
                    for dz in sides(c[2]) {
                        for dy in sides(c[1]) {
                            for dx in sides(c[0]) {
                                m |= 1 << ((dx + 1) + (dy + 1) * 3 + (dz + 1) * 9);
                            }
                        }
                    }
                    m
                })
            })
            .collect()
    });
    &tables[passes.clamp(1, BRICK_EDGE as usize)]
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
            active,
            quiet: FxHashMap::default(),
            presence: FxHashMap::default(),
            wake_pending: false,
            tick: 0,
            seed,
        }
    }

    fn inside(&self, b: IVec3) -> bool {
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

    /// Bricks awake.
    pub fn active_bricks(&self) -> usize {
        self.active.len()
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

    pub(super) fn wake_all_known(&mut self) {
        self.wake_pending = true;
    }

    /// Wake every brick inside the bounds that is not empty or holds a
    /// channel array (see `wake_pending`).
    fn wake_everything(&mut self, store: &BrickStore) {
        let mut all: Vec<IVec3> = store.iter().map(|(b, _)| b).collect();
        all.extend(self.channels.all_bricks());
        all.retain(|b| self.inside(*b));
        self.active.extend(all);
        self.quiet.clear();
    }

    /// Wake `bricks` and their neighbours, and forget their material
    /// presence (an edit from outside: the column write-back, a user).
    pub fn notify_edited(&mut self, bricks: &[IVec3]) {
        for &b in bricks {
            self.presence.remove(&b);
            self.wake(b);
        }
    }

    fn wake(&mut self, b: IVec3) {
        for n in 0..27 {
            let nb = b + neighbour_offset(n);
            if self.inside(nb) {
                self.active.insert(nb);
                self.quiet.remove(&nb);
            }
        }
    }

    fn presence(&mut self, store: &BrickStore, b: IVec3) -> MatSet {
        if let Some(p) = self.presence.get(&b) {
            return *p;
        }
        let mut d = [0u8; VOXEL_CELLS];
        store.read_dense(b, &mut d);
        let p = presence_of(&d);
        self.presence.insert(b, p);
        p
    }

    /// The bricks script `si` runs on this step, sorted. Its seeds are the
    /// active bricks that hold one of its `only` materials or any value of
    /// its channels (water too shallow to be drawn still flows); without
    /// `only`, every active brick. Each seed runs, and so does each
    /// neighbour that something in the seed can reach this step: a script
    /// of P passes moves things at most P voxels, so a neighbour is added
    /// only when a seed's material or value lies within P voxels of it. A
    /// falling drop in the middle of a brick runs that one brick, not 27.
    /// `sky` scripts run on the world's top layer of bricks only.
    fn candidates(&mut self, store: &BrickStore, si: usize) -> Vec<IVec3> {
        if self.scripts[si].spec.sky {
            let mut out = Vec::new();
            for z in self.lo.z..self.hi.z {
                for x in self.lo.x..self.hi.x {
                    out.push(IVec3::new(x, self.hi.y - 1, z));
                }
            }
            return out;
        }
        let only = self.scripts[si].only;
        let chans = self.scripts[si].channel_ids.clone();
        let reach = reach_masks(self.scripts[si].spec.passes.len());
        let mut active: Vec<IVec3> = self.active.iter().copied().collect();
        active.sort_by_key(|b| (b.z, b.y, b.x));
        let mut out = FxHashSet::default();
        let mut dense = [0u8; VOXEL_CELLS];
        for b in active {
            let mut mask = 0u32;
            for &c in &chans {
                if let Some(v) = self.channels.get(c, b) {
                    for (i, x) in v.iter().enumerate() {
                        if x.to_bits() != 0 {
                            mask |= reach[i];
                        }
                    }
                }
            }
            match only {
                Some(o) => {
                    if meets(&self.presence(store, b), &o) {
                        store.read_dense(b, &mut dense);
                        for (i, &m) in dense.iter().enumerate() {
                            if o[m as usize >> 6] & (1 << (m & 63)) != 0 {
                                mask |= reach[i];
                            }
                        }
                    }
                }
                None => {
                    mask |= 1 << SELF;
                    if store.cell(b) != crate::world::Cell::Empty {
                        store.read_dense(b, &mut dense);
                        for (i, &m) in dense.iter().enumerate() {
                            if m != 0 {
                                mask |= reach[i];
                            }
                        }
                    }
                }
            }
            for n in 0..27 {
                if mask & (1 << n) != 0 {
                    let nb = b + neighbour_offset(n);
                    if self.inside(nb) {
                        out.insert(nb);
                    }
                }
            }
        }
        let mut out: Vec<IVec3> = out.into_iter().collect();
        out.sort_by_key(|b| (b.z, b.y, b.x));
        out
    }

    /// The active set and quiet counters, sorted (for checkpoints).
    #[allow(clippy::type_complexity)]
    ///
    /// A wake still pending (a parameter changed since the last step) is
    /// saved as done, from `store`: the next step of a run that never
    /// stopped wakes exactly those bricks, from the same world (nothing
    /// edits it between a commit and the next step), so the resumed run
    /// continues the same (regression: a pending wake was lost on stop).
    pub fn sleep_state(&self, store: &BrickStore) -> (Vec<IVec3>, Vec<(IVec3, u8)>) {
        let mut active = self.active.clone();
        let mut quiet = self.quiet.clone();
        if self.wake_pending {
            active.extend(
                store
                    .iter()
                    .map(|(b, _)| b)
                    .chain(self.channels.all_bricks())
                    .filter(|b| self.inside(*b)),
            );
            quiet.clear();
        }
        let mut a: Vec<IVec3> = active.into_iter().collect();
        a.sort_by_key(|b| (b.z, b.y, b.x));
        let mut q: Vec<(IVec3, u8)> = quiet.iter().map(|(b, n)| (*b, *n)).collect();
        q.sort_by_key(|(b, _)| (b.z, b.y, b.x));
        (a, q)
    }

    /// Restore what [`sleep_state`](Self::sleep_state) saved. A wake
    /// pending from parameters set before (a resume sets the stored ones)
    /// is dropped: the saved state already holds the wake that was pending
    /// when it was saved, and nothing else (regression: every resume woke
    /// every brick at its first step, which the run that never stopped did
    /// not).
    pub fn restore_sleep_state(&mut self, active: &[IVec3], quiet: &[(IVec3, u8)]) {
        self.wake_pending = false;
        self.active = active.iter().copied().filter(|b| self.inside(*b)).collect();
        self.quiet = quiet
            .iter()
            .copied()
            .filter(|(b, _)| self.inside(*b))
            .collect();
    }

    /// Advance every voxel script by `dt`; changed materials go through
    /// `store`'s recorded edit path. A failed script is rolled back alone.
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
                (s.every, s.suspended.is_some())
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
                (self.lo, self.hi),
                &valid,
                dt,
                serial,
                key,
            );
            let s = &mut self.scripts[si];
            // Bricks this script changed, woken at once so that the next
            // script's seeds include them (regression, from review: a drop
            // rain3d put into a sleeping brick was not a water3d seed in the
            // same tick, so its reach was missing and water could be lost).
            let mut now_changed = Vec::new();
            match result {
                Ok(work) => {
                    if !cands.is_empty() {
                        s.failures = 0;
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
                    s.failures = s.failures.saturating_add(1);
                    if s.failures >= SUSPEND_AFTER {
                        s.suspended = Some(e.clone());
                    }
                    report.errors.push(e);
                }
            }
            for b in now_changed {
                self.wake(b);
            }
            report.script_ms[si] = t0.elapsed().as_secs_f64() * 1e3;
        }
        // Sleep and wake.
        let keep = self.scripts.iter().fold([0u64; 4], |a, s| {
            std::array::from_fn(|i| a[i] | s.keep_awake[i])
        });
        // Every awake brick that nothing changed this tick (whether or not a
        // script visited it) moves towards sleep.
        // A step that rejected a script moves nothing towards sleep.
        let mut awake: Vec<IVec3> = if report.errors.is_empty() {
            self.active.iter().copied().collect()
        } else {
            Vec::new()
        };
        awake.sort_by_key(|b| (b.z, b.y, b.x));
        for b in awake {
            if changed.contains(&b) {
                continue;
            }
            if keep != [0; 4] && meets(&self.presence(store, b), &keep) {
                continue;
            }
            let q = self.quiet.entry(b).or_insert(0);
            *q += 1;
            if *q >= SLEEP_AFTER {
                self.active.remove(&b);
                self.quiet.remove(&b);
            }
        }
        let mut changed: Vec<IVec3> = changed.into_iter().collect();
        changed.sort_by_key(|b| (b.z, b.y, b.x));
        for &b in &changed {
            self.wake(b);
        }
        self.tick += 1;
        report.changed = changed;
        report
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::world::voxel_index;

    #[test]
    fn a_cell_reaches_only_the_neighbours_within_the_scripts_passes() {
        let count = |m: u32| m.count_ones();
        let two = reach_masks(2);
        // The middle of a brick: only the brick itself.
        assert_eq!(two[voxel_index(3, 3, 4)], 1 << SELF);
        // One voxel from the -x face: that neighbour too.
        let m = two[voxel_index(1, 4, 4)];
        assert_eq!(count(m), 2);
        assert_ne!(m & (1 << 12), 0, "-x is neighbour 12");
        // A corner reaches the seven bricks around it.
        assert_eq!(count(reach_masks(1)[voxel_index(7, 7, 7)]), 8);
        assert_eq!(count(reach_masks(1)[voxel_index(6, 7, 7)]), 4);
        // Eight passes reach every neighbour from anywhere.
        assert!(reach_masks(8).iter().all(|&m| count(m) == 27));
    }

    /// A wake pending at a commit (a parameter changed, no step since) is
    /// in the saved sleep state: a resumed run wakes what the run that
    /// never stopped wakes at its next step.
    #[test]
    fn a_pending_wake_is_saved_with_the_sleep_state() {
        let mut store = BrickStore::new(crate::world::Palette::grey_ramp());
        store.set_voxel(IVec3::new(3, 3, 3), 1);
        store.set_voxel(IVec3::new(20, 3, 3), 1);
        let mut sim = VoxelSim::new(&store, IVec3::ZERO, IVec3::splat(32), 1);
        // Everything fell asleep; one brick is quiet.
        sim.active.clear();
        sim.quiet.insert(IVec3::new(2, 0, 0), 3);
        assert_eq!(sim.sleep_state(&store).0, Vec::<IVec3>::new());
        sim.wake_all_known();
        let (active, quiet) = sim.sleep_state(&store);
        assert_eq!(active, vec![IVec3::ZERO, IVec3::new(2, 0, 0)]);
        assert!(quiet.is_empty());
        // The next step wakes the same bricks.
        sim.wake_everything(&store);
        assert_eq!(sim.sleep_state(&store).0, active);
    }

    /// A resume sets the stored parameters (each set wakes everything) and
    /// then restores the sleep state: only the saved bricks are awake after
    /// it (regression: every resume woke every brick at its first step).
    #[test]
    fn restoring_a_sleep_state_drops_the_wake_of_the_parameters_set_before() {
        let mut store = BrickStore::new(crate::world::Palette::grey_ramp());
        store.set_voxel(IVec3::new(3, 3, 3), 1);
        store.set_voxel(IVec3::new(20, 3, 3), 1);
        let mut sim = VoxelSim::new(&store, IVec3::ZERO, IVec3::splat(32), 1);
        sim.wake_all_known();
        sim.restore_sleep_state(&[IVec3::new(2, 0, 0)], &[]);
        assert_eq!(sim.sleep_state(&store).0, vec![IVec3::new(2, 0, 0)]);
    }
}
