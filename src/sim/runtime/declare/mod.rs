//! Reading a script's returned table into a [`ScriptSpec`]: every field
//! checked, each error naming the script, the field and its line.

use mlua::{Table, Value};

use super::spec::{CflSpec, Grid, MAT, ParamSpec, PassSpec, ScriptSource, ScriptSpec};
use crate::sim::SimError;

mod keys;
pub(super) use keys::only_known_keys;
use keys::{COLUMN_ONLY, SCRIPT_KEYS, VOXEL_ONLY, no_duplicates, plain};
pub use keys::{MAX_NAME_LEN, is_plain_name};

/// Line of the first occurrence of `needle` in `text` (for declaration errors).
fn line_in(text: &str, needle: &str) -> Option<usize> {
    text.lines().position(|l| l.contains(needle)).map(|i| i + 1)
}

/// The most channels one script may declare (the stored blobs' bound: a
/// chunk or column blob carries at most as many).
pub const MAX_SCRIPT_CHANNELS: usize = 256;
/// The most parameters one script may declare.
pub const MAX_SCRIPT_PARAMS: usize = 256;

/// A declaration error in `src`, at the line of `needle` if given.
///
/// `msg` may hold an error of Luau's (a metamethod of the returned table
/// that raised one): only its first line is kept, without the
/// `runtime error:` tag, and its own `NAME.lua:LINE:` becomes the line
/// (regression: a stack traceback and a repeated location reached a
/// one-line error).
pub(super) fn declaration(
    src: &ScriptSource,
    needle: Option<&str>,
    msg: impl Into<String>,
) -> SimError {
    let msg = msg.into();
    let first = msg
        .lines()
        .next()
        .unwrap_or("")
        .trim_start_matches("runtime error: ");
    let own = format!("{}.lua:", src.name);
    let (line, msg) = match first.find(&own) {
        Some(i) => (
            super::errors::line_of(&first[i..]),
            super::errors::strip_location(&first[i..]),
        ),
        None => (
            needle.and_then(|n| line_in(&src.text, n)),
            first.to_string(),
        ),
    };
    SimError::Declaration {
        script: src.name.clone(),
        line,
        // Names in it come from the script: no raw control characters.
        msg: super::log::escape_controls(&msg, false).into_owned(),
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

fn strings(src: &ScriptSource, t: &Table, field: &str) -> Result<Vec<String>, SimError> {
    let v: Value = t
        .get(field)
        .map_err(|e| declaration(src, Some(field), e.to_string()))?;
    match v {
        Value::Nil => Ok(Vec::new()),
        Value::Table(list) => {
            let mut out = Vec::new();
            for item in list.sequence_values::<Value>() {
                match item {
                    Ok(Value::String(s)) => {
                        out.push(s.to_str().map(|s| s.to_string()).unwrap_or_default())
                    }
                    Ok(other) => {
                        return Err(declaration(
                            src,
                            Some(field),
                            format!(
                                "'{field}' must list strings, found {}",
                                a(other.type_name())
                            ),
                        ));
                    }
                    Err(e) => return Err(declaration(src, Some(field), e.to_string())),
                }
            }
            Ok(out)
        }
        other => Err(declaration(
            src,
            Some(field),
            format!(
                "'{field}' must be a list of strings, found {}",
                a(other.type_name())
            ),
        )),
    }
}

fn number(src: &ScriptSource, t: &Table, field: &str, param: &str) -> Result<f64, SimError> {
    match t.get::<Value>(field) {
        Ok(Value::Number(n)) => Ok(n),
        Ok(Value::Integer(n)) => Ok(n as f64),
        Ok(other) => Err(declaration(
            src,
            Some(param),
            format!(
                "parameter '{param}': '{field}' must be a number, found {}",
                a(other.type_name())
            ),
        )),
        Err(e) => Err(declaration(src, Some(param), e.to_string())),
    }
}

/// The validated declarations of the table `def` that `src` returned.
pub(super) fn parse(src: &ScriptSource, def: &Table) -> Result<ScriptSpec, SimError> {
    only_known_keys(src, def, "the script's table", &SCRIPT_KEYS)?;
    let channels = strings(src, def, "channels")?;
    no_duplicates(src, "channel", &channels)?;
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
    let voxel_grid = matches!(def.get::<Value>("grid"), Ok(Value::String(ref g)) if g.to_str().is_ok_and(|g| g == "voxels"));
    if channels.is_empty() && !voxel_grid {
        return Err(declaration(
            src,
            Some("channels"),
            "the script declares no channels",
        ));
    }
    let grid = match def.get::<Value>("grid") {
        Ok(Value::Nil) => Grid::Columns,
        Ok(Value::String(g)) if g.to_str().is_ok_and(|g| g == "columns") => Grid::Columns,
        Ok(Value::String(g)) if g.to_str().is_ok_and(|g| g == "voxels") => Grid::Voxels,
        Err(e) => return Err(declaration(src, Some("grid"), e.to_string())),
        _ => {
            return Err(declaration(
                src,
                Some("grid"),
                "'grid' must be \"columns\" or \"voxels\"",
            ));
        }
    };
    // A declaration the runtime would not act on for this grid is refused,
    // not ignored (regression: `nonnegative`, `boundary` and `cfl` loaded on
    // voxel scripts and did nothing).
    let (foreign, kind): (&[&str], &str) = match grid {
        Grid::Columns => (&VOXEL_ONLY, "voxel scripts (grid = \"voxels\")"),
        Grid::Voxels => (&COLUMN_ONLY, "column scripts (grid = \"columns\")"),
    };
    for field in foreign {
        let v: Value = def
            .get(*field)
            .map_err(|e| declaration(src, Some(field), e.to_string()))?;
        // `sky = false` says nothing, on either grid.
        if !matches!(v, Value::Nil | Value::Boolean(false)) {
            return Err(declaration(
                src,
                Some(field),
                format!("'{field}' is for {kind}"),
            ));
        }
    }
    let materials = strings(src, def, "materials")?;
    let only = strings(src, def, "only")?;
    let keep_awake = strings(src, def, "keep_awake")?;
    let conserved = strings(src, def, "conserved")?;
    let sky = match def.get::<Value>("sky") {
        Ok(Value::Nil) => false,
        Ok(Value::Boolean(b)) if grid == Grid::Voxels || !b => b,
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
    match def.get::<Value>("boundary") {
        Ok(Value::Nil) => {}
        Ok(Value::Table(t)) => {
            for pair in t.pairs::<String, f64>() {
                let (ch, v) = pair.map_err(|e| {
                    declaration(
                        src,
                        Some("boundary"),
                        format!("'boundary' maps channel names to numbers: {e}"),
                    )
                })?;
                known(&ch, "'boundary'")?;
                if !v.is_finite() {
                    return Err(declaration(
                        src,
                        Some("boundary"),
                        format!("boundary.{ch} must be finite"),
                    ));
                }
                boundary.push((ch, v));
            }
            boundary.sort_by(|a, b| a.0.cmp(&b.0));
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
    let cfl = match def.get::<Value>("cfl") {
        Ok(Value::Nil) => None,
        Ok(Value::Table(t)) => {
            let bad = || {
                declaration(
                    src,
                    Some("cfl"),
                    "'cfl' is { depth = CHANNEL, velocities = { CHANNEL… }, gravity = PARAM, dx = PARAM }",
                )
            };
            only_known_keys(src, &t, "'cfl'", &["depth", "velocities", "gravity", "dx"])?;
            let depth: String = t.get("depth").map_err(|_| bad())?;
            let gravity: String = t.get("gravity").map_err(|_| bad())?;
            let dx: String = t.get("dx").map_err(|_| bad())?;
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
    match def.get::<Value>("fills") {
        Ok(Value::Nil) => {}
        Ok(Value::Table(t)) => {
            for pair in t.pairs::<String, String>() {
                let (ch, m) = pair.map_err(|e| {
                    declaration(
                        src,
                        Some("fills"),
                        format!("'fills' maps channel names to material names: {e}"),
                    )
                })?;
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
            fills.sort();
        }
        _ => return Err(declaration(src, Some("fills"), "'fills' must be a table")),
    }
    for m in &materials {
        plain(src, "material", m)?;
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
    let nonnegative = strings(src, def, "nonnegative")?;
    for c in &nonnegative {
        known(c, "'nonnegative'")?;
    }
    for c in &conserved {
        known(c, "'conserved'")?;
    }
    let mut params = Vec::new();
    match def.get::<Value>("params") {
        Ok(Value::Nil) => {}
        Ok(Value::Table(t)) => {
            for pair in t.pairs::<String, Value>() {
                // Every parameter is in each `/status` and each step's
                // context: 50 000 of them slowed the engine fourfold.
                if params.len() == MAX_SCRIPT_PARAMS {
                    return Err(declaration(
                        src,
                        Some("params"),
                        format!("more than {MAX_SCRIPT_PARAMS} parameters"),
                    ));
                }
                let (name, v) =
                    pair.map_err(|e| declaration(src, Some("params"), format!("params: {e}")))?;
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
                let (default, min, max) = (
                    number(src, &p, "default", &name)?,
                    number(src, &p, "min", &name)?,
                    number(src, &p, "max", &name)?,
                );
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
            params.sort_by(|a, b| a.name.cmp(&b.name));
        }
        Ok(other) => {
            return Err(declaration(
                src,
                Some("params"),
                format!("'params' must be a table, found {}", a(other.type_name())),
            ));
        }
        Err(e) => return Err(declaration(src, Some("params"), e.to_string())),
    }
    let mut ranges = Vec::new();
    match def.get::<Value>("ranges") {
        Ok(Value::Nil) => {}
        Ok(Value::Table(t)) => {
            for pair in t.pairs::<String, Value>() {
                let (name, v) =
                    pair.map_err(|e| declaration(src, Some("ranges"), format!("ranges: {e}")))?;
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
                let (lo, hi): (f64, f64) =
                    (r.get(1).map_err(|_| bad())?, r.get(2).map_err(|_| bad())?);
                if !(lo.is_finite() && hi.is_finite() && lo <= hi) {
                    return Err(bad());
                }
                ranges.push((name, lo, hi));
            }
            ranges.sort_by(|a, b| a.0.cmp(&b.0));
        }
        Ok(other) => {
            return Err(declaration(
                src,
                Some("ranges"),
                format!("'ranges' must be a table, found {}", a(other.type_name())),
            ));
        }
        Err(e) => return Err(declaration(src, Some("ranges"), e.to_string())),
    }
    let passes_v: Value = def
        .get("passes")
        .map_err(|e| declaration(src, Some("passes"), e.to_string()))?;
    let Value::Table(passes_t) = passes_v else {
        return Err(declaration(
            src,
            Some("passes"),
            "the script has no 'passes' list (each pass needs a kernel)",
        ));
    };
    let mut passes = Vec::new();
    for (i, p) in passes_t.sequence_values::<Value>().enumerate() {
        let p = p.map_err(|e| declaration(src, Some("passes"), e.to_string()))?;
        let Value::Table(p) = p else {
            return Err(declaration(
                src,
                Some("passes"),
                format!("passes[{}] must be a table", i + 1),
            ));
        };
        let name: String = match p.get::<Value>("name") {
            Ok(Value::String(s)) => s.to_str().map(|s| s.to_string()).unwrap_or_default(),
            _ => format!("pass{}", i + 1),
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
