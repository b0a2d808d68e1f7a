//! GPU tracer against the CPU reference: the same voxel on every pixel of
//! an exact walk and on ≥ 99.99 % with level of detail (on a software
//! adapter, as in CI; ≥ 99.9 % on a hardware GPU), depths within 1e-3
//! relative, colours within 2/255, over the standard scenes and the three
//! bench views.
//!
//! Without a GPU adapter these tests report it and pass, unless
//! `BRICKWORLD_REQUIRE_GPU=1` (set by `.ci/run` after installing lavapipe),
//! in which case they fail.

mod common;

use brickworld::gpu::{GpuBrickmap, GpuContext};
use brickworld::trace::{Camera, RenderOptions, render};
use glam::DVec3;

/// Largest colour difference per channel allowed on a pixel where GPU and CPU
/// hit the same voxel (f32 shading on both, different instruction order).
const COLOUR_TOLERANCE: u8 = 2;

fn context() -> Option<GpuContext> {
    common::gpu_context()
}

fn parity(name: &str, b: &common::Built, ctx: &GpuContext, shadows: bool, fog: f32) {
    let opts = RenderOptions {
        shadows,
        fog,
        ..Default::default()
    };
    parity_with(name, b, ctx, opts);
}

/// The GPU with `opts` against the CPU with the same options, except beam
/// starts: the CPU traces without them, so a GPU beam that skipped a hit
/// would show.
fn parity_with(name: &str, b: &common::Built, ctx: &GpuContext, opts: RenderOptions) {
    let (fog, lod, ao) = (opts.fog, opts.lod, opts.ao);
    let gpu_opts = opts;
    let opts = RenderOptions {
        beam: false,
        ..opts
    };
    let mut gpu = GpuBrickmap::preloaded(
        ctx,
        b.world.grid(),
        b.world.store().pool(),
        b.world.store().palette(),
    )
    .unwrap();
    let bm = b.brickmap();
    for (vi, v) in b.world.default_views().iter().enumerate() {
        let cam = Camera::new(DVec3::from(v.eye), DVec3::from(v.target), v.fov, 160, 120).unwrap();
        let cpu = render(&bm, &cam, b.world.store().palette(), &opts);
        if fog > 0.0 {
            // The fog shows: most hits move towards the sky colour.
            let clear = RenderOptions { fog: 0.0, ..opts };
            let plain = render(&bm, &cam, b.world.store().palette(), &clear);
            let hits = cpu.hits.iter().filter(|h| h.is_some()).count();
            let moved = (0..cpu.hits.len())
                .filter(|&i| cpu.hits[i].is_some())
                .filter(|&i| (0..3).any(|k| cpu.rgb[i * 3 + k].abs_diff(plain.rgb[i * 3 + k]) > 8))
                .count();
            assert!(moved * 2 > hits, "{name}: fog moved {moved} of {hits} hits");
        }
        if ao {
            // The occlusion shows: a good share of hits darken.
            let flat = RenderOptions { ao: false, ..opts };
            let plain = render(&bm, &cam, b.world.store().palette(), &flat);
            let darker = (0..cpu.hits.len())
                .filter(|&i| {
                    (0..3).any(|k| cpu.rgb[i * 3 + k] as u32 + 4 < plain.rgb[i * 3 + k] as u32)
                })
                .count();
            assert!(
                darker * 20 > cpu.hits.iter().filter(|h| h.is_some()).count(),
                "{name} view {vi}: ambient occlusion darkened only {darker} pixels"
            );
        }
        if lod > 0.0 {
            // The levels are used: many hits differ from the exact ones.
            let exact = RenderOptions { lod: 0.0, ..opts };
            let plain = render(&bm, &cam, b.world.store().palette(), &exact);
            let coarse = (0..cpu.hits.len())
                .filter(|&i| cpu.hits[i].map(|h| h.t) != plain.hits[i].map(|h| h.t))
                .count();
            assert!(
                coarse * 20 > cpu.hits.len(),
                "{name} view {vi}: level of detail changed only {coarse} pixels"
            );
        }
        let (g, _) = gpu
            .render(ctx, &cam, &gpu_opts, b.world.grid(), b.world.store().pool())
            .unwrap();
        let n = cpu.hits.len();
        let (mut same, mut depth_bad, mut colour_bad) = (0usize, 0usize, 0usize);
        for i in 0..n {
            let c = cpu.hits[i].map(|h| (h.voxel, h.normal));
            if c.map(|x| x.0) == g.hits[i].map(|x| x.0) {
                same += 1;
                if let Some(h) = cpu.hits[i] {
                    let rel = (g.depth[i] - h.t).abs() / h.t.max(1.0);
                    depth_bad += (rel > 1e-3) as usize;
                    let d = (0..3)
                        .map(|k| cpu.rgb[i * 3 + k].abs_diff(g.rgb[i * 3 + k]))
                        .max()
                        .unwrap();
                    colour_bad += (d > COLOUR_TOLERANCE) as usize;
                }
            }
        }
        let frac = same as f64 / n as f64;
        eprintln!(
            "{name} view {vi}: same voxel {:.4} %, depth off {depth_bad}, colour off {colour_bad}",
            frac * 100.0
        );
        // The bounds the docs state: on a software adapter (lavapipe, what
        // CI runs) every pixel of an exact walk hits the same voxel, a level
        // walk the same cell on at least 99.99 %, and every same-voxel
        // pixel's colour is within the tolerance. A hardware GPU may fuse
        // or reorder f32 operations: 99.9 %, and 0.5 % of colours (a
        // shadow ray resolving a near-tie the other way).
        let strict = ctx.is_software();
        let least = match (strict, lod > 0.0) {
            (true, false) => 1.0,
            (true, true) => 0.9999,
            (false, _) => 0.999,
        };
        assert!(
            frac >= least,
            "{name} view {vi}: only {:.4} % of pixels hit the same voxel (at least {} % required on {})",
            frac * 100.0,
            least * 100.0,
            ctx.describe()
        );
        assert_eq!(
            depth_bad, 0,
            "{name} view {vi}: depths differ by more than 1e-3 relative"
        );
        let colours_allowed = if strict { 0.0 } else { 0.005 * n as f64 };
        assert!(
            colour_bad as f64 <= colours_allowed,
            "{name} view {vi}: {colour_bad} pixels differ in colour by more than {COLOUR_TOLERANCE}/255"
        );
    }
}

