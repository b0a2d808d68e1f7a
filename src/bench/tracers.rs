//! `brickworld bench tracers`: build the dense grid, the octree and the
//! brickmap for one scene, render the same views with each, and report speed,
//! memory, counts and agreement (every pixel's hit compared across tracers).

use std::time::Instant;

use anyhow::{Context, Result};
use glam::DVec3;
use serde::Serialize;

use crate::app::{build_world, thread_pool};
use crate::config::BenchTracersSettings;
use crate::progress::bar;
use crate::scene::View;
use crate::trace::{Camera, RenderOptions, Structure, Tracer, render};
use crate::world::BrickGrid;

/// One structure's figures, or why it could not be built.
#[derive(Debug, Clone, Serialize)]
#[serde(untagged)]
pub enum StructureReport {
    /// Built and measured.
    Ok(StructureFigures),
    /// Not built.
    Failed {
        /// Structure name.
        name: &'static str,
        /// Why.
        error: String,
    },
}

/// Figures of one structure, averaged over the views.
#[derive(Debug, Clone, Serialize)]
pub struct StructureFigures {
    /// Structure name.
    pub name: &'static str,
    /// Seconds to build it from the store.
    pub build_s: f64,
    /// Bytes as traced.
    pub bytes: u64,
    /// Solid voxels represented.
    pub solid_voxels: u64,
    /// Voxels (dense), descriptors (svo) or non-empty bricks (brickmap).
    pub nodes_or_bricks: u64,
    /// Primary rays per second over all views, millions (shading included).
    pub mrays_per_s: f64,
    /// The same divided by the thread count.
    pub mrays_per_s_per_thread: f64,
    /// Frames per second (mean over views).
    pub fps: f64,
    /// Fraction of primary rays that hit.
    pub hit_fraction: f64,
    /// `bytes / solid_voxels`.
    pub bytes_per_solid_voxel: f64,
    /// Mrays/s of each view.
    pub view_mrays_per_s: Vec<f64>,
}

/// Cross-tracer agreement.
#[derive(Debug, Clone, Serialize)]
pub struct Agreement {
    /// Rays compared (pixels × views).
    pub rays: u64,
    /// Rays on which some tracer disagreed with the first (voxel, face, t or material).
    pub mismatches: u64,
}

/// The whole report, as written to `--json`.
#[derive(Debug, Clone, Serialize)]
pub struct BenchReport {
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
    /// Views rendered.
    pub views: Vec<View>,
    /// Per structure.
    pub structures: Vec<StructureReport>,
    /// Agreement.
    pub agree: Agreement,
    /// Voxels of the plain cartesian grid over the scene.
    pub grid_voxels: u64,
    /// Seconds to build the scene into the brick store.
    pub scene_build_s: f64,
    /// The brickmap with beam starts (its hits count in `agree` too).
    pub brickmap_beam: BeamFigures,
    /// The brickmap's primary hits alone (no shading, sky or image), per
    /// view: what a peer that only intersects rays is compared with (its
    /// hits count in `agree` too).
    pub brickmap_hits_only: HitsOnlyFigures,
}

/// The brickmap's primary rays traced for their hits alone, per view.
#[derive(Debug, Clone, Serialize)]
pub struct HitsOnlyFigures {
    /// Mrays/s of each view (the rays made and traced; nothing shaded).
    pub view_mrays_per_s: Vec<f64>,
    /// Speed relative to the brickmap's rendered frames, per view.
    pub view_speedup: Vec<f64>,
}

/// The brickmap with beam starts, per view.
#[derive(Debug, Clone, Serialize)]
pub struct BeamFigures {
    /// Mrays/s of each view.
    pub view_mrays_per_s: Vec<f64>,
    /// Speed relative to the brickmap without beams, per view.
    pub view_speedup: Vec<f64>,
}

/// Run the bench and write its JSON (and chart).
pub fn run(s: &BenchTracersSettings) -> Result<()> {
    let pool = thread_pool(s.view.threads)?;
    let report = pool.install(|| measure(s))?;
    let json = serde_json::to_string_pretty(&report)? + "\n";
    let draw = |p: &std::path::Path| super::chart::memory_vs_speed(p, &[&report]);
    super::write_outputs(&s.json, &json, s.chart.as_deref(), draw)?;
    print_table(&report);
    verdict(&report.agree)
}

/// The bench's exit: an error when the tracers disagreed on any ray.
fn verdict(agree: &Agreement) -> Result<()> {
    if agree.mismatches > 0 {
        anyhow::bail!(
            "tracers disagree on {} of {} rays: this is a bug",
            agree.mismatches,
            agree.rays
        );
    }
    Ok(())
}

