//! A [`WorldSim`]'s step: the column scripts in as many sub-steps as the
//! water CFL limit needs (one tick whatever their number), then the voxel
//! step, and the bricks both changed published once, sorted, in the step's
//! report.

use super::run::{MAX_SUBSTEPS, WorldSim};
use crate::scene::SceneWorld;
use crate::sim::step::StepReport;

impl WorldSim {
    /// Sub-steps needed to keep one step of `dt` within the gravity-wave
    /// CFL limit `dt · (|u| + sqrt(g h)) / dx ≤ cfl` of every script that
    /// declares `cfl` (1 if none does; at most [`MAX_SUBSTEPS`]).
    pub fn substeps_for(&self, dt: f64, cfl: f64) -> u32 {
        let mut n = 1;
        for i in 0..self.sim.script_count() {
            let spec = self.sim.spec(i);
            let Some(c) = &spec.cfl else { continue };
            let param = |name: &str| {
                spec.params
                    .iter()
                    .position(|p| p.name == name)
                    .map(|k| self.sim.params(i)[k])
            };
            let (Some(g), Some(dx)) = (param(&c.gravity), param(&c.dx)) else {
                continue;
            };
            let ch = self.sim.channels();
            let m = |name: &str| ch.find(name).map_or(0.0, |id| ch.max_abs(id));
            let speed =
                c.velocities.iter().map(|v| m(v)).fold(0.0, f64::max) + (g * m(&c.depth)).sqrt();
            // A script run every N ticks steps by N·dt.
            let its_dt = dt * self.sim.every(i) as f64;
            n = n.max(((its_dt * speed / (cfl * dx)).ceil() as u32).clamp(1, MAX_SUBSTEPS));
        }
        n
    }

    /// One step of `dt`, split into column sub-steps that respect the
    /// water CFL limit, then one voxel step. The step counts as one tick,
    /// whatever its sub-steps (they all run at the step's tick, so
    /// per-script rates see whole steps), and publishes one batch of dirty
    /// bricks.
    pub fn step_within_cfl(
        &mut self,
        world: &mut SceneWorld,
        dt: f64,
        cfl: f64,
    ) -> (StepReport, u32) {
        let n = self.substeps_for(dt, cfl);
        let tick = self.sim.tick();
        let mut report = StepReport::default();
        let mut bricks = Vec::new();
        for _ in 0..n {
            self.sim.set_tick(tick);
            let r = self.column_step(world, dt / n as f64, &mut bricks);
            report.script_ms.resize(r.script_ms.len(), 0.0);
            for (t, ms) in report.script_ms.iter_mut().zip(&r.script_ms) {
                *t += ms;
            }
            report.active_tiles = report.active_tiles.max(r.active_tiles);
            report.changed_tiles.extend(r.changed_tiles);
            report.errors.extend(r.errors);
        }
        self.sim.set_tick(tick + 1);
        report.changed_tiles.sort_by_key(|t| (t.y, t.x));
        report.changed_tiles.dedup();
        self.voxel_step(world, dt, tick, &mut bricks, &mut report);
        publish(&mut report, bricks);
        (report, n)
    }

    /// One step: the columns (written back into bricks), then the voxel
    /// scripts; the changed bricks go to the grid and the report's
    /// [`bricks`](StepReport::bricks).
    pub fn step(&mut self, world: &mut SceneWorld, dt: f64) -> StepReport {
        let tick = self.sim.tick();
        let mut bricks = Vec::new();
        let mut report = self.column_step(world, dt, &mut bricks);
        self.voxel_step(world, dt, tick, &mut bricks, &mut report);
        publish(&mut report, bricks);
        report
    }

    /// The voxel scripts at `tick`, after telling them which bricks the
    /// columns changed.
    fn voxel_step(
        &mut self,
        world: &mut SceneWorld,
        dt: f64,
        tick: u64,
        bricks: &mut Vec<glam::IVec3>,
        report: &mut StepReport,
    ) {
        if self.vox.script_count() == 0 {
            return;
        }
        self.vox.notify_edited(bricks);
        self.vox.set_tick(tick);
        let (r, changed) = world.edit(|s, m| self.vox.step(s, m, dt));
        let redrawn = self.follow_voxels(world, &changed);
        bricks.extend(changed);
        bricks.extend(redrawn);
        report.errors.extend(r.errors.iter().cloned());
        report.voxel = r;
    }

