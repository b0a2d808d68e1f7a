//! The engine daemon as a user runs it: the real binary on a free loopback
//! port. Status, pause and step; checkpoints on demand and on SIGTERM;
//! token rejection (401) and malformed requests (400, 404, 413); kill -9 then
//! a restart that resumes from the last commit, repeated at random moments
//! and in the middle of commits, ending bit-identical to a run that never
//! stopped; hot reload of a
//! changed and of a broken script; a port already in use; a bad world config.

use std::path::Path;
use std::process::{Command, Stdio};
use std::time::{Duration, Instant};

use brickworld::engine::ctl::request;

mod common;
use common::cli::assert_success;

use common::daemon::*;

#[test]
fn status_pause_step_and_control_errors() {
    let (_scratch, cfg, state, addr) = setup("control");
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
        "frames",
        "frames_skipped",
        "snapshot_ms",
        "last_commit",
        "loaded_from",
        "commit_error",
        "render_error",
        "dirty_chunks",
        "store_bytes",
    ] {
        assert!(s.get(k).is_some(), "missing {k} in {s}");
    }
    assert_eq!(s["scripts"][0]["name"], "water");
    // No frame time before a frame: null, never a 0 ms frame (a frame may
    // end between the two reads, so only one way round).
    assert!(
        s["frame_ms"].is_null()
            || (s["frame_ms"].as_f64().unwrap() > 0.0 && s["frames"].as_u64().unwrap() > 0),
        "{s}"
    );
    status_matches_the_readme(&s);
    // The resident memory's high-water mark is read after the tick's
    // sample, and never falls, so it is at least that sample.
    #[cfg(target_os = "linux")]
    {
        let (rss, peak) = (
            s["rss_bytes"].as_u64().unwrap(),
            s["rss_peak_bytes"].as_u64().unwrap(),
        );
        assert!(rss > 0 && peak >= rss, "{s}");
    }
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
    // An empty body is one step, and `step` pauses a running engine.
    assert_eq!(post(&addr, &state, "/resume", "").0, 200);
    assert_eq!(post(&addr, &state, "/step", "").0, 200);
    std::thread::sleep(Duration::from_millis(500));
    let t1 = status(&addr)["tick"].as_u64().unwrap();
    assert_eq!(status(&addr)["paused"], true);
    std::thread::sleep(Duration::from_millis(300));
    assert_eq!(
        status(&addr)["tick"].as_u64().unwrap(),
        t1,
        "step paused the engine"
    );
    assert!(t1 > t0 + 3, "the resume ran steps");
    assert_eq!(post(&addr, &state, "/step", "lots").0, 400);
    assert_eq!(post(&addr, &state, "/camera", "{\"eye\": [1, 2]}").0, 400);
    let cam = "{\"eye\": [-20, 60, -20], \"target\": [24, 10, 24], \"fov\": 45}";
    assert_eq!(post(&addr, &state, "/camera", cam).0, 200);
    let (code, page) = request(&addr, "GET", "/", None, "").unwrap();
    assert_eq!(code, 200);
    for control in [
        "frame.png",
        "pause",
        "resume",
        "step",
        "/camera",
        "/events",
        "/scripts/",
    ] {
        assert!(page.contains(control), "the viewer lacks {control}");
    }
    assert_eq!(post(&addr, &state, "/nowhere", "").0, 404);
    assert_eq!(request(&addr, "GET", "/nowhere", None, "").unwrap().0, 404);
    // A known route with the wrong method is 405, not 404 (regression).
    let (code, body) = request(&addr, "GET", "/pause", None, "").unwrap();
    assert_eq!(code, 405, "{body}");
    assert!(body.contains("use POST"), "{body}");
    let (code, body) = post(&addr, &state, "/status", "");
    assert_eq!(code, 405, "{body}");
    assert!(body.contains("use GET"), "{body}");
    // HEAD answers as GET does, without the body, on every GET route but
    // the event stream, which it does not open.
    let head = |path: &str| -> String {
        use std::io::{Read, Write};
        let mut s = std::net::TcpStream::connect(&addr).unwrap();
        s.set_read_timeout(Some(Duration::from_secs(10))).unwrap();
        s.write_all(
            format!("HEAD {path} HTTP/1.1\r\nHost: localhost\r\nConnection: close\r\n\r\n")
                .as_bytes(),
        )
        .unwrap();
        let mut got = String::new();
        s.read_to_string(&mut got).unwrap();
        got
    };
    let deadline = Instant::now() + Duration::from_secs(60);
    while request(&addr, "GET", "/frame.png", None, "").unwrap().0 != 200 {
        assert!(Instant::now() < deadline, "no frame within 60 s");
        std::thread::sleep(Duration::from_millis(100));
    }
    for path in ["/status", "/", "/timeline", "/frame.png"] {
        let got = head(path);
        assert!(got.starts_with("HTTP/1.1 200"), "HEAD {path}: {got}");
        assert!(got.ends_with("\r\n\r\n"), "HEAD {path} sent a body: {got}");
    }
    let got = head("/events");
    assert!(got.starts_with("HTTP/1.1 405"), "HEAD /events: {got}");
    // The body limit is 64 KiB exactly: 65 536 bytes are read (and
    // refused as a step count out of range), one more is 413 unread.
    assert_eq!(post(&addr, &state, "/step", &"9".repeat(65_536)).0, 400);
    assert_eq!(post(&addr, &state, "/step", &"9".repeat(65_537)).0, 413);
    // A tiny value is logged in exponent form (regression, hostile probe:
    // 1e-320 took about 330 digits), then the one checked below.
    assert_eq!(
        post(&addr, &state, "/scripts/water/params", "{\"rain\": 1e-320}").0,
        200
    );
    assert_eq!(
        post(&addr, &state, "/scripts/water/params", "{\"rain\": 0.5}").0,
        200
    );
    // Refused values are refused at once (400, with the range), not
    // accepted and reported later.
    let (code, body) = post(&addr, &state, "/scripts/water/params", "{\"rain\": 99}");
    assert_eq!(code, 400, "{body}");
    assert!(body.contains("outside [0, 10]"), "{body}");
    assert_eq!(request(&addr, "GET", "/", None, "").unwrap().0, 200);
    // 200 means written: the answer waits for the commit.
    let (code, body) = post(&addr, &state, "/commit", "");
    assert_eq!(code, 200, "{body}");
    let v: serde_json::Value = serde_json::from_str(&body).unwrap();
    assert_eq!(v["applied"], true, "{body}");
    std::thread::sleep(Duration::from_millis(500));
    let c = &status(&addr)["last_commit"];
    assert!(c["tick"].is_u64() && c["ms"].is_f64(), "{c}");
    // The old name still commits.
    assert_eq!(post(&addr, &state, "/checkpoint", "").0, 200);
    let out = stop(child);
    assert_success(&out);
    // The change is logged with its tick; the refused one is not
    // (researcher probe: parameter changes were recorded nowhere).
    let log = String::from_utf8_lossy(&out.stderr);
    let line = log
        .lines()
        .find(|l| l.contains("water.rain = 0.5 (was "))
        .unwrap_or_else(|| panic!("no line for the change: {log}"));
    assert!(line.starts_with("tick "), "{line}");
    assert!(line.ends_with("(was 1e-320)"), "{line}");
    assert!(!log.contains("water.rain = 99"), "{log}");
}

