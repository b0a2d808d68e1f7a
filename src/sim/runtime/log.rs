//! `log(...)` for scripts: rate-limited lines per script, kept for
//! `/status` (the last [`KEPT`]) and handed once to whoever prints them (the
//! daemon's log, `sim`'s output). Nothing is allocated or locked unless a
//! script calls `log`.

use std::collections::VecDeque;
use std::sync::{Mutex, OnceLock};
use std::time::Instant;

use rustc_hash::FxHashMap;

use crate::text::escape_controls;

/// Lines kept per script for `/status`.
pub const KEPT: usize = 20;
/// Lines accepted per script per second; more are counted as dropped.
pub const PER_SECOND: u32 = 20;
/// Longest line kept, in characters.
pub const MAX_LINE: usize = 200;

#[derive(Default)]
struct ScriptLog {
    recent: VecDeque<String>,
    unprinted: Vec<String>,
    dropped: u64,
    /// Lines accepted so far (the sequence number of the next one).
    accepted: u64,
    window: Option<Instant>,
    in_window: u32,
}

fn logs() -> &'static Mutex<FxHashMap<String, ScriptLog>> {
    static LOGS: OnceLock<Mutex<FxHashMap<String, ScriptLog>>> = OnceLock::new();
    LOGS.get_or_init(Default::default)
}

thread_local! {
    static AT_LOAD: std::cell::Cell<bool> = const { std::cell::Cell::new(false) };
}

/// Run `f`, a script's load-time smoke test, with the lines it logs marked
/// `(load test)`: they come from a sample tile or brick, with the smoke
/// test's `dt`, not from a step of the world (regression, docs walk: they
/// looked like the first step's lines).
pub fn at_load<T>(f: impl FnOnce() -> T) -> T {
    struct Reset;
    impl Drop for Reset {
        fn drop(&mut self) {
            AT_LOAD.with(|a| a.set(false));
        }
    }
    AT_LOAD.with(|a| a.set(true));
    let _reset = Reset;
    f()
}

/// Record a line from `script` (rate-limited, truncated, one line).
pub fn push(script: &str, line: String) {
    let line = if AT_LOAD.with(|a| a.get()) {
        format!("(load test) {line}")
    } else {
        line
    };
    // Control characters are written as escapes: a script's newline, CR or
    // terminal escape must not forge daemon log lines or drive the
    // terminal (regression). Tab stays: it separates `log`'s arguments and
    // cannot break a line.
    let mut line = match escape_controls(&line, true) {
        std::borrow::Cow::Borrowed(_) => line,
        std::borrow::Cow::Owned(escaped) => escaped,
    };
    if line.chars().count() > MAX_LINE {
        line = line.chars().take(MAX_LINE).collect::<String>() + "…";
    }
    let Ok(mut map) = logs().lock() else { return };
    let log = map.entry(script.to_string()).or_default();
    let now = Instant::now();
    if log
        .window
        .is_none_or(|w| now.duration_since(w).as_secs_f64() >= 1.0)
    {
        log.window = Some(now);
        log.in_window = 0;
    }
    if log.in_window >= PER_SECOND {
        log.dropped += 1;
        return;
    }
    log.in_window += 1;
    log.accepted += 1;
    log.recent.push_back(line.clone());
    while log.recent.len() > KEPT {
        log.recent.pop_front();
    }
    if log.unprinted.len() < 1000 {
        log.unprinted.push(line);
    }
}

/// Count `n` lines of `script` as dropped by the rate limit without
/// recording them (lines a kernel call logged past the most one call
/// holds: they could never be accepted in the same second).
pub fn drop_lines(script: &str, n: u64) {
    if n == 0 {
        return;
    }
    let Ok(mut map) = logs().lock() else { return };
    let log = map.entry(script.to_string()).or_default();
    log.dropped = log.dropped.saturating_add(n);
}

/// The text of one `log(...)` call: its arguments as text, joined by tabs,
/// cut once it is sure to be longer than the [`MAX_LINE`] characters
/// [`push`] keeps. Only that prefix is copied, so a script logging a huge
/// string allocates nothing outside its VM's memory limit for it
/// (regression, panic audit: 400 calls of `log` with an 8 MiB string held
/// 3.2 GB in lines and aborted the process).
pub fn line_of<'a>(parts: impl IntoIterator<Item = LogPart<'a>>) -> String {
    // Enough bytes for MAX_LINE + 1 characters of any width.
    const LINE_BYTES: usize = 4 * (MAX_LINE + 1);
    let mut line = String::new();
    for (k, part) in parts.into_iter().enumerate() {
        if k > 0 {
            line.push('\t');
        }
        match part {
            LogPart::Text(t) => line.push_str(&t),
            LogPart::Bytes(b) => {
                let room = LINE_BYTES.saturating_sub(line.len()) + 1;
                line.push_str(&String::from_utf8_lossy(&b[..b.len().min(room)]));
            }
        }
        if line.len() > LINE_BYTES {
            break;
        }
    }
    line
}

/// One argument of `log(...)`: text made from a value, or a string's bytes.
pub enum LogPart<'a> {
    /// A number, a boolean, nil or a type name.
    Text(String),
    /// A Lua string's bytes (not necessarily UTF-8).
    Bytes(&'a [u8]),
}

/// The last lines of `script`, how many were dropped by the rate limit,
/// and how many were accepted so far (the last line is number `seq - 1`).
pub fn recent(script: &str) -> (Vec<String>, u64, u64) {
    let Ok(map) = logs().lock() else {
        return (Vec::new(), 0, 0);
    };
    map.get(script)
        .map(|l| (l.recent.iter().cloned().collect(), l.dropped, l.accepted))
        .unwrap_or_default()
}

/// Lines not yet printed, as (script, line), oldest first per script.
pub fn take_unprinted() -> Vec<(String, String)> {
    let Ok(mut map) = logs().lock() else {
        return Vec::new();
    };
    let mut names: Vec<&String> = map.keys().collect();
    names.sort();
    let names: Vec<String> = names.into_iter().cloned().collect();
    let mut out = Vec::new();
    for n in names {
        if let Some(l) = map.get_mut(&n) {
            out.extend(l.unprinted.drain(..).map(|line| (n.clone(), line)));
        }
    }
    out
}

#[cfg(test)]
mod tests {
    use super::*;

    /// Regression (hostile probe): a script's newline, CR, ANSI escape and
    /// NUL went raw to the daemon's stderr.
    #[test]
    fn control_characters_are_escaped_into_one_line() {
        push(
            "escapes-test",
            "first\nsecond\r\u{1b}[31mRED\u{0}\tok".into(),
        );
        let (lines, _, _) = recent("escapes-test");
        // The tab between `log`'s arguments is kept (regression: the escape
        // turned every separator into a literal "\t").
        assert_eq!(lines, ["first\\nsecond\\r\\u{1b}[31mRED\\u{0}\tok"]);
    }
}
