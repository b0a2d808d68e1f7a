//! The parts of a declaration that are tables of their own: `boundary`,
//! `cfl`, `fills`, `params`, `ranges` and `passes`, each read strictly and
//! checked against the declared channels, materials and grid.

use mlua::{Table, Value};

use super::keys::{only_known_keys, plain};
use super::read::{field, list, map, number, strings, text};
use super::{MAX_SCRIPT_PARAMS, MAX_SCRIPT_PASSES};
use super::{a, declaration};
use crate::sim::SimError;
use crate::sim::runtime::spec::{CflSpec, Grid, MAT, ParamSpec, PassSpec, ScriptSource};

/// `name` is one of the declared `channels`, else an error saying `what`
/// named an unknown one.
pub(super) fn known(
    src: &ScriptSource,
    channels: &[String],
    name: &str,
    what: &str,
) -> Result<usize, SimError> {
    if let Some(i) = channels.iter().position(|c| c == name) {
        Ok(i)
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
}

/// `boundary`: a finite value per declared channel.
pub(super) fn parse_boundary(
    src: &ScriptSource,
    def: &Table,
    channels: &[String],
) -> Result<Vec<(String, f64)>, SimError> {
    let mut boundary = Vec::new();
    match field(src, def, "boundary")? {
        Value::Nil => {}
        Value::Table(t) => {
            for (ch, v) in map(src, &t, "boundary")? {
                known(src, channels, &ch, "'boundary'")?;
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
    Ok(boundary)
}

/// `cfl`: the depth and velocity channels and the gravity and dx parameters.
pub(super) fn parse_cfl(
    src: &ScriptSource,
    def: &Table,
    channels: &[String],
) -> Result<Option<CflSpec>, SimError> {
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
            known(src, channels, &depth, "'cfl.depth'")?;
            for v in &velocities {
                known(src, channels, v, "'cfl.velocities'")?;
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
    Ok(cfl)
}

/// `fills`: a declared channel per declared material.
pub(super) fn parse_fills(
    src: &ScriptSource,
    def: &Table,
    channels: &[String],
    materials: &[String],
) -> Result<Vec<(String, String)>, SimError> {
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
    Ok(fills)
}

/// `params`: each `{default, min, max}`, finite, ordered, bounded in number.
pub(super) fn parse_params(src: &ScriptSource, def: &Table) -> Result<Vec<ParamSpec>, SimError> {
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
    Ok(params)
}

/// `ranges`: exactly `{min, max}`, finite numbers, per declared channel.
pub(super) fn parse_ranges(
    src: &ScriptSource,
    def: &Table,
    channels: &[String],
) -> Result<Vec<(String, f64, f64)>, SimError> {
    let mut ranges = Vec::new();
    match field(src, def, "ranges")? {
        Value::Nil => {}
        Value::Table(t) => {
            for (name, v) in map(src, &t, "ranges")? {
                known(src, channels, &name, "'ranges'")?;
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
    Ok(ranges)
}

/// `passes`: named, each reading and writing declared channels (or `mat`
/// on the voxel grid), at least one, bounded in number.
pub(super) fn parse_passes(
    src: &ScriptSource,
    def: &Table,
    grid: Grid,
    channels: &[String],
) -> Result<Vec<PassSpec>, SimError> {
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
        let read_idx = reads
            .iter()
            .filter(|r| !is_mat(r))
            .map(|r| known(src, channels, r, &format!("pass '{name}' reads")))
            .collect::<Result<Vec<_>, _>>()?;
        let write_idx = writes
            .iter()
            .filter(|w| !is_mat(w))
            .map(|w| known(src, channels, w, &format!("pass '{name}' writes")))
            .collect::<Result<Vec<_>, _>>()?;
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
            read_idx,
            write_idx,
        });
    }
    if passes.is_empty() {
        return Err(declaration(
            src,
            Some("passes"),
            "the script declares no passes",
        ));
    }
    Ok(passes)
}
