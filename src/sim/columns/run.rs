//! A simulation running on a scene: the column simulation and the voxel
//! simulation behind one script registry, built over a scene's columns
//! (with a drained moat or closed edges). Its step, which hands each
//! step's changed bricks to the caller in its report, is in `world_step`.

use std::path::Path;

use crate::scene::SceneWorld;
use crate::sim::script::Grid;
use crate::sim::step::{Kernel, Simulation, StepReport};
use crate::sim::voxels::VoxelSim;
use crate::sim::writeback::{
    ColumnSync, SEDIMENT, SNOW, WATER, ground_of_tile, set_palette, tiles_of,
};
use crate::sim::{Limits, ScriptSource, SimError, read_script};
use crate::sim::{ScriptSpec, ScriptVm};

/// Most column sub-steps one step is split into for the CFL limit; a step
/// that needs more runs at this many, and the limit is not met.
pub const MAX_SUBSTEPS: u32 = 256;

/// The materials of `materials` that hold the ids simulations keep for
/// water, snow and sediment (252 to 254) under other names, as a message
/// for the user; `None` when there is none. A simulation would take those
/// ids over, so the world's voxels of those materials would become water,
/// snow or sediment (regression, panic audit); only a `.vox` model of more
/// than 251 colours can hold them (the loader moves fewer out of the way).
pub fn reserved_conflicts(materials: &crate::world::MaterialRegistry) -> Option<String> {
    use super::writeback::{SEDIMENT, SNOW, WATER};
    let held: Vec<String> = [(WATER, "water"), (SNOW, "snow"), (SEDIMENT, "sediment")]
        .into_iter()
        .filter_map(|(id, sim)| {
            let (name, _) = materials.get(id)?;
            (name != sim).then(|| format!("{name} (id {id})"))
        })
        .collect();
    (!held.is_empty()).then(|| {
        format!(
            "the world's materials {} hold ids 252 to 254, which simulations keep for water, snow and sediment; a .vox model can use at most 251 colours to run them",
            held.join(", ")
        )
    })
}

/// What a world reaching below y = 0 loses to column scripts, which see
/// the world from y = 0 up (their ground, snow and water heights start
/// there), as a warning; `None` when `ws` runs no column script or the
/// world starts at or above 0 (regression, panic audit: a `.vox` model is
/// centred on the origin, and column scripts saw nothing of its lower half,
/// without a word).
pub fn below_zero_warning(ws: &WorldSim, world: &SceneWorld) -> Option<String> {
    let lo = world.bounds().0.y;
    (lo < 0 && ws.sim.script_count() > 0).then(|| {
        format!(
            "warning: column scripts see the world from y = 0 up, and this world reaches down to y = {lo} (a .vox model is centred on the origin): they see nothing below y = 0; voxel scripts (grid = \"voxels\") see all of it"
        )
    })
}

/// A simulation coupled to a scene's voxels.
pub struct WorldSim {
    /// The column simulation.
    pub sim: Simulation,
    /// The voxel simulation.
    pub vox: VoxelSim,
    pub(super) sync: ColumnSync,
    /// Voxel-world tiles `[min, max)`; with drained edges the simulation
    /// also covers a one-tile moat around them.
    pub(super) world_tiles: (glam::IVec2, glam::IVec2),
    /// World tiles only partly inside the world (its size is not a
    /// multiple of the tile), with their outside cells (bit per cell).
    pub(super) partial: Vec<(glam::IVec2, u64)>,
    pub(super) drain: bool,
    /// Water that left the world over its edges (rain falling on the moat
    /// itself is counted here too).
    pub drained: f64,
}

impl WorldSim {
    /// Set up a simulation over `world`'s columns, reading the ground from
    /// its voxels, with closed edges.
    pub fn new(world: &mut SceneWorld) -> Self {
        Self::with_edges(world, false)
    }

