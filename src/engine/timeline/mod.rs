//! The timeline: one CSV row per frame interval, appended to
//! `STATE/timeline.csv`; [`chart`](mod@chart) reads it back and draws it
//! (`brickworld chart STATE`).
//!
//! The fixed [`COLUMNS`] come first, then one `ms:SCRIPT` column per script
//! (its time in the step) and one `total:SCRIPT.CHANNEL` column per channel
//! a script declares `conserved`. A file whose header differs (another
//! world, another set of scripts) is renamed aside, never overwritten, and a
//! file past [`ROTATE_BYTES`] is rotated to `timeline.1.csv`; files set
//! aside are pruned, oldest first, past [`ASIDE_BYTES`] or [`ASIDE_FILES`],
//! so a world left running for days keeps a bounded timeline.

use std::fs::{File, OpenOptions};
use std::io::{BufRead, BufReader, Read, Write};
use std::path::{Path, PathBuf};

mod aside;
mod chart;
mod row;
pub use aside::{ASIDE_BYTES, ASIDE_FILES};
use aside::{aside_path, prune_aside};
pub use chart::{Table, chart, read, read_tail};
pub use row::{COLUMNS, Row};

/// The most of a timeline's first line read to compare headers.
const MAX_HEADER_BYTES: u64 = 1 << 20;

/// A timeline file is rotated to `timeline.1.csv` past this size.
pub const ROTATE_BYTES: u64 = 32 << 20;

/// Where the timeline named `path` is reached: in the folder held open
/// as `folder`, where there is one.
fn reached(path: &Path, folder: Option<&File>) -> std::path::PathBuf {
    match (folder.and_then(crate::files::held_folder), path.file_name()) {
        (Some(dir), Some(name)) => dir.join(name),
        _ => path.to_path_buf(),
    }
}

/// `other`, a file in the timeline's folder reached through the held
/// folder, named as the user names that folder (beside `path`).
fn beside(path: &Path, other: &Path) -> std::path::PathBuf {
    match other.file_name() {
        Some(name) => path.with_file_name(name),
        None => other.to_path_buf(),
    }
}

/// An append-only CSV timeline.
pub struct Timeline {
    file: File,
    /// The path it was opened by, as messages name it.
    path: std::path::PathBuf,
    /// Its folder, held open: the file is opened again there, never in
    /// another folder made at the same path since.
    folder: Option<File>,
    /// Where the file is reached: through the held folder where there is
    /// one (found once, at open; the descriptor's path does not change).
    at: std::path::PathBuf,
    /// Said that `path` no longer names `file` and it could not be made
    /// again (said once until it can).
    astray: bool,
    header: String,
    /// Per-script columns in the header.
    extra: usize,
    /// Their names.
    extra_names: Vec<String>,
    /// Bytes toward the next rotation (not the held file's length: after a
    /// failed rotation the held file is the one moved aside).
    written: u64,
    /// Since a row could not be written: the first such row's tick and
    /// how many were lost, until one is written again.
    failing: Option<(u64, u64)>,
}

pub use crate::scene::budget::{rss_kb, rss_kb_of};

/// What can go wrong with the timeline file. The daemon says each in one
/// line; none stops a running engine (see [`Timeline::record`]).
#[derive(Debug, thiserror::Error)]
pub enum TimelineError {
    /// Something other than a regular file is at the timeline's path.
    #[error(
        "{} is not a regular file: move it away (the engine writes its timeline there)",
        path.display()
    )]
    NotAFile {
        /// The timeline's path.
        path: PathBuf,
    },
    /// The OS refused what `what` says was being done (not a `source`:
    /// the text says it, and a chain would print it twice).
    #[error("{what}: {error}")]
    Io {
        /// What was being done, and to which file.
        what: String,
        /// What the OS said.
        error: std::io::Error,
    },
    /// The file could not be read back.
    #[error("cannot trim {}: {error}", path.display())]
    Read {
        /// The timeline's path.
        path: PathBuf,
        /// Why.
        error: crate::files::FileError,
    },
    /// The rows after a tick could not be copied aside, so they stay.
    #[error(
        "cannot copy the rows after tick {tick} of {} to {}: {error}; they stay, so the ticks run again appear twice",
        path.display(),
        aside.display()
    )]
    CopyAside {
        /// The tick after which rows were to be dropped.
        tick: u64,
        /// The timeline's path.
        path: PathBuf,
        /// Where they were to be copied.
        aside: PathBuf,
        /// What the OS said.
        error: std::io::Error,
    },
}

