//! `brickworld bench gpu`'s edge: its flags checked (and a streamed
//! world's config read) before the device is opened, the device asked
//! whether a frame fits before any world is built, then the benchmark,
//! its JSON and a table.

use anyhow::Result;

use super::build_world;
use crate::bench::gpu::{GpuBenchReport, GpuBenchSetup, NamedView};
use crate::config::SceneSettings;
use crate::engine::world_config::WorldConfig;
use crate::progress::bar;
use crate::trace::RenderOptions;

/// What `bench gpu` traces, its flags checked.
enum Source<'a> {
    /// A streamed world's render window (the config read and checked).
    World(&'a std::path::Path, Box<WorldConfig>),
    /// A scene built whole.
    Scene(SceneSettings),
}

pub(super) fn run_bench_gpu(a: &crate::cli::BenchGpuArgs) -> Result<()> {
    let mut setup = setup_of(a)?;
    let source = match &a.world {
        Some(path) => {
            crate::config::not_an_input("--json", &a.json, &[("world config", path)])?;
            if let Some(c) = &a.chart {
                crate::config::not_an_input("--chart", c, &[("world config", path)])?;
            }
            let cfg = WorldConfig::load(path)?;
            if cfg.stream.is_none() {
                anyhow::bail!(
                    "--world needs a streamed world (a [stream] table in its config); use --scene for one built whole"
                );
            }
            Source::World(path, Box::new(cfg))
        }
        None => {
            let s = SceneSettings::from_args(&a.scene, glam::IVec3::new(2048, 256, 2048))?;
            s.check_outputs(&a.json, a.chart.as_deref())?;
            Source::Scene(s)
        }
    };
    // The device: a frame it cannot hold is refused before any world is
    // built, and a software rasterizer is named before the run.
    let ctx = crate::gpu::GpuContext::new()?;
    ctx.check_frame(a.width, a.height)?;
    if ctx.is_software() {
        crate::say!(
            "note: {} is a software rasterizer: these figures measure the CPU, and at large sizes they take long",
            ctx.describe()
        );
    }
    let r = match source {
        Source::World(path, cfg) => {
            // The daemon's look, primary rays only.
            setup.look = RenderOptions {
                shadows: false,
                ..cfg.look.options()
            };
            let pb = bar("render window", 0);
            let (w, views) =
                crate::bench::gpu::open_window(&cfg, std::time::Duration::from_secs(600))?;
            pb.finish_and_clear();
            let label = format!(
                "{}: render window of {} bricks at the camera's start",
                path.display(),
                w.world().store().pool().len()
            );
            run_with_bar(&ctx, w.world(), &label, &views, &setup)?
        }
        Source::Scene(scene) => {
            let world = build_world(&scene)?;
            let names = ["overview", "medium", "close-up"];
            let views: Vec<NamedView> = world
                .default_views()
                .iter()
                .zip(names)
                .map(|(v, name)| NamedView {
                    name: name.into(),
                    eye: glam::DVec3::from(v.eye),
                    target: glam::DVec3::from(v.target),
                    fov: v.fov,
                })
                .collect();
            // The world's own extent: file scenes ignore the default size.
            let (lo, hi) = world.bounds();
            let e = hi - lo;
            let label = format!(
                "{} {}x{}x{} ({} bricks)",
                a.scene.scene,
                e.x,
                e.y,
                e.z,
                world.store().pool().len()
            );
            run_with_bar(&ctx, &world, &label, &views, &setup)?
        }
    };
    let text = serde_json::to_string_pretty(&r)? + "\n";
    let draw = |path: &std::path::Path| crate::bench::gpu::draw_chart(path, &r);
    crate::bench::write_outputs(&a.json, &text, a.chart.as_deref(), draw)?;
    print_table(&r);
    Ok(())
}

/// The run's settings from its flags, each checked.
fn setup_of(a: &crate::cli::BenchGpuArgs) -> Result<GpuBenchSetup> {
    if a.width == 0 || a.height == 0 || a.width > 8192 || a.height > 8192 {
        anyhow::bail!(
            "invalid --width x --height {}x{}: each side must be in 1..=8192",
            a.width,
            a.height
        );
    }
    if a.frames == 0 || a.frames > 1000 {
        anyhow::bail!("invalid --frames {}: 1 to 1000 timed frames", a.frames);
    }
    if a.warmup_ms > 60_000 {
        anyhow::bail!("invalid --warmup-ms {}: at most 60000", a.warmup_ms);
    }
    if a.uploads == 0 || a.uploads > crate::gpu::MAX_POOL_SLOTS {
        anyhow::bail!(
            "invalid --uploads {}: 1 to {} bricks per frame",
            a.uploads,
            crate::gpu::MAX_POOL_SLOTS
        );
    }
    let lods = gpu_lods(&a.lod)?;
    if a.spp > 256 {
        anyhow::bail!("invalid --spp {}: 0 to 256 samples per pixel", a.spp);
    }
    if a.chart.is_some() && a.spp == 0 {
        anyhow::bail!("--chart needs the image error: give --spp above 0");
    }
    crate::config::check_bench_outputs(&a.json, a.chart.as_deref())?;
    Ok(GpuBenchSetup {
        width: a.width,
        height: a.height,
        lods,
        frames: a.frames,
        uploads: a.uploads,
        warmup: std::time::Duration::from_millis(a.warmup_ms),
        spp: a.spp,
        look: RenderOptions {
            ao: true,
            ..Default::default()
        },
    })
}

