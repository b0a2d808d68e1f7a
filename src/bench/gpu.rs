//! `brickworld bench gpu`: the GPU tracer's primary-ray throughput at a
//! chosen resolution (1920×1080 by default), per view, exact and at each
//! level-of-detail `C`, with beam starts off and on.
//!
//! Each setting first streams until the view is converged (no requests,
//! no pixel shown by an unloaded brick's LOD colour), then times frames.
//! Four times are reported: the whole frame by the wall clock
//! (parameters, dispatch, readback of every pixel's outputs and their
//! decoding on the CPU, which is what `render` pays); the whole frame of
//! the image alone (`render_image`, what the daemon pays); the tracer's
//! passes of a `render` frame on the device, from timestamp queries
//! written at the passes' boundaries; and the tracer's device time per
//! frame with many `render` frames traced back to back (what a renderer
//! that kept its pixels on the GPU would pay; the trace writes every
//! output, as `render`'s does). The last is the headline: one frame at a time leaves
//! the device idle while the CPU reads and decodes, and an NVIDIA H200 so
//! loaded ran its passes up to several times slower (lower clocks) than
//! when kept busy.
//!
//! The scene is a built world (`--scene`, three default views) or a
//! streamed world's render window at its camera's start (`--world`, the
//! start view and a view to the horizon).

use std::time::{Duration, Instant};

use anyhow::{Result, bail};
use glam::DVec3;
use serde::Serialize;

use super::chart::{ChartError, Series, xy_chart};
use crate::gpu::{GpuBrickmap, GpuContext, StreamConfig};
use crate::scene::SceneWorld;
use crate::trace::{Camera, RenderOptions, render, supersample};

/// One named camera view.
#[derive(Clone, Debug)]
pub struct NamedView {
    /// Its name in the report.
    pub name: String,
    /// Eye.
    pub eye: DVec3,
    /// Look-at point.
    pub target: DVec3,
    /// Vertical field of view, degrees.
    pub fov: f64,
}

/// What to measure.
#[derive(Clone, Debug)]
pub struct GpuBenchSetup {
    /// Image size.
    pub width: u32,
    /// Image size.
    pub height: u32,
    /// Footprints `C` (0: exact), in the order measured.
    pub lods: Vec<f32>,
    /// Timed frames per view and setting (the median counts); as many
    /// back to back per submission, at most 100.
    pub frames: u32,
    /// Most bricks uploaded per frame while converging.
    pub uploads: u32,
    /// Shading besides LOD and beams (AO, fog).
    pub look: RenderOptions,
    /// Untimed back-to-back tracing before each setting's timed runs.
    pub warmup: Duration,
    /// Samples per pixel of each view's reference (0: no image error).
    pub spp: u32,
}

/// One view at one setting.
#[derive(Debug, Serialize)]
pub struct GpuRow {
    /// View name.
    pub view: String,
    /// Footprint `C` (0: exact).
    pub lod_c: f32,
    /// Beam starts on.
    pub beam: bool,
    /// Frames until nothing was requested and no pixel showed an unloaded
    /// brick (0: not within 400 frames; the timed frames then show some
    /// bricks by their LOD colour).
    pub frames_to_converge: u32,
    /// Bricks resident on the device when timed.
    pub resident_bricks: u32,
    /// Pool slots when timed.
    pub pool_slots: u32,
    /// Fraction of pixels whose ray hit something.
    pub hit_fraction: f64,
    /// Mean FLIP of the converged image (`render_image`'s) against the
    /// view's reference: the same look traced exactly on the CPU with
    /// `spp` jittered samples a pixel (`None` without `--spp`).
    pub flip: Option<f64>,
    /// Median whole frame by the wall clock, ms.
    pub frame_ms: f64,
    /// Median whole frame of the image alone (`render_image`, as the
    /// daemon draws: 4 bytes a pixel read back), by the wall clock, ms.
    pub image_ms: f64,
    /// Primary rays per second over such frames, millions.
    pub image_mrays_per_s: f64,
    /// Median of the tracer's passes on the device, ms (`None`: the device
    /// has no timestamp queries).
    pub gpu_ms: Option<f64>,
    /// Of which the beam-start pass, ms.
    pub beam_ms: Option<f64>,
    /// Primary rays per second over the whole frame, millions.
    pub frame_mrays_per_s: f64,
    /// Primary rays per second over the tracer's passes, millions.
    pub gpu_mrays_per_s: Option<f64>,
    /// The tracer's device time per frame with `frames` frames traced back
    /// to back in one submission (median of three such runs), ms: the
    /// device busy at its working clocks, as in a renderer that keeps its
    /// pixels on the GPU. One frame at a time leaves it idle between
    /// frames, and a lightly loaded GPU runs at lower clocks.
    pub sustained_ms: Option<f64>,
    /// Whether the last three back-to-back runs agreed within 5 % (else
    /// the median of the last three of 20 runs).
    pub sustained_stable: bool,
    /// Primary rays per second back to back, millions (the headline).
    pub sustained_mrays_per_s: Option<f64>,
}

