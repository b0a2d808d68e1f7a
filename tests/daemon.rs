//! The engine daemon as a user runs it: the real binary on a free loopback
//! port. Status, pause and step; checkpoints on demand and on SIGTERM;
//! token rejection (401) and malformed requests (400, 404, 413); kill -9 then
//! a restart that resumes with the checkpoint's hash; a port already in use;
//! a bad world config.

use std::path::{Path, PathBuf};
use std::process::{Child, Command, Stdio};
use std::time::{Duration, Instant};

use brickworld::engine::checkpoint;
use brickworld::engine::ctl::request;

fn free_port() -> u16 {
    std::net::TcpListener::bind("127.0.0.1:0")
        .unwrap()
        .local_addr()
        .unwrap()
        .port()
}

fn setup(name: &str) -> (PathBuf, PathBuf, String) {
    let dir = std::env::temp_dir().join(format!("brickworld-daemon-{name}-{}", std::process::id()));
    let _ = std::fs::remove_dir_all(&dir);
    std::fs::create_dir_all(&dir).unwrap();
    let addr = format!("127.0.0.1:{}", free_port());
    let cfg = dir.join("world.toml");
    std::fs::write(
        &cfg,
        format!(
            "[world]\nsource = \"terrain\"\nsize = [48, 32, 48]\nseed = 3\n[sim]\ndt = 0.05\nscripts_dir = \"{}/scripts\"\n\
             [[scripts]]\nfile = \"water.lua\"\nparams = {{ rain = 0.2 }}\n[render]\nwidth = 32\nheight = 24\ntracer = \"cpu\"\n\
             [frames]\nevery = 5\n[checkpoint]\nevery = 40\n[control]\naddr = \"{addr}\"\n",
            env!("CARGO_MANIFEST_DIR")
        ),
    )
    .unwrap();
    (cfg, dir.join("state"), addr)
}

fn start(cfg: &Path, state: &Path) -> Child {
    Command::new(env!("CARGO_BIN_EXE_brickworld"))
        .arg("run")
        .arg(cfg)
        .arg("--state")
        .arg(state)
        .stdout(Stdio::null())
        .stderr(Stdio::piped())
        .spawn()
        .unwrap()
}

fn status(addr: &str) -> serde_json::Value {
    let (code, body) = request(addr, "GET", "/status", None, "").unwrap();
    assert_eq!(code, 200, "{body}");
    serde_json::from_str(&body).unwrap()
}

fn wait_ready(addr: &str) {
    let t = Instant::now();
    while t.elapsed() < Duration::from_secs(30) {
        // Ready once the engine reports its scripts (the server starts first).
        if let Ok((200, body)) = request(addr, "GET", "/status", None, "")
            && serde_json::from_str::<serde_json::Value>(&body)
                .is_ok_and(|s| s["scripts"].as_array().is_some_and(|a| !a.is_empty()))
        {
            return;
        }
        std::thread::sleep(Duration::from_millis(50));
    }
    panic!("the daemon did not answer within 30 s");
}

fn token(state: &Path) -> String {
    std::fs::read_to_string(state.join("control.token")).unwrap()
}

fn post(addr: &str, state: &Path, path: &str, body: &str) -> (u16, String) {
    request(addr, "POST", path, Some(&token(state)), body).unwrap()
}

fn stop(mut child: Child) -> std::process::Output {
    // SIGTERM: the daemon checkpoints and exits cleanly.
    let _ = Command::new("kill")
        .arg("-TERM")
        .arg(child.id().to_string())
        .status();
    let t = Instant::now();
    while t.elapsed() < Duration::from_secs(30) {
        if child.try_wait().unwrap().is_some() {
            return child.wait_with_output().unwrap();
        }
        std::thread::sleep(Duration::from_millis(50));
    }
    child.kill().unwrap();
    panic!("the daemon did not stop on SIGTERM");
}

