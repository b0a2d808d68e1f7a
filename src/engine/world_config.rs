//! World configs (`worlds/*.toml`), in two stages: plain serde structs that
//! reject unknown fields, then validation into typed settings whose errors
//! name the file, the field and the reason.
//!
//! ```toml
//! [world]
//! source = "terrain"          # terrain, terrain:caves, balls, hairball, heightmap:FILE.png, vox:FILE.vox
//! size = [256, 96, 256]       # procedural sources only
//! seed = 1
//!
//! # height = 256            # instead of size: unbounded in x and z (terrain; needs [stream])
//!
//! # [stream]                 # keep only the simulated region and a window around the camera
//! # view_distance = 1024.0   # voxels from the camera to the window's edge
//! # memory_budget = "1.5GiB" # the window and its cache of generated columns (also --memory-budget)
//! # fetchers = 2             # threads generating chunk columns
//!
//! [sim]
//! dt = 0.05
//! scripts_dir = "scripts"
//! # region = { min = [0, 0], max = [512, 512] }  # columns (x, z) the column scripts run on
//! # radius = 256.0            # or: a square of this half-side around the camera's eye
//! #                          # (a streamed world needs a region: it is what stays resident)
//!
//! [[scripts]]
//! file = "water.lua"
//! every = 1                   # run every N ticks
//! params = { rain = 0.05 }
//!
//! [camera]
//! mode = "orbit"              # fixed, orbit, fly (eye to fly_to and back) or line
//! # velocity = [40.0, 0.0, 0.0]  (mode = "line": voxels per simulated second, for ever)
//! eye = [-100.0, 200.0, -100.0]
//! target = [128.0, 40.0, 128.0]
//! fov = 50.0
//! orbit_period_s = 60.0
//! # fly_to = [300.0, 150.0, 20.0]; fly_period_s = 60.0  (mode = "fly")
//!
//! [render]
//! width = 640
//! height = 360
//! tracer = "auto"             # auto (the GPU unless it is software), gpu (falls back to cpu) or cpu
//! shadows = true
//! fog = 512.0                 # distance fog extent in voxels (0: none; default: half the view distance of a streamed world, else none)
//! ao = true                   # per-voxel ambient occlusion
//! aa = 1                      # jittered samples per pixel, averaged (1..=16; 1: no anti-aliasing)
//! beam = false                # beam starts: a coarse pass per 8x8 block; the same image
//! lod = 1.0                   # level of detail: cells under this many pixels are traced whole (0: exact)
//!
//! [frames]
//! dir = "frames"              # relative to the state directory
//! every = 10                  # ticks
//! keep = 200                  # frames kept on disk; older ones are deleted
//! max_mb = 256                # and at most this many MiB of them (oldest go first)
//!
//! [checkpoint]
//! every = 500                 # ticks
//!
//! [control]
//! addr = "127.0.0.1:7878"
//!
//! [[place]]                   # boxes placed into a freshly built world
//! material = "lava_source"    # a material name (scene, simulation or materials.lua)
//! at = [100, 60, 100]
//! size = [1, 1, 1]
//! ```

use std::collections::BTreeMap;
use std::net::SocketAddr;
use std::path::{Path, PathBuf};

use glam::{DVec3, IVec3};
use serde::Deserialize;
use thiserror::Error;

use crate::scene::SceneSpec;

/// The embedded default world (`worlds/default.toml`).
pub const DEFAULT_WORLD: &str = include_str!("../../worlds/default.toml");

/// A config that could not be read or is invalid.
#[derive(Debug, Error, PartialEq)]
#[error("{file}: {field}: {reason}")]
pub struct WorldConfigError {
    /// The config file (or `<embedded default>`).
    pub file: String,
    /// The field at fault, dotted (e.g. `camera.fov`), or the line and column
    /// of a syntax error.
    pub field: String,
    /// What is wrong.
    pub reason: String,
}