#[test]
fn kill_dash_nine_then_restart_resumes_from_the_last_commit() {
    let (_scratch, cfg, state, addr) = setup("kill");
    let mut child = start(&cfg, &state);
    wait_ready(&addr);
    // Let periodic commits happen, then kill without warning.
    let t = Instant::now();
    while status(&addr)["last_commit"].is_null() && t.elapsed() < Duration::from_secs(30) {
        std::thread::sleep(Duration::from_millis(50));
    }
    let seen = status(&addr)["last_commit"]["tick"].as_u64().unwrap();
    child.kill().unwrap();
    child.wait().unwrap();
    let tick = stored_tick(&cfg, &state).expect("a commit survived kill -9");
    assert!(
        tick >= seen,
        "committed tick {seen} was lost (store has {tick})"
    );
    let child = start(&cfg, &state);
    wait_ready(&addr);
    let s = status(&addr);
    assert_eq!(s["loaded_from"]["tick"], tick, "{s}");
    assert!(s["loaded_from"]["hash"].is_string(), "{s}");
    assert!(stop(child).status.success());
}

/// A camera set through `/camera` is committed with the state: a
/// simulation region that follows the camera follows it after a resume too
/// (regression: the resume went back to the configured camera, so it
/// simulated other tiles than a run that never stopped; found by review).
#[test]
fn a_camera_set_through_the_api_survives_a_resume() {
    let (_scratch, cfg, state, addr) = setup("camera-resume");
    edit_config(&cfg, "[sim]\n", "[sim]\nradius = 12.0\n");
    let child = start(&cfg, &state);
    wait_ready(&addr);
    let region = |addr: &str| {
        let t = Instant::now();
        while status(addr)["sim_region"].is_null() && t.elapsed() < Duration::from_secs(20) {
            std::thread::sleep(Duration::from_millis(50));
        }
        status(addr)["sim_region"].clone()
    };
    let before = region(&addr);
    assert!(!before.is_null());
    let cam = "{\"eye\": [40, 30, 40], \"target\": [20, 5, 20], \"fov\": 45}";
    assert_eq!(post(&addr, &state, "/camera", cam).0, 200);
    let t = Instant::now();
    let moved = loop {
        let r = status(&addr)["sim_region"].clone();
        if r != before || t.elapsed() > Duration::from_secs(20) {
            break r;
        }
        std::thread::sleep(Duration::from_millis(50));
    };
    assert_ne!(moved, before, "the region follows the camera");
    assert!(stop(child).status.success());
    let child = start(&cfg, &state);
    wait_ready(&addr);
    assert_eq!(region(&addr), moved, "the region after the resume");
    assert!(stop(child).status.success());
}

#[test]
fn a_port_in_use_and_a_bad_config_are_clear_errors() {
    let (_scratch, cfg, state, old_addr) = setup("port");
    // Hold a port we own for the whole test rather than re-binding the one
    // `setup` probed: a parallel test could have been handed that port since
    // (regression: flaky `AddrInUse` panic at the holder's bind).
    let _holder = std::net::TcpListener::bind("127.0.0.1:0").unwrap();
    let addr = _holder.local_addr().unwrap().to_string();
    edit_config(&cfg, &old_addr, &addr);
    let out = run_cmd(&cfg, &state).output().unwrap();
    let err = String::from_utf8_lossy(&out.stderr);
    assert!(!out.status.success());
    assert!(
        err.contains(&format!(
            "world.toml: control.addr (or --addr): cannot listen on {addr}"
        )),
        "{err}"
    );
    common::cli::assert_no_panic(&err, "the engine");
    std::fs::write(
        &cfg,
        "[world]\nsource = \"terrain\"\n[render]\nwidth = -4\n",
    )
    .unwrap();
    let out = run_cmd(&cfg, &state).output().unwrap();
    let err = String::from_utf8_lossy(&out.stderr);
    assert!(!out.status.success());
    assert!(err.contains("render.width"), "{err}");
}

/// Every key `/status` sends is in the README's schema, and every key the
/// README lists for a script is sent (a script's `totals` are keyed by
/// channel names, which the schema writes as `CHANNEL`).
fn status_matches_the_readme(s: &serde_json::Value) {
    let readme =
        std::fs::read_to_string(concat!(env!("CARGO_MANIFEST_DIR"), "/README.md")).unwrap();
    let line = readme
        .lines()
        .find(|l| l.starts_with("| `GET /status` |"))
        .expect("the README documents /status");
    let documented: std::collections::BTreeSet<&str> = line.split('"').skip(1).step_by(2).collect();
    fn keys<'a>(v: &'a serde_json::Value, out: &mut Vec<&'a str>) {
        match v {
            serde_json::Value::Object(m) => {
                for (k, x) in m {
                    out.push(k);
                    if k != "totals" {
                        keys(x, out);
                    }
                }
            }
            serde_json::Value::Array(a) => a.iter().for_each(|x| keys(x, out)),
            _ => {}
        }
    }
    let mut sent = Vec::new();
    keys(s, &mut sent);
    for k in &sent {
        assert!(
            documented.contains(k),
            "/status sends {k:?}, which the README's schema lacks"
        );
    }
    // The top level, both ways (claims audit: a documented key never sent
    // passed): the keys of the schema's outermost object.
    let schema = line.split('`').nth(3).expect("the schema in backquotes");
    let (mut depth, mut top, mut quoted, mut key) = (0, Vec::new(), false, String::new());
    for c in schema.chars() {
        match c {
            '"' if quoted => {
                quoted = false;
                if depth == 1 {
                    top.push(std::mem::take(&mut key));
                }
                key.clear();
            }
            '"' => quoted = true,
            c if quoted => key.push(c),
            '{' | '[' => depth += 1,
            '}' | ']' => depth -= 1,
            _ => {}
        }
    }
    let sent_top: std::collections::BTreeSet<&str> =
        s.as_object().unwrap().keys().map(String::as_str).collect();
    let documented_top: std::collections::BTreeSet<&str> = top.iter().map(String::as_str).collect();
    assert_eq!(
        sent_top, documented_top,
        "/status's top-level keys against the README's"
    );
    let script = s["scripts"][0].as_object().unwrap();
    let listed = line.split("\"scripts\":[{").nth(1).unwrap();
    // The script's own keys: its text up to its closing brace, without
    // the nested `params` entries and `totals`.
    let mut depth = 0;
    let mut own = String::new();
    for c in listed.chars() {
        match c {
            '{' | '[' => depth += 1,
            '}' | ']' if depth == 0 => break,
            '}' | ']' => depth -= 1,
            c if depth == 0 => own.push(c),
            _ => {}
        }
    }
    for k in own.split('"').skip(1).step_by(2) {
        assert!(
            script.contains_key(k),
            "the README lists {k:?} for a script; /status lacks it"
        );
    }
    assert!(script["totals"].is_object(), "{script:?}");
}

fn save_like_an_editor(path: &Path, text: &str) {
    let tmp = path.with_extension("lua.swp");
    std::fs::write(&tmp, text).unwrap();
    std::fs::rename(&tmp, path).unwrap();
}

/// Polls `/status` until `pred` holds for the water script's status; returns
/// how long it took (the wait is a generous cap, not a timing assertion).
fn wait_for_script(addr: &str, pred: impl Fn(&serde_json::Value) -> bool) -> Duration {
    let t = Instant::now();
    while t.elapsed() < Duration::from_secs(20) {
        let s = status(addr);
        if pred(&s["scripts"][0]) {
            return t.elapsed();
        }
        std::thread::sleep(Duration::from_millis(20));
    }
    panic!("the script status never changed: {}", status(addr));
}

