//! `brickworld bench flight`: fly a streamed world's render window along
//! the camera's line for a long way and watch memory against the budget,
//! the cost of each slide, how fast the fetchers keep up, and what frames
//! cost on the way.
//!
//! The flight runs in this process with no simulation, so the resident
//! memory it samples is the window, its cache and the fetchers, nothing
//! else (plus the process's baseline, measured before the window opens).

use std::sync::Arc;
use std::time::{Duration, Instant};

use anyhow::{Result, bail};
use glam::DVec3;
use serde::Serialize;

use crate::engine::world_config::{CameraMode, WorldConfig};
use crate::scene::budget::rss_kb;
use crate::scene::{ChunkGen, RenderWindow, WindowSettings};
use crate::trace::{Camera, RenderOptions, render};

/// The flight's report.
#[derive(Debug, Serialize)]
pub struct FlightReport {
    /// Voxels flown.
    pub distance: f64,
    /// Wall seconds.
    pub seconds: f64,
    /// Voxels per second achieved (each step waits for exact columns when
    /// `exact` is set).
    pub voxels_per_s: f64,
    /// Whether every step waited for its window to be exact.
    pub exact: bool,
    /// The memory budget, bytes.
    pub budget_bytes: u64,
    /// Resident memory before the window opened, KiB.
    pub baseline_kb: u64,
    /// (distance, resident KiB) samples.
    pub rss_kb: Vec<(f64, u64)>,
    /// Largest resident memory, KiB.
    pub rss_max_kb: u64,
    /// Largest resident memory over the budget, percent (negative: under).
    pub rss_max_over_budget_pct: f64,
    /// Slides of the window.
    pub slides: u64,
    /// Mean and worst slide time, ms.
    pub slide_ms_mean: f64,
    /// Worst.
    pub slide_ms_max: f64,
    /// Frames rendered on the way and their mean time, ms.
    pub frames: u64,
    /// Mean frame time.
    pub frame_ms_mean: f64,
    /// Columns still coarse when frames were drawn, mean fraction.
    pub coarse_fraction_mean: f64,
    /// The window at the end.
    pub window: crate::scene::WindowStats,
}

/// A streamed world's camera at the start of a benchmark: the config's
/// eye and target, else above the origin looking along +x and down.
pub fn start_view(cfg: &WorldConfig) -> (DVec3, DVec3) {
    let eye = cfg
        .camera
        .eye
        .unwrap_or(DVec3::new(0.0, cfg.size.y as f64 * 1.2, 0.0));
    let target = cfg
        .camera
        .target
        .unwrap_or(eye + DVec3::new(300.0, -100.0, 0.0));
    (eye, target)
}

