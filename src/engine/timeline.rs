//! The timeline: one CSV row per frame interval, appended to
//! `STATE/timeline.csv`, and `brickworld chart STATE` to draw it.

use std::fs::{File, OpenOptions};
use std::io::{BufRead, BufReader, Write};
use std::path::Path;

use anyhow::{Context, Result};

/// Column names, in order.
pub const COLUMNS: [&str; 11] = [
    "tick",
    "steps_per_s",
    "active_bricks",
    "dirty_bricks",
    "frame_ms",
    "bricks_streamed",
    "rss_kb",
    "water",
    "ground_plus_sediment",
    "snow",
    "drained",
];

/// One row.
#[derive(Clone, Debug, Default, PartialEq)]
pub struct Row {
    /// Simulation tick.
    pub tick: u64,
    /// Steps per second.
    pub steps_per_s: f64,
    /// Active tiles.
    pub active_bricks: usize,
    /// Dirty bricks this tick.
    pub dirty_bricks: usize,
    /// Last frame's time.
    pub frame_ms: f64,
    /// Bricks streamed so far.
    pub bricks_streamed: u64,
    /// Resident memory, KiB.
    pub rss_kb: u64,
    /// Total water.
    pub water: f64,
    /// Total ground plus sediment.
    pub ground_plus_sediment: f64,
    /// Total snow.
    pub snow: f64,
    /// Water drained over the edges so far.
    pub drained: f64,
}

/// An append-only CSV timeline.
pub struct Timeline {
    file: File,
}

/// Resident memory of this process in KiB (Linux), 0 if unknown.
pub fn rss_kb() -> u64 {
    rss_kb_of(std::process::id())
}

/// Resident memory of process `pid` in KiB (Linux), 0 if unknown.
pub fn rss_kb_of(pid: u32) -> u64 {
    std::fs::read_to_string(format!("/proc/{pid}/status"))
        .ok()
        .and_then(|s| {
            s.lines()
                .find(|l| l.starts_with("VmRSS:"))
                .and_then(|l| l.split_whitespace().nth(1))
                .and_then(|v| v.parse().ok())
        })
        .unwrap_or(0)
}

impl Timeline {
    /// Open (creating, with a header) the timeline at `path`.
    pub fn open(path: &Path) -> Result<Self> {
        let fresh = !path.exists();
        let mut file = OpenOptions::new()
            .create(true)
            .append(true)
            .open(path)
            .with_context(|| format!("cannot open {}", path.display()))?;
        if fresh {
            writeln!(file, "{}", COLUMNS.join(","))
                .with_context(|| format!("cannot write {}", path.display()))?;
        }
        Ok(Timeline { file })
    }

    /// Append a row (errors are ignored: the timeline must never stop the engine).
    pub fn record(&mut self, r: &Row) {
        let _ = writeln!(
            self.file,
            "{},{:.3},{},{},{:.3},{},{},{:.9},{:.9},{:.9},{:.9}",
            r.tick,
            r.steps_per_s,
            r.active_bricks,
            r.dirty_bricks,
            r.frame_ms,
            r.bricks_streamed,
            r.rss_kb,
            r.water,
            r.ground_plus_sediment,
            r.snow,
            r.drained
        );
    }
}

/// Read a timeline CSV.
pub fn read(path: &Path) -> Result<Vec<Vec<f64>>> {
    let f = File::open(path).with_context(|| format!("cannot read {}", path.display()))?;
    let mut rows = Vec::new();
    for (i, line) in BufReader::new(f).lines().enumerate() {
        let line = line?;
        if i == 0 || line.trim().is_empty() {
            continue;
        }
        let vals: Vec<f64> = line
            .split(',')
            .map(|v| v.trim().parse().unwrap_or(f64::NAN))
            .collect();
        if vals.len() == COLUMNS.len() {
            rows.push(vals);
        }
    }
    Ok(rows)
}

/// `brickworld chart STATE`: draw the timeline as SVG charts in `STATE/charts`.
pub fn chart(state: &Path) -> Result<Vec<std::path::PathBuf>> {
    use crate::bench::chart::{Series, xy_chart};
    use plotters::style::RGBColor;
    let rows = read(&state.join("timeline.csv"))?;
    if rows.len() < 2 {
        anyhow::bail!(
            "{} has fewer than two rows: let the engine run a little longer",
            state.join("timeline.csv").display()
        );
    }
    let dir = state.join("charts");
    std::fs::create_dir_all(&dir).with_context(|| format!("cannot create {}", dir.display()))?;
    let col = |name: &str| {
        COLUMNS
            .iter()
            .position(|c| *c == name)
            .expect("known column")
    };
    let series = |name: &'static str, color: RGBColor| Series {
        name,
        color,
        points: rows
            .iter()
            .map(|r| (r[0].max(1.0), r[col(name)].abs().max(1e-9)))
            .collect(),
    };
    let mut out = Vec::new();
    for (file, title, y, list) in [
        (
            "rate.svg",
            "Steps per second and frame time",
            "value (log)",
            vec![
                series("steps_per_s", RGBColor(60, 110, 200)),
                series("frame_ms", RGBColor(200, 70, 60)),
            ],
        ),
        (
            "memory.svg",
            "Resident memory (KiB)",
            "KiB (log)",
            vec![series("rss_kb", RGBColor(40, 150, 80))],
        ),
        (
            "work.svg",
            "Active tiles and dirty bricks",
            "count (log)",
            vec![
                series("active_bricks", RGBColor(60, 110, 200)),
                series("dirty_bricks", RGBColor(200, 70, 60)),
            ],
        ),
        (
            "totals.svg",
            "Conserved totals",
            "total (log)",
            vec![
                series("water", RGBColor(60, 110, 200)),
                series("ground_plus_sediment", RGBColor(150, 110, 80)),
                series("snow", RGBColor(120, 120, 140)),
                series("drained", RGBColor(200, 70, 60)),
            ],
        ),
    ] {
        let path = dir.join(file);
        xy_chart(&path, title, "tick (log)", y, &list)?;
        out.push(path);
    }
    Ok(out)
}
