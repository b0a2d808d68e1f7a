//! The control server: HTTP on loopback (tiny_http), one thread.
//!
//! `GET /status`, `GET /frame.png` and `GET /` (a small viewer) are open;
//! every `POST` needs `Authorization: Bearer TOKEN`. Unknown routes get 404,
//! malformed requests 400, bodies over 64 KiB 413, wrong tokens 401. Nothing
//! a request says can crash the engine: commands are queued for the engine
//! loop, which validates them.

use std::io::Read;
use std::sync::atomic::{AtomicBool, Ordering};
use std::sync::{Arc, Mutex};
use std::time::Duration;

use serde::Serialize;
use tiny_http::{Header, Method, Request, Response, Server};

/// Largest request body accepted.
pub const MAX_BODY: usize = 64 << 10;

/// One script's line in `/status`.
#[derive(Clone, Debug, Default, Serialize)]
pub struct ScriptStatus {
    /// Script name.
    pub name: String,
    /// Steps per second over the last second of running.
    pub steps_per_s: f64,
    /// The last error, with file and line, if the last step failed.
    pub error: Option<String>,
}

/// A checkpoint reference in `/status`.
#[derive(Clone, Debug, Serialize, PartialEq, Eq)]
pub struct CheckpointRef {
    /// Tick.
    pub tick: u64,
    /// World hash, hex.
    pub hash: String,
}

/// What `/status` returns.
#[derive(Clone, Debug, Default, Serialize)]
pub struct Status {
    /// Simulation tick.
    pub tick: u64,
    /// Whether paused.
    pub paused: bool,
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
    /// The last checkpoint written.
    pub last_checkpoint: Option<CheckpointRef>,
    /// The checkpoint this run resumed from.
    pub loaded_from: Option<CheckpointRef>,
    /// The last checkpoint failure (a full disk, say), if any.
    pub checkpoint_error: Option<String>,
}