#[derive(Debug, Deserialize)]
#[serde(deny_unknown_fields)]
struct RawConfig {
    world: RawWorld,
    #[serde(default)]
    sim: RawSim,
    #[serde(default)]
    scripts: Vec<RawScript>,
    camera: Option<RawCamera>,
    #[serde(default)]
    render: RawRender,
    #[serde(default)]
    frames: RawFrames,
    #[serde(default)]
    checkpoint: RawCheckpoint,
    #[serde(default)]
    control: RawControl,
    #[serde(default)]
    place: Vec<RawPlace>,
    stream: Option<RawStream>,
}

#[derive(Debug, Deserialize)]
#[serde(deny_unknown_fields)]
struct RawStream {
    view_distance: Option<f64>,
    memory_budget: Option<toml::Value>,
    fetchers: Option<i64>,
}

/// How a streamed world keeps memory bounded (`[stream]`).
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct StreamSettings {
    /// Voxels from the camera to the render window's edge.
    pub view_distance: f64,
    /// Bytes the render window and its cache may hold.
    pub memory_budget: u64,
    /// Fetcher threads.
    pub fetchers: usize,
}

/// The default memory budget of a streamed world: 1.5 GiB.
pub const DEFAULT_MEMORY_BUDGET: u64 = 3 << 29;

/// Most MiB of frames kept on disk when `frames.max_mb` is not set.
pub const DEFAULT_FRAMES_MB: f64 = 256.0;

/// Level-of-detail `C` of the daemon's frames when `render.lod` is not set
/// (see README, "Level of detail", for the measurement behind it).
pub const DEFAULT_LOD: f32 = 1.0;
/// Largest world config file.
pub const MAX_CONFIG_BYTES: u64 = 1 << 20;
/// Largest camera coordinate, in voxels: the command line's `--eye` bound.
const MAX_COORD: f64 = 1e9;

/// Parse a byte size: a number of bytes, or a number with a unit (`512MiB`,
/// `1.5GiB`, `2GB`, `800M`…).
pub fn parse_bytes(text: &str) -> Result<u64, String> {
    let t = text.trim();
    let split = t
        .find(|c: char| !(c.is_ascii_digit() || c == '.'))
        .unwrap_or(t.len());
    let (num, unit) = t.split_at(split);
    let n: f64 = num
        .parse()
        .map_err(|_| format!("'{text}' is not a size such as 1536MiB or 1.5GiB"))?;
    let mult: f64 = match unit.trim().to_ascii_lowercase().as_str() {
        "" | "b" => 1.0,
        "k" | "kb" => 1e3,
        "kib" => 1024.0,
        "m" | "mb" => 1e6,
        "mib" => 1024.0 * 1024.0,
        "g" | "gb" => 1e9,
        "gib" => 1024.0 * 1024.0 * 1024.0,
        "t" | "tb" => 1e12,
        "tib" => 1024f64.powi(4),
        u => {
            return Err(format!(
                "'{text}': unknown unit '{u}' (use B, KiB, MiB, GiB or TiB)"
            ));
        }
    };
    let v = n * mult;
    if !v.is_finite() || !(1.0..=1e15).contains(&v) {
        return Err(format!("'{text}' is outside 1 B..1 PB"));
    }
    Ok(v as u64)
}

#[derive(Debug, Deserialize)]
#[serde(deny_unknown_fields)]
struct RawPlace {
    material: String,
    at: [i64; 3],
    size: Option<[i64; 3]>,
}

/// A box of one material placed into a freshly built world.
#[derive(Clone, Debug, PartialEq)]
pub struct Placement {
    /// Material name (resolved once `materials.lua` is loaded).
    pub material: String,
    /// Lowest corner.
    pub at: IVec3,
    /// Size (at least 1 on every axis).
    pub size: IVec3,
}

#[derive(Debug, Deserialize)]
#[serde(deny_unknown_fields)]
struct RawWorld {
    source: String,
    size: Option<[i64; 3]>,
    height: Option<i64>,
    #[serde(default)]
    seed: u64,
}

#[derive(Debug, Default, Deserialize)]
#[serde(deny_unknown_fields)]
struct RawSim {
    dt: Option<f64>,
    scripts_dir: Option<String>,
    region: Option<RawRegion>,
    radius: Option<f64>,
}

#[derive(Debug, Deserialize)]
#[serde(deny_unknown_fields)]
struct RawRegion {
    min: [i64; 2],
    max: [i64; 2],
}

