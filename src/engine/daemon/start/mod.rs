//! The engine's start-up, in named stages: listen, install the signal
//! handler, open the store, build the world, watch the scripts folder,
//! reconcile the material ids and load the scripts ([`super::scripts`]),
//! then resume from the store or place the config's boxes on a first
//! start; then the frames folder, the render thread and the timeline.

mod world;

pub(crate) use world::fixed_world;

use std::path::Path;
use std::sync::Arc;
use std::sync::atomic::Ordering;
use std::time::Instant;

use anyhow::{Context, Result};
use rustc_hash::FxHashSet;

use self::world::{Loaded, build_world, first_start, open_store, resume};
use super::report::{ring_columns, timeline_columns};
use super::scripts::{load_scripts, reconcile_materials, start_watcher};
use super::{DaemonOptions, Engine, ScriptNotes};
use crate::engine::control::{ControlServer, Shared};
use crate::engine::persistence::{self, DirtyChunks};
use crate::engine::render_thread::{RenderSettings, RenderThread};
use crate::engine::state_dir;
use crate::engine::timeline::Timeline;
use crate::engine::world_config::WorldConfig;
use crate::sim::WorldSim;

impl Engine {
    /// Lock, listen, resume or build, load the scripts, start rendering. A
    /// start that fails removes the state directory if it made it
    /// (regression: a missing script left a directory with a lock, a token
    /// and an empty store behind).
    pub fn start(opts: DaemonOptions) -> Result<Engine> {
        let state = opts.state.clone();
        // The lock comes first: a second engine on this directory must not
        // touch its token or checkpoints.
        let (lock, made) = state_dir::claim(&state)?;
        // Held through a failed start's clean-up, so no other engine can
        // have taken the directory meanwhile (one lock, two handles).
        let held = match lock.try_clone() {
            Ok(held) => held,
            Err(e) => {
                // Still locked by `lock`: what this start made goes
                // (regression, hostile environment probe: at `ulimit -n 4`
                // a folder holding only engine.lock was left). Out of file
                // handles, a folder cannot be opened to be emptied: it holds
                // only the lock file, which is removed by name.
                if !made.is_empty() {
                    let _ = std::fs::remove_file(state.join("engine.lock"));
                    crate::files::remove_made_if_empty(&made);
                }
                return Err(e.into());
            }
        };
        let started = Self::start_locked(opts, lock);
        if started.is_err() {
            crate::files::remove_made(&made);
        }
        drop(held);
        started
    }