#[test]
fn gpu_matches_cpu_on_the_standard_scenes_and_views() {
    let Some(ctx) = context() else { return };
    eprintln!("adapter: {}", ctx.describe());
    parity("terrain", common::terrain(), &ctx, true, 0.0);
    parity("caves", common::caves(), &ctx, false, 0.0);
    parity("balls", common::balls(), &ctx, true, 0.0);
    parity("hairball", common::hairball(), &ctx, false, 0.0);
    // Distance fog, on both tracers alike (the colour check would fail if
    // either left it out: at this extent it moves most hits by far more
    // than the tolerance).
    parity("terrain with fog", common::terrain(), &ctx, true, 40.0);
}

/// Level of detail picks the same levels, cells and materials on both
/// (the footprint rule is the same f32 comparisons); the test fails if the
/// shader ignores `lod_k` (checked by replacing it with 0).
#[test]
fn gpu_matches_cpu_with_level_of_detail() {
    let Some(ctx) = context() else { return };
    parity_with(
        "terrain, C = 4",
        common::terrain(),
        &ctx,
        RenderOptions {
            shadows: true,
            fog: 0.0,
            lod: 4.0,
            ao: false,
            ..Default::default()
        },
    );
    parity_with(
        "balls, C = 8",
        common::balls(),
        &ctx,
        RenderOptions {
            shadows: false,
            fog: 0.0,
            lod: 8.0,
            ao: false,
            ..Default::default()
        },
    );
    parity_with(
        "hairball, C = 16",
        common::hairball(),
        &ctx,
        RenderOptions {
            shadows: false,
            fog: 30.0,
            lod: 16.0,
            ao: false,
            ..Default::default()
        },
    );
}

/// Beam starts on the GPU change nothing: the CPU traces without them.
#[test]
fn gpu_beam_starts_match_the_cpu_without_them() {
    let Some(ctx) = context() else { return };
    for (name, b) in [
        ("terrain", common::terrain()),
        ("caves", common::caves()),
        ("balls", common::balls()),
    ] {
        parity_with(
            name,
            b,
            &ctx,
            RenderOptions {
                beam: true,
                ..Default::default()
            },
        );
    }
    parity_with(
        "terrain, C = 4, with beams",
        common::terrain(),
        &ctx,
        RenderOptions {
            beam: true,
            lod: 4.0,
            shadows: true,
            ..Default::default()
        },
    );
}