#[test]
fn status_pause_step_and_control_errors() {
    let (cfg, state, addr) = setup("control");
    let child = start(&cfg, &state);
    wait_ready(&addr);
    let s = status(&addr);
    for k in [
        "tick",
        "paused",
        "scripts",
        "active_bricks",
        "dirty_queue",
        "frame_ms",
        "bricks_streamed",
        "last_checkpoint",
        "loaded_from",
    ] {
        assert!(s.get(k).is_some(), "missing {k} in {s}");
    }
    assert_eq!(s["scripts"][0]["name"], "water");
    // Token file is owner-only.
    #[cfg(unix)]
    {
        use std::os::unix::fs::PermissionsExt;
        assert_eq!(
            std::fs::metadata(state.join("control.token"))
                .unwrap()
                .permissions()
                .mode()
                & 0o777,
            0o600
        );
    }
    assert_eq!(request(&addr, "POST", "/pause", None, "").unwrap().0, 401);
    assert_eq!(
        request(&addr, "POST", "/pause", Some("wrong"), "")
            .unwrap()
            .0,
        401
    );
    assert_eq!(post(&addr, &state, "/pause", "").0, 200);
    std::thread::sleep(Duration::from_millis(300));
    let t0 = status(&addr)["tick"].as_u64().unwrap();
    std::thread::sleep(Duration::from_millis(300));
    assert_eq!(status(&addr)["tick"].as_u64().unwrap(), t0, "paused");
    assert_eq!(post(&addr, &state, "/step", "3").0, 200);
    std::thread::sleep(Duration::from_millis(500));
    assert_eq!(
        status(&addr)["tick"].as_u64().unwrap(),
        t0 + 3,
        "exactly three steps"
    );
    assert_eq!(post(&addr, &state, "/step", "lots").0, 400);
    assert_eq!(post(&addr, &state, "/camera", "{\"eye\": [1, 2]}").0, 400);
    assert_eq!(post(&addr, &state, "/nowhere", "").0, 404);
    assert_eq!(request(&addr, "GET", "/nowhere", None, "").unwrap().0, 404);
    assert_eq!(post(&addr, &state, "/step", &"9".repeat(70_000)).0, 413);
    assert_eq!(
        post(&addr, &state, "/scripts/water/params", "{\"rain\": 0.5}").0,
        200
    );
    assert_eq!(
        post(&addr, &state, "/scripts/water/params", "{\"rain\": 99}").0,
        200
    );
    assert_eq!(post(&addr, &state, "/step", "1").0, 200);
    std::thread::sleep(Duration::from_millis(300));
    let s = status(&addr);
    assert!(
        s["scripts"][0]["error"]
            .as_str()
            .unwrap_or("")
            .contains("outside"),
        "{s}"
    );
    assert_eq!(request(&addr, "GET", "/", None, "").unwrap().0, 200);
    assert_eq!(post(&addr, &state, "/checkpoint", "").0, 200);
    std::thread::sleep(Duration::from_millis(500));
    assert!(status(&addr)["last_checkpoint"]["hash"].is_string());
    let out = stop(child);
    assert!(
        out.status.success(),
        "{}",
        String::from_utf8_lossy(&out.stderr)
    );
}

#[test]
fn kill_dash_nine_then_restart_resumes_with_the_checkpoints_hash() {
    let (cfg, state, addr) = setup("kill");
    let mut child = start(&cfg, &state);
    wait_ready(&addr);
    // Let periodic checkpoints happen, then kill without warning.
    let t = Instant::now();
    while status(&addr)["last_checkpoint"].is_null() && t.elapsed() < Duration::from_secs(30) {
        std::thread::sleep(Duration::from_millis(50));
    }
    child.kill().unwrap();
    child.wait().unwrap();
    let newest = checkpoint::latest(&state)
        .unwrap()
        .found
        .expect("a checkpoint survived kill -9");
    let hash = format!(
        "{:#018x}",
        checkpoint::world_hash(&newest.1.store, &newest.1.channels)
    );
    let child = start(&cfg, &state);
    wait_ready(&addr);
    let s = status(&addr);
    assert_eq!(s["loaded_from"]["hash"], hash.as_str(), "{s}");
    assert_eq!(s["loaded_from"]["tick"], newest.1.tick);
    assert!(stop(child).status.success());
}

#[test]
fn a_port_in_use_and_a_bad_config_are_clear_errors() {
    let (cfg, state, old_addr) = setup("port");
    // Hold a port we own for the whole test rather than re-binding the one
    // `setup` probed: a parallel test could have been handed that port since
    // (regression: flaky `AddrInUse` panic at the holder's bind).
    let _holder = std::net::TcpListener::bind("127.0.0.1:0").unwrap();
    let addr = _holder.local_addr().unwrap().to_string();
    let text = std::fs::read_to_string(&cfg).unwrap();
    std::fs::write(&cfg, text.replace(&old_addr, &addr)).unwrap();
    let out = Command::new(env!("CARGO_BIN_EXE_brickworld"))
        .arg("run")
        .arg(&cfg)
        .arg("--state")
        .arg(&state)
        .output()
        .unwrap();
    let err = String::from_utf8_lossy(&out.stderr);
    assert!(!out.status.success());
    assert!(err.contains(&format!("cannot listen on {addr}")), "{err}");
    assert!(!err.contains("panicked"));
    std::fs::write(
        &cfg,
        "[world]\nsource = \"terrain\"\n[render]\nwidth = -4\n",
    )
    .unwrap();
    let out = Command::new(env!("CARGO_BIN_EXE_brickworld"))
        .arg("run")
        .arg(&cfg)
        .arg("--state")
        .arg(&state)
        .output()
        .unwrap();
    let err = String::from_utf8_lossy(&out.stderr);
    assert!(!out.status.success());
    assert!(err.contains("render.width"), "{err}");
}
