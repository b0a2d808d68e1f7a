//! The second stage of a world config: each section's raw fields
//! ([`super::raw`]) checked and turned into typed settings; the view's
//! sections (camera, render, frames) are in [`super::view`]. Every error
//! names the file, the field and the reason.

use std::net::SocketAddr;
use std::path::Path;

use glam::IVec3;

use super::raw::{RawConfig, RawPlace, RawScript, RawSim, RawStream, RawWorld};
use super::{
    DEFAULT_MEMORY_BUDGET, Placement, ScriptSettings, SimRegion, StreamSettings, WorldConfigError,
    parse_bytes,
};
use crate::scene::SceneSpec;

/// Where errors point: the config file's name.
#[derive(Clone, Copy)]
pub(super) struct Fields<'a> {
    /// The config file (or `<embedded default>`).
    pub(super) file: &'a str,
}

impl Fields<'_> {
    /// The error for `field`.
    pub(super) fn err(self, field: &str, reason: String) -> WorldConfigError {
        WorldConfigError {
            file: self.file.to_string(),
            field: field.to_string(),
            reason,
        }
    }
}

/// The TOML parsed into the raw structs; an error names its line and
/// column, and the dotted key there when there is one (regression, hostile
/// probe: `width = "64"` said only "line 18, column 9: invalid type:
/// string "64", expected i64").
pub(super) fn syntax(at: Fields, text: &str) -> Result<RawConfig, WorldConfigError> {
    toml::from_str(text).map_err(|e| {
        let place = e.span().map(|s| {
            let start = s.start.min(text.len());
            let line = text[..start].matches('\n').count() + 1;
            let col = start - text[..start].rfind('\n').map_or(0, |i| i + 1) + 1;
            match key_at(text, line) {
                Some(key) => format!("{key} (line {line}, column {col})"),
                None => format!("line {line}, column {col}"),
            }
        });
        at.err(
            &place.unwrap_or_else(|| "(syntax)".into()),
            plain_types(e.message()),
        )
    })
}

/// The dotted key set on line `line` (1-based) of a TOML text: the last
/// table header above it (`[render]`, or `[[scripts]]` as `scripts[N]`)
/// and the line's own key, if the line is `key = …`.
fn key_at(text: &str, line: usize) -> Option<String> {
    let mut table = String::new();
    let mut counts: std::collections::HashMap<String, usize> = Default::default();
    let mut own = None;
    for (i, l) in text.lines().take(line).enumerate() {
        let l = l.trim();
        if let Some(name) = l.strip_prefix("[[").and_then(|r| r.split_once("]]")) {
            let name = name.0.trim().to_string();
            let n = counts.entry(name.clone()).or_insert(0);
            table = format!("{name}[{n}]");
            *n += 1;
        } else if let Some(name) = l.strip_prefix('[').and_then(|r| r.split_once(']')) {
            table = name.0.trim().to_string();
        } else if i + 1 == line {
            own = l
                .split_once('=')
                .map(|(k, _)| k.trim().trim_matches('"').to_string())
                .filter(|k| !k.is_empty() && !k.starts_with('#'));
        }
    }
    match (table.is_empty(), own) {
        (_, None) => None,
        (true, Some(k)) => Some(k),
        (false, Some(k)) => Some(format!("{table}.{k}")),
    }
}

