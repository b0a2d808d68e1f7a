//! The control API: what the engine shares with its control server
//! ([`Status`], the [`Command`] queue, the latest frame, the token).
//!
//! - [`server`]: the transport (hyper on a tokio thread) and its limits
//!   against hostile clients.
//! - [`routes`]: the routes, the token rule and request validation.
//! - [`live`]: what live viewers are pushed (server-sent events), the
//!   camera lease and parameter verdicts.
//! - `viewer.html`: the viewer page, embedded in the binary.
//!
//! Nothing a request says can crash or stall the engine: commands are
//! validated, queued (bounded) and applied by the engine loop between steps.

pub mod commands;
pub mod exchange;
pub mod inflight;
pub mod live;
pub mod routes;
pub mod server;

use std::sync::Mutex;
use std::sync::atomic::AtomicBool;

use serde::Serialize;

pub use server::ControlServer;

/// Largest request body accepted.
pub const MAX_BODY: usize = 64 << 10;
/// Commands that may wait for the engine loop; more get 503.
pub const MAX_QUEUED_COMMANDS: usize = 1024;

/// One parameter of a script in `/status`.
#[derive(Clone, Debug, Default, Serialize, PartialEq)]
pub struct ParamStatus {
    /// Name.
    pub name: String,
    /// Current value.
    pub value: f64,
    /// Declared default.
    pub default: f64,
    /// Smallest allowed value.
    pub min: f64,
    /// Largest allowed value.
    pub max: f64,
}

/// One script's line in `/status`.
#[derive(Clone, Debug, Default, Serialize)]
pub struct ScriptStatus {
    /// Script name.
    pub name: String,
    /// Its runs per second over the last second of running: the engine's
    /// steps per second divided by its `every`.
    pub steps_per_s: f64,
    /// `running`, `sleeping` (it did no work for two of its intervals:
    /// nothing is awake for it), `failing` (its last step failed) or
    /// `suspended` (it failed too many steps in a row and waits for a fix or
    /// a reload).
    pub state: String,
    /// The last error, with file and line, if the last step failed.
    pub error: Option<String>,
    /// Failed steps in a row.
    pub failures_in_a_row: u32,
    /// Steps it failed since the engine started (a script failing every
    /// few ticks shows as running between its failures, and the log says
    /// that it began to fail at most once a minute).
    pub failed_steps: u64,
    /// Parameters with their ranges.
    pub params: Vec<ParamStatus>,
    /// Milliseconds the script took in its last run (kept between the runs of a script run every N ticks).
    pub ms_per_step: f64,
    /// Totals of the channels it declares `conserved`.
    pub totals: std::collections::BTreeMap<String, f64>,
    /// Its last `log(...)` lines (rate-limited), and how many were dropped.
    pub log: Vec<String>,
    /// Log lines dropped by the rate limit.
    pub log_dropped: u64,
    /// The last warning about this script (a parameter clamped on reload,
    /// a refused parameter change…).
    pub warning: Option<String>,
    /// Lines `log(...)` accepted so far: the last of [`log`](Self::log) is
    /// number `log_seq - 1` (for followers such as `ctl log`).
    pub log_seq: u64,
    /// Hot reloads of this script in this run, and the tick of the last.
    pub reloads: u64,
    /// Tick of the last hot reload (0: none).
    pub reloaded_at: u64,
}

/// The camera in `/status`.
#[derive(Clone, Debug, Default, Serialize, PartialEq)]
pub struct CameraStatus {
    /// Eye (world voxels).
    pub eye: [f64; 3],
    /// Look-at point.
    pub target: [f64; 3],
    /// Vertical field of view, degrees.
    pub fov: f64,
    /// `path` (the world's configured camera) or `set` (through `/camera`).
    pub mode: String,
    /// The viewer holding the camera lease, if one does.
    pub holder: Option<String>,
}

/// Where a run resumed from, in `/status`.
#[derive(Clone, Debug, Serialize, PartialEq, Eq)]
pub struct CheckpointRef {
    /// Tick.
    pub tick: u64,
    /// World hash (bricks, column and voxel channels), hex.
    pub hash: String,
}

/// The last commit to the world store, in `/status`.
#[derive(Clone, Debug, Serialize, PartialEq)]
pub struct CommitRef {
    /// Tick committed.
    pub tick: u64,
    /// Chunks written.
    pub chunks: usize,
    /// Chunk columns (column channels) written.
    pub columns: usize,
    /// Bytes written.
    pub bytes: usize,
    /// Time the commit took (encoding, transaction and fsync), in ms.
    pub ms: f64,
}

