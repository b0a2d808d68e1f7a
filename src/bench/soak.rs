//! `brickworld soak`: run the real daemon for M minutes and watch it: resident
//! memory over time (it must stay flat), queue lengths (bounded), `/status`
//! latency, ticks per second, frame time, and the drift of conserved totals.

use std::path::Path;
use std::process::{Command, Stdio};
use std::time::{Duration, Instant};

use anyhow::{Context, Result, bail};
use serde::Serialize;

use crate::engine::ctl::request;

/// The soak report.
#[derive(Debug, Serialize)]
pub struct SoakReport {
    /// Minutes run.
    pub minutes: f64,
    /// (seconds, resident KiB) samples.
    pub rss_kb: Vec<(f64, u64)>,
    /// Resident memory growth from the end of warm-up (first fifth) to the end, percent.
    /// Two single samples: sensitive to the per-frame snapshot's sawtooth.
    pub rss_growth_after_warmup_pct: f64,
    /// Growth of the peak resident memory, second fifth of the run against the last fifth, percent.
    pub rss_peak_growth_pct: f64,
    /// Growth of the median resident memory, second fifth against the last fifth, percent.
    pub rss_median_growth_pct: f64,
    /// Largest dirty-brick queue seen.
    pub max_dirty_queue: u64,
    /// `/status` latency percentiles, milliseconds.
    pub status_ms_p50: f64,
    /// 99th percentile.
    pub status_ms_p99: f64,
    /// Worst.
    pub status_ms_max: f64,
    /// Ticks per second over the run.
    pub ticks_per_s: f64,
    /// Mean frame time from the timeline.
    pub frame_ms_mean: f64,
    /// Relative drift of ground + sediment (conserved exactly) over the run.
    pub ground_plus_sediment_drift: f64,
    /// Relative drift of each channel a script declares conserved (the
    /// timeline's `total:SCRIPT.CHANNEL` columns) over the run: a world of
    /// voxel scripts has no column ground, so ground + sediment alone said
    /// nothing of it (researcher probe).
    pub conserved_drift: Vec<(String, f64)>,
    /// Ticks run.
    pub ticks: u64,
    /// Frames the render thread drew.
    pub frames: u64,
    /// Frames skipped because the renderer was busy (the simulation went on).
    pub frames_skipped: u64,
    /// Seconds from starting the daemon to its first frame.
    pub first_frame_s: f64,
    /// Largest resident memory seen, KiB.
    pub rss_max_kb: u64,
    /// The engine's per-frame snapshot time, milliseconds: median and worst.
    pub snapshot_ms_p50: f64,
    /// Worst.
    pub snapshot_ms_max: f64,
    /// The slowest commit seen (ms) and its chunk count.
    pub commit_ms_max: f64,
    /// Chunks in that commit.
    pub commit_chunks: u64,
    /// A streamed world's memory budget, bytes (null otherwise).
    pub memory_budget: Option<u64>,
    /// A streamed world's render window at the end (null otherwise).
    pub window: Option<serde_json::Value>,
}

/// The engine a soak watches, stopped with SIGTERM (a final commit) when
/// the soak ends early: an error or an interrupt left it running for good,
/// with nobody to stop it (regression, stop-path probe).
struct Engine(std::process::Child);

impl Drop for Engine {
    fn drop(&mut self) {
        if matches!(self.0.try_wait(), Ok(None)) {
            stop_engine(self.0.id());
            let _ = self.0.wait();
        }
    }
}

/// Ask the engine `pid` to stop (SIGTERM: it commits and exits), and wait
/// up to a minute for it to be gone (or a zombie, its parent's to reap).
fn stop_engine(pid: u32) {
    let _ = Command::new("kill")
        .arg("-TERM")
        .arg(pid.to_string())
        .stdout(Stdio::null())
        .stderr(Stdio::null())
        .status();
    let t = Instant::now();
    while t.elapsed() < Duration::from_secs(60) {
        let gone = std::fs::read_to_string(format!("/proc/{pid}/stat")).map_or(true, |s| {
            s.rsplit(')')
                .next()
                .is_some_and(|r| r.trim_start().starts_with('Z'))
        });
        if gone {
            return;
        }
        std::thread::sleep(Duration::from_millis(50));
    }
}

