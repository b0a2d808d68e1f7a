//! The live viewer's server side, as a browser and `ctl` use it (issue 12):
//! the event stream pushes frames, status and timeline rows; parameter
//! changes answer with the engine's verdict; the camera lease keeps two
//! viewers from fighting; the token check; `ctl params` and `ctl log`; the
//! page is small and self-contained.

use std::io::{Read, Write};
use std::net::TcpStream;
use std::path::Path;
use std::time::{Duration, Instant};

use brickworld::engine::ctl::request;

mod common;
use common::cli::{assert_clear_failure, assert_success};
use common::daemon::*;

/// Read `GET /events` until `done` says so (or 20 s pass); returns the
/// events as (kind, data JSON).
fn events(
    addr: &str,
    done: impl Fn(&[(String, serde_json::Value)]) -> bool,
) -> Vec<(String, serde_json::Value)> {
    let mut s = TcpStream::connect(addr).unwrap();
    s.set_read_timeout(Some(Duration::from_millis(500)))
        .unwrap();
    write!(s, "GET /events HTTP/1.1\r\nHost: {addr}\r\n\r\n").unwrap();
    let (mut buf, mut seen) = (String::new(), Vec::new());
    let t = Instant::now();
    let mut chunk = [0u8; 65536];
    while t.elapsed() < Duration::from_secs(20) && !done(&seen) {
        if let Ok(n) = s.read(&mut chunk) {
            if n == 0 {
                break;
            }
            buf.push_str(&String::from_utf8_lossy(&chunk[..n]));
        }
        // Chunked transfer framing aside, each event is "event: K\ndata: J\n\n".
        while let Some(i) = buf.find("event: ") {
            let rest = &buf[i..];
            let Some(end) = rest.find("\n\n") else { break };
            let block = &rest[..end];
            let kind = block["event: ".len()..]
                .lines()
                .next()
                .unwrap_or("")
                .to_string();
            if let Some(d) = block.lines().find_map(|l| l.strip_prefix("data: "))
                && let Ok(v) = serde_json::from_str(d)
            {
                seen.push((kind, v));
            }
            buf = buf[i + end + 2..].to_string();
        }
    }
    seen
}