    /// As [`new`](Self::new); with `drain`, water flows over the world's
    /// edges into a one-tile moat two units below the lowest ground and is
    /// removed there each step (counted in [`drained`](Self::drained), so
    /// world water + drained water is conserved).
    pub fn with_edges(world: &mut SceneWorld, drain: bool) -> Self {
        let (lo, hi) = world.bounds();
        let (tmin, tmax) = tiles_of(lo, hi);
        let (smin, smax) = if drain {
            (tmin - 1, tmax + 1)
        } else {
            (tmin, tmax)
        };
        let mut sim = Simulation::new(smin, smax);
        sim.set_world_height((hi.y - lo.y) as f64);
        sim.set_world_columns(glam::IVec2::new(lo.x, lo.z), glam::IVec2::new(hi.x, hi.z));
        let mut sync = ColumnSync::new(hi.y);
        let g = sim.channels_mut().channel("ground");
        let mut lowest = f64::INFINITY;
        let mut partial = Vec::new();
        for tz in tmin.y..tmax.y {
            for tx in tmin.x..tmax.x {
                let t = glam::IVec2::new(tx, tz);
                let ground = ground_of_tile(world.store(), t, hi.y);
                let outside = super::writeback::outside_mask(t, lo, hi);
                // Only the world's own columns: a partial tile's outer
                // cells read as ground 0, which sank the moat far below
                // the terrain, and erosion failed over the drop on every
                // world whose size is not a multiple of 8 (regression,
                // hostile probe).
                lowest = ground
                    .iter()
                    .enumerate()
                    .filter(|(c, _)| outside >> c & 1 == 0)
                    .fold(lowest, |m, (_, v)| m.min(*v));
                sim.channels_mut().set(t, g, &ground);
                sync.record(t, &ground);
                if outside != 0 {
                    sync.set_outside(t, outside);
                    partial.push((t, outside));
                }
            }
        }
        if drain {
            // A partial tile's outer cells are moat too: as low, and
            // drained each step (they are never written into voxels).
            for &(t, outside) in &partial {
                // (A tile of ground 0 everywhere stores no array.)
                let mut ground = sim
                    .channels()
                    .get(t, g)
                    .copied()
                    .unwrap_or([0.0; crate::sim::tile::TILE_CELLS]);
                for (c, v) in ground.iter_mut().enumerate() {
                    if outside >> c & 1 != 0 {
                        *v = lowest - 2.0;
                    }
                }
                sim.channels_mut().set(t, g, &ground);
                sync.record(t, &ground);
            }
            let moat = [lowest - 2.0; crate::sim::tile::TILE_CELLS];
            for tz in smin.y..smax.y {
                for tx in smin.x..smax.x {
                    let t = glam::IVec2::new(tx, tz);
                    if !(t.cmpge(tmin).all() && t.cmplt(tmax).all()) {
                        sim.channels_mut().set(t, g, &moat);
                    }
                }
            }
        }
        // A world being built: nothing has drawn or stored it yet, so the
        // bricks recoloured go nowhere.
        let (_, _recoloured) = world.edit(|s, _| set_palette(s));
        for (id, name) in [(WATER, "water"), (SNOW, "snow"), (SEDIMENT, "sediment")] {
            let def = crate::world::MaterialDef {
                color: world.store().palette().rgb(id),
                kind: if id == WATER {
                    crate::world::MaterialKind::Liquid
                } else {
                    crate::world::MaterialKind::Granular
                },
                density: if id == WATER { 1.0 } else { 0.4 },
            };
            let _ = world.materials.register_at(id, name, def);
        }
        let vox = VoxelSim::new(world.store(), lo, hi, 0);
        WorldSim {
            sim,
            vox,
            sync,
            world_tiles: (tmin, tmax),
            partial,
            drain,
            drained: 0.0,
        }
    }

    /// Bytes the column simulation needs at most once its scripts are
    /// loaded: every channel dense on every tile of the simulated area, and
    /// a step's outputs for its widest pass
    /// ([`Simulation::channel_bytes`]). It counted half of every channel
    /// again instead of the widest pass, and one script writing 250
    /// channels took twice what it said (memory probe).
    pub fn column_bytes(&self) -> u64 {
        self.sim.channel_bytes(
            self.sim.channels().channels().count(),
            self.sim.most_writes(),
        )
    }

    /// Refuse a column simulation whose [`column_bytes`](Self::column_bytes)
    /// would not fit what this process may still allocate (regression,
    /// scale probe: three scripts on a 6144 × 4096 world, which fitted
    /// alone, aborted at their first step with "memory allocation failed").
    pub fn check_memory(&self) -> Result<(), crate::scene::SceneError> {
        use crate::scene::budget::{headroom_bytes, human};
        let (need, room) = (self.column_bytes(), headroom_bytes());
        if self.sim.script_count() > 0 && need > room {
            let (a, b) = self.sim.tile_bounds();
            return Err(crate::scene::SceneError::OutOfMemory {
                what: "the column simulation".into(),
                msg: format!(
                    "{} channels over {} by {} tiles need about {}; {} is available: simulate a smaller world or region, or fewer column scripts",
                    self.sim.channels().channels().count(),
                    b.x - a.x,
                    b.y - a.y,
                    human(need),
                    human(room)
                ),
            });
        }
        Ok(())
    }

    /// Load a column Lua script (see [`add_script`](Self::add_script) for
    /// either grid).
    pub fn add_lua(&mut self, src: ScriptSource, limits: Limits) -> Result<usize, SimError> {
        self.unique_name(&src)?;
        self.sim.add_script(src, Kernel::Lua, limits)
    }