/// Ambient occlusion is the same on both (same corner rule, same lookups);
/// the test fails if the shader leaves it out (checked by mutation).
#[test]
fn gpu_matches_cpu_with_ambient_occlusion() {
    let Some(ctx) = context() else { return };
    parity_with(
        "terrain with AO",
        common::terrain(),
        &ctx,
        RenderOptions {
            shadows: true,
            fog: 0.0,
            lod: 0.0,
            ao: true,
            ..Default::default()
        },
    );
    parity_with(
        "caves with AO",
        common::caves(),
        &ctx,
        RenderOptions {
            shadows: false,
            fog: 0.0,
            lod: 0.0,
            ao: true,
            ..Default::default()
        },
    );
    parity_with(
        "hairball with AO and C = 4",
        common::hairball(),
        &ctx,
        RenderOptions {
            shadows: false,
            fog: 0.0,
            lod: 4.0,
            ao: true,
            ..Default::default()
        },
    );
}

/// The far eye of the two tests below: 2·10⁷ voxels out, looking at a
/// 256-voxel terrain through 0.01° over 64 rows (the world is about 5
/// pixels wide, a pixel about 54 voxels).
const FAR_EYE: DVec3 = DVec3::new(2e7, 100.0, 128.0);

fn far_view() -> (&'static common::Built, Camera) {
    static WORLD: std::sync::OnceLock<common::Built> = std::sync::OnceLock::new();
    let b = WORLD.get_or_init(|| common::Built::new("terrain", glam::IVec3::new(256, 64, 256), 1));
    let cam = Camera::new(FAR_EYE, DVec3::new(128.0, 32.0, 128.0), 0.01, 64, 64).unwrap();
    (b, cam)
}

/// The GPU's frame of `cam` over `b` with `opts`.
fn gpu_frame(
    ctx: &GpuContext,
    b: &common::Built,
    cam: &Camera,
    opts: &RenderOptions,
) -> brickworld::gpu::GpuFrame {
    let palette = b.world.store().palette();
    let mut gpu =
        GpuBrickmap::preloaded(ctx, b.world.grid(), b.world.store().pool(), palette).unwrap();
    gpu.render(ctx, cam, opts, b.world.grid(), b.world.store().pool())
        .unwrap()
        .0
}

/// Regression (hostile probe): an eye more than 2^24 voxels from the
/// world's anchor saw nothing on the CPU (the DDA refuses origins whose f32
/// coordinates are no longer exact). Its rays now start where they enter
/// the exact range: the three CPU tracers agree, the world is there at the
/// distance it is, and the GPU hits the same pixels, each within 2 voxels
/// of the CPU's (its f32 walk already reached them, from an eye rounded to
/// f32).
#[test]
fn an_eye_past_2_24_voxels_sees_the_world_on_every_tracer() {
    use brickworld::trace::Tracer;
    let (b, cam) = far_view();
    let eye = FAR_EYE;
    let opts = RenderOptions::default();
    let bm = b.brickmap();
    let palette = b.world.store().palette();
    let tracers: [&dyn Tracer; 3] = [&b.dense, &b.svo, &bm];
    let frames: Vec<_> = tracers
        .iter()
        .map(|t| render(*t, &cam, palette, &opts))
        .collect();
    let hits: Vec<_> = frames[0].hits.iter().flatten().collect();
    assert!(hits.len() >= 3, "the far eye sees {} voxels", hits.len());
    for h in &hits {
        let d = (h.voxel.as_dvec3() - eye).length();
        assert!(
            (h.t as f64 - d).abs() < 2.0,
            "hit at t {} for a voxel {d} away",
            h.t
        );
    }
    for (t, f) in tracers.iter().zip(&frames).skip(1) {
        assert_eq!(f.hits, frames[0].hits, "{} differs from dense", t.name());
    }
    let Some(ctx) = context() else { return };
    let g = gpu_frame(&ctx, b, &cam, &opts);
    let cpu: Vec<_> = frames[0].hits.iter().map(|h| h.map(|h| h.voxel)).collect();
    let gpu_hits: Vec<_> = g.hits.iter().map(|h| h.map(|h| h.0)).collect();
    // The shader's eye is f32, so 2e7 voxels out it is rounded to 2 voxels
    // (a pixel here spans 50): the same pixels hit, each within 2 voxels.
    let differ: Vec<_> = (0..cpu.len())
        .filter(|&i| match (cpu[i], gpu_hits[i]) {
            (Some(c), Some(g)) => (c - g).abs().max_element() > 2,
            (c, g) => c != g,
        })
        .map(|i| (i, cpu[i], gpu_hits[i]))
        .collect();
    assert!(differ.is_empty(), "the GPU sees other voxels: {differ:?}");
}

