//! `brickworld ctl`: a small HTTP client for a running engine; it reads the
//! control token from the state directory.

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
    let (method, path, body) = match words.as_slice() {
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
            "unknown ctl command {:?}: expected status, pause, resume, step [N], checkpoint or param SCRIPT NAME VALUE",
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
