//! Reading a timeline back ([`read`], tolerant of hand-made and cut-off
//! files) and `brickworld chart STATE`, which draws it as SVG charts.

use std::path::Path;

use anyhow::{Context, Result, bail};

use super::ROTATE_BYTES;

/// A timeline read back: its column names and rows.
#[derive(Clone, Debug, Default)]
pub struct Table {
    /// Column names, from the header.
    pub columns: Vec<String>,
    /// Rows (only those with every column).
    pub rows: Vec<Vec<f64>>,
    /// Lines left out: a field count other than the header's.
    pub skipped: usize,
}

impl Table {
    /// Index of column `name`.
    pub fn col(&self, name: &str) -> Option<usize> {
        self.columns.iter().position(|c| c == name)
    }
}

/// Read a timeline CSV: a regular file of at most 4 × [`ROTATE_BYTES`]
/// (the engine rotates its own at one; regression: a link to /dev/zero
/// filled memory).
pub fn read(path: &Path) -> Result<Table> {
    let text = crate::files::read_bounded(path, 4 * ROTATE_BYTES)?;
    let text = String::from_utf8_lossy(&text);
    let mut t = Table::default();
    // A last line without its newline was cut off (a kill or a full disk
    // in the middle of an append): not a row, and not a sign of a foreign
    // file either.
    let complete = if text.ends_with('\n') {
        &text[..]
    } else {
        text.rsplit_once('\n').map_or("", |(head, _)| head)
    };
    let mut lines = complete.lines();
    if let Some(header) = lines.next() {
        t.columns = header.trim().split(',').map(str::to_string).collect();
    }
    add_rows(&mut t, lines);
    Ok(t)
}

/// Parse `lines` as rows of `t`: blank ones are skipped, and those with
/// a field count other than the header's are counted in `skipped`.
fn add_rows<'a>(t: &mut Table, lines: impl Iterator<Item = &'a str>) {
    for line in lines.filter(|l| !l.trim().is_empty()) {
        let vals: Vec<f64> = line
            .split(',')
            .map(|v| v.trim().parse().unwrap_or(f64::NAN))
            .collect();
        if vals.len() == t.columns.len() {
            t.rows.push(vals);
        } else {
            t.skipped += 1;
        }
    }
}

/// The header and the last rows (at most `rows`) of a timeline CSV,
/// reading only its end: the engine seeds the viewer's charts with them at
/// start. Lines that are not whole rows are left out, as in [`read`].
pub fn read_tail(path: &Path, rows: usize) -> Result<Table> {
    use std::io::{BufRead, Read, Seek, SeekFrom};
    // Rows are under 1 KiB: this much of the end holds `rows` of them.
    let span = (rows as u64).saturating_mul(1024).max(64 * 1024);
    let meta =
        std::fs::metadata(path).with_context(|| format!("cannot read {}", path.display()))?;
    if !meta.is_file() {
        anyhow::bail!("{} is not a regular file", path.display());
    }
    let mut f = std::io::BufReader::new(
        std::fs::File::open(path).with_context(|| format!("cannot read {}", path.display()))?,
    );
    let mut header = String::new();
    (&mut f).take(1 << 20).read_line(&mut header)?;
    let mut t = Table {
        columns: header.trim().split(',').map(str::to_string).collect(),
        ..Table::default()
    };
    let from = meta.len().saturating_sub(span).max(header.len() as u64);
    f.seek(SeekFrom::Start(from))?;
    let mut tail = Vec::new();
    f.take(span).read_to_end(&mut tail)?;
    let mut text = String::from_utf8_lossy(&tail).into_owned();
    if from > header.len() as u64 {
        // Started inside a line: drop it.
        let first = text.find('\n').map_or(text.len(), |i| i + 1);
        text.drain(..first);
    }
    if !text.ends_with('\n') {
        // A last line cut off by a kill is not a row.
        let keep = text.rfind('\n').map_or(0, |i| i + 1);
        text.truncate(keep);
    }
    add_rows(&mut t, text.lines());
    let extra = t.rows.len().saturating_sub(rows);
    t.rows.drain(..extra);
    Ok(t)
}

/// The most points a chart's line keeps: a longer timeline is thinned.
pub const MAX_CHART_POINTS: usize = 2000;