    fn start_locked(opts: DaemonOptions, lock: state_dir::StateLock) -> Result<Engine> {
        let cfg = opts.world;
        // A frame (and an anti-aliased frame's sums) must fit in memory.
        crate::scene::budget::check_images(
            "render.width/render.height",
            cfg.width,
            cfg.height,
            if cfg.look.aa > 1 { 3 } else { 2 },
        )?;
        let token = state_dir::new_token()?;
        let shared = Arc::new(Shared::new(token.clone(), cfg.hosts.clone()));
        // Listen before any work: a taken port is a clear error at once.
        // Named by its field (a taken port is the usual cause).
        let server = ControlServer::start(cfg.addr, shared.clone()).map_err(|e| {
            if e.blames_addr() {
                anyhow::anyhow!("{}: control.addr (or --addr): {e}", cfg.file)
            } else {
                anyhow::anyhow!("{e}")
            }
        })?;
        // The command that reaches this engine, as its hints give it (the
        // bound address: port 0 picks one; review).
        let ctl = crate::engine::ctl::ctl_command(server.addr, &opts.state);
        install_signal_handler(&shared)?;
        let mut db = open_store(&opts.state, &cfg)?;
        // Written once the store is this engine's: a second engine refused
        // by the store's own lock replaced the running engine's token
        // (regression, hostile probe).
        let token_path = state_dir::write_token(&opts.state, &token)?;
        state_dir::write_addr(&opts.state, server.addr)?;
        let (mut world, stream_plan) = build_world(&cfg, &db)?;
        let follow = stream_plan
            .as_ref()
            .filter(|(_, rule)| rule.follows())
            .map(|(plan, rule)| super::follow::Follow::new(plan.gen_.clone(), *rule));
        let stream_plan = stream_plan.map(|(plan, _)| plan);
        // `/status` shows the budget kept to, lowered where the machine
        // has less than the config asks (review).
        let mut cfg = cfg;
        if let (Some(st), Some(plan)) = (cfg.stream.as_mut(), &stream_plan) {
            st.memory_budget = plan.window.budget_bytes;
        }
        if let Some(msg) = crate::sim::run::reserved_conflicts(&world.materials) {
            anyhow::bail!("{}: {msg}", cfg.file);
        }
        // A region that follows the camera has closed edges (see
        // `follow.rs`); a fixed one drains over them like a small world.
        let mut ws = WorldSim::with_edges(&mut world, follow.is_none());
        // The ground read from the generated world is regenerated on every
        // start: not a change to commit.
        ws.sim.channels_mut().take_dirty();
        ws.set_seed(cfg.seed);
        let mut dirty_chunks = DirtyChunks::default();
        // A stored name keeps its stored id for `materials.lua` and the
        // scripts (regression: a material declared before the others
        // shifted their ids, under voxels stored with the old ones).
        // The scene declares its materials (and the simulation's).
        let scene: Vec<(u8, String)> = world.materials.names();
        persistence::seed_materials(&db, &mut world)?;
        let watcher = start_watcher(&cfg);
        reconcile_materials(&cfg, &db, &mut world, scene)?;
        // `BRICKWORLD_TEST_START_STALL_MS`: a pause before the scripts
        // load, so a test can stop a start that takes longer than
        // STOP_GRACE. Unset in normal use.
        if let Some(ms) = std::env::var("BRICKWORLD_TEST_START_STALL_MS")
            .ok()
            .and_then(|v| v.parse().ok())
        {
            std::thread::sleep(std::time::Duration::from_millis(ms));
        }
        load_scripts(&cfg, &mut world, &mut ws)?;
        let watcher = watcher.unwrap_or_else(|e| {
            crate::say!("warning: hot reload is off: {e}");
            None
        });
        ws.check_memory()
            .with_context(|| format!("{}: [sim] scripts", cfg.file))?;
        if let Some(w) = crate::sim::run::below_zero_warning(&ws, &world) {
            crate::say!("{w}");
        }
        // The stored chunks go over the generated world once the scripts
        // have registered their channels, so channel ids are the same as in
        // a run that never stopped.
        let resumed = persistence::restore_chunks(
            &db,
            &mut world,
            &mut ws,
            &mut dirty_chunks,
            persistence::RestoreScope {
                regenerable: cfg.source.is_procedural(),
                region: cfg.stream.is_some(),
                whole_columns: follow.is_some(),
            },
        )?;
        let Loaded {
            camera,
            camera_override,
            loaded_from,
        } = match &resumed {
            None => {
                first_start(&cfg, &mut db, &mut world, &mut ws, &mut dirty_chunks)?;
                Loaded {
                    camera: cfg.camera,
                    camera_override: None,
                    loaded_from: None,
                }
            }
            Some(r) => resume(&cfg, &ctl, &db, &world, &mut ws, r),
        };
        let frames_dir = frames_folder(&opts.state, &cfg)?;
        let renderer = RenderThread::spawn(
            RenderSettings {
                look: cfg.look,
                stream: stream_plan,
                frames_dir,
                keep: cfg.frames_keep,
                max_bytes: cfg.frames_max_bytes,
            },
            shared.clone(),
        )
        .context("cannot start the render thread")?;
        let timeline = open_timeline(&opts.state, &ws, &shared)?;
        // A stop asked for while the world loaded: the engine commits and
        // ends before its first step, so it does not say it is running
        // (regression: it printed the viewer's address, then stopped).
        // `--until-tick` at or below the restored tick: nothing runs, so
        // the engine does not say it is running either (newcomer walk: it
        // printed the viewer's address, then "nothing to run").
        let nothing_to_run = opts.until_tick.is_some_and(|t| ws.sim.tick() >= t);
        if shared.shutdown.load(Ordering::Relaxed) {
            crate::say!("the world is loaded: stopping, as asked during the start");
        } else if nothing_to_run {
            crate::say!(
                "the world is already at tick {}: nothing to run",
                ws.sim.tick()
            );
        } else {
            crate::tell!(
                "brickworld is running: viewer http://{}/ (control token in {}: {token})",
                server.addr,
                token_path.display()
            );
        }
        if opts.paused && !shared.shutdown.load(Ordering::Relaxed) && !nothing_to_run {
            crate::say!(
                "paused at tick {}: `{ctl} resume` or `{ctl} step N` runs it",
                ws.sim.tick()
            );
        }
        let n = ws.script_count();
        // A first start has the world to store, and a resume that repaired
        // chunks (regenerated a corrupt one) has them; otherwise nothing is
        // new until something runs or changes.
        let changed_since_load = loaded_from.is_none() || !dirty_chunks.is_empty();
        let mut engine = Engine {
            camera,
            camera_override,
            start_tick: ws.sim.tick(),
            cfg,
            max_ticks: opts.max_ticks,
            until_tick: opts.until_tick,
            _lock: lock,
            shared,
            server: Some(server),
            world,
            ws,
            renderer,
            db,
            watcher,
            timeline,
            dirty_pending: FxHashSet::default(),
            dirty_chunks,
            mirror_sent: false,
            view_due: false,
            paused: opts.paused,
            steps_left: 0,
            notes: vec![ScriptNotes::default(); n],
            last_commit: None,
            loaded_from,
            commit_error: None,
            render_error: None,
            materials_note: None,
            snapshot_ms: 0.0,
            active_bricks: 0,
            rate: super::rate::StepRate::new(Instant::now()),
            script_ms: vec![0.0; n],
            follow,
            step_cut: false,
            changed_since_load,
        };
        // Publish the loaded world in one go: a client that sees the scripts
        // also sees the tick and where it was resumed from (regression: a
        // restart test read `loaded_from: null` in between).
        engine.publish_status();
        engine.shared.started.store(true, Ordering::Release);
        Ok(engine)
    }
}

