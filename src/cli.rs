//! Command-line surface (clap). Values stay raw strings here; [`crate::config`]
//! validates them into typed settings whose errors name the bad flag.
//!
//! The doc comments here are `--help` texts, where `[N]` means an optional
//! argument, not a link.
#![allow(rustdoc::broken_intra_doc_links)]

use std::path::PathBuf;

use clap::{Args, Parser, Subcommand};

/// brickworld: a voxel world engine on sparse 8³ bricks.
#[derive(Debug, Parser)]
#[command(name = "brickworld", version, about, propagate_version = true)]
pub struct Cli {
    /// What to do.
    #[command(subcommand)]
    pub command: Command,
}

/// Subcommands.
#[derive(Debug, Subcommand)]
pub enum Command {
    /// Build a scene and ray-trace it to a PNG (and optionally depth .npy).
    Render(RenderArgs),
    /// Run the engine: simulation, rendering, commits to the world store and the control server.
    Run(RunArgs),
    /// Write the default world and its scripts into DIR for editing
    /// (DIR/world.toml, DIR/scripts/*.lua); DIR may hold other files, but if one of these
    /// exists nothing is written (nothing is overwritten).
    Init {
        /// Directory to create or fill
        dir: PathBuf,
    },
    /// Write a world's committed state as one file (a single-file backup).
    Export {
        /// Backup file to write (replaced atomically)
        out: PathBuf,
        /// World config (default: the embedded default world)
        #[arg(long)]
        world: Option<PathBuf>,
        /// State directory of the world (the engine must be stopped)
        #[arg(long, default_value = "state")]
        state: PathBuf,
    },
    /// Load a single-file backup (or an old checkpoint) into an empty state directory.
    Import {
        /// Backup file to read
        file: PathBuf,
        /// World config the backup belongs to (default: the embedded default world)
        #[arg(long)]
        world: Option<PathBuf>,
        /// Empty state directory to fill
        #[arg(long, default_value = "state")]
        state: PathBuf,
    },
    /// Talk to a running engine: status, pause, resume, step [N], commit, param SCRIPT NAME VALUE, params [SCRIPT], log [SCRIPT], camera path.
    Ctl(CtlArgs),
    /// Run the daemon for M minutes and report memory, queues, latency and drift.
    Soak {
        /// Minutes to run (the README's figures: 20)
        #[arg(long, default_value_t = 20.0)]
        minutes: f64,
        /// Write the results as JSON here
        #[arg(long)]
        json: PathBuf,
        /// World config (default: the embedded default world)
        #[arg(long)]
        world: Option<PathBuf>,
        /// State directory for the run (new, empty, or one an earlier soak made: emptied first)
        #[arg(long, default_value = "soak-state")]
        state: PathBuf,
    },
    /// Draw a state directory's timeline as SVG charts (into STATE/charts).
    Chart {
        /// State directory of a `brickworld run`
        state: PathBuf,
    },
    /// Run Lua simulations on a scene headless, then render the result.
    Sim(SimArgs),
    /// Benchmarks.
    #[command(subcommand)]
    Bench(BenchCommand),
    /// Accuracy checks against analytic solutions and invariants.
    #[command(subcommand)]
    Verify(VerifyCommand),
}

/// Verification suites.
#[derive(Debug, Subcommand)]
pub enum VerifyCommand {
    /// The simulation scripts: Ritter dam break, lake at rest, conservation,
    /// talus angle, stability sweep, determinism; and the voxel scripts:
    /// U-tube, sand pile, lava cooling, cave fill, stability, determinism.
    Sims(VerifySimsArgs),
}

/// `brickworld verify sims`.
#[derive(Debug, Args)]
pub struct VerifySimsArgs {
    /// Write the results as JSON here
    #[arg(long)]
    pub json: PathBuf,
    /// Also draw charts into this directory
    #[arg(long)]
    pub chart: Option<PathBuf>,
    /// Steps of the conservation run (10000 for the full check)
    #[arg(long, default_value_t = 10_000)]
    pub conservation_steps: u64,
}

