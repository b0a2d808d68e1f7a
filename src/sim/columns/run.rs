//! A simulation running on a scene: the column simulation, the voxel
//! coupling, and the editing queue that publishes each step's dirty bricks.

use std::path::Path;

use crossbeam_channel::{Receiver, Sender, unbounded};
use glam::IVec3;

use crate::scene::SceneWorld;
use crate::sim::step::{Kernel, Simulation, StepReport};
use crate::sim::writeback::{ColumnSync, ground_of_tile, set_palette, tiles_of};
use crate::sim::{Limits, ScriptSource, SimError};

/// One step's dirty bricks, each listed once.
#[derive(Clone, Debug, PartialEq, Eq)]
pub struct DirtyBatch {
    /// Step number (1 for the first step).
    pub tick: u64,
    /// Bricks whose voxels changed in this step.
    pub bricks: Vec<IVec3>,
}

/// A simulation coupled to a scene's voxels.
pub struct WorldSim {
    /// The column simulation.
    pub sim: Simulation,
    sync: ColumnSync,
    /// Voxel-world tiles `[min, max)`; with drained edges the simulation
    /// also covers a one-tile moat around them.
    world_tiles: (glam::IVec2, glam::IVec2),
    drain: bool,
    /// Water that left the world over its edges (rain falling on the moat
    /// itself is counted here too).
    pub drained: f64,
    queue: Sender<DirtyBatch>,
    /// The editing queue's receiving end (the renderer's).
    pub dirty: Receiver<DirtyBatch>,
}

/// Read a script file into a source named after its stem.
pub fn read_script(path: &Path) -> Result<ScriptSource, SimError> {
    let name = path
        .file_stem()
        .map(|s| s.to_string_lossy().to_string())
        .unwrap_or_else(|| "script".into());
    let text = std::fs::read_to_string(path).map_err(|e| SimError::Declaration {
        script: name.clone(),
        line: None,
        msg: format!("cannot read {}: {e}", path.display()),
    })?;
    Ok(ScriptSource {
        name,
        text: text.into(),
    })
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
        let (lo, hi) = world.bounds;
        let (tmin, tmax) = tiles_of(lo, hi);
        let (smin, smax) = if drain {
            (tmin - 1, tmax + 1)
        } else {
            (tmin, tmax)
        };
        let mut sim = Simulation::new(smin, smax);
        sim.set_world_height((hi.y - lo.y) as f64);
        let mut sync = ColumnSync::new(hi.y);
        let g = sim.channels_mut().channel("ground");
        let mut lowest = f64::INFINITY;
        for tz in tmin.y..tmax.y {
            for tx in tmin.x..tmax.x {
                let t = glam::IVec2::new(tx, tz);
                let ground = ground_of_tile(&world.store, t, hi.y);
                lowest = ground.iter().fold(lowest, |m, v| m.min(*v));
                sim.channels_mut().set(t, g, &ground);
                sync.record(t, &ground);
            }
        }
        if drain {
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
        set_palette(&mut world.store);
        let (queue, dirty) = unbounded();
        WorldSim {
            sim,
            sync,
            world_tiles: (tmin, tmax),
            drain,
            drained: 0.0,
            queue,
            dirty,
        }
    }

    /// Load a Lua script.
    pub fn add_lua(&mut self, src: ScriptSource, limits: Limits) -> Result<usize, SimError> {
        self.sim.add_script(src, Kernel::Lua, limits)
    }

    /// Reload the script at `path` (matched by file stem). On error the old
    /// version keeps running and the error (with file and line) is returned.
    /// On success: the script's index and any warnings (parameters clamped
    /// into a narrowed range).
    pub fn reload(&mut self, path: &Path) -> Result<Option<(usize, Vec<String>)>, SimError> {
        let src = read_script(path)?;
        let Some(index) = self.sim.script_index(&src.name) else {
            return Ok(None);
        };
        let warnings = self.sim.replace_script(index, src)?;
        Ok(Some((index, warnings)))
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

    /// Sub-steps needed to keep one step of `dt` within the gravity-wave CFL
    /// limit `dt · (|u| + sqrt(g h)) / dx ≤ cfl` of the `water` script, if one
    /// is loaded (1 otherwise; at most 256).
    pub fn substeps_for(&self, dt: f64, cfl: f64) -> u32 {
        let Some(w) = self.sim.script_index("water") else {
            return 1;
        };
        let spec = self.sim.spec(w);
        let param = |n: &str| {
            spec.params
                .iter()
                .position(|p| p.name == n)
                .map(|i| self.sim.params(w)[i])
        };
        let (Some(g), Some(dx)) = (param("gravity"), param("dx")) else {
            return 1;
        };
        let ch = self.sim.channels();
        let m = |n: &str| ch.find(n).map_or(0.0, |id| ch.max_abs(id));
        let speed = m("u").max(m("v")) + (g * m("water")).sqrt();
        ((dt * speed / (cfl * dx)).ceil() as u32).clamp(1, 256)
    }

    /// One step of `dt`, split into sub-steps that respect the water CFL
    /// limit. The step counts as one tick, whatever its sub-steps (they all
    /// run at the step's tick, so per-script rates see whole steps).
    pub fn step_within_cfl(
        &mut self,
        world: &mut SceneWorld,
        dt: f64,
        cfl: f64,
    ) -> (StepReport, u32) {
        let n = self.substeps_for(dt, cfl);
        let tick = self.sim.tick();
        let mut report = StepReport::default();
        for _ in 0..n {
            self.sim.set_tick(tick);
            let r = self.step(world, dt / n as f64);
            report.active_tiles = report.active_tiles.max(r.active_tiles);
            report.changed_tiles.extend(r.changed_tiles);
            report.errors.extend(r.errors);
        }
        self.sim.set_tick(tick + 1);
        report.changed_tiles.sort_by_key(|t| (t.y, t.x));
        report.changed_tiles.dedup();
        (report, n)
    }

    /// One step: simulate, write changed columns into bricks, patch the grid,
    /// and publish the changed bricks on the editing queue.
    pub fn step(&mut self, world: &mut SceneWorld, dt: f64) -> StepReport {
        let report = self.sim.step(dt);
        let (tmin, tmax) = self.world_tiles;
        let inside = |t: &glam::IVec2| t.cmpge(tmin).all() && t.cmplt(tmax).all();
        if self.drain
            && let Some(w) = self.sim.channels().find("water")
        {
            // Empty the moat: what flowed over the edge has left the world.
            for t in report.changed_tiles.iter().filter(|t| !inside(t)) {
                if let Some(d) = self.sim.channels().get(*t, w) {
                    self.drained += d.iter().sum::<f64>();
                    self.sim
                        .channels_mut()
                        .set(*t, w, &[0.0; crate::sim::tile::TILE_CELLS]);
                }
            }
        }
        let changed: Vec<glam::IVec2> = report
            .changed_tiles
            .iter()
            .copied()
            .filter(inside)
            .collect();
        self.sync
            .write(self.sim.channels(), &changed, &mut world.store);
        let bricks = world.apply_edits();
        // The receiver lives in `self`, so sending cannot fail.
        let _ = self.queue.send(DirtyBatch {
            tick: self.sim.tick(),
            bricks,
        });
        report
    }
}