#[test]
fn hot_reload_of_a_changed_and_a_broken_script() {
    let (_scratch, cfg, state, addr) = setup("reload");
    let scripts = cfg.parent().unwrap().join("scripts");
    std::fs::create_dir_all(&scripts).unwrap();
    let original =
        std::fs::read_to_string(concat!(env!("CARGO_MANIFEST_DIR"), "/scripts/water.lua")).unwrap();
    let water = scripts.join("water.lua");
    std::fs::write(&water, &original).unwrap();
    edit_config(
        &cfg,
        concat!(env!("CARGO_MANIFEST_DIR"), "/scripts"),
        scripts.to_str().unwrap(),
    );
    let child = start(&cfg, &state);
    wait_ready(&addr);
    assert!(status(&addr)["scripts"][0]["error"].is_null());

    // A broken save: the old version keeps running, the error names the file
    // and line.
    save_like_an_editor(&water, "return {\n  channels = { \"water\" \n}\n");
    let broken = wait_for_script(&addr, |s| {
        s["error"].as_str().is_some_and(|e| e.contains("water.lua"))
    });
    let err = status(&addr)["scripts"][0]["error"]
        .as_str()
        .unwrap()
        .to_string();
    assert!(
        err.contains("water.lua:4:") && err.contains("syntax error"),
        "{err}"
    );
    let tick = status(&addr)["tick"].as_u64().unwrap();
    let t = Instant::now();
    while status(&addr)["tick"].as_u64().unwrap() <= tick + 2 {
        assert!(
            t.elapsed() < Duration::from_secs(20),
            "the old version stopped running"
        );
        std::thread::sleep(Duration::from_millis(20));
    }

    // A changed script takes effect: this version logs from its first
    // kernel, which only the new code can do. (It used to raise an error
    // there, which the smoke test refused, so the old version ran on and
    // the test saw only the refusal: it never showed a swap.)
    let v2 = original.replacen(
        "kernel = function(c)\n",
        "kernel = function(c)\n        log(\"v2 is running\")\n",
        1,
    );
    assert_ne!(v2, original);
    save_like_an_editor(&water, &v2);
    let changed = wait_for_script(&addr, |s| {
        s["log"].as_array().is_some_and(|l| {
            l.iter()
                .any(|x| x.as_str().is_some_and(|x| x.contains("v2 is running")))
        })
    });
    let s = &status(&addr)["scripts"][0];
    assert!(s["error"].is_null(), "{s}");

    // `/status` counts the reload and says when it happened.
    let (reloads, at) = (
        s["reloads"].as_u64().unwrap(),
        s["reloaded_at"].as_u64().unwrap(),
    );
    assert!(reloads >= 1 && at > 0, "{s}");

    // A version without the parameter the config sets: it runs, with a
    // warning that the next start would refuse the config (regression: it
    // was said nowhere).
    // (Only the parameter: a blind replace made `drains` `ddrizzles`, which
    // loaded while unknown keys were ignored.)
    let drizzle = original
        .replace("rain = { default", "drizzle = { default")
        .replace("c.p.rain", "c.p.drizzle");
    assert_eq!(drizzle.matches("drizzle").count(), 2);
    save_like_an_editor(&water, &drizzle);
    wait_for_script(&addr, |s| {
        s["warning"].as_str().is_some_and(|w| {
            w.contains("sets parameter 'rain'") && w.contains("no longer declares")
        })
    });

    let s = &status(&addr)["scripts"][0];
    assert_eq!(s["reloads"].as_u64().unwrap(), reloads + 1, "{s}");
    assert!(s["reloaded_at"].as_u64().unwrap() >= at, "{s}");

    // A version whose range leaves out the config's value (rain = 0.2):
    // it runs clamped, and says now that the next start would refuse the
    // config (regression, hostile probe 2: only that start said so).
    let narrowed = original.replace(
        "rain = { default = 0, min = 0, max = 10 }",
        "rain = { default = 0, min = 0, max = 0.1 }",
    );
    assert_ne!(narrowed, original);
    save_like_an_editor(&water, &narrowed);
    wait_for_script(&addr, |s| {
        s["warning"].as_str().is_some_and(|w| {
            w.contains("sets parameter 'rain' of water.lua to 0.2, outside its new range [0, 0.1]")
                && w.contains("the next start will refuse the config")
        })
    });

    // A .lua that is not a loaded script, made and deleted: none of the
    // engine's business (checked in the log below).
    std::fs::write(scripts.join("other.lua"), "return {}").unwrap();
    std::thread::sleep(Duration::from_millis(400));
    std::fs::remove_file(scripts.join("other.lua")).unwrap();

    // A change to materials.lua is applied and said, a broken one refused
    // and said, not silently ignored (regression, hostile probe).
    let materials = scripts.join("materials.lua");
    let wait_note = |says: &str| {
        let t = Instant::now();
        loop {
            let st = status(&addr);
            if st["materials_note"]
                .as_str()
                .is_some_and(|n| n.contains(says))
            {
                return;
            }
            assert!(t.elapsed() < Duration::from_secs(20), "{says}: {st}");
            std::thread::sleep(Duration::from_millis(50));
        }
    };
    save_like_an_editor(
        &materials,
        "return { moss = { color = { 60, 140, 60 }, kind = \"solid\", density = 1 } }\n",
    );
    wait_note("applied: 1 new material (moss), 0 recoloured");
    save_like_an_editor(&materials, "return { moss = 1 }\n");
    wait_note("does not load");
    std::fs::remove_file(&materials).unwrap();

    // A deleted script: the loaded version runs on, and /status says why
    // it was not reloaded (regression: said nowhere).
    std::fs::remove_file(&water).unwrap();
    wait_for_script(&addr, |s| {
        s["error"]
            .as_str()
            .is_some_and(|e| e.contains("water.lua") && e.contains("No such file"))
    });

    // And the original back: the error clears.
    save_like_an_editor(&water, &original);
    wait_for_script(&addr, |s| s["error"].is_null());
    eprintln!("hot reload seen in /status after: broken {broken:?}, changed {changed:?}");
    let out = stop(child);
    assert!(out.status.success());
    let log = String::from_utf8_lossy(&out.stderr);
    // Each reload is said with its tick: the one `/status` dated `at` too
    // (claims audit: only the word "reloaded" was checked).
    assert!(
        log.lines()
            .any(|l| l.contains(&format!("tick {at}: reloaded ")) && l.ends_with("water.lua")),
        "{log}"
    );
    common::cli::assert_no_panic(&log, "the engine");
    assert!(!log.contains("other.lua"), "{log}");
}

fn set_commit_every(cfg: &Path, every: u64) {
    edit_config(
        cfg,
        "[checkpoint]\nevery = 40",
        &format!("[checkpoint]\nevery = {every}"),
    );
}

/// Start a daemon whose every commit stalls inside its write transaction;
/// returns once a commit is stalled there.
fn start_stalled_in_a_commit(cfg: &Path, state: &Path) -> Daemon {
    use std::io::BufRead;
    let mut child = run_cmd(cfg, state)
        .env("BRICKWORLD_TEST_COMMIT_STALL_MS", "60000")
        .stdout(Stdio::null())
        .stderr(Stdio::piped())
        .spawn()
        .unwrap();
    let err = child.stderr.take().unwrap();
    let (tx, rx) = std::sync::mpsc::channel();
    std::thread::spawn(move || {
        for line in std::io::BufReader::new(err).lines().map_while(Result::ok) {
            if line.contains("a commit is stalled") {
                let _ = tx.send(());
            }
        }
    });
    let daemon = Daemon(Some(child));
    rx.recv_timeout(Duration::from_secs(60))
        .expect("no commit started within 60 s");
    daemon
}

