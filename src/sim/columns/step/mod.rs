//! The parallel, race-free, deterministic step.
//!
//! Each script's passes run in order. In a pass every active tile runs on a
//! rayon worker with its own VM (one per worker thread, created lazily),
//! reading the *previous generation* of its channels with a one-cell halo and
//! writing only its own tile's next generation into a staging overlay. The
//! overlay is committed when all passes of the script succeed; if any tile
//! fails, the script's whole step is dropped and the world stays at the
//! previous generation. Results are merged in sorted tile order, so the
//! outcome is bit-identical for any thread count.
//!
//! **Active set.** A tile that did not change for [`SLEEP_AFTER`] steps
//! sleeps; a change wakes its neighbourhood; edits wake tiles explicitly.
//! Cost therefore grows with the active tiles, not the world.
//!
//! One script's step over the work set (gather, passes, validation) is
//! [`super::exec`]; loading, replacing and tuning scripts is `scripts`.

mod scripts;

use std::sync::Arc;
use std::sync::atomic::{AtomicU64, Ordering};

use glam::IVec2;
use rayon::prelude::*;
use rustc_hash::{FxHashMap, FxHashSet};

use super::exec::{StepContext, StepScratch, WorkSet, run_script};
use crate::sim::SimError;
use crate::sim::channels::{ChannelId, ChannelStore};
use crate::sim::slot::ScriptSlot;
use crate::sim::tile::{HALO_CELLS, TILE_CELLS, TileCoord, neighbourhood};

/// Steps without change before a tile sleeps.
pub const SLEEP_AFTER: u8 = 2;
/// Channels without a declared range are bounded by ± this many world
/// heights (a script that copies the halo's wall value into `ground`, say,
/// is stopped before the write-back allocates bricks up to it).
pub const DEFAULT_BOUND_HEIGHTS: f64 = 4.0;
/// The world height that bound uses is at least this many voxels: a flat
/// world one voxel high would otherwise stop snow at 4 (regression).
pub const MIN_BOUND_HEIGHT: f64 = 64.0;

/// A kernel implemented in Rust, with the same contract as a Lua pass.
pub trait NativeKernel: Send + Sync {
    /// Run pass `pass` on one tile. `reads[i]` is the halo of the script's
    /// channel `i` (zeros for channels the pass does not read); `writes[i]`
    /// holds the current values of channel `i` and receives the new ones.
    fn run(
        &self,
        pass: usize,
        dt: f64,
        params: &[f64],
        reads: &[[f64; HALO_CELLS]],
        writes: &mut [[f64; TILE_CELLS]],
    );
}

/// How a script's passes are executed.
#[derive(Clone)]
pub enum Kernel {
    /// The script's Lua kernels.
    Lua,
    /// A native reference with the same declarations.
    Native(Arc<dyn NativeKernel>),
}

static STEP_SERIAL: AtomicU64 = AtomicU64::new(1);

/// A loaded column script: what both grids keep ([`ScriptSlot`], which it
/// dereferences to), its channel ids, boundary values and kernel.
pub(super) struct Loaded {
    pub(super) slot: ScriptSlot,
    pub(super) ids: Vec<ChannelId>,
    pub(super) boundary: Vec<f64>,
    pub(super) nonneg: Vec<usize>,
    pub(super) kernel: Kernel,
}

crate::sim::slot::extends_slot!(Loaded);

/// What one step did.
#[derive(Clone, Debug, Default)]
pub struct StepReport {
    /// Tiles computed this step.
    pub active_tiles: usize,
    /// Tiles whose channels changed (sorted).
    pub changed_tiles: Vec<TileCoord>,
    /// Scripts whose step was rejected, with why.
    pub errors: Vec<SimError>,
    /// What the voxel scripts did in the same tick.
    pub voxel: crate::sim::voxels::VoxelStepReport,
    /// Milliseconds each column script took (script order; 0 if it did not
    /// run).
    pub script_ms: Vec<f64>,
    /// Bricks whose voxels changed in this step, sorted, each once (set by
    /// `WorldSim`'s steps): the step's editing batch, handed to the caller in
    /// one hop for its renderer and store to take.
    pub bricks: Vec<glam::IVec3>,
}

/// The simulation state: channels, scripts, active set.
pub struct Simulation {
    channels: ChannelStore,
    scripts: Vec<Loaded>,
    tiles_min: TileCoord,
    tiles_max: TileCoord,
    active: FxHashSet<TileCoord>,
    quiet: FxHashMap<TileCoord, u8>,
    tick: u64,
    seed: u64,
    /// Bound of channels without a declared range.
    default_bound: f64,
    /// The world's own columns `[min, max)`, where the tiles around them
    /// are a ring the world drains into (None: all of them are the world's).
    world_columns: Option<(glam::IVec2, glam::IVec2)>,
    /// Tiles `[min, max)` a step runs on (None: all); see
    /// [`set_region`](Simulation::set_region).
    region: Option<(TileCoord, TileCoord)>,
    /// Dense buffers reused by every step (allocating and faulting in
    /// hundreds of MB per step at 2048² cost more than the copies).
    scratch: StepScratch,
}