    /// A script is known by its name (its file's stem): parameters, logs
    /// and `/status` address it so (regression: `sim --script W --script
    /// W` ran water twice a step, one copy deaf to --param).
    fn unique_name(&self, src: &ScriptSource) -> Result<(), SimError> {
        if self.script_index(&src.name).is_some() {
            return Err(SimError::Declaration {
                script: src.name.to_string(),
                line: None,
                msg: format!(
                    "a script named '{}' is already loaded: each script needs a name (file name) of its own",
                    src.name
                ),
            });
        }
        Ok(())
    }

    /// Load a script on the grid it declares; returns its id (column
    /// scripts first, then voxel scripts, each in load order).
    pub fn add_script(
        &mut self,
        world: &SceneWorld,
        src: ScriptSource,
        limits: Limits,
    ) -> Result<usize, SimError> {
        self.unique_name(&src)?;
        let (_, spec) = ScriptVm::load(&src, limits)?;
        match spec.grid {
            Grid::Columns => {
                // Voxel scripts' ids shift up by one.
                self.sim.add_script(src, Kernel::Lua, limits)
            }
            Grid::Voxels => {
                let i = self.vox.add_script(src, limits, &world.materials)?;
                Ok(self.sim.script_count() + i)
            }
        }
    }

    /// Register the materials of a `materials.lua` and colour them in the
    /// palette (ids are stable: a name keeps its id). Returns the names it
    /// declares and the bricks whose LOD colours changed with the palette
    /// (see [`SceneWorld::set_palette`]).
    pub fn load_materials(
        &mut self,
        world: &mut SceneWorld,
        src: &ScriptSource,
    ) -> Result<(Vec<String>, Vec<glam::IVec3>), SimError> {
        let names = crate::sim::runtime::materials::load_materials(src, &mut world.materials)?;
        let mut palette = world.store().palette().clone();
        world.materials.apply(&mut palette);
        Ok((names, world.set_palette(palette)))
    }

    /// Key every script's random numbers with the world's seed.
    pub fn set_seed(&mut self, seed: u64) {
        self.sim.set_seed(seed);
        self.vox.set_seed(seed);
    }

    /// Every script's source, limits, rate and health, in id order (what
    /// [`rebuild_scripts`](Self::rebuild_scripts) takes).
    pub fn script_states(&self) -> Vec<crate::sim::ScriptState> {
        (0..self.sim.script_count())
            .map(|c| self.sim.script_state(c))
            .chain((0..self.vox.script_count()).map(|v| self.vox.script_state(v)))
            .collect()
    }

    /// Load `scripts` (from [`script_states`](Self::script_states) of the
    /// simulation this one replaces) with their rates and health; their ids
    /// and channel ids come out as before. Parameters are the state's to
    /// restore.
    pub fn rebuild_scripts(
        &mut self,
        world: &SceneWorld,
        scripts: &[crate::sim::ScriptState],
    ) -> Result<(), SimError> {
        for s in scripts {
            let i = self.add_script(world, s.src.clone(), s.limits)?;
            self.set_every(i, s.every);
        }
        for (i, s) in scripts.iter().enumerate() {
            match self.route(i) {
                Ok(c) => self.sim.set_health(c, s.failures, s.suspended.clone()),
                Err(v) => self.vox.set_health(v, s.failures, s.suspended.clone()),
            }
        }
        Ok(())
    }

    /// Give script `i` a health restored from a stored state (see
    /// [`rebuild_scripts`](Self::rebuild_scripts) for a rebuild's).
    pub fn set_health(&mut self, i: usize, failures: u32, suspended: Option<SimError>) {
        match self.route(i) {
            Ok(c) => self.sim.set_health(c, failures, suspended),
            Err(v) => self.vox.set_health(v, failures, suspended),
        }
    }

    /// The source script `i` runs now (hot reloads included).
    pub fn source(&self, i: usize) -> crate::sim::ScriptSource {
        match self.route(i) {
            Ok(c) => self.sim.script_state(c).src,
            Err(v) => self.vox.script_state(v).src,
        }
    }

    fn route(&self, i: usize) -> Result<usize, usize> {
        let n = self.sim.script_count();
        if i < n { Ok(i) } else { Err(i - n) }
    }

    /// Scripts on both grids.
    pub fn script_count(&self) -> usize {
        self.sim.script_count() + self.vox.script_count()
    }

    /// Declarations of script `i`.
    pub fn spec(&self, i: usize) -> &ScriptSpec {
        match self.route(i) {
            Ok(c) => self.sim.spec(c),
            Err(v) => self.vox.spec(v),
        }
    }

    /// The id of the script called `name`.
    pub fn script_index(&self, name: &str) -> Option<usize> {
        (0..self.script_count()).find(|&i| self.spec(i).name == name)
    }