/// serde's type names in words a config's author knows.
fn plain_types(message: &str) -> String {
    let mut m = message.trim_end().to_string();
    for (rust, plain) in [
        ("expected i64", "expected a whole number"),
        ("expected u64", "expected a whole number"),
        ("expected u32", "expected a whole number"),
        ("expected i32", "expected a whole number"),
        ("expected usize", "expected a whole number"),
        ("expected f64", "expected a number"),
        ("expected f32", "expected a number"),
        ("expected a boolean", "expected true or false"),
    ] {
        if m.ends_with(rust) {
            m = format!("{}{plain}", &m[..m.len() - rust.len()]);
        }
    }
    // A whole number past 64 bits is one (regression, hostile probe 2:
    // "invalid value: integer `18446744073709551615`, expected a whole
    // number").
    if let Some(rest) = m.strip_prefix("invalid value: integer `")
        && let Some((n, "expected a whole number")) = rest.split_once("`, ")
    {
        // Or below 0 for a field that takes none (review: "-1 is too large").
        m = if n.starts_with('-') {
            format!("{n} is below 0")
        } else {
            format!("{n} is too large")
        };
    }
    m
}

/// `[world]`: the source (relative files resolve against `base`) and the
/// size (x and z are 0 for an unbounded world).
pub(super) fn world(
    at: Fields,
    w: &RawWorld,
    base: &Path,
) -> Result<(SceneSpec, IVec3), WorldConfigError> {
    let err = |f: &str, r: String| at.err(f, r);
    let source: SceneSpec = w
        .source
        .parse()
        .map_err(|e: crate::scene::SceneError| err("world.source", e.to_string()))?;
    let source = match source {
        SceneSpec::Heightmap(p) if p.is_relative() => SceneSpec::Heightmap(base.join(p)),
        SceneSpec::Vox(p) if p.is_relative() => SceneSpec::Vox(base.join(p)),
        s => s,
    };
    let size = match (w.size, w.height) {
        (Some(_), Some(_)) => {
            return Err(err(
                "world.height",
                "give size (a bounded world) or height (unbounded in x and z), not both".into(),
            ));
        }
        (None, Some(h)) => {
            if !matches!(source, SceneSpec::Terrain { .. }) {
                return Err(err(
                    "world.height",
                    "only terrain and terrain:caves can be unbounded".into(),
                ));
            }
            if !(8..=4096).contains(&h) {
                return Err(err("world.height", format!("{h} is outside 8..=4096")));
            }
            IVec3::new(0, h as i32, 0)
        }
        (Some(s), None) => {
            if !source.is_procedural() {
                return Err(err(
                    "world.size",
                    "heightmap and vox sources take their size from the file".into(),
                ));
            }
            if s.iter().any(|v| *v < 8) || s[0] > 65536 || s[2] > 65536 || s[1] > 4096 {
                return Err(err(
                    "world.size",
                    format!("{s:?} is outside 8..=65536 x 8..=4096 x 8..=65536"),
                ));
            }
            IVec3::new(s[0] as i32, s[1] as i32, s[2] as i32)
        }
        (None, None) => IVec3::new(256, 96, 256),
    };
    Ok((source, size))
}

/// `[stream]`: required for an unbounded world, terrain only.
pub(super) fn stream(
    at: Fields,
    raw: Option<RawStream>,
    source: &SceneSpec,
    unbounded: bool,
) -> Result<Option<StreamSettings>, WorldConfigError> {
    let err = |f: &str, r: String| at.err(f, r);
    let st = match raw {
        None if unbounded => {
            return Err(err(
                "stream",
                "an unbounded world must stream: add a [stream] table (its defaults are fine)"
                    .into(),
            ));
        }
        None => return Ok(None),
        Some(st) => st,
    };
    if !matches!(source, SceneSpec::Terrain { .. }) {
        return Err(err(
            "stream",
            "only terrain and terrain:caves worlds stream; other sources are built whole".into(),
        ));
    }
    let view_distance = st.view_distance.unwrap_or(1024.0);
    if !(64.0..=16384.0).contains(&view_distance) {
        return Err(err(
            "stream.view_distance",
            format!("{view_distance} is outside 64..=16384 voxels"),
        ));
    }
    let memory_budget = match st.memory_budget {
        None => DEFAULT_MEMORY_BUDGET,
        Some(toml::Value::String(t)) => {
            parse_bytes(&t).map_err(|e| err("stream.memory_budget", e))?
        }
        Some(toml::Value::Integer(n)) if n > 0 => n as u64,
        Some(v) => {
            return Err(err(
                "stream.memory_budget",
                format!("{v} is not a size such as \"1.5GiB\" or a positive number of bytes"),
            ));
        }
    };
    let fetchers = st.fetchers.unwrap_or(2);
    if !(1..=16).contains(&fetchers) {
        return Err(err(
            "stream.fetchers",
            format!("{fetchers} is outside 1..=16"),
        ));
    }
    Ok(Some(StreamSettings {
        view_distance,
        memory_budget,
        fetchers: fetchers as usize,
    }))
}