/// Regression (review): with level of detail, a far eye's rays took their
/// levels from where their walk started (2^23 voxels from the anchor), not
/// from the eye, so they were finer than the footprint allows and than the
/// GPU's. At 2·10⁷ voxels a pixel here spans about 54 voxels: every hit is
/// a 32-voxel cell, and the GPU enters the same cells (depths within the 2
/// voxels its f32 eye is off by).
#[test]
fn a_far_eye_takes_its_levels_from_the_eye() {
    let (b, cam) = far_view();
    let opts = RenderOptions {
        lod: 1.0,
        ..Default::default()
    };
    let bm = b.brickmap();
    let palette = b.world.store().palette();
    let cpu = render(&bm, &cam, palette, &opts);
    let hits: Vec<_> = cpu.hits.iter().flatten().collect();
    assert!(hits.len() >= 3, "the far eye sees {} cells", hits.len());
    for h in &hits {
        assert_eq!(h.level, 5, "a hit on level {} at t {}", h.level, h.t);
    }
    let Some(ctx) = context() else { return };
    let g = gpu_frame(&ctx, b, &cam, &opts);
    for i in 0..cpu.depth.len() {
        let (c, d) = (cpu.depth[i], g.depth[i]);
        assert!(
            c == d || (c - d).abs() <= 4.0,
            "pixel {i}: the CPU's depth {c}, the GPU's {d}"
        );
    }
}

/// A palette uploaded after the GPU brickmap was built is the one it draws
/// with (a hot reload of `materials.lua` recolours materials): its frame
/// matches the CPU's with the new palette, not the old one.
#[test]
fn a_new_palette_reaches_the_gpu() {
    let Some(ctx) = context() else { return };
    let (b, _) = far_view();
    let v = b.world.default_views()[1];
    let cam = Camera::new(DVec3::from(v.eye), DVec3::from(v.target), v.fov, 64, 48).unwrap();
    let opts = RenderOptions::default();
    let old = b.world.store().palette();
    let mut new = old.clone();
    for m in 1..=255u8 {
        let c = old.rgb(m);
        new.set(m, [255 - c[0], c[2], c[1]]);
    }
    let mut gpu =
        GpuBrickmap::preloaded(&ctx, b.world.grid(), b.world.store().pool(), old).unwrap();
    gpu.set_palette(&ctx, &new);
    let (g, _) = gpu
        .render(&ctx, &cam, &opts, b.world.grid(), b.world.store().pool())
        .unwrap();
    let bm = b.brickmap();
    let cpu_new = render(&bm, &cam, &new, &opts);
    let cpu_old = render(&bm, &cam, old, &opts);
    let hits: Vec<usize> = (0..cpu_new.hits.len())
        .filter(|&i| cpu_new.hits[i].is_some())
        .collect();
    assert!(hits.len() > 100, "{} hits", hits.len());
    let off = |a: &[u8], i: usize| {
        (0..3)
            .map(|k| a[i * 3 + k].abs_diff(g.rgb[i * 3 + k]))
            .max()
            .unwrap()
    };
    let bad = hits
        .iter()
        .filter(|&&i| off(&cpu_new.rgb, i) > COLOUR_TOLERANCE)
        .count();
    assert!(
        bad * 200 <= hits.len(),
        "{bad} of {} pixels off the new palette",
        hits.len()
    );
    let old_like = hits
        .iter()
        .filter(|&&i| off(&cpu_old.rgb, i) <= COLOUR_TOLERANCE)
        .count();
    assert!(
        old_like * 10 < hits.len(),
        "{old_like} pixels still in the old colours"
    );
}
