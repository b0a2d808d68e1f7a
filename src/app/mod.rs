//! The binary's edge: turns parsed arguments into work and reports errors
//! with context (anyhow lives here and in `main`, nowhere else).

mod bench;
mod bench_gpu;
mod render;

use anyhow::{Context, Result, bail};

use crate::cli::{BenchCommand, Cli, Command, VerifyCommand};
use crate::config::{BenchTracersSettings, RenderSettings, SceneSettings};
use crate::progress::bar;
use crate::scene::{SceneWorld, build_scene};
use bench::{run_bench_flight, run_bench_sim, run_bench_store, run_bench_stream, run_bench_voxels};
use render::run_render;

/// Run a parsed command line.
pub fn run(cli: Cli) -> Result<()> {
    // Before any thread: `nohup`'s ignore of SIGHUP holds for every command.
    crate::files::keep_sighup_ignored();
    if !matches!(
        cli.command,
        Command::Ctl(_) | Command::Init { .. } | Command::Chart { .. }
    ) {
        min_stack_env()?;
    }
    if matches!(cli.command, Command::Run(_)) {
        // Before any thread: the engine stops on it with a commit.
        crate::files::block_stop_signals();
    }
    match &cli.command {
        // Commands that build and run worlds on rayon's global pool.
        // The benches that build worlds without a pool of their own too
        // (regression, hostile environment probe: at a low `ulimit -u`,
        // rayon's lazy start of the global pool panicked inside them).
        Command::Run(_)
        | Command::Export { .. }
        | Command::Import { .. }
        | Command::Bench(
            BenchCommand::Store(_)
            | BenchCommand::Stream(_)
            | BenchCommand::Flight(_)
            | BenchCommand::Gpu(_),
        ) => global_pool()?,
        // The others use pools of their own (which read
        // `RAYON_NUM_THREADS` too), or none.
        Command::Ctl(_) | Command::Init { .. } | Command::Chart { .. } => {}
        _ => {
            rayon_env_threads()?;
        }
    }
    // One-shot commands that write files: an interrupt removes what they
    // were writing and says what is left (regression, stop-path probe:
    // they were killed by the signal and left their temporaries). The
    // engine, `import` and `soak` take their signals themselves, `export`
    // below, and `bench store` clears its scratch space too.
    if matches!(
        cli.command,
        Command::Render(_)
            | Command::Sim(_)
            | Command::Chart { .. }
            | Command::Init { .. }
            | Command::Verify(_)
    ) || matches!(&cli.command, Command::Bench(b) if !matches!(b, BenchCommand::Store(_)))
    {
        crate::files::remove_temps_on_interrupt()
            .context("cannot install the interrupt handler")?;
    }
    match cli.command {
        Command::Render(a) => run_render(RenderSettings::from_args(&a)?),
        Command::Run(a) => run_daemon(&a),
        Command::Ctl(a) => crate::engine::ctl::run(&a),
        Command::Export { out, world, state } => {
            crate::files::remove_temps_on_interrupt()?;
            let cfg = load_world_config(world.as_deref())?;
            let (tick, hash) = crate::engine::backup::export_world(&cfg, &state, &out)?;
            match hash {
                Some(hash) => crate::tell!(
                    "exported tick {tick} to {} (world hash {hash:#018x})",
                    out.display()
                ),
                None => crate::tell!("exported tick {tick} to {}", out.display()),
            }
            Ok(())
        }
        Command::Import { file, world, state } => {
            let cfg = load_world_config(world.as_deref())?;
            let redo = format!(
                "brickworld import {}{} --state {}",
                crate::shell_quoted(&file),
                world
                    .as_deref()
                    .map(|w| format!(" --world {}", crate::shell_quoted(w)))
                    .unwrap_or_default(),
                crate::shell_quoted(&state)
            );
            crate::engine::backup::say_interrupted_imports(redo)
                .context("cannot install the interrupt handler")?;
            let st = crate::engine::backup::import_world(&cfg, &state, &file)?;
            crate::tell!(
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
                crate::tell!("wrote {}", p.display());
            }
            // `shell_quoted` writes `-x` as `./-x`, so it is not a flag.
            crate::tell!(
                "run it with: brickworld run {} (scripts reload when saved)",
                crate::shell_quoted(&dir.join("world.toml"))
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
            // Checked before the soak, not after its minutes (regression,
            // odd-paths probe).
            crate::config::check_bench_outputs(&json, None)?;
            if let Some(w) = &world {
                crate::config::not_an_input("--json", &json, &[("world config", w)])?;
            }
            let pb = bar("soak (s)", 0);
            let r = crate::bench::soak::run(world.as_deref(), minutes, &state, &pb)?;
            pb.finish_and_clear();
            crate::bench::write_json(&json, &r)?;
            crate::bench::soak::reported();
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
            for (name, d) in &r.conserved_drift {
                println!(
                    "{name} (declared conserved) drift {d:.2e} (relative; absolute where it started at 0)"
                );
            }
            Ok(())
        }
        Command::Chart { state } => {
            for p in crate::engine::timeline::chart(&state)? {
                crate::tell!("{}", p.display());
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
            // Where the results go is checked before minutes of work
            // (regression: a --json into a missing folder failed at the end).
            crate::config::check_bench_outputs(&a.json, None)?;
            if let Some(dir) = &a.chart {
                if dir.exists() && !dir.is_dir() {
                    bail!(
                        "invalid --chart '{}': is a file; name a folder for the charts",
                        dir.display()
                    );
                }
                std::fs::create_dir_all(dir)
                    .with_context(|| format!("cannot create {}", dir.display()))?;
            }
            crate::verify::run_sims(&a.json, a.chart.as_deref(), a.conservation_steps)
        }
        Command::Bench(BenchCommand::Sim(a)) => run_bench_sim(&a),
        Command::Bench(BenchCommand::Stream(a)) => run_bench_stream(&a),
        Command::Bench(BenchCommand::Voxels(a)) => run_bench_voxels(&a),
        Command::Bench(BenchCommand::Store(a)) => run_bench_store(&a),
        Command::Bench(BenchCommand::Flight(a)) => run_bench_flight(&a),
        Command::Bench(BenchCommand::Gpu(a)) => bench_gpu::run_bench_gpu(&a),
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
    let flags = crate::config::RunSettings::from_args(a)?;
    let mut world = match &a.world {
        Some(p) => WorldConfig::load(p)?,
        None => WorldConfig::default_world(),
    };
    if let Some(addr) = flags.addr {
        world.addr = addr;
    }
    if let Some(bytes) = flags.memory_budget {
        match world.stream.as_mut() {
            Some(st) => st.memory_budget = bytes,
            None => anyhow::bail!(
                "--memory-budget applies to streamed worlds; this world is resident whole (add a [stream] table to its config to stream it)"
            ),
        }
    }
    if let Some(dir) = flags.scripts {
        // Named by its flag (regression, newcomer walk: `--scripts
        // w/world.toml` was reported as the config's `sim.scripts_dir`).
        if !dir.is_dir() {
            anyhow::bail!(
                "--scripts {}: not a folder (it names the folder that holds the world's scripts)",
                crate::text::shown(&dir.display().to_string(), 200)
            );
        }
        world.scripts_dir = dir;
        world.scripts_embedded = false;
    }
    crate::engine::daemon::run(crate::engine::daemon::DaemonOptions {
        world,
        state: a.state.clone(),
        max_ticks: flags.ticks,
        until_tick: a.until_tick,
        paused: a.paused,
    })
}

/// Address space one worker thread takes: its 2 MiB stack, guard and
/// signal stack, with room for what it allocates.
const THREAD_ADDRESS_SPACE: u64 = (2 << 20) + (256 << 10);

/// A rayon pool of `threads` workers (when `None`, `RAYON_NUM_THREADS`'s
/// count, else all cores).
pub fn thread_pool(threads: Option<usize>) -> Result<rayon::ThreadPool> {
    let (threads, hint) = match threads {
        Some(n) => (Some(n), " (ask for fewer with --threads)"),
        None => (
            rayon_env_threads()?,
            " (ask for fewer with --threads or RAYON_NUM_THREADS)",
        ),
    };
    // The build error's text already holds the OS error, which is also its
    // source: as a context chain it printed twice (regression).
    pool_builder(threads, hint)?
        .build()
        .map_err(|e| pool_error(e, threads.map(|_| hint)))
}

/// The most workers `RAYON_NUM_THREADS` may ask for (as `--threads`).
const MAX_THREADS: usize = 1024;

/// Build rayon's global pool, which the engine's stages and the scenes'
/// builders use, with `RAYON_NUM_THREADS` workers if set (1 to 1024; 0 or
/// unset: all cores). Built here, so that a pool that cannot start is one
/// line; on first use, rayon panics instead (regression, hostile probe:
/// `RAYON_NUM_THREADS=1000 brickworld run` under `ulimit -v` printed an
/// "internal bug", and 5 000 threads ran a 64³ world for minutes).
fn global_pool() -> Result<()> {
    let threads = rayon_env_threads()?;
    let hint = " (ask for fewer with RAYON_NUM_THREADS)";
    pool_builder(threads, hint)?
        .build_global()
        .map_err(|e| pool_error(e, threads.map(|_| hint)))
}

/// The least stack a thread of ours may be given: std's default for new
/// threads, which scripts' recursion limits and the tracers are sized for.
pub const MIN_THREAD_STACK: usize = 2 << 20;

/// The most stack a thread of ours may ask for through `RUST_MIN_STACK`.
pub const MAX_THREAD_STACK: usize = 1 << 30;

/// Refuse a `RUST_MIN_STACK` below [`MIN_THREAD_STACK`], or not a number:
/// std gives every new thread (rayon's workers, the render thread) that
/// much stack, and at 128 KiB a script's deep recursion overflowed a
/// worker, which aborts the process and loses the work since the last
/// commit; below 64 KiB even `render` aborted (regression, hostile
/// environment probe).
fn min_stack_env() -> Result<()> {
    let Some(v) = std::env::var_os("RUST_MIN_STACK") else {
        return Ok(());
    };
    // Empty is unset, as std reads it (a CI may export it empty; review).
    if v.to_str().is_some_and(|t| t.trim().is_empty()) {
        return Ok(());
    }
    match v.to_str().and_then(|t| t.trim().parse::<usize>().ok()) {
        Some(n) if (MIN_THREAD_STACK..=MAX_THREAD_STACK).contains(&n) => {
            // Every thread reserves that much address space: under `ulimit
            // -v` the threads then failed to start with errors that blamed
            // the thread limit or the signal handler (review).
            let threads = std::thread::available_parallelism().map_or(1, |c| c.get()) as u64 + 8;
            match crate::scene::budget::address_space_left() {
                Some(left) if (n as u64).saturating_mul(threads) > left => bail!(
                    "invalid RUST_MIN_STACK {n}: about {threads} threads of that stack need {}, and {} of address space is left (ulimit -v); ask for less, or unset it",
                    crate::scene::budget::human((n as u64).saturating_mul(threads)),
                    crate::scene::budget::human(left)
                ),
                _ => Ok(()),
            }
        }
        Some(n) if n < MIN_THREAD_STACK => bail!(
            "invalid RUST_MIN_STACK {n}: threads need at least {MIN_THREAD_STACK} bytes (2 MiB) of stack; unset it for the default"
        ),
        // Past this, starting threads fails for want of memory, which the
        // pool's error blamed on the thread limit (review).
        Some(n) => bail!(
            "invalid RUST_MIN_STACK {n}: at most {MAX_THREAD_STACK} bytes (1 GiB) of stack a thread; unset it for the default"
        ),
        None => bail!(
            "invalid RUST_MIN_STACK {v:?}: must be a number of bytes, at least {MIN_THREAD_STACK}; unset it for the default"
        ),
    }
}

/// The worker count `RAYON_NUM_THREADS` asks for: `None` when unset or 0
/// (all cores), an error outside 1..=1024.
fn rayon_env_threads() -> Result<Option<usize>> {
    Ok(match std::env::var("RAYON_NUM_THREADS") {
        Err(std::env::VarError::NotPresent) => None,
        Ok(v) => match v.trim().parse::<usize>() {
            Ok(0) => None,
            Ok(n) if n <= MAX_THREADS => Some(n),
            _ => bail!(
                "invalid RAYON_NUM_THREADS {v:?}: must be a number of worker threads in 1..={MAX_THREADS} (0, or unset, for all cores)"
            ),
        },
        Err(std::env::VarError::NotUnicode(v)) => {
            bail!("invalid RAYON_NUM_THREADS {v:?}: must be a number in 1..={MAX_THREADS}")
        }
    })
}

/// A pool builder for `threads` workers, refusing a count the address
/// space cannot hold (`hint` says how to ask for fewer).
fn pool_builder(threads: Option<usize>, hint: &str) -> Result<rayon::ThreadPoolBuilder> {
    let mut b = rayon::ThreadPoolBuilder::new();
    if let Some(n) = threads {
        // Threads that start in the last of the address space fail inside
        // the runtime (an abort, now and then) rather than at creation:
        // refuse a count that cannot fit before starting any (regression).
        let need = n as u64 * THREAD_ADDRESS_SPACE;
        if let Some(left) = crate::scene::budget::address_space_left()
            && need > left / 2
        {
            bail!(
                "cannot start the worker threads: {n} threads need about {} MiB of address space, and the limit (ulimit -v) leaves {} MiB{hint}",
                need >> 20,
                left >> 20
            );
        }
        b = b.num_threads(n);
    }
    Ok(b)
}

/// The one line for a pool that could not start.
fn pool_error(e: rayon::ThreadPoolBuildError, hint: Option<&str>) -> anyhow::Error {
    anyhow::anyhow!("cannot start the worker threads: {e}{}", hint.unwrap_or(""))
}

/// Build the scene with a progress bar.
pub fn build_world(s: &SceneSettings) -> Result<SceneWorld> {
    let pb = bar("scene", 0);
    let world = build_scene(&s.spec, s.size, s.seed, &pb).context("cannot build the scene")?;
    pb.finish_and_clear();
    Ok(world)
}