/// Which tiles sleep and how close the awake ones are to sleeping: part of
/// what defines a world's future, so checkpoints save it.
#[derive(Clone, Debug, Default, PartialEq, Eq)]
pub struct SleepState {
    /// Awake tiles, sorted.
    pub active: Vec<TileCoord>,
    /// Awake tiles' quiet-step counters, sorted by tile.
    pub quiet: Vec<(TileCoord, u8)>,
}

impl Simulation {
    /// A simulation over the tiles `[min, max)` (brick-column coordinates).
    /// Every tile starts awake.
    pub fn new(tiles_min: TileCoord, tiles_max: TileCoord) -> Self {
        let mut active = FxHashSet::default();
        for z in tiles_min.y..tiles_max.y {
            for x in tiles_min.x..tiles_max.x {
                active.insert(IVec2::new(x, z));
            }
        }
        Simulation {
            channels: ChannelStore::default(),
            scripts: Vec::new(),
            tiles_min,
            tiles_max,
            active,
            quiet: FxHashMap::default(),
            tick: 0,
            seed: 0,
            default_bound: f64::MAX,
            world_columns: None,
            region: None,
            scratch: StepScratch::default(),
        }
    }

    /// The world's seed, which keys every script's random numbers.
    pub fn set_seed(&mut self, seed: u64) {
        self.seed = seed;
    }

    /// Bound channels without a declared range to ±`height` (at least
    /// [`MIN_BOUND_HEIGHT`]) × [`DEFAULT_BOUND_HEIGHTS`].
    pub fn set_world_height(&mut self, height: f64) {
        self.default_bound = height.abs().max(MIN_BOUND_HEIGHT) * DEFAULT_BOUND_HEIGHTS;
    }

    /// The world's own columns `[min, max)`: an error at a column outside
    /// them says it lies in the ring of tiles around the world.
    pub fn set_world_columns(&mut self, min: glam::IVec2, max: glam::IVec2) {
        self.world_columns = Some((min, max));
    }

    /// The active set and quiet counters (sorted, for checkpoints).
    pub fn sleep_state(&self) -> SleepState {
        let mut active: Vec<TileCoord> = self.active.iter().copied().collect();
        active.sort_by_key(|t| (t.y, t.x));
        let mut quiet: Vec<(TileCoord, u8)> = self.quiet.iter().map(|(t, q)| (*t, *q)).collect();
        quiet.sort_by_key(|(t, _)| (t.y, t.x));
        SleepState { active, quiet }
    }

    /// Restore what [`sleep_state`](Self::sleep_state) saved (tiles outside
    /// the world are dropped).
    pub fn restore_sleep_state(&mut self, s: &SleepState) {
        let inside = |t: &TileCoord| t.cmpge(self.tiles_min).all() && t.cmplt(self.tiles_max).all();
        self.active = s.active.iter().copied().filter(inside).collect();
        self.quiet = s.quiet.iter().copied().filter(|(t, _)| inside(t)).collect();
    }

    /// Why script `index` is suspended, if it is (it failed
    /// [`SUSPEND_AFTER`](crate::sim::SUSPEND_AFTER) steps in a row; a
    /// reload resumes it).
    pub fn suspended(&self, index: usize) -> Option<&SimError> {
        self.scripts[index].health.suspended()
    }

    /// Failed steps in a row of script `index`.
    pub fn failures(&self, index: usize) -> u32 {
        self.scripts[index].health.failures()
    }

    /// The channels.
    pub fn channels(&self) -> &ChannelStore {
        &self.channels
    }

    /// Replace every channel (a resume): each script's channels are found
    /// again by name, so the store's own id order does not matter.
    pub fn set_channels(&mut self, channels: ChannelStore) {
        self.channels = channels;
        for s in &mut self.scripts {
            s.ids = s
                .spec
                .channels
                .iter()
                .map(|c| self.channels.channel(c))
                .collect();
        }
    }

    /// Mutable channels (initial conditions); wakes nothing by itself.
    pub fn channels_mut(&mut self) -> &mut ChannelStore {
        &mut self.channels
    }

    /// Steps taken.
    pub fn tick(&self) -> u64 {
        self.tick
    }

    /// Tiles currently awake.
    pub fn active_tiles(&self) -> usize {
        self.active.len()
    }

    /// Run steps only on tiles `[min, max)` (None: everywhere). Awake tiles
    /// outside keep their state and stay awake, frozen, until the region
    /// reaches them again; the region's edge is a wall (neighbours outside
    /// it read as the scripts' boundary values, like the world's edge), so
    /// nothing flows across it and conserved channels stay conserved.
    pub fn set_region(&mut self, region: Option<(TileCoord, TileCoord)>) {
        self.region = region;
    }

    /// The region set by [`set_region`](Self::set_region).
    pub fn region(&self) -> Option<(TileCoord, TileCoord)> {
        self.region
    }

    /// World bounds in tiles (the drain moat included).
    pub fn tile_bounds(&self) -> (TileCoord, TileCoord) {
        (self.tiles_min, self.tiles_max)
    }

