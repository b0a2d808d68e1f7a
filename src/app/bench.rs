//! The `bench` subcommands' edge: checks their arguments, runs the
//! benchmark with a progress bar, writes its JSON (and chart) and prints
//! a summary.

use anyhow::Result;

use super::{build_world, thread_pool};
use crate::config::SceneSettings;
use crate::progress::bar;
use crate::trace::RenderOptions;

pub(super) fn run_bench_stream(a: &crate::cli::BenchStreamArgs) -> Result<()> {
    let scene = SceneSettings::from_args(&a.scene, glam::IVec3::new(512, 128, 512))?;
    if a.view > 2 {
        anyhow::bail!("invalid --view {}: must be 0, 1 or 2", a.view);
    }
    if a.width == 0 || a.height == 0 || a.width > 8192 || a.height > 8192 {
        anyhow::bail!(
            "invalid --width x --height {}x{}: each side must be in 1..=8192",
            a.width,
            a.height
        );
    }
    if a.uploads == 0 {
        anyhow::bail!("invalid --uploads 0: at least one brick per frame");
    }
    crate::config::check_bench_outputs(&a.json, a.chart.as_deref())?;
    scene.check_outputs(&a.json, a.chart.as_deref())?;
    if a.pool == 0 || a.pool > crate::gpu::MAX_POOL_SLOTS {
        anyhow::bail!(
            "invalid --pool {}: must be in 1..={} slots (the pool's cap)",
            a.pool,
            crate::gpu::MAX_POOL_SLOTS
        );
    }
    let lod = a
        .lod
        .map(|c| crate::config::lod_c("--lod", c))
        .transpose()?
        .unwrap_or(0.0);
    let mut world = build_world(&scene)?;
    let pb = bar("bench stream", 0);
    let setup = crate::bench::stream::StreamSetup {
        view: a.view,
        width: a.width,
        height: a.height,
        budget: a.uploads,
        pool_slots: a.pool,
        opts: RenderOptions {
            lod,
            beam: a.beam,
            ..Default::default()
        },
    };
    let r = crate::bench::stream::run(&mut world, &setup, &pb)?;
    pb.finish_and_clear();
    let pts: Vec<(f64, f64)> = r
        .uploads_per_frame
        .iter()
        .enumerate()
        .map(|(i, u)| ((i + 1) as f64, (*u).max(1) as f64))
        .collect();
    let draw = |path: &std::path::Path| {
        crate::bench::chart::xy_chart(
            path,
            "Bricks uploaded per frame from a cold pool",
            "frame (log)",
            "bricks uploaded (log; 1 = none)",
            &[crate::bench::chart::Series {
                name: "uploads",
                color: plotters::style::RGBColor(60, 110, 200),
                points: pts.clone(),
            }],
        )
    };
    crate::bench::write_outputs(
        &a.json,
        &(serde_json::to_string_pretty(&r)? + "\n"),
        a.chart.as_deref(),
        draw,
    )?;
    println!("adapter: {}", r.adapter);
    println!(
        "converged after {} frames; uploads per frame {:?}",
        r.frames_to_converge, r.uploads_per_frame
    );
    println!(
        "frame ms: static {:.1}, streaming {:.1} ({:+.0} %), editing {:.1} ({:+.0} %)",
        r.frame_ms.r#static,
        r.frame_ms.streaming,
        (r.frame_ms.streaming / r.frame_ms.r#static - 1.0) * 100.0,
        r.frame_ms.editing,
        (r.frame_ms.editing / r.frame_ms.r#static - 1.0) * 100.0
    );
    println!(
        "GPU memory {} B = {:.1} % of the world's {} B; {} of {} bricks resident",
        r.gpu_bytes,
        r.gpu_bytes as f64 / r.world_brick_bytes as f64 * 100.0,
        r.world_brick_bytes,
        r.resident_bricks,
        r.world_bricks
    );
    println!(
        "working set (bricks the converged frame's rays touched): {} bricks, {:.1} % of the world's bytes",
        r.working_set_bricks,
        r.working_set_fraction * 100.0
    );
    let visible = match r.edit_to_visible_frames {
        Some(n) => format!("edit visible after {n} frame(s)"),
        None => format!(
            "edit NOT visible within {} frames (raise --uploads or --pool)",
            crate::bench::stream::EDIT_FRAMES
        ),
    };
    println!(
        "{visible}; GPU {:.2} Mrays/s, CPU {:.2} Mrays/s; upload {:.1} MB/s",
        r.gpu_mrays_per_s, r.cpu_mrays_per_s, r.upload_mb_per_s
    );
    println!(
        "material bytes uploaded: {} with hidden voxels culled, {} without, {} as DXT1",
        r.material_bytes_culled, r.material_bytes_unculled, r.material_bytes_dxt1
    );
    Ok(())
}

pub(super) fn run_bench_sim(a: &crate::cli::BenchSimArgs) -> Result<()> {
    let sizes = crate::config::parse_sim_sizes(&a.sizes)?;
    // Measured: about 290 bytes a column at its peak (1024²: 317 MB), plus
    // the process; refused before any work, not by the allocator's abort
    // (regression, hostile probe: --sizes 4096 and 8192 aborted).
    let have = crate::scene::budget::available_bytes();
    for &size in &sizes {
        let need = 320 * (size as u64).pow(2) + (64 << 20);
        if need > have {
            anyhow::bail!(
                "bench sim --sizes {size} needs about {} of memory; {} is available (use a smaller size)",
                crate::scene::budget::human(need),
                crate::scene::budget::human(have)
            );
        }
    }
    crate::config::check_bench_outputs(&a.json, None)?;
    let pool = bench_pool(a.steps, a.threads)?;
    pool.install(|| {
        let pb = bar("bench sim", 0);
        let r = crate::bench::sim::run(&a.json, &sizes, a.steps, &pb)?;
        pb.finish_and_clear();
        println!(
            "{:<8} {:>6} {:>14} {:>14} {:>8} {:>7}",
            "script", "size", "lua cells/s", "native cells/s", "ratio", "active"
        );
        for s in &r.scripts {
            println!(
                "{:<8} {:>6} {:>14.3e} {:>14} {:>8} {:>7}",
                s.name,
                s.size,
                s.lua_cells_per_s,
                s.native_cells_per_s
                    .map_or("-".into(), |n| format!("{n:.3e}")),
                s.lua_over_native.map_or("-".into(), |r| format!("{r:.2}")),
                s.active_bricks
            );
        }
        for p in &r.scaling {
            println!(
                "wet {:>6.4}: {:>6} active tiles, {:.2} ms/step",
                p.wet_fraction, p.active_bricks, p.step_ms
            );
        }
        print_voxels(&r.voxels);
        Ok(())
    })
}

fn print_voxels(v: &crate::bench::voxels::VoxelBench) {
    println!(
        "water3d on {}x{}x{} ({} bricks, {} threads): Lua {:.3e} active-voxel updates/s, native {:.3e} (Lua/native {:.2}); halo and crossing alone {:.3e} ({:.0} % of a Lua step); native bit-identical to Lua: {}",
        v.world[0],
        v.world[1],
        v.world[2],
        v.bricks,
        v.threads,
        v.lua.updates_per_s,
        v.native.updates_per_s,
        v.lua_over_native,
        v.crossing.updates_per_s,
        v.crossing_share * 100.0,
        v.native_matches_lua
    );
    println!(
        "sleeping: {:.2} % of bricks awake ({:.0} candidates) costs {:.4} of a fully active step ({:.2} ms against {:.1} ms)",
        v.sparse.active_fraction * 100.0,
        v.sparse.candidates,
        v.sparse.over_full,
        v.sparse.step_ms,
        v.lua.step_ms
    );
}

/// The simulation benches' shared checks of `--steps` and `--threads`, and
/// their thread pool.
fn bench_pool(steps: u32, threads: Option<usize>) -> Result<rayon::ThreadPool> {
    if steps == 0 || steps > 10_000 {
        anyhow::bail!("invalid --steps {steps}: must be in 1..=10000");
    }
    if threads == Some(0) {
        anyhow::bail!("invalid --threads 0: must be at least 1");
    }
    thread_pool(threads)
}

/// Most bricks `bench voxels` builds (each holds ~5 KB of materials and
/// channels, in three worlds built one after another).
const MAX_BENCH_VOXEL_BRICKS: i64 = 1 << 17;

pub(super) fn run_bench_flight(a: &crate::cli::BenchFlightArgs) -> Result<()> {
    use crate::engine::world_config::WorldConfig;
    let mut cfg = match &a.world {
        Some(p) => WorldConfig::load(p)?,
        None => WorldConfig::parse(
            "<embedded endless>",
            include_str!("../../worlds/endless.toml"),
            std::path::Path::new("worlds"),
        )?,
    };
    // The output is checked before the flight, and is not the config it
    // flies (regression, odd-paths probe: a missing folder failed after
    // the whole run; `--json W --world W` replaced the config).
    crate::config::check_bench_outputs(&a.json, None)?;
    if let Some(w) = &a.world {
        crate::config::not_an_input("--json", &a.json, &[("world config", w)])?;
    }
    if let (Some(text), Some(st)) = (&a.memory_budget, cfg.stream.as_mut()) {
        st.memory_budget = crate::engine::world_config::parse_bytes(text)
            .map_err(|e| anyhow::anyhow!("invalid --memory-budget: {e}"))?;
    }
    let pb = bar("flight (steps)", 0);
    let r = crate::bench::flight::run(&cfg, a.distance, a.step, a.frame_every, !a.no_wait, &pb)?;
    pb.finish_and_clear();
    crate::bench::write_json(&a.json, &r)?;
    println!(
        "flew {:.0} voxels in {:.1} s ({:.0} voxels/s{}): resident memory peaked at {} against a budget of {} ({:+.1} %), baseline {}; {} slides of {:.1} ms mean, {:.1} ms worst; {} frames of {:.0} ms, {:.0} % of columns still coarse when drawn; {} columns generated, {} from the cache, {} evicted",
        r.distance,
        r.seconds,
        r.voxels_per_s,
        if r.exact { ", every step exact" } else { "" },
        crate::scene::budget::human(r.rss_max_kb * 1024),
        crate::scene::budget::human(r.budget_bytes),
        r.rss_max_over_budget_pct,
        crate::scene::budget::human(r.baseline_kb * 1024),
        r.slides,
        r.slide_ms_mean,
        r.slide_ms_max,
        r.frames,
        r.frame_ms_mean,
        r.coarse_fraction_mean * 100.0,
        r.window.generated,
        r.window.cache_hits,
        r.window.evicted,
    );
    Ok(())
}

pub(super) fn run_bench_store(a: &crate::cli::BenchStoreArgs) -> Result<()> {
    let size = crate::config::parse_size(&a.size)?;
    let bytes = size.x as i64 * size.y as i64 * size.z as i64;
    if bytes > 1 << 34 {
        anyhow::bail!("invalid --size {}: at most 2^34 voxels", a.size);
    }
    crate::scene::budget::check_world("the terrain", size)?;
    crate::config::check_bench_outputs(&a.json, None)?;
    if a.chunks == 0 {
        anyhow::bail!("invalid --chunks 0: at least 1 chunk");
    }
    if a.repeats == 0 || a.repeats > 100 {
        anyhow::bail!("invalid --repeats {}: 1 to 100 repeats", a.repeats);
    }
    crate::files::remove_scratch_on_interrupt()?;
    let pb = crate::progress::spinner("bench store");
    let r = crate::bench::store::run(size, a.chunks, a.repeats, &a.dir)?;
    pb.finish_and_clear();
    crate::bench::write_json(&a.json, &r)?;
    println!(
        "store on terrain {}x{}x{} ({} chunks): commit of {} chunks + {} columns {:.0} ms best ({:?}), {} bytes ({:.0} per blob); store file {} bytes; generate {:.0} ms, restore {:.0} ms",
        r.size[0],
        r.size[1],
        r.size[2],
        r.world_chunks,
        r.chunks,
        r.columns,
        r.commit_best_ms,
        r.commit_ms.iter().map(|m| m.round()).collect::<Vec<_>>(),
        r.commit_bytes,
        r.bytes_per_chunk,
        r.store_file_bytes,
        r.generate_ms,
        r.restore_ms
    );
    Ok(())
}

pub(super) fn run_bench_voxels(a: &crate::cli::BenchVoxelsArgs) -> Result<()> {
    let size = crate::config::parse_size(&a.size)?;
    if size.y < 48 || size.x % 16 != 0 || size.z % 16 != 0 || size.x < 32 || size.z < 32 {
        anyhow::bail!(
            "invalid --size {}: x and z must be multiples of 16 of at least 32, y at least 48",
            a.size
        );
    }
    let bricks = (size.x / 8) as i64 * (size.y / 8) as i64 * (size.z / 8) as i64;
    if bricks > MAX_BENCH_VOXEL_BRICKS {
        anyhow::bail!(
            "invalid --size {}: {bricks} bricks; at most {MAX_BENCH_VOXEL_BRICKS}",
            a.size
        );
    }
    crate::config::check_bench_outputs(&a.json, None)?;
    let pool = bench_pool(a.steps, a.threads)?;
    pool.install(|| {
        let pb = bar("bench voxels", 4);
        let r = crate::bench::voxels::run(size, a.steps as usize, || pb.inc(1));
        pb.finish_and_clear();
        crate::bench::write_json(&a.json, &r)?;
        print_voxels(&r);
        Ok(())
    })
}
