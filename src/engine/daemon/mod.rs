//! `brickworld run`: the long-running engine, a type whose loop calls named
//! stages (like a physics pipeline's `step`):
//!
//! 1. [`Engine::start`] (`start.rs`): lock the state directory, listen,
//!    write the token, open the world store, build the world (or a streamed
//!    world's simulated region), load the scripts, resume from the store or
//!    place the config's boxes, start the render thread.
//! 2. Each turn of [`Engine::run`]: [`hot_reload`](Engine::hot_reload) and
//!    [`apply_commands`](Engine::apply_commands) (`inputs.rs`),
//!    [`step`](Engine::step), [`collect_dirty`](Engine::collect_dirty),
//!    [`offer_frame`](Engine::offer_frame) (`view.rs`, with the camera),
//!    [`periodic_commit`](Engine::periodic_commit),
//!    [`record_timeline`](Engine::record_timeline) and
//!    [`publish_status`](Engine::publish_status) (`report.rs`); the step
//!    rate (`rate.rs`) and a region that follows the camera (`follow.rs`).
//!    `brickworld init` lives in `init.rs`.
//! 3. [`Engine::finish`]: a final commit, the frame in flight, then the
//!    control server (which waits for no client).
//!
//! Rendering runs on its own thread ([`super::render_thread`]): the loop
//! offers it a snapshot every `frames.every` ticks only when it is idle, and
//! otherwise skips the frame, so the simulation never waits for it. The
//! dirty brick ids between frames are coalesced in a set (bounded by the
//! world's brick count).

use std::path::PathBuf;
use std::sync::Arc;
use std::sync::atomic::Ordering;
use std::time::Instant;

use anyhow::{Context, Result, bail};
use glam::IVec3;
use rustc_hash::FxHashSet;

use super::control::{CheckpointRef, CommitRef, ControlServer, Shared};
mod follow;
mod init;
mod inputs;
mod rate;
mod report;
mod scripts;
mod start;
mod view;

pub use init::init;

pub(crate) use scripts::load_scripts;
pub(crate) use start::fixed_world;

use super::checkpoint::CameraOverride;
use super::persistence::{self, DirtyChunks};
use super::render_thread::RenderThread;
use super::state_dir::StateLock;
use super::timeline::Timeline;
use super::world_config::{CameraSettings, WorldConfig};
use crate::persist::WorldDb;
use crate::scene::SceneWorld;
use crate::sim::{ScriptSource, ScriptWatcher, SimError, StepReport, WorldSim, read_script};

/// How long a stop waits for the step in flight before interrupting its
/// scripts.
pub const STOP_GRACE: std::time::Duration = std::time::Duration::from_secs(5);
/// A second SIGINT/SIGTERM this soon after the first is the same request
/// (GNU `timeout` signals the engine and then its process group); a later
/// one exits at once, without a final checkpoint.
pub const SAME_REQUEST: std::time::Duration = std::time::Duration::from_secs(1);

/// A step that took at least this long is committed at once, whatever
/// `checkpoint.every` says: the next one may be cut by a stop, which drops
/// it, and would otherwise lose every tick since the last commit
/// (regression: 169 finished ticks of a slow world were lost).
pub const SLOW_STEP: std::time::Duration = std::time::Duration::from_secs(1);

/// Options of `brickworld run`.
#[derive(Clone, Debug)]
pub struct DaemonOptions {
    /// The world.
    pub world: WorldConfig,
    /// State directory (checkpoints, frames, token).
    pub state: PathBuf,
    /// Stop (with a commit) after this many ticks: for tests and soaks.
    pub max_ticks: Option<u64>,
    /// Stop (with a commit) once the world reaches this tick.
    pub until_tick: Option<u64>,
    /// Start paused (steps only on resume or step commands).
    pub paused: bool,
}

/// Run the engine until stopped.
pub fn run(opts: DaemonOptions) -> Result<()> {
    Engine::start(opts)?.run()
}

/// The script called `file`, from the scripts directory or the binary.
fn load_source(cfg: &WorldConfig, file: &str) -> Result<ScriptSource> {
    if cfg.scripts_embedded {
        crate::sim::embedded::script(file)
            .with_context(|| format!("no built-in script named {file}"))
    } else {
        Ok(read_script(&cfg.scripts_dir.join(file))?)
    }
}

/// `materials.lua`, from the scripts directory or the binary, if there is one.
fn materials_source(cfg: &WorldConfig) -> Result<Option<ScriptSource>> {
    if cfg.scripts_embedded {
        return Ok(crate::sim::embedded::script("materials.lua"));
    }
    // A scripts folder that cannot be read (a link loop, a file) is named
    // with its config and field (regression, odd-paths probe: "cannot read
    // loopx/materials.lua" said neither).
    crate::sim::read_optional_script(&cfg.scripts_dir.join("materials.lua"))
        .map_err(|e| anyhow::anyhow!("{}: sim.scripts_dir: {e}", cfg.file))
}