#[test]
fn the_event_stream_pushes_frames_status_and_timeline_rows() {
    let (_scratch, cfg, state, addr) = setup("viewer-events");
    let d = start(&cfg, &state);
    wait_ready(&addr);
    let seen = events(&addr, |e| {
        let frames: Vec<u64> = e
            .iter()
            .filter(|(k, _)| k == "frame")
            .filter_map(|(_, v)| v["seq"].as_u64())
            .collect();
        frames.len() >= 2
            && frames.windows(2).all(|w| w[0] < w[1])
            && e.iter().any(|(k, _)| k == "status")
            && e.iter()
                .any(|(k, v)| k == "rows" && !v["rows"].as_array().unwrap().is_empty())
    });
    let kinds: Vec<&str> = seen.iter().map(|(k, _)| k.as_str()).collect();
    let frames: Vec<&serde_json::Value> = seen
        .iter()
        .filter(|(k, _)| k == "frame")
        .map(|(_, v)| v)
        .collect();
    assert!(frames.len() >= 2, "frames arrive and change: {kinds:?}");
    assert!(
        frames
            .windows(2)
            .all(|w| w[0]["seq"].as_u64() < w[1]["seq"].as_u64())
    );
    assert!(frames[0]["rendered_unix_ms"].as_f64().unwrap() > 1e12);
    let status = &seen
        .iter()
        .find(|(k, _)| k == "status")
        .expect("a status event")
        .1;
    assert!(status["camera"]["eye"].is_array() && status["scripts"][0]["name"] == "water");
    let rows = &seen
        .iter()
        .find(|(k, v)| k == "rows" && !v["rows"].as_array().unwrap().is_empty())
        .expect("a rows event")
        .1;
    assert_eq!(rows["columns"][0], "tick");
    assert!(
        rows["columns"]
            .as_array()
            .unwrap()
            .iter()
            .any(|c| c == "ms:water")
    );
    // The frame itself is a plain PNG, never cached.
    let mut s = TcpStream::connect(&addr).unwrap();
    write!(
        s,
        "GET /frame.png HTTP/1.1\r\nHost: localhost\r\nConnection: close\r\n\r\n"
    )
    .unwrap();
    let mut png = Vec::new();
    s.read_to_end(&mut png).unwrap();
    let head = String::from_utf8_lossy(&png[..png.len().min(400)]).to_lowercase();
    assert!(head.starts_with("http/1.1 200"), "{head}");
    assert!(
        head.contains("content-type: image/png") && head.contains("cache-control: no-store"),
        "{head}"
    );
    // /timeline hands out the same rows; bad arguments are a 400.
    let (code, body) = request(&addr, "GET", "/timeline?since=0", None, "").unwrap();
    assert_eq!(code, 200, "{body}");
    assert!(body.contains("\"steps_per_s\""));
    assert_eq!(
        request(&addr, "GET", "/timeline?since=x", None, "")
            .unwrap()
            .0,
        400
    );
    // The page is self-contained and small.
    let (code, page) = request(&addr, "GET", "/", None, "").unwrap();
    assert_eq!(code, 200);
    assert!(page.len() < 1 << 20, "the page is {} bytes", page.len());
    assert!(
        page.contains("EventSource") && !page.contains("http://") && !page.contains("https://")
    );
    assert!(
        !page.contains("localStorage"),
        "the token must live in sessionStorage only"
    );
    // Frames are fetched when an event says so, never polled on a timer.
    assert!(!page.contains("setInterval"), "the page polls");
    let out = stop(d);
    assert!(
        out.status.success(),
        "{}",
        String::from_utf8_lossy(&out.stderr)
    );
}

#[test]
fn parameter_changes_get_the_engines_verdict_and_viewers_share_the_camera_by_lease() {
    let (_scratch, cfg, state, addr) = setup("viewer-verdicts");
    let d = start(&cfg, &state);
    wait_ready(&addr);
    // Applied: the answer says so, and /status agrees.
    let (code, body) = post(&addr, &state, "/scripts/water/params", "{\"rain\": 0.7}");
    assert_eq!(code, 200, "{body}");
    assert!(body.contains("\"applied\": true"), "{body}");
    let t = Instant::now();
    while status(&addr)["scripts"][0]["params"][3]["value"] != 0.7 {
        assert!(
            t.elapsed() < Duration::from_secs(10),
            "applied but not shown"
        );
        std::thread::sleep(Duration::from_millis(20));
    }
    // Refused: out of range and not a number, with the reason.
    let (code, body) = post(&addr, &state, "/scripts/water/params", "{\"rain\": 50}");
    assert_eq!(code, 400);
    assert!(body.contains("outside [0, 10]"), "{body}");
    assert_eq!(
        post(&addr, &state, "/scripts/water/params", "{\"rain\": \"x\"}").0,
        400
    );
    // The token: the page's check, wrong and right.
    assert_eq!(
        request(&addr, "POST", "/auth", Some("wrong"), "")
            .unwrap()
            .0,
        401
    );
    assert_eq!(post(&addr, &state, "/auth", "").0, 200);
    // The camera lease: viewer a moves; b is refused while a moves; ctl wins.
    let cam =
        |v: &str| format!("{{\"eye\": [5, 60, 5], \"target\": [24, 10, 24], \"viewer\": \"{v}\"}}");
    assert_eq!(post(&addr, &state, "/camera", &cam("a")).0, 200);
    let (code, body) = post(&addr, &state, "/camera", &cam("b"));
    assert_eq!(code, 409, "{body}");
    assert!(body.contains("another viewer"), "{body}");
    assert_eq!(post(&addr, &state, "/camera", &cam("bad id!")).0, 400);
    let t = Instant::now();
    while status(&addr)["camera"]["mode"] != "set" {
        assert!(
            t.elapsed() < Duration::from_secs(10),
            "the camera was not set"
        );
        std::thread::sleep(Duration::from_millis(50));
    }
    assert_eq!(status(&addr)["camera"]["eye"][1], 60.0);
    // A viewer's return to the path is held to the lease too (regression,
    // viewer probe: any page took the camera from the viewer holding it);
    // the holder's own return, and an administrative one, are not.
    assert_eq!(post(&addr, &state, "/camera", &cam("a")).0, 200);
    let (code, body) = post(&addr, &state, "/camera/path", "{\"viewer\": \"b\"}");
    assert_eq!(code, 409, "{body}");
    assert_eq!(
        post(&addr, &state, "/camera/path", "{\"viewer\": \"bad id!\"}").0,
        400
    );
    assert_eq!(
        post(&addr, &state, "/camera/path", "{\"viewr\": \"a\"}").0,
        400
    );
    assert_eq!(
        post(&addr, &state, "/camera/path", "{\"viewer\": \"a\"}").0,
        200
    );
    // Back to the world's path.
    assert_eq!(post(&addr, &state, "/camera/path", "").0, 200);
    while status(&addr)["camera"]["mode"] != "path" {
        assert!(
            t.elapsed() < Duration::from_secs(10),
            "the camera did not return to its path"
        );
        std::thread::sleep(Duration::from_millis(50));
    }
    let out = stop(d);
    assert!(
        out.status.success(),
        "{}",
        String::from_utf8_lossy(&out.stderr)
    );
}