/// Fly `distance` voxels in `step`-voxel steps along the world's camera
/// line (or along +x), drawing a frame every `frame_every` voxels.
pub fn run(
    cfg: &WorldConfig,
    distance: f64,
    step: f64,
    frame_every: f64,
    exact: bool,
    progress: &indicatif::ProgressBar,
) -> Result<FlightReport> {
    let Some(stream) = cfg.stream else {
        bail!("bench flight needs a streamed world (a [stream] table in its config)");
    };
    if !(distance > 0.0 && step > 0.0 && frame_every > 0.0) || distance / step > 1e7 {
        bail!("--distance, --step and --frame-every must be positive, at most 10^7 steps");
    }
    let size = (!cfg.unbounded).then_some(cfg.size);
    let gen_ = Arc::new(ChunkGen::new(&cfg.source, size, cfg.size.y, cfg.seed)?);
    let (eye0, target0) = start_view(cfg);
    let dir = match cfg.camera.mode {
        CameraMode::Line { velocity } if velocity.length() > 0.0 => velocity.normalize(),
        _ => DVec3::X,
    };
    // The render window's coordinates stop at ±10^9 voxels: a flight past
    // them went on "flying" with the window pinned at the edge and
    // reported the distance as flown (regression, panic audit).
    let end = eye0 + dir * distance;
    if !end.is_finite() || end.abs().max_element() > 1e9 {
        bail!(
            "--distance {distance}: the flight would end at ({:.0}, {:.0}, {:.0}), past the ±10^9 voxels a world's coordinates reach",
            end.x,
            end.y,
            end.z
        );
    }
    let settings = WindowSettings {
        radius: WindowSettings::radius_for(stream.view_distance),
        budget_bytes: stream.memory_budget,
        fetchers: stream.fetchers,
    };
    let baseline_kb = rss_kb();
    // What the process holds already, and the margin the engine keeps, is
    // a floor no budget can be under (regression: 1 byte was accepted and
    // the report compared 117 MiB with a budget of 0 KiB).
    let floor = baseline_kb * 1024 + crate::engine::streaming::RUNTIME_MARGIN;
    if stream.memory_budget < floor {
        bail!(
            "memory budget {} is too small: the process already holds {} and keeps a margin of {}; give at least {} (--memory-budget)",
            crate::scene::budget::human(stream.memory_budget),
            crate::scene::budget::human(baseline_kb * 1024),
            crate::scene::budget::human(crate::engine::streaming::RUNTIME_MARGIN),
            crate::scene::budget::human(floor)
        );
    }
    let mut w = RenderWindow::new(gen_, None, settings, eye0, None, None)?;
    w.settle(Duration::from_secs(60));
    w.measure_overhead();
    let opts = RenderOptions {
        shadows: cfg.look.shadows,
        ..Default::default()
    };
    let steps = (distance / step).ceil() as u64;
    progress.set_length(steps);
    let t0 = Instant::now();
    let (mut rss, mut slide_ms, mut frame_ms, mut coarse) =
        (Vec::new(), Vec::new(), Vec::new(), Vec::new());
    let mut last_slides = 0;
    let mut next_frame = 0.0;
    for i in 0..=steps {
        let d = (i as f64 * step).min(distance);
        let eye = eye0 + dir * d;
        w.update(eye, None, &[]);
        if exact {
            w.settle(Duration::from_secs(60));
        }
        let s = w.stats();
        if s.slides > last_slides {
            last_slides = s.slides;
            slide_ms.push(s.slide_ms);
        }
        if d >= next_frame {
            next_frame += frame_every;
            let cam = Camera::new(
                eye,
                target0 + dir * d,
                cfg.camera.fov,
                cfg.width,
                cfg.height,
            )?;
            let t = Instant::now();
            let world = w.world();
            let _ = render(&world.brickmap(), &cam, world.store().palette(), &opts);
            frame_ms.push(t.elapsed().as_secs_f64() * 1e3);
            coarse.push(s.coarse as f64 / s.columns.max(1) as f64);
        }
        if i % 8 == 0 || i == steps {
            rss.push((d, rss_kb()));
        }
        progress.set_position(i);
    }
    let seconds = t0.elapsed().as_secs_f64();
    let mean = |v: &[f64]| v.iter().sum::<f64>() / v.len().max(1) as f64;
    let rss_max_kb = rss.iter().map(|r| r.1).max().unwrap_or(0);
    // The budget the window kept to (less than asked where the machine has less).
    let budget = w.budget_bytes();
    let budget_kb = budget as f64 / 1024.0;
    Ok(FlightReport {
        distance,
        seconds,
        voxels_per_s: distance / seconds,
        exact,
        budget_bytes: budget,
        baseline_kb,
        rss_max_over_budget_pct: (rss_max_kb as f64 - budget_kb) / budget_kb * 100.0,
        rss_max_kb,
        rss_kb: rss,
        slides: w.stats().slides,
        slide_ms_mean: mean(&slide_ms),
        slide_ms_max: slide_ms.iter().copied().fold(0.0, f64::max),
        frames: frame_ms.len() as u64,
        frame_ms_mean: mean(&frame_ms),
        coarse_fraction_mean: mean(&coarse),
        window: w.stats(),
    })
}
