//! `brickworld run`: the long-running engine.
//!
//! Start-up resumes from the newest checkpoint in the state directory that
//! verifies (reporting any corrupt newer one), or builds the world from its
//! config. The engine loop then steps the scripts, hands each step's dirty
//! bricks to the renderer, renders a frame every `frames.every` ticks
//! (GPU with streaming, or CPU), writes checkpoints periodically, on request
//! and on SIGINT/SIGTERM, and obeys the control server's commands at step
//! boundaries.
//!
//! Rendering runs on its own thread ([`super::render_thread`]): the loop
//! offers it a snapshot every `frames.every` ticks only when it is idle, and
//! otherwise skips the frame, so the simulation never waits for it. The
//! dirty brick ids between frames are coalesced in a set (bounded by the
//! world's brick count).

use std::path::{Path, PathBuf};
use std::sync::atomic::Ordering;
use std::sync::{Arc, Mutex};
use std::time::Instant;

use anyhow::{Context, Result, bail};
use glam::{DVec3, IVec3};
use rustc_hash::FxHashSet;

use super::checkpoint::{self, WorldRef};
use super::control::{self, CheckpointRef, Command, ScriptStatus, Shared, Status};
use super::render_thread::{FrameJob, RenderSettings, RenderThread};
use super::world_config::{CameraMode, WorldConfig};
use crate::progress::bar;
use crate::scene::{SceneWorld, build_scene};
use crate::sim::{Limits, WorldSim, read_script};
use crate::trace::Camera;

/// Options of `brickworld run`.
#[derive(Clone, Debug)]
pub struct DaemonOptions {
    /// The world.
    pub world: WorldConfig,
    /// State directory (checkpoints, frames, token).
    pub state: PathBuf,
    /// Stop (with a checkpoint) after this many ticks: for tests and soaks.
    pub max_ticks: Option<u64>,
}

fn token() -> String {
    let mut bytes = [0u8; 16];
    if let Ok(mut f) = std::fs::File::open("/dev/urandom") {
        use std::io::Read;
        let _ = f.read_exact(&mut bytes);
    }
    let salt = Instant::now().elapsed().as_nanos() as u64 ^ std::process::id() as u64;
    bytes
        .iter()
        .enumerate()
        .map(|(i, b)| format!("{:02x}", b ^ (salt >> ((i % 8) * 8)) as u8))
        .collect()
}

fn write_token(state: &Path, token: &str) -> Result<PathBuf> {
    let path = state.join("control.token");
    std::fs::write(&path, token).with_context(|| format!("cannot write {}", path.display()))?;
    #[cfg(unix)]
    {
        use std::os::unix::fs::PermissionsExt;
        std::fs::set_permissions(&path, std::fs::Permissions::from_mode(0o600))
            .with_context(|| format!("cannot restrict {}", path.display()))?;
    }
    Ok(path)
}

fn total(ws: &WorldSim, name: &str) -> f64 {
    ws.sim
        .channels()
        .find(name)
        .map_or(0.0, |c| ws.sim.channels().total(c))
}

