//! The render thread's loop: one frame job through named stages, from the
//! job's world to a published PNG (see [`RenderLoop`]).

use std::path::PathBuf;
use std::sync::Arc;
use std::sync::atomic::Ordering;
use std::time::{Duration, Instant};

use glam::IVec3;

use super::{FrameJob, FrameWorld, RenderSettings, RenderStats};
use crate::engine::control::Shared;
use crate::engine::control::live::{FrameEvent, unix_ms};
use crate::engine::frames::{FrameFiles, png_bytes, write_frame};
use crate::engine::streaming::columns_of;
use crate::gpu::{GpuBrickmap, GpuContext, StreamConfig};
use crate::scene::{RenderWindow, SceneWorld};
use crate::trace::{Camera, RenderOptions, render, supersample};

/// The render thread's state between jobs. Each job goes through named
/// stages, in order: [`apply_world`](Self::apply_world) (the job's world
/// onto the thread's own copy), [`update_window`](Self::update_window) (a
/// streamed world's window around the camera), [`sync_gpu`](Self::sync_gpu)
/// (changed bricks and colours to the GPU), [`draw`](Self::draw),
/// [`keep_frame`](Self::keep_frame) (the PNG into the frames folder) and
/// [`publish`](Self::publish) (the live frame and the counters).
pub(super) struct RenderLoop {
    settings: RenderSettings,
    shared: Arc<Shared>,
    stats: Arc<RenderStats>,
    gpu: Option<(GpuContext, GpuBrickmap)>,
    gpu_tried: bool,
    /// The frames folder the engine started with, held open and written
    /// through its descriptor: one deleted or replaced since (a new state
    /// directory, another engine's) gets no frames and loses none to
    /// pruning (regression, operator probe: a stale engine wrote its
    /// frames into the state directory of the engine started after it;
    /// the folder's inode number is reused at once, so it cannot tell them).
    held: Option<std::fs::File>,
    frames_at: PathBuf,
    written: FrameFiles,
    /// When a frame file last failed to be written, if the last one did.
    frame_error: Option<Instant>,
    /// The render thread's own copy of the world, kept current by the
    /// jobs' deltas: the engine never copies the world again.
    mirror: Option<SceneWorld>,
    window: Option<RenderWindow>,
}

/// What a job changed in the world the frame shows.
struct Changes {
    /// The job brought a whole world.
    full: bool,
    /// The bricks a delta changed, and those a new palette recoloured.
    delta: Vec<IVec3>,
    /// Recoloured materials (`materials.lua` reloaded), or the first world.
    palette: bool,
    /// What changed in a streamed world's window (slides too).
    window: Vec<IVec3>,
}

/// The world a frame shows: a streamed world's window, else the copy.
fn shown<'a>(mirror: &'a Option<SceneWorld>, window: &'a Option<RenderWindow>) -> &'a SceneWorld {
    match window {
        Some(w) => w.world(),
        None => mirror.as_ref().expect("a world was applied first"),
    }
}

impl RenderLoop {
    pub(super) fn new(
        settings: RenderSettings,
        shared: Arc<Shared>,
        stats: Arc<RenderStats>,
    ) -> Self {
        let held = std::fs::File::open(&settings.frames_dir).ok();
        let frames_at = held
            .as_ref()
            .and_then(crate::files::held_folder)
            .unwrap_or_else(|| settings.frames_dir.clone());
        let written = FrameFiles::scan(&frames_at);
        RenderLoop {
            settings,
            shared,
            stats,
            gpu: None,
            gpu_tried: false,
            held,
            frames_at,
            written,
            frame_error: None,
            mirror: None,
            window: None,
        }
    }

    pub(super) fn run(mut self, jobs: crossbeam_channel::Receiver<FrameJob>) {
        // `BRICKWORLD_TEST_RENDER_PANIC_AT_TICK`: a test hook that makes
        // this thread panic at its first frame of that tick or later, as a
        // bug would, so that the daemon's tests hold what the engine then
        // does (`/status` `render_error`, the simulation going on).
        let panic_at: Option<u64> = std::env::var("BRICKWORLD_TEST_RENDER_PANIC_AT_TICK")
            .ok()
            .and_then(|v| v.parse().ok());
        for job in jobs.iter() {
            if let Some(at) = panic_at
                && job.tick >= at
            {
                panic!("test hook: the render thread panics at tick {}", job.tick);
            }
            self.frame(job);
        }
    }