/// `BRICKWORLD_KILL_TRIALS` sets the number of trials (6 by default; the
/// README's figure comes from 20). Every other trial kills the engine in
/// the middle of a commit. After each kill, the store must hold at least
/// the last commit the engine reported; after all of them, running on to a
/// fixed tick must give the same world hash as a run that never stopped.
#[test]
fn kill_9_at_random_moments_and_mid_commit_loses_nothing_and_resumes_bit_identically() {
    let trials: u64 = std::env::var("BRICKWORLD_KILL_TRIALS")
        .ok()
        .and_then(|v| v.parse().ok())
        .unwrap_or(6);
    let (_scratch, cfg, state, addr) = setup("killtrials");
    set_commit_every(&cfg, 10);
    let mut rng = 0x9e37_79b9_7f4a_7c15u64;
    let mut last_tick = 0;
    for trial in 0..trials {
        let (mut child, seen, delay) = if trial % 2 == 1 {
            let seen = stored_tick(&cfg, &state).unwrap_or(0);
            (start_stalled_in_a_commit(&cfg, &state), seen, 0)
        } else {
            let child = start(&cfg, &state);
            wait_ready(&addr);
            rng = rng
                .wrapping_mul(6364136223846793005)
                .wrapping_add(1442695040888963407);
            let delay = 50 + (rng >> 33) % 1500;
            std::thread::sleep(Duration::from_millis(delay));
            let seen = status(&addr)["last_commit"]["tick"].as_u64().unwrap_or(0);
            (child, seen, delay)
        };
        child.kill().unwrap();
        child.wait().unwrap();
        let tick = stored_tick(&cfg, &state).unwrap_or(0);
        assert!(
            tick >= seen && tick >= last_tick,
            "trial {trial}: the store holds tick {tick}, but {seen} was committed (and {last_tick} before)"
        );
        if trial % 2 == 1 {
            assert_eq!(
                tick, seen,
                "trial {trial}: the stalled commit must not land"
            );
        }
        last_tick = tick;
        eprintln!("kill -9 trial {trial}: killed after {delay} ms, the store holds tick {tick}");
    }
    let end = last_tick + 30;
    let resumed = hash_at(&cfg, &state, end);
    let (_scratch, cfg2, state2, _) = setup("killtrials-straight");
    set_commit_every(&cfg2, 10);
    let straight = hash_at(&cfg2, &state2, end);
    assert_eq!(
        resumed, straight,
        "resumed after {trials} kills vs never stopped"
    );
}

#[test]
fn a_slow_renderer_skips_frames_and_never_holds_up_the_simulation() {
    let (_scratch, cfg, state, addr) = setup("slowrender");
    // A frame every tick, far larger than the 48x32x48 world needs: each
    // frame takes many steps' time.
    edit_config(
        &cfg,
        "width = 32\nheight = 24",
        "width = 1024\nheight = 768\nshadows = true",
    );
    edit_config(&cfg, "[frames]\nevery = 5", "[frames]\nevery = 1");
    let child = start(&cfg, &state);
    wait_ready(&addr);
    let t = Instant::now();
    let s = loop {
        let s = status(&addr);
        if s["frames"].as_u64().unwrap() >= 2 || t.elapsed() > Duration::from_secs(60) {
            break s;
        }
        std::thread::sleep(Duration::from_millis(50));
    };
    let (tick, frames, skipped) = (
        s["tick"].as_u64().unwrap(),
        s["frames"].as_u64().unwrap(),
        s["frames_skipped"].as_u64().unwrap(),
    );
    assert!(frames >= 2, "{s}");
    assert!(skipped > 0, "the renderer kept up with every tick: {s}");
    assert!(tick > frames + skipped / 2, "{s}");
    // Coalesced: at most every brick of the world once (6 x 4 x 6).
    assert!(s["dirty_queue"].as_u64().unwrap() <= 144, "{s}");
    assert!(stop(child).status.success());
}

/// Claim (README, "Stopping"): at a stop the frame in flight gets 3 s,
/// and a longer one is abandoned, with a warning, without holding up the
/// final commit or leaving a half-written frame behind.
#[test]
fn a_stop_gives_the_frame_in_flight_3_s_then_abandons_it() {
    let (_scratch, cfg, state, addr) = setup("frameinflight");
    // 16 samples of 2048 x 1536 with shadows: about 10 s a frame here.
    edit_config(
        &cfg,
        "width = 32\nheight = 24",
        "width = 2048\nheight = 1536\nshadows = true",
    );
    edit_config(&cfg, "aa = 2", "aa = 16");
    let d = start(&cfg, &state);
    wait_ready(&addr);
    // The first frame is being drawn: later ones are skipped meanwhile.
    wait_status(&addr, "no frame in flight", |s| {
        s["frames"] == 0 && s["frames_skipped"].as_u64().unwrap() > 0
    });
    ctl_ok(&addr, &state, &["pause"]);
    let s = wait_status(&addr, "pausing", |s| s["paused"] == true);
    let tick = s["tick"].as_u64().unwrap();
    assert_eq!(s["frames"], 0, "the frame must still be in flight: {s}");
    let t = Instant::now();
    let out = stop(d);
    let took = t.elapsed();
    let err = String::from_utf8_lossy(&out.stderr);
    assert!(out.status.success(), "{err}");
    assert!(
        err.contains("the frame in flight is abandoned (3 s limit at shutdown)"),
        "{err}"
    );
    assert!(
        took >= Duration::from_millis(2900) && took < Duration::from_secs(20),
        "the stop took {took:?}"
    );
    assert_eq!(stored_tick(&cfg, &state), Some(tick));
    // Nothing half-written: no frame, and no temporary file of one.
    let frames: Vec<_> = std::fs::read_dir(state.join("frames"))
        .unwrap()
        .map(|e| e.unwrap().file_name())
        .collect();
    assert!(frames.is_empty(), "{frames:?}");
}

/// Claim (README): the control token is printed at start, on the line
/// that says the engine runs, and it is the token `STATE/control.token`
/// holds, which the API accepts (claims audit: nothing compared them).
#[test]
fn the_token_printed_at_start_is_the_one_the_state_directory_holds() {
    use std::io::BufRead;
    let (_scratch, cfg, state, addr) = setup("tokenline");
    let child = run_cmd(&cfg, &state)
        .stdout(Stdio::piped())
        .stderr(Stdio::piped())
        .spawn()
        .unwrap();
    let mut d = Daemon(Some(child));
    let out = d.0.as_mut().unwrap().stdout.take().unwrap();
    let line = std::io::BufReader::new(out)
        .lines()
        .find(|l| l.as_ref().map_or(true, |l| l.contains("is running")))
        .expect("the engine ended without saying it runs")
        .unwrap();
    wait_ready(&addr);
    let token = token(&state);
    let said = line
        .rsplit_once(": ")
        .map(|(_, t)| t.trim_end_matches(')'))
        .unwrap_or_default();
    assert_eq!(said, token.trim(), "{line}");
    assert!(line.contains(&format!("http://{addr}/")), "{line}");
    let (code, body) = request(&addr, "POST", "/auth", Some(said), "").unwrap();
    assert_eq!(code, 200, "{body}");
    assert!(stop(d).status.success());
}

/// Regression (long-run probe): an engine on port 0 picks its port, and
/// `ctl --state` tried the default address. The engine writes the bound
/// address to `STATE/control.addr`, and `ctl` uses it when no `--addr` is
/// given; an `--addr` given still wins.
#[test]
fn ctl_finds_an_engine_on_port_0_through_its_state_directory() {
    let (_scratch, cfg, state, addr) = setup("port0");
    edit_config(
        &cfg,
        &format!("addr = \"{addr}\""),
        "addr = \"127.0.0.1:0\"",
    );
    let d = start(&cfg, &state);
    let t = Instant::now();
    let bound = loop {
        if let Ok(text) = std::fs::read_to_string(state.join("control.addr"))
            && text.ends_with('\n')
        {
            break text.trim().to_string();
        }
        assert!(t.elapsed() < Duration::from_secs(60), "no control.addr");
        std::thread::sleep(Duration::from_millis(50));
    };
    assert_ne!(bound, "127.0.0.1:0");
    wait_ready(&bound);
    let ctl = |extra: &[&str]| {
        std::process::Command::new(env!("CARGO_BIN_EXE_brickworld"))
            .args(["ctl", "--state"])
            .arg(&state)
            .args(extra)
            .arg("pause")
            .output()
            .unwrap()
    };
    let out = ctl(&[]);
    assert_success(&out);
    let wrong = ctl(&["--addr", "127.0.0.1:1"]);
    assert!(!wrong.status.success(), "--addr did not win");
    assert!(stop(d).status.success());
}

