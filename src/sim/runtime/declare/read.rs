//! Reading values out of a declaration strictly: lists with no holes and
//! no other keys, strings that are UTF-8 and not repeated, numbers that are
//! numbers (not strings Luau would coerce), and Luau's own errors cut to
//! one clean line.
//!
//! Regression (hostile probe 3): `sequence_values` read a list up to its
//! first `nil` and skipped string keys, so `nonnegative = { a = true }`,
//! `channels = { "a", nil, "b" }` and a pass after a gap loaded and were
//! ignored; lists of 200 000 names were checked for repeats in quadratic
//! time outside every script budget.

use mlua::{Table, Value};

use super::{a, declaration};
use crate::sim::SimError;
use crate::sim::runtime::spec::ScriptSource;

/// The most entries a list in a declaration may hold (channels, passes and
/// parameters have their own, lower bounds).
pub const MAX_LIST: usize = 1024;

/// The message of one of Luau's errors (all its lines, up to the stack
/// traceback), without its `runtime error:` or `syntax error:` tag, and the
/// line it names in `src` if it starts with `src`'s own location (which it
/// then loses). Callers escape its line breaks for a one-line error.
pub(in crate::sim::runtime) fn lua_text(
    src: &ScriptSource,
    e: &mlua::Error,
) -> (Option<usize>, String) {
    lua_text_of(&src.name, &e.to_string())
}

/// What a call of nil is told: the functions the sandbox removed, and what
/// to use instead.
pub const SANDBOX_HINT: &str = " (a misspelt name, or one the sandbox removes: print, loadstring, load, require, math.random…; use log(...) and c.random(...))";

/// [`lua_text`] of error text `text` raised by script `name`.
pub(in crate::sim::runtime) fn lua_text_of(name: &str, text: &str) -> (Option<usize>, String) {
    // All of the message: a script's `error("a\nb")` lost its second line
    // without a mark (regression, modder probe).
    let first = text
        .rsplit_once("\nstack traceback:")
        .map_or(text, |(head, _)| head)
        .trim_end()
        .trim_start_matches("runtime error: ")
        .trim_start_matches("syntax error: ");
    // Luau names no function here: say which ones the sandbox removed
    // (docs walk: `print()` got a bare "attempt to call a nil value").
    let hinted;
    let first = if first.ends_with("attempt to call a nil value") {
        hinted = format!("{first}{SANDBOX_HINT}");
        hinted.as_str()
    } else {
        first
    };
    let own = format!("{name}.lua:");
    if let Some(rest) = first.strip_prefix(&own)
        && let Some((line, msg)) = rest.split_once(": ")
        && let Ok(line) = line.parse::<usize>()
    {
        return (Some(line), msg.to_string());
    }
    // Else the line Luau's own traceback names first (a budget error, which
    // has no location; regression: "instruction budget exceeded" at load
    // lost its line): after the last "stack traceback:", so that text the
    // script raised cannot pose as it.
    let line = text.rsplit_once("stack traceback:").and_then(|(_, tb)| {
        tb.lines().find_map(|l| {
            let at = l.find(&own)?;
            let (n, _) = l[at + own.len()..].split_once(':')?;
            n.parse::<usize>().ok()
        })
    });
    (line, first.to_string())
}

/// A declaration error from one of Luau's (a metamethod of the returned
/// table that raised one): its first line, at its own line, else at
/// `needle`'s (regression: a stack traceback and a repeated location
/// reached a one-line error).
pub(in crate::sim::runtime) fn from_lua(
    src: &ScriptSource,
    needle: Option<&str>,
    e: &mlua::Error,
) -> SimError {
    let (line, msg) = lua_text(src, e);
    match declaration(src, needle, msg) {
        SimError::Declaration {
            script,
            line: at,
            msg,
        } => SimError::Declaration {
            script,
            line: line.or(at),
            msg,
        },
        other => other,
    }
}

/// `t[field]`, read raw: a metatable's `__index` is never called, so
/// what is read is what the key checks saw (regression, review: a
/// declaration served by `__index` passed the unknown-key check unseen).
pub(super) fn field(src: &ScriptSource, t: &Table, field: &str) -> Result<Value, SimError> {
    t.raw_get(field).map_err(|e| from_lua(src, Some(field), &e))
}

/// The error of a list or map `what` past [`MAX_LIST`] entries (it is
/// refused before anything is checked for repeats).
fn too_many(src: &ScriptSource, what: &str) -> SimError {
    declaration(
        src,
        Some(what),
        format!("'{what}' has more than {MAX_LIST} entries"),
    )
}

/// Refuse table `t` (named `what`) if it has a metatable: a declaration is
/// what its tables hold, and they are read raw, so entries served by
/// `__index` were never seen (regression, fuzzing: `nonnegative =
/// setmetatable({}, { __index = { "water" } })` loaded and did nothing).
pub(in crate::sim::runtime) fn plain_table(
    src: &ScriptSource,
    t: &Table,
    what: &str,
) -> Result<(), SimError> {
    if t.metatable().is_some() {
        return Err(declaration(
            src,
            Some("setmetatable"),
            format!("'{what}' has a metatable; declarations are plain tables"),
        ));
    }
    Ok(())
}