#[derive(Debug, Deserialize)]
#[serde(deny_unknown_fields)]
struct RawScript {
    file: String,
    every: Option<i64>,
    #[serde(default)]
    params: BTreeMap<String, f64>,
}

#[derive(Debug, Deserialize)]
#[serde(deny_unknown_fields)]
struct RawCamera {
    mode: Option<String>,
    eye: Option<[f64; 3]>,
    target: Option<[f64; 3]>,
    fov: Option<f64>,
    orbit_period_s: Option<f64>,
    fly_to: Option<[f64; 3]>,
    fly_period_s: Option<f64>,
    velocity: Option<[f64; 3]>,
}

#[derive(Debug, Default, Deserialize)]
#[serde(deny_unknown_fields)]
struct RawRender {
    width: Option<i64>,
    height: Option<i64>,
    tracer: Option<String>,
    shadows: Option<bool>,
    fog: Option<f64>,
    lod: Option<f64>,
    ao: Option<bool>,
    aa: Option<i64>,
    beam: Option<bool>,
}

#[derive(Debug, Default, Deserialize)]
#[serde(deny_unknown_fields)]
struct RawFrames {
    dir: Option<String>,
    every: Option<i64>,
    keep: Option<i64>,
    max_mb: Option<f64>,
}

#[derive(Debug, Default, Deserialize)]
#[serde(deny_unknown_fields)]
struct RawCheckpoint {
    every: Option<i64>,
}

#[derive(Debug, Default, Deserialize)]
#[serde(deny_unknown_fields)]
struct RawControl {
    addr: Option<String>,
}

/// A script to run and how.
#[derive(Clone, Debug, PartialEq)]
pub struct ScriptSettings {
    /// File name inside the scripts directory.
    pub file: String,
    /// Run every this many ticks.
    pub every: u64,
    /// Parameter values to set (validated against the script when it loads).
    pub params: BTreeMap<String, f64>,
}

/// How the camera moves.
#[derive(Clone, Copy, Debug, PartialEq)]
pub enum CameraMode {
    /// Stays put.
    Fixed,
    /// Circles the target once per period (seconds).
    Orbit {
        /// Seconds per turn.
        period_s: f64,
    },
    /// Flies from `eye` to `to` and back once per period, looking the same
    /// way (the target moves with the eye).
    Fly {
        /// Where the flight turns round.
        to: DVec3,
        /// Seconds per round trip.
        period_s: f64,
    },
    /// Flies in a straight line for ever, looking the same way.
    Line {
        /// Voxels per simulated second.
        velocity: DVec3,
    },
}

/// Where the column scripts run; outside it the world keeps its state and
/// the region's edge is a wall (nothing flows across it, so what the
/// scripts conserve stays conserved).
#[derive(Clone, Copy, Debug, PartialEq)]
pub enum SimRegion {
    /// The whole world.
    Everywhere,
    /// Columns `[min, max)` in voxels, (x, z).
    Box {
        /// First column.
        min: glam::IVec2,
        /// One past the last column.
        max: glam::IVec2,
    },
    /// Columns within this many voxels (a square) of the camera's eye.
    AroundCamera {
        /// Half the square's side, in voxels.
        radius: f64,
    },
}

/// The camera: `None` eye/target means the scene's medium default view.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct CameraSettings {
    /// Movement.
    pub mode: CameraMode,
    /// Eye, if given.
    pub eye: Option<DVec3>,
    /// Target, if given.
    pub target: Option<DVec3>,
    /// Vertical field of view, degrees.
    pub fov: f64,
}