/// `[sim]`: the time step and where the column scripts run.
pub(super) fn sim(
    at: Fields,
    raw: &RawSim,
    streamed: bool,
    size: IVec3,
    unbounded: bool,
) -> Result<(f64, SimRegion), WorldConfigError> {
    let err = |f: &str, r: String| at.err(f, r);
    let dt = raw.dt.unwrap_or(0.05);
    if !(dt > 0.0 && dt <= 10.0) {
        return Err(err(
            "sim.dt",
            format!("{} is outside (0, 10]", crate::sim::fmt_num(dt)),
        ));
    }
    let sim_region = match (&raw.region, raw.radius) {
        (Some(_), Some(_)) => {
            return Err(err(
                "sim.region",
                "give a region or a radius around the camera, not both".into(),
            ));
        }
        (Some(r), None) => {
            let ok = |v: i64| (-(1 << 30)..=(1 << 30)).contains(&v);
            if !r.min.iter().chain(&r.max).all(|v| ok(*v))
                || r.min[0] >= r.max[0]
                || r.min[1] >= r.max[1]
            {
                return Err(err(
                    "sim.region",
                    format!(
                        "min {:?} must be below max {:?} on both axes (x, z), within ±2^30",
                        r.min, r.max
                    ),
                ));
            }
            SimRegion::Box {
                min: glam::IVec2::new(r.min[0] as i32, r.min[1] as i32),
                max: glam::IVec2::new(r.max[0] as i32, r.max[1] as i32),
            }
        }
        (None, Some(radius)) => {
            if !(8.0..=1e6).contains(&radius) {
                return Err(err(
                    "sim.radius",
                    format!("{radius} is outside 8..=1000000 voxels"),
                ));
            }
            SimRegion::AroundCamera { radius }
        }
        (None, None) => SimRegion::Everywhere,
    };
    if streamed && sim_region == SimRegion::Everywhere {
        return Err(err(
            "sim.region",
            "a streamed world keeps only its simulated region resident: give [sim] region = { min = [x, z], max = [x, z] }, or [sim] radius to follow the camera"
                .into(),
        ));
    }
    if let (SimRegion::Box { min, max }, false) = (sim_region, unbounded)
        && streamed
        && (min.x >= size.x || min.y >= size.z || max.x <= 0 || max.y <= 0)
    {
        return Err(err(
            "sim.region",
            format!(
                "min {min} .. max {max} lies outside the world (0, 0) .. ({}, {})",
                size.x, size.z
            ),
        ));
    }
    Ok((dt, sim_region))
}

