//! `brickworld bench stream`: ray-guided streaming on the GPU, measured.
//!
//! Cold start from an empty pool at a static view (frames to converge,
//! uploads per frame, frame time while streaming), the converged static frame
//! time, frame time while a snow simulation edits the world, frames from an
//! edit to its visibility, GPU memory in use against the world's full brick
//! data, and GPU and CPU Mrays/s in the same run.

use std::time::Instant;

use anyhow::{Context, Result};
use glam::DVec3;
use serde::Serialize;

use crate::gpu::{GpuBrickmap, GpuContext, StreamConfig};
use crate::scene::SceneWorld;
use crate::sim::{Limits, ScriptSource, WorldSim};
use crate::trace::{Camera, RenderOptions, render};
use crate::world::brick_of;

/// Frame times in milliseconds.
#[derive(Debug, Clone, Serialize)]
pub struct FrameMs {
    /// Converged view, nothing to stream.
    pub r#static: f64,
    /// Frames that uploaded bricks during the cold start.
    pub streaming: f64,
    /// Frames while a snow simulation edits the world every frame.
    pub editing: f64,
}

/// Frames an edit is given to become visible before the report says it
/// did not (the documented latency is 2).
pub const EDIT_FRAMES: u32 = 20;

/// The report.
#[derive(Debug, Clone, Serialize)]
pub struct StreamReport {
    /// Adapter used.
    pub adapter: String,
    /// Level-of-detail footprint `C` in pixels (0: exact): bricks whose
    /// footprint is under it are drawn whole and never streamed.
    pub lod_c: f32,
    /// Beam starts on the GPU (and on the CPU run of the same view).
    pub beam: bool,
    /// `gpu_bytes / world_brick_bytes`.
    pub gpu_memory_fraction: f64,
    /// Frames from an empty pool until a static view requests nothing more.
    pub frames_to_converge: u32,
    /// Bricks uploaded after each cold-start frame.
    pub uploads_per_frame: Vec<u32>,
    /// Frame times.
    pub frame_ms: FrameMs,
    /// GPU bytes in use once converged (grid, occupancy, resident bricks).
    pub gpu_bytes: u64,
    /// The world's full brick data (grid, occupancy, every brick).
    pub world_brick_bytes: u64,
    /// Frames from an edit arriving to every edited-brick pixel being exact;
    /// `None` (JSON `null`) when that did not happen within
    /// [`EDIT_FRAMES`] frames (a tiny `--uploads` or `--pool` can do it).
    pub edit_to_visible_frames: Option<u32>,
    /// Converged GPU primary rays per second, millions (shading included).
    pub gpu_mrays_per_s: f64,
    /// CPU brickmap tracer on the same view, millions of rays per second.
    pub cpu_mrays_per_s: f64,
    /// Upload bandwidth while streaming, MB/s (bytes uploaded ÷ frame time).
    pub upload_mb_per_s: f64,
    /// Bricks resident once converged, and in the world.
    pub resident_bricks: u32,
    /// Of the resident bricks, those the converged frame's rays touched:
    /// the view's working set. The rest were asked for by rays that later
    /// stopped in front of them (an unloaded brick lets rays walk on
    /// through it), and stay until the pool needs their room.
    pub working_set_bricks: u32,
    /// Bytes of the grid and the working set over `world_brick_bytes`.
    pub working_set_fraction: f64,
    /// Mixed bricks in the world.
    pub world_bricks: u32,
    /// Slots the pool started with, and holds at the end (it doubles when
    /// a view needs more, up to [`crate::gpu::MAX_POOL_SLOTS`]).
    pub pool_slots: (u32, u32),
    /// The streaming budget used.
    pub uploads_budget: u32,
    /// Material bytes uploaded during the cold start, with hidden voxels'
    /// materials culled (what was sent).
    pub material_bytes_culled: u64,
    /// The same bricks' material bytes without culling.
    pub material_bytes_unculled: u64,
    /// What DXT1 colours (4 bits per voxel, the thesis' §4.2) would take for
    /// the same bricks: 256 bytes each.
    pub material_bytes_dxt1: u64,
}