/// A validated world config.
#[derive(Clone, Debug, PartialEq)]
pub struct WorldConfig {
    /// Where the voxels come from.
    pub source: SceneSpec,
    /// Size of procedural sources; x and z are 0 when unbounded.
    pub size: IVec3,
    /// Unbounded in x and z (`[world] height` without `size`).
    pub unbounded: bool,
    /// Streaming (`[stream]`): only the simulated region and a window
    /// around the camera are resident.
    pub stream: Option<StreamSettings>,
    /// Seed.
    pub seed: u64,
    /// Simulation time step.
    pub dt: f64,
    /// Scripts directory (relative paths resolve against the config's directory).
    pub scripts_dir: PathBuf,
    /// Where the column scripts run (`[sim] region` or `radius`).
    pub sim_region: SimRegion,
    /// Take the scripts from the binary ([`crate::sim::embedded`]) instead
    /// of `scripts_dir`: true for the embedded default world, so it runs
    /// from any directory.
    pub scripts_embedded: bool,
    /// `world.source` as written (part of the world's identity).
    pub source_text: String,
    /// A hash of the config text (checkpoints record it).
    pub config_hash: u64,
    /// Scripts in run order.
    pub scripts: Vec<ScriptSettings>,
    /// Camera.
    pub camera: CameraSettings,
    /// Frame size.
    pub width: u32,
    /// Frame size.
    pub height: u32,
    /// Where frames are traced (`auto`: the GPU unless it is a software
    /// rasterizer).
    pub tracer: crate::gpu::TracerChoice,
    /// Hard shadows.
    pub shadows: bool,
    /// Distance fog extent in voxels (0: none).
    pub fog: f32,
    /// Level of detail `C` in pixels (0: exact).
    pub lod: f32,
    /// Ambient occlusion in frames.
    pub ao: bool,
    /// Jittered anti-aliasing samples per pixel in frames (1: none).
    pub aa: u32,
    /// Beam starts in frames (the same image; off by default: on this
    /// machine they bought under 10 %).
    pub beam: bool,
    /// Frame directory, relative to the state directory.
    pub frames_dir: PathBuf,
    /// Write a frame every this many ticks.
    pub frames_every: u64,
    /// Frames kept on disk (older ones are deleted).
    pub frames_keep: usize,
    /// Most bytes of frames kept on disk; the oldest go first.
    pub frames_max_bytes: u64,
    /// Checkpoint every this many ticks.
    pub checkpoint_every: u64,
    /// Control server address.
    pub addr: SocketAddr,
    /// Boxes of material placed into a freshly built world (a lava source).
    pub place: Vec<Placement>,
}

impl WorldConfig {
    /// Read and validate a config file.
    pub fn load(path: &Path) -> Result<Self, WorldConfigError> {
        let file = path.display().to_string();
        // Only a regular file of at most 1 MiB: a FIFO or /dev/zero named as
        // the config hung or filled memory (regression).
        let text =
            crate::files::read_text(path, MAX_CONFIG_BYTES).map_err(|e| WorldConfigError {
                file: file.clone(),
                field: "(file)".into(),
                reason: match e {
                    crate::files::FileError::Io { source, .. } => format!("cannot read: {source}"),
                    e => e.to_string(),
                },
            })?;
        Self::parse(&file, &text, path.parent().unwrap_or(Path::new(".")))
    }

    /// The embedded default world, with its scripts embedded too.
    pub fn default_world() -> Self {
        let mut w = Self::parse("<embedded default>", DEFAULT_WORLD, Path::new("worlds"))
            .expect("the embedded default world is valid");
        w.scripts_embedded = true;
        w
    }

    /// The identity checkpoints record for this world.
    pub fn identity(&self) -> crate::engine::checkpoint::WorldIdentity {
        crate::engine::checkpoint::WorldIdentity {
            source: self.source_text.clone(),
            size: self.size.to_array(),
            seed: self.seed,
            config_hash: self.config_hash,
        }
    }