/// `brickworld run`.
#[derive(Debug, Args)]
pub struct RunArgs {
    /// World config (TOML); without one, the embedded default world
    pub world: Option<PathBuf>,
    /// State directory: the world store, frames, timeline, control token
    #[arg(long, default_value = "state")]
    pub state: PathBuf,
    /// Control server address HOST:PORT (overrides the config)
    #[arg(long)]
    pub addr: Option<String>,
    /// Scripts directory (overrides the config)
    #[arg(long)]
    pub scripts: Option<PathBuf>,
    /// Stop with a commit after this many ticks
    #[arg(long, conflicts_with = "until_tick")]
    pub ticks: Option<u64>,
    /// Stop with a commit once the world reaches this tick
    #[arg(long)]
    pub until_tick: Option<u64>,
    /// Start paused: the world is loaded and served, and steps only on
    /// `ctl resume` or `ctl step N`
    #[arg(long)]
    pub paused: bool,
    /// Memory budget of a streamed world (overrides [stream] memory_budget), e.g. 1.5GiB
    #[arg(long)]
    pub memory_budget: Option<String>,
}

/// `brickworld ctl`.
#[derive(Clone, Debug, Args)]
pub struct CtlArgs {
    /// Engine address HOST:PORT [default: the one the engine wrote to
    /// STATE/control.addr, else 127.0.0.1:7878]
    #[arg(long)]
    pub addr: Option<String>,
    /// State directory holding control.token
    #[arg(long, default_value = crate::engine::ctl::DEFAULT_STATE)]
    pub state: PathBuf,
    /// `log`: print the lines there are and exit, instead of following
    #[arg(long)]
    pub no_follow: bool,
    /// status | pause | resume | step [N] | commit | param SCRIPT NAME VALUE |
    /// params [SCRIPT] | log [SCRIPT] | camera path
    #[arg(required = true, num_args = 1.., allow_hyphen_values = true)]
    pub command: Vec<String>,
}

/// `brickworld sim`.
#[derive(Debug, Args)]
pub struct SimArgs {
    #[allow(missing_docs)]
    #[command(flatten)]
    pub scene: SceneArgs,
    #[allow(missing_docs)]
    #[command(flatten)]
    pub view: ViewArgs,
    /// Lua script to run (repeat for several; they run in this order each step)
    #[arg(long = "script", required = true)]
    pub scripts: Vec<PathBuf>,
    /// Steps to run
    #[arg(long, default_value = "100", allow_hyphen_values = true)]
    pub steps: String,
    /// Time step in seconds
    #[arg(long, default_value = "0.05", allow_hyphen_values = true)]
    pub dt: String,
    /// Parameter override SCRIPT.NAME=VALUE (repeatable), e.g. water.rain=0.2; NAME follows the last dot
    #[arg(long = "param")]
    pub params: Vec<String>,
    /// PNG of the final state
    #[arg(long, default_value = "sim.png")]
    pub out: PathBuf,
    /// Trace hard shadows in the final render
    #[arg(long)]
    pub shadows: bool,
    /// Watch the scripts' directories and hot-reload edited scripts between steps
    #[arg(long)]
    pub watch: bool,
    /// Keep the world's edges closed (by default water drains over them)
    #[arg(long)]
    pub closed_edges: bool,
    /// Split steps to keep water within this CFL number (0 disables sub-stepping)
    #[arg(long, default_value = "0.5", allow_hyphen_values = true)]
    pub cfl: String,
}