    /// One job, stage by stage; a stage that cannot go on skips the frame.
    fn frame(&mut self, job: FrameJob) {
        let t = Instant::now();
        let FrameJob {
            tick,
            world,
            dirty,
            camera,
            left,
            keep,
        } = job;
        let Some(mut changes) = self.apply_world(world) else {
            return;
        };
        if self.settings.stream.is_some() {
            let Some(changed) = self.update_window(&camera, &changes, &dirty, &left) else {
                return;
            };
            changes.window = changed;
        }
        self.sync_gpu(&changes, &dirty);
        let png = match self.draw(&camera) {
            Ok(png) => png,
            Err(e) => {
                // A bug, not the world's: said, and the frame skipped.
                crate::say!("error: a frame of tick {tick} could not be encoded as PNG: {e}");
                return;
            }
        };
        // A view rendered for a camera move is for the live viewers only.
        if keep {
            self.keep_frame(tick, &png);
        }
        self.written
            .prune(self.settings.keep, self.settings.max_bytes);
        self.publish(tick, &camera, png, t);
    }

    /// The job's world onto the thread's copy; `None` (frame skipped) for
    /// a delta before any world.
    fn apply_world(&mut self, world: FrameWorld) -> Option<Changes> {
        let full = matches!(world, FrameWorld::Full(_));
        let palette_before = self.mirror.as_ref().map(|m| m.store().palette().clone());
        let mut delta = Vec::new();
        match world {
            FrameWorld::Full(w) => self.mirror = Some(*w),
            FrameWorld::Delta(d) => match self.mirror.as_mut() {
                Some(m) => delta = m.apply_delta(d),
                None => {
                    crate::say!("warning: a frame delta came before the world; frame skipped");
                    return None;
                }
            },
        }
        let world = self.mirror.as_ref().expect("set above");
        Some(Changes {
            full,
            delta,
            palette: palette_before.as_ref() != Some(world.store().palette()),
            window: Vec::new(),
        })
    }

    /// A streamed world's window around the camera, opened at the first
    /// frame; what changed in it, or `None` (frame skipped) if it cannot
    /// be opened.
    fn update_window(
        &mut self,
        camera: &Camera,
        changes: &Changes,
        dirty: &[IVec3],
        left: &[glam::IVec2],
    ) -> Option<Vec<IVec3>> {
        let plan = self.settings.stream.as_ref()?;
        let world = self.mirror.as_ref().expect("applied first");
        let eye = camera.eye;
        // A whole world after the first: the simulated region moved (it is
        // the engine's world).
        let live = columns_of(world);
        match self.window.as_mut() {
            Some(w) => {
                if changes.full {
                    w.set_live(live, world, left);
                }
                w.update(eye, Some(world), dirty)
            }
            None => match RenderWindow::new(
                plan.gen_.clone(),
                Some(live),
                plan.window,
                eye,
                Some(world),
                plan.overlay.clone(),
            ) {
                Ok(mut w) => {
                    // The first frame waits for its exact columns (the
                    // simulation does not); later ones show stand-ins
                    // until then.
                    w.settle(std::time::Duration::from_secs(30));
                    w.measure_overhead();
                    if self.settings.look.tracer != crate::gpu::TracerChoice::Cpu {
                        w.track_changes();
                    }
                    w.set_palette(world.store().palette().clone());
                    self.window = Some(w);
                }
                Err(e) => {
                    crate::say!("warning: cannot open the render window: {e}");
                    return None;
                }
            },
        }
        let w = self.window.as_mut().expect("set above");
        if changes.palette {
            w.set_palette(world.store().palette().clone());
        }
        if let Ok(mut s) = self.stats.window.lock() {
            *s = Some(w.stats());
        }
        Some(w.take_changed())
    }

    /// The GPU, started at the first frame (it says which tracer it chose,
    /// and why), then told what changed.
    fn sync_gpu(&mut self, changes: &Changes, dirty: &[IVec3]) {
        let world = shown(&self.mirror, &self.window);
        if !self.gpu_tried {
            self.gpu_tried = true;
            self.gpu = start_gpu(world, self.settings.look.tracer);
        } else if let Some((ctx, g)) = self.gpu.as_mut() {
            // A streamed world's window reports what changed in it (slides
            // too); a resident one, the job's bricks.
            let changed = if self.settings.stream.is_some() {
                &changes.window
            } else if changes.full {
                dirty
            } else {
                &changes.delta
            };
            g.apply_edits(ctx, world.grid(), world.store().pool(), changed);
            if changes.palette {
                g.set_palette(ctx, world.store().palette());
            }
        }
    }

