//! What the engine tells the outside after each turn: the timeline row
//! ([`Engine::record_timeline`]) and the `/status` snapshot
//! ([`Engine::publish_status`]) with each script's and the camera's state.

use std::time::Instant;

use super::Engine;
use crate::engine::control::{ParamStatus, ScriptStatus, Status};
use crate::engine::timeline::Row;
use crate::sim::{StepReport, WorldSim};

/// What the timeline and `/status` call active bricks: the column
/// scripts' awake tiles (each a column of 8×8 voxel columns; the moat's
/// count too) plus the voxel simulation's awake bricks (regression,
/// researcher probe: a world of voxel scripts alone read 0).
pub(super) fn active_count(r: &StepReport, ws: &WorldSim) -> usize {
    // Without voxel scripts the voxel set is never stepped, so it never
    // sleeps: it holds every solid brick of the world as built.
    let voxel = if ws.vox.script_count() > 0 {
        ws.vox.active_bricks()
    } else {
        0
    };
    r.active_tiles + voxel
}

impl Engine {
    pub(super) fn record_timeline(&mut self, r: &StepReport) {
        let tick = self.ws.sim.tick();
        if !tick.is_multiple_of(self.cfg.frames_every) {
            return;
        }
        // A reload can change a script's conserved channels: a new header
        // (the old file is moved aside) rather than shifted columns.
        let columns = timeline_columns(&self.ws);
        if columns != self.timeline.extra_columns()
            && let Ok(t) = self.timeline.reopen(&columns)
        {
            self.timeline = t;
        }
        let stats = &self.renderer.stats;
        let row = Row {
            tick,
            steps_per_s: self.rate.per_s(Instant::now()),
            active_bricks: active_count(r, &self.ws),
            // The bricks this step changed: the renderer's pending set was
            // just handed over with the frame (regression, researcher
            // probe: the column read 0 in every row).
            dirty_bricks: r.bricks.len(),
            // Regression (note): the first row after a start read 0 ms.
            frame_ms: stats.last_frame_ms().unwrap_or(f64::NAN),
            bricks_streamed: stats.bricks_streamed(),
            rss_kb: crate::engine::timeline::rss_kb(),
            water: total(&self.ws, "water"),
            ground_plus_sediment: total(&self.ws, "ground") + total(&self.ws, "sediment"),
            snow: total(&self.ws, "snow"),
            drained: self.ws.drained,
            unix_s: std::time::SystemTime::now()
                .duration_since(std::time::UNIX_EPOCH)
                .map_or(f64::NAN, |d| (d.as_millis() as f64) / 1e3),
            script_ms: self.script_ms.clone(),
            conserved: (0..self.ws.script_count())
                .flat_map(|i| self.ws.conserved_totals(i).into_iter().map(|(_, v)| v))
                .collect(),
        };
        self.timeline.record(&row);
        // The viewer's charts: the same row, same columns.
        let names = ring_columns(columns);
        let mut values = row.values();
        values.resize(names.len(), f64::NAN);
        if let Ok(mut ring) = self.shared.timeline.lock() {
            ring.push(&names, values);
        }
    }

    pub(super) fn script_status(&self, i: usize) -> ScriptStatus {
        let sim = &self.ws;
        let spec = sim.spec(i);
        let (log, log_dropped, log_seq) = crate::sim::runtime::log::recent(&spec.name);
        let note = self.notes.get(i).cloned().unwrap_or_default();
        let (state, error) = match sim.suspended(i) {
            Some(e) => (
                "suspended",
                Some(format!(
                    "suspended after {} failed steps in a row (fix or reload it, or change one of its parameters): {e}",
                    sim.failures(i)
                )),
            ),
            // A streak restored by a resume has no error text of this run.
            None if sim.failures(i) > 0 => (
                "failing",
                note.step_error.or_else(|| {
                    Some(format!(
                        "{} failed steps in a row before the engine stopped",
                        sim.failures(i)
                    ))
                }),
            ),
            // Nothing awake for it for longer than two of its intervals.
            None if note.reload_error.is_none() && note.idle_steps >= 2 * sim.every(i) => {
                ("sleeping", None)
            }
            // A broken save: the last good version runs; its error is shown.
            None => ("running", note.reload_error),
        };
        ScriptStatus {
            name: spec.name.clone(),
            // A script run every N ticks runs at 1/N of the step rate
            // (long-run probe: snow, every 2 ticks, showed water's rate).
            steps_per_s: self.rate.per_s(Instant::now()) / sim.every(i) as f64,
            state: state.into(),
            error,
            failures_in_a_row: sim.failures(i),
            failed_steps: note.failed_steps,
            params: spec
                .params
                .iter()
                .zip(sim.params(i))
                .map(|(p, v)| ParamStatus {
                    name: p.name.clone(),
                    value: *v,
                    default: p.default,
                    min: p.min,
                    max: p.max,
                })
                .collect(),
            warning: match (note.warning, note.substep_cap) {
                (Some(w), Some(c)) => Some(format!("{w}; {c}")),
                (w, c) => w.or(c),
            },
            ms_per_step: self.script_ms.get(i).copied().unwrap_or(0.0),
            totals: sim.conserved_totals(i).into_iter().collect(),
            log,
            log_dropped,
            log_seq,
            reloads: note.reloads,
            reloaded_at: note.reloaded_at,
        }
    }