/// Per-script messages shown in `/status`.
#[derive(Clone, Debug, Default)]
struct ScriptNotes {
    /// The last step's error (cleared by a step that succeeds).
    step_error: Option<String>,
    /// The last failed reload (cleared by a successful one).
    reload_error: Option<String>,
    warning: Option<String>,
    /// Set while the script's CFL limit needs more sub-steps than a step
    /// may take (its steps may then go unstable).
    substep_cap: Option<String>,
    /// Hot reloads in this run, and the tick of the last.
    reloads: u64,
    reloaded_at: u64,
    /// Steps in a row in which the script did no work (nothing awake for
    /// it, or not its tick).
    idle_steps: u64,
    /// When the log last said that it began to fail.
    announced: Option<Instant>,
    /// Steps it failed in this run (modder probe: a script failing one
    /// step in four showed as running most of the time, with nothing to
    /// count its failures).
    failed_steps: u64,
}

/// How often the log may say that one script began to fail again.
const ANNOUNCE_EVERY: std::time::Duration = std::time::Duration::from_secs(60);

/// The script a step's error names ("" for errors of no one script).
fn error_script(e: &SimError) -> &str {
    e.step_script()
}

/// The running engine.
pub struct Engine {
    cfg: WorldConfig,
    max_ticks: Option<u64>,
    until_tick: Option<u64>,
    _lock: StateLock,
    shared: Arc<Shared>,
    server: Option<ControlServer>,
    world: SceneWorld,
    ws: WorldSim,
    renderer: RenderThread,
    db: WorldDb,
    watcher: Option<ScriptWatcher>,
    timeline: Timeline,
    camera: CameraSettings,
    /// The camera set through `/camera` (stored with each commit).
    camera_override: Option<CameraOverride>,
    /// Dirty bricks not yet handed to the renderer, each once.
    dirty_pending: FxHashSet<IVec3>,
    /// Chunks changed since the last commit.
    dirty_chunks: DirtyChunks,
    /// Whether the render thread holds its copy of the world (then frame
    /// jobs carry only deltas).
    mirror_sent: bool,
    /// The camera moved since the last frame: a view is rendered as soon
    /// as the renderer is idle, paused or between frame ticks.
    view_due: bool,
    paused: bool,
    steps_left: u64,
    notes: Vec<ScriptNotes>,
    last_commit: Option<CommitRef>,
    loaded_from: Option<CheckpointRef>,
    commit_error: Option<String>,
    /// Why the render thread stopped, if it did (`/status`).
    render_error: Option<String>,
    /// What the last change to `materials.lua` on disk did (applied live,
    /// or refused).
    materials_note: Option<String>,
    snapshot_ms: f64,
    active_bricks: usize,
    rate: rate::StepRate,
    start_tick: u64,
    /// Milliseconds each script took in the last step (script id order).
    script_ms: Vec<f64>,
    /// A streamed world's region that follows the camera.
    follow: Option<follow::Follow>,
    /// The stop interrupted a step: no final commit.
    step_cut: bool,
    /// Something ran or changed since the world was loaded (a step, a
    /// command, a reload): without it, the stop commits nothing.
    changed_since_load: bool,
}

impl Engine {
    /// The loop: stages in order until stopped, then [`finish`](Self::finish).
    pub fn run(mut self) -> Result<()> {
        // `--until-tick` at or below the restored tick stops before the
        // first step (regression: one tick ran before the check); the
        // start said so.
        loop {
            if self.shared.shutdown.load(Ordering::Relaxed) || self.reached_stop() {
                break;
            }
            // The last tick a stored state may claim: stepping on would
            // commit a world the next start refuses (regression, fuzzing:
            // a backup at 2^53 ran on and could not be resumed).
            if self.ws.sim.tick() >= crate::engine::checkpoint::MAX_TICK {
                crate::say!(
                    "warning: the world is at tick {}, 2^53, past which simulated time is no longer exact: it steps no further",
                    self.ws.sim.tick()
                );
                break;
            }
            self.hot_reload();
            if self.apply_commands() {
                self.changed_since_load = true;
                // What the commands changed shows at once, not after the
                // next step (regression: a step of 40 s kept a paused
                // engine showing as running).
                self.publish_status();
            }
            // A stop that came during the reload or the commands: the step
            // would start already interrupted and be dropped, with its
            // final commit (regression).
            if self.shared.shutdown.load(Ordering::Relaxed) {
                break;
            }
            if self.should_step() && self.follow_camera() {
                self.changed_since_load = true;
                let started = Instant::now();
                let report = self.step();
                if crate::sim::interrupt::stopping() {
                    // The step may have been cut half-way: it is neither
                    // shown nor committed.
                    self.step_cut = true;
                    break;
                }
                self.collect_dirty(&report);
                self.offer_frame();
                self.offer_view();
                self.periodic_commit(started.elapsed());
                self.record_timeline(&report);
            } else {
                self.offer_view();
                std::thread::sleep(std::time::Duration::from_millis(5));
            }
            self.publish_status();
            if self.reached_stop() {
                break;
            }
        }
        self.finish()
    }

