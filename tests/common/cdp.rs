//! A minimal Chrome DevTools Protocol client for browser tests: starts
//! headless Chromium (Debian's package), attaches to one page over the
//! protocol's WebSocket (flat sessions), sends commands and keeps the events
//! that arrive meanwhile. Every wait has a deadline; Chromium is killed when
//! the client is dropped.

use std::io::{BufRead, BufReader};
use std::net::TcpStream;
use std::os::unix::process::CommandExt;
use std::process::{Child, Command, Stdio};
use std::time::{Duration, Instant};

use serde_json::{Value, json};
use tungstenite::{Message, WebSocket};

/// The Chromium binary: `BRICKWORLD_CHROMIUM`, else Debian's.
pub fn chromium_path() -> Option<std::path::PathBuf> {
    if let Some(p) = std::env::var_os("BRICKWORLD_CHROMIUM") {
        return Some(p.into());
    }
    ["/usr/bin/chromium", "/usr/bin/chromium-browser"]
        .iter()
        .map(std::path::PathBuf::from)
        .find(|p| p.exists())
}

/// Whether a missing browser must fail the test (CI, where `.ci/run`
/// installs it) rather than skip it.
pub fn browser_required() -> bool {
    std::env::var("BRICKWORLD_REQUIRE_BROWSER").as_deref() == Ok("1")
}

/// A page in headless Chromium.
pub struct Browser {
    child: Child,
    ws: WebSocket<TcpStream>,
    session: String,
    next: u64,
    /// Protocol events received so far (method and params).
    pub events: Vec<Value>,
    _profile: tempdir::Dir,
}

mod tempdir {
    /// A directory removed on drop.
    pub struct Dir(pub std::path::PathBuf);
    impl Drop for Dir {
        fn drop(&mut self) {
            // A process that was writing in it may take a moment to go
            // (regression: a profile half removed under a Chromium helper
            // still writing was left behind, and `.ci/run` failed on it).
            for _ in 0..100 {
                if std::fs::remove_dir_all(&self.0).is_ok() || !self.0.exists() {
                    return;
                }
                std::thread::sleep(std::time::Duration::from_millis(20));
            }
        }
    }
}

impl Browser {
    /// Start Chromium (the flags the machine notes require: no sandbox as
    /// root, no background networking on a closed network) with a
    /// `width`×`height` page, attached and with Runtime, Log and Page events on.
    pub fn start(exe: &std::path::Path, width: u32, height: u32) -> Browser {
        let profile = std::env::temp_dir().join(format!(
            "brickworld-chromium-{}-{}",
            std::process::id(),
            Instant::now().elapsed().as_nanos()
        ));
        // Chromium's own temporary files go inside the profile, which is
        // removed with it (regression: a killed Chromium left its
        // `org.chromium.Chromium.*` folders in the temp dir, one a test).
        let own_tmp = profile.join("tmp");
        std::fs::create_dir_all(&own_tmp).unwrap();
        let profile_guard = tempdir::Dir(profile.clone());
        // In a process group of its own, so that its helper processes
        // (renderer, GPU, zygote) go with it (see Drop).
        let mut child = Command::new(exe)
            .process_group(0)
            .env("TMPDIR", &own_tmp)
            .args([
                "--headless",
                "--no-sandbox",
                "--disable-gpu",
                "--disable-quic",
                "--no-first-run",
                "--disable-background-networking",
                "--disable-component-update",
                "--disable-sync",
                "--remote-debugging-port=0",
                "--hide-scrollbars",
                "--font-render-hinting=none",
            ])
            .arg(format!("--window-size={width},{height}"))
            .arg(format!("--user-data-dir={}", profile.display()))
            .arg("about:blank")
            .stdout(Stdio::null())
            .stderr(Stdio::piped())
            .spawn()
            .expect("start chromium");
        // "DevTools listening on ws://127.0.0.1:PORT/devtools/browser/ID".
        let stderr = child.stderr.take().unwrap();
        let (tx, rx) = std::sync::mpsc::channel();
        std::thread::spawn(move || {
            for line in BufReader::new(stderr).lines().map_while(Result::ok) {
                if let Some(i) = line.find("ws://") {
                    let _ = tx.send(line[i..].trim().to_string());
                }
            }
        });
        let url = match rx.recv_timeout(Duration::from_secs(60)) {
            Ok(u) => u,
            Err(_) => {
                let group = nix::unistd::Pid::from_raw(child.id() as i32);
                let _ = nix::sys::signal::killpg(group, nix::sys::signal::Signal::SIGKILL);
                let _ = child.wait();
                panic!("chromium did not open its DevTools port within 60 s");
            }
        };
        let hostport = url["ws://".len()..].split('/').next().unwrap().to_string();
        let stream = TcpStream::connect(&hostport).unwrap();
        stream
            .set_read_timeout(Some(Duration::from_secs(30)))
            .unwrap();
        let (ws, _) = tungstenite::client(url.as_str(), stream).expect("DevTools handshake");
        // Short reads from now on, so that every wait checks its deadline.
        ws.get_ref()
            .set_read_timeout(Some(Duration::from_millis(200)))
            .unwrap();
        let mut b = Browser {
            child,
            ws,
            session: String::new(),
            next: 1,
            events: Vec::new(),
            _profile: profile_guard,
        };
        let target = b.call("Target.createTarget", json!({ "url": "about:blank" }));
        let target = target["targetId"].as_str().unwrap().to_string();
        let s = b.call(
            "Target.attachToTarget",
            json!({ "targetId": target, "flatten": true }),
        );
        b.session = s["sessionId"].as_str().unwrap().to_string();
        for m in ["Runtime.enable", "Log.enable", "Page.enable"] {
            b.call(m, json!({}));
        }
        b.call(
            "Emulation.setDeviceMetricsOverride",
            json!({ "width": width, "height": height, "deviceScaleFactor": 1, "mobile": false }),
        );
        b
    }