fn measure(s: &BenchTracersSettings) -> Result<BenchReport> {
    // The reference hits and the frame being measured.
    crate::scene::budget::check_images("bench tracers", s.view.width, s.view.height, 2)?;
    let threads = rayon::current_num_threads();
    let t0 = Instant::now();
    let world = build_world(&s.scene)?;
    let scene_build_s = t0.elapsed().as_secs_f64();
    let views = super::views(&world, &s.view);
    let cameras: Vec<Camera> = views
        .iter()
        .map(|v| {
            Camera::new(
                DVec3::from(v.eye),
                DVec3::from(v.target),
                v.fov,
                s.view.width,
                s.view.height,
            )
        })
        .collect::<Result<_, _>>()
        .context("invalid camera")?;
    let solid = world.store().solid_voxels();

    // Build each structure, timing it; failures are reported and skipped.
    let t = Instant::now();
    let grid = BrickGrid::build(world.store(), world.grid().origin(), world.grid().dims());
    let grid_s = t.elapsed().as_secs_f64();
    drop(grid);
    let t = Instant::now();
    let dense = world.dense(s.dense_limit);
    let dense_s = t.elapsed().as_secs_f64();
    let pb = bar("octree", 0);
    let t = Instant::now();
    let svo = world.svo(&pb);
    let svo_s = t.elapsed().as_secs_f64();
    pb.finish_and_clear();
    let brickmap = world.brickmap();

    let mut built: Vec<(Structure, &dyn Tracer, f64)> = Vec::new();
    let mut reports: Vec<StructureReport> = Vec::new();
    let mut failed = Vec::new();
    match &dense {
        Ok(d) => built.push((Structure::Dense, d, dense_s)),
        Err(e) => failed.push(StructureReport::Failed {
            name: "dense",
            error: e.to_string(),
        }),
    }
    match &svo {
        Ok(t) => built.push((Structure::Svo, t, svo_s)),
        Err(e) => failed.push(StructureReport::Failed {
            name: "svo",
            error: e.to_string(),
        }),
    }
    built.push((Structure::Brickmap, &brickmap, grid_s));

    let pb = bar(
        "bench",
        (views.len() * (built.len() + 2)) as u64 * s.repeat as u64,
    );
    let mut beam_times = vec![0f64; cameras.len()];
    let mut hits_times = vec![0f64; cameras.len()];
    let opts = RenderOptions::default();
    let palette = world.store().palette();
    let pixels = (s.view.width * s.view.height) as u64;
    let mut times = vec![vec![0f64; cameras.len()]; built.len()];
    let mut hit_counts = vec![0u64; built.len()];
    let mut mismatches = 0u64;
    for (vi, cam) in cameras.iter().enumerate() {
        let mut reference: Option<Vec<_>> = None;
        for (si, (_, tracer, _)) in built.iter().enumerate() {
            let mut best = f64::INFINITY;
            let mut out = None;
            for _ in 0..s.repeat {
                let t = Instant::now();
                let o = render(*tracer, cam, palette, &opts);
                best = best.min(t.elapsed().as_secs_f64());
                out = Some(o);
                pb.inc(1);
            }
            let out = out.expect("repeat >= 1");
            times[si][vi] = best;
            hit_counts[si] += out.hits.iter().filter(|h| h.is_some()).count() as u64;
            match &reference {
                None => reference = Some(out.hits),
                Some(r) => {
                    mismatches += r.iter().zip(&out.hits).filter(|(a, b)| a != b).count() as u64
                }
            }
        }
        // The brickmap again with beam starts: the same hits, sooner.
        let beamed = RenderOptions { beam: true, ..opts };
        let mut best = f64::INFINITY;
        for _ in 0..s.repeat {
            let t = Instant::now();
            let o = render(&brickmap, cam, palette, &beamed);
            best = best.min(t.elapsed().as_secs_f64());
            if let Some(r) = &reference {
                mismatches += r.iter().zip(&o.hits).filter(|(a, b)| a != b).count() as u64;
            }
            pb.inc(1);
        }
        beam_times[vi] = best;
        // The brickmap's hits alone: tracing without shading or image.
        let mut best = f64::INFINITY;
        for _ in 0..s.repeat {
            let t = Instant::now();
            let hits = crate::trace::trace_hits(&brickmap, cam, &opts);
            best = best.min(t.elapsed().as_secs_f64());
            if let Some(r) = &reference {
                mismatches += r.iter().zip(&hits).filter(|(a, b)| a != b).count() as u64;
            }
            pb.inc(1);
        }
        hits_times[vi] = best;
    }
    pb.finish_and_clear();
    let brickmap_i = built.len() - 1;
    let beam = BeamFigures {
        view_mrays_per_s: beam_times.iter().map(|t| pixels as f64 / t / 1e6).collect(),
        view_speedup: beam_times
            .iter()
            .zip(&times[brickmap_i])
            .map(|(b, p)| p / b)
            .collect(),
    };

    let hits_only = HitsOnlyFigures {
        view_mrays_per_s: hits_times.iter().map(|t| pixels as f64 / t / 1e6).collect(),
        view_speedup: hits_times
            .iter()
            .zip(&times[brickmap_i])
            .map(|(h, p)| p / h)
            .collect(),
    };
    for (si, (structure, tracer, build_s)) in built.iter().enumerate() {
        let total: f64 = times[si].iter().sum();
        let rays = pixels * cameras.len() as u64;
        let mrays = rays as f64 / total / 1e6;
        let bytes = tracer.bytes() as u64;
        reports.push(StructureReport::Ok(StructureFigures {
            name: structure.name(),
            build_s: *build_s,
            bytes,
            solid_voxels: solid,
            nodes_or_bricks: tracer.nodes_or_bricks(),
            mrays_per_s: mrays,
            mrays_per_s_per_thread: mrays / threads as f64,
            fps: times[si].iter().map(|t| 1.0 / t).sum::<f64>() / cameras.len() as f64,
            hit_fraction: hit_counts[si] as f64 / rays as f64,
            bytes_per_solid_voxel: bytes as f64 / solid.max(1) as f64,
            view_mrays_per_s: times[si].iter().map(|t| pixels as f64 / t / 1e6).collect(),
        }));
    }
    // Keep the dense, svo, brickmap order with failures in place.
    reports.extend(failed);
    reports.sort_by_key(|r| {
        let n = match r {
            StructureReport::Ok(f) => f.name,
            StructureReport::Failed { name, .. } => name,
        };
        Structure::ALL.iter().position(|s| s.name() == n)
    });
    let ext = world.bounds().1 - world.bounds().0;
    Ok(BenchReport {
        scene: scene_name(&s.scene.spec),
        size: ext.to_array(),
        width: s.view.width,
        height: s.view.height,
        threads,
        views,
        structures: reports,
        agree: Agreement {
            rays: if built.len() > 1 {
                pixels * cameras.len() as u64
            } else {
                0
            },
            mismatches,
        },
        grid_voxels: ext.as_u64vec3().element_product(),
        scene_build_s,
        brickmap_beam: beam,
        brickmap_hits_only: hits_only,
    })
}

