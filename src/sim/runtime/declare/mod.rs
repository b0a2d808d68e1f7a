//! Reading a script's returned table into a [`ScriptSpec`]: every field
//! checked, each error naming the script, the field and its line.

use mlua::{Table, Value};

use super::spec::{CflSpec, Grid, MAT, ParamSpec, PassSpec, ScriptSource, ScriptSpec};
use crate::sim::SimError;

mod keys;
pub(super) mod read;
pub(super) use keys::only_known_keys;
use keys::{COLUMN_ONLY, SCRIPT_KEYS, VOXEL_ONLY, plain};
pub use keys::{MAX_NAME_LEN, is_plain_name};
pub use read::MAX_LIST;
use read::{field, list, map, number, strings, text};

/// Line of the first occurrence of `needle` in `text` (for declaration errors).
fn line_in(text: &str, needle: &str) -> Option<usize> {
    text.lines().position(|l| l.contains(needle)).map(|i| i + 1)
}

/// The most channels one script may declare (the stored blobs' bound: a
/// chunk or column blob carries at most as many).
pub const MAX_SCRIPT_CHANNELS: usize = 256;
/// The most parameters one script may declare.
pub const MAX_SCRIPT_PARAMS: usize = 256;
/// The most passes one script may declare.
pub const MAX_SCRIPT_PASSES: usize = 256;

/// A declaration error in `src`, at the line of `needle` if given. The
/// message is cut to one readable line: names in it come from the script,
/// so control characters (a newline too) are escaped, not cut at
/// (regression, hostile probe 3: a key holding a newline ended the message
/// there, and a key holding `x.lua:42:` was taken for Luau's location).
/// Errors of Luau's go through [`read::from_lua`].
pub(super) fn declaration(
    src: &ScriptSource,
    needle: Option<&str>,
    msg: impl Into<String>,
) -> SimError {
    SimError::Declaration {
        script: src.name.clone(),
        line: needle.and_then(|n| line_in(&src.text, n)),
        msg: super::errors::one_line(&msg.into()),
    }
}

/// A Lua type name with its article ("a table", "an integer").
pub(super) fn a(type_name: &str) -> String {
    match type_name.chars().next() {
        // Not 'u': "a userdata".
        Some('a' | 'e' | 'i' | 'o') => format!("an {type_name}"),
        _ => format!("a {type_name}"),
    }
}