fn ctl(state: &Path, addr: &str, args: &[&str]) -> std::process::Output {
    std::process::Command::new(env!("CARGO_BIN_EXE_brickworld"))
        .arg("ctl")
        .args(["--addr", addr])
        .arg("--state")
        .arg(state)
        .args(args)
        .output()
        .unwrap()
}

#[test]
fn ctl_params_reads_values_and_ctl_log_prints_a_scripts_lines_once() {
    let (_scratch, cfg, state, addr) = setup("viewer-ctl");
    // A script that logs every step.
    let dir = cfg.parent().unwrap().join("scripts");
    std::fs::create_dir_all(&dir).unwrap();
    std::fs::write(
        dir.join("logger.lua"),
        "return { channels = { \"logger_v\" }, params = { level = { default = 2, min = 0, max = 5 } },\n\
         passes = { { name = \"p\", reads = {}, writes = { \"logger_v\" },\n\
         kernel = function(c, tx, tz) if tx == 0 and tz == 0 then log(\"tick\", c.tick) end end } } }\n",
    )
    .unwrap();
    let text = std::fs::read_to_string(&cfg).unwrap();
    let text = text
        .replace(
            &format!("{}/scripts", env!("CARGO_MANIFEST_DIR")),
            &dir.display().to_string(),
        )
        .replace(
            "file = \"water.lua\"\nparams = { rain = 0.2 }",
            "file = \"logger.lua\"",
        );
    std::fs::write(&cfg, text).unwrap();
    let d = start(&cfg, &state);
    wait_ready(&addr);
    let out = ctl(&state, &addr, &["params", "logger"]);
    assert_success(&out);
    let text = String::from_utf8_lossy(&out.stdout);
    assert!(
        text.contains("logger.level = 2 (default 2, range [0, 5])"),
        "{text}"
    );
    assert_clear_failure(
        &ctl(&state, &addr, &["params", "nosuch"]),
        "ctl params nosuch",
        "no script named 'nosuch' (loaded: logger)",
    );
    // Wait for a few lines, then read them twice: no line twice within a run.
    let t = Instant::now();
    while status(&addr)["scripts"][0]["log_seq"].as_u64().unwrap_or(0) < 3 {
        assert!(
            t.elapsed() < Duration::from_secs(20),
            "the script logged nothing"
        );
        std::thread::sleep(Duration::from_millis(50));
    }
    // Paused, the log stands still: ctl log prints exactly what /status
    // keeps, and following it for a while prints each line once.
    assert_eq!(post(&addr, &state, "/pause", "").0, 200);
    std::thread::sleep(Duration::from_millis(300));
    let kept: Vec<String> = status(&addr)["scripts"][0]["log"]
        .as_array()
        .unwrap()
        .iter()
        .map(|l| format!("[logger] {}", l.as_str().unwrap()))
        .collect();
    assert!(kept.len() >= 3, "{kept:?}");
    let out = ctl(&state, &addr, &["--no-follow", "log", "logger"]);
    assert_success(&out);
    let lines: Vec<String> = String::from_utf8_lossy(&out.stdout)
        .lines()
        .map(String::from)
        .collect();
    assert_eq!(lines, kept);
    let follow = std::process::Command::new(env!("CARGO_BIN_EXE_brickworld"))
        .arg("ctl")
        .args(["--addr", &addr])
        .arg("--state")
        .arg(&state)
        .args(["log", "logger"])
        .stdout(std::process::Stdio::piped())
        .spawn()
        .unwrap();
    // Three polls or more.
    std::thread::sleep(Duration::from_millis(1800));
    let _ = std::process::Command::new("kill")
        .arg(follow.id().to_string())
        .status();
    let out = follow.wait_with_output().unwrap();
    let followed: Vec<String> = String::from_utf8_lossy(&out.stdout)
        .lines()
        .map(String::from)
        .collect();
    assert_eq!(
        followed, kept,
        "following printed a line twice or missed one"
    );
    let out = stop(d);
    assert!(
        out.status.success(),
        "{}",
        String::from_utf8_lossy(&out.stderr)
    );
}

