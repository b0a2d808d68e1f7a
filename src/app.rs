//! The binary's edge: turns parsed arguments into work and reports errors
//! with context (anyhow lives here and in `main`, nowhere else).

use std::time::Instant;

use anyhow::{Context, Result, bail};
use glam::DVec3;

use crate::cli::{BenchCommand, Cli, Command, VerifyCommand};
use crate::config::{BenchTracersSettings, RenderSettings, SceneSettings};
use crate::progress::bar;
use crate::scene::{SceneWorld, build_scene};
use crate::trace::{Camera, RenderOptions, Structure, Tracer, render, write_npy, write_png};

/// Run a parsed command line.
pub fn run(cli: Cli) -> Result<()> {
    match cli.command {
        Command::Render(a) => run_render(RenderSettings::from_args(&a)?),
        Command::Run(a) => run_daemon(&a),
        Command::Ctl(a) => crate::engine::ctl::run(&a),
        Command::Export { out, world, state } => {
            let cfg = load_world_config(world.as_deref())?;
            let (tick, hash) = crate::engine::backup::export_world(&cfg, &state, &out)?;
            match hash {
                Some(hash) => println!(
                    "exported tick {tick} to {} (world hash {hash:#018x})",
                    out.display()
                ),
                None => println!("exported tick {tick} to {}", out.display()),
            }
            Ok(())
        }
        Command::Import { file, world, state } => {
            let cfg = load_world_config(world.as_deref())?;
            let st = crate::engine::backup::import_world(&cfg, &state, &file)?;
            println!(
                "imported {} into {} ({} chunks, {} chunk columns, {} bytes)",
                file.display(),
                state.display(),
                st.chunks,
                st.columns,
                st.bytes
            );
            Ok(())
        }
        Command::Init { dir } => {
            for p in crate::engine::daemon::init(&dir)? {
                println!("wrote {}", p.display());
            }
            println!(
                "run it with: brickworld run {} (scripts reload when saved)",
                dir.join("world.toml").display()
            );
            Ok(())
        }
        Command::Soak {
            minutes,
            json,
            world,
            state,
        } => {
            // The report compares fifths of one-second samples: shorter
            // runs printed NaN and -100 % as if they were results.
            if !(0.5..=24.0 * 60.0).contains(&minutes) {
                anyhow::bail!(
                    "invalid --minutes {minutes}: must be in 0.5..=1440 (the report compares fifths of one-second samples)"
                );
            }
            let pb = bar("soak (s)", 0);
            let r = crate::bench::soak::run(world.as_deref(), minutes, &state, &pb)?;
            pb.finish_and_clear();
            std::fs::write(&json, serde_json::to_string_pretty(&r)? + "\n")
                .with_context(|| format!("cannot write {}", json.display()))?;
            println!(
                "{:.1} min, {} ticks ({:.1}/s); RSS growth after warm-up {:+.2} % (end points), {:+.2} % (peak), {:+.2} % (median); max dirty queue {}; frames {} ({} skipped); /status p50 {:.2} ms, p99 {:.2} ms, max {:.2} ms; frame {:.1} ms; ground+sediment drift {:.2e}",
                r.minutes,
                r.ticks,
                r.ticks_per_s,
                r.rss_growth_after_warmup_pct,
                r.rss_peak_growth_pct,
                r.rss_median_growth_pct,
                r.max_dirty_queue,
                r.frames,
                r.frames_skipped,
                r.status_ms_p50,
                r.status_ms_p99,
                r.status_ms_max,
                r.frame_ms_mean,
                r.ground_plus_sediment_drift
            );
            Ok(())
        }
        Command::Chart { state } => {
            for p in crate::engine::timeline::chart(&state)? {
                println!("{}", p.display());
            }
            Ok(())
        }
        Command::Sim(a) => crate::sim_cmd::run(&crate::config::SimSettings::from_args(&a)?),
        Command::Verify(VerifyCommand::Sims(a)) => {
            // Refused, not clamped (regression: 2^64-1 ran for ever).
            if !(1..=1_000_000).contains(&a.conservation_steps) {
                anyhow::bail!(
                    "invalid --conservation-steps {}: must be in 1..=1000000 (10000 is the full check)",
                    a.conservation_steps
                );
            }
            crate::verify::run_sims(&a.json, a.chart.as_deref(), a.conservation_steps)
        }
        Command::Bench(BenchCommand::Sim(a)) => run_bench_sim(&a),
        Command::Bench(BenchCommand::Stream(a)) => run_bench_stream(&a),
        Command::Bench(BenchCommand::Voxels(a)) => run_bench_voxels(&a),
        Command::Bench(BenchCommand::Store(a)) => run_bench_store(&a),
        Command::Bench(BenchCommand::Flight(a)) => run_bench_flight(&a),
        Command::Bench(BenchCommand::Lod(a)) => {
            crate::bench::lod::run(&crate::config::BenchLodSettings::from_args(&a)?)
        }
        Command::Bench(BenchCommand::Tracers(a)) => {
            crate::bench::tracers::run(&BenchTracersSettings::from_args(&a)?)
        }
    }
}