    /// Whether `--ticks` or `--until-tick` says to stop now.
    fn reached_stop(&self) -> bool {
        let tick = self.ws.sim.tick();
        self.max_ticks
            .is_some_and(|m| tick.saturating_sub(self.start_tick) >= m)
            || self.until_tick.is_some_and(|t| tick >= t)
    }

    fn should_step(&self) -> bool {
        !self.paused || self.steps_left > 0
    }

    /// One tick of every script (CFL sub-stepped), with errors noted per script.
    fn step(&mut self) -> StepReport {
        if self.paused {
            self.steps_left -= 1;
        }
        let region = self.sim_region();
        self.ws.sim.set_region(region);
        let before: Vec<(u32, bool)> = (0..self.ws.script_count())
            .map(|i| (self.ws.failures(i), self.ws.suspended(i).is_some()))
            .collect();
        let (r, substeps) = self.ws.step_within_cfl(&mut self.world, self.cfg.dt, 0.5);
        self.note_substep_cap(substeps);
        self.announce_failures(&before, &r);
        for (i, n) in self.notes.iter_mut().enumerate() {
            if self.ws.failures(i) == 0 && self.ws.suspended(i).is_none() {
                n.step_error = None;
            }
        }
        let mut failed = vec![false; self.notes.len()];
        for e in &r.errors {
            if let Some(i) = self.ws.script_index(error_script(e)) {
                self.notes[i].step_error = Some(e.to_string());
                failed[i] = true;
            }
        }
        for (n, f) in self.notes.iter_mut().zip(failed) {
            n.failed_steps += f as u64;
        }
        self.rate.step(Instant::now());
        self.active_bricks = report::active_count(&r, &self.ws);
        // A script's time in its last run: a script run every N ticks
        // keeps it between its runs (regression, researcher probe: one run
        // every 2 ticks showed 0 ms in every timeline row, which fall on
        // even ticks, where it does not run).
        let ran_at = self.ws.sim.tick().saturating_sub(1);
        let n = self.ws.script_count();
        self.script_ms.resize(n, 0.0);
        for i in 0..n {
            if ran_at.is_multiple_of(self.ws.every(i)) {
                self.script_ms[i] = self.ws.script_ms(&r, i);
            }
        }
        for (i, n) in self.notes.iter_mut().enumerate() {
            n.idle_steps = if self.ws.did_work(&r, i) {
                0
            } else {
                n.idle_steps + 1
            };
        }
        for (script, line) in crate::sim::runtime::log::take_unprinted() {
            crate::say!("[{script}] {line}");
        }
        r
    }

    /// When a step needed the most sub-steps there are, say so for every
    /// script with a CFL limit, in `/status` and once on stderr: its steps
    /// may go unstable, and the failure that follows names only a channel
    /// out of bounds (regression, hostile probe: water.lua at its declared
    /// least `dx` was suspended with no word of the cause).
    fn note_substep_cap(&mut self, substeps: u32) {
        use crate::sim::columns::run::MAX_SUBSTEPS;
        for (i, note) in self.notes.iter_mut().enumerate() {
            let spec = self.ws.spec(i);
            let Some(cfl) = spec.cfl.as_ref().filter(|_| substeps >= MAX_SUBSTEPS) else {
                note.substep_cap = None;
                continue;
            };
            if note.substep_cap.is_none() {
                let msg = format!(
                    "its CFL limit needs all the {MAX_SUBSTEPS} sub-steps a step may take, or more, so its steps may go unstable: lower sim.dt, or raise '{}' or lower '{}'",
                    cfl.dx, cfl.gravity
                );
                crate::say!("warning: {}.lua: {msg}", spec.name);
                note.substep_cap = Some(msg);
            }
        }
    }