/// A command for the engine loop.
#[derive(Clone, Debug, PartialEq)]
pub enum Command {
    /// Pause at the next step boundary.
    Pause,
    /// Resume.
    Resume,
    /// Run N steps (while paused).
    Step(u64),
    /// Write a checkpoint now.
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

const VIEWER: &str = r#"<!doctype html><meta charset="utf-8"><title>brickworld</title>
<style>body{font:14px sans-serif;margin:1em;background:#eef}img{max-width:100%;border:1px solid #999}pre{background:#fff;padding:.5em}</style>
<h1>brickworld</h1><img id="f" src="/frame.png"><p>
<button onclick="post('pause')">pause</button> <button onclick="post('resume')">resume</button>
<button onclick="post('step','1')">step</button> <button onclick="post('checkpoint')">checkpoint</button>
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

fn json<T: Serialize>(code: u16, v: &T) -> Response<std::io::Cursor<Vec<u8>>> {
    let body = serde_json::to_string_pretty(v).unwrap_or_else(|_| "{}".into());
    Response::from_string(body)
        .with_status_code(code)
        .with_header(Header::from_bytes("Content-Type", "application/json").expect("static header"))
}

fn error(code: u16, msg: &str) -> Response<std::io::Cursor<Vec<u8>>> {
    json(code, &serde_json::json!({ "error": msg }))
}

/// Start the server on `addr` (fails clearly if the port is taken); the
/// returned thread runs until `shared.shutdown` is set.
pub fn start(
    addr: std::net::SocketAddr,
    shared: Arc<Shared>,
) -> Result<(std::thread::JoinHandle<()>, String), String> {
    let server = Server::http(addr).map_err(|e| format!("cannot listen on {addr}: {e}"))?;
    // The address actually bound (port 0 picks a free one).
    let bound = server
        .server_addr()
        .to_ip()
        .map_or_else(|| addr.to_string(), |a| a.to_string());
    let handle = std::thread::spawn(move || {
        while !shared.shutdown.load(Ordering::Relaxed) {
            match server.recv_timeout(Duration::from_millis(100)) {
                Ok(Some(req)) => handle(req, &shared),
                Ok(None) => {}
                Err(_) => std::thread::sleep(Duration::from_millis(10)),
            }
        }
    });
    Ok((handle, bound))
}

fn handle(mut req: Request, shared: &Shared) {
    let url = req.url().split('?').next().unwrap_or("").to_string();
    let method = req.method().clone();
    let response = match (&method, url.as_str()) {
        (Method::Get, "/status") => json(200, &*shared.status.lock().expect("status lock")),
        (Method::Get, "/frame.png") => match shared.frame.lock().expect("frame lock").clone() {
            Some(png) => Response::from_data(png).with_header(
                Header::from_bytes("Content-Type", "image/png").expect("static header"),
            ),
            None => error(404, "no frame rendered yet"),
        },
        (Method::Get, "/") => Response::from_string(VIEWER).with_header(
            Header::from_bytes("Content-Type", "text/html; charset=utf-8").expect("static header"),
        ),
        (Method::Post, path) => {
            let authorized = req
                .headers()
                .iter()
                .find(|h| h.field.equiv("Authorization"))
                .is_some_and(|h| h.value.as_str() == format!("Bearer {}", shared.token));
            if !authorized {
                error(
                    401,
                    "missing or wrong token (send Authorization: Bearer TOKEN, from STATE/control.token)",
                )
            } else if req.body_length().is_some_and(|n| n > MAX_BODY) {
                error(413, "request body over 64 KiB")
            } else {
                let mut body = String::new();
                let read = req
                    .as_reader()
                    .take(MAX_BODY as u64 + 1)
                    .read_to_string(&mut body);
                if read.is_err() {
                    error(400, "the body is not UTF-8 text")
                } else if body.len() > MAX_BODY {
                    error(413, "request body over 64 KiB")
                } else {
                    match parse_command(path, &body) {
                        Ok(cmd) => {
                            shared.commands.lock().expect("command lock").push(cmd);
                            json(200, &serde_json::json!({ "ok": true }))
                        }
                        Err((code, msg)) => error(code, &msg),
                    }
                }
            }
        }
        _ => error(404, &format!("no route {method} {url}")),
    };
    let _ = req.respond(response);
}

fn parse_command(path: &str, body: &str) -> Result<Command, (u16, String)> {
    let bad = |m: String| (400u16, m);
    match path {
        "/pause" => Ok(Command::Pause),
        "/resume" => Ok(Command::Resume),
        "/checkpoint" => Ok(Command::Checkpoint),
        "/step" => {
            let t = body.trim();
            let n = if t.is_empty() {
                1
            } else {
                t.parse::<u64>()
                    .map_err(|_| bad(format!("step count '{t}' is not a whole number")))?
            };
            if !(1..=100_000).contains(&n) {
                return Err(bad(format!("step count {n} is outside 1..=100000")));
            }
            Ok(Command::Step(n))
        }
        "/camera" => {
            #[derive(serde::Deserialize)]
            #[serde(deny_unknown_fields)]
            struct Cam {
                eye: [f64; 3],
                target: [f64; 3],
                fov: Option<f64>,
            }
            let c: Cam =
                serde_json::from_str(body).map_err(|e| bad(format!("camera JSON: {e}")))?;
            let fov = c.fov.unwrap_or(50.0);
            let cam = crate::trace::Camera::new(c.eye.into(), c.target.into(), fov, 8, 8)
                .map_err(|e| bad(e.to_string()))?;
            let _ = cam;
            Ok(Command::Camera {
                eye: c.eye,
                target: c.target,
                fov,
            })
        }
        p if p.starts_with("/scripts/") && p.ends_with("/params") => {
            let script = p["/scripts/".len()..p.len() - "/params".len()].to_string();
            if script.is_empty() || script.contains('/') {
                return Err((404, format!("no route POST {p}")));
            }
            let map: std::collections::BTreeMap<String, f64> = serde_json::from_str(body)
                .map_err(|e| bad(format!("params JSON (an object of numbers): {e}")))?;
            if let Some((k, v)) = map.iter().find(|(_, v)| !v.is_finite()) {
                return Err(bad(format!("parameter {k} = {v} is not finite")));
            }
            Ok(Command::Params {
                script,
                values: map.into_iter().collect(),
            })
        }
        other => Err((404, format!("no route POST {other}"))),
    }
}