pub(crate) fn scene_name(spec: &crate::scene::SceneSpec) -> String {
    use crate::scene::SceneSpec::*;
    match spec {
        Terrain { caves: false } => "terrain".into(),
        Terrain { caves: true } => "terrain:caves".into(),
        Balls => "balls".into(),
        Hairball => "hairball".into(),
        Heightmap(p) => format!("heightmap:{}", p.display()),
        Vox(p) => format!("vox:{}", p.display()),
    }
}

fn print_table(r: &BenchReport) {
    println!(
        "{} {}x{}x{} at {}x{}, {} thread(s), {} view(s); cartesian grid {} voxels, {} solid",
        r.scene,
        r.size[0],
        r.size[1],
        r.size[2],
        r.width,
        r.height,
        r.threads,
        r.views.len(),
        r.grid_voxels,
        r.structures
            .iter()
            .find_map(|s| match s {
                StructureReport::Ok(f) => Some(f.solid_voxels),
                _ => None,
            })
            .unwrap_or(0)
    );
    println!(
        "{:<9} {:>9} {:>12} {:>9} {:>13} {:>9} {:>10} {:>7} {:>6}",
        "structure",
        "build s",
        "bytes",
        "B/solid",
        "nodes/bricks",
        "Mrays/s",
        "Mr/s/thr",
        "fps",
        "hit %"
    );
    for s in &r.structures {
        match s {
            StructureReport::Ok(f) => println!(
                "{:<9} {:>9.2} {:>12} {:>9.3} {:>13} {:>9.2} {:>10.2} {:>7.2} {:>6.1}",
                f.name,
                f.build_s,
                f.bytes,
                f.bytes_per_solid_voxel,
                f.nodes_or_bricks,
                f.mrays_per_s,
                f.mrays_per_s_per_thread,
                f.fps,
                f.hit_fraction * 100.0
            ),
            StructureReport::Failed { name, error } => println!("{name:<9} not built: {error}"),
        }
    }
    let per_view = |v: &[f64]| {
        v.iter()
            .map(|x| format!("{x:.2}"))
            .collect::<Vec<_>>()
            .join(" / ")
    };
    println!(
        "brickmap with beam starts: {} Mrays/s per view, {} x the plain brickmap",
        per_view(&r.brickmap_beam.view_mrays_per_s),
        per_view(&r.brickmap_beam.view_speedup)
    );
    println!(
        "brickmap hits alone (no shading): {} Mrays/s per view, {} x the rendered frames",
        per_view(&r.brickmap_hits_only.view_mrays_per_s),
        per_view(&r.brickmap_hits_only.view_speedup)
    );
    println!(
        "agreement: {} mismatches in {} rays",
        r.agree.mismatches, r.agree.rays
    );
}

#[cfg(test)]
mod tests {
    use super::{Agreement, verdict};

    /// "The bench exits non-zero if any mismatch is found": one mismatch
    /// is an error naming the count; none is success.
    #[test]
    fn any_mismatch_fails_the_bench() {
        assert!(
            verdict(&Agreement {
                rays: 100,
                mismatches: 0
            })
            .is_ok()
        );
        let e = verdict(&Agreement {
            rays: 100,
            mismatches: 1,
        })
        .unwrap_err()
        .to_string();
        assert!(e.contains("disagree on 1 of 100 rays"), "{e}");
    }
}