type Result<T> = std::result::Result<T, TimelineError>;

impl Timeline {
    /// Open (creating, with a header) the timeline at `path`, with the
    /// per-script columns `extra` after the fixed ones. An existing file
    /// with another header is renamed `timeline.<unix seconds>.csv` first.
    pub fn open(path: &Path, extra: &[String]) -> Result<Self> {
        let dir = match path.parent() {
            Some(d) if !d.as_os_str().is_empty() => d,
            _ => Path::new("."),
        };
        Self::open_in(path, File::open(dir).ok(), extra)
    }

    /// The same file opened again, in the folder held since the start,
    /// with the per-script columns `extra` (a file there with another
    /// header is moved aside first, as [`Timeline::open`] does).
    pub fn reopen(&self, extra: &[String]) -> Result<Self> {
        let folder = self.folder.as_ref().and_then(|f| f.try_clone().ok());
        Self::open_in(&self.path, folder, extra)
    }

    fn open_in(path: &Path, folder: Option<File>, extra: &[String]) -> Result<Self> {
        let at = reached(path, folder.as_ref());
        let header = COLUMNS
            .iter()
            .map(|c| c.to_string())
            .chain(extra.iter().cloned())
            .collect::<Vec<_>>()
            .join(",");
        // Only a regular file is read or appended to: a FIFO there hung the
        // engine at start (and it ignored SIGTERM), a link to /dev/zero
        // filled memory looking for a newline (regression).
        if crate::files::is_there_but_not_a_file(&at) {
            return Err(TimelineError::NotAFile {
                path: path.to_path_buf(),
            });
        }
        if let Ok(f) = crate::files::open_for_reading(&at) {
            let (mut first, mut second) = (String::new(), String::new());
            let mut lines = BufReader::new(f.take(MAX_HEADER_BYTES));
            let _ = lines.read_line(&mut first);
            let _ = lines.read_line(&mut second);
            // A file that holds no row, and at most a part of this header
            // (a full disk cut it, or refused it whole), has no history to
            // keep: emptied, it gets its header from `create` (regression,
            // review: each start moved it aside, as a 0- or 1-byte file).
            let no_rows = second.is_empty() && header.starts_with(first.trim_end());
            if no_rows && !first.is_empty() {
                OpenOptions::new()
                    .write(true)
                    .open(&at)
                    .and_then(|f| f.set_len(0))
                    .map_err(|error| TimelineError::Io {
                        what: format!("cannot empty {}", path.display()),
                        error,
                    })?;
            }
            if !no_rows && first.trim_end() != header {
                let aside = aside_path(&at);
                std::fs::rename(&at, &aside).map_err(|error| TimelineError::Io {
                    what: format!(
                        "cannot move {} aside to {}",
                        path.display(),
                        beside(path, &aside).display()
                    ),
                    error,
                })?;
                prune_aside(&at);
            }
        }
        let mut t = Timeline {
            file: Self::create(&at, &header).map_err(|error| TimelineError::Io {
                what: format!("cannot open {}", path.display()),
                error,
            })?,
            path: path.to_path_buf(),
            folder,
            at: at.clone(),
            astray: false,
            header,
            extra: extra.len(),
            extra_names: extra.to_vec(),
            written: 0,
            failing: None,
        };
        t.written = t.file.metadata().map_or(0, |m| m.len());
        Ok(t)
    }