/// Regression (long-run probe): every script's `steps_per_s` was the
/// engine's, so one run every 2 ticks showed twice its rate. It is the
/// engine's divided by the script's `every`.
#[test]
fn a_scripts_rate_counts_its_own_runs() {
    let (_scratch, cfg, state, addr) = setup("script-rate");
    add_script(
        &cfg,
        "slow.lua",
        "return { channels = { \"s\" }, passes = { { name = \"p\", reads = {}, writes = { \"s\" },\n\
         kernel = function(c) buffer.writef64(c.w.s, 0, c.tick) end } } }",
    );
    edit_config(
        &cfg,
        "file = \"slow.lua\"",
        "file = \"slow.lua\"\nevery = 2",
    );
    let d = start(&cfg, &state);
    wait_ready(&addr);
    let s = wait_status(&addr, "a rate", |s| {
        s["scripts"][0]["steps_per_s"].as_f64().unwrap_or(0.0) > 0.0
    });
    let (water, slow) = (
        s["scripts"][0]["steps_per_s"].as_f64().unwrap(),
        s["scripts"][1]["steps_per_s"].as_f64().unwrap(),
    );
    assert_eq!(s["scripts"][1]["name"], "slow", "{s}");
    assert!(
        (slow * 2.0 - water).abs() < 1e-9 * water,
        "{water} and {slow}: {s}"
    );
    assert!(stop(d).status.success());
}