/// Run the engine until stopped.
pub fn run(opts: DaemonOptions) -> Result<()> {
    let cfg = &opts.world;
    std::fs::create_dir_all(&opts.state)
        .with_context(|| format!("cannot create the state directory {}", opts.state.display()))?;
    let token = token();
    let shared = Arc::new(Shared {
        status: Mutex::new(Status::default()),
        commands: Mutex::new(Vec::new()),
        frame: Mutex::new(None),
        token: token.clone(),
        shutdown: Default::default(),
    });
    // Listen first: a taken port is a clear error before any work.
    let (server, bound) = control::start(cfg.addr, shared.clone()).map_err(anyhow::Error::msg)?;
    let token_path = write_token(&opts.state, &token)?;
    {
        let s = shared.clone();
        ctrlc::set_handler(move || s.shutdown.store(true, Ordering::Relaxed))
            .context("cannot install the SIGINT/SIGTERM handler")?;
    }
    // Resume or build.
    let latest = checkpoint::latest(&opts.state)?;
    for e in &latest.skipped {
        eprintln!("warning: {e}; trying the previous checkpoint");
    }
    let (mut world, resumed) = match latest.found {
        Some((path, st)) => {
            eprintln!("resuming from {} (tick {})", path.display(), st.tick);
            let w = SceneWorld::new(st.store, st.bounds.0, st.bounds.1)?;
            (w, Some((st.tick, st.channels, st.params)))
        }
        None => {
            let pb = bar("scene", 0);
            let w = build_scene(&cfg.source, cfg.size, cfg.seed, &pb)
                .context("cannot build the world")?;
            pb.finish_and_clear();
            (w, None)
        }
    };
    let mut ws = WorldSim::with_edges(&mut world, true);
    for (i, s) in cfg.scripts.iter().enumerate() {
        let src = read_script(&cfg.scripts_dir.join(&s.file))?;
        ws.add_lua(src, Limits::default())
            .with_context(|| format!("cannot load script {}", s.file))?;
        ws.sim.set_every(i, s.every);
        for (k, v) in &s.params {
            ws.sim
                .set_param(i, k, *v)
                .with_context(|| format!("in the world config's scripts[{i}].params"))?;
        }
    }
    let mut loaded_from = None;
    if let Some((tick, channels, params)) = resumed {
        *ws.sim.channels_mut() = channels;
        ws.sim.set_tick(tick);
        ws.sim.wake_all();
        for (script, values) in params {
            if let Some(i) = ws.sim.script_index(&script) {
                for (k, v) in values {
                    let _ = ws.sim.set_param(i, &k, v);
                }
            }
        }
        let hash = checkpoint::world_hash(&world.store, ws.sim.channels());
        loaded_from = Some(CheckpointRef {
            tick,
            hash: format!("{hash:#018x}"),
        });
    }
    // Publish the loaded world in one go: a client that sees the scripts
    // also sees the tick and where it was resumed from (regression: a restart
    // test read `loaded_from: null` in between).
    {
        let mut st = shared.status.lock().expect("status lock");
        st.tick = ws.sim.tick();
        st.loaded_from = loaded_from.clone();
        st.scripts = (0..ws.sim.script_count())
            .map(|i| ScriptStatus {
                name: ws.sim.spec(i).name.clone(),
                ..Default::default()
            })
            .collect();
    }
    let frames_dir = opts.state.join(&cfg.frames_dir);
    std::fs::create_dir_all(&frames_dir)
        .with_context(|| format!("cannot create {}", frames_dir.display()))?;
    let renderer = RenderThread::spawn(
        RenderSettings {
            gpu: cfg.gpu,
            shadows: cfg.shadows,
            frames_dir,
        },
        shared.clone(),
    )
    .context("cannot start the render thread")?;
    // Dirty bricks not yet handed to the renderer, each once.
    let mut dirty_pending: FxHashSet<IVec3> = FxHashSet::default();
    let mut snapshot_ms = 0.0;
    let mut active_bricks = 0;
    println!(
        "brickworld is running: viewer http://{bound}/  (control token in {}: {token})",
        token_path.display()
    );
    let mut camera = cfg.camera;
    let (mut paused, mut steps_left) = (false, 0u64);
    let mut last_checkpoint = None;
    let mut checkpoint_error = None;
    let mut rate_window = (Instant::now(), 0u64);
    let mut steps_per_s = 0.0;
    let start_tick = ws.sim.tick();
    let write_checkpoint = |ws: &WorldSim, world: &SceneWorld| -> Result<CheckpointRef, String> {
        let params: Vec<(String, Vec<(String, f64)>)> = (0..ws.sim.script_count())
            .map(|i| {
                let spec = ws.sim.spec(i);
                (
                    spec.name.clone(),
                    spec.params
                        .iter()
                        .zip(ws.sim.params(i))
                        .map(|(p, v)| (p.name.clone(), *v))
                        .collect(),
                )
            })
            .collect();
        let r = WorldRef {
            tick: ws.sim.tick(),
            store: &world.store,
            bounds: world.bounds,
            channels: ws.sim.channels(),
            params: &params,
        };
        checkpoint::write_ref(&opts.state, r)
            .map(|(_, hash)| CheckpointRef {
                tick: ws.sim.tick(),
                hash: format!("{hash:#018x}"),
            })
            .map_err(|e| e.to_string())
    };
    let mut last_errors: Vec<Option<String>> = vec![None; ws.sim.script_count()];
    // Hot reload: the scripts directory is watched; a changed script is
    // compiled and smoke-tested in a fresh VM and swapped in here, between
    // steps; a broken one keeps the last good version running.
    let mut watcher = match crate::sim::ScriptWatcher::new(
        &cfg.scripts_dir,
        std::time::Duration::from_millis(150),
    ) {
        Ok(w) => Some(w),
        Err(e) => {
            eprintln!("warning: hot reload is off: {e}");
            None
        }
    };
    let timeline_path = opts.state.join("timeline.csv");
    let mut timeline = super::timeline::Timeline::open(&timeline_path)?;
    loop {
        if shared.shutdown.load(Ordering::Relaxed) {
            break;
        }
        if let Some(w) = watcher.as_mut() {
            for path in w.poll() {
                let name = path
                    .file_stem()
                    .map(|s| s.to_string_lossy().to_string())
                    .unwrap_or_default();
                let index = ws.sim.script_index(&name);
                match ws.reload(&path) {
                    Ok(Some(i)) => {
                        eprintln!("reloaded {}", path.display());
                        last_errors[i] = None;
                    }
                    Ok(None) => {}
                    Err(e) => {
                        eprintln!("warning: kept the last good version: {e}");
                        if let Some(i) = index {
                            last_errors[i] = Some(e.to_string());
                        }
                    }
                }
            }
        }
        let commands: Vec<Command> =
            std::mem::take(&mut *shared.commands.lock().expect("command lock"));
        for c in commands {
            match c {
                Command::Pause => paused = true,
                Command::Resume => paused = false,
                Command::Step(n) => steps_left += n,
                Command::Checkpoint => match write_checkpoint(&ws, &world) {
                    Ok(r) => last_checkpoint = Some(r),
                    Err(e) => checkpoint_error = Some(e),
                },
                Command::Camera { eye, target, fov } => {
                    camera.mode = CameraMode::Fixed;
                    camera.eye = Some(DVec3::from(eye));
                    camera.target = Some(DVec3::from(target));
                    camera.fov = fov;
                }
                Command::Params { script, values } => {
                    let Some(i) = ws.sim.script_index(&script) else {
                        last_errors.push(Some(format!("no script named '{script}'")));
                        continue;
                    };
                    for (k, v) in values {
                        if let Err(e) = ws.sim.set_param(i, &k, v) {
                            last_errors[i] = Some(e.to_string());
                        }
                    }
                }
            }
        }
        let run_step = !paused || steps_left > 0;
        if run_step {
            if paused {
                steps_left -= 1;
            }
            let (r, _) = ws.step_within_cfl(&mut world, cfg.dt, 0.5);
            for e in &r.errors {
                let name = match e {
                    crate::sim::SimError::Runtime { script, .. }
                    | crate::sim::SimError::Unstable { script, .. } => script.clone(),
                    _ => String::new(),
                };
                if let Some(i) = ws.sim.script_index(&name) {
                    last_errors[i] = Some(e.to_string());
                }
            }
            rate_window.1 += 1;
            if rate_window.0.elapsed().as_secs_f64() >= 1.0 {
                steps_per_s = rate_window.1 as f64 / rate_window.0.elapsed().as_secs_f64();
                rate_window = (Instant::now(), 0);
            }
            let mut dirty = 0;
            for batch in ws.dirty.try_iter() {
                dirty += batch.bricks.len();
                dirty_pending.extend(batch.bricks);
            }
            let tick = ws.sim.tick();
            if tick.is_multiple_of(cfg.frames_every) {
                if renderer.ready() {
                    let views = world.default_views();
                    let (mut eye, target) = match (camera.eye, camera.target) {
                        (Some(e), Some(t)) => (e, t),
                        _ => (DVec3::from(views[1].eye), DVec3::from(views[1].target)),
                    };
                    let mut target = target;
                    let phase = |period_s: f64| tick as f64 * cfg.dt / period_s;
                    match camera.mode {
                        CameraMode::Fixed => {}
                        CameraMode::Orbit { period_s } => {
                            let angle = phase(period_s) * std::f64::consts::TAU;
                            let d = eye - target;
                            let (s, c) = angle.sin_cos();
                            eye = target + DVec3::new(d.x * c - d.z * s, d.y, d.x * s + d.z * c);
                        }
                        CameraMode::Fly { to, period_s } => {
                            // 0 → 1 → 0 over one period.
                            let f = 1.0 - (phase(period_s).fract() * 2.0 - 1.0).abs();
                            let step = (to - eye) * f;
                            eye += step;
                            target += step;
                        }
                    }
                    if let Ok(cam) = Camera::new(eye, target, camera.fov, cfg.width, cfg.height) {
                        let copy = Instant::now();
                        let snapshot = world.clone();
                        snapshot_ms = copy.elapsed().as_secs_f64() * 1e3;
                        let job = FrameJob {
                            tick,
                            world: snapshot,
                            dirty: dirty_pending.drain().collect(),
                            camera: cam,
                        };
                        if let Err(back) = renderer.offer(job) {
                            dirty_pending.extend(back);
                        }
                    }
                } else {
                    renderer.skip();
                }
            }
            if tick.is_multiple_of(cfg.checkpoint_every) {
                match write_checkpoint(&ws, &world) {
                    Ok(r) => {
                        last_checkpoint = Some(r);
                        checkpoint_error = None;
                    }
                    Err(e) => {
                        eprintln!("warning: checkpoint failed, the last good one is kept: {e}");
                        checkpoint_error = Some(e);
                    }
                }
            }
            if tick.is_multiple_of(cfg.frames_every) {
                timeline.record(&super::timeline::Row {
                    tick,
                    steps_per_s,
                    active_bricks: r.active_tiles,
                    dirty_bricks: dirty,
                    frame_ms: renderer.stats.frame_ms(),
                    bricks_streamed: renderer.stats.bricks_streamed(),
                    rss_kb: super::timeline::rss_kb(),
                    water: total(&ws, "water"),
                    ground_plus_sediment: total(&ws, "ground") + total(&ws, "sediment"),
                    snow: total(&ws, "snow"),
                    drained: ws.drained,
                });
            }
            active_bricks = r.active_tiles;
        } else {
            std::thread::sleep(std::time::Duration::from_millis(5));
        }
        {
            let mut st = shared.status.lock().expect("status lock");
            st.tick = ws.sim.tick();
            st.paused = paused;
            st.active_bricks = active_bricks;
            st.dirty_queue = dirty_pending.len();
            st.frame_ms = renderer.stats.frame_ms();
            st.bricks_streamed = renderer.stats.bricks_streamed();
            st.frames = renderer.stats.frames();
            st.frames_skipped = renderer.stats.skipped();
            st.snapshot_ms = snapshot_ms;
            st.last_checkpoint = last_checkpoint.clone();
            st.loaded_from = loaded_from.clone();
            st.checkpoint_error = checkpoint_error.clone();
            st.scripts = (0..ws.sim.script_count())
                .map(|i| ScriptStatus {
                    name: ws.sim.spec(i).name.clone(),
                    steps_per_s,
                    error: last_errors.get(i).cloned().flatten(),
                })
                .collect();
        }
        if opts
            .max_ticks
            .is_some_and(|m| ws.sim.tick() - start_tick >= m)
        {
            break;
        }
    }
    // Stop: finish the frame in flight, a final checkpoint, then the server.
    renderer.finish();
    let result = write_checkpoint(&ws, &world);
    shared.shutdown.store(true, Ordering::Relaxed);
    let _ = server.join();
    match result {
        Ok(r) => {
            println!("stopped at tick {} (checkpoint {})", r.tick, r.hash);
            Ok(())
        }
        Err(e) => bail!("the final checkpoint failed (the previous one is kept): {e}"),
    }
}