    /// Current parameter values of script `i`.
    pub fn params(&self, i: usize) -> &[f64] {
        match self.route(i) {
            Ok(c) => self.sim.params(c),
            Err(v) => self.vox.params(v),
        }
    }

    /// Set a parameter of script `i` (refused outside its range).
    pub fn set_param(&mut self, i: usize, name: &str, value: f64) -> Result<(), SimError> {
        match self.route(i) {
            Ok(c) => self.sim.set_param(c, name, value),
            Err(v) => self.vox.set_param(v, name, value),
        }
    }

    /// Run script `i` every `every` ticks.
    pub fn set_every(&mut self, i: usize, every: u64) {
        match self.route(i) {
            Ok(c) => self.sim.set_every(c, every),
            Err(v) => self.vox.set_every(v, every),
        }
    }

    /// The tick interval of script `i`.
    pub fn every(&self, i: usize) -> u64 {
        match self.route(i) {
            Ok(c) => self.sim.every(c),
            Err(v) => self.vox.every(v),
        }
    }

    /// Whether script `i` ran on anything awake in the step `report`
    /// describes (false when it was not its tick, or everything it runs on
    /// sleeps).
    pub fn did_work(&self, report: &StepReport, i: usize) -> bool {
        let (awake, ms) = match self.route(i) {
            Ok(c) => (report.active_tiles, report.script_ms.get(c)),
            Err(v) => (report.voxel.candidates, report.voxel.script_ms.get(v)),
        };
        awake > 0 && ms.is_some_and(|&m| m > 0.0)
    }

    /// Milliseconds script `i` took in the step `report` describes.
    pub fn script_ms(&self, report: &StepReport, i: usize) -> f64 {
        match self.route(i) {
            Ok(c) => report.script_ms.get(c).copied().unwrap_or(0.0),
            Err(v) => report.voxel.script_ms.get(v).copied().unwrap_or(0.0),
        }
    }

    /// The totals of the channels script `i` declares `conserved`.
    pub fn conserved_totals(&self, i: usize) -> Vec<(String, f64)> {
        let spec = self.spec(i);
        spec.conserved
            .iter()
            .map(|name| {
                let total = match self.route(i) {
                    Ok(_) => {
                        let ch = self.sim.channels();
                        ch.find(name).map_or(0.0, |id| ch.total(id))
                    }
                    Err(_) => {
                        let ch = self.vox.channels();
                        ch.find(name).map_or(0.0, |id| ch.total(id))
                    }
                };
                (name.clone(), total)
            })
            .collect()
    }

    /// Failed steps in a row of script `i`.
    pub fn failures(&self, i: usize) -> u32 {
        match self.route(i) {
            Ok(c) => self.sim.failures(c),
            Err(v) => self.vox.failures(v),
        }
    }

    /// Why script `i` is suspended, if it is.
    pub fn suspended(&self, i: usize) -> Option<&SimError> {
        match self.route(i) {
            Ok(c) => self.sim.suspended(c),
            Err(v) => self.vox.suspended(v),
        }
    }

    /// Reload the script at `path` (matched by file stem). On error the old
    /// version keeps running and the error (with file and line) is returned.
    /// On success: the script's index and any warnings (parameters clamped
    /// into a narrowed range).
    pub fn reload(
        &mut self,
        world: &SceneWorld,
        path: &Path,
    ) -> Result<Option<(usize, Vec<String>)>, SimError> {
        // Matched before reading: a file that is not a loaded script (a
        // deleted `old.lua`, an editor's lock file) is none of our business
        // (regression: its removal printed "kept the last good version").
        let name = path
            .file_stem()
            .map(|s| s.to_string_lossy().to_string())
            .unwrap_or_default();
        let Some(index) = self.script_index(&name) else {
            return Ok(None);
        };
        let src = read_script(path)?;
        let warnings = match self.route(index) {
            Ok(c) => self.sim.replace_script(c, src)?,
            Err(v) => self.vox.replace_script(v, src, &world.materials)?,
        };
        Ok(Some((index, warnings)))
    }

    /// Wake what script `i` runs on, as its hot reload does (a resume whose
    /// script changed while the engine was stopped).
    pub fn wake_for_reload(&mut self, i: usize) {
        match self.route(i) {
            Ok(_) => self.sim.wake_all(),
            Err(_) => self.vox.wake_all(),
        }
    }

    /// After the channels were replaced (a resume), make the record of the
    /// surfaces last written agree with them, as it does after every step.
    pub fn resync_columns(&mut self) {
        let (tmin, tmax) = self.world_tiles;
        for tz in tmin.y..tmax.y {
            for tx in tmin.x..tmax.x {
                self.sync
                    .resync(self.sim.channels(), glam::IVec2::new(tx, tz));
            }
        }
    }
}