    /// The camera of the next frame, and who holds it, for `/status`.
    pub(super) fn camera_status(&self) -> crate::engine::control::CameraStatus {
        let holder = self
            .shared
            .camera_lease
            .lock()
            .ok()
            .and_then(|l| l.holder(Instant::now()).map(str::to_string));
        let mode = if self.camera_override.is_some() {
            "set"
        } else {
            "path"
        };
        match self.camera_at(self.ws.sim.tick()) {
            Ok(c) => crate::engine::control::CameraStatus {
                eye: c.eye.to_array(),
                target: c.target.to_array(),
                fov: c.fov_deg,
                mode: mode.into(),
                holder,
            },
            Err(_) => crate::engine::control::CameraStatus {
                mode: mode.into(),
                holder,
                ..Default::default()
            },
        }
    }

    /// Publish `/status` (one lock, everything at once).
    pub(super) fn publish_status(&mut self) {
        let scripts = (0..self.ws.script_count())
            .map(|i| self.script_status(i))
            .collect();
        let stats = &self.renderer.stats;
        let mut st = self.shared.status.lock().expect("status lock");
        *st = Status {
            tick: self.ws.sim.tick(),
            paused: self.paused,
            steps_pending: self.steps_left,
            scripts,
            active_bricks: self.active_bricks,
            dirty_queue: self.dirty_pending.len(),
            frame_ms: stats.last_frame_ms(),
            bricks_streamed: stats.bricks_streamed(),
            frames: stats.frames(),
            frames_skipped: stats.skipped(),
            snapshot_ms: self.snapshot_ms,
            last_commit: self.last_commit.clone(),
            loaded_from: self.loaded_from.clone(),
            commit_error: self.commit_error.clone(),
            render_error: self.render_error.clone(),
            materials_note: self.materials_note.clone(),
            dirty_chunks: self.dirty_chunks.len(),
            store_bytes: self.db.file_bytes(),
            sim_region: self
                .ws
                .sim
                .region()
                .map(|(a, b)| [a.x * 8, a.y * 8, b.x * 8, b.y * 8])
                .or_else(|| {
                    let (lo, hi) = self.world.bounds();
                    self.cfg.stream.map(|_| [lo.x, lo.z, hi.x, hi.z])
                }),
            region_moves: self.follow.as_ref().map(|f| (f.moves, f.move_ms)),
            window: stats.window(),
            memory_budget: self.cfg.stream.map(|s| s.memory_budget),
            rss_bytes: crate::engine::timeline::rss_kb() * 1024,
            rss_peak_bytes: crate::scene::budget::rss_peak_kb() * 1024,
            camera: self.camera_status(),
        };
    }
}

/// The columns of the viewer's timeline (and of `timeline.csv`): the
/// fixed ones, then the scripts' `extra` ones.
pub(super) fn ring_columns(extra: Vec<String>) -> Vec<String> {
    crate::engine::timeline::COLUMNS
        .iter()
        .map(|c| c.to_string())
        .chain(extra)
        .collect()
}

/// The timeline's per-script columns: each script's time, then each
/// declared conserved total.
pub(super) fn timeline_columns(ws: &WorldSim) -> Vec<String> {
    let n = ws.script_count();
    // A CSV header: no commas in a column's name.
    let clean = |s: &str| s.replace([',', '\n', '\r'], "_");
    let times = (0..n).map(|i| format!("ms:{}", clean(&ws.spec(i).name)));
    let totals = (0..n).flat_map(|i| {
        let name = clean(&ws.spec(i).name);
        ws.conserved_totals(i)
            .into_iter()
            .map(move |(ch, _)| format!("total:{name}.{}", clean(&ch)))
    });
    times.chain(totals).collect()
}

/// The world's total of column channel `name` (0 if no script declares it).
fn total(ws: &WorldSim, name: &str) -> f64 {
    ws.sim
        .channels()
        .find(name)
        .map_or(0.0, |c| ws.sim.channels().total(c))
}