/// The report.
#[derive(Debug, Serialize)]
pub struct GpuBenchReport {
    /// The adapter.
    pub adapter: String,
    /// Whether it is a software rasterizer (its figures measure a CPU).
    pub software: bool,
    /// Whether the device has timestamp queries (the device times are
    /// `None` without).
    pub timestamps: bool,
    /// What was traced.
    pub world: String,
    /// Image size.
    pub width: u32,
    /// Image size.
    pub height: u32,
    /// Samples per pixel of the references (0: no image error measured).
    pub spp: u32,
    /// Seconds spent on the references (CPU, untimed by the rows).
    pub reference_s: f64,
    /// Rows, view by view.
    pub rows: Vec<GpuRow>,
}

fn median(v: &mut [f64]) -> f64 {
    v.sort_by(f64::total_cmp);
    v[v.len() / 2]
}

/// Measure `views` of `world` as `setup` says; `label` names the world in
/// the report.
pub fn run(
    ctx: &GpuContext,
    world: &SceneWorld,
    label: &str,
    views: &[NamedView],
    setup: &GpuBenchSetup,
    progress: &indicatif::ProgressBar,
) -> Result<GpuBenchReport> {
    let settings: Vec<(f32, bool)> = setup
        .lods
        .iter()
        .flat_map(|&c| [(c, false), (c, true)])
        .collect();
    progress.set_length((views.len() * settings.len()) as u64);
    let mut rows = Vec::new();
    let mut reference_s = 0.0;
    for v in views {
        let cam = Camera::new(v.eye, v.target, v.fov, setup.width, setup.height)?;
        // The reference can take a while on the CPU: the bar says so
        // (review: it sat at its last count with nothing named).
        let t = Instant::now();
        let shown = progress.message();
        if setup.spp > 0 {
            progress.set_message(format!("{}: {}-sample CPU reference", v.name, setup.spp));
        }
        let reference = reference(world, &cam, setup);
        progress.set_message(shown);
        if reference.is_some() {
            reference_s += t.elapsed().as_secs_f64();
        }
        let cfg = StreamConfig {
            uploads_per_frame: setup.uploads,
            feedback_capacity: setup.uploads.max(4096),
            ..Default::default()
        };
        let mut gpu = GpuBrickmap::streaming(
            ctx,
            world.grid(),
            world.store().pool(),
            world.store().palette(),
            cfg,
        )?;
        for &(lod, beam) in &settings {
            let opts = RenderOptions {
                lod,
                beam,
                ..setup.look
            };
            rows.push(measure(
                ctx,
                &mut gpu,
                world,
                (&v.name, &cam, reference.as_deref()),
                &opts,
                setup,
            )?);
            progress.inc(1);
        }
    }
    Ok(GpuBenchReport {
        adapter: ctx.describe(),
        software: ctx.is_software(),
        timestamps: ctx.timestamps,
        world: label.to_string(),
        width: setup.width,
        height: setup.height,
        spp: setup.spp,
        reference_s,
        rows,
    })
}