/// What `/status` returns.
#[derive(Clone, Debug, Default, Serialize)]
pub struct Status {
    /// Simulation tick.
    pub tick: u64,
    /// Whether paused.
    pub paused: bool,
    /// Steps asked for with `POST /step` and not yet run (0 unless paused).
    pub steps_pending: u64,
    /// Per script.
    pub scripts: Vec<ScriptStatus>,
    /// Tiles (brick columns) awake in the last step.
    pub active_bricks: usize,
    /// Dirty bricks waiting for the renderer.
    pub dirty_queue: usize,
    /// Last frame's render time; null before the first frame (it read 0,
    /// a frame that took no time).
    pub frame_ms: Option<f64>,
    /// Bricks streamed to the GPU so far.
    pub bricks_streamed: u64,
    /// Frames drawn by the render thread so far.
    pub frames: u64,
    /// Frames skipped because the renderer was still busy with the last.
    pub frames_skipped: u64,
    /// Time the engine loop spent copying the world for the last frame job.
    pub snapshot_ms: f64,
    /// The last commit to the world store.
    pub last_commit: Option<CommitRef>,
    /// The committed state this run resumed from.
    pub loaded_from: Option<CheckpointRef>,
    /// The last commit failure (a full disk, say), if any; cleared by the
    /// next commit that succeeds. Nothing committed before it is lost.
    pub commit_error: Option<String>,
    /// Why the render thread stopped, if it did (a bug): frames are no
    /// longer drawn, and the simulation goes on.
    pub render_error: Option<String>,
    /// Set when `materials.lua` changed on disk while the engine ran: what
    /// was applied (new materials, recoloured ones), or why the file was
    /// refused.
    pub materials_note: Option<String>,
    /// Chunks and chunk columns changed since the last commit.
    pub dirty_chunks: usize,
    /// The world store's size on disk, in bytes.
    pub store_bytes: u64,
    /// The columns the column scripts ran on in the last step, `[x0, z0,
    /// x1, z1)` in voxels (a streamed world's simulated region); null for
    /// the whole world.
    pub sim_region: Option<[i32; 4]>,
    /// Times a streamed world's simulated region moved after the camera in
    /// this run, and the milliseconds the last move took (commit and
    /// rebuild); null when it does not follow the camera.
    pub region_moves: Option<(u64, f64)>,
    /// A streamed world's render window after the last frame (null for a
    /// world that is resident whole).
    pub window: Option<crate::scene::WindowStats>,
    /// A streamed world's memory budget in bytes.
    pub memory_budget: Option<u64>,
    /// The engine process's resident memory (Linux; 0 elsewhere).
    pub rss_bytes: u64,
    /// The most resident memory the engine process has held since it
    /// started (the kernel's high-water mark, `VmHWM`; Linux, 0
    /// elsewhere): unlike `rss_bytes`, which is sampled once a tick, it
    /// includes the peak inside a long step.
    pub rss_peak_bytes: u64,
    /// The camera of the next frame.
    pub camera: CameraStatus,
}

/// A command for the engine loop.
#[derive(Clone, Debug, PartialEq)]
pub enum Command {
    /// Pause at the next step boundary.
    Pause,
    /// Resume.
    Resume,
    /// Run N steps, then stay paused (pauses first if running).
    Step(u64),
    /// Commit what changed to the world store now.
    Checkpoint {
        /// Where the engine says whether the commit was written.
        verdict: exchange::VerdictSlot,
    },
    /// Go back to the world's configured camera (path).
    CameraPath {
        /// The viewer asking (held to the camera lease); None: `ctl` or
        /// another administrative call, which always wins.
        viewer: Option<String>,
    },
    /// Set a camera.
    Camera {
        /// Eye.
        eye: [f64; 3],
        /// Target.
        target: [f64; 3],
        /// Field of view, degrees.
        fov: f64,
        /// The viewer that moved it (the lease holder), if a viewer did.
        viewer: Option<String>,
    },
    /// Set script parameters.
    Params {
        /// Script name.
        script: String,
        /// Name → value.
        values: Vec<(String, f64)>,
        /// Where the engine says whether it applied them.
        verdict: exchange::VerdictSlot,
    },
}

/// State shared between the engine loop and the control server.
pub struct Shared {
    /// What `/status` shows.
    pub status: Mutex<Status>,
    /// Commands waiting for the engine loop.
    pub commands: Mutex<Vec<Command>>,
    /// The latest frame, PNG bytes, shared (reference-counted) by every
    /// response that sends it: a slow client pins a reference, not a copy
    /// (regression, memory probe: 500 slow clients of a 1080p frame held
    /// 575 MB of copies).
    pub frame: Mutex<Option<bytes::Bytes>>,
    /// The control token.
    pub token: String,
    /// Host names requests may name besides IPs and `localhost`
    /// (`[control] hosts`, lower-cased).
    pub hosts: Vec<String>,
    /// Set to stop everything.
    pub shutdown: AtomicBool,
    /// Set once the world is loaded and its status published: until then
    /// `/status` and commands get 503 (there is no state to show or to
    /// check a command against).
    pub started: AtomicBool,
    /// The latest rendered frame, for live viewers.
    pub frame_events: tokio::sync::watch::Sender<live::FrameEvent>,
    /// The timeline's last rows, for the viewer's charts.
    pub timeline: Mutex<exchange::TimelineRing>,
    /// Which viewer holds the camera.
    pub camera_lease: Mutex<exchange::CameraLease>,
    /// Slots for live viewers' event streams.
    pub viewers: std::sync::Arc<live::Viewers>,
    /// Bytes of built responses (the timeline's) still being sent.
    pub in_flight: std::sync::Arc<inflight::InFlight>,
}

impl Shared {
    /// Shared state for an engine whose control token is `token`, served
    /// to requests whose `Host` is an IP address, `localhost` or one of
    /// `hosts`.
    pub fn new(token: String, hosts: Vec<String>) -> Self {
        Shared {
            status: Mutex::new(Status::default()),
            commands: Mutex::new(Vec::new()),
            frame: Mutex::new(None),
            token,
            hosts,
            shutdown: AtomicBool::new(false),
            started: AtomicBool::new(false),
            frame_events: tokio::sync::watch::Sender::new(live::FrameEvent::default()),
            timeline: Mutex::new(exchange::TimelineRing::default()),
            camera_lease: Mutex::new(exchange::CameraLease::default()),
            viewers: std::sync::Arc::new(live::Viewers::default()),
            in_flight: std::sync::Arc::new(inflight::InFlight::default()),
        }
    }
}

/// The viewer page (HTML, CSS and script in one file, no external assets).
pub(crate) const VIEWER: &str = include_str!("viewer.html");