/// Read `s` for at most `limit`: true once the server closes it, or once
/// `done` says so of all read so far.
fn read_until(s: &mut TcpStream, limit: Duration, done: impl Fn(&[u8]) -> bool) -> bool {
    let t = Instant::now();
    let mut seen = Vec::new();
    let mut b = [0u8; 4096];
    while t.elapsed() < limit {
        s.set_read_timeout(Some(Duration::from_millis(100)))
            .unwrap();
        match s.read(&mut b) {
            Ok(0) => return true,
            Ok(n) => {
                seen.extend_from_slice(&b[..n]);
                if done(&seen) {
                    return true;
                }
            }
            Err(e)
                if matches!(
                    e.kind(),
                    std::io::ErrorKind::WouldBlock | std::io::ErrorKind::TimedOut
                ) => {}
            Err(_) => return true,
        }
    }
    false
}

/// Whether the event stream on `s` ends within `limit`: the connection
/// closes, or the chunked body's last chunk arrives.
fn stream_ended(s: &mut TcpStream, limit: Duration) -> bool {
    read_until(s, limit, |seen| seen.windows(5).any(|w| w == b"0\r\n\r\n"))
}

/// Whether the server closes `s` within `limit` (what it sent is read and
/// dropped).
fn closed_within(s: &mut TcpStream, limit: Duration) -> bool {
    read_until(s, limit, |_| false)
}