/// Claim (README, `POST /scripts/NAME/params`): a value the server
/// accepted against `/status`, whose range a hot reload narrowed before
/// the engine applied it, gets 409 with the engine's reason. The engine
/// reloads at the start of a turn, before it applies commands, and
/// publishes `/status` only after them: a change queued while it steps
/// (slowly here) meets the new range first. A refused request changes
/// nothing: the value set beside the refused one keeps its old value
/// (regression: values before the refused one stayed applied).
#[test]
fn a_parameter_a_reload_narrowed_meanwhile_gets_409() {
    let (_scratch, cfg, state, addr) = setup("paramrace");
    let script = |max: u32| {
        format!(
            "return {{ channels = {{ \"s\" }}, params = {{ j = {{ default = 0, min = 0, max = 100000 }}, k = {{ default = 1, min = 0, max = {max} }} }},\n\
             passes = {{ {{ name = \"p\", reads = {{}}, writes = {{ \"s\" }},\n\
             kernel = function(c) for i = 1, 3000000 do end end }} }} }}"
        )
    };
    add_script(&cfg, "slow.lua", &script(10));
    let d = start(&cfg, &state);
    wait_ready(&addr);
    // `j` is listed first, so an engine that applied values one by one
    // would set it before refusing `k`.
    let set = |j: u32| {
        let body = format!(r#"{{"j":{j},"k":5}}"#);
        post(&addr, &state, "/scripts/slow/params", &body)
    };
    assert_eq!(set(1).0, 200);
    save_like_an_editor(&cfg.parent().unwrap().join("scripts/slow.lua"), &script(2));
    // Until the reload, 5 is applied; then the engine refuses it (409)
    // before `/status` shows the new range, and after that the server
    // refuses it itself (400).
    let mut answers = Vec::new();
    let t = Instant::now();
    let mut j = 1;
    let refused = loop {
        j += 1;
        let (code, body) = set(j);
        answers.push(code);
        if code != 200 {
            break (code, body);
        }
        assert!(t.elapsed() < Duration::from_secs(60), "never reloaded");
    };
    assert_eq!(refused.0, 409, "answers {answers:?}: {}", refused.1);
    assert!(
        refused.1.contains("refused") && refused.1.contains("'k'"),
        "{}",
        refused.1
    );
    let s = wait_status(&addr, "the new range", |s| {
        s["scripts"][1]["warning"]
            .as_str()
            .is_some_and(|w| w.contains("refused"))
    });
    assert!(s["scripts"][1]["error"].is_null(), "{s}");
    let params = s["scripts"][1]["params"].as_array().unwrap();
    let value = |name: &str| {
        let p = params.iter().find(|p| p["name"] == name).unwrap();
        p["value"].as_f64().unwrap()
    };
    assert_eq!(
        value("j"),
        f64::from(j - 1),
        "the refused request set j: {s}"
    );
    assert_eq!(value("k"), 2.0, "clamped into the narrowed range: {s}");
    let (code, body) = set(j + 1);
    assert_eq!(code, 400, "{body}");
    assert!(stop(d).status.success());
}

/// Regression (hostile probe): `water.lua` at its declared least `dx`
/// needs more CFL sub-steps than a step may take; its steps went unstable
/// and it was suspended for a channel out of bounds, with no word of the
/// cause. `/status` and the log now say it.
#[test]
fn a_script_past_the_sub_step_cap_is_told_why() {
    let (_scratch, cfg, state, addr) = setup("substepcap");
    edit_config(
        &cfg,
        "params = { rain = 0.2 }",
        "params = { rain = 0.2, dx = 0.001 }",
    );
    let d = start(&cfg, &state);
    wait_ready(&addr);
    let s = wait_status(&addr, "no sub-step warning", |s| {
        s["scripts"][0]["warning"]
            .as_str()
            .is_some_and(|w| w.contains("256 sub-steps"))
    });
    let w = s["scripts"][0]["warning"].as_str().unwrap();
    assert!(w.contains("sim.dt") && w.contains("'dx'"), "{w}");
    let out = stop(d);
    let err = String::from_utf8_lossy(&out.stderr);
    assert_eq!(err.matches("256 sub-steps").count(), 1, "said once: {err}");
}

/// Regression (hostile probe): `[frames] dir = "/dev/null"` said "cannot
/// create /dev/null: File exists", naming no field.
#[test]
fn a_frames_dir_that_is_not_a_folder_names_its_field() {
    let (_scratch, cfg, state, _) = setup("framesdir");
    edit_config(
        &cfg,
        "[frames]\nevery = 5",
        "[frames]\nevery = 5\ndir = \"/dev/null\"",
    );
    let out = run_cmd(&cfg, &state).output().unwrap();
    common::cli::assert_clear_failure(
        &out,
        "frames.dir = /dev/null",
        "frames.dir: /dev/null is not a folder",
    );
    assert!(!state.exists(), "the failed start left its state directory");
}

/// Audit: SIGTERM and SIGINT end the engine with a final commit of the
/// tick it stopped at (the periodic commit is every 40 ticks; the tick
/// here is not a multiple of 40, so only the final commit can hold it).
#[test]
fn sigterm_and_sigint_commit_the_tick_the_engine_stopped_at() {
    let (_scratch, cfg, state, addr) = setup("finalcommit");
    for sig in ["-TERM", "-INT"] {
        let mut d = start(&cfg, &state);
        wait_ready(&addr);
        let first = status(&addr)["tick"].as_u64().unwrap();
        wait_status(&addr, "no steps", |s| {
            s["tick"].as_u64().unwrap() >= first + 3
        });
        // Through `ctl`, which exits 0 once the engine applied it (audit:
        // no test ran ctl's success path against an engine).
        let ctl = |args: &[&str]| ctl_ok(&addr, &state, args);
        ctl(&["pause"]);
        let paused = |before: Option<u64>| paused_tick(&addr, before);
        let mut tick = paused(None);
        if tick.is_multiple_of(40) {
            ctl(&["step", "1"]);
            tick = paused(Some(tick));
        }
        ctl(&["param", "water", "rain", "0.3"]);
        if sig == "-TERM" {
            // `ctl commit` exits 0 once the commit is written.
            ctl(&["commit"]);
            // (/status shows it once the engine publishes, just after.)
            wait_status(&addr, "ctl commit wrote nothing", |s| {
                s["last_commit"]["tick"] == tick
            });
            // One more step, so that only the final commit can hold it.
            ctl(&["step", "1"]);
            tick = paused(Some(tick));
        }
        let _ = std::process::Command::new("kill")
            .args([sig, &d.id().to_string()])
            .status();
        let code = wait_for_exit(&mut d, 30, &format!("{sig} did not stop it"));
        assert!(code.success(), "{sig}: {code:?}");
        assert_eq!(stored_tick(&cfg, &state), Some(tick), "after {sig}");
    }
}

/// Regression (hostile probe): after a kill -9 the resumed engine ran the
/// ticks since its last commit again and appended their timeline rows a
/// second time, so ticks repeated (and a row cut by the kill stayed torn).
/// A resume now drops the rows after its tick, and a cut last row.
#[test]
fn a_resume_drops_the_timeline_rows_it_will_run_again() {
    let (_scratch, cfg, state, _) = setup("timelinecut");
    hash_at(&cfg, &state, 50);
    let path = state.join("timeline.csv");
    // What a kill leaves: rows past the commit, the last one cut.
    let mut text = std::fs::read_to_string(&path).unwrap();
    let last = text.lines().last().unwrap().to_string();
    let fields = last.split_once(',').unwrap().1;
    text.push_str(&format!("55,{fields}\n60,{fields}\n65,1.5,3"));
    std::fs::write(&path, &text).unwrap();
    let (_, err) = run_ok(&cfg, &state, "--until-tick", 70);
    assert!(err.contains("timeline: rows after tick 50"), "{err}");
    // The rows dropped are kept aside under the header (found by review: a
    // world restarted from an older store lost its history), and only
    // they (regression, crash probe: the whole file was copied at each
    // crash, 29 MiB a restart for a long-lived world).
    let kept = std::fs::read_dir(&state)
        .unwrap()
        .filter_map(|e| e.ok())
        .map(|e| e.path())
        .filter(|p| {
            p.file_name()
                .unwrap()
                .to_string_lossy()
                .starts_with("timeline.")
        })
        .filter(|p| p != &path)
        .map(|p| std::fs::read_to_string(p).unwrap())
        .collect::<Vec<_>>();
    let header = text.lines().next().unwrap();
    let dropped = format!("{header}\n55,{fields}\n60,{fields}\n65,1.5,3");
    assert_eq!(kept, vec![dropped], "one copy of the rows dropped");
    let table = brickworld::engine::timeline::read(&path).unwrap();
    assert_eq!(table.skipped, 0, "a torn row is left");
    let ticks: Vec<u64> = table.rows.iter().map(|r| r[0] as u64).collect();
    assert!(ticks.windows(2).all(|w| w[0] < w[1]), "{ticks:?}");
    assert_eq!(ticks.last(), Some(&70), "{ticks:?}");
}

/// Regression (docs walk): after a restart `/timeline` was empty, so the
/// viewer's charts lost the world's history at every start; it now starts
/// with the rows on disk, whole and in order.
#[test]
fn the_viewers_timeline_starts_with_the_history_on_disk() {
    let (_scratch, cfg, state, addr) = setup("timelinehistory");
    hash_at(&cfg, &state, 50);
    let on_disk = brickworld::engine::timeline::read(&state.join("timeline.csv")).unwrap();
    assert!(on_disk.rows.len() >= 5, "{:?}", on_disk.rows);
    let d = spawn(run_cmd(&cfg, &state).arg("--paused"));
    wait_ready(&addr);
    let (code, body) = request(&addr, "GET", "/timeline", None, "").unwrap();
    assert_eq!(code, 200, "{body}");
    let v: serde_json::Value = serde_json::from_str(&body).unwrap();
    let columns: Vec<&str> = v["columns"]
        .as_array()
        .unwrap()
        .iter()
        .map(|c| c.as_str().unwrap())
        .collect();
    assert_eq!(columns, on_disk.columns, "{body}");
    let served: Vec<f64> = v["rows"]
        .as_array()
        .unwrap()
        .iter()
        .map(|r| r[0].as_f64().unwrap())
        .collect();
    let stored: Vec<f64> = on_disk.rows.iter().map(|r| r[0]).collect();
    assert_eq!(served, stored, "{body}");
    assert_success(&stop(d));
}

/// `materials.lua` is applied while the engine runs: a voxel script whose
/// reload waited for a material is reloaded once the material is declared,
/// a recoloured material is said and stored, and the ids are those the
/// same edits made while the engine was stopped give.
#[test]
fn a_material_declared_while_the_engine_runs_is_used_by_the_script_waiting_for_it() {
    let (_scratch, cfg, state, addr, scripts) = lava_world("livematerials");
    let lava_src = shipped_script("lava.lua");
    let materials = scripts.join("materials.lua");
    let shipped = shipped_script("materials.lua");
    let child = start(&cfg, &state);
    wait_ready(&addr);
    let lava = |pred: &dyn Fn(&serde_json::Value) -> bool| {
        let t = Instant::now();
        loop {
            let st = status(&addr);
            if pred(&st["scripts"][1]) {
                return st;
            }
            assert!(t.elapsed() < Duration::from_secs(20), "{st}");
            std::thread::sleep(Duration::from_millis(20));
        }
    };
    lava(&|s| s["name"] == "lava");

    // Lava cools to `obsidian` now, a material not declared yet: the
    // reload is refused and the old version runs on.
    let v2 = lava_src
        .replace("\"basalt\", \"water\"", "\"obsidian\", \"water\"")
        .replace("c.m.basalt", "c.m.obsidian");
    assert_ne!(v2, lava_src);
    save_like_an_editor(&scripts.join("lava.lua"), &v2);
    lava(&|s| {
        s["error"]
            .as_str()
            .is_some_and(|e| e.contains("unknown material 'obsidian'"))
    });
    let reloads = status(&addr)["scripts"][1]["reloads"].as_u64().unwrap();

    // Declared, with lava recoloured: applied, and the waiting script
    // reloads by itself.
    let declared = shipped
        .replacen(
            "return {",
            "return {\n  obsidian = { color = { 30, 20, 40 }, kind = \"solid\", density = 2.6 },",
            1,
        )
        .replace("color = { 255, 96, 24 }", "color = { 250, 10, 10 }");
    save_like_an_editor(&materials, &declared);
    let st = lava(&|s| s["error"].is_null() && s["reloads"].as_u64() > Some(reloads));
    let note = st["materials_note"].as_str().unwrap_or_default();
    assert!(
        note.contains(
            "applied: 1 new material (obsidian), 1 recoloured, 0 with a new kind or density"
        ),
        "{st}"
    );
    let out = stop(child);
    assert!(out.status.success());
    let log = String::from_utf8_lossy(&out.stderr);
    common::cli::assert_no_panic(&log, "the engine");
    let (live, palette) = stored_materials(&cfg, &state);
    let id = |m: &[(u8, String)], n: &str| m.iter().find(|e| e.1 == n).unwrap().0;
    assert_eq!(palette[id(&live, "lava") as usize], [250, 10, 10]);
    assert_eq!(palette[id(&live, "obsidian") as usize], [30, 20, 40]);

    // The same edits made while the engine was stopped give the same ids.
    let (_scratch, cfg2, state2, _, scripts2) = lava_world("livematerials-restart");
    run_ok(&cfg2, &state2, "--ticks", 2);
    std::fs::write(scripts2.join("lava.lua"), &v2).unwrap();
    std::fs::write(scripts2.join("materials.lua"), &declared).unwrap();
    run_ok(&cfg2, &state2, "--ticks", 2);
    assert_eq!(stored_materials(&cfg2, &state2).0, live);
}

/// Regression: the world hash followed the order channels were registered
/// in, and counted channels without data. A reload that renamed a channel
/// (lava's `poured` to `spilled`) left the old name registered, so the
/// engine printed one hash when it stopped and another when the same store
/// resumed, with no change to the world.
#[test]
fn a_reload_that_renames_a_channel_keeps_the_hash_across_a_resume() {
    let (_scratch, cfg, state, addr, scripts) = lava_world("renamedchannel");
    let lava_src = shipped_script("lava.lua");
    let mut cmd = run_cmd(&cfg, &state);
    cmd.arg("--paused")
        .stdout(Stdio::piped())
        .stderr(Stdio::piped());
    let child = Daemon(Some(cmd.spawn().unwrap()));
    wait_ready(&addr);
    // Five ticks with `poured`, then five with `spilled`.
    assert_eq!(post(&addr, &state, "/step", "5").0, 200);
    wait_status(&addr, "five ticks", |s| s["tick"] == 5);
    let renamed = lava_src.replace("poured", "spilled");
    assert_ne!(renamed, lava_src);
    save_like_an_editor(&scripts.join("lava.lua"), &renamed);
    wait_status(&addr, "the reload", |s| s["scripts"][1]["reloads"] == 1);
    assert_eq!(post(&addr, &state, "/step", "5").0, 200);
    wait_status(&addr, "ten ticks", |s| s["tick"] == 10);
    let out = stop(child);
    assert!(out.status.success());
    let said = String::from_utf8_lossy(&out.stdout);
    let at_stop = said
        .lines()
        .find_map(|l| l.strip_prefix("stopped at tick 10 (world hash "))
        .unwrap_or_else(|| panic!("{said}"))
        .trim_end_matches(')')
        .to_string();
    assert_eq!(hash_at(&cfg, &state, 10), at_stop);
}

/// Regression (docs walk): a script's CFL sub-steps each counted as a
/// failed step, so a streak could begin and suspend the script in one
/// tick; the log then said only the suspension, though the README says it
/// says both. The beginning is said first, and (since a tick counts one
/// failure, however many sub-steps failed) the suspension comes after 3
/// failed ticks, not within one.
#[test]
fn a_streak_that_suspends_a_script_in_one_tick_is_said_to_begin_too() {
    let (_scratch, cfg, state, _) = setup("onetickstreak");
    let scripts = cfg.parent().unwrap().join("scripts");
    std::fs::create_dir_all(&scripts).unwrap();
    let water = shipped_script("water.lua").replacen(
        "kernel = function(c)",
        "kernel = function(c) if c.tick > 0 then error('late boom') end",
        1,
    );
    std::fs::write(scripts.join("water.lua"), water).unwrap();
    edit_config(
        &cfg,
        concat!(env!("CARGO_MANIFEST_DIR"), "/scripts"),
        scripts.to_str().unwrap(),
    );
    // A tiny dx: many sub-steps once there is water (after tick 0).
    edit_config(
        &cfg,
        "params = { rain = 0.2 }",
        "params = { rain = 0.2, dx = 0.001 }",
    );
    // Ticks 1 and 2 fail in every sub-step: two failed steps, no suspension.
    let err = stderr_of_ticks(&cfg, &state, 3);
    assert!(err.contains("warning: water.lua failed a step: "), "{err}");
    assert!(!err.contains("is suspended"), "{err}");
    assert!(err.contains("late boom"), "{err}");
    // The third failed tick (the resumed run's tick 3) suspends it.
    let err = stderr_of_ticks(&cfg, &state, 2);
    assert!(
        err.contains("warning: water.lua is suspended after 3 failed steps in a row"),
        "{err}"
    );
}

/// Regression (researcher probe): the timeline's `dirty_bricks` read 0 in
/// every row (the renderer's pending set had just been handed over with
/// the frame), `ms:snow` read 0 in every row of a world running snow every
/// 2 ticks (rows fell on ticks it did not run), and `active_bricks` read 0
/// in a world of voxel scripts alone.
#[test]
fn the_timeline_counts_dirty_and_active_bricks_and_keeps_a_scripts_last_time() {
    let (_scratch, cfg, state, _) = setup("timelinecounts");
    edit_config(
        &cfg,
        "params = { rain = 0.2 }\n",
        "params = { rain = 0.2 }\n[[scripts]]\nfile = \"snow.lua\"\nevery = 2\nparams = { snowfall = 0.5 }\n",
    );
    edit_config(&cfg, "[frames]\nevery = 5", "[frames]\nevery = 4");
    let now = || {
        std::time::SystemTime::now()
            .duration_since(std::time::UNIX_EPOCH)
            .unwrap()
            .as_secs_f64()
    };
    let began = now();
    run_ok(&cfg, &state, "--until-tick", 40);
    let ended = now();
    let t = brickworld::engine::timeline::read(&state.join("timeline.csv")).unwrap();
    let col = |name: &str| {
        let i = t
            .columns
            .iter()
            .position(|c| c == name)
            .unwrap_or_else(|| panic!("{name}: {:?}", t.columns));
        t.rows.iter().map(|r| r[i]).collect::<Vec<f64>>()
    };
    assert!(
        col("dirty_bricks").iter().any(|&v| v > 0.0),
        "{:?}",
        col("dirty_bricks")
    );
    assert!(
        col("ms:snow").iter().all(|&v| v > 0.0),
        "{:?}",
        col("ms:snow")
    );
    assert!(
        col("active_bricks").iter().all(|&v| v > 0.0),
        "{:?}",
        col("active_bricks")
    );
    // Each row says when it was written, in order, within the run.
    let wall = col("unix_s");
    assert!(
        wall.iter().all(|&s| s >= began - 0.01 && s <= ended + 0.01)
            && wall.windows(2).all(|w| w[0] <= w[1]),
        "{wall:?} outside {began}..{ended}"
    );
    // No 0 ms frame: a row before the first frame has no frame time.
    assert!(
        col("frame_ms").iter().all(|&v| v.is_nan() || v > 0.0),
        "{:?}",
        col("frame_ms")
    );

    // Voxel scripts alone: rain3d's drops keep the top layer of bricks
    // awake.
    let (_scratch, cfg, state, _) = setup("timelinevoxels");
    edit_config(
        &cfg,
        "file = \"water.lua\"\nparams = { rain = 0.2 }",
        "file = \"rain3d.lua\"\nparams = { rain = 0.5 }",
    );
    run_ok(&cfg, &state, "--until-tick", 20);
    let t = brickworld::engine::timeline::read(&state.join("timeline.csv")).unwrap();
    let i = t.columns.iter().position(|c| c == "active_bricks").unwrap();
    assert!(t.rows.iter().all(|r| r[i] > 0.0), "{:?}", t.rows);
}

/// Claim (README, `/status`): a render thread that dies (a bug) is said once,
/// shown in `/status` `render_error`, and the simulation and its commits go
/// on (claims audit: only the unit test of `take_death` held any of it;
/// dropping the daemon's `render_error = Some(..)` passed every test). The
/// test hook `BRICKWORLD_TEST_RENDER_PANIC_AT_TICK` kills the thread.
#[test]
fn a_dead_render_thread_is_reported_and_the_simulation_goes_on() {
    let (_scratch, cfg, state, addr) = setup("render-death");
    let mut d = spawn(run_cmd(&cfg, &state).env("BRICKWORLD_TEST_RENDER_PANIC_AT_TICK", "10"));
    wait_ready(&addr);
    let s = wait_status(&addr, "render_error", |s| s["render_error"].is_string());
    let said = s["render_error"].as_str().unwrap().to_string();
    assert!(
        said.contains("the render thread stopped (test hook: the render thread panics at tick")
            && said.contains("the simulation and its commits go on"),
        "{said}"
    );
    let tick = s["tick"].as_u64().unwrap();
    let frames = s["frames"].as_u64();
    let later = wait_status(&addr, "ticks after the death", |s| {
        s["tick"].as_u64().unwrap() >= tick + 50
    });
    assert_eq!(later["render_error"].as_str(), Some(said.as_str()));
    assert_eq!(
        later["frames"].as_u64(),
        frames,
        "frames drawn after it died"
    );
    // A stop commits as usual; the death was said once.
    let _ = Command::new("kill")
        .arg("-TERM")
        .arg(d.id().to_string())
        .status();
    let child = d.0.take().unwrap();
    let out = child.wait_with_output().unwrap();
    assert!(out.status.success());
    let err = String::from_utf8_lossy(&out.stderr);
    assert_eq!(err.matches("the render thread stopped").count(), 1, "{err}");
    assert!(stored_tick(&cfg, &state).unwrap() >= tick + 50);
}

/// The engine runs with glibc's mmap threshold fixed (the memory budget's
/// fix for a heap that fragmented under teleports), through one re-exec
/// that keeps the pid; a threshold the user chose is left alone.
#[cfg(all(target_os = "linux", target_env = "gnu"))]
#[test]
fn the_engine_runs_with_a_fixed_mmap_threshold_unless_the_user_chose_one() {
    let (_scratch, cfg, state, addr) = setup("mmap");
    // The engine's environment once it answers, as `/proc` shows it.
    let environ = |user: Option<&str>| -> Vec<String> {
        let mut cmd = run_cmd(&cfg, &state);
        cmd.env_remove("GLIBC_TUNABLES");
        match user {
            Some(v) => cmd.env("MALLOC_MMAP_THRESHOLD_", v),
            None => cmd.env_remove("MALLOC_MMAP_THRESHOLD_"),
        };
        let d = spawn(&mut cmd);
        wait_ready(&addr);
        let text = std::fs::read(format!("/proc/{}/environ", d.id())).unwrap();
        let out = stop(d);
        assert!(
            out.status.success(),
            "{}",
            String::from_utf8_lossy(&out.stderr)
        );
        text.split(|&b| b == 0)
            .map(|v| String::from_utf8_lossy(v).into_owned())
            .filter(|v| v.starts_with("MALLOC_MMAP_THRESHOLD_="))
            .collect()
    };
    assert_eq!(environ(None), ["MALLOC_MMAP_THRESHOLD_=131072"]);
    assert_eq!(environ(Some("65536")), ["MALLOC_MMAP_THRESHOLD_=65536"]);
}

/// Regression (hostile environment probe): SIGXCPU, which a soft CPU-time
/// limit sends (batch schedulers set one to say "save now" before the hard
/// limit), killed the engine without a final commit. It is now a stop
/// request with one, and its repeats (the kernel sends it again each
/// second past the limit) are not a second request that exits at once.
#[cfg(unix)]
#[test]
fn sigxcpu_stops_the_engine_with_a_final_commit() {
    let (_scratch, cfg, state, addr) = setup("sigxcpu");
    // Every commit takes 1.5 s (test hook), so a SIGTERM arrives during the
    // final one.
    let mut d = spawn(run_cmd(&cfg, &state).env("BRICKWORLD_TEST_COMMIT_STALL_MS", "1500"));
    wait_ready(&addr);
    let tick = paused_between_commits(&addr, &state);
    for _ in 0..3 {
        let _ = std::process::Command::new("kill")
            .args(["-XCPU", &d.id().to_string()])
            .status();
        std::thread::sleep(Duration::from_millis(30));
    }
    // A scheduler's SIGTERM after its SIGXCPU is not a second request
    // (review: it skipped the final commit).
    std::thread::sleep(Duration::from_millis(300));
    let _ = std::process::Command::new("kill")
        .args(["-TERM", &d.id().to_string()])
        .status();
    let code = wait_for_exit(&mut d, 30, "SIGXCPU did not stop it");
    let mut err = String::new();
    std::io::Read::read_to_string(d.stderr.as_mut().unwrap(), &mut err).unwrap();
    assert!(code.success(), "{code:?}: {err}");
    assert_eq!(err.matches("soft CPU-time limit").count(), 1, "{err}");
    assert!(!err.contains("second signal"), "{err}");
    assert_eq!(stored_tick(&cfg, &state), Some(tick));
}

/// Regression (the last hostile environment probe's leftover): SIGQUIT,
/// SIGUSR1, SIGUSR2 and SIGALRM kept their default action and killed the
/// engine without a final commit, losing the ticks since the last one, and
/// so did the real-time signals (a known gap). Each is now a stop request
/// with a final commit, and says so. (SIGHUP, like SIGINT and SIGTERM,
/// always was.)
#[cfg(unix)]
#[test]
fn quit_usr_and_alarm_signals_stop_the_engine_with_a_final_commit() {
    let (_scratch, cfg, state, addr) = setup("stop-signals");
    // SIGHUP goes through the SIGINT/SIGTERM handler (claims audit: the
    // docs did not say it stops the engine, and no test held it).
    // The real-time signals too (a known gap: they kept their default).
    // SIGHUP stays ignored where the engine's parent ignores it (nohup):
    // then it is sent in `sighup_ignored_at_start_stays_ignored` instead.
    let hup_ignored = brickworld::files::ignored_at_start(nix::sys::signal::Signal::SIGHUP);
    for sig in [
        "QUIT", "USR1", "USR2", "ALRM", "VTALRM", "PWR", "HUP", "RTMIN", "RTMIN+3", "RTMIN+30",
    ] {
        if sig == "HUP" && hup_ignored {
            continue;
        }
        let mut d = spawn(&mut run_cmd(&cfg, &state));
        wait_ready(&addr);
        let tick = paused_between_commits(&addr, &state);
        let _ = std::process::Command::new("kill")
            .args([&format!("-{sig}"), &d.id().to_string()])
            .status();
        let code = wait_for_exit(&mut d, 30, &format!("SIG{sig} did not stop it"));
        let mut err = String::new();
        std::io::Read::read_to_string(d.stderr.as_mut().unwrap(), &mut err).unwrap();
        assert!(code.success(), "SIG{sig}: {code:?}: {err}");
        // (SIGRTMIN+30 is glibc's SIGRTMAX, which tokio's handlers missed.)
        let said = err.contains(&format!("SIG{sig} received: stopping with a final commit"));
        assert!(sig == "HUP" || said, "{err}");
        assert_eq!(stored_tick(&cfg, &state), Some(tick), "SIG{sig}: {err}");
    }
}

/// Regression (stop-path probe): the engine's SIGHUP handler replaced the
/// ignore `nohup` sets, so `nohup brickworld run` stopped when its
/// terminal closed. Under `nohup`, SIGHUP now leaves it running, and
/// SIGTERM still stops it with a final commit.
#[cfg(target_os = "linux")]
#[test]
fn sighup_ignored_at_start_stays_ignored() {
    let (_scratch, cfg, state, addr) = setup("nohup");
    let run = run_cmd(&cfg, &state);
    let mut nohup = std::process::Command::new("nohup");
    nohup.arg(run.get_program()).args(run.get_args());
    let mut d = spawn(&mut nohup);
    wait_ready(&addr);
    let tick = paused_between_commits(&addr, &state);
    common::signal("-HUP", d.id());
    std::thread::sleep(Duration::from_millis(1500));
    assert!(d.try_wait().unwrap().is_none(), "SIGHUP stopped it");
    assert_eq!(status(&addr)["tick"].as_u64(), Some(tick));
    common::signal("-TERM", d.id());
    let code = wait_for_exit(&mut d, 30, "SIGTERM did not stop it");
    let mut err = String::new();
    std::io::Read::read_to_string(d.stderr.as_mut().unwrap(), &mut err).unwrap();
    assert!(code.success(), "{code:?}: {err}");
    assert_eq!(stored_tick(&cfg, &state), Some(tick), "{err}");
}

/// Pause the engine at `addr` on a tick that is not a commit's
/// (`checkpoint.every` is 40 in `setup`'s world), so that only a final
/// commit can store it; that tick.
fn paused_between_commits(addr: &str, state: &std::path::Path) -> u64 {
    ctl_ok(addr, state, &["pause"]);
    let tick = paused_tick(addr, None);
    if !tick.is_multiple_of(40) {
        return tick;
    }
    ctl_ok(addr, state, &["step", "1"]);
    paused_tick(addr, Some(tick))
}