fn load_world_config(
    path: Option<&std::path::Path>,
) -> Result<crate::engine::world_config::WorldConfig> {
    use crate::engine::world_config::WorldConfig;
    Ok(match path {
        Some(p) => WorldConfig::load(p)?,
        None => WorldConfig::default_world(),
    })
}

fn run_daemon(a: &crate::cli::RunArgs) -> Result<()> {
    use crate::engine::world_config::WorldConfig;
    let mut world = match &a.world {
        Some(p) => WorldConfig::load(p)?,
        None => WorldConfig::default_world(),
    };
    if let Some(addr) = &a.addr {
        world.addr = addr.parse().map_err(|_| {
            anyhow::anyhow!("invalid --addr '{addr}': expected HOST:PORT, e.g. 127.0.0.1:7878")
        })?;
    }
    if let Some(text) = &a.memory_budget {
        let bytes = crate::engine::world_config::parse_bytes(text)
            .map_err(|e| anyhow::anyhow!("invalid --memory-budget: {e}"))?;
        match world.stream.as_mut() {
            Some(st) => st.memory_budget = bytes,
            None => anyhow::bail!(
                "--memory-budget applies to streamed worlds; this world is resident whole (add a [stream] table to its config to stream it)"
            ),
        }
    }
    if let Some(dir) = &a.scripts {
        world.scripts_dir = dir.clone();
        world.scripts_embedded = false;
    }
    if a.ticks == Some(0) {
        anyhow::bail!("invalid --ticks 0: at least one tick");
    }
    crate::engine::daemon::run(crate::engine::daemon::DaemonOptions {
        world,
        state: a.state.clone(),
        max_ticks: a.ticks,
        until_tick: a.until_tick,
        paused: a.paused,
    })
}