/// Where a soak stands, for its interrupt (second review: one flag said
/// "before its engine ran" while the soak stopped it at its end, and
/// "no report" after the report was written).
#[derive(Clone, Copy)]
enum Phase {
    /// No engine yet.
    Starting,
    /// The engine (this process id) runs.
    Running(u32),
    /// The minutes are up: the soak stops its engine, then reports.
    Ending,
    /// The report is written.
    Reported,
}

static PHASE: std::sync::Mutex<Phase> = std::sync::Mutex::new(Phase::Starting);

fn phase() -> std::sync::MutexGuard<'static, Phase> {
    PHASE.lock().unwrap_or_else(|e| e.into_inner())
}

/// The soak's report is written: an interrupt now says so.
pub fn reported() {
    *phase() = Phase::Reported;
}

/// Ctrl-C or SIGTERM stops the soak's engine (with its final commit, once
/// it has taken its signals), says what is left, and exits with status 130.
fn stop_engine_on_interrupt(state: &Path) -> Result<()> {
    let state = state.display().to_string();
    ctrlc::set_handler(move || {
        // Held to the exit: the soak cannot move on meanwhile.
        let phase = phase();
        match *phase {
            Phase::Starting => {
                crate::say!("interrupted before the soak's engine ran; no report was written")
            }
            Phase::Running(pid) => {
                stop_engine(pid);
                crate::say!(
                    "interrupted: the soak's engine was stopped (its state is in {state}); no report was written"
                );
            }
            Phase::Ending => crate::say!(
                "interrupted as the soak ended: its engine is stopping with a final commit (its state is in {state}); no report was written"
            ),
            Phase::Reported => crate::say!("interrupted after the soak's report was written"),
        }
        std::process::exit(130);
    })
    .context("cannot install the interrupt handler")
}