/// What the streaming benchmark runs: a view, a frame size, a streaming
/// budget, a starting pool and the render options.
#[derive(Clone, Debug)]
pub struct StreamSetup {
    /// Which of the world's three bench views.
    pub view: usize,
    /// Frame width in pixels.
    pub width: u32,
    /// Frame height in pixels.
    pub height: u32,
    /// Bricks uploaded per frame at most.
    pub budget: u32,
    /// Slots the pool starts with.
    pub pool_slots: u32,
    /// Level of detail, beams and shading.
    pub opts: RenderOptions,
}

/// Run the streaming benchmark on `world` as `setup` says.
pub fn run(
    world: &mut SceneWorld,
    setup: &StreamSetup,
    progress: &indicatif::ProgressBar,
) -> Result<StreamReport> {
    let StreamSetup {
        view,
        width,
        height,
        budget,
        pool_slots,
        opts,
    } = *setup;
    let lod = opts.lod;
    let ctx = GpuContext::new()?;
    let v = world.default_views()[view];
    let cam = Camera::new(
        DVec3::from(v.eye),
        DVec3::from(v.target),
        v.fov,
        width,
        height,
    )?;
    let cfg = StreamConfig {
        uploads_per_frame: budget,
        pool_slots,
        arena_bytes: pool_slots.saturating_mul(96),
        ..Default::default()
    };
    let mut gpu = GpuBrickmap::streaming(
        &ctx,
        world.grid(),
        world.store().pool(),
        world.store().palette(),
        cfg,
    )?;
    progress.set_length(300);
    // Cold start.
    let (mut uploads, mut streaming_ms, mut streaming_bytes) = (Vec::new(), Vec::new(), 0u64);
    let (mut culled, mut unculled, mut uploaded) = (0u64, 0u64, 0u64);
    let mut frames_to_converge = 0;
    for n in 1..=400u32 {
        let t = Instant::now();
        let (f, s) = gpu.render(&ctx, &cam, &opts, world.grid(), world.store().pool())?;
        let ms = t.elapsed().as_secs_f64() * 1e3;
        progress.inc(1);
        uploads.push(s.uploads);
        culled += s.material_bytes;
        unculled += s.unculled_material_bytes;
        uploaded += s.uploads as u64;
        if s.uploads > 0 {
            streaming_ms.push(ms);
            streaming_bytes += s.upload_bytes;
        }
        if s.requests == 0 && f.lod_pixels == 0 {
            frames_to_converge = n;
            break;
        }
    }
    if frames_to_converge == 0 {
        anyhow::bail!(
            "streaming did not converge in 400 frames ({budget} uploads per frame, {pool_slots} pool slots grown to {}, {} resident): the view needs more slots than the device or the cap ({}) allows",
            gpu.pool_slots(),
            gpu.resident(),
            crate::gpu::MAX_POOL_SLOTS
        );
    }
    let gpu_bytes = gpu.gpu_bytes_used();
    let resident = gpu.resident();
    let (working_bytes, working_bricks) = gpu.working_set().unwrap_or((gpu_bytes, resident));
    // Converged static frames.
    let mut static_ms = Vec::new();
    for _ in 0..5 {
        let t = Instant::now();
        gpu.render(&ctx, &cam, &opts, world.grid(), world.store().pool())?;
        static_ms.push(t.elapsed().as_secs_f64() * 1e3);
        progress.inc(1);
    }
    let static_ms = static_ms.iter().copied().fold(f64::INFINITY, f64::min);
    // CPU on the same view.
    let bm = world.brickmap();
    let t = Instant::now();
    render(&bm, &cam, world.store().palette(), &opts);
    let cpu_s = t.elapsed().as_secs_f64();
    let rays = (width * height) as f64;
    // An edit through the store where the view looks (a crater of radius 10
    // at the centre pixel's hit): frames until every edited-brick pixel is exact.
    let centre = render(&world.brickmap(), &cam, world.store().palette(), &opts).hits
        [(height / 2 * width + width / 2) as usize];
    let at = centre.map_or(
        (world.bounds().0 + world.bounds().1).as_dvec3() * 0.5,
        |h| h.voxel.as_dvec3(),
    );
    let ((), changed) = world.edit(|s, _| s.fill_sphere(at, 10.0, 0));
    gpu.apply_edits(&ctx, world.grid(), world.store().pool(), &changed);
    let edited: rustc_hash::FxHashSet<glam::IVec3> = changed.iter().copied().collect();
    let cpu = render(&world.brickmap(), &cam, world.store().palette(), &opts);
    let mut edit_to_visible = None;
    for n in 1..=EDIT_FRAMES {
        let (f, _) = gpu.render(&ctx, &cam, &opts, world.grid(), world.store().pool())?;
        progress.inc(1);
        let wrong = (0..f.hits.len())
            .filter(|&i| cpu.hits[i].is_some_and(|h| edited.contains(&brick_of(h.voxel))))
            .filter(|&i| f.lod[i] || f.hits[i].map(|x| x.0) != cpu.hits[i].map(|h| h.voxel))
            .count();
        if wrong == 0 {
            edit_to_visible = Some(n);
            break;
        }
    }
    // A snow simulation editing the world every frame.
    let mut ws = WorldSim::new(world);
    let src = ScriptSource {
        name: "snow".into(),
        text: crate::verify::sims::SNOW.into(),
    };
    ws.add_lua(src, Limits::default())
        .context("cannot load snow.lua")?;
    ws.sim.set_param(0, "snowfall", 2.0)?;
    let mut editing_ms = Vec::new();
    for _ in 0..15 {
        let r = ws.step(world, 0.2);
        if let Some(e) = r.errors.first() {
            anyhow::bail!("the snow simulation failed: {e}");
        }
        let t = Instant::now();
        gpu.apply_edits(&ctx, world.grid(), world.store().pool(), &r.bricks);
        gpu.render(&ctx, &cam, &opts, world.grid(), world.store().pool())?;
        editing_ms.push(t.elapsed().as_secs_f64() * 1e3);
        progress.inc(1);
    }
    let mean = |v: &[f64]| {
        if v.is_empty() {
            0.0
        } else {
            v.iter().sum::<f64>() / v.len() as f64
        }
    };
    let world_brick_bytes = world.grid().bytes() as u64 + world.store().pool().bytes() as u64;
    Ok(StreamReport {
        adapter: ctx.describe(),
        lod_c: lod,
        beam: opts.beam,
        gpu_memory_fraction: gpu_bytes as f64 / world_brick_bytes.max(1) as f64,
        frames_to_converge,
        uploads_per_frame: uploads,
        frame_ms: FrameMs {
            r#static: static_ms,
            streaming: mean(&streaming_ms),
            editing: mean(&editing_ms),
        },
        gpu_bytes,
        world_brick_bytes,
        edit_to_visible_frames: edit_to_visible,
        gpu_mrays_per_s: rays / (static_ms / 1e3) / 1e6,
        cpu_mrays_per_s: rays / cpu_s / 1e6,
        upload_mb_per_s: streaming_bytes as f64
            / 1e6
            / (streaming_ms.iter().sum::<f64>() / 1e3).max(1e-9),
        resident_bricks: resident,
        working_set_bricks: working_bricks,
        working_set_fraction: working_bytes as f64 / world_brick_bytes.max(1) as f64,
        world_bricks: world.store().pool().len() as u32,
        uploads_budget: budget,
        material_bytes_culled: culled,
        material_bytes_unculled: unculled,
        material_bytes_dxt1: uploaded * 256,
        pool_slots: (pool_slots, gpu.pool_slots()),
    })
}