    /// Parse and validate config text; relative paths resolve against `base`.
    pub fn parse(file: &str, text: &str, base: &Path) -> Result<Self, WorldConfigError> {
        let err = |field: &str, reason: String| WorldConfigError {
            file: file.to_string(),
            field: field.to_string(),
            reason,
        };
        let raw: RawConfig = toml::from_str(text).map_err(|e| {
            let at = e.span().map(|s| {
                let line = text[..s.start].matches('\n').count() + 1;
                let col = s.start - text[..s.start].rfind('\n').map_or(0, |i| i + 1) + 1;
                format!("line {line}, column {col}")
            });
            err(
                &at.unwrap_or_else(|| "(syntax)".into()),
                e.message().to_string(),
            )
        })?;
        let source: SceneSpec = raw
            .world
            .source
            .parse()
            .map_err(|e: crate::scene::SceneError| err("world.source", e.to_string()))?;
        let source = match source {
            SceneSpec::Heightmap(p) if p.is_relative() => SceneSpec::Heightmap(base.join(p)),
            SceneSpec::Vox(p) if p.is_relative() => SceneSpec::Vox(base.join(p)),
            s => s,
        };
        let size = match (raw.world.size, raw.world.height) {
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
        let unbounded = size.x == 0;
        let stream = match raw.stream {
            None if unbounded => {
                return Err(err(
                    "stream",
                    "an unbounded world must stream: add a [stream] table (its defaults are fine)"
                        .into(),
                ));
            }
            None => None,
            Some(st) => {
                if !matches!(source, SceneSpec::Terrain { .. }) {
                    return Err(err(
                        "stream",
                        "only terrain and terrain:caves worlds stream; other sources are built whole"
                            .into(),
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
                            format!(
                                "{v} is not a size such as \"1.5GiB\" or a positive number of bytes"
                            ),
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
                Some(StreamSettings {
                    view_distance,
                    memory_budget,
                    fetchers: fetchers as usize,
                })
            }
        };
        let dt = raw.sim.dt.unwrap_or(0.05);
        if !(dt > 0.0 && dt <= 10.0) {
            return Err(err(
                "sim.dt",
                format!("{} is outside (0, 10]", crate::sim::fmt_num(dt)),
            ));
        }
        let scripts_dir = base.join(raw.sim.scripts_dir.unwrap_or_else(|| "scripts".into()));
        let sim_region = match (raw.sim.region, raw.sim.radius) {
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
        if stream.is_some() && sim_region == SimRegion::Everywhere {
            return Err(err(
                "sim.region",
                "a streamed world keeps only its simulated region resident: give [sim] region = { min = [x, z], max = [x, z] }, or [sim] radius to follow the camera"
                    .into(),
            ));
        }
        if let (SimRegion::Box { min, max }, false) = (sim_region, unbounded)
            && stream.is_some()
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
        let mut scripts = Vec::new();
        for (i, s) in raw.scripts.into_iter().enumerate() {
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
        let cam = raw.camera.unwrap_or(RawCamera {
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
            "orbit" => {
                let p = cam.orbit_period_s.unwrap_or(60.0);
                // At least 10 ms: a subnormal period made the camera's
                // phase infinite and no frame was drawn (regression).
                if !(0.01..=1e9).contains(&p) {
                    return Err(err(
                        "camera.orbit_period_s",
                        format!(
                            "{} must be from 0.01 to 1e9 seconds",
                            crate::sim::fmt_num(p)
                        ),
                    ));
                }
                CameraMode::Orbit { period_s: p }
            }
            "fly" => {
                let p = cam.fly_period_s.unwrap_or(60.0);
                // At least 10 ms: a subnormal period made the camera's
                // phase infinite and no frame was drawn (regression).
                if !(0.01..=1e9).contains(&p) {
                    return Err(err(
                        "camera.fly_period_s",
                        format!(
                            "{} must be from 0.01 to 1e9 seconds",
                            crate::sim::fmt_num(p)
                        ),
                    ));
                }
                let to = match cam.fly_to {
                    Some(a) if a.iter().all(|x| x.is_finite() && x.abs() <= MAX_COORD) => {
                        DVec3::from(a)
                    }
                    Some(a) => {
                        return Err(err(
                            "camera.fly_to",
                            format!("{a:?} must be finite and within ±1e9 voxels (as --eye)"),
                        ));
                    }
                    None => {
                        return Err(err("camera.fly_to", "is needed with mode = \"fly\"".into()));
                    }
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
        let vec = |v: Option<[f64; 3]>, f: &str| -> Result<Option<DVec3>, WorldConfigError> {
            match v {
                Some(a) if a.iter().all(|x| x.is_finite() && x.abs() <= MAX_COORD) => {
                    Ok(Some(DVec3::from(a)))
                }
                Some(a) => Err(err(
                    f,
                    format!("{a:?} must be finite and within ±1e9 voxels (as --eye)"),
                )),
                None => Ok(None),
            }
        };
        let (eye, target) = (
            vec(cam.eye, "camera.eye")?,
            vec(cam.target, "camera.target")?,
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
            (None, None)
                if stream.is_some() && matches!(sim_region, SimRegion::AroundCamera { .. }) =>
            {
                // The default view is the region's own: it would move with it.
                return Err(err(
                    "camera.eye",
                    "is needed when a streamed world's region follows the camera ([sim] radius)"
                        .into(),
                ));
            }
            _ => {}
        }
        let dim = |v: Option<i64>, d: i64, f: &str| -> Result<u32, WorldConfigError> {
            let v = v.unwrap_or(d);
            if !(1..=8192).contains(&v) {
                return Err(err(f, format!("{v} is outside 1..=8192")));
            }
            Ok(v as u32)
        };
        // A streamed world's window ends at the view distance: fog hides
        // the edge by default.
        let fog = match raw.render.fog {
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
        let tracer: crate::gpu::TracerChoice = raw
            .render
            .tracer
            .as_deref()
            .unwrap_or("auto")
            .parse()
            .map_err(|e| err("render.tracer", e))?;
        let every = |v: Option<i64>, d: i64, f: &str| -> Result<u64, WorldConfigError> {
            let v = v.unwrap_or(d);
            if !(1..=100_000_000).contains(&v) {
                return Err(err(f, format!("{v} is outside 1..=100000000 ticks")));
            }
            Ok(v as u64)
        };
        let addr_text = raw.control.addr.unwrap_or_else(|| "127.0.0.1:7878".into());
        let addr: SocketAddr = addr_text.parse().map_err(|_| {
            err(
                "control.addr",
                format!("'{addr_text}' is not HOST:PORT (an IP address and a port)"),
            )
        })?;
        let config_hash = crate::persist::bytes::fnv1a(text.as_bytes());
        let mut place = Vec::new();
        for (i, p) in raw.place.iter().enumerate() {
            let size = p.size.unwrap_or([1, 1, 1]);
            if size.iter().any(|v| !(1..=65536).contains(v))
                || p.at.iter().any(|v| v.abs() > 1 << 24)
            {
                return Err(err(
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
        Ok(WorldConfig {
            place,
            source_text: raw.world.source.clone(),
            config_hash,
            scripts_embedded: false,
            source,
            size,
            unbounded,
            stream,
            seed: raw.world.seed,
            dt,
            scripts_dir,
            sim_region,
            scripts,
            camera: CameraSettings {
                mode,
                eye,
                target,
                fov,
            },
            width: dim(raw.render.width, 640, "render.width")?,
            height: dim(raw.render.height, 360, "render.height")?,
            tracer,
            shadows: raw.render.shadows.unwrap_or(true),
            ao: raw.render.ao.unwrap_or(true),
            beam: raw.render.beam.unwrap_or(false),
            aa: match raw.render.aa.unwrap_or(1) {
                n @ 1..=16 => n as u32,
                n => {
                    return Err(err(
                        "render.aa",
                        format!("{n} is outside 1..=16 samples per pixel (1 is no anti-aliasing)"),
                    ));
                }
            },
            fog,
            lod: match raw.render.lod {
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
            frames_dir: PathBuf::from(raw.frames.dir.unwrap_or_else(|| "frames".into())),
            frames_every: every(raw.frames.every, 10, "frames.every")?,
            frames_keep: match raw.frames.keep.unwrap_or(200) {
                k @ 1..=1_000_000 => k as usize,
                k => return Err(err("frames.keep", format!("{k} is outside 1..=1000000"))),
            },
            frames_max_bytes: match raw.frames.max_mb.unwrap_or(DEFAULT_FRAMES_MB) {
                m if m.is_finite() && (1.0..=1_048_576.0).contains(&m) => (m * 1048576.0) as u64,
                m => {
                    return Err(err(
                        "frames.max_mb",
                        format!("{m} is outside 1..=1048576 MiB"),
                    ));
                }
            },
            checkpoint_every: every(raw.checkpoint.every, 500, "checkpoint.every")?,
            addr,
        })
    }
}