fn run_with_bar(
    ctx: &crate::gpu::GpuContext,
    world: &crate::scene::SceneWorld,
    label: &str,
    views: &[NamedView],
    setup: &GpuBenchSetup,
) -> Result<GpuBenchReport> {
    let pb = bar("bench gpu (settings)", 0);
    let r = crate::bench::gpu::run(ctx, world, label, views, setup, &pb)?;
    pb.finish_and_clear();
    Ok(r)
}

fn print_table(r: &GpuBenchReport) {
    println!(
        "adapter: {}{}; {}; {}x{}",
        r.adapter,
        if r.software {
            " (a software rasterizer: these figures measure the CPU)"
        } else {
            ""
        },
        r.world,
        r.width,
        r.height
    );
    println!(
        "{:<9} {:>5} {:>5} {:>9} {:>6} {:>7} {:>9} {:>8} {:>9} {:>8} {:>11} {:>13} {:>8}",
        "view",
        "C",
        "beam",
        "converge",
        "hits",
        "FLIP",
        "frame ms",
        "Mrays/s",
        "image ms",
        "Mrays/s",
        "1 frame ms",
        "sustained ms",
        "Mrays/s"
    );
    for row in &r.rows {
        let opt =
            |v: Option<f64>, digits: usize| v.map_or("-".to_string(), |x| format!("{x:.digits$}"));
        println!(
            "{:<9} {:>5} {:>5} {:>9} {:>5.0}% {:>7} {:>9.2} {:>8.1} {:>9.2} {:>8.1} {:>11} {:>13} {:>8}",
            row.view,
            if row.lod_c == 0.0 {
                "exact".to_string()
            } else {
                format!("{}", row.lod_c)
            },
            if row.beam { "on" } else { "off" },
            if row.frames_to_converge == 0 {
                "no".to_string()
            } else {
                row.frames_to_converge.to_string()
            },
            row.hit_fraction * 100.0,
            opt(row.flip, 4),
            row.frame_ms,
            row.frame_mrays_per_s,
            row.image_ms,
            row.image_mrays_per_s,
            opt(row.gpu_ms, 3),
            opt(row.sustained_ms, 3),
            opt(row.sustained_mrays_per_s, 1),
        );
    }
    if r.rows.iter().any(|row| row.frames_to_converge == 0) {
        println!(
            "warning: a view marked 'no' did not converge within 400 frames: it was timed showing some bricks by their LOD colour (raise --uploads)"
        );
    }
    if r.spp > 0 {
        println!(
            "FLIP: each image's mean error against its view's {}-sample CPU reference ({:.1} s in all, untimed)",
            r.spp, r.reference_s
        );
    }
    if !r.timestamps {
        println!("this device writes no timestamps: only whole frames were timed");
    } else {
        println!(
            "Mrays/s: over whole frames (every output read back and decoded), over whole frames of the image alone, and over the tracer's device time with frames traced back to back"
        );
    }
}

/// `bench gpu --lod`: exact tracing (always measured, first), then each
/// distinct C of the list; "none" (alone, any case) measures exact
/// tracing only.
fn gpu_lods(text: &str) -> Result<Vec<f32>> {
    let mut lods = vec![0.0f32];
    if text.trim().eq_ignore_ascii_case("none") {
        return Ok(lods);
    }
    for part in text.split(',') {
        let part = part.trim();
        let bad = |why: &str| {
            anyhow::anyhow!(
                "invalid --lod '{text}': {why} (a list of C in {}..={} pixels; exact tracing is always measured; \"none\" alone measures only it)",
                crate::config::MIN_LOD,
                crate::config::MAX_LOD
            )
        };
        let c: f64 = part
            .parse()
            .map_err(|_| bad(&format!("'{part}' is not a number")))?;
        if !crate::config::lod_in_range(c) {
            return Err(bad(&format!("{part} is out of range")));
        }
        let c = c as f32;
        if !lods.contains(&c) {
            lods.push(c);
        }
    }
    Ok(lods)
}
