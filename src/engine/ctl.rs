//! `brickworld ctl`: a small HTTP client for a running engine; it reads the
//! control token from the state directory. `ctl params [SCRIPT]` prints
//! parameter values with their defaults and ranges; `ctl log [SCRIPT]`
//! follows scripts' `log(...)` lines (by their sequence numbers in
//! `/status`, so a line is printed once, and lines lost to the rate limit
//! or to a gap between polls are counted).

use std::io::{Read, Write};
use std::net::TcpStream;
use std::time::Duration;

use anyhow::{Context, Result, bail};

use crate::cli::CtlArgs;

/// The longest a request may take, all reads together.
pub const DEADLINE: Duration = Duration::from_secs(60);
/// The largest answer read (a `/status` of many scripts is a few MB).
pub const MAX_RESPONSE: u64 = 64 << 20;

/// `text` with every byte but letters, digits and `-_.~` as `%XX`, for a
/// path segment (regression: a script name with a space or CR/LF went into
/// the request line raw; `water?x` became a query).
pub fn percent_encoded(text: &str) -> String {
    let mut out = String::with_capacity(text.len());
    for b in text.bytes() {
        if b.is_ascii_alphanumeric() || b"-_.~".contains(&b) {
            out.push(b as char);
        } else {
            out.push_str(&format!("%{b:02X}"));
        }
    }
    out
}

/// Send one request; returns (status code, body). The answer must be HTTP,
/// arrive within [`DEADLINE`] and be at most [`MAX_RESPONSE`] bytes: a
/// server that trickles or streams for ever, or is not HTTP, is an error
/// (regression: `ctl` waited for ever or filled memory).
pub fn request(
    addr: &str,
    method: &str,
    path: &str,
    token: Option<&str>,
    body: &str,
) -> Result<(u16, String)> {
    request_within(addr, method, path, token, body, DEADLINE)
}

/// [`request`] with its own deadline in place of [`DEADLINE`] (for tests).
pub fn request_within(
    addr: &str,
    method: &str,
    path: &str,
    token: Option<&str>,
    body: &str,
    deadline: Duration,
) -> Result<(u16, String)> {
    let mut s = TcpStream::connect(addr).with_context(|| {
        format!("cannot reach the engine at {addr} (is `brickworld run` running?)")
    })?;
    let start = std::time::Instant::now();
    s.set_read_timeout(Some(deadline))?;
    s.set_write_timeout(Some(deadline))?;
    let auth = token
        .map(|t| format!("Authorization: Bearer {t}\r\n"))
        .unwrap_or_default();
    // The address connected to, not the name typed: the engine serves
    // only IPs and localhost unless told other names (a guard against DNS
    // rebinding that browsers need and `ctl` does not).
    let host = s
        .peer_addr()
        .map_or_else(|_| addr.to_string(), |a| a.to_string());
    write!(
        s,
        "{method} {path} HTTP/1.1\r\nHost: {host}\r\n{auth}Content-Length: {}\r\nConnection: close\r\n\r\n{body}",
        body.len()
    )?;
    // A command sent but not answered may still be carried out: the
    // request waits in the engine's socket until it reads it (regression,
    // crash probe: `ctl pause` to a stopped engine failed after 60 s, and
    // the engine paused when it was continued).
    let unsure = if method == "GET" {
        ""
    } else {
        "; the command was sent and may still be carried out (see `brickworld ctl status`)"
    };
    let late = || {
        anyhow::anyhow!(
            "{addr} did not answer within {} s{unsure}",
            deadline.as_secs()
        )
    };
    // Regression (crash probe): an engine killed mid-request was "not HTTP".
    let closed = || {
        anyhow::anyhow!(
            "{addr} closed the connection before answering (did the engine stop?){unsure}"
        )
    };
    let mut raw = Vec::new();
    let mut buf = [0u8; 64 << 10];
    loop {
        let left = deadline.saturating_sub(start.elapsed());
        if left.is_zero() {
            return Err(late());
        }
        s.set_read_timeout(Some(left))?;
        let n = match s.read(&mut buf) {
            Ok(n) => n,
            Err(e)
                if matches!(
                    e.kind(),
                    std::io::ErrorKind::WouldBlock | std::io::ErrorKind::TimedOut
                ) =>
            {
                return Err(late());
            }
            Err(e)
                if raw.is_empty()
                    && matches!(
                        e.kind(),
                        std::io::ErrorKind::ConnectionReset | std::io::ErrorKind::ConnectionAborted
                    ) =>
            {
                return Err(closed());
            }
            Err(e) => return Err(e).with_context(|| format!("reading the answer from {addr}")),
        };
        if n == 0 {
            if raw.is_empty() {
                return Err(closed());
            }
            break;
        }
        raw.extend_from_slice(&buf[..n]);
        if raw.len() as u64 > MAX_RESPONSE {
            bail!("{addr} sent more than {MAX_RESPONSE} bytes: not a brickworld engine's answer");
        }
    }
    let resp = String::from_utf8_lossy(&raw);
    let not_http = || anyhow::anyhow!("{addr} did not answer in HTTP: is it a brickworld engine?");
    let (head, body) = resp.split_once("\r\n\r\n").ok_or_else(not_http)?;
    let mut status = head.split_whitespace();
    if !status.next().is_some_and(|v| v.starts_with("HTTP/1.")) {
        return Err(not_http());
    }
    let code: u16 = status
        .next()
        .and_then(|c| c.parse().ok())
        .filter(|c| (100..600).contains(c))
        .ok_or_else(not_http)?;
    Ok((code, body.to_string()))
}