    /// Say on stderr when a script begins to fail (at most once a minute per
    /// script, however it alternates) and when failures suspend it: a
    /// headless run has no viewer to show it. `before` is each script's
    /// (failures in a row, suspended) before the step.
    fn announce_failures(&mut self, before: &[(u32, bool)], r: &StepReport) {
        for (i, &(failed, suspended)) in before.iter().enumerate() {
            let name = &self.ws.spec(i).name;
            let now_suspended = self.ws.suspended(i).is_some();
            if suspended {
                continue;
            }
            // Should a streak begin and suspend the script in one step
            // (no rule does that today: a tick's CFL sub-steps count one
            // failure), the beginning is said first (regression, docs walk:
            // only the suspension was said).
            let began = failed == 0 && (self.ws.failures(i) > 0 || now_suspended);
            let quiet = self.notes[i]
                .announced
                .is_none_or(|t| t.elapsed() >= ANNOUNCE_EVERY);
            if began
                && quiet
                && let Some(e) = r.errors.iter().find(|e| error_script(e) == name)
            {
                crate::say!("warning: {name}.lua failed a step: {e}");
                self.notes[i].announced = Some(Instant::now());
            }
            if let Some(e) = self.ws.suspended(i) {
                crate::say!(
                    "warning: {name}.lua is suspended after {} failed steps in a row (fix or reload it, or change one of its parameters): {e}",
                    self.ws.failures(i)
                );
            }
        }
    }

    /// The step's changed bricks, in one hop each into the renderer's
    /// pending set and the store's dirty chunks.
    fn collect_dirty(&mut self, report: &StepReport) {
        self.dirty_chunks.bricks(&report.bricks);
        self.dirty_pending.extend(report.bricks.iter().copied());
    }

    fn periodic_commit(&mut self, step_took: std::time::Duration) {
        if self.ws.sim.tick().is_multiple_of(self.cfg.checkpoint_every) || step_took >= SLOW_STEP {
            self.commit();
        }
    }

    /// Commit the dirty chunks and the simulation state in one transaction;
    /// a failure (a full disk) is reported and retried at the next commit,
    /// and loses nothing committed before.
    fn commit(&mut self) {
        let start = Instant::now();
        match persistence::commit(
            &mut self.db,
            &mut self.dirty_chunks,
            &self.world,
            &mut self.ws,
            self.camera_override,
        ) {
            Ok(st) => {
                if self.commit_error.is_some() {
                    crate::say!("committing again: nothing was lost");
                }
                self.last_commit = Some(CommitRef {
                    tick: self.ws.sim.tick(),
                    chunks: st.chunks,
                    columns: st.columns,
                    bytes: st.bytes,
                    ms: start.elapsed().as_secs_f64() * 1e3,
                });
                self.commit_error = None;
            }
            Err(e) => {
                // Once per distinct failure (a full disk fails every
                // interval); `/status` always shows the current one.
                let msg = e.to_string();
                if self.commit_error.as_deref() != Some(msg.as_str()) {
                    crate::say!("warning: {msg}; retrying at every commit");
                }
                self.commit_error = Some(msg);
            }
        }
    }

    /// Stop: the commands queued before the stop, a final commit, the
    /// frame in flight, then the server.
    fn finish(mut self) -> Result<()> {
        // Commands arriving from now on are refused (503); those already
        // queued were answered 200 and are applied, so a camera set just
        // before the stop is committed with the world (regression,
        // concurrency probe: it was dropped, and the restart showed the
        // camera as it was before). The flag is set before the queue is
        // taken, under its lock (see routes.rs).
        self.shared.shutdown.store(true, Ordering::Release);
        if self.step_cut {
            // Half a step is not committed: its commands go unapplied,
            // and those waiting for a verdict are told so.
            self.shared.commands.lock().expect("command lock").clear();
        } else if self.apply_commands() {
            self.changed_since_load = true;
        }
        if self.step_cut {
            crate::say!(
                "a step was still running {} s after the stop request: its scripts were interrupted and the step is dropped; the world stays as last committed",
                STOP_GRACE.as_secs()
            );
        } else if self.changed_since_load {
            self.commit();
        } else {
            // Nothing ran and nothing changed: the store keeps exactly what
            // it held. A commit would store the world as this start loaded
            // it, which a changed config may load otherwise (regression,
            // researcher probe: a start without `[stream]`, stopped before
            // any tick, changed a streamed world's later history).
            crate::say!(
                "nothing ran or changed since the world was loaded: the store is left as it was"
            );
        }
        self.renderer.finish(std::time::Duration::from_secs(3));
        self.shared.shutdown.store(true, Ordering::Relaxed);
        if let Some(s) = self.server.take() {
            s.stop();
        }
        if let Some(e) = &self.commit_error {
            bail!("the final {e}");
        }
        if self.step_cut {
            // The state in memory is half a step: no hash of it is shown.
            match &self.last_commit {
                Some(c) => println!("stopped; the world store holds tick {}", c.tick),
                None => println!(
                    "stopped; nothing was committed in this run (the world store holds what it held)"
                ),
            }
            return Ok(());
        }
        let hash = persistence::engine_hash(&self.world, &self.ws);
        println!(
            "stopped at tick {} (world hash {hash:#018x})",
            self.ws.sim.tick()
        );
        Ok(())
    }
}