    /// Send a command (to the page once attached) and wait up to 30 s for
    /// its answer; a protocol error panics with its message.
    pub fn call(&mut self, method: &str, params: Value) -> Value {
        let id = self.next;
        self.next += 1;
        let mut msg = json!({ "id": id, "method": method, "params": params });
        if !self.session.is_empty() {
            msg["sessionId"] = json!(self.session);
        }
        self.ws.send(Message::Text(msg.to_string().into())).unwrap();
        let t = Instant::now();
        while t.elapsed() < Duration::from_secs(30) {
            let m = match self.ws.read() {
                Ok(Message::Text(s)) => s,
                Ok(_) => continue,
                Err(tungstenite::Error::Io(e))
                    if matches!(
                        e.kind(),
                        std::io::ErrorKind::WouldBlock | std::io::ErrorKind::TimedOut
                    ) =>
                {
                    continue;
                }
                Err(e) => panic!("DevTools connection lost during {method}: {e}"),
            };
            let v: Value = serde_json::from_str(m.as_str()).unwrap();
            if v["id"] == id {
                if let Some(e) = v.get("error") {
                    panic!("{method} failed: {e}");
                }
                return v["result"].clone();
            }
            if v.get("method").is_some() {
                self.events.push(v);
            }
        }
        panic!("no answer to {method} within 30 s");
    }

    /// Load `url` and wait (up to 30 s) until the document is complete.
    pub fn navigate(&mut self, url: &str) {
        self.call("Page.navigate", json!({ "url": url }));
        self.wait_for(
            "the page loads",
            30,
            "location.href + ' ' + document.readyState",
            |v| v.as_str() == Some(&format!("{url} complete")),
        );
    }

    /// Evaluate `expr` in the page (promises awaited) and return its value.
    pub fn eval(&mut self, expr: &str) -> Value {
        let r = self.call(
            "Runtime.evaluate",
            json!({ "expression": expr, "awaitPromise": true, "returnByValue": true }),
        );
        if let Some(e) = r.get("exceptionDetails") {
            panic!("{expr} threw: {e}");
        }
        r["result"]["value"].clone()
    }

    /// Evaluate `expr` every 100 ms until `ok` accepts its value (within
    /// `secs`); returns that value, or panics saying `what` never happened.
    pub fn wait_for(
        &mut self,
        what: &str,
        secs: u64,
        expr: &str,
        ok: impl Fn(&Value) -> bool,
    ) -> Value {
        let t = Instant::now();
        loop {
            let v = self.eval(expr);
            if ok(&v) {
                return v;
            }
            assert!(
                t.elapsed() < Duration::from_secs(secs),
                "{what}: not within {secs} s (last value {v})"
            );
            std::thread::sleep(Duration::from_millis(100));
        }
    }

    /// Errors the page reported: uncaught exceptions, `console.error`, and
    /// log entries other than network responses (a 401 or 409 the page asked
    /// for and then shows is an answer, not an error of the page).
    pub fn page_errors(&self) -> Vec<String> {
        self.events
            .iter()
            .filter_map(|e| {
                let p = &e["params"];
                match e["method"].as_str()? {
                    "Runtime.exceptionThrown" => Some(p["exceptionDetails"].to_string()),
                    "Runtime.consoleAPICalled" if p["type"] == "error" => {
                        Some(p["args"].to_string())
                    }
                    "Log.entryAdded"
                        if p["entry"]["level"] == "error" && p["entry"]["source"] != "network" =>
                    {
                        Some(p["entry"]["text"].to_string())
                    }
                    _ => None,
                }
            })
            .collect()
    }