    /// The per-script columns this file was opened with.
    pub fn extra_columns(&self) -> &[String] {
        &self.extra_names
    }

    fn create(path: &Path, header: &str) -> std::io::Result<File> {
        let mut file = OpenOptions::new().create(true).append(true).open(path)?;
        // An empty file, not only a new one: a header that a full disk
        // refused is written by the next open (found by review: a file made
        // but left empty was taken as started, and went on without one).
        if file.metadata()?.len() == 0 {
            append(&mut file, format!("{header}\n").as_bytes())?;
        }
        Ok(file)
    }

    /// Open the file again when its path no longer names it (deleted,
    /// moved, or replaced while the engine ran): rows went on into the
    /// file held open, which nothing named, without a word (regression,
    /// operator probe). When it cannot be made again (a folder is there),
    /// that is said once and rows go on into the file held open.
    fn follow_path(&mut self, tick: u64) {
        if crate::files::names_open_file(&self.at, &self.file) {
            return;
        }
        match self.reopen(&self.extra_names) {
            Ok(t) => {
                crate::say!(
                    "{} was moved, removed or replaced while the engine ran: a new one starts at tick {tick}",
                    self.path.display()
                );
                self.file = t.file;
                self.written = t.written;
                self.astray = false;
            }
            Err(e) if !self.astray => {
                self.astray = true;
                crate::say!(
                    "warning: {} was moved, removed or replaced while the engine ran, and cannot be made again: {e:#}; rows from tick {tick} go on into the file the engine holds open, which that path no longer names, until it can",
                    self.path.display()
                );
            }
            Err(_) => {}
        }
    }

    /// Append a row. Errors never stop the engine: the first row that
    /// cannot be written is said, and so is the first written again, with
    /// the ticks lost in between (regression, operator probe: rows were
    /// lost without a word while the disk was full). Past
    /// [`ROTATE_BYTES`] the file becomes `timeline.1.csv` (replacing the
    /// one before) and a fresh one starts.
    pub fn record(&mut self, r: &Row) {
        let mut line = format!(
            "{},{:.3},{},{},{:.3},{},{},{:.9},{:.9},{:.9},{:.9},{:.3}",
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
            r.drained,
            r.unix_s
        );
        // As many per-script values as the header names (the engine reopens
        // the timeline when a reload changes the columns; this only guards
        // the row's shape).
        let mut extra: Vec<String> = r
            .script_ms
            .iter()
            .map(|v| format!("{v:.3}"))
            .chain(r.conserved.iter().map(|v| format!("{v:.9}")))
            .collect();
        extra.resize(self.extra, "nan".into());
        for v in extra {
            line.push(',');
            line.push_str(&v);
        }
        line.push('\n');
        self.follow_path(r.tick);
        let at = self.at.clone();
        if self.written + line.len() as u64 > ROTATE_BYTES
            && std::fs::rename(&at, at.with_extension("1.csv")).is_ok()
        {
            match Self::create(&at, &self.header) {
                Ok(f) => {
                    self.file = f;
                    self.written = self.header.len() as u64 + 1;
                }
                // Rows go on into the file just moved (its handle is still
                // open), and no rotation is tried until it grows again: a
                // half-made new file renamed over it would destroy the
                // history (found by review).
                Err(_) => self.written = 0,
            }
        }
        // What the held file holds before the row: a row cut by a full
        // disk is taken back to there.
        let before = self.file.metadata().map(|m| m.len());
        match append(&mut self.file, line.as_bytes()) {
            Ok(()) => {
                self.written += line.len() as u64;
                if let Some((first, lost)) = self.failing.take() {
                    crate::say!(
                        "{} is written again; {lost} row(s) from tick {first} to tick {} are missing from it",
                        self.path.display(),
                        r.tick.saturating_sub(1)
                    );
                }
            }
            Err(e) => {
                // A row cut by a full disk is taken back, so the next one
                // does not start in its middle (regression, hostile probe:
                // torn rows that `chart` then left out): to the file's own
                // length, never the rotation count (regression, code
                // review: after a failed rotation that count restarts at
                // 0 while the held file is the history moved aside, and
                // the next failed row emptied it).
                if let Ok(len) = before {
                    let _ = self.file.set_len(len);
                }
                match &mut self.failing {
                    Some((_, lost)) => *lost += 1,
                    None => {
                        crate::say!(
                            "warning: cannot append to {}: {e}; its rows are lost until it can be written again",
                            self.path.display()
                        );
                        self.failing = Some((r.tick, 1));
                    }
                }
            }
        }
    }

