//! The second stage of a world config: each section's raw fields
//! ([`super::raw`]) checked and turned into typed settings. Every error
//! names the file, the field and the reason.

use std::net::SocketAddr;
use std::path::{Path, PathBuf};

use glam::{DVec3, IVec3};

use super::raw::{
    RawCamera, RawConfig, RawFrames, RawPlace, RawRender, RawScript, RawSim, RawStream, RawWorld,
};
use super::{
    CameraMode, CameraSettings, DEFAULT_FRAMES_MB, DEFAULT_LOD, DEFAULT_MEMORY_BUDGET, MAX_COORD,
    Placement, ScriptSettings, SimRegion, StreamSettings, WorldConfigError, parse_bytes,
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
    fn err(self, field: &str, reason: String) -> WorldConfigError {
        WorldConfigError {
            file: self.file.to_string(),
            field: field.to_string(),
            reason,
        }
    }
}

/// The TOML parsed into the raw structs; a syntax error names its line and
/// column.
pub(super) fn syntax(at: Fields, text: &str) -> Result<RawConfig, WorldConfigError> {
    toml::from_str(text).map_err(|e| {
        let place = e.span().map(|s| {
            let line = text[..s.start].matches('\n').count() + 1;
            let col = s.start - text[..s.start].rfind('\n').map_or(0, |i| i + 1) + 1;
            format!("line {line}, column {col}")
        });
        at.err(
            &place.unwrap_or_else(|| "(syntax)".into()),
            e.message().to_string(),
        )
    })
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

/// A camera coordinate: finite and within the command line's `--eye` bound.
fn coord(at: Fields, v: Option<[f64; 3]>, f: &str) -> Result<Option<DVec3>, WorldConfigError> {
    match v {
        Some(a) if a.iter().all(|x| x.is_finite() && x.abs() <= MAX_COORD) => {
            Ok(Some(DVec3::from(a)))
        }
        Some(a) => Err(at.err(
            f,
            format!("{a:?} must be finite and within ±1e9 voxels (as --eye)"),
        )),
        None => Ok(None),
    }
}

/// A camera period: at least 10 ms (a subnormal period made the camera's
/// phase infinite and no frame was drawn; regression).
fn period(at: Fields, p: f64, f: &str) -> Result<f64, WorldConfigError> {
    if !(0.01..=1e9).contains(&p) {
        return Err(at.err(
            f,
            format!(
                "{} must be from 0.01 to 1e9 seconds",
                crate::sim::fmt_num(p)
            ),
        ));
    }
    Ok(p)
}

/// `[camera]`: its movement, eye and target. `follows_region`: a streamed
/// world's region follows the camera, so the camera must be placed.
pub(super) fn camera(
    at: Fields,
    raw: Option<RawCamera>,
    follows_region: bool,
) -> Result<CameraSettings, WorldConfigError> {
    let err = |f: &str, r: String| at.err(f, r);
    let cam = raw.unwrap_or(RawCamera {
        mode: None,
        eye: None,
        target: None,
        fov: None,
        orbit_period_s: None,
        fly_to: None,
        fly_period_s: None,
        velocity: None,
    });
    let fov = cam.fov.unwrap_or(50.0);
    if !(fov > 0.0 && fov < 180.0) {
        return Err(err("camera.fov", format!("{fov} is outside (0, 180)")));
    }
    let mode = match cam.mode.as_deref().unwrap_or("fixed") {
        "fixed" => CameraMode::Fixed,
        "orbit" => CameraMode::Orbit {
            period_s: period(
                at,
                cam.orbit_period_s.unwrap_or(60.0),
                "camera.orbit_period_s",
            )?,
        },
        "fly" => {
            let p = period(at, cam.fly_period_s.unwrap_or(60.0), "camera.fly_period_s")?;
            let Some(to) = coord(at, cam.fly_to, "camera.fly_to")? else {
                return Err(err("camera.fly_to", "is needed with mode = \"fly\"".into()));
            };
            if cam.eye.is_none() {
                return Err(err("camera.eye", "is needed with mode = \"fly\"".into()));
            }
            CameraMode::Fly { to, period_s: p }
        }
        "line" => {
            let velocity = match cam.velocity {
                Some(a) if a.iter().all(|x| x.is_finite() && x.abs() <= 1e5) => DVec3::from(a),
                Some(a) => {
                    return Err(err(
                        "camera.velocity",
                        format!("{a:?} must be finite, at most 100000 voxels/s per axis"),
                    ));
                }
                None => {
                    return Err(err(
                        "camera.velocity",
                        "is needed with mode = \"line\"".into(),
                    ));
                }
            };
            if cam.eye.is_none() {
                return Err(err("camera.eye", "is needed with mode = \"line\"".into()));
            }
            CameraMode::Line { velocity }
        }
        other => {
            return Err(err(
                "camera.mode",
                format!("'{other}' is not fixed, orbit, fly or line"),
            ));
        }
    };
    let (eye, target) = (
        coord(at, cam.eye, "camera.eye")?,
        coord(at, cam.target, "camera.target")?,
    );
    match (eye, target) {
        (Some(e), Some(t)) if e == t => {
            return Err(err("camera.target", "equals camera.eye".into()));
        }
        (Some(e), Some(t)) if (t - e).normalize().cross(DVec3::Y).length() < 1e-9 => {
            return Err(err(
                "camera.target",
                "is straight above or below camera.eye".into(),
            ));
        }
        (Some(_), None) => {
            return Err(err("camera.target", "is needed with camera.eye".into()));
        }
        (None, Some(_)) => {
            return Err(err("camera.eye", "is needed with camera.target".into()));
        }
        (None, None) if follows_region => {
            // The default view is the region's own: it would move with it.
            return Err(err(
                "camera.eye",
                "is needed when a streamed world's region follows the camera ([sim] radius)".into(),
            ));
        }
        _ => {}
    }
    Ok(CameraSettings {
        mode,
        eye,
        target,
        fov,
    })
}

/// `[render]`, validated.
pub(super) struct Render {
    pub(super) width: u32,
    pub(super) height: u32,
    pub(super) look: super::FrameLook,
}

/// `[render]`: frame size, tracer and shading. A streamed world's window
/// ends at the view distance: fog hides the edge by default.
pub(super) fn render(
    at: Fields,
    r: &RawRender,
    stream: Option<StreamSettings>,
) -> Result<Render, WorldConfigError> {
    let err = |f: &str, r: String| at.err(f, r);
    let dim = |v: Option<i64>, d: i64, f: &str| -> Result<u32, WorldConfigError> {
        let v = v.unwrap_or(d);
        if !(1..=8192).contains(&v) {
            return Err(err(f, format!("{v} is outside 1..=8192")));
        }
        Ok(v as u32)
    };
    let fog = match r.fog {
        Some(f) if f.is_finite() && (0.0..=1e6).contains(&f) => f as f32,
        Some(f) => {
            return Err(err(
                "render.fog",
                format!(
                    "{} is outside 0..=1000000 voxels (0 is no fog)",
                    crate::sim::fmt_num(f)
                ),
            ));
        }
        None => stream.map_or(0.0, |s| (s.view_distance * 0.5) as f32),
    };
    let tracer: crate::gpu::TracerChoice = r
        .tracer
        .as_deref()
        .unwrap_or("auto")
        .parse()
        .map_err(|e| err("render.tracer", e))?;
    let width = dim(r.width, 640, "render.width")?;
    let height = dim(r.height, 360, "render.height")?;
    let look = super::FrameLook {
        tracer,
        shadows: r.shadows.unwrap_or(true),
        ao: r.ao.unwrap_or(true),
        beam: r.beam.unwrap_or(false),
        aa: match r.aa.unwrap_or(1) {
            n @ 1..=16 => n as u32,
            n => {
                return Err(err(
                    "render.aa",
                    format!("{n} is outside 1..=16 samples per pixel (1 is no anti-aliasing)"),
                ));
            }
        },
        fog,
        lod: match r.lod {
            None => DEFAULT_LOD,
            Some(0.0) => 0.0,
            Some(c) if crate::config::lod_in_range(c) => c as f32,
            Some(c) => {
                return Err(err(
                    "render.lod",
                    format!(
                        "{c} is not a cell footprint in pixels from {} to {} (0 turns level of detail off)",
                        crate::config::MIN_LOD,
                        crate::config::MAX_LOD
                    ),
                ));
            }
        },
    };
    Ok(Render {
        width,
        height,
        look,
    })
}

/// A tick interval (`frames.every`, `checkpoint.every`), `d` if not given.
pub(super) fn every(at: Fields, v: Option<i64>, d: i64, f: &str) -> Result<u64, WorldConfigError> {
    let v = v.unwrap_or(d);
    if !(1..=100_000_000).contains(&v) {
        return Err(at.err(f, format!("{v} is outside 1..=100000000 ticks")));
    }
    Ok(v as u64)
}

/// `[frames]`, validated.
pub(super) struct Frames {
    pub(super) dir: PathBuf,
    pub(super) every: u64,
    pub(super) keep: usize,
    pub(super) max_bytes: u64,
}

/// `[frames]`: where frames go, how often, and how many are kept.
pub(super) fn frames(at: Fields, f: &RawFrames) -> Result<Frames, WorldConfigError> {
    let err = |field: &str, r: String| at.err(field, r);
    Ok(Frames {
        dir: PathBuf::from(f.dir.clone().unwrap_or_else(|| "frames".into())),
        every: every(at, f.every, 10, "frames.every")?,
        keep: match f.keep.unwrap_or(200) {
            k @ 1..=1_000_000 => k as usize,
            k => return Err(err("frames.keep", format!("{k} is outside 1..=1000000"))),
        },
        max_bytes: match f.max_mb.unwrap_or(DEFAULT_FRAMES_MB) {
            m if m.is_finite() && (1.0..=1_048_576.0).contains(&m) => (m * 1048576.0) as u64,
            m => {
                return Err(err(
                    "frames.max_mb",
                    format!("{m} is outside 1..=1048576 MiB"),
                ));
            }
        },
    })
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
        if size.iter().any(|v| !(1..=65536).contains(v)) || p.at.iter().any(|v| v.abs() > 1 << 24) {
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