/// `a` with the options written after the command words moved where
/// clap puts them, and the command words alone. The words take values that
/// start with '-' (`param water rain -1e-3`), so clap leaves everything
/// after the first word to them (regression, hostile probe 2: `ctl status
/// --addr A` was an "unknown ctl command").
fn with_trailing_options(a: &CtlArgs) -> Result<(CtlArgs, Vec<String>)> {
    let mut out = a.clone();
    let mut words = Vec::new();
    let mut it = a.command.iter();
    while let Some(w) = it.next() {
        let (name, inline) = match w.split_once('=') {
            Some((n, v)) if n.starts_with("--") => (n, Some(v.to_string())),
            _ => (w.as_str(), None),
        };
        let mut value = |what: &str| -> Result<String> {
            inline
                .clone()
                .or_else(|| it.next().cloned())
                .with_context(|| format!("{what} needs a value"))
        };
        match name {
            "--no-follow" if inline.is_none() => out.no_follow = true,
            "--no-follow" => bail!("--no-follow takes no value"),
            "--help" => bail!("--help goes before the command words: brickworld ctl --help"),
            "--addr" => out.addr = Some(value("--addr")?),
            "--state" => out.state = value("--state")?.into(),
            n if n.starts_with("--") => bail!(
                "unknown option '{n}' for ctl (its options are --addr, --state and --no-follow)"
            ),
            _ => words.push(w.clone()),
        }
    }
    out.command = words.clone();
    Ok((out, words))
}

/// `ctl`'s default engine address.
pub const DEFAULT_ADDR: &str = "127.0.0.1:7878";
/// `ctl`'s default state directory.
pub const DEFAULT_STATE: &str = "state";

/// The `brickworld ctl` command that reaches the engine at `addr` with the
/// token in `state`: the flags are given only where they are not `ctl`'s
/// defaults (regression, newcomer walk: an engine on another address said
/// to run `brickworld ctl resume`, which could not reach it).
///
/// ```
/// use std::path::Path;
/// use brickworld::engine::ctl::ctl_command;
/// assert_eq!(ctl_command("127.0.0.1:7878".parse().unwrap(), Path::new("state")), "brickworld ctl");
/// assert_eq!(
///     ctl_command("127.0.0.1:7979".parse().unwrap(), Path::new("my state")),
///     "brickworld ctl --addr 127.0.0.1:7979 --state 'my state'"
/// );
/// assert_eq!(
///     ctl_command("[::1]:7979".parse().unwrap(), Path::new("state")),
///     "brickworld ctl --addr '[::1]:7979'"
/// );
/// ```
pub fn ctl_command(addr: std::net::SocketAddr, state: &std::path::Path) -> String {
    let mut c = String::from("brickworld ctl");
    if addr.to_string() != DEFAULT_ADDR {
        // Quoted where a shell would read it otherwise (IPv6's brackets
        // are a glob pattern; review).
        c += &format!(
            " --addr {}",
            crate::shell_quoted(std::path::Path::new(&addr.to_string()))
        );
    }
    if state != std::path::Path::new(DEFAULT_STATE) {
        c += &format!(" --state {}", crate::shell_quoted(state));
    }
    c
}