/// Benchmarks.
#[derive(Debug, Subcommand)]
pub enum BenchCommand {
    /// Compare the dense, svo and brickmap tracers on one scene.
    Tracers(BenchTracersArgs),
    /// Level of detail: speed against image error (FLIP) over C, against a supersampled reference
    Lod(BenchLodArgs),
    /// Column updates per second of each simulation script, Lua and native.
    Sim(BenchSimArgs),
    /// Ray-guided streaming of bricks to the GPU tracer.
    Stream(BenchStreamArgs),
    /// water3d's voxel updates per second: Lua, native and crossing cost; and what sleeping bricks cost.
    Voxels(BenchVoxelsArgs),
    /// Commit and restore costs of the chunked world store on a terrain.
    Store(BenchStoreArgs),
    /// Fly a streamed world's render window a long way: memory against the budget, slides, frames.
    Flight(BenchFlightArgs),
    /// The GPU tracer's primary rays per second (1920x1080 by default): whole frames and device time, per view, exact and with LOD.
    Gpu(BenchGpuArgs),
}

/// `brickworld bench gpu`.
#[derive(Debug, Args)]
pub struct BenchGpuArgs {
    #[allow(missing_docs)]
    #[command(flatten)]
    pub scene: SceneArgs,
    /// A streamed world's config: trace its render window at the camera's start instead of a scene (whose --size defaults to 2048x256x2048 here)
    #[arg(long, conflicts_with_all = ["size", "scene", "seed"])]
    pub world: Option<PathBuf>,
    /// Image width (1 to 8192)
    #[arg(long, default_value_t = 1920)]
    pub width: u32,
    /// Image height (1 to 8192)
    #[arg(long, default_value_t = 1080)]
    pub height: u32,
    /// Footprints C to measure besides exact tracing, comma-separated ("none": exact only)
    #[arg(
        long,
        value_name = "C,C,...",
        default_value = "1",
        allow_hyphen_values = true
    )]
    pub lod: String,
    /// Timed frames per view and setting, one by one, then back to back (at most 100 per submission); medians count (1 to 1000)
    #[arg(long, default_value_t = 20)]
    pub frames: u32,
    /// Most bricks uploaded per frame while the view converges (1 to 1048576)
    #[arg(long, default_value_t = 16_384)]
    pub uploads: u32,
    /// Untimed back-to-back tracing before each setting's timed runs, ms (0 to 60000; a run of frames started is finished)
    #[arg(long, default_value_t = 1000)]
    pub warmup_ms: u64,
    /// Samples per pixel of each view's CPU reference, against which each image's error (mean FLIP) is measured (0: no error measured; at most 256)
    #[arg(long, default_value_t = 16)]
    pub spp: u32,
    /// Write the results as JSON here
    #[arg(long)]
    pub json: PathBuf,
    /// Also draw speed against image error over C as SVG (needs --spp above 0)
    #[arg(long)]
    pub chart: Option<PathBuf>,
}

/// `brickworld bench flight`.
#[derive(Debug, Args)]
pub struct BenchFlightArgs {
    /// A streamed world's config (default: the shipped endless world)
    #[arg(long)]
    pub world: Option<PathBuf>,
    /// Write the results as JSON here
    #[arg(long)]
    pub json: PathBuf,
    /// Voxels to fly
    #[arg(long, default_value_t = 100_000.0)]
    pub distance: f64,
    /// Voxels per step
    #[arg(long, default_value_t = 32.0)]
    pub step: f64,
    /// Draw a frame every this many voxels
    #[arg(long, default_value_t = 1024.0)]
    pub frame_every: f64,
    /// Do not wait for exact columns at each step (fly as fast as the loop goes)
    #[arg(long)]
    pub no_wait: bool,
    /// Memory budget (overrides the world's), e.g. 512MiB
    #[arg(long)]
    pub memory_budget: Option<String>,
}

/// `brickworld bench voxels`.
#[derive(Debug, Args)]
pub struct BenchVoxelsArgs {
    /// Write the results as JSON here
    #[arg(long)]
    pub json: PathBuf,
    /// World size XxYxZ in voxels (X and Z multiples of 16 of at least 32, Y at least 48; the pool fills y < 40)
    #[arg(long, default_value = "256x48x256")]
    pub size: String,
    /// Timed steps per measurement
    #[arg(long, default_value_t = 10)]
    pub steps: u32,
    /// Worker threads (default: all cores)
    #[arg(long)]
    pub threads: Option<usize>,
}