/// The frames folder, made if missing; something else at its path is
/// refused, naming the field (regression, hostile probe: `dir =
/// "/dev/null"` said "cannot create /dev/null: File exists").
fn frames_folder(state: &Path, cfg: &WorldConfig) -> Result<std::path::PathBuf> {
    let frames_dir = state.join(&cfg.frames_dir);
    if frames_dir.exists() && !frames_dir.is_dir() {
        anyhow::bail!(
            "frames.dir: {} is not a folder (frames are written into one)",
            frames_dir.display()
        );
    }
    std::fs::create_dir_all(&frames_dir)
        .with_context(|| format!("frames.dir: cannot create {}", frames_dir.display()))?;
    // A folder no file can be made in (`/proc`, a read-only mount) is
    // refused at start (regression, hostile probe: every frame failed,
    // said once a minute as "its folder was deleted or replaced").
    let (probe, _) = crate::files::fresh_temp_beside(&frames_dir.join("frame"))
        .with_context(|| format!("frames.dir: cannot write in {}", frames_dir.display()))?;
    let _ = std::fs::remove_file(probe);
    Ok(frames_dir)
}

/// The timeline, with the rows after the resumed tick dropped (they run
/// again), and the viewer's charts filled from its history on disk.
fn open_timeline(state: &Path, ws: &WorldSim, shared: &Shared) -> Result<Timeline> {
    let mut timeline = Timeline::open(&state.join("timeline.csv"), &timeline_columns(ws))?;
    // The timeline never stops the engine: a trim that fails is said.
    match timeline.drop_rows_after(ws.sim.tick()) {
        Ok(Some(aside)) => crate::say!(
            "timeline: rows after tick {} (to be run again) dropped; they are kept in {}",
            ws.sim.tick(),
            aside.display()
        ),
        Ok(None) => {}
        Err(e) => crate::say!("warning: {e:#}"),
    }
    // The viewer's charts start from the history on disk, not empty
    // after every restart (regression, docs walk). Only rows of the
    // same columns: another header was moved aside by `open`.
    let names = ring_columns(timeline_columns(ws));
    if let Ok(past) = crate::engine::timeline::read_tail(
        &state.join("timeline.csv"),
        crate::engine::control::exchange::TIMELINE_ROWS,
    ) && past.columns == names
        && let Ok(mut ring) = shared.timeline.lock()
    {
        for row in past.rows {
            ring.push(&names, row);
        }
    }
    Ok(timeline)
}