    /// A left-button drag from `from` to `to` in page pixels, in `steps` moves.
    pub fn drag(&mut self, from: (f64, f64), to: (f64, f64), steps: u32) {
        let ev = |t: &str, x: f64, y: f64, buttons: u32| json!({ "type": t, "x": x, "y": y, "button": "left", "buttons": buttons, "clickCount": 1 });
        self.call(
            "Input.dispatchMouseEvent",
            ev("mouseMoved", from.0, from.1, 0),
        );
        self.call(
            "Input.dispatchMouseEvent",
            ev("mousePressed", from.0, from.1, 1),
        );
        for i in 1..=steps {
            let f = i as f64 / steps as f64;
            let (x, y) = (from.0 + (to.0 - from.0) * f, from.1 + (to.1 - from.1) * f);
            self.call("Input.dispatchMouseEvent", ev("mouseMoved", x, y, 1));
            std::thread::sleep(Duration::from_millis(30));
        }
        self.call(
            "Input.dispatchMouseEvent",
            ev("mouseReleased", to.0, to.1, 0),
        );
    }

    /// Press and release a key (`key` as the DOM names it, with its
    /// Windows virtual key code) on the focused element.
    pub fn key(&mut self, key: &str, code: u32) {
        for t in ["rawKeyDown", "keyUp"] {
            self.call(
                "Input.dispatchKeyEvent",
                json!({ "type": t, "key": key, "code": key, "windowsVirtualKeyCode": code }),
            );
        }
    }

    /// A PNG screenshot of the page, decoded to RGBA.
    pub fn screenshot(&mut self) -> (u32, u32, Vec<u8>) {
        let r = self.call("Page.captureScreenshot", json!({ "format": "png" }));
        let png = base64(r["data"].as_str().unwrap());
        decode_png(&png)
    }
}

impl Drop for Browser {
    fn drop(&mut self) {
        // The whole group: killing the browser alone left its helpers
        // writing into the profile while it was removed.
        let group = nix::unistd::Pid::from_raw(self.child.id() as i32);
        let _ = nix::sys::signal::killpg(group, nix::sys::signal::Signal::SIGKILL);
        let _ = self.child.kill();
        let _ = self.child.wait();
    }
}

/// Standard base64 (the protocol's screenshots), padding allowed.
pub fn base64(s: &str) -> Vec<u8> {
    let val = |c: u8| match c {
        b'A'..=b'Z' => c - b'A',
        b'a'..=b'z' => c - b'a' + 26,
        b'0'..=b'9' => c - b'0' + 52,
        b'+' => 62,
        b'/' => 63,
        _ => panic!("not base64: {c}"),
    };
    let bytes: Vec<u8> = s
        .bytes()
        .filter(|&c| c != b'=' && !c.is_ascii_whitespace())
        .collect();
    let mut out = Vec::with_capacity(bytes.len() * 3 / 4);
    for chunk in bytes.chunks(4) {
        let mut acc = 0u32;
        for (i, &c) in chunk.iter().enumerate() {
            acc |= (val(c) as u32) << (18 - 6 * i);
        }
        let n = chunk.len() * 6 / 8;
        out.extend_from_slice(&acc.to_be_bytes()[1..1 + n]);
    }
    out
}

/// Decode a PNG to 8-bit RGBA.
pub fn decode_png(bytes: &[u8]) -> (u32, u32, Vec<u8>) {
    let mut dec = png::Decoder::new(std::io::Cursor::new(bytes));
    dec.set_transformations(png::Transformations::EXPAND | png::Transformations::ALPHA);
    let mut r = dec.read_info().unwrap();
    let mut buf = vec![0; r.output_buffer_size().unwrap()];
    let info = r.next_frame(&mut buf).unwrap();
    buf.truncate(info.buffer_size());
    assert_eq!(info.bit_depth, png::BitDepth::Eight);
    let rgba = match info.color_type {
        png::ColorType::Rgba => buf,
        png::ColorType::Rgb => buf
            .chunks(3)
            .flat_map(|p| [p[0], p[1], p[2], 255])
            .collect(),
        c => panic!("unexpected PNG colour type {c:?}"),
    };
    (info.width, info.height, rgba)
}