/// Viewers that never read their stream do not slow the engine or shut out
/// other requests or viewers: past the viewer limit a new stream takes the
/// longest-connected one's slot (regression: sixteen streams that never read
/// got every later viewer a 503, for ever while the engine was paused).
#[test]
fn viewers_that_never_read_do_not_hold_up_the_engine() {
    let (_scratch, cfg, state, addr) = setup("viewer-stalled");
    let d = start(&cfg, &state);
    wait_ready(&addr);
    let mut stalled = Vec::new();
    for _ in 0..16 {
        let mut s = TcpStream::connect(&addr).unwrap();
        write!(s, "GET /events HTTP/1.1\r\nHost: localhost\r\n\r\n").unwrap();
        stalled.push(s);
    }
    std::thread::sleep(Duration::from_millis(500));
    // Paused: nothing is sent that could fill the stalled streams' buffers.
    assert_eq!(post(&addr, &state, "/pause", "").0, 200);
    let mut newer = TcpStream::connect(&addr).unwrap();
    newer
        .set_read_timeout(Some(Duration::from_secs(10)))
        .unwrap();
    write!(newer, "GET /events HTTP/1.1\r\nHost: localhost\r\n\r\n").unwrap();
    let mut b = [0u8; 64];
    let n = newer.read(&mut b).unwrap_or(0);
    assert!(
        String::from_utf8_lossy(&b[..n]).starts_with("HTTP/1.1 200"),
        "{}",
        String::from_utf8_lossy(&b[..n])
    );
    // The longest-connected stream was ended (its chunked body closed or
    // the connection dropped), a newer one was not (audit: not checked).
    assert!(
        stream_ended(&mut stalled[0], Duration::from_secs(10)),
        "the oldest stream was not ended"
    );
    // And its connection is closed at once (within the server's 1 s watch),
    // not left to hyper, which waits to flush into a client that reads
    // nothing (regression, hostile probe: such connections stayed for
    // ever, each holding a slot and its socket buffer). A client that does
    // read would see hyper close it only after the 5 s head limit.
    assert!(
        closed_within(&mut stalled[0], Duration::from_secs(4)),
        "the ended stream's connection stayed open"
    );
    assert!(
        !stream_ended(&mut stalled[1], Duration::from_millis(500)),
        "a newer stream was ended"
    );
    assert_eq!(post(&addr, &state, "/resume", "").0, 200);
    let t0 = status(&addr)["tick"].as_u64().unwrap();
    std::thread::sleep(Duration::from_secs(2));
    let t1 = status(&addr)["tick"].as_u64().unwrap();
    assert!(t1 > t0 + 5, "the engine stalled: tick {t0} then {t1}");
    assert_eq!(post(&addr, &state, "/pause", "").0, 200);
    // A stream opens once they close (that their slots are freed, rather
    // than taken by eviction, is `live`'s unit test).
    drop(stalled);
    let t = Instant::now();
    loop {
        let mut s = TcpStream::connect(&addr).unwrap();
        s.set_read_timeout(Some(Duration::from_secs(2))).unwrap();
        write!(s, "GET /events HTTP/1.1\r\nHost: localhost\r\n\r\n").unwrap();
        let mut b = [0u8; 64];
        let n = s.read(&mut b).unwrap_or(0);
        if String::from_utf8_lossy(&b[..n]).starts_with("HTTP/1.1 200") {
            break;
        }
        assert!(
            t.elapsed() < Duration::from_secs(10),
            "slots were not freed"
        );
        std::thread::sleep(Duration::from_millis(200));
    }
    let out = stop(d);
    assert!(
        out.status.success(),
        "{}",
        String::from_utf8_lossy(&out.stderr)
    );
}

/// Regression (viewer probe): moving the camera of a paused engine showed
/// nothing, as frames came only every `frames.every` ticks. A camera move
/// (and a return to the path) renders a view of the present tick for the
/// live viewers as soon as the renderer is idle, without stepping and
/// without a file in the frames directory, which keeps one frame per
/// `frames.every` ticks.
#[test]
fn a_camera_move_shows_at_once_even_paused() {
    let (_scratch, cfg, state, addr) = setup("viewer-camera-paused");
    let d = spawn(run_cmd(&cfg, &state).arg("--paused"));
    wait_ready(&addr);
    let frames = |addr: &str| status(addr)["frames"].as_u64().unwrap();
    let on_disk = || {
        std::fs::read_dir(state.join("frames")).map_or(0, |d| {
            d.flatten()
                .filter(|e| e.file_name().to_string_lossy().starts_with("frame-"))
                .count()
        })
    };
    let (tick, before, files) = (status(&addr)["tick"].clone(), frames(&addr), on_disk());
    let wait_for_frame = |after: u64| {
        let t = Instant::now();
        while frames(&addr) <= after {
            assert!(
                t.elapsed() < Duration::from_secs(30),
                "no frame after the camera moved"
            );
            std::thread::sleep(Duration::from_millis(50));
        }
    };
    let cam = "{\"eye\": [-20, 60, -20], \"target\": [24, 10, 24], \"fov\": 45}";
    assert_eq!(post(&addr, &state, "/camera", cam).0, 200);
    wait_for_frame(before);
    let (code, png) = request(&addr, "GET", "/frame.png", None, "").unwrap();
    assert_eq!(code, 200, "{png}");
    let shown = frames(&addr);
    assert_eq!(post(&addr, &state, "/camera/path", "").0, 200);
    wait_for_frame(shown);
    assert_eq!(status(&addr)["tick"], tick, "nothing stepped");
    assert_eq!(on_disk(), files, "a view went into the frames directory");
    let out = stop(d);
    assert!(
        out.status.success(),
        "{}",
        String::from_utf8_lossy(&out.stderr)
    );
}