    /// Wake a tile and its neighbours (after an edit).
    pub fn wake(&mut self, t: TileCoord) {
        for n in neighbourhood(t) {
            if n.cmpge(self.tiles_min).all() && n.cmplt(self.tiles_max).all() {
                self.active.insert(n);
                self.quiet.remove(&n);
            }
        }
    }

    /// Wake every tile.
    pub fn wake_all(&mut self) {
        for z in self.tiles_min.y..self.tiles_max.y {
            for x in self.tiles_min.x..self.tiles_max.x {
                self.active.insert(IVec2::new(x, z));
            }
        }
        self.quiet.clear();
    }

    /// Continue counting ticks from `tick` (after a resume).
    pub fn set_tick(&mut self, tick: u64) {
        self.tick = tick;
    }

    /// Advance every script by `dt`. A script whose step fails is rolled
    /// back alone (reported in [`StepReport::errors`]); the others commit.
    /// A script run every N ticks (see [`set_every`](Self::set_every)) is
    /// advanced by N·`dt` on the ticks it runs.
    pub fn step(&mut self, dt: f64) -> StepReport {
        let serial = STEP_SERIAL.fetch_add(1, Ordering::Relaxed);
        let (lo, hi) = match self.region {
            Some((a, b)) => (a.max(self.tiles_min), b.min(self.tiles_max)),
            None => (self.tiles_min, self.tiles_max),
        };
        let mut tiles: Vec<TileCoord> = self
            .active
            .iter()
            .copied()
            .filter(|t| t.cmpge(lo).all() && t.cmplt(hi).all())
            .collect();
        tiles.sort_by_key(|t| (t.y, t.x));
        let ws = WorkSet::new(&tiles, lo, hi);
        let mut errors = Vec::new();
        let mut changed: FxHashSet<TileCoord> = FxHashSet::default();
        let mut script_ms = vec![0.0; self.scripts.len()];
        for (si, script) in self.scripts.iter_mut().enumerate() {
            if !self.tick.is_multiple_of(script.every) || script.health.suspended().is_some() {
                continue;
            }
            // A script run every N ticks covers N steps' time: its `c.dt`
            // is N·dt (regression: it was dt, so such a script integrated a
            // rate at 1/N of its nominal value).
            let ctx = StepContext {
                dt: dt * script.every as f64,
                serial,
                seed: self.seed,
                tick: self.tick,
                default_bound: self.default_bound,
                world_columns: self.world_columns,
            };
            let t0 = std::time::Instant::now();
            let result = run_script(script, &self.channels, &ws, &ctx, &mut self.scratch);
            match result {
                Ok(written) => {
                    // A step that ran on no tile proves nothing: a failing
                    // script stays failing (regression: its world fell asleep
                    // and the streak reset). Nor does a later sub-step of a
                    // tick that already failed.
                    if !ws.active.is_empty() {
                        script.health.succeeded(self.tick);
                    }
                    // Which tiles changed is found in parallel; the store is
                    // written serially, in sorted tile order.
                    let stride = script.ids.len();
                    for i in written {
                        let data = &self.scratch.data;
                        let id = script.ids[i];
                        let base = &self.channels;
                        let differs: Vec<bool> = ws
                            .active
                            .par_iter()
                            .map(|&w| {
                                let new = &data[w as usize * stride + i];
                                match base.get(ws.tiles[w as usize], id) {
                                    Some(o) => o
                                        .iter()
                                        .zip(new.iter())
                                        .any(|(a, b)| a.to_bits() != b.to_bits()),
                                    None => new.iter().any(|v| v.to_bits() != 0),
                                }
                            })
                            .collect();
                        for (&w, _) in ws.active.iter().zip(&differs).filter(|(_, d)| **d) {
                            let t = ws.tiles[w as usize];
                            changed.insert(t);
                            self.channels.set(t, id, &data[w as usize * stride + i]);
                        }
                    }
                }
                Err(e) => {
                    script.health.failed(self.tick, &e);
                    errors.push(e);
                }
            }
            script_ms[si] = t0.elapsed().as_secs_f64() * 1e3;
        }
        let mut changed: Vec<TileCoord> = changed.into_iter().collect();
        changed.sort_by_key(|t| (t.y, t.x));
        let changed_set: FxHashSet<TileCoord> = changed.iter().copied().collect();
        let active_n = tiles.len();
        // A failed script did not get its say: nothing moves towards sleep
        // in a step that rejected one (regression: a failing script's tiles
        // fell asleep before it was suspended, hiding its error).
        let tiles = if errors.is_empty() { tiles } else { Vec::new() };
        for t in tiles {
            if changed_set.contains(&t) {
                self.quiet.remove(&t);
            } else {
                let q = self.quiet.entry(t).or_insert(0);
                *q += 1;
                if *q >= SLEEP_AFTER {
                    self.active.remove(&t);
                    self.quiet.remove(&t);
                }
            }
        }
        for &t in &changed {
            self.wake(t);
        }
        self.tick += 1;
        StepReport {
            active_tiles: active_n,
            changed_tiles: changed,
            errors,
            script_ms,
            ..Default::default()
        }
    }
}