    /// The frame as PNG bytes (supersampled as the look asks).
    fn draw(&mut self, camera: &Camera) -> Result<Vec<u8>, png::EncodingError> {
        let world = shown(&self.mirror, &self.window);
        let opts = self.settings.look.options();
        let (gpu, stats) = (&mut self.gpu, &self.stats);
        let rgb = supersample(self.settings.look.aa, &opts, |o| {
            draw(gpu, world, camera, o, stats)
        });
        png_bytes(camera.width, camera.height, &rgb)
    }

    /// The frame into the frames folder; a failure is said at most once a
    /// minute, not silently dropped (regression: a full disk or a bad
    /// frames.dir left no trace); the live frame still serves.
    fn keep_frame(&mut self, tick: u64, png: &[u8]) {
        let held = self.held.is_some();
        let wrote = write_frame(&self.frames_at, tick, png).map_err(|e| {
            if e.kind() == std::io::ErrorKind::NotFound && held {
                std::io::Error::other(
                    "its folder was deleted or replaced while the engine runs (a new state directory?), so no frame goes there",
                )
            } else {
                e
            }
        });
        match wrote {
            Ok(path) => {
                self.written.push(path, png.len() as u64);
                if self.frame_error.take().is_some() {
                    crate::say!(
                        "frames are written again to {}",
                        self.settings.frames_dir.display()
                    );
                }
            }
            Err(e) => {
                if self
                    .frame_error
                    .is_none_or(|t: Instant| t.elapsed() >= Duration::from_secs(60))
                {
                    crate::say!(
                        "warning: cannot write frame {}: {e} (the live view goes on; said at most once a minute)",
                        self.settings
                            .frames_dir
                            .join(format!("frame-{tick:08}.png"))
                            .display()
                    );
                    self.frame_error = Some(Instant::now());
                }
            }
        }
    }

    /// The live frame for `/frame.png`, an event for the live viewers (a
    /// value stored, never a wait for them) and the counters.
    fn publish(&self, tick: u64, camera: &Camera, png: Vec<u8>, started: Instant) {
        if let Ok(mut f) = self.shared.frame.lock() {
            *f = Some(png.into());
        }
        let seq = self.stats.frames.load(Ordering::Relaxed) + 1;
        self.shared.frame_events.send_replace(FrameEvent {
            seq,
            tick,
            width: camera.width,
            height: camera.height,
            rendered_unix_ms: unix_ms(),
        });
        self.stats.frame_ms_bits.store(
            (started.elapsed().as_secs_f64() * 1e3).to_bits(),
            Ordering::Relaxed,
        );
        self.stats.frames.fetch_add(1, Ordering::Relaxed);
    }
}

fn start_gpu(
    world: &SceneWorld,
    choice: crate::gpu::TracerChoice,
) -> Option<(GpuContext, GpuBrickmap)> {
    let (ctx, line) = crate::gpu::choose(
        choice,
        "`tracer = \"gpu\"` under `[render]` in the world config",
    );
    crate::say!("{line}");
    let ctx = ctx?;
    match GpuBrickmap::streaming(
        &ctx,
        world.grid(),
        world.store().pool(),
        world.store().palette(),
        StreamConfig::default(),
    ) {
        Ok(g) => Some((ctx, g)),
        Err(e) => {
            crate::say!("warning: {e}; rendering on the CPU");
            None
        }
    }
}

fn draw(
    gpu: &mut Option<(GpuContext, GpuBrickmap)>,
    world: &SceneWorld,
    camera: &Camera,
    opts: &RenderOptions,
    stats: &RenderStats,
) -> Vec<u8> {
    if let Some((ctx, g)) = gpu.as_mut() {
        // The image alone: a frame here is only shown.
        match g.render_image(ctx, camera, opts, world.grid(), world.store().pool()) {
            Ok((rgb, s)) => {
                stats
                    .streamed
                    .fetch_add(s.uploads as u64, Ordering::Relaxed);
                return rgb;
            }
            Err(e) => {
                crate::say!("warning: GPU frame failed ({e}); rendering on the CPU from now on");
                *gpu = None;
            }
        }
    }
    render(&world.brickmap(), camera, world.store().palette(), opts).rgb
}