/// A script with nothing awake for it is shown as sleeping, not running.
#[test]
fn a_script_with_nothing_awake_is_shown_sleeping() {
    let (_scratch, cfg, state, addr) = setup("viewer-sleeping");
    edit_config(&cfg, "params = { rain = 0.2 }", "params = { rain = 0.0 }");
    let d = start(&cfg, &state);
    wait_ready(&addr);
    let t = Instant::now();
    while status(&addr)["scripts"][0]["state"] != "sleeping" {
        assert!(
            t.elapsed() < Duration::from_secs(30),
            "a dry world's water never sleeps: {}",
            status(&addr)["scripts"][0]
        );
        std::thread::sleep(Duration::from_millis(50));
    }
    // Rain wakes it: running again.
    assert_eq!(
        post(&addr, &state, "/scripts/water/params", "{\"rain\": 1}").0,
        200
    );
    while status(&addr)["scripts"][0]["state"] != "running" {
        assert!(
            t.elapsed() < Duration::from_secs(60),
            "rain did not wake the water"
        );
        std::thread::sleep(Duration::from_millis(50));
    }
    let out = stop(d);
    assert!(
        out.status.success(),
        "{}",
        String::from_utf8_lossy(&out.stderr)
    );
}

/// Audit: "`status` events at most every 250 ms and only when it changed"
/// had no test. A running engine's status changes every step: over 2 s a
/// stream gets at most 2 / 0.25 + 1 of them (and a few at least). A paused
/// engine's does not change: one event, then one only when the process's
/// RSS moved, never the same status twice.
#[test]
fn status_events_come_at_most_every_250_ms_and_only_when_it_changed() {
    let (_scratch, cfg, state, addr) = setup("viewer-throttle");
    let d = start(&cfg, &state);
    wait_ready(&addr);
    let count =
        |seen: &[(String, serde_json::Value)]| seen.iter().filter(|(k, _)| k == "status").count();
    let t = Instant::now();
    let running = count(&events(&addr, |_| t.elapsed() > Duration::from_secs(2)));
    let most = (t.elapsed().as_millis() / 250 + 1) as usize;
    assert!(
        (3..=most).contains(&running),
        "{running} status events (at most {most})"
    );
    assert_eq!(post(&addr, &state, "/pause", "").0, 200);
    // Paused, and its step rate has fallen to 0 (2 s after the last step:
    // regression, long-run probe, a paused engine showed the rate of its
    // last second of running).
    let settled = Instant::now();
    let at_rest =
        |s: &serde_json::Value| s["paused"] == true && s["scripts"][0]["steps_per_s"] == 0.0;
    while !at_rest(&status(&addr)) && settled.elapsed() < Duration::from_secs(30) {
        std::thread::sleep(Duration::from_millis(20));
    }
    let s = status(&addr);
    assert!(
        at_rest(&s),
        "a paused engine's steps_per_s: {}",
        s["scripts"][0]["steps_per_s"]
    );
    std::thread::sleep(Duration::from_millis(300));
    let t = Instant::now();
    let seen = events(&addr, |_| t.elapsed() > Duration::from_millis(1500));
    let shown: Vec<&serde_json::Value> = seen
        .iter()
        .filter(|(k, _)| k == "status")
        .map(|(_, v)| v)
        .collect();
    // Sent once, then again only when something changed: while paused only
    // the process's RSS and its peak can (they are sampled, not stepped).
    assert!(!shown.is_empty() && shown.len() <= 7, "{shown:#?}");
    for pair in shown.windows(2) {
        assert_ne!(pair[0], pair[1], "the same status was sent twice");
        let strip = |v: &serde_json::Value| {
            let mut v = v.clone();
            v.as_object_mut().unwrap().remove("rss_bytes");
            v.as_object_mut().unwrap().remove("rss_peak_bytes");
            v
        };
        assert_eq!(
            strip(pair[0]),
            strip(pair[1]),
            "a paused engine's status changed"
        );
    }
    let out = stop(d);
    assert!(
        out.status.success(),
        "{}",
        String::from_utf8_lossy(&out.stderr)
    );
}