/// Who asked the engine to stop, for [`install_signal_handler`].
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
enum Asked {
    /// SIGINT, SIGTERM or SIGHUP (through `ctrlc`).
    Terminal,
    /// Another signal a user sends (SIGQUIT, SIGUSR1/2, SIGALRM).
    Named(&'static str),
    /// SIGXCPU, which the kernel repeats each second.
    CpuLimit,
}

/// The first SIGINT/SIGTERM/SIGHUP (or SIGQUIT, SIGUSR1/2, SIGALRM)
/// stops after the step in flight, with a final
/// checkpoint; a step still running after STOP_GRACE is interrupted (and
/// not committed). A second signal exits at once (the last checkpoint on
/// disk stays good), unless it came within SAME_REQUEST of the first: GNU
/// timeout signals the engine and then its process group, so one request
/// arrives twice (regression, operator probe: a run under `timeout` lost
/// its final commit one time in three).
///
/// The grace timer's thread starts here, not in the handler: a handler
/// that could not start it (the process at its thread limit) panicked,
/// which ended the handler's thread, and a second signal no longer stopped
/// the engine (regression, hostile environment probe).
fn install_signal_handler(shared: &Arc<Shared>) -> Result<()> {
    let (arm, armed) = crossbeam_channel::bounded::<()>(1);
    std::thread::Builder::new()
        .name("stop grace".into())
        .spawn(move || {
            if armed.recv().is_ok() {
                std::thread::sleep(super::STOP_GRACE);
                crate::sim::interrupt::stop_all();
            }
        })
        .context("cannot start the stop timer's thread")?;
    let s = shared.clone();
    let mut first: Option<std::time::Instant> = None;
    // `Asked::CpuLimit`: SIGXCPU, a request of the system's, which it
    // repeats each second: its repeats are not a second request, and a
    // user's signal after it is the user's first (review: each repeat
    // printed its line again, and a SIGTERM after it skipped the final
    // commit).
    let on_signal = move |asked: Asked| {
        let stopping = s.shutdown.swap(true, Ordering::Relaxed);
        if asked == Asked::CpuLimit {
            if stopping {
                return;
            }
            crate::say!("the soft CPU-time limit was reached (SIGXCPU): stopping");
        } else {
            if let Some(t) = first {
                if t.elapsed() < super::SAME_REQUEST {
                    return;
                }
                crate::say!("second signal: exiting now, without a final checkpoint");
                std::process::exit(130);
            }
            first = Some(std::time::Instant::now());
            if let Asked::Named(name) = asked {
                crate::say!("{name} received: stopping with a final commit");
            }
            if stopping {
                // A stop is under way (SIGXCPU asked first): this joins it.
                return;
            }
        }
        // While the world is still loading no step is in flight,
        // and the loop checks the flag before each: interrupting
        // the scripts would fail the start's own smoke tests
        // (regression, concurrency probe: a stop during a start of
        // over 5 s ended in "materials.lua: interrupted", exit 1).
        if !s.started.load(Ordering::Acquire) {
            crate::say!("stopping once the world is loaded");
            return;
        }
        let _ = arm.try_send(());
    };
    let on_signal = Arc::new(std::sync::Mutex::new(on_signal));
    let handler = on_signal.clone();
    ctrlc::set_handler(move || {
        (handler.lock().unwrap_or_else(|e| e.into_inner()))(Asked::Terminal)
    })
    .context("cannot install the SIGINT/SIGTERM handler")?;
    // The other stop signals (SIGXCPU past a soft CPU-time limit, as batch
    // schedulers set to say "save now" before the hard limit; SIGQUIT;
    // SIGUSR1/2; SIGALRM): blocked in every thread since `app::run` (see
    // [`crate::files::block_stop_signals`]), and taken here as a stop
    // request. Each killed the engine without a final commit (regressions,
    // hostile environment probe and its follow-up).
    #[cfg(target_os = "linux")]
    let real_time = on_signal.clone();
    #[cfg(unix)]
    std::thread::Builder::new()
        .name("stop signals".into())
        .spawn(move || {
            use nix::sys::signal::Signal;
            let set = crate::files::stop_signals();
            while let Ok(sig) = set.wait() {
                let asked = match sig {
                    Signal::SIGXCPU => Asked::CpuLimit,
                    other => Asked::Named(other.as_str()),
                };
                (on_signal.lock().unwrap_or_else(|e| e.into_inner()))(asked);
            }
        })
        .context("cannot start the stop signals' thread")?;
    #[cfg(target_os = "linux")]
    take_real_time_signals(real_time)?;
    Ok(())
}

/// The names of the real-time signals, from `SIGRTMIN` up (Linux has 32
/// at most; glibc keeps the first two or three for itself).
#[cfg(target_os = "linux")]
const REAL_TIME: [&str; 32] = [
    "SIGRTMIN",
    "SIGRTMIN+1",
    "SIGRTMIN+2",
    "SIGRTMIN+3",
    "SIGRTMIN+4",
    "SIGRTMIN+5",
    "SIGRTMIN+6",
    "SIGRTMIN+7",
    "SIGRTMIN+8",
    "SIGRTMIN+9",
    "SIGRTMIN+10",
    "SIGRTMIN+11",
    "SIGRTMIN+12",
    "SIGRTMIN+13",
    "SIGRTMIN+14",
    "SIGRTMIN+15",
    "SIGRTMIN+16",
    "SIGRTMIN+17",
    "SIGRTMIN+18",
    "SIGRTMIN+19",
    "SIGRTMIN+20",
    "SIGRTMIN+21",
    "SIGRTMIN+22",
    "SIGRTMIN+23",
    "SIGRTMIN+24",
    "SIGRTMIN+25",
    "SIGRTMIN+26",
    "SIGRTMIN+27",
    "SIGRTMIN+28",
    "SIGRTMIN+29",
    "SIGRTMIN+30",
    "SIGRTMIN+31",
];

/// Take the real-time signals (`SIGRTMIN` to `SIGRTMAX`) as stop requests
/// too, on a thread of their own: their default action ended the engine
/// without a final commit (a known gap). `nix`'s signal sets, which the
/// other stop signals' thread waits on, cannot name them, so
/// `signal-hook`'s safe handlers take them here.
#[cfg(target_os = "linux")]
fn take_real_time_signals<F: FnMut(Asked) + Send + 'static>(
    on_signal: Arc<std::sync::Mutex<F>>,
) -> Result<()> {
    let (lo, hi) = (libc::SIGRTMIN(), libc::SIGRTMAX());
    // Registered here, before the thread starts, so that a signal sent once
    // `run` says it is up is taken.
    let mut signals = signal_hook::iterator::Signals::new(lo..=hi)
        .context("cannot take the real-time signals")?;
    std::thread::Builder::new()
        .name("real-time signals".into())
        .spawn(move || {
            for n in signals.forever() {
                let name = usize::try_from(n - lo)
                    .ok()
                    .and_then(|k| REAL_TIME.get(k))
                    .copied()
                    .unwrap_or("a real-time signal");
                (on_signal.lock().unwrap_or_else(|e| e.into_inner()))(Asked::Named(name));
            }
        })
        .context("cannot start the real-time signals' thread")?;
    Ok(())
}
