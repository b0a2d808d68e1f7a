//! `brickworld bench lod`: speed against image error over the level-of-detail
//! footprint `C`, the chart that rendering owes.
//!
//! For each view the reference is the same view supersampled: `--spp`
//! jittered samples per pixel (an R2 low-discrepancy pattern), traced
//! exactly, averaged over the 8-bit sRGB values. Every measured image is
//! one sample per pixel at the pixel centre, exact (`C = 0`) or with level
//! of detail; its error is the mean of NVIDIA's FLIP (LDR, through
//! `nv-flip`, at its default 67 pixels per degree) against the reference.
//! Speed is primary rays per second of the fastest of `--repeat` renders,
//! shading included.

use std::time::Instant;

use anyhow::{Context, Result};
use glam::DVec3;
use serde::Serialize;

use crate::app::{build_world, thread_pool};
use crate::bench::chart::{Series, xy_chart};
use crate::config::BenchLodSettings;
use crate::engine::world_config::DEFAULT_LOD;
use crate::progress::bar;
use crate::scene::View;
use crate::trace::{Camera, RenderOptions, Tracer, render, supersample};
use crate::world::Palette;

/// One measured image.
#[derive(Debug, Clone, Serialize)]
pub struct LodPoint {
    /// Footprint `C` in pixels (0: exact).
    pub c: f32,
    /// Seconds of the fastest render.
    pub seconds: f64,
    /// Primary rays per second, millions.
    pub mrays_per_s: f64,
    /// Mean FLIP error against the supersampled reference (0 = identical).
    pub flip: f64,
    /// Speed relative to exact tracing of the same view.
    pub speedup: f64,
    /// Error relative to exact tracing's (one sample per pixel).
    pub error_ratio: f64,
    /// Fraction of pixels whose hit differs from exact tracing's (drawn
    /// from a coarser level).
    pub coarse_fraction: f64,
}

/// One view's curve.
#[derive(Debug, Clone, Serialize)]
pub struct LodView {
    /// The view.
    pub view: View,
    /// Seconds to render the reference.
    pub reference_s: f64,
    /// Exact first, then each `C` ascending.
    pub points: Vec<LodPoint>,
}

/// The report written to `--json`.
#[derive(Debug, Clone, Serialize)]
pub struct LodReport {
    /// Scene name.
    pub scene: String,
    /// Scene size in voxels.
    pub size: [i32; 3],
    /// Image width.
    pub width: u32,
    /// Image height.
    pub height: u32,
    /// Worker threads.
    pub threads: usize,
    /// Reference samples per pixel.
    pub spp: u32,
    /// The daemon's default `C`.
    pub default_c: f32,
    /// Per view (overview, medium, close-up unless one view was given).
    pub views: Vec<LodView>,
    /// On the first view at the default `C`: error ≤ ½ exact's at ≥ 1.5×
    /// its speed (`null` when the default `C` was not measured).
    pub target_met: Option<bool>,
}

/// The supersampled reference of one view.
fn reference(tracer: &dyn Tracer, cam: &Camera, palette: &Palette, spp: u32) -> Vec<u8> {
    supersample(spp, &RenderOptions::default(), |o| {
        render(tracer, cam, palette, o).rgb
    })
}

/// Mean FLIP of `test` against `reference` (RGB8, `w`×`h`).
pub fn flip_mean(reference: &[u8], test: &[u8], w: u32, h: u32) -> f64 {
    let r = nv_flip::FlipImageRgb8::with_data(w, h, reference);
    let t = nv_flip::FlipImageRgb8::with_data(w, h, test);
    let err = nv_flip::flip(r, t, nv_flip::DEFAULT_PIXELS_PER_DEGREE);
    nv_flip::FlipPool::from_image(&err).mean() as f64
}

/// Run the bench and write its JSON (and chart).
pub fn run(s: &BenchLodSettings) -> Result<()> {
    let pool = thread_pool(s.view.threads)?;
    let report = pool.install(|| measure(s))?;
    let json = serde_json::to_string_pretty(&report)? + "\n";
    let draw = |path: &std::path::Path| draw_chart(path, &report);
    super::write_outputs(&s.json, &json, s.chart.as_deref(), draw)?;
    for (vi, v) in report.views.iter().enumerate() {
        crate::say!("view {vi} (reference {:.1} s):", v.reference_s);
        crate::say!(
            "  {:>6} {:>10} {:>8} {:>8} {:>8} {:>8}",
            "C",
            "Mrays/s",
            "FLIP",
            "speed",
            "error",
            "coarse"
        );
        for p in &v.points {
            crate::say!(
                "  {:>6} {:>10.2} {:>8.4} {:>7.2}x {:>7.2}x {:>7.1}%",
                if p.c == 0.0 {
                    "exact".to_string()
                } else {
                    p.c.to_string()
                },
                p.mrays_per_s,
                p.flip,
                p.speedup,
                p.error_ratio,
                p.coarse_fraction * 100.0
            );
        }
    }
    if let Some(met) = report.target_met {
        crate::say!(
            "target (view 0, C = {DEFAULT_LOD}: error <= 0.5x and speed >= 1.5x exact): {}",
            if met { "met" } else { "missed" }
        );
    }
    Ok(())
}