/// `brickworld bench store`.
#[derive(Debug, Args)]
pub struct BenchStoreArgs {
    /// Write the results as JSON here
    #[arg(long)]
    pub json: PathBuf,
    /// Terrain size XxYxZ in voxels
    #[arg(long, default_value = "2048x256x2048")]
    pub size: String,
    /// Dirty chunks per commit
    #[arg(long, default_value_t = 1000)]
    pub chunks: usize,
    /// Commits to time
    #[arg(long, default_value_t = 3)]
    pub repeats: usize,
    /// Scratch directory for the store (new, empty, or made by an earlier run): removed afterwards (also on Ctrl-C) with any parent it made, or emptied if it was there
    #[arg(long, default_value = "bench-store")]
    pub dir: PathBuf,
}

/// `brickworld bench stream`.
#[derive(Debug, Args)]
pub struct BenchStreamArgs {
    #[allow(missing_docs)]
    #[command(flatten)]
    pub scene: SceneArgs,
    /// Image width
    #[arg(long, default_value_t = 512)]
    pub width: u32,
    /// Image height
    #[arg(long, default_value_t = 384)]
    pub height: u32,
    /// Which default view: 0 overview, 1 medium, 2 close-up
    #[arg(long, default_value_t = 1)]
    pub view: usize,
    /// Most bricks uploaded per frame
    #[arg(long, default_value_t = 256)]
    pub uploads: u32,
    /// Brick slots the GPU pool starts with (it doubles when the view needs more, up to 2^20)
    #[arg(long, default_value_t = 65_536)]
    pub pool: u32,
    /// Level of detail: bricks under C pixels wide are drawn whole and not streamed (leave out for exact)
    #[arg(long, value_name = "C", allow_hyphen_values = true)]
    pub lod: Option<f64>,
    /// Beam starts: a coarse pass per 8x8 pixel block finds where its rays may start (same image)
    #[arg(long)]
    pub beam: bool,
    /// Write the results as JSON here
    #[arg(long)]
    pub json: PathBuf,
    /// Also chart uploads per frame as SVG
    #[arg(long)]
    pub chart: Option<PathBuf>,
}

/// `brickworld bench lod`.
#[derive(Debug, Args)]
pub struct BenchLodArgs {
    #[allow(missing_docs)]
    #[command(flatten)]
    pub scene: SceneArgs,
    #[allow(missing_docs)]
    #[command(flatten)]
    pub view: ViewArgs,
    /// Footprints C to measure, in pixels, comma-separated (exact tracing is always measured too)
    #[arg(
        long,
        value_name = "C,C,...",
        default_value = "0.5,1,2,4,8",
        allow_hyphen_values = true
    )]
    pub lod: String,
    /// Jittered samples per pixel of the reference image (16 to 1024)
    #[arg(long, default_value = "16", allow_hyphen_values = true)]
    pub spp: String,
    /// Timed renders per view and C, the fastest counting (1 to 100)
    #[arg(long, default_value = "3", allow_hyphen_values = true)]
    pub repeat: String,
    /// Write the results as JSON here
    #[arg(long)]
    pub json: PathBuf,
    /// Also chart speed against image error as SVG
    #[arg(long)]
    pub chart: Option<PathBuf>,
}

/// `brickworld bench sim`.
#[derive(Debug, Args)]
pub struct BenchSimArgs {
    /// Write the results as JSON here
    #[arg(long)]
    pub json: PathBuf,
    /// World sizes in columns per side (multiples of 8 in 8..=8192)
    #[arg(long, value_delimiter = ',', default_value = "512,1024")]
    pub sizes: Vec<String>,
    /// Timed steps per measurement
    #[arg(long, default_value_t = 10)]
    pub steps: u32,
    /// Worker threads (default: all cores)
    #[arg(long)]
    pub threads: Option<usize>,
}