/// Run the soak.
pub fn run(
    world: Option<&Path>,
    minutes: f64,
    state: &Path,
    progress: &indicatif::ProgressBar,
) -> Result<SoakReport> {
    let port = std::net::TcpListener::bind("127.0.0.1:0")?
        .local_addr()?
        .port();
    let addr = format!("127.0.0.1:{port}");
    // Kept afterwards, to look at (the next soak empties it).
    crate::files::fresh_scratch_dir(state)
        .map_err(|e| anyhow::anyhow!("invalid --state: {e}"))?
        .keep();
    stop_engine_on_interrupt(state)?;
    let exe = std::env::current_exe().context("cannot find the brickworld executable")?;
    let mut cmd = Command::new(exe);
    cmd.arg("run");
    if let Some(w) = world {
        cmd.arg(w);
    }
    // Started and recorded as one: an interrupt waits for both.
    let mut child = {
        let mut now = phase();
        let child = Engine(
            cmd.arg("--state")
                .arg(state)
                .arg("--addr")
                .arg(&addr)
                .stdout(Stdio::null())
                .stderr(Stdio::null())
                .spawn()
                .context("cannot start the daemon")?,
        );
        *now = Phase::Running(child.0.id());
        child
    };
    let start = Instant::now();
    let mut first_frame_s = f64::NAN;
    while request(&addr, "GET", "/status", None, "").is_err() {
        if start.elapsed() > Duration::from_secs(120) {
            let _ = child.0.kill();
            bail!("the daemon did not start within two minutes");
        }
        std::thread::sleep(Duration::from_millis(100));
    }
    let total = Duration::from_secs_f64(minutes * 60.0);
    progress.set_length(total.as_secs());
    let t0 = Instant::now();
    let (mut rss, mut lat, mut max_q, mut first_tick, mut last_tick) =
        (Vec::new(), Vec::new(), 0u64, None, 0u64);
    let mut frames = (0u64, 0u64);
    let mut snaps = Vec::new();
    let (mut commit_ms_max, mut commit_chunks) = (0f64, 0u64);
    let (mut memory_budget, mut last_window) = (None, None);
    while t0.elapsed() < total {
        let t = Instant::now();
        let r = request(&addr, "GET", "/status", None, "");
        lat.push(t.elapsed().as_secs_f64() * 1e3);
        if let Ok((200, body)) = r
            && let Ok(s) = serde_json::from_str::<serde_json::Value>(&body)
        {
            let tick = s["tick"].as_u64().unwrap_or(0);
            first_tick.get_or_insert(tick);
            last_tick = tick;
            max_q = max_q.max(s["dirty_queue"].as_u64().unwrap_or(0));
            frames = (
                s["frames"].as_u64().unwrap_or(0),
                s["frames_skipped"].as_u64().unwrap_or(0),
            );
            if frames.0 > 0 && first_frame_s.is_nan() {
                first_frame_s = start.elapsed().as_secs_f64();
            }
            if frames.0 > 0 {
                snaps.push(s["snapshot_ms"].as_f64().unwrap_or(0.0));
            }
            let c = &s["last_commit"];
            if c["ms"].as_f64().unwrap_or(0.0) > commit_ms_max {
                commit_ms_max = c["ms"].as_f64().unwrap_or(0.0);
                commit_chunks = c["chunks"].as_u64().unwrap_or(0);
            }
            memory_budget = s["memory_budget"].as_u64();
            last_window = Some(s["window"].clone()).filter(|w| !w.is_null());
        }
        // One memory sample a second (the fifths compare equal spans).
        let now = t0.elapsed().as_secs_f64();
        if rss.last().is_none_or(|r: &(f64, u64)| now - r.0 >= 0.999) {
            rss.push((now, crate::engine::timeline::rss_kb_of(child.0.id())));
        }
        if let Some(status) = child.0.try_wait()? {
            // An interrupt that stopped it holds the phase to its exit:
            // wait for it rather than report the stop as a failure (a
            // race seen once: exit 1 instead of 130).
            let _interrupt_first = phase();
            bail!("the daemon exited early ({status})");
        }
        progress.set_position(t0.elapsed().as_secs());
        // Sample finely until the first frame, to time it; then each second.
        let period = if first_frame_s.is_nan() { 50 } else { 1000 };
        std::thread::sleep(Duration::from_millis(period).saturating_sub(t.elapsed()));
    }
    let secs = t0.elapsed().as_secs_f64();
    // From here the soak stops its engine itself.
    *phase() = Phase::Ending;
    drop(child);
    lat.sort_by(|a, b| a.total_cmp(b));
    let pct = |p: f64| {
        lat.get(((lat.len() as f64 - 1.0) * p) as usize)
            .copied()
            .unwrap_or(0.0)
    };
    let warm = rss.len() / 5;
    let base = rss.get(warm).map_or(0, |r| r.1).max(1) as f64;
    let end = rss.last().map_or(0, |r| r.1) as f64;
    let table = crate::engine::timeline::read(&state.join("timeline.csv")).unwrap_or_default();
    let rows = &table.rows;
    let col = |n: &str| {
        crate::engine::timeline::COLUMNS
            .iter()
            .position(|c| *c == n)
            .expect("column")
    };
    let gs = |r: &Vec<f64>| r[col("ground_plus_sediment")];
    let drift = match (rows.first(), rows.last()) {
        (Some(a), Some(b)) if gs(a) != 0.0 => ((gs(b) - gs(a)) / gs(a)).abs(),
        _ => f64::NAN,
    };
    let conserved_drift = conserved_drift(&table);
    let frame = rows
        .iter()
        .map(|r| r[col("frame_ms")])
        .filter(|v| *v > 0.0)
        .collect::<Vec<_>>();
    let fifth = (rss.len() / 5).max(1);
    let window = |from: usize, to: usize| -> Vec<u64> {
        let mut v: Vec<u64> = rss[from.min(rss.len())..to.min(rss.len())]
            .iter()
            .map(|r| r.1)
            .collect();
        v.sort_unstable();
        v
    };
    let (early, late) = (
        window(fifth, 2 * fifth),
        window(rss.len().saturating_sub(fifth), rss.len()),
    );
    let growth = |a: Option<&u64>, b: Option<&u64>| match (a, b) {
        (Some(&a), Some(&b)) if a > 0 => (b as f64 - a as f64) / a as f64 * 100.0,
        _ => f64::NAN,
    };
    let rss_peak_growth_pct = growth(early.last(), late.last());
    let rss_median_growth_pct = growth(early.get(early.len() / 2), late.get(late.len() / 2));
    snaps.sort_by(|a, b| a.total_cmp(b));
    let rss_max_kb = rss.iter().map(|r| r.1).max().unwrap_or(0);
    Ok(SoakReport {
        rss_peak_growth_pct,
        rss_median_growth_pct,
        minutes: secs / 60.0,
        rss_growth_after_warmup_pct: (end - base) / base * 100.0,
        rss_kb: rss,
        max_dirty_queue: max_q,
        status_ms_p50: pct(0.5),
        status_ms_p99: pct(0.99),
        status_ms_max: lat.last().copied().unwrap_or(0.0),
        ticks_per_s: (last_tick - first_tick.unwrap_or(0)) as f64 / secs,
        frame_ms_mean: frame.iter().sum::<f64>() / frame.len().max(1) as f64,
        ground_plus_sediment_drift: drift,
        conserved_drift,
        ticks: last_tick,
        frames: frames.0,
        frames_skipped: frames.1,
        first_frame_s,
        rss_max_kb,
        snapshot_ms_p50: snaps.get(snaps.len() / 2).copied().unwrap_or(0.0),
        snapshot_ms_max: snaps.last().copied().unwrap_or(0.0),
        commit_ms_max,
        commit_chunks,
        memory_budget,
        window: last_window,
    })
}