    /// Drop the rows after `tick` and a last row cut short: a resumed
    /// engine runs those ticks again from its last commit, and appended
    /// them a second time (regression, hostile probe: ticks repeated after
    /// each kill -9). The rows dropped are copied aside first, under the
    /// header (`timeline.<unix seconds>.csv`), so a world restarted from an
    /// older store (or afresh) loses no history (found by review); only
    /// those rows, not the whole file, so an engine restarted after many
    /// crashes does not copy its whole history each time (regression,
    /// crash probe: 29 MiB more a crash). Returns where they were copied,
    /// if anything was dropped.
    pub fn drop_rows_after(&mut self, tick: u64) -> Result<Option<std::path::PathBuf>> {
        let at = self.at.clone();
        let text = crate::files::read_bounded(&at, ROTATE_BYTES * 2).map_err(|error| {
            TimelineError::Read {
                path: self.path.clone(),
                error: error.named(&self.path),
            }
        })?;
        let mut keep = 0usize;
        for (i, line) in text.split_inclusive(|&b| b == b'\n').enumerate() {
            if !line.ends_with(b"\n") {
                break;
            }
            let first = line.split(|&b| b == b',').next().unwrap_or_default();
            let row_tick = std::str::from_utf8(first)
                .ok()
                .and_then(|t| t.trim().parse::<u64>().ok());
            if i > 0 && row_tick.is_some_and(|t| t > tick) {
                break;
            }
            keep += line.len();
        }
        if keep == text.len() {
            return Ok(None);
        }
        let header = text
            .split_inclusive(|&b| b == b'\n')
            .next()
            .unwrap_or_default();
        let dropped = if keep == 0 {
            text.clone()
        } else {
            [header, &text[keep..]].concat()
        };
        let aside = aside_path(&at);
        if let Err(e) = std::fs::write(&aside, &dropped) {
            // No empty or partial copy is left behind (regression,
            // operator probe: each start on a full disk left a 0-byte one).
            let _ = std::fs::remove_file(&aside);
            return Err(TimelineError::CopyAside {
                tick,
                path: self.path.clone(),
                aside: beside(&self.path, &aside),
                error: e,
            });
        }
        self.file
            .set_len(keep as u64)
            .map_err(|error| TimelineError::Io {
                what: format!("cannot trim {}", self.path.display()),
                error,
            })?;
        self.written = keep as u64;
        prune_aside(&at);
        Ok(Some(beside(&self.path, &aside)))
    }
}

/// Append `bytes` to `file` (tests: refused while `FULL_DISK` is set,
/// as a full disk refuses, on an ordinary file).
fn append(file: &mut File, bytes: &[u8]) -> std::io::Result<()> {
    #[cfg(test)]
    if FULL_DISK.get() {
        return Err(std::io::Error::from_raw_os_error(28));
    }
    file.write_all(bytes)
}

#[cfg(test)]
thread_local! {
    /// Tests: every append fails, as on a full disk.
    static FULL_DISK: std::cell::Cell<bool> = const { std::cell::Cell::new(false) };
}

#[cfg(test)]
mod tests;