/// `points` thinned to at most [`MAX_CHART_POINTS`]: consecutive runs of
/// rows keep their lowest and highest value, in order, so spikes and dips
/// stay drawn (long-run probe: a day's timeline drew one point per row,
/// Zeros on a log chart (no dirty bricks, a script that took 0.000 ms) sit
/// a decade below the chart's least positive value, not at 1e-9, which
/// stretched its axis nine decades (review); a chart of zeros alone keeps
/// them at 1e-9.
fn floor_zeros(list: &mut [crate::bench::chart::Series<'_>]) {
    const ZERO: f64 = 1e-9;
    let least = list
        .iter()
        .flat_map(|s| s.points.iter().map(|p| p.1))
        .filter(|&y| y > ZERO)
        .fold(f64::INFINITY, f64::min);
    if least.is_finite() {
        for s in list.iter_mut() {
            for p in &mut s.points {
                if p.1 <= ZERO {
                    p.1 = least / 10.0;
                }
            }
        }
    }
}

/// 13 MB of SVG at 11 000 rows and some 300 MB by the timeline's rotation).
pub fn thin(points: Vec<(f64, f64)>) -> Vec<(f64, f64)> {
    if points.len() <= MAX_CHART_POINTS {
        return points;
    }
    let run = points.len().div_ceil(MAX_CHART_POINTS / 2);
    let mut out = Vec::with_capacity(MAX_CHART_POINTS);
    for chunk in points.chunks(run) {
        let by_y = |a: &&(f64, f64), b: &&(f64, f64)| a.1.total_cmp(&b.1);
        let (lo, hi) = (
            chunk.iter().min_by(by_y).copied(),
            chunk.iter().max_by(by_y).copied(),
        );
        match (lo, hi) {
            (Some(lo), Some(hi)) if lo.0 <= hi.0 => out.extend([lo, hi]),
            (Some(lo), Some(hi)) => out.extend([hi, lo]),
            _ => {}
        }
    }
    out.dedup();
    out
}

/// `brickworld chart STATE`: draw the timeline as SVG charts in `STATE/charts`.
pub fn chart(state: &Path) -> Result<Vec<std::path::PathBuf>> {
    use crate::bench::chart::Series;
    use plotters::style::RGBColor;
    let table = read(&state.join("timeline.csv"))?;
    let rows = &table.rows;
    let file = state.join("timeline.csv");
    // Rows that do not fit the header are not the engine's (regression:
    // a file of nothing else was said to need a longer run).
    if rows.len() < 2 && table.skipped > 0 {
        anyhow::bail!(
            "{} has {} lines whose fields do not match its header's {} columns: it is not a timeline the engine wrote",
            file.display(),
            table.skipped,
            table.columns.len()
        );
    }
    if rows.len() < 2 {
        anyhow::bail!(
            "{} has fewer than two rows: let the engine run a little longer",
            file.display()
        );
    }
    if table.skipped > 0 {
        crate::say!(
            "warning: {} left out {} lines whose fields do not match its header",
            file.display(),
            table.skipped
        );
    }
    let dir = state.join("charts");
    // Regression (hostile probe 2): a file there gave "File exists".
    // A link to a folder elsewhere too (review): the SVGs go in STATE.
    if std::fs::symlink_metadata(&dir).is_ok_and(|m| !m.file_type().is_dir()) {
        bail!(
            "{} is not a folder: chart writes its SVGs there, so move it away",
            dir.display()
        );
    }
    std::fs::create_dir_all(&dir).with_context(|| format!("cannot create {}", dir.display()))?;
    let palette = [
        RGBColor(60, 110, 200),
        RGBColor(200, 70, 60),
        RGBColor(40, 150, 80),
        RGBColor(150, 110, 80),
        RGBColor(120, 120, 140),
        RGBColor(170, 60, 170),
        RGBColor(30, 160, 170),
        RGBColor(220, 150, 30),
    ];
    if table.columns.first().map(String::as_str) != Some("tick") {
        anyhow::bail!(
            "{} is not a brickworld timeline: its first column is not 'tick'",
            state.join("timeline.csv").display()
        );
    }
    // A column a hand-made or older file lacks leaves its line out
    // (regression: it was a panic).
    let series = |name: &str, color: RGBColor| -> Option<Series<'_>> {
        let c = table.col(name)?;
        Some(Series {
            name: table.columns[c].as_str(),
            color,
            points: thin(
                // No value (NaN: `frame_ms` before a start's first frame,
                // a column a reload added) is no point, not the floor
                // (review: each start drew a frame at 1e-9 ms).
                rows.iter()
                    .filter(|r| r[c].is_finite())
                    .map(|r| (r[0].max(1.0), r[c].abs().max(1e-9)))
                    .collect(),
            ),
        })
    };
    let with_prefix = |prefix: &str| -> Vec<Series<'_>> {
        table
            .columns
            .iter()
            .filter(|c| c.starts_with(prefix))
            .enumerate()
            .filter_map(|(i, c)| series(c, palette[i % palette.len()]))
            .collect()
    };
    let mut totals: Vec<Series<'_>> = [
        series("water", palette[0]),
        series("ground_plus_sediment", palette[3]),
        series("snow", palette[4]),
        series("drained", palette[1]),
    ]
    .into_iter()
    .flatten()
    .collect();
    totals.extend(with_prefix("total:"));
    let mut out = Vec::new();
    for (file, title, y, mut list) in [
        (
            "rate.svg",
            "Steps per second and frame time",
            "value (log)",
            [
                series("steps_per_s", palette[0]),
                series("frame_ms", palette[1]),
            ]
            .into_iter()
            .flatten()
            .collect(),
        ),
        (
            "memory.svg",
            "Resident memory (KiB)",
            "KiB (log)",
            series("rss_kb", palette[2]).into_iter().collect(),
        ),
        (
            "work.svg",
            "Active tiles and dirty bricks",
            "count (log)",
            [
                series("active_bricks", palette[0]),
                series("dirty_bricks", palette[1]),
            ]
            .into_iter()
            .flatten()
            .collect(),
        ),
        (
            "scripts.svg",
            "Time per step of each script (ms)",
            "ms (log)",
            with_prefix("ms:"),
        ),
    ] {
        if list.is_empty() {
            continue;
        }
        floor_zeros(&mut list);
        let path = dir.join(file);
        refuse_special(&path)?;
        let svg = crate::bench::chart::xy_svg(&path, title, "tick (log)", y, &list)?;
        write_svg(&path, &svg)?;
        out.push(path);
    }
    // Each total on its own chart, with linear axes, so that its drift
    // shows (researcher probe: on one log chart of all totals, titled
    // "Conserved totals", a drift was invisible and rain-fed water looked
    // conserved). `total-NAME.svg`; the old `totals.svg` is removed.
    for s in totals {
        let short = s.name.strip_prefix("total:").unwrap_or(s.name);
        let safe: String = (short.chars())
            .map(|c| {
                if c.is_ascii_alphanumeric() || c == '_' || c == '.' {
                    c
                } else {
                    '-'
                }
            })
            .collect();
        let path = dir.join(format!("total-{safe}.svg"));
        refuse_special(&path)?;
        let raw = Series {
            points: thin(
                rows.iter()
                    .map(|r| (r[0], r[table.col(s.name).unwrap_or(0)]))
                    .collect(),
            ),
            ..s
        };
        let what = if s.name.starts_with("total:") {
            "declared conserved by its script"
        } else {
            "a column total, the moat included"
        };
        let title = format!("{} ({what})", s.name);
        // A column with no finite value (a hand-made file) is skipped,
        // not the end of every chart (review).
        let svg = match crate::bench::chart::line_svg(&path, &title, "tick", "total", &[raw]) {
            Ok(svg) => svg,
            Err(e) => {
                crate::say!("warning: {e}");
                continue;
            }
        };
        write_svg(&path, &svg)?;
        out.push(path);
    }
    // Charts of totals this timeline no longer has (another set of
    // scripts), and the old single `totals.svg`, are removed (review).
    if let Ok(entries) = std::fs::read_dir(&dir) {
        for e in entries.flatten() {
            let name = e.file_name().to_string_lossy().to_string();
            let stale = (name == "totals.svg"
                || (name.starts_with("total-") && name.ends_with(".svg")))
                && !out
                    .iter()
                    .any(|p| p.file_name() == Some(e.file_name().as_os_str()));
            if stale && e.file_type().is_ok_and(|t| t.is_file()) {
                let _ = std::fs::remove_file(e.path());
            }
        }
    }
    Ok(out)
}

/// The names are fixed, inside STATE: anything there but a file is
/// refused, not written into (regression, hostile probe 3: a FIFO hung
/// `chart`, and a link made it overwrite a file outside STATE).
fn refuse_special(path: &Path) -> Result<()> {
    if std::fs::symlink_metadata(path).is_ok_and(|m| !m.file_type().is_file()) {
        bail!(
            "{} is not a regular file (a link, folder or FIFO): chart replaces its SVGs there, so move it away",
            path.display()
        );
    }
    Ok(())
}

/// Written beside and renamed over its name: a link or FIFO put there
/// after [`refuse_special`] is replaced, never written through.
fn write_svg(path: &Path, svg: &str) -> Result<()> {
    crate::files::Staged::replacing(path)
        .and_then(|f| std::fs::write(f.path(), svg).and_then(|_| f.commit()))
        .with_context(|| format!("cannot write {}", path.display()))
}

#[cfg(test)]
mod tests;
