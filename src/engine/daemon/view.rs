//! Where the engine looks and what it shows: the camera at a tick
//! ([`Engine::camera_at`]), the region the column scripts run on
//! ([`Engine::sim_region`]) and the frames offered to the render thread
//! ([`Engine::offer_frame`], and [`Engine::offer_view`] after a camera
//! move).

use std::time::Instant;

use glam::{DVec3, IVec3};

use super::Engine;
use crate::engine::render_thread::{FrameJob, FrameWorld};
use crate::engine::world_config::{CameraMode, SimRegion};
use crate::trace::Camera;

impl Engine {
    /// Every `frames.every` ticks: hand the renderer a snapshot if it is
    /// idle, else count a skipped frame.
    pub(super) fn offer_frame(&mut self) {
        let tick = self.ws.sim.tick();
        if !tick.is_multiple_of(self.cfg.frames_every) {
            return;
        }
        if let Some(why) = self.renderer.take_death() {
            let msg = format!(
                "the render thread stopped ({why}): no more frames are drawn, while the simulation and its commits go on; this is a bug (please report it), and a restart draws again"
            );
            crate::say!("error: {msg}");
            self.render_error = Some(msg);
        }
        if !self.renderer.ready() {
            self.renderer.skip();
            return;
        }
        self.send_frame(tick, true);
    }

    /// After the camera moved (`/camera`, `/camera/path`): a frame of the
    /// present tick for the live view, as soon as the renderer is idle, so
    /// that a moved camera shows while the engine is paused or between
    /// frame ticks (regression, viewer probe: dragging a paused world
    /// showed nothing). It is not written to the frames directory, which
    /// keeps one frame per `frames.every` ticks.
    pub(super) fn offer_view(&mut self) {
        if !self.view_due || !self.renderer.ready() {
            return;
        }
        self.send_frame(self.ws.sim.tick(), false);
    }

    /// Hand the renderer the world at `tick` (whole the first time, then
    /// the bricks changed since) and the camera then; `keep`: written to
    /// the frames directory.
    fn send_frame(&mut self, tick: u64, keep: bool) {
        // Cleared first: a camera that cannot be placed is not retried
        // every loop.
        self.view_due = false;
        let Ok(cam) = self.camera_at(tick) else {
            return;
        };
        // The render thread keeps its own copy: the first job carries the
        // world, every later one only the bricks that changed since.
        let copy = Instant::now();
        let dirty: Vec<IVec3> = self.dirty_pending.drain().collect();
        let full = !self.mirror_sent;
        let world = if full {
            FrameWorld::Full(Box::new(self.world.clone()))
        } else {
            FrameWorld::Delta(self.world.delta(&dirty))
        };
        self.snapshot_ms = copy.elapsed().as_secs_f64() * 1e3;
        let left = match (&self.follow, full) {
            (Some(f), true) => f.left(),
            _ => Vec::new(),
        };
        let job = FrameJob {
            tick,
            world,
            dirty,
            camera: cam,
            left,
            keep,
        };
        match self.renderer.offer(job) {
            Ok(()) => {
                self.mirror_sent |= full;
                if let (Some(f), true) = (self.follow.as_mut(), full) {
                    f.delivered();
                }
            }
            Err(back) => {
                self.dirty_pending.extend(back);
                self.view_due |= !keep;
            }
        }
    }

    /// The tiles the column scripts run on this tick (`[sim] region` or
    /// `radius` around the camera's eye), None for everywhere.
    pub(super) fn sim_region(&self) -> Option<(glam::IVec2, glam::IVec2)> {
        let tile = |x: f64| (x.floor() as i64).div_euclid(8).clamp(-(1 << 28), 1 << 28) as i32;
        if self.cfg.stream.is_some() {
            // The engine's world is the region (whole chunk columns).
            return None;
        }
        match self.cfg.sim_region {
            SimRegion::Everywhere => None,
            SimRegion::Box { min, max } => Some((
                glam::IVec2::new(tile(min.x as f64), tile(min.y as f64)),
                glam::IVec2::new(tile(max.x as f64 - 1.0) + 1, tile(max.y as f64 - 1.0) + 1),
            )),
            SimRegion::AroundCamera { radius } => {
                let eye = self.camera_at(self.ws.sim.tick()).ok()?.eye;
                Some((
                    glam::IVec2::new(tile(eye.x - radius), tile(eye.z - radius)),
                    glam::IVec2::new(tile(eye.x + radius) + 1, tile(eye.z + radius) + 1),
                ))
            }
        }
    }

    pub(super) fn camera_at(&self, tick: u64) -> Result<Camera, crate::trace::CameraError> {
        let views = self.world.default_views();
        let c = &self.camera;
        let (mut eye, mut target) = match (c.eye, c.target) {
            (Some(e), Some(t)) => (e, t),
            _ => (DVec3::from(views[1].eye), DVec3::from(views[1].target)),
        };
        let phase = |period_s: f64| tick as f64 * self.cfg.dt / period_s;
        match c.mode {
            CameraMode::Fixed => {}
            CameraMode::Orbit { period_s } => {
                let angle = phase(period_s) * std::f64::consts::TAU;
                let d = eye - target;
                let (s, co) = angle.sin_cos();
                eye = target + DVec3::new(d.x * co - d.z * s, d.y, d.x * s + d.z * co);
            }
            CameraMode::Fly { to, period_s } => {
                // 0 → 1 → 0 over one period.
                let f = 1.0 - (phase(period_s).fract() * 2.0 - 1.0).abs();
                let step = (to - eye) * f;
                eye += step;
                target += step;
            }
            CameraMode::Line { velocity } => {
                let step = velocity * (tick as f64 * self.cfg.dt);
                eye += step;
                target += step;
            }
        }
        Camera::new(eye, target, c.fov, self.cfg.width, self.cfg.height)
    }
}