/// `[[scripts]]`: file names inside the scripts directory, each once.
pub(super) fn scripts(
    at: Fields,
    raw: Vec<RawScript>,
) -> Result<Vec<ScriptSettings>, WorldConfigError> {
    let err = |f: &str, r: String| at.err(f, r);
    let mut scripts = Vec::new();
    for (i, s) in raw.into_iter().enumerate() {
        let field = |f: &str| format!("scripts[{i}].{f}");
        if s.file.is_empty()
            || !s.file.ends_with(".lua")
            || s.file.contains('/')
            || s.file.contains('\\')
        {
            return Err(err(
                &field("file"),
                format!(
                    "'{}' must be a .lua file name inside the scripts directory",
                    s.file
                ),
            ));
        }
        // Scripts are known by name (parameters, health, status): one
        // file listed twice would be two scripts sharing one name.
        if let Some(j) = scripts
            .iter()
            .position(|o: &ScriptSettings| o.file == s.file)
        {
            return Err(err(
                &field("file"),
                format!("'{}' is already listed as scripts[{j}]", s.file),
            ));
        }
        let every = s.every.unwrap_or(1);
        if !(1..=1_000_000).contains(&every) {
            return Err(err(
                &field("every"),
                format!("{every} is outside 1..=1000000"),
            ));
        }
        if let Some((k, v)) = s.params.iter().find(|(_, v)| !v.is_finite()) {
            return Err(err(
                &field(&format!("params.{k}")),
                format!("{v} is not a finite number"),
            ));
        }
        scripts.push(ScriptSettings {
            file: s.file,
            every: every as u64,
            params: s.params,
        });
    }
    Ok(scripts)
}

/// A tick interval (`frames.every`, `checkpoint.every`), `d` if not given.
pub(super) fn every(at: Fields, v: Option<i64>, d: i64, f: &str) -> Result<u64, WorldConfigError> {
    let v = v.unwrap_or(d);
    if !(1..=100_000_000).contains(&v) {
        return Err(at.err(f, format!("{v} is outside 1..=100000000 ticks")));
    }
    Ok(v as u64)
}

/// `[control] addr`: an IP address and a port.
pub(super) fn addr(at: Fields, raw: Option<String>) -> Result<SocketAddr, WorldConfigError> {
    let text = raw.unwrap_or_else(|| "127.0.0.1:7878".into());
    text.parse().map_err(|_| {
        at.err(
            "control.addr",
            format!("'{text}' is not HOST:PORT (an IP address and a port)"),
        )
    })
}

/// `[control] hosts`: DNS names a browser may reach the control server by
/// (lower-cased). At most 64, each a valid host name.
pub(super) fn hosts(at: Fields, raw: Option<Vec<String>>) -> Result<Vec<String>, WorldConfigError> {
    let raw = raw.unwrap_or_default();
    if raw.len() > 64 {
        return Err(at.err("control.hosts", format!("{} names; at most 64", raw.len())));
    }
    raw.into_iter()
        .map(|h| {
            let name = h.trim_end_matches('.').to_ascii_lowercase();
            let label_ok = |l: &str| {
                (1..=63).contains(&l.len())
                    && l.bytes().all(|b| b.is_ascii_alphanumeric() || b == b'-')
                    && !l.starts_with('-')
                    && !l.ends_with('-')
            };
            if name.len() > 253 || !name.split('.').all(label_ok) {
                Err(at.err(
                    "control.hosts",
                    format!("{h:?} is not a host name (letters, digits, '-' and '.', no port)"),
                ))
            } else {
                Ok(name)
            }
        })
        .collect()
}

/// `[[place]]`: boxes of material placed into a freshly built world.
pub(super) fn place(at: Fields, raw: &[RawPlace]) -> Result<Vec<Placement>, WorldConfigError> {
    let mut place = Vec::new();
    for (i, p) in raw.iter().enumerate() {
        let size = p.size.unwrap_or([1, 1, 1]);
        if size.iter().any(|v| !(1..=65536).contains(v))
            || p.at.iter().any(|v| v.unsigned_abs() > 1 << 24)
        {
            return Err(at.err(
                &format!("place[{i}]"),
                format!(
                    "at {:?} size {size:?}: sizes must be 1..=65536 and positions within ±2^24",
                    p.at
                ),
            ));
        }
        place.push(Placement {
            material: p.material.clone(),
            at: IVec3::new(p.at[0] as i32, p.at[1] as i32, p.at[2] as i32),
            size: IVec3::new(size[0] as i32, size[1] as i32, size[2] as i32),
        });
    }
    Ok(place)
}
