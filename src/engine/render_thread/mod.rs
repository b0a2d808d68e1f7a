//! The daemon's render thread: it owns the GPU (or falls back to the CPU),
//! turns frame jobs into PNG frames, and streams the bricks each job names as
//! changed.
//!
//! The simulation never waits for it. The hand-over is a crossbeam channel
//! of capacity one: the engine loop offers a job only when the slot is free,
//! and otherwise skips that frame and keeps coalescing the dirty brick ids
//! (a set, so it is bounded by the world's brick count) for the next job.
//! A job carries a snapshot of the world taken at a step boundary, so the
//! renderer never sees a half-applied step.

use std::path::PathBuf;
use std::sync::Arc;
use std::sync::atomic::{AtomicU64, Ordering};
use std::thread::JoinHandle;

use crossbeam_channel::{Sender, TrySendError, bounded};
use glam::IVec3;

use super::control::Shared;
use super::streaming::StreamPlan;
use crate::scene::{SceneWorld, WindowStats, WorldDelta};
use crate::trace::Camera;

mod stages;
use stages::RenderLoop;

/// The world a frame job brings: the whole of it once, then only what
/// changed, applied to the render thread's own copy.
#[derive(Debug)]
pub enum FrameWorld {
    /// A full copy (the first job).
    Full(Box<SceneWorld>),
    /// The changes since the previous job (O(changed bricks)).
    Delta(WorldDelta),
}

/// One frame to draw.
#[derive(Debug)]
pub struct FrameJob {
    /// The tick the snapshot was taken at (names the PNG).
    pub tick: u64,
    /// The world at that tick, whole or as a delta.
    pub world: FrameWorld,
    /// Bricks changed since the last job the renderer took.
    pub dirty: Vec<IVec3>,
    /// Where to look from.
    pub camera: Camera,
    /// With a whole world after the first (a streamed world's region
    /// moved): the chunk columns the region covered since the last whole
    /// world and no longer does, to be fetched again from the store.
    pub left: Vec<glam::IVec2>,
    /// Written to the frames directory (false: a view for the live
    /// viewers only, rendered because the camera moved).
    pub keep: bool,
}

/// Counters the render thread publishes (read by `/status` and the timeline).
#[derive(Debug, Default)]
pub struct RenderStats {
    frame_ms_bits: AtomicU64,
    streamed: AtomicU64,
    frames: AtomicU64,
    skipped: AtomicU64,
    window: std::sync::Mutex<Option<WindowStats>>,
}

impl RenderStats {
    /// The last frame's render time in milliseconds.
    pub fn frame_ms(&self) -> f64 {
        f64::from_bits(self.frame_ms_bits.load(Ordering::Relaxed))
    }
    /// The last frame's render time, or `None` before the first frame (the
    /// timeline writes `NaN` there, not a 0 ms frame).
    pub fn last_frame_ms(&self) -> Option<f64> {
        // `publish` stores the time before it counts the frame.
        (self.frames() > 0).then(|| self.frame_ms())
    }
    /// Bricks uploaded to the GPU so far.
    pub fn bricks_streamed(&self) -> u64 {
        self.streamed.load(Ordering::Relaxed)
    }
    /// Frames drawn so far.
    pub fn frames(&self) -> u64 {
        self.frames.load(Ordering::Relaxed)
    }
    /// Frames skipped because the renderer was still busy.
    pub fn skipped(&self) -> u64 {
        self.skipped.load(Ordering::Relaxed)
    }
    /// The render window of a streamed world, after the last frame.
    pub fn window(&self) -> Option<WindowStats> {
        self.window.lock().ok().and_then(|w| *w)
    }
}

/// Settings the render thread keeps for its whole life.
#[derive(Clone, Debug)]
pub struct RenderSettings {
    /// How frames are drawn, as the world config says (`auto` says which
    /// tracer it chose, and why, at the first frame).
    pub look: crate::engine::world_config::FrameLook,
    /// A streamed world: the jobs' world is the simulated region, and the
    /// frames show a window around the camera streamed from this plan.
    pub stream: Option<StreamPlan>,
    /// Where frame PNGs go.
    pub frames_dir: PathBuf,
    /// Frames kept on disk; older ones are deleted.
    pub keep: usize,
    /// Most bytes of frames kept on disk; the oldest go first (the newest
    /// frame is always kept).
    pub max_bytes: u64,
}

/// The running render thread.
#[derive(Debug)]
pub struct RenderThread {
    tx: Option<Sender<FrameJob>>,
    handle: Option<JoinHandle<()>>,
    /// Its counters.
    pub stats: Arc<RenderStats>,
}