/// Scene selection shared by every command.
#[derive(Debug, Args, Clone)]
pub struct SceneArgs {
    /// terrain, terrain:caves, balls, hairball, heightmap:FILE.png or vox:FILE.vox
    #[arg(long, default_value = "terrain")]
    pub scene: String,
    /// Scene size XxYxZ in voxels, Y up (procedural scenes only)
    #[arg(long)]
    pub size: Option<String>,
    /// Seed for procedural scenes
    #[arg(long, default_value_t = 1)]
    pub seed: u64,
}

/// Camera and image flags shared by render and bench.
#[derive(Debug, Args, Clone)]
pub struct ViewArgs {
    /// Eye position x,y,z (world voxels); default: the scene's overview
    #[arg(long, allow_hyphen_values = true)]
    pub eye: Option<String>,
    /// Look-at point x,y,z; required with --eye
    #[arg(long, allow_hyphen_values = true)]
    pub target: Option<String>,
    /// Vertical field of view in degrees
    #[arg(long)]
    pub fov: Option<String>,
    /// Image width in pixels
    #[arg(long)]
    pub width: Option<String>,
    /// Image height in pixels
    #[arg(long)]
    pub height: Option<String>,
    /// Worker threads (default: all cores)
    #[arg(long)]
    pub threads: Option<String>,
}

/// `brickworld render`.
#[derive(Debug, Args)]
pub struct RenderArgs {
    #[allow(missing_docs)]
    #[command(flatten)]
    pub scene: SceneArgs,
    #[allow(missing_docs)]
    #[command(flatten)]
    pub view: ViewArgs,
    /// Tracer: dense, svo or brickmap
    #[arg(long, default_value = "brickmap")]
    pub structure: String,
    /// Where to trace: cpu, gpu (the brickmap on wgpu; falls back to the CPU with one line if no adapter), or auto (the GPU unless its only adapter is a software rasterizer)
    #[arg(long, default_value = "cpu")]
    pub tracer: String,
    /// Trace hard shadows towards the light
    #[arg(long)]
    pub shadows: bool,
    /// Distance fog extent in voxels: hits blend towards the sky by 1 - exp(-t / FOG) (0: none)
    #[arg(long, default_value_t = 0.0, allow_negative_numbers = true)]
    pub fog: f64,
    /// Per-voxel ambient occlusion (darkens creases and corners from the neighbouring voxels)
    #[arg(long)]
    pub ao: bool,
    /// Beam starts: a coarse pass per 8x8 pixel block finds where its rays may start (same image)
    #[arg(long)]
    pub beam: bool,
    /// Level of detail: stop at cells under C pixels wide (brickmap only; leave out for exact output)
    #[arg(long, value_name = "C", allow_hyphen_values = true)]
    pub lod: Option<f64>,
    /// Output PNG
    #[arg(long, default_value = "brickworld.png")]
    pub out: PathBuf,
    /// Also write depth as float32 .npy, shape (H, W), +inf for a miss
    #[arg(long)]
    pub depth_out: Option<PathBuf>,
    /// Largest dense grid to build, MiB
    #[arg(long, default_value_t = 8192)]
    pub dense_limit_mib: u64,
}

/// `brickworld bench tracers`.
#[derive(Debug, Args)]
pub struct BenchTracersArgs {
    #[allow(missing_docs)]
    #[command(flatten)]
    pub scene: SceneArgs,
    #[allow(missing_docs)]
    #[command(flatten)]
    pub view: ViewArgs,
    /// Write the results as JSON here
    #[arg(long)]
    pub json: PathBuf,
    /// Also draw memory against speed as SVG
    #[arg(long)]
    pub chart: Option<PathBuf>,
    /// Timed renders per view and structure; the fastest counts
    #[arg(long, default_value_t = 1)]
    pub repeat: u32,
    /// Largest dense grid to build, MiB (bigger grids report an error and the bench goes on)
    #[arg(long, default_value_t = 8192)]
    pub dense_limit_mib: u64,
}