fn run_bench_stream(a: &crate::cli::BenchStreamArgs) -> Result<()> {
    let scene = SceneSettings::from_args(&a.scene, glam::IVec3::new(512, 128, 512))?;
    if a.view > 2 {
        anyhow::bail!("invalid --view {}: must be 0, 1 or 2", a.view);
    }
    if a.width == 0 || a.height == 0 || a.width > 8192 || a.height > 8192 {
        anyhow::bail!(
            "invalid image size {}x{}: each side must be in 1..=8192",
            a.width,
            a.height
        );
    }
    if a.uploads == 0 {
        anyhow::bail!("invalid --uploads 0: at least one brick per frame");
    }
    crate::config::check_bench_outputs(&a.json, a.chart.as_deref())?;
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
    let r = crate::bench::stream::run(
        &mut world,
        a.view,
        a.width,
        a.height,
        a.uploads,
        a.pool,
        RenderOptions {
            lod,
            beam: a.beam,
            ..Default::default()
        },
        &pb,
    )?;
    pb.finish_and_clear();
    std::fs::write(&a.json, serde_json::to_string_pretty(&r)? + "\n")
        .with_context(|| format!("cannot write {}", a.json.display()))?;
    if let Some(path) = &a.chart {
        let pts: Vec<(f64, f64)> = r
            .uploads_per_frame
            .iter()
            .enumerate()
            .map(|(i, u)| ((i + 1) as f64, (*u).max(1) as f64))
            .collect();
        crate::bench::chart::xy_chart(
            path,
            "Bricks uploaded per frame from a cold pool",
            "frame (log)",
            "bricks uploaded (log; 1 = none)",
            &[crate::bench::chart::Series {
                name: "uploads",
                color: plotters::style::RGBColor(60, 110, 200),
                points: pts,
            }],
        )?;
    }
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
        "edit visible after {} frame(s); GPU {:.2} Mrays/s, CPU {:.2} Mrays/s; upload {:.1} MB/s",
        r.edit_to_visible_frames, r.gpu_mrays_per_s, r.cpu_mrays_per_s, r.upload_mb_per_s
    );
    println!(
        "material bytes uploaded: {} with hidden voxels culled, {} without, {} as DXT1",
        r.material_bytes_culled, r.material_bytes_unculled, r.material_bytes_dxt1
    );
    Ok(())
}