/// Run `brickworld ctl`.
pub fn run(a: &CtlArgs) -> Result<()> {
    let (a, words) = with_trailing_options(a)?;
    // The address given, else the one the engine of `--state` bound (an
    // engine on port 0 picks its own; long-run probe: `ctl --state` could
    // not find it), else the default.
    let addr = match &a.addr {
        Some(addr) => addr.clone(),
        None => crate::engine::state_dir::read_addr(&a.state)
            .map_err(|e| anyhow::anyhow!(e))?
            .unwrap_or_else(|| DEFAULT_ADDR.to_string()),
    };
    let a = &a;
    let words: Vec<&str> = words.iter().map(|s| s.as_str()).collect();
    let token_path = a.state.join("control.token");
    let token = || {
        crate::files::read_text(&token_path, 4096).map_err(|e| match e {
            crate::files::FileError::Io { error, .. } => anyhow::anyhow!(
                "cannot read the control token {}: {error} (is the engine running with --state {}?)",
                token_path.display(),
                a.state.display()
            ),
            e => anyhow::anyhow!("the control token: {e}"),
        })
    };
    match words.as_slice() {
        ["params"] => return params(&addr, None),
        ["params", script] => return params(&addr, Some(script)),
        ["log"] => return log(&addr, None, !a.no_follow),
        ["log", script] => return log(&addr, Some(script), !a.no_follow),
        _ => {}
    }
    let (method, path, body) = match words.as_slice() {
        ["camera", "path"] => ("POST", "/camera/path".into(), String::new()),
        ["status"] => ("GET", "/status".to_string(), String::new()),
        ["pause"] => ("POST", "/pause".into(), String::new()),
        ["resume"] => ("POST", "/resume".into(), String::new()),
        ["checkpoint"] | ["commit"] => ("POST", "/checkpoint".into(), String::new()),
        ["step"] => ("POST", "/step".into(), "1".into()),
        ["step", n] => ("POST", "/step".into(), n.to_string()),
        ["param", script, name, value] => {
            let v: f64 = value
                .parse()
                .ok()
                .filter(|v: &f64| v.is_finite())
                .ok_or_else(|| anyhow::anyhow!("invalid VALUE '{value}': not a finite number"))?;
            (
                "POST",
                format!("/scripts/{}/params", percent_encoded(script)),
                serde_json::json!({ *name: v }).to_string(),
            )
        }
        _ => bail!(
            "unknown ctl command {:?}: expected status, pause, resume, step [N], commit (or checkpoint), param SCRIPT NAME VALUE, params [SCRIPT], log [SCRIPT] or camera path",
            a.command
        ),
    };
    let tok = if method == "POST" {
        Some(token()?)
    } else {
        None
    };
    let (code, body) = request(&addr, method, &path, tok.as_deref().map(str::trim), &body)?;
    // Every answer of the engine, errors too, is JSON.
    if serde_json::from_str::<serde_json::Value>(&body).is_err() {
        bail!(
            "{} answered {code} with something that is not JSON: is it a brickworld engine?",
            addr
        );
    }
    println!("{}", body.trim());
    if !(200..300).contains(&code) {
        bail!("the engine answered {code}");
    }
    // Only the engine's own words count as done (regression, hostile
    // probe: any 2xx JSON, `{}` from another server, was taken for applied,
    // so `ctl commit && backup` could back up nothing).
    let answer: serde_json::Value = serde_json::from_str(&body).unwrap_or_default();
    let done = if method == "GET" {
        answer.get("tick").is_some_and(|t| t.is_u64())
    } else {
        answer["ok"] == true
            && (code == 202
                || (!path.starts_with("/scripts/") && path != "/checkpoint")
                || answer["applied"] == true)
    };
    if !done {
        bail!(
            "{} answered {code} without saying it was done: is it a brickworld engine?",
            addr
        );
    }
    // Accepted but not yet applied (the engine is busy in a step): not a
    // success a script may build on (regression: `ctl commit && backup`
    // went ahead with nothing written).
    if code == 202 {
        bail!(
            "the engine has not applied it yet (it is busy in a step); it will at the next step boundary: see ctl status"
        );
    }
    Ok(())
}