impl RenderThread {
    /// Start the thread; frames also go to `shared.frame` for `/frame.png`.
    pub fn spawn(settings: RenderSettings, shared: Arc<Shared>) -> std::io::Result<Self> {
        let (tx, rx) = bounded::<FrameJob>(1);
        let stats = Arc::new(RenderStats::default());
        let state = RenderLoop::new(settings, shared, stats.clone());
        let handle = std::thread::Builder::new()
            .name("render".into())
            .spawn(move || state.run(rx))?;
        Ok(RenderThread {
            tx: Some(tx),
            handle: Some(handle),
            stats,
        })
    }

    /// Whether a job offered now would be taken. The engine loop checks this
    /// before it spends time on a snapshot.
    pub fn ready(&self) -> bool {
        self.tx.as_ref().is_some_and(|tx| !tx.is_full()) && !self.died()
    }

    fn died(&self) -> bool {
        self.tx.is_some() && self.handle.as_ref().is_some_and(|h| h.is_finished())
    }

    /// Why the thread ended while it was still wanted (a panic: a bug), the
    /// first time this is asked after it did; it is then let go, and every
    /// later frame is skipped (found by review: a dead render thread went
    /// unseen, frames stopped, and the engine went on making snapshots for
    /// nobody).
    pub fn take_death(&mut self) -> Option<String> {
        if !self.died() {
            return None;
        }
        self.tx = None;
        let why = match self.handle.take()?.join() {
            Ok(()) => "it ended".to_string(),
            Err(p) => p
                .downcast_ref::<&str>()
                .map(|s| s.to_string())
                .or_else(|| p.downcast_ref::<String>().cloned())
                .unwrap_or_else(|| "it panicked".into()),
        };
        Some(why)
    }

    /// Offer a job without waiting. If the renderer is busy the frame is
    /// counted as skipped and the job's dirty bricks come back, to go into
    /// the next job.
    pub fn offer(&self, job: FrameJob) -> Result<(), Vec<IVec3>> {
        let Some(tx) = self.tx.as_ref() else {
            return Err(job.dirty);
        };
        match tx.try_send(job) {
            Ok(()) => Ok(()),
            Err(TrySendError::Full(j) | TrySendError::Disconnected(j)) => {
                self.skip();
                Err(j.dirty)
            }
        }
    }

    /// Count a frame skipped because the renderer was busy.
    pub fn skip(&self) {
        self.stats.skipped.fetch_add(1, Ordering::Relaxed);
    }

    /// Finish the frame in flight and stop the thread, waiting at most
    /// `limit`: a huge frame must not hold up shutdown (the thread is then
    /// left to end with the process; frames are written atomically, so a
    /// half-written one never appears under a final name).
    pub fn finish(mut self, limit: std::time::Duration) {
        self.tx = None;
        if let Some(h) = self.handle.take() {
            let start = std::time::Instant::now();
            while !h.is_finished() && start.elapsed() < limit {
                std::thread::sleep(std::time::Duration::from_millis(10));
            }
            if h.is_finished() {
                let _ = h.join();
            } else {
                crate::say!(
                    "warning: the frame in flight is abandoned ({} s limit at shutdown)",
                    limit.as_secs()
                );
            }
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// Regression (note): the timeline's first row after a start read a
    /// 0 ms frame, before any frame was drawn.
    #[test]
    fn no_frame_time_before_the_first_frame() {
        let stats = RenderStats::default();
        assert_eq!(stats.last_frame_ms(), None);
        stats
            .frame_ms_bits
            .store(12.5f64.to_bits(), Ordering::Relaxed);
        stats.frames.fetch_add(1, Ordering::Relaxed);
        assert_eq!(stats.last_frame_ms(), Some(12.5));
    }

    /// Found by review: a render thread that panicked went unseen. It is
    /// found once, with its message; it is then not ready, and a job
    /// offered gives its bricks back.
    #[test]
    fn a_dead_render_thread_is_found_once_and_offered_nothing() {
        let (tx, _rx) = bounded::<FrameJob>(1);
        // `resume_unwind`: a panic that skips the hook, which prints.
        let handle = std::thread::spawn(|| std::panic::resume_unwind(Box::new("boom")));
        let mut r = RenderThread {
            tx: Some(tx),
            handle: Some(handle),
            stats: Arc::default(),
        };
        while !r.handle.as_ref().unwrap().is_finished() {
            std::thread::sleep(std::time::Duration::from_millis(1));
        }
        assert!(!r.ready());
        assert_eq!(r.take_death().as_deref(), Some("boom"));
        assert_eq!(r.take_death(), None);
        assert!(!r.ready());
    }
}
