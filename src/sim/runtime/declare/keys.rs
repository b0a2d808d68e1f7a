//! The names and keys a declaration may use: plain names for channels,
//! passes, parameters and materials, the known keys at each level of the
//! returned table (with the nearest one suggested for a typo), the keys
//! that belong to one grid only, and names given twice.

use mlua::{Table, Value};

use super::declaration;
use crate::sim::SimError;
use crate::sim::runtime::spec::ScriptSource;

/// Longest name of a pass, parameter or channel.
pub const MAX_NAME_LEN: usize = 64;

/// Whether `name` is 1 to [`MAX_NAME_LEN`] letters, digits and `_`: the
/// names of channels, passes and parameters, which reach error messages,
/// `/status`, `ctl` and URLs (regression: a pass named with a newline and a
/// terminal escape forged a line in the daemon's log).
pub fn is_plain_name(name: &str) -> bool {
    (1..=MAX_NAME_LEN).contains(&name.len())
        && name.bytes().all(|b| b.is_ascii_alphanumeric() || b == b'_')
}

/// `Err` naming `what` unless `name` [`is_plain_name`].
pub(super) fn plain(src: &ScriptSource, what: &str, name: &str) -> Result<(), SimError> {
    if is_plain_name(name) {
        Ok(())
    } else {
        Err(declaration(
            src,
            Some(name),
            format!("{what} name {name:?} must be 1 to {MAX_NAME_LEN} letters, digits and '_'"),
        ))
    }
}

/// The keys a script's returned table may hold.
pub(super) const SCRIPT_KEYS: [&str; 15] = [
    "grid",
    "channels",
    "materials",
    "only",
    "keep_awake",
    "conserved",
    "sky",
    "fills",
    "boundary",
    "drains",
    "cfl",
    "nonnegative",
    "params",
    "ranges",
    "passes",
];
/// The declarations the runtime acts on only for column scripts.
pub(super) const COLUMN_ONLY: [&str; 3] = ["boundary", "drains", "cfl"];
/// The declarations the runtime acts on only for voxel scripts.
pub(super) const VOXEL_ONLY: [&str; 5] = ["materials", "only", "keep_awake", "sky", "fills"];

/// `Err` naming the first key of `t` not in `known` (regression: a typo
/// such as `nonnegatve` loaded and silently did nothing), with the nearest
/// known key when one is close.
pub(in crate::sim::runtime) fn only_known_keys(
    src: &ScriptSource,
    t: &Table,
    what: &str,
    known: &[&str],
) -> Result<(), SimError> {
    super::read::plain_table(src, t, what)?;
    // Table order is not the file's: report the least unknown key, so the
    // message is the same on every load.
    let mut least: Option<String> = None;
    for pair in t.pairs::<Value, Value>() {
        let (k, _) = pair.map_err(|e| super::read::from_lua(src, None, &e))?;
        // Integer keys show as `[1]`; a string key written so is no
        // integer key (regression, review).
        let (name, is_known) = match &k {
            Value::String(s) => {
                let name = s.to_string_lossy();
                let is_known = known.contains(&name.as_str()) && !name.starts_with('[');
                (name, is_known)
            }
            Value::Integer(i) => {
                let name = format!("[{i}]");
                let is_known = known.contains(&name.as_str());
                (name, is_known)
            }
            Value::Number(n) => (format!("[{n}]"), false),
            other => (format!("a {} key", other.type_name()), false),
        };
        if !is_known && least.as_ref().is_none_or(|l| name < *l) {
            least = Some(name);
        }
    }
    let Some(bad) = least.as_deref() else {
        return Ok(());
    };
    // The distance costs len(bad) × len(k): a key far longer than every
    // known one is near none of them, and is not measured (regression,
    // review: a 50-million-character key took seconds outside the budget).
    let longest = known.iter().map(|k| k.len()).max().unwrap_or(0);
    // An index is near no name: `[4]` is not a typo of `[1]` (regression,
    // fuzzing: "did you mean '[1]'?" for a colour of five numbers).
    let near = (bad.len() <= longest + 2 && !bad.starts_with('['))
        .then(|| {
            known
                .iter()
                .map(|k| (strsim::damerau_levenshtein(bad, k), *k))
                .min()
        })
        .flatten()
        .filter(|(d, k)| *d <= 2.max(k.len() / 3) && *d < bad.len());
    let hint = match near {
        Some((_, k)) => format!("; did you mean '{k}'?"),
        None => format!(" (known: {})", known.join(", ")),
    };
    // At most 64 characters of it; integer keys give no line (their digits
    // are anywhere in the file).
    let shown: String = bad.chars().take(MAX_NAME_LEN).collect();
    let cut = if shown.len() < bad.len() { "…" } else { "" };
    Err(declaration(
        src,
        (!bad.starts_with('[')).then_some(shown.as_str()),
        format!("{what} has an unknown key '{shown}{cut}'{hint}"),
    ))
}
