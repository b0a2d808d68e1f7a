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

use std::cell::RefCell;
use std::sync::Arc;
use std::sync::atomic::{AtomicU64, Ordering};

use glam::IVec2;
use rayon::prelude::*;
use rustc_hash::{FxHashMap, FxHashSet};

use super::SimError;
use super::channels::{ChannelId, ChannelStore};
use super::script::{Limits, ScriptSource, ScriptSpec, ScriptVm};
use super::tile::{HALO_CELLS, TILE, TILE_CELLS, TileCoord, halo, neighbourhood};

/// Steps without change before a tile sleeps.
pub const SLEEP_AFTER: u8 = 2;

/// A kernel implemented in Rust, with the same contract as a Lua pass.
pub trait NativeKernel: Send + Sync {
    /// Run pass `pass` on one tile. `reads[i]` is the halo of the script's
    /// channel `i` (zeros for channels the pass does not read); `writes[i]`
    /// holds the current values of channel `i` and receives the new ones.
    fn run(&self, pass: usize, dt: f64, params: &[f64], reads: &[[f64; HALO_CELLS]], writes: &mut [[f64; TILE_CELLS]]);
}

/// How a script's passes are executed.
#[derive(Clone)]
pub enum Kernel {
    /// The script's Lua kernels.
    Lua,
    /// A native reference with the same declarations.
    Native(Arc<dyn NativeKernel>),
}

static NEXT_UID: AtomicU64 = AtomicU64::new(1);
static STEP_SERIAL: AtomicU64 = AtomicU64::new(1);

struct Loaded {
    uid: u64,
    src: ScriptSource,
    spec: ScriptSpec,
    params: Vec<f64>,
    ids: Vec<ChannelId>,
    boundary: Vec<f64>,
    nonneg: Vec<usize>,
    kernel: Kernel,
    limits: Limits,
}

/// What one step did.
#[derive(Clone, Debug, Default)]
pub struct StepReport {
    /// Tiles computed this step.
    pub active_tiles: usize,
    /// Tiles whose channels changed (sorted).
    pub changed_tiles: Vec<TileCoord>,
    /// Scripts whose step was rejected, with why.
    pub errors: Vec<SimError>,
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
}

thread_local! {
    static VMS: RefCell<FxHashMap<u64, (ScriptVm, u64)>> = RefCell::new(FxHashMap::default());
}

type Staging = FxHashMap<(TileCoord, ChannelId), [f64; TILE_CELLS]>;

struct View<'a> {
    base: &'a ChannelStore,
    done: &'a Staging,
    current: &'a Staging,
    min: TileCoord,
    max: TileCoord,
}

impl View<'_> {
    #[inline]
    fn tile(&self, t: TileCoord, ch: ChannelId, boundary: f64) -> Option<&[f64; TILE_CELLS]> {
        let _ = boundary;
        if let Some(v) = self.current.get(&(t, ch)) {
            return Some(v);
        }
        if let Some(v) = self.done.get(&(t, ch)) {
            return Some(v);
        }
        self.base.get(t, ch)
    }

    fn inside(&self, t: TileCoord) -> bool {
        t.cmpge(self.min).all() && t.cmplt(self.max).all()
    }

    fn gather(&self, t: TileCoord, ch: ChannelId, boundary: f64, out: &mut [f64; HALO_CELLS]) {
        for nz in -1..=1 {
            for nx in -1..=1 {
                let nt = t + IVec2::new(nx, nz);
                let inside = self.inside(nt);
                let src = if inside { self.tile(nt, ch, boundary) } else { None };
                let x0 = if nx < 0 { TILE - 1 } else { 0 };
                let x1 = if nx > 0 { 1 } else { TILE };
                let z0 = if nz < 0 { TILE - 1 } else { 0 };
                let z1 = if nz > 0 { 1 } else { TILE };
                for lz in z0..z1 {
                    for lx in x0..x1 {
                        let v = match src {
                            Some(s) => s[(lz * TILE + lx) as usize],
                            None if inside => 0.0,
                            None => boundary,
                        };
                        out[halo(lx + nx * TILE, lz + nz * TILE)] = v;
                    }
                }
            }
        }
    }

    fn own(&self, t: TileCoord, ch: ChannelId) -> [f64; TILE_CELLS] {
        self.tile(t, ch, 0.0).copied().unwrap_or([0.0; TILE_CELLS])
    }
}