    /// Give the columns over the bricks in `changed`, which something
    /// other than the columns edited, the ground those bricks now hold
    /// ([`ColumnSync::follow_ground`](super::writeback::ColumnSync::follow_ground)),
    /// wake them, and redraw their snow and water on it. Returns the
    /// bricks the redraw changed (the voxel scripts are told of them).
    pub fn follow_voxels(
        &mut self,
        world: &mut SceneWorld,
        changed: &[glam::IVec3],
    ) -> Vec<glam::IVec3> {
        let (tmin, tmax) = self.world_tiles;
        let mut tiles: Vec<glam::IVec2> = changed
            .iter()
            .map(|b| glam::IVec2::new(b.x, b.z))
            .filter(|t| t.cmpge(tmin).all() && t.cmplt(tmax).all())
            .collect();
        if tiles.is_empty() {
            return Vec::new();
        }
        tiles.sort_by_key(|t| (t.y, t.x));
        tiles.dedup();
        // Water and snow a voxel script holds in its own channel (water3d's
        // fill) stay that script's.
        let vch = self.vox.channels();
        let (vw, vs) = (vch.find("water"), vch.find("snow"));
        let held = |p: glam::IVec3, m: u8| {
            let id = if m == super::writeback::WATER { vw } else { vs };
            id.is_some_and(|id| vch.at(id, p) > 0.0)
        };
        let moved = self
            .sync
            .follow_ground(world.store(), self.sim.channels_mut(), &tiles, held);
        for &t in &moved {
            self.sim.wake(t);
        }
        let (_, redrawn) = world.edit(|s, _| self.sync.write(self.sim.channels(), &moved, s));
        self.vox.notify_edited(&redrawn);
        redrawn
    }

    /// The column scripts for `dt`, written back into bricks; the bricks
    /// changed are appended to `bricks` (and patched into the grid).
    fn column_step(
        &mut self,
        world: &mut SceneWorld,
        dt: f64,
        bricks: &mut Vec<glam::IVec3>,
    ) -> StepReport {
        let report = self.sim.step(dt);
        let (tmin, tmax) = self.world_tiles;
        let inside = |t: &glam::IVec2| t.cmpge(tmin).all() && t.cmplt(tmax).all();
        if self.drain {
            // Empty the moat of every channel a script declares in `drains`:
            // what flowed over the edge has left the world.
            let mut drains: Vec<String> = (0..self.sim.script_count())
                .flat_map(|i| self.sim.spec(i).drains.clone())
                .collect();
            drains.sort();
            drains.dedup();
            for name in drains {
                let Some(w) = self.sim.channels().find(&name) else {
                    continue;
                };
                for t in report.changed_tiles.iter().filter(|t| !inside(t)) {
                    if let Some(d) = self.sim.channels().get(*t, w) {
                        self.drained += d.iter().sum::<f64>();
                        self.sim
                            .channels_mut()
                            .set(*t, w, &[0.0; crate::sim::tile::TILE_CELLS]);
                    }
                }
                for &(t, outside) in &self.partial {
                    if let Some(d) = self.sim.channels().get(t, w) {
                        let mut d = *d;
                        let mut left = 0.0;
                        for (c, v) in d.iter_mut().enumerate() {
                            if outside >> c & 1 != 0 {
                                left += *v;
                                *v = 0.0;
                            }
                        }
                        if left != 0.0 {
                            self.drained += left;
                            self.sim.channels_mut().set(t, w, &d);
                        }
                    }
                }
            }
        }
        let changed: Vec<glam::IVec2> = report
            .changed_tiles
            .iter()
            .copied()
            .filter(inside)
            .collect();
        let (_, written) = world.edit(|s, _| self.sync.write(self.sim.channels(), &changed, s));
        bricks.extend(written);
        report
    }
}

/// The step's changed bricks into its report, sorted and each once.
fn publish(report: &mut StepReport, mut bricks: Vec<glam::IVec3>) {
    bricks.sort_by_key(|b| (b.z, b.y, b.x));
    bricks.dedup();
    report.bricks = bricks;
}