/// Audit: "a client that has read nothing for 30 s is closed" had no test.
/// A viewer with a tiny receive buffer opens the event stream of a running
/// engine and never reads: once the stream's queue has been full for
/// `STALL_LIMIT`, the stream ends and the server closes the connection,
/// while the engine keeps ticking. The close is seen without reading (which
/// would unstall the stream), in the kernel's TCP table: the server's end
/// leaves ESTABLISHED. The buffers between the stream and the client take
/// a while to fill at the engine's few kilobytes of events a second
/// (measured: closed 37 s after opening with the server's bounded send
/// buffer, 109 s before it), so the test allows four minutes past the
/// limit on a slow machine.
#[cfg(target_os = "linux")]
#[test]
fn a_viewer_that_reads_nothing_is_closed_after_the_stall_limit() {
    use brickworld::engine::control::live::STALL_LIMIT;
    use nix::sys::socket::{
        AddressFamily, SockFlag, SockType, SockaddrIn, connect, setsockopt, socket, sockopt::RcvBuf,
    };
    let (_scratch, cfg, state, addr) = setup("viewer-stall-limit");
    let d = start(&cfg, &state);
    wait_ready(&addr);
    // The receive buffer is set before connecting: the window a connection
    // opens with is never shrunk afterwards.
    let fd = socket(
        AddressFamily::Inet,
        SockType::Stream,
        SockFlag::empty(),
        None,
    )
    .unwrap();
    setsockopt(&fd, RcvBuf, &2048).unwrap();
    let to: std::net::SocketAddrV4 = addr.parse().unwrap();
    connect(std::os::fd::AsRawFd::as_raw_fd(&fd), &SockaddrIn::from(to)).unwrap();
    let mut s = TcpStream::from(fd);
    write!(s, "GET /events HTTP/1.1\r\nHost: localhost\r\n\r\n").unwrap();
    let opened = Instant::now();
    let (local, remote) = (
        s.local_addr().unwrap().port(),
        s.peer_addr().unwrap().port(),
    );
    // The server's end of the connection leaves ESTABLISHED (01) when the
    // server closes it: its FIN waits behind data this client never reads
    // (FIN_WAIT1).
    let closed_by_server = || !server_end_in(remote, local, &["01"]);
    let t0 = status(&addr)["tick"].as_u64().unwrap();
    while !closed_by_server() {
        assert!(
            opened.elapsed() < STALL_LIMIT + Duration::from_secs(240),
            "the stalled stream was still open after {:?}",
            opened.elapsed()
        );
        std::thread::sleep(Duration::from_millis(250));
    }
    let waited = opened.elapsed();
    assert!(
        waited >= STALL_LIMIT,
        "closed after {waited:?}, before the limit"
    );
    let t1 = status(&addr)["tick"].as_u64().unwrap();
    assert!(t1 > t0, "the engine stalled: tick {t0} then {t1}");
    eprintln!("stalled stream closed after {waited:?}");
    drop(s);
    let out = stop(d);
    assert!(
        out.status.success(),
        "{}",
        String::from_utf8_lossy(&out.stderr)
    );
}