fn run_bench_sim(a: &crate::cli::BenchSimArgs) -> Result<()> {
    if a.sizes.is_empty() || a.sizes.iter().any(|s| *s < 8 || *s % 8 != 0 || *s > 8192) {
        anyhow::bail!(
            "invalid --sizes {:?}: each must be a multiple of 8 in 8..=8192",
            a.sizes
        );
    }
    let pool = bench_pool(a.steps, a.threads)?;
    pool.install(|| {
        let pb = bar("bench sim", 0);
        let r = crate::bench::sim::run(&a.json, &a.sizes, a.steps, &pb)?;
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

fn run_bench_flight(a: &crate::cli::BenchFlightArgs) -> Result<()> {
    use crate::engine::world_config::WorldConfig;
    let mut cfg = match &a.world {
        Some(p) => WorldConfig::load(p)?,
        None => WorldConfig::parse(
            "<embedded endless>",
            include_str!("../worlds/endless.toml"),
            std::path::Path::new("worlds"),
        )?,
    };
    if let (Some(text), Some(st)) = (&a.memory_budget, cfg.stream.as_mut()) {
        st.memory_budget = crate::engine::world_config::parse_bytes(text)
            .map_err(|e| anyhow::anyhow!("invalid --memory-budget: {e}"))?;
    }
    let pb = bar("flight (steps)", 0);
    let r = crate::bench::flight::run(&cfg, a.distance, a.step, a.frame_every, !a.no_wait, &pb)?;
    pb.finish_and_clear();
    std::fs::write(&a.json, serde_json::to_string_pretty(&r)? + "\n")
        .with_context(|| format!("cannot write {}", a.json.display()))?;
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

fn run_bench_store(a: &crate::cli::BenchStoreArgs) -> Result<()> {
    let size = crate::config::parse_size(&a.size)?;
    let bytes = size.x as i64 * size.y as i64 * size.z as i64;
    if bytes > 1 << 34 {
        anyhow::bail!("invalid --size {}: at most 2^34 voxels", a.size);
    }
    crate::scene::budget::check_world("the terrain", size)?;
    if a.chunks == 0 || a.repeats == 0 || a.repeats > 100 {
        anyhow::bail!("invalid --chunks/--repeats: at least 1 chunk, 1 to 100 repeats");
    }
    let pb = indicatif::ProgressBar::new_spinner().with_message("bench store");
    pb.enable_steady_tick(std::time::Duration::from_millis(200));
    let r = crate::bench::store::run(size, a.chunks, a.repeats, &a.dir)?;
    pb.finish_and_clear();
    std::fs::write(&a.json, serde_json::to_string_pretty(&r)? + "\n")
        .with_context(|| format!("cannot write {}", a.json.display()))?;
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

fn run_bench_voxels(a: &crate::cli::BenchVoxelsArgs) -> Result<()> {
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
    let pool = bench_pool(a.steps, a.threads)?;
    pool.install(|| {
        let pb = bar("bench voxels", 4);
        let r = crate::bench::voxels::run(size, a.steps as usize, || pb.inc(1));
        pb.finish_and_clear();
        std::fs::write(&a.json, serde_json::to_string_pretty(&r)? + "\n")
            .with_context(|| format!("cannot write {}", a.json.display()))?;
        print_voxels(&r);
        Ok(())
    })
}

/// Address space one worker thread takes: its 2 MiB stack, guard and
/// signal stack, with room for what it allocates.
const THREAD_ADDRESS_SPACE: u64 = (2 << 20) + (256 << 10);

/// Address space the process may still map under `ulimit -v`, if limited.
fn address_space_left() -> Option<u64> {
    #[cfg(target_os = "linux")]
    {
        let (soft, _) =
            nix::sys::resource::getrlimit(nix::sys::resource::Resource::RLIMIT_AS).ok()?;
        if soft == nix::sys::resource::RLIM_INFINITY {
            return None;
        }
        let status = std::fs::read_to_string("/proc/self/status").ok()?;
        let kb: u64 = status
            .lines()
            .find_map(|l| l.strip_prefix("VmSize:"))?
            .trim()
            .trim_end_matches("kB")
            .trim()
            .parse()
            .ok()?;
        Some(soft.saturating_sub(kb * 1024))
    }
    #[cfg(not(target_os = "linux"))]
    None
}

/// A rayon pool of `threads` workers (all cores when `None`).
pub fn thread_pool(threads: Option<usize>) -> Result<rayon::ThreadPool> {
    let mut b = rayon::ThreadPoolBuilder::new();
    if let Some(n) = threads {
        // Threads that start in the last of the address space fail inside
        // the runtime (an abort, now and then) rather than at creation:
        // refuse a count that cannot fit before starting any (regression).
        let need = n as u64 * THREAD_ADDRESS_SPACE;
        if let Some(left) = address_space_left()
            && need > left / 2
        {
            bail!(
                "cannot start the worker threads: {n} threads need about {} MiB of address space, and the limit (ulimit -v) leaves {} MiB (ask for fewer with --threads)",
                need >> 20,
                left >> 20
            );
        }
        b = b.num_threads(n);
    }
    // The build error's text already holds the OS error, which is also its
    // source: as a context chain it printed twice (regression).
    b.build().map_err(|e| {
        let lower = if threads.is_some() {
            " (ask for fewer with --threads)"
        } else {
            ""
        };
        anyhow::anyhow!("cannot start the worker threads: {e}{lower}")
    })
}

/// Build the scene with a progress bar.
pub fn build_world(s: &SceneSettings) -> Result<SceneWorld> {
    let pb = bar("scene", 0);
    let world = build_scene(&s.spec, s.size, s.seed, &pb).context("cannot build the scene")?;
    pb.finish_and_clear();
    Ok(world)
}

fn run_render(s: RenderSettings) -> Result<()> {
    crate::scene::budget::check_images("render", s.view.width, s.view.height, 1)?;
    let pool = thread_pool(s.view.threads)?;
    pool.install(|| {
        let t0 = Instant::now();
        let world = build_world(&s.scene)?;
        let view = s.view.view.unwrap_or_else(|| {
            let mut v = world.default_views()[0];
            if let Some(f) = s.view.fov {
                v.fov = f;
            }
            v
        });
        let camera = Camera::new(
            DVec3::from(view.eye),
            DVec3::from(view.target),
            view.fov,
            s.view.width,
            s.view.height,
        )
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
                let (ctx, line) = crate::gpu::choose(TracerChoice::Auto);
                eprintln!("{line}");
                ctx
            }
            TracerChoice::Gpu => match crate::gpu::GpuContext::new() {
                Ok(ctx) => Some(ctx),
                Err(e) => {
                    eprintln!("warning: {e}; rendering on the CPU instead");
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
            eprintln!(
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
        eprintln!(
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
