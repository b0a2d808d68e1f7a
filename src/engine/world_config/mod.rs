//! World configs (`worlds/*.toml`), in two stages: plain serde structs that
//! reject unknown fields (`raw.rs`), then validation, a stage per section
//! (`validate.rs`; the camera, render and frames sections in `view.rs`), into the typed settings here, whose errors name the file,
//! the field and the reason.
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
//! hosts = []                  # host names browsers may use besides IPs and localhost
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
use thiserror::Error;

mod raw;
mod validate;
mod view;

use crate::scene::SceneSpec;

/// The embedded default world (`worlds/default.toml`).
pub const DEFAULT_WORLD: &str = include_str!("../../../worlds/default.toml");

/// A config that could not be read or is invalid.
#[derive(Debug, Error, PartialEq)]
#[error("{}: {}{}", shown(file), if field.is_empty() { String::new() } else { format!("{}: ", shown(field)) }, shown(reason))]
pub struct WorldConfigError {
    /// The config file (or `<embedded default>`).
    pub file: String,
    /// The field at fault, dotted (e.g. `camera.fov`), or the line and column
    /// of a syntax error; empty when the file itself is at fault.
    pub field: String,
    /// What is wrong.
    pub reason: String,
}

/// Text from a config as an error shows it: control characters escaped
/// and at most [`SHOWN_CHARS`] characters (regression, fuzzing: a NUL in
/// a key was printed raw, and a 100 000-character tracer name made a
/// 100 KB line).
fn shown(text: &str) -> String {
    crate::text::shown(text, SHOWN_CHARS)
}

/// Characters of a config error's field and reason that are shown.
const SHOWN_CHARS: usize = 300;

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
    /// The config's file as its errors name it (`<embedded default>` for
    /// the built-in world): errors found only when the world starts name
    /// it too.
    pub file: String,
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
    /// How frames are drawn (the rest of `[render]`).
    pub look: FrameLook,
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
    /// Host names (besides IP addresses and `localhost`) that requests may
    /// name in their `Host` header; see [`crate::engine::control::routes::host_allowed`].
    pub hosts: Vec<String>,
    /// Boxes of material placed into a freshly built world (a lava source).
    pub place: Vec<Placement>,
}

/// How the daemon draws its frames: `[render]` less the frame size. The
/// config holds it and the render thread takes it as is, so a setting
/// is declared once.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct FrameLook {
    /// Where frames are traced (`auto`: the GPU unless it is a software
    /// rasterizer).
    pub tracer: crate::gpu::TracerChoice,
    /// Hard shadows.
    pub shadows: bool,
    /// Distance fog extent in voxels (0: none).
    pub fog: f32,
    /// Level of detail `C` in pixels (0: exact).
    pub lod: f32,
    /// Ambient occlusion.
    pub ao: bool,
    /// Jittered anti-aliasing samples per pixel (1: none).
    pub aa: u32,
    /// Beam starts (the same image; off by default: on this machine they
    /// bought under 10 %).
    pub beam: bool,
}

impl FrameLook {
    /// The tracer options of one sample (anti-aliasing jitters them).
    pub fn options(&self) -> crate::trace::RenderOptions {
        crate::trace::RenderOptions {
            shadows: self.shadows,
            fog: self.fog,
            lod: self.lod,
            ao: self.ao,
            beam: self.beam,
            ..Default::default()
        }
    }
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
                // The file itself is at fault: no field, and its path said
                // once (regression, hostile probe: "d: (file): d is not a
                // regular file").
                field: String::new(),
                reason: match e {
                    crate::files::FileError::Io { error, .. } => format!("cannot read: {error}"),
                    crate::files::FileError::NotAFile { .. } if path.is_dir() => {
                        "is a folder: name the world's .toml file".into()
                    }
                    crate::files::FileError::NotAFile { .. } => {
                        "is not a regular file: name the world's .toml file".into()
                    }
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
    /// Each section is validated by its own stage (`validate.rs`), in the
    /// order the file reads.
    pub fn parse(file: &str, text: &str, base: &Path) -> Result<Self, WorldConfigError> {
        let at = validate::Fields { file };
        let raw = validate::syntax(at, text)?;
        let (source, size) = validate::world(at, &raw.world, base)?;
        let unbounded = size.x == 0;
        let stream = validate::stream(at, raw.stream, &source, unbounded)?;
        let (dt, sim_region) = validate::sim(at, &raw.sim, stream.is_some(), size, unbounded)?;
        let scripts = validate::scripts(at, raw.scripts)?;
        let camera = view::camera(
            at,
            raw.camera,
            stream.is_some() && matches!(sim_region, SimRegion::AroundCamera { .. }),
        )?;
        let render = view::render(at, &raw.render, stream)?;
        let frames = view::frames(at, &raw.frames)?;
        let checkpoint_every = validate::every(at, raw.checkpoint.every, 500, "checkpoint.every")?;
        let addr = validate::addr(at, raw.control.addr)?;
        let hosts = validate::hosts(at, raw.control.hosts)?;
        let place = validate::place(at, &raw.place)?;
        Ok(WorldConfig {
            file: crate::text::shown(file, 200),
            place,
            source_text: raw.world.source,
            config_hash: crate::persist::bytes::fnv1a(text.as_bytes()),
            scripts_embedded: false,
            source,
            size,
            unbounded,
            stream,
            seed: raw.world.seed,
            dt,
            scripts_dir: base.join(raw.sim.scripts_dir.unwrap_or_else(|| "scripts".into())),
            sim_region,
            scripts,
            camera,
            width: render.width,
            height: render.height,
            look: render.look,
            frames_dir: frames.dir,
            frames_every: frames.every,
            frames_keep: frames.keep,
            frames_max_bytes: frames.max_bytes,
            checkpoint_every,
            addr,
            hosts,
        })
    }
}
