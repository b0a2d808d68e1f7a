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

/// Send one request; returns (status code, body).
pub fn request(
    addr: &str,
    method: &str,
    path: &str,
    token: Option<&str>,
    body: &str,
) -> Result<(u16, String)> {
    let mut s = TcpStream::connect(addr).with_context(|| {
        format!("cannot reach the engine at {addr} (is `brickworld run` running?)")
    })?;
    s.set_read_timeout(Some(Duration::from_secs(30)))?;
    let auth = token
        .map(|t| format!("Authorization: Bearer {t}\r\n"))
        .unwrap_or_default();
    write!(
        s,
        "{method} {path} HTTP/1.1\r\nHost: {addr}\r\n{auth}Content-Length: {}\r\nConnection: close\r\n\r\n{body}",
        body.len()
    )?;
    let mut resp = String::new();
    s.read_to_string(&mut resp)?;
    let code = resp
        .split_whitespace()
        .nth(1)
        .and_then(|c| c.parse().ok())
        .unwrap_or(0);
    let body = resp
        .split_once("\r\n\r\n")
        .map_or("", |(_, b)| b)
        .to_string();
    Ok((code, body))
}

/// Run `brickworld ctl`.
pub fn run(a: &CtlArgs) -> Result<()> {
    let token_path = a.state.join("control.token");
    let token = || {
        std::fs::read_to_string(&token_path)
            .with_context(|| format!("cannot read the control token {}", token_path.display()))
    };
    let words: Vec<&str> = a.command.iter().map(|s| s.as_str()).collect();
    match words.as_slice() {
        ["params"] => return params(&a.addr, None),
        ["params", script] => return params(&a.addr, Some(script)),
        ["log"] => return log(&a.addr, None, !a.no_follow),
        ["log", script] => return log(&a.addr, Some(script), !a.no_follow),
        _ => {}
    }
    let (method, path, body) = match words.as_slice() {
        ["camera", "path"] => ("POST", "/camera/path".into(), String::new()),
        ["status"] => ("GET", "/status".to_string(), String::new()),
        ["pause"] => ("POST", "/pause".into(), String::new()),
        ["resume"] => ("POST", "/resume".into(), String::new()),
        ["checkpoint"] => ("POST", "/checkpoint".into(), String::new()),
        ["step"] => ("POST", "/step".into(), "1".into()),
        ["step", n] => ("POST", "/step".into(), n.to_string()),
        ["param", script, name, value] => {
            let v: f64 = value
                .parse()
                .map_err(|_| anyhow::anyhow!("invalid VALUE '{value}': not a number"))?;
            (
                "POST",
                format!("/scripts/{script}/params"),
                serde_json::json!({ *name: v }).to_string(),
            )
        }
        _ => bail!(
            "unknown ctl command {:?}: expected status, pause, resume, step [N], checkpoint, param SCRIPT NAME VALUE, params [SCRIPT], log [SCRIPT] or camera path",
            a.command
        ),
    };
    let tok = if method == "POST" {
        Some(token()?)
    } else {
        None
    };
    let (code, body) = request(&a.addr, method, &path, tok.as_deref().map(str::trim), &body)?;
    println!("{}", body.trim());
    if !(200..300).contains(&code) {
        bail!("the engine answered {code}");
    }
    Ok(())
}

/// `/status`, parsed.
fn status(addr: &str) -> Result<serde_json::Value> {
    let (code, body) = request(addr, "GET", "/status", None, "")?;
    if code != 200 {
        bail!("the engine answered {code} to GET /status");
    }
    serde_json::from_str(&body).context("the engine's /status is not JSON")
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
        let name = s["name"].as_str().unwrap_or("?");
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
                p["name"].as_str().unwrap_or("?"),
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
            let name = s["name"].as_str().unwrap_or("?").to_string();
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
                    println!("[{name}] {l}");
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
