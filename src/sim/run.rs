//! A simulation running on a scene: the column simulation, the voxel
//! coupling, and the editing queue that publishes each step's dirty bricks.

use std::path::Path;

use crossbeam_channel::{Receiver, Sender, unbounded};
use glam::IVec3;

use super::step::{Kernel, Simulation, StepReport};
use super::voxels::{ColumnSync, ground_of_tile, set_palette, tiles_of};
use super::{Limits, ScriptSource, SimError};
use crate::scene::SceneWorld;

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
    /// Set up a simulation over `world`'s columns, reading the ground from its voxels.
    pub fn new(world: &mut SceneWorld) -> Self {
        let (lo, hi) = world.bounds;
        let (tmin, tmax) = tiles_of(lo, hi);
        let mut sim = Simulation::new(tmin, tmax);
        let mut sync = ColumnSync::default();
        let g = sim.channels_mut().channel("ground");
        for tz in tmin.y..tmax.y {
            for tx in tmin.x..tmax.x {
                let t = glam::IVec2::new(tx, tz);
                let ground = ground_of_tile(&world.store, t, hi.y);
                sim.channels_mut().set(t, g, &ground);
                sync.record(t, &ground);
            }
        }
        set_palette(&mut world.store);
        let (queue, dirty) = unbounded();
        WorldSim {
            sim,
            sync,
            queue,
            dirty,
        }
    }

    /// Load a Lua script.
    pub fn add_lua(&mut self, src: ScriptSource, limits: Limits) -> Result<usize, SimError> {
        self.sim.add_script(src, Kernel::Lua, limits)
    }

    /// One step: simulate, write changed columns into bricks, patch the grid,
    /// and publish the changed bricks on the editing queue.
    pub fn step(&mut self, world: &mut SceneWorld, dt: f64) -> StepReport {
        let report = self.sim.step(dt);
        self.sync
            .write(self.sim.channels(), &report.changed_tiles, &mut world.store);
        let bricks = world.apply_edits();
        // The receiver lives in `self`, so sending cannot fail.
        let _ = self.queue.send(DirtyBatch {
            tick: self.sim.tick(),
            bricks,
        });
        report
    }
}