/// The reference a view's images are held to: the look of the rows (LOD
/// and beams aside) traced exactly on the CPU, `spp` jittered samples a
/// pixel averaged, as `bench lod`'s are; `None` when `spp` is 0.
fn reference(world: &SceneWorld, cam: &Camera, setup: &GpuBenchSetup) -> Option<Vec<u8>> {
    if setup.spp == 0 {
        return None;
    }
    let exact = RenderOptions {
        lod: 0.0,
        beam: false,
        jitter: None,
        ..setup.look
    };
    let tracer = world.brickmap();
    let palette = world.store().palette();
    Some(supersample(setup.spp, &exact, |o| {
        render(&tracer, cam, palette, o).rgb
    }))
}

/// The chart of speed against image error over C: per view, the rows
/// with beams off, at their back-to-back device speed (or the image
/// frames' wall-clock speed on a device without timestamps).
pub fn draw_chart(path: &std::path::Path, r: &GpuBenchReport) -> Result<(), ChartError> {
    const COLOURS: [plotters::style::RGBColor; 3] = [
        plotters::style::RGBColor(31, 119, 180),
        plotters::style::RGBColor(214, 39, 40),
        plotters::style::RGBColor(44, 160, 44),
    ];
    let mut names: Vec<&str> = Vec::new();
    for row in &r.rows {
        if !names.contains(&row.view.as_str()) {
            names.push(&row.view);
        }
    }
    let speed = |row: &GpuRow| row.sustained_mrays_per_s.unwrap_or(row.image_mrays_per_s);
    let series: Vec<Series> = names
        .iter()
        .enumerate()
        .map(|(i, name)| Series {
            name,
            color: COLOURS[i % 3],
            points: r
                .rows
                .iter()
                .filter(|row| row.view == *name && !row.beam)
                .filter_map(|row| row.flip.map(|f| (f, speed(row))))
                .collect(),
        })
        .collect();
    let what = if r.timestamps {
        "device time, frames back to back"
    } else {
        "whole image frames"
    };
    xy_chart(
        path,
        &format!(
            "{}, {}x{}, {}: speed against FLIP over C",
            r.world, r.width, r.height, r.adapter
        ),
        &format!("mean FLIP vs {}-spp CPU reference (log)", r.spp),
        &format!("Mrays/s, {what} (log)"),
        &series,
    )
}

/// One view at one setting: converge, then time `render` frames, image
/// frames and back-to-back tracing.
fn measure(
    ctx: &GpuContext,
    gpu: &mut GpuBrickmap,
    world: &SceneWorld,
    (view, cam, reference): (&str, &Camera, Option<&[u8]>),
    opts: &RenderOptions,
    setup: &GpuBenchSetup,
) -> Result<GpuRow> {
    let (grid, pool) = (world.grid(), world.store().pool());
    let rays = setup.width as f64 * setup.height as f64;
    let mut frames_to_converge = 0;
    for n in 1..=400u32 {
        let (f, s) = gpu.render(ctx, cam, opts, grid, pool)?;
        if s.requests == 0 && f.lod_pixels == 0 {
            frames_to_converge = n;
            break;
        }
    }
    // One untimed frame more: the first after uploads pays for them.
    let (f, _) = gpu.render(ctx, cam, opts, grid, pool)?;
    let hit_fraction = f.hits.iter().filter(|h| h.is_some()).count() as f64 / rays;
    let flip = match reference {
        Some(r) => {
            let (image, _) = gpu.render_image(ctx, cam, opts, grid, pool)?;
            Some(super::lod::flip_mean(r, &image, setup.width, setup.height))
        }
        None => None,
    };
    let (mut wall, mut dev, mut beam_dev) = (Vec::new(), Vec::new(), Vec::new());
    for _ in 0..setup.frames {
        let t = Instant::now();
        let (_, s) = gpu.render(ctx, cam, opts, grid, pool)?;
        wall.push(t.elapsed().as_secs_f64() * 1e3);
        dev.extend(s.gpu_ms);
        beam_dev.extend(s.beam_ms);
    }
    let mut image_wall = Vec::new();
    for _ in 0..setup.frames {
        let t = Instant::now();
        gpu.render_image(ctx, cam, opts, grid, pool)?;
        image_wall.push(t.elapsed().as_secs_f64() * 1e3);
    }
    let image_ms = median(&mut image_wall);
    let (sustained_ms, sustained_stable) = sustained(ctx, gpu, cam, opts, grid, setup)?;
    let frame_ms = median(&mut wall);
    let gpu_ms = (!dev.is_empty()).then(|| median(&mut dev));
    let mrays = |ms: f64| (ms > 0.0).then(|| rays / ms / 1e3);
    Ok(GpuRow {
        view: view.to_string(),
        lod_c: opts.lod,
        beam: opts.beam,
        frames_to_converge,
        resident_bricks: gpu.resident(),
        pool_slots: gpu.pool_slots(),
        hit_fraction,
        flip,
        frame_ms,
        gpu_ms,
        beam_ms: (!beam_dev.is_empty()).then(|| median(&mut beam_dev)),
        frame_mrays_per_s: rays / frame_ms / 1e3,
        image_ms,
        image_mrays_per_s: rays / image_ms / 1e3,
        gpu_mrays_per_s: gpu_ms.and_then(mrays),
        sustained_ms,
        sustained_stable,
        sustained_mrays_per_s: sustained_ms.and_then(mrays),
    })
}