/// `/status`, parsed; it must list the scripts by name, as the engine's does.
fn status(addr: &str) -> Result<serde_json::Value> {
    let (code, body) = request(addr, "GET", "/status", None, "")?;
    if code != 200 {
        bail!("the engine answered {code} to GET /status");
    }
    let st: serde_json::Value =
        serde_json::from_str(&body).context("the engine's /status is not JSON")?;
    let named = st["scripts"]
        .as_array()
        .is_some_and(|a| a.iter().all(|s| s["name"].is_string()));
    if !named {
        bail!("{addr}'s /status lists no scripts by name: is it a brickworld engine?");
    }
    Ok(st)
}

/// Text from the server as it may be printed: control characters but the
/// tab (`log` joins its values with tabs; a terminal's escapes) shown escaped (regression, hostile probe: a name or
/// log line could clear the screen or set the terminal's title).
fn printable(text: &str) -> String {
    text.chars()
        .map(|c| {
            if c.is_control() && c != '\t' {
                c.escape_default().to_string()
            } else {
                c.to_string()
            }
        })
        .collect()
}

/// The scripts in `st`, or only `only` (an unknown name is an error that
/// lists the loaded ones).
fn scripts<'a>(
    st: &'a serde_json::Value,
    only: Option<&str>,
) -> Result<Vec<&'a serde_json::Value>> {
    let all: Vec<&serde_json::Value> = st["scripts"].as_array().into_iter().flatten().collect();
    let Some(name) = only else { return Ok(all) };
    let found: Vec<_> = all.iter().copied().filter(|s| s["name"] == name).collect();
    if found.is_empty() {
        let names: Vec<&str> = all.iter().filter_map(|s| s["name"].as_str()).collect();
        bail!("no script named '{name}' (loaded: {})", names.join(", "));
    }
    Ok(found)
}

/// `ctl params [SCRIPT]`: `script.name = value (default d, range [a, b])`.
fn params(addr: &str, only: Option<&str>) -> Result<()> {
    let st = status(addr)?;
    for s in scripts(&st, only)? {
        let name = printable(s["name"].as_str().unwrap_or("?"));
        let ps = s["params"]
            .as_array()
            .map(Vec::as_slice)
            .unwrap_or_default();
        if ps.is_empty() {
            println!("{name}: no parameters");
        }
        for p in ps {
            let num = |k: &str| p[k].as_f64().map_or("?".into(), crate::sim::fmt_num);
            println!(
                "{name}.{} = {} (default {}, range [{}, {}])",
                printable(p["name"].as_str().unwrap_or("?")),
                num("value"),
                num("default"),
                num("min"),
                num("max")
            );
        }
    }
    Ok(())
}