/// The entries of list `t`, named `what` in errors: its keys must be 1 to
/// n with no gap, and n at most [`MAX_LIST`].
pub(super) fn list(src: &ScriptSource, t: &Table, what: &str) -> Result<Vec<Value>, SimError> {
    plain_table(src, t, what)?;
    let mut entries: Vec<(i64, Value)> = Vec::new();
    for pair in t.pairs::<Value, Value>() {
        let (k, v) = pair.map_err(|e| from_lua(src, Some(what), &e))?;
        let i = match k {
            Value::Integer(i) => i,
            Value::Number(n) if n.fract() == 0.0 && n.abs() < 1e15 => n as i64,
            other => {
                let key = match &other {
                    Value::String(s) => format!("the key '{}'", s.to_string_lossy()),
                    o => format!("{} key", a(o.type_name())),
                };
                return Err(declaration(
                    src,
                    Some(what),
                    format!("'{what}' must be a list, but it has {key}"),
                ));
            }
        };
        if entries.len() == MAX_LIST {
            return Err(too_many(src, what));
        }
        entries.push((i, v));
    }
    entries.sort_by_key(|e| e.0);
    for (n, (i, _)) in entries.iter().enumerate() {
        if *i != n as i64 + 1 {
            return Err(declaration(
                src,
                Some(what),
                format!(
                    "'{what}' must be a list without gaps: entry {} is missing",
                    n + 1
                ),
            ));
        }
    }
    Ok(entries.into_iter().map(|e| e.1).collect())
}

/// A string value as UTF-8 text, or an error naming `what`, at the line of
/// `needle`.
pub(super) fn text(
    src: &ScriptSource,
    v: &Value,
    what: &str,
    needle: &str,
) -> Result<String, SimError> {
    match v {
        Value::String(s) => s.to_str().map(|s| s.to_string()).map_err(|_| {
            declaration(
                src,
                Some(needle),
                format!("{what}: {:?} is not UTF-8 text", s.to_string_lossy()),
            )
        }),
        other => Err(declaration(
            src,
            Some(needle),
            format!("{what} must be a string, found {}", a(other.type_name())),
        )),
    }
}

/// The list of strings at `t[field]` (none when absent), each given once.
pub(super) fn strings(src: &ScriptSource, t: &Table, field: &str) -> Result<Vec<String>, SimError> {
    let list_t = match self::field(src, t, field)? {
        Value::Nil => return Ok(Vec::new()),
        Value::Table(l) => l,
        other => {
            return Err(declaration(
                src,
                Some(field),
                format!(
                    "'{field}' must be a list of strings, found {}",
                    a(other.type_name())
                ),
            ));
        }
    };
    let mut out = Vec::new();
    let mut seen = std::collections::HashSet::new();
    for v in list(src, &list_t, field)? {
        let s = text(src, &v, &format!("an entry of '{field}'"), field)?;
        if !seen.insert(s.clone()) {
            return Err(declaration(
                src,
                Some(&format!("\"{s}\"")),
                format!("'{field}' lists '{s}' twice"),
            ));
        }
        out.push(s);
    }
    Ok(out)
}

/// A number (never a string Luau would coerce), or an error: `what` names
/// it, and `needle` its line.
pub(super) fn number(
    src: &ScriptSource,
    v: &Value,
    what: &str,
    needle: &str,
) -> Result<f64, SimError> {
    match v {
        Value::Number(n) => Ok(*n),
        Value::Integer(n) => Ok(*n as f64),
        // A key left out reads as nil: say it is missing (modder probe:
        // "'min' must be a number, found a nil").
        Value::Nil => Err(declaration(
            src,
            Some(needle),
            format!("{what} is missing: it must be a number"),
        )),
        other => Err(declaration(
            src,
            Some(needle),
            format!("{what} must be a number, found {}", a(other.type_name())),
        )),
    }
}

/// The entries of map `t` (names to values), named `what` in errors, in
/// name order (so what is built from them needs no sort of its own): every key a UTF-8 string, at most [`MAX_LIST`] of them.
pub(super) fn map(
    src: &ScriptSource,
    t: &Table,
    what: &str,
) -> Result<Vec<(String, Value)>, SimError> {
    plain_table(src, t, what)?;
    let mut out = Vec::new();
    for pair in t.pairs::<Value, Value>() {
        let (k, v) = pair.map_err(|e| from_lua(src, Some(what), &e))?;
        if !matches!(k, Value::String(_)) {
            return Err(declaration(
                src,
                Some(what),
                format!(
                    "'{what}' maps names to values, but it has {} key",
                    a(k.type_name())
                ),
            ));
        }
        let name = text(src, &k, &format!("a key of '{what}'"), what)?;
        if out.len() == MAX_LIST {
            return Err(too_many(src, what));
        }
        out.push((name, v));
    }
    out.sort_by(|a, b| a.0.cmp(&b.0));
    Ok(out)
}