/// The tracer's device time per frame traced back to back: untimed runs
/// for `setup.warmup` bring the clocks up (on the H200 the first setting
/// of a view read up to 1.5× slow without), then runs until the last three
/// agree within 5 % (at most 20); their median counts, and whether they
/// agreed. `None` without timestamps.
fn sustained(
    ctx: &GpuContext,
    gpu: &mut GpuBrickmap,
    cam: &Camera,
    opts: &RenderOptions,
    grid: &crate::world::BrickGrid,
    setup: &GpuBenchSetup,
) -> Result<(Option<f64>, bool)> {
    // One submission of many frames can outlast a display GPU's watchdog.
    let back_to_back = setup.frames.min(100);
    let t = Instant::now();
    while t.elapsed() < setup.warmup {
        if gpu
            .sustained_ms(ctx, cam, opts, grid, back_to_back)?
            .is_none()
        {
            break;
        }
    }
    let mut runs: Vec<f64> = Vec::new();
    while runs.len() < 20 {
        let Some(ms) = gpu.sustained_ms(ctx, cam, opts, grid, back_to_back)? else {
            break;
        };
        runs.push(ms);
        if let [.., a, b, c] = runs[..] {
            let (lo, hi) = (a.min(b).min(c), a.max(b).max(c));
            if hi <= lo * 1.05 {
                let n = runs.len();
                return Ok((Some(median(&mut runs[n - 3..])), true));
            }
        }
    }
    let n = runs.len();
    Ok((
        (n > 0).then(|| median(&mut runs[n.saturating_sub(3)..])),
        false,
    ))
}

/// A streamed world's render window opened at its camera's start and
/// settled (every column exact, or `limit` passed), with the start view
/// and a level view to the horizon along the same heading.
pub fn open_window(
    cfg: &crate::engine::world_config::WorldConfig,
    limit: Duration,
) -> Result<(crate::scene::RenderWindow, Vec<NamedView>)> {
    use crate::scene::{ChunkGen, RenderWindow, WindowSettings};
    let Some(stream) = cfg.stream else {
        bail!("the world has no [stream] table: it is built whole, not streamed");
    };
    let size = (!cfg.unbounded).then_some(cfg.size);
    let gen_ = std::sync::Arc::new(ChunkGen::new(&cfg.source, size, cfg.size.y, cfg.seed)?);
    let (eye, target) = super::flight::start_view(cfg);
    let settings = WindowSettings {
        radius: WindowSettings::radius_for(stream.view_distance),
        budget_bytes: stream.memory_budget,
        fetchers: stream.fetchers,
    };
    let mut w = RenderWindow::new(gen_, None, settings, eye, None, None)?;
    if !w.settle(limit) {
        bail!(
            "the render window was not exact within {} s",
            limit.as_secs()
        );
    }
    let heading = DVec3::new(target.x - eye.x, 0.0, target.z - eye.z).normalize_or(DVec3::X);
    let views = vec![
        NamedView {
            name: "start".into(),
            eye,
            target,
            fov: cfg.camera.fov,
        },
        NamedView {
            name: "horizon".into(),
            eye,
            target: eye + heading * 1000.0 - DVec3::Y * 50.0,
            fov: cfg.camera.fov,
        },
    ];
    Ok((w, views))
}