/// The validated declarations of the table `def` that `src` returned.
pub(super) fn parse(src: &ScriptSource, def: &Table) -> Result<ScriptSpec, SimError> {
    // A plain table: what is declared is what is there.
    if def.metatable().is_some() {
        return Err(declaration(
            src,
            Some("setmetatable"),
            "the returned table has a metatable; a declaration is a plain table",
        ));
    }
    only_known_keys(src, def, "the script's table", &SCRIPT_KEYS)?;
    // The grid first: a typo there explains the rest (regression: `grid =
    // "voxel"` was reported as declaring no channels).
    let grid = match field(src, def, "grid")? {
        Value::Nil => Grid::Columns,
        Value::String(g) if g.to_str().is_ok_and(|g| g == "columns") => Grid::Columns,
        Value::String(g) if g.to_str().is_ok_and(|g| g == "voxels") => Grid::Voxels,
        _ => {
            return Err(declaration(
                src,
                Some("grid"),
                "'grid' must be \"columns\" or \"voxels\"",
            ));
        }
    };
    let channels = strings(src, def, "channels")?;
    if channels.len() > MAX_SCRIPT_CHANNELS {
        return Err(declaration(
            src,
            Some("channels"),
            format!(
                "the script declares {} channels, more than {MAX_SCRIPT_CHANNELS}",
                channels.len()
            ),
        ));
    }
    // Names are bounded (64 plain characters) before any is compared with
    // another (regression, review: 40 KB names made the checks below cost
    // a second of Rust time per load).
    for c in &channels {
        if c == MAT && grid == Grid::Voxels {
            return Err(declaration(
                src,
                Some(c),
                "'mat' is the material buffer; name the channel otherwise",
            ));
        }
        plain(src, "channel", c)?;
    }
    if channels.is_empty() && grid == Grid::Columns {
        return Err(declaration(
            src,
            Some("channels"),
            "the script declares no channels",
        ));
    }
    // A declaration the runtime would not act on for this grid is refused,
    // not ignored (regression: `nonnegative`, `boundary` and `cfl` loaded on
    // voxel scripts and did nothing).
    let (foreign, kind): (&[&str], &str) = match grid {
        Grid::Columns => (&VOXEL_ONLY, "voxel scripts (grid = \"voxels\")"),
        Grid::Voxels => (&COLUMN_ONLY, "column scripts (grid = \"columns\")"),
    };
    for key in foreign {
        let v = field(src, def, key)?;
        // `sky = false` says nothing, on either grid.
        let says_nothing = match v {
            Value::Nil => true,
            Value::Boolean(false) => *key == "sky",
            _ => false,
        };
        if !says_nothing {
            let field = key;
            return Err(declaration(
                src,
                Some(field),
                format!("'{field}' is for {kind}"),
            ));
        }
    }
    let materials = strings(src, def, "materials")?;
    for m in &materials {
        plain(src, "material", m)?;
    }
    let only = strings(src, def, "only")?;
    let keep_awake = strings(src, def, "keep_awake")?;
    let conserved = strings(src, def, "conserved")?;
    let sky = match field(src, def, "sky")? {
        Value::Nil => false,
        Value::Boolean(b) if grid == Grid::Voxels || !b => b,
        _ => {
            return Err(declaration(
                src,
                Some("sky"),
                "'sky' is true or false, for voxel scripts",
            ));
        }
    };
    let known = |name: &str, what: &str| -> Result<(), SimError> {
        if channels.iter().any(|c| c == name) {
            Ok(())
        } else {
            Err(declaration(
                src,
                Some(&format!("\"{name}\"")),
                format!(
                    "{what} names unknown channel '{name}' (declared: {})",
                    channels.join(", ")
                ),
            ))
        }
    };
    let mut boundary = Vec::new();
    match field(src, def, "boundary")? {
        Value::Nil => {}
        Value::Table(t) => {
            for (ch, v) in map(src, &t, "boundary")? {
                known(&ch, "'boundary'")?;
                let v = number(src, &v, &format!("boundary.{ch}"), "boundary")?;
                if !v.is_finite() {
                    return Err(declaration(
                        src,
                        Some("boundary"),
                        format!("boundary.{ch} must be finite"),
                    ));
                }
                boundary.push((ch, v));
            }
        }
        _ => {
            return Err(declaration(
                src,
                Some("boundary"),
                "'boundary' must be a table",
            ));
        }
    }
    let drains = strings(src, def, "drains")?;
    for d in &drains {
        known(d, "'drains'")?;
    }
    let cfl = match field(src, def, "cfl")? {
        Value::Nil => None,
        Value::Table(t) => {
            only_known_keys(src, &t, "'cfl'", &["depth", "velocities", "gravity", "dx"])?;
            let name = |key: &str| -> Result<String, SimError> {
                text(src, &field(src, &t, key)?, &format!("cfl.{key}"), "cfl").map_err(|_| {
                    declaration(
                        src,
                        Some("cfl"),
                        "'cfl' is { depth = CHANNEL, velocities = { CHANNEL… }, gravity = PARAM, dx = PARAM }",
                    )
                })
            };
            let (depth, gravity, dx) = (name("depth")?, name("gravity")?, name("dx")?);
            let velocities = strings(src, &t, "velocities")?;
            known(&depth, "'cfl.depth'")?;
            for v in &velocities {
                known(v, "'cfl.velocities'")?;
            }
            Some(CflSpec {
                depth,
                velocities,
                gravity,
                dx,
            })
        }
        _ => return Err(declaration(src, Some("cfl"), "'cfl' must be a table")),
    };
    let mut fills = Vec::new();
    match field(src, def, "fills")? {
        Value::Nil => {}
        Value::Table(t) => {
            for (ch, m) in map(src, &t, "fills")? {
                let m = text(src, &m, &format!("fills.{ch}"), "fills")?;
                if !channels.contains(&ch) || !materials.contains(&m) {
                    return Err(declaration(
                        src,
                        Some("fills"),
                        format!(
                            "fills.{ch} = \"{m}\": the channel must be in 'channels' and the material in 'materials'"
                        ),
                    ));
                }
                fills.push((ch, m));
            }
        }
        _ => return Err(declaration(src, Some("fills"), "'fills' must be a table")),
    }
    for m in only.iter().chain(&keep_awake) {
        if !materials.contains(m) {
            return Err(declaration(
                src,
                Some(m),
                format!("material '{m}' must also be listed in 'materials'"),
            ));
        }
    }
    let nonnegative = strings(src, def, "nonnegative")?;
    for c in &nonnegative {
        known(c, "'nonnegative'")?;
    }
    for c in &conserved {
        known(c, "'conserved'")?;
    }
    let mut params = Vec::new();
    match field(src, def, "params")? {
        Value::Nil => {}
        Value::Table(t) => {
            for (name, v) in map(src, &t, "params")? {
                // Every parameter is in each `/status` and each step's
                // context: 50 000 of them slowed the engine fourfold.
                if params.len() == MAX_SCRIPT_PARAMS {
                    return Err(declaration(
                        src,
                        Some("params"),
                        format!("more than {MAX_SCRIPT_PARAMS} parameters"),
                    ));
                }
                plain(src, "parameter", &name)?;
                let Value::Table(p) = v else {
                    return Err(declaration(
                        src,
                        Some(&name),
                        format!("parameter '{name}' must be a table {{default, min, max}}"),
                    ));
                };
                only_known_keys(
                    src,
                    &p,
                    &format!("parameter '{name}'"),
                    &["default", "min", "max"],
                )?;
                let value = |key: &str| -> Result<f64, SimError> {
                    let v = field(src, &p, key)?;
                    number(src, &v, &format!("parameter '{name}': '{key}'"), &name)
                };
                let (default, min, max) = (value("default")?, value("min")?, value("max")?);
                // Ranges are finite (regression: `min = -math.huge` loaded,
                // and `/status` showed the range as `null`).
                if !(default.is_finite() && min.is_finite() && max.is_finite()) {
                    return Err(declaration(
                        src,
                        Some(&name),
                        format!(
                            "parameter '{name}': default {default}, min {min} and max {max} must be finite numbers"
                        ),
                    ));
                }
                if min > max {
                    return Err(declaration(
                        src,
                        Some(&name),
                        format!("parameter '{name}': min {min} is above max {max}"),
                    ));
                }
                if !(min..=max).contains(&default) {
                    return Err(declaration(
                        src,
                        Some(&name),
                        format!("parameter '{name}': default {default} is outside [{min}, {max}]"),
                    ));
                }
                params.push(ParamSpec {
                    name,
                    default,
                    min,
                    max,
                });
            }
        }
        other => {
            return Err(declaration(
                src,
                Some("params"),
                format!("'params' must be a table, found {}", a(other.type_name())),
            ));
        }
    }
    let mut ranges = Vec::new();
    match field(src, def, "ranges")? {
        Value::Nil => {}
        Value::Table(t) => {
            for (name, v) in map(src, &t, "ranges")? {
                known(&name, "'ranges'")?;
                let bad = || {
                    declaration(
                        src,
                        Some("ranges"),
                        format!("ranges.{name} must be {{min, max}} with min <= max, finite"),
                    )
                };
                let Value::Table(r) = v else {
                    return Err(bad());
                };
                // Exactly { min, max }, numbers (regression: extra entries
                // and numbers written as strings were taken).
                let entries = list(src, &r, &format!("ranges.{name}"))?;
                let [lo, hi] = entries.as_slice() else {
                    return Err(bad());
                };
                let (Value::Number(_) | Value::Integer(_), Value::Number(_) | Value::Integer(_)) =
                    (lo, hi)
                else {
                    return Err(bad());
                };
                let what = format!("ranges.{name}");
                let (lo, hi) = (
                    number(src, lo, &what, "ranges")?,
                    number(src, hi, &what, "ranges")?,
                );
                if !(lo.is_finite() && hi.is_finite() && lo <= hi) {
                    return Err(bad());
                }
                ranges.push((name, lo, hi));
            }
        }
        other => {
            return Err(declaration(
                src,
                Some("ranges"),
                format!("'ranges' must be a table, found {}", a(other.type_name())),
            ));
        }
    }
    let Value::Table(passes_t) = field(src, def, "passes")? else {
        return Err(declaration(
            src,
            Some("passes"),
            "the script has no 'passes' list (each pass needs a kernel)",
        ));
    };
    let passes_list = list(src, &passes_t, "passes")?;
    if passes_list.len() > MAX_SCRIPT_PASSES {
        return Err(declaration(
            src,
            Some("passes"),
            format!(
                "the script declares {} passes, more than {MAX_SCRIPT_PASSES}",
                passes_list.len()
            ),
        ));
    }
    let mut passes = Vec::new();
    for (i, p) in passes_list.into_iter().enumerate() {
        let Value::Table(p) = p else {
            return Err(declaration(
                src,
                Some("passes"),
                format!("passes[{}] must be a table", i + 1),
            ));
        };
        let name: String = match field(src, &p, "name")? {
            Value::Nil => format!("pass{}", i + 1),
            v => text(src, &v, &format!("passes[{}].name", i + 1), "name")?,
        };
        plain(src, "pass", &name)?;
        only_known_keys(
            src,
            &p,
            &format!("pass '{name}'"),
            &["name", "reads", "writes", "kernel"],
        )?;
        if passes.iter().any(|q: &PassSpec| q.name == name) {
            return Err(declaration(
                src,
                Some(&format!("\"{name}\"")),
                format!("pass name '{name}' is used twice"),
            ));
        }
        let reads = strings(src, &p, "reads")?;
        let writes = strings(src, &p, "writes")?;
        let is_mat = |c: &str| grid == Grid::Voxels && c == MAT;
        for r in reads.iter().filter(|r| !is_mat(r)) {
            known(r, &format!("pass '{name}' reads"))?;
        }
        for w in writes.iter().filter(|w| !is_mat(w)) {
            known(w, &format!("pass '{name}' writes"))?;
        }
        if writes.is_empty() {
            return Err(declaration(
                src,
                Some(&name),
                format!("pass '{name}' writes no channel"),
            ));
        }
        passes.push(PassSpec {
            name,
            reads,
            writes,
        });
    }
    if passes.is_empty() {
        return Err(declaration(
            src,
            Some("passes"),
            "the script declares no passes",
        ));
    }
    if let Some(c) = &cfl {
        for p in [&c.gravity, &c.dx] {
            if !params.iter().any(|q| &q.name == p) {
                return Err(declaration(
                    src,
                    Some("cfl"),
                    format!("cfl names parameter '{p}', which the script does not declare"),
                ));
            }
        }
    }
    Ok(ScriptSpec {
        name: src.name.clone(),
        grid,
        materials,
        only,
        keep_awake,
        conserved,
        sky,
        boundary,
        cfl,
        drains,
        fills,
        channels,
        nonnegative,
        params,
        ranges,
        passes,
    })
}
