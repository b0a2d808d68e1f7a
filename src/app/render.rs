//! The `render` subcommand's edge: builds the scene, picks the tracer
//! (CPU structure or GPU), renders one image and writes it (and its depth)
//! so that a failure leaves existing files as they were.

use std::time::Instant;

use anyhow::{Context, Result};

use super::{build_world, thread_pool};
use crate::config::RenderSettings;
use crate::progress::bar;
use crate::trace::{RenderOptions, Structure, Tracer, render, write_npy, write_png};

pub(super) fn run_render(s: RenderSettings) -> Result<()> {
    crate::scene::budget::check_images("render", s.view.width, s.view.height, 1)?;
    let pool = thread_pool(s.view.threads)?;
    pool.install(|| {
        let t0 = Instant::now();
        let world = build_world(&s.scene)?;
        let camera = s
            .view
            .camera(world.default_views()[0])
            .context("invalid camera")?;
        let opts = RenderOptions {
            shadows: s.shadows,
            fog: s.fog,
            lod: s.lod,
            ao: s.ao,
            beam: s.beam,
            ..Default::default()
        };
        let built = t0.elapsed();
        use crate::gpu::TracerChoice;
        if s.tracer == TracerChoice::Gpu && s.structure != Structure::Brickmap {
            anyhow::bail!("--tracer gpu renders the brickmap only; drop --structure {}", s.structure);
        }
        let gpu = match s.tracer {
            TracerChoice::Cpu => None,
            // auto traces the dense grid and the octree on the CPU.
            TracerChoice::Auto if s.structure != Structure::Brickmap => None,
            TracerChoice::Auto => {
                let (ctx, line) = crate::gpu::choose(TracerChoice::Auto, "`--tracer gpu`");
                crate::say!("{line}");
                ctx
            }
            TracerChoice::Gpu => match crate::gpu::GpuContext::new() {
                Ok(ctx) => Some(ctx),
                Err(e) => {
                    crate::say!("warning: {e}; rendering on the CPU instead");
                    None
                }
            },
        };
        if let Some(ctx) = gpu {
            let t1 = Instant::now();
            let mut gpu = crate::gpu::GpuBrickmap::preloaded(&ctx, world.grid(), world.store().pool(), world.store().palette())?;
            let (out, _) = gpu.render(&ctx, &camera, &opts, world.grid(), world.store().pool())?;
            let traced = t1.elapsed();
            write_image_files(&s.out, s.depth_out.as_deref(), out.width, out.height, &out.rgb, &out.depth)?;
            crate::say!(
                "rendered {}x{} on the GPU ({}) in {:.3} s, upload included (scene built in {:.2} s) -> {}",
                out.width,
                out.height,
                ctx.describe(),
                traced.as_secs_f64(),
                built.as_secs_f64(),
                s.out.display()
            );
            return Ok(());
        }
        let t1 = Instant::now();
        let out = match s.structure {
            Structure::Brickmap => render(&world.brickmap(), &camera, world.store().palette(), &opts),
            Structure::Svo => {
                let pb = bar("octree", 0);
                let svo = world.svo(&pb)?;
                pb.finish_and_clear();
                render(&svo, &camera, world.store().palette(), &opts)
            }
            Structure::Dense => {
                let dense = world.dense(s.dense_limit)?;
                render(&dense as &dyn Tracer, &camera, world.store().palette(), &opts)
            }
        };
        let traced = t1.elapsed();
        write_image_files(
            &s.out,
            s.depth_out.as_deref(),
            out.width,
            out.height,
            &out.rgb,
            &out.depth,
        )?;
        crate::say!(
            "rendered {}x{} with {} in {:.3} s (scene built in {:.2} s; {:.1}% of rays hit) -> {}",
            out.width,
            out.height,
            s.structure,
            traced.as_secs_f64(),
            built.as_secs_f64(),
            out.hit_fraction() * 100.0,
            s.out.display()
        );
        Ok(())
    })
}

/// Write the image and, if asked, the depth: each to a temporary file
/// first, so that a failure leaves both destinations as they were
/// (regression: a depth path in a missing folder failed after the PNG had
/// already replaced an existing one).
fn write_image_files(
    png: &std::path::Path,
    depth: Option<&std::path::Path>,
    width: u32,
    height: u32,
    rgb: &[u8],
    z: &[f32],
) -> Result<()> {
    use crate::files::Staged;
    let cannot = |p: &std::path::Path| format!("cannot write {}", p.display());
    let img = Staged::new(png).with_context(|| cannot(png))?;
    write_png(img.path(), width, height, rgb).with_context(|| cannot(png))?;
    let dep = match depth {
        Some(d) => {
            let st = Staged::new(d).with_context(|| cannot(d))?;
            write_npy(st.path(), width, height, z).with_context(|| cannot(d))?;
            Some((st, d))
        }
        None => None,
    };
    img.commit().with_context(|| cannot(png))?;
    if let Some((st, d)) = dep {
        st.commit().with_context(|| cannot(d))?;
    }
    Ok(())
}