fn to_bytes<const N: usize, const B: usize>(v: &[f64; N], out: &mut [u8; B]) {
    for (i, x) in v.iter().enumerate() {
        out[i * 8..i * 8 + 8].copy_from_slice(&x.to_le_bytes());
    }
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
        }
    }

    /// The channels.
    pub fn channels(&self) -> &ChannelStore {
        &self.channels
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

    /// World bounds in tiles.
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

    /// Load a script (validated and smoke-tested on a sample tile). Returns
    /// its index.
    pub fn add_script(&mut self, src: ScriptSource, kernel: Kernel, limits: Limits) -> Result<usize, SimError> {
        let loaded = self.prepare(src, kernel, limits)?;
        self.scripts.push(loaded);
        Ok(self.scripts.len() - 1)
    }

    /// Replace script `index` with a new version, keeping parameter values
    /// that still exist. On error the old version stays.
    pub fn replace_script(&mut self, index: usize, src: ScriptSource) -> Result<(), SimError> {
        let (kernel, limits) = (self.scripts[index].kernel.clone(), self.scripts[index].limits);
        let mut loaded = self.prepare(src, kernel, limits)?;
        let old = &self.scripts[index];
        for (i, p) in loaded.spec.params.iter().enumerate() {
            if let Some(j) = old.spec.params.iter().position(|q| q.name == p.name)
                && (p.min..=p.max).contains(&old.params[j])
            {
                loaded.params[i] = old.params[j];
            }
        }
        self.scripts[index] = loaded;
        self.wake_all();
        Ok(())
    }

    fn prepare(&mut self, src: ScriptSource, kernel: Kernel, limits: Limits) -> Result<Loaded, SimError> {
        let (mut vm, spec) = ScriptVm::load(&src, limits)?;
        let ids: Vec<ChannelId> = spec.channels.iter().map(|c| self.channels.channel(c)).collect();
        let boundary: Vec<f64> = spec
            .channels
            .iter()
            .map(|c| if c == "ground" { 1e9 } else { 0.0 })
            .collect();
        let nonneg = spec.nonnegative.iter().filter_map(|n| spec.channels.iter().position(|c| c == n)).collect();
        let params: Vec<f64> = spec.params.iter().map(|p| p.default).collect();
        // Smoke test: every pass once on a dry sample tile, in this fresh VM.
        if matches!(kernel, Kernel::Lua) {
            vm.begin_step(0.01, &spec, &params)?;
            for (pi, pass) in spec.passes.iter().enumerate() {
                vm.run(pi, &pass.name, 0, 0)?;
            }
        }
        Ok(Loaded {
            uid: NEXT_UID.fetch_add(1, Ordering::Relaxed),
            src,
            spec,
            params,
            ids,
            boundary,
            nonneg,
            kernel,
            limits,
        })
    }

    /// Declarations of script `index`.
    pub fn spec(&self, index: usize) -> &ScriptSpec {
        &self.scripts[index].spec
    }

    /// Number of scripts.
    pub fn script_count(&self) -> usize {
        self.scripts.len()
    }

    /// Current parameter values of script `index` (spec order).
    pub fn params(&self, index: usize) -> &[f64] {
        &self.scripts[index].params
    }

    /// Change a parameter; refused outside its declared range. Takes effect
    /// at the next step, with no restart.
    pub fn set_param(&mut self, index: usize, name: &str, value: f64) -> Result<(), SimError> {
        let s = &mut self.scripts[index];
        let err = |msg: String| SimError::Param {
            script: s.spec.name.clone(),
            msg,
        };
        let Some(i) = s.spec.params.iter().position(|p| p.name == name) else {
            let known: Vec<&str> = s.spec.params.iter().map(|p| p.name.as_str()).collect();
            return Err(err(format!("no parameter '{name}' (known: {})", known.join(", "))));
        };
        let p = &s.spec.params[i];
        if !(p.min..=p.max).contains(&value) {
            return Err(err(format!("parameter '{name}' = {value} is outside [{}, {}]", p.min, p.max)));
        }
        s.params[i] = value;
        self.wake_all();
        Ok(())
    }

    /// Advance every script by `dt`. A script whose step fails is rolled
    /// back alone (reported in [`StepReport::errors`]); the others commit.
    pub fn step(&mut self, dt: f64) -> StepReport {
        let serial = STEP_SERIAL.fetch_add(1, Ordering::Relaxed);
        let mut tiles: Vec<TileCoord> = self.active.iter().copied().collect();
        tiles.sort_by_key(|t| (t.y, t.x));
        let mut done: Staging = FxHashMap::default();
        let mut errors = Vec::new();
        for script in &self.scripts {
            match run_script(script, &self.channels, &done, &tiles, self.tiles_min, self.tiles_max, dt, serial) {
                Ok(staged) => done.extend(staged),
                Err(e) => errors.push(e),
            }
        }
        // Commit in sorted order and find what changed.
        let mut keys: Vec<(TileCoord, ChannelId)> = done.keys().copied().collect();
        keys.sort_by_key(|(t, c)| (t.y, t.x, *c));
        let mut changed: FxHashSet<TileCoord> = FxHashSet::default();
        for k in keys {
            let new = &done[&k];
            let old = self.channels.get(k.0, k.1).copied().unwrap_or([0.0; TILE_CELLS]);
            if old.iter().zip(new.iter()).any(|(a, b)| a.to_bits() != b.to_bits()) {
                changed.insert(k.0);
                self.channels.set(k.0, k.1, new);
            }
        }
        let mut changed: Vec<TileCoord> = changed.into_iter().collect();
        changed.sort_by_key(|t| (t.y, t.x));
        let changed_set: FxHashSet<TileCoord> = changed.iter().copied().collect();
        let active_n = tiles.len();
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
        }
    }
}