/// The chart of speed against FLIP over C, one series per view.
fn draw_chart(path: &std::path::Path, report: &LodReport) -> Result<(), super::chart::ChartError> {
    const COLOURS: [plotters::style::RGBColor; 3] = [
        plotters::style::RGBColor(31, 119, 180),
        plotters::style::RGBColor(214, 39, 40),
        plotters::style::RGBColor(44, 160, 44),
    ];
    let names: Vec<String> = (0..report.views.len())
        .map(|i| match (report.views.len(), i) {
            (3, 0) => "overview".to_string(),
            (3, 1) => "medium".to_string(),
            (3, 2) => "close-up".to_string(),
            _ => format!("view {i}"),
        })
        .collect();
    let series: Vec<Series> = report
        .views
        .iter()
        .enumerate()
        .map(|(i, v)| Series {
            name: &names[i],
            color: COLOURS[i % 3],
            points: v.points.iter().map(|p| (p.flip, p.mrays_per_s)).collect(),
        })
        .collect();
    let title = format!(
        "{} {}x{}x{}: speed against FLIP over C (exact = leftmost speed)",
        report.scene, report.size[0], report.size[1], report.size[2]
    );
    xy_chart(
        path,
        &title,
        "mean FLIP vs 16-spp reference (log)",
        "Mrays/s (log)",
        &series,
    )
}

fn measure(s: &BenchLodSettings) -> Result<LodReport> {
    // The reference's sums and image, the exact hits, two frames alive in
    // the repeat loop, and FLIP's float images.
    crate::scene::budget::check_images("bench lod", s.view.width, s.view.height, 5)?;
    let world = build_world(&s.scene)?;
    let views = super::views(&world, &s.view);
    let (w, h) = (s.view.width, s.view.height);
    let tracer = world.brickmap();
    let palette = world.store().palette();
    let cs: Vec<f32> = std::iter::once(0.0).chain(s.lods.iter().copied()).collect();
    let pb = bar(
        "bench lod",
        views.len() as u64 * (s.spp as u64 + cs.len() as u64 * s.repeat as u64),
    );
    let mut out = Vec::new();
    for v in &views {
        let cam = Camera::new(DVec3::from(v.eye), DVec3::from(v.target), v.fov, w, h)
            .context("invalid camera")?;
        let t = Instant::now();
        let refimg = reference(&tracer, &cam, palette, s.spp);
        let reference_s = t.elapsed().as_secs_f64();
        pb.inc(s.spp as u64);
        let mut points: Vec<LodPoint> = Vec::new();
        let mut exact_hits: Option<Vec<Option<crate::trace::Hit>>> = None;
        for &c in &cs {
            let opts = RenderOptions {
                lod: c,
                ..Default::default()
            };
            let mut best = f64::INFINITY;
            let mut out = None;
            for _ in 0..s.repeat {
                let t = Instant::now();
                let o = render(&tracer, &cam, palette, &opts);
                best = best.min(t.elapsed().as_secs_f64());
                out = Some(o);
                pb.inc(1);
            }
            let out = out.expect("repeat >= 1");
            let flip = flip_mean(&refimg, &out.rgb, w, h);
            let exact_hits = exact_hits.get_or_insert_with(|| out.hits.clone());
            let coarse = exact_hits
                .iter()
                .zip(&out.hits)
                .filter(|(a, b)| a != b)
                .count();
            let (base_s, base_flip) = points.first().map_or((best, flip), |e| (e.seconds, e.flip));
            points.push(LodPoint {
                c,
                seconds: best,
                mrays_per_s: (w * h) as f64 / best / 1e6,
                flip,
                speedup: base_s / best,
                error_ratio: if base_flip > 0.0 {
                    flip / base_flip
                } else {
                    1.0
                },
                coarse_fraction: coarse as f64 / (w * h) as f64,
            });
        }
        out.push(LodView {
            view: *v,
            reference_s,
            points,
        });
    }
    pb.finish_and_clear();
    let target_met = out.first().and_then(|v| {
        v.points
            .iter()
            .find(|p| p.c == DEFAULT_LOD)
            .map(|p| p.error_ratio <= 0.5 && p.speedup >= 1.5)
    });
    Ok(LodReport {
        scene: crate::bench::tracers::scene_name(&s.scene.spec),
        size: (world.bounds().1 - world.bounds().0).to_array(),
        width: w,
        height: h,
        threads: rayon::current_num_threads(),
        spp: s.spp,
        default_c: DEFAULT_LOD,
        views: out,
        target_met,
    })
}