/// `ctl log [SCRIPT]`: print `[script] line` for every line not printed
/// yet, then (when following) poll every half second until interrupted.
fn log(addr: &str, only: Option<&str>, follow: bool) -> Result<()> {
    let mut printed: std::collections::HashMap<String, u64> = Default::default();
    loop {
        let st = status(addr)?;
        for s in scripts(&st, only)? {
            let name = printable(s["name"].as_str().unwrap_or("?"));
            let seq = s["log_seq"].as_u64().unwrap_or(0);
            let lines: Vec<&str> = s["log"]
                .as_array()
                .into_iter()
                .flatten()
                .filter_map(|l| l.as_str())
                .collect();
            let first = seq.saturating_sub(lines.len() as u64);
            let done = printed.get(&name).copied().unwrap_or(first);
            // A restarted engine counts from 0 again.
            let done = if done > seq { first } else { done };
            if done < first {
                println!(
                    "[{name}] … {} lines not shown (more than /status keeps)",
                    first - done
                );
            }
            for (i, l) in lines.iter().enumerate() {
                if first + i as u64 >= done {
                    println!("[{name}] {}", printable(l));
                }
            }
            printed.insert(name, seq);
        }
        if !follow {
            return Ok(());
        }
        use std::io::Write as _;
        let _ = std::io::stdout().flush();
        std::thread::sleep(Duration::from_millis(500));
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// Regression (hostile probe 2): options after the command words were
    /// taken as words ("unknown ctl command"), except `--no-follow`. They
    /// now count wherever they are, in both spellings; values that start
    /// with '-' stay words, and an unknown option is named.
    #[test]
    fn options_after_the_command_words_count() {
        let args = |words: &[&str]| {
            let a = CtlArgs {
                addr: Some("127.0.0.1:7878".into()),
                state: "state".into(),
                no_follow: false,
                command: words.iter().map(|w| w.to_string()).collect(),
            };
            with_trailing_options(&a).map(|(a, w)| (a.addr, a.state, a.no_follow, w))
        };
        let (addr, state, follow, words) = args(&[
            "param",
            "water",
            "rain",
            "--addr",
            "10.0.0.1:9",
            "-1e-3",
            "--state=s2",
        ])
        .unwrap();
        assert_eq!(
            (addr.as_deref(), state, follow, words),
            (
                Some("10.0.0.1:9"),
                std::path::PathBuf::from("s2"),
                false,
                vec![
                    "param".into(),
                    "water".into(),
                    "rain".into(),
                    "-1e-3".into()
                ]
            )
        );
        let (_, _, follow, words) = args(&["log", "--no-follow", "water"]).unwrap();
        assert!(follow);
        assert_eq!(words, ["log", "water"]);
        let e = args(&["status", "--addr"]).unwrap_err().to_string();
        assert_eq!(e, "--addr needs a value");
        let e = args(&["log", "--no-follow=yes"]).unwrap_err().to_string();
        assert_eq!(e, "--no-follow takes no value");
        let e = args(&["status", "--adr", "x"]).unwrap_err().to_string();
        assert!(e.starts_with("unknown option '--adr' for ctl"), "{e}");
    }

    /// Regression (hostile probe): names and log lines from the server
    /// reached the terminal with their escapes.
    #[test]
    fn server_text_is_printed_without_its_control_characters() {
        assert_eq!(
            printable("a\u{1b}]0;pwn\u{7}b\tc\r"),
            "a\\u{1b}]0;pwn\\u{7}b\tc\\r"
        );
    }

    /// Regression (review): `ctl --addr NAME:PORT` sent `Host: NAME:PORT`,
    /// which the engine's guard against DNS rebinding refuses unless the
    /// name is listed; `ctl` names the address it connected to.
    #[test]
    fn ctl_names_the_address_it_connected_to() {
        let listener = std::net::TcpListener::bind("127.0.0.1:0").unwrap();
        let port = listener.local_addr().unwrap().port();
        let server = std::thread::spawn(move || {
            let (mut s, _) = listener.accept().unwrap();
            let mut buf = vec![0u8; 4096];
            let mut got = Vec::new();
            while !got.windows(4).any(|w| w == b"\r\n\r\n") {
                let n = s.read(&mut buf).unwrap();
                got.extend_from_slice(&buf[..n]);
            }
            s.write_all(b"HTTP/1.1 200 OK\r\nContent-Length: 2\r\n\r\n{}")
                .unwrap();
            String::from_utf8(got).unwrap()
        });
        let (code, _) = request(&format!("localhost:{port}"), "GET", "/status", None, "").unwrap();
        assert_eq!(code, 200);
        let head = server.join().unwrap();
        assert!(
            head.contains(&format!("Host: 127.0.0.1:{port}\r\n")),
            "{head}"
        );
    }
}