/// The drift of each `total:SCRIPT.CHANNEL` column of a timeline from its
/// first row to its last: relative, or absolute where the total starts at 0.
fn conserved_drift(table: &crate::engine::timeline::Table) -> Vec<(String, f64)> {
    let rel = |a: f64, b: f64| {
        if a != 0.0 {
            ((b - a) / a).abs()
        } else {
            (b - a).abs()
        }
    };
    let rows = &table.rows;
    (table.columns.iter().enumerate())
        .filter(|(_, c)| c.starts_with("total:"))
        .filter_map(|(i, c)| {
            let (a, b) = (rows.first()?.get(i)?, rows.last()?.get(i)?);
            Some((c["total:".len()..].to_string(), rel(*a, *b)))
        })
        .collect()
}

#[cfg(test)]
mod tests {
    /// Regression (researcher probe): `soak` reported the drift of ground
    /// plus sediment only, meaningless on a world of voxel scripts; it
    /// reports each declared conserved channel's too.
    #[test]
    fn soak_reports_the_drift_of_each_declared_conserved_total() {
        let table = crate::engine::timeline::Table {
            columns: ["tick", "water", "total:water3d.water", "total:x.y"]
                .map(String::from)
                .to_vec(),
            rows: vec![vec![1.0, 5.0, 200.0, 0.0], vec![2.0, 9.0, 200.5, 0.25]],
            skipped: 0,
        };
        assert_eq!(
            super::conserved_drift(&table),
            vec![
                ("water3d.water".to_string(), 0.0025),
                ("x.y".to_string(), 0.25)
            ]
        );
    }
}