#[allow(clippy::too_many_arguments)]
fn run_script(
    s: &Loaded,
    base: &ChannelStore,
    done: &Staging,
    tiles: &[TileCoord],
    min: TileCoord,
    max: TileCoord,
    dt: f64,
    serial: u64,
) -> Result<Staging, SimError> {
    let mut staged: Staging = FxHashMap::default();
    for (pi, pass) in s.spec.passes.iter().enumerate() {
        let read_idx: Vec<usize> = pass.reads.iter().map(|r| s.spec.channels.iter().position(|c| c == r).unwrap_or(0)).collect();
        let write_idx: Vec<usize> = pass.writes.iter().map(|w| s.spec.channels.iter().position(|c| c == w).unwrap_or(0)).collect();
        let view = View {
            base,
            done,
            current: &staged,
            min,
            max,
        };
        let results: Result<Vec<(TileCoord, Vec<[f64; TILE_CELLS]>)>, SimError> = tiles
            .par_iter()
            .map(|&t| {
                let mut reads = vec![[0.0f64; HALO_CELLS]; s.spec.channels.len()];
                for &i in &read_idx {
                    view.gather(t, s.ids[i], s.boundary[i], &mut reads[i]);
                }
                let mut writes = vec![[0.0f64; TILE_CELLS]; s.spec.channels.len()];
                for &i in &write_idx {
                    writes[i] = view.own(t, s.ids[i]);
                }
                match &s.kernel {
                    Kernel::Native(k) => k.run(pi, dt, &s.params, &reads, &mut writes),
                    Kernel::Lua => run_lua(s, pi, t, dt, serial, &read_idx, &write_idx, &reads, &mut writes)?,
                }
                Ok((t, write_idx.iter().map(|&i| writes[i]).collect()))
            })
            .collect();
        for (t, outs) in results? {
            for (k, &i) in write_idx.iter().enumerate() {
                staged.insert((t, s.ids[i]), outs[k]);
            }
        }
    }
    // Reject blow-ups before they reach the world.
    for ((t, ch), v) in &staged {
        let i = s.ids.iter().position(|c| c == ch).unwrap_or(0);
        let nonneg = s.nonneg.contains(&i);
        if let Some((cell, x)) = v.iter().enumerate().find(|(_, x)| !x.is_finite() || (nonneg && **x < -1e-9)) {
            return Err(SimError::Unstable {
                script: s.spec.name.clone(),
                msg: format!(
                    "channel '{}' = {x} at column ({}, {}); reduce dt (or enable sub-stepping)",
                    s.spec.channels[i],
                    t.x * TILE + (cell as i32 % TILE),
                    t.y * TILE + (cell as i32 / TILE)
                ),
            });
        }
    }
    Ok(staged)
}

#[allow(clippy::too_many_arguments)]
fn run_lua(
    s: &Loaded,
    pass: usize,
    t: TileCoord,
    dt: f64,
    serial: u64,
    read_idx: &[usize],
    write_idx: &[usize],
    reads: &[[f64; HALO_CELLS]],
    writes: &mut [[f64; TILE_CELLS]],
) -> Result<(), SimError> {
    VMS.with(|cell| {
        let mut map = cell.borrow_mut();
        if !map.contains_key(&s.uid) {
            if map.len() > 32 {
                map.clear();
            }
            let (vm, _) = ScriptVm::load(&s.src, s.limits)?;
            map.insert(s.uid, (vm, 0));
        }
        let r = run_in_vm(map.get_mut(&s.uid).expect("inserted above"), s, pass, t, dt, serial, read_idx, write_idx, reads, writes);
        if r.is_err() {
            // A VM that failed mid-kernel is rebuilt next time.
            map.remove(&s.uid);
        }
        r
    })
}

#[allow(clippy::too_many_arguments)]
fn run_in_vm(
    entry: &mut (ScriptVm, u64),
    s: &Loaded,
    pass: usize,
    t: TileCoord,
    dt: f64,
    serial: u64,
    read_idx: &[usize],
    write_idx: &[usize],
    reads: &[[f64; HALO_CELLS]],
    writes: &mut [[f64; TILE_CELLS]],
) -> Result<(), SimError> {
    {
        let (vm, prepared) = entry;
        if *prepared != serial {
            vm.begin_step(dt, &s.spec, &s.params)?;
            *prepared = serial;
        }
        let mut rb = [0u8; HALO_CELLS * 8];
        for &i in read_idx {
            to_bytes(&reads[i], &mut rb);
            vm.read_buffer(i).write_bytes(0, &rb);
        }
        let mut wb = [0u8; TILE_CELLS * 8];
        for &i in write_idx {
            to_bytes(&writes[i], &mut wb);
            vm.write_buffer(i).write_bytes(0, &wb);
        }
        vm.run(pass, &s.spec.passes[pass].name, t.x, t.y)?;
        for &i in write_idx {
            let bytes: [u8; TILE_CELLS * 8] = vm.write_buffer(i).read_bytes(0);
            for (k, w) in writes[i].iter_mut().enumerate() {
                *w = f64::from_le_bytes(bytes[k * 8..k * 8 + 8].try_into().expect("8 bytes"));
            }
        }
        Ok(())
    }
}
