//! The control API: what the engine shares with its control server
//! ([`Status`], the [`Command`] queue, the latest frame, the token).
//!
//! - [`server`]: the transport (hyper on a tokio thread) and its limits
//!   against hostile clients.
//! - [`routes`]: the routes, the token rule and request validation.
//!
//! Nothing a request says can crash or stall the engine: commands are
//! validated, queued (bounded) and applied by the engine loop between steps.

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
    /// Steps per second over the last second of running.
    pub steps_per_s: f64,
    /// `running`, `failing` (its last step failed) or `suspended` (it
    /// failed too many steps in a row and waits for a fix or a reload).
    pub state: String,
    /// The last error, with file and line, if the last step failed.
    pub error: Option<String>,
    /// Failed steps in a row.
    pub failures_in_a_row: u32,
    /// Parameters with their ranges.
    pub params: Vec<ParamStatus>,
    /// Milliseconds the script took in the last step.
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
    /// Last frame's render time.
    pub frame_ms: f64,
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
    Checkpoint,
    /// Set a camera.
    Camera {
        /// Eye.
        eye: [f64; 3],
        /// Target.
        target: [f64; 3],
        /// Field of view, degrees.
        fov: f64,
    },
    /// Set script parameters.
    Params {
        /// Script name.
        script: String,
        /// Name → value.
        values: Vec<(String, f64)>,
    },
}

/// State shared between the engine loop and the control server.
pub struct Shared {
    /// What `/status` shows.
    pub status: Mutex<Status>,
    /// Commands waiting for the engine loop.
    pub commands: Mutex<Vec<Command>>,
    /// The latest frame, PNG bytes.
    pub frame: Mutex<Option<Vec<u8>>>,
    /// The control token.
    pub token: String,
    /// Set to stop everything.
    pub shutdown: AtomicBool,
}

pub(crate) const VIEWER: &str = r#"<!doctype html><meta charset="utf-8"><title>brickworld</title>
<style>body{font:14px sans-serif;margin:1em;background:#eef}img{max-width:100%;border:1px solid #999}pre{background:#fff;padding:.5em}</style>
<h1>brickworld</h1><img id="f" src="/frame.png"><p>
<button onclick="post('pause')">pause</button> <button onclick="post('resume')">resume</button>
<button onclick="post('step','1')">step</button> <button onclick="post('commit')">commit</button>
token <input id="t" size="34" placeholder="from STATE/control.token"></p>
<p>camera: eye <input id="ce" size="16" placeholder="x,y,z"> target <input id="ct" size="16" placeholder="x,y,z">
fov <input id="cf" size="4" value="50"> <button onclick="cam()">set camera</button></p><pre id="s"></pre>
<script>
const t=document.getElementById('t');t.value=localStorage.getItem('bw-token')||'';
t.onchange=()=>localStorage.setItem('bw-token',t.value);
function v3(id){return document.getElementById(id).value.split(',').map(Number)}
function cam(){post('camera',JSON.stringify({eye:v3('ce'),target:v3('ct'),fov:Number(document.getElementById('cf').value)}))}
function post(p,b){fetch('/'+p,{method:'POST',headers:{Authorization:'Bearer '+t.value},body:b||''}).then(r=>r.text()).then(x=>document.getElementById('s').textContent=x)}
setInterval(()=>{fetch('/status').then(r=>r.json()).then(s=>document.getElementById('s').textContent=JSON.stringify(s,null,1));
document.getElementById('f').src='/frame.png?'+Date.now()},1000);
</script>"#;
