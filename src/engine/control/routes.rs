//! The control API's routes: what each request means, the token rule, and
//! replies; [`super::commands`] turns a POST body into a [`Command`] or a 4xx.
//!
//! `GET /status`, `GET /frame.png`, `GET /events` (live viewers, see
//! [`super::live`]), `GET /timeline` and `GET /` (the viewer) are open;
//! every `POST` needs `Authorization: Bearer TOKEN` (compared in constant
//! time). `POST /auth` only checks the token (the viewer's login).
//! `POST /scripts/NAME/params` waits up to [`VERDICT_WAIT`] for the
//! engine's verdict and answers 409 with the reason when the engine refuses
//! (202 if it has not decided yet). `POST /commit` (or `/checkpoint`) waits
//! as long for the commit: 200 once written, 500 with the reason if it
//! failed, 202 if the engine is still busy. `POST /camera` from a viewer (a
//! `viewer` id in the body) holds the camera lease; another viewer's move
//! meanwhile gets 409.
//! A request whose `Host` names neither an IP address, `localhost` nor one
//! of `[control] hosts` gets 403 before anything else ([`host_allowed`]):
//! a web page cannot rebind its own DNS name to this machine and read the
//! engine through the visitor's browser.
//! Unknown routes get 404, a known route asked with the wrong method 405
//! (with `Allow`; `HEAD` works wherever `GET` does, except `/events`),
//! malformed requests or refused values 400, a
//! wrong token 401, a body over [`MAX_BODY`] 413 (decided from the declared
//! length, before the body is read), a body too slow 408, and a full command
//! queue 503, as is a large timeline answer while others of over
//! [`super::inflight::MAX_IN_FLIGHT`] bytes are still being sent
//! ([`super::inflight`]).

use std::convert::Infallible;
use std::sync::Arc;
use std::sync::atomic::AtomicU8;
use std::time::{Duration, Instant};

use bytes::Bytes;
use http_body_util::combinators::BoxBody;
use http_body_util::{BodyExt, Full, Limited};
use hyper::body::Incoming;
use hyper::header::{AUTHORIZATION, CONTENT_LENGTH, CONTENT_TYPE};
use hyper::{Method, Request, Response, StatusCode};
use serde::Serialize;

use super::commands::parse_command;
use super::exchange::VerdictSlot;
use super::live;
use super::server::BODY_TIMEOUT;
use super::{Command, MAX_BODY, MAX_QUEUED_COMMANDS, Shared};

/// A response: a whole body, or an event stream.
pub type Reply = Response<BoxBody<Bytes, Infallible>>;

/// Longest a parameter change or a commit waits for the engine's verdict.
pub const VERDICT_WAIT: Duration = Duration::from_secs(3);

fn reply(code: u16, content_type: &'static str, body: impl Into<Bytes>) -> Reply {
    let mut r = Response::new(Full::new(body.into()).boxed());
    *r.status_mut() = StatusCode::from_u16(code).unwrap_or(StatusCode::INTERNAL_SERVER_ERROR);
    r.headers_mut().insert(
        CONTENT_TYPE,
        hyper::header::HeaderValue::from_static(content_type),
    );
    r
}

fn json<T: Serialize>(code: u16, v: &T) -> Reply {
    let body = serde_json::to_string_pretty(v).unwrap_or_else(|_| "{}".into());
    reply(code, "application/json", body)
}

fn error(code: u16, msg: &str) -> Reply {
    json(code, &serde_json::json!({ "error": msg }))
}

/// Equal in constant time (for equal lengths): the token check must not
/// leak how many leading bytes matched.
pub fn same_secret(a: &[u8], b: &[u8]) -> bool {
    a.len() == b.len() && a.iter().zip(b).fold(0u8, |acc, (x, y)| acc | (x ^ y)) == 0
}

/// A path segment with its `%XX` escapes decoded (None if one is
/// malformed or the result is not UTF-8).
pub(super) fn percent_decoded(segment: &str) -> Option<String> {
    let b = segment.as_bytes();
    let mut out = Vec::with_capacity(b.len());
    let mut i = 0;
    while i < b.len() {
        if b[i] == b'%' {
            let hex = std::str::from_utf8(b.get(i + 1..i + 3)?).ok()?;
            if !hex.bytes().all(|c| c.is_ascii_hexdigit()) {
                return None;
            }
            out.push(u8::from_str_radix(hex, 16).ok()?);
            i += 3;
        } else {
            out.push(b[i]);
            i += 1;
        }
    }
    String::from_utf8(out).ok()
}

/// Who a command claims the camera lease for: a move's viewer (None, an
/// administrative move, clears the lease), or a viewer returning the
/// camera to its path; nothing for other commands and an administrative
/// return.
fn lease_claim(cmd: &Command) -> Option<Option<&str>> {
    match cmd {
        Command::Camera { viewer, .. } => Some(viewer.as_deref()),
        Command::CameraPath {
            viewer: Some(v), ..
        } => Some(Some(v.as_str())),
        _ => None,
    }
}

/// A name from a request as an error message shows it: escaped, at most
/// 64 characters.
pub(super) fn shown(name: &str) -> String {
    crate::text::shown(name, 64)
}

/// Whether a request naming `host` (a `Host` header: a name or IP, and
/// perhaps a port) may be served: an IP literal (v4, or v6 in brackets),
/// `localhost` or a name under `.localhost`, or one of `allowed`
/// (lower-case names). DNS rebinding needs a DNS name that resolves to this
/// machine, so every other name is refused.
///
/// ```
/// use brickworld::engine::control::routes::host_allowed;
/// assert!(host_allowed("127.0.0.1:7878", &[]));
/// assert!(host_allowed("[::1]:7878", &[]));
/// assert!(host_allowed("[fe80::1%2]:7878", &[]));
/// assert!(host_allowed("localhost:7878", &[]));
/// assert!(!host_allowed("evil.example:7878", &[]));
/// assert!(!host_allowed("127.0.0.1:99999", &[]));
/// assert!(host_allowed("Box.LAN:7878", &["box.lan".to_string()]));
/// ```
pub fn host_allowed(host: &str, allowed: &[String]) -> bool {
    let name = if let Some(rest) = host.strip_prefix('[') {
        // [v6] or [v6]:port
        return match rest.split_once(']') {
            Some((ip, port)) => {
                // A link-local address may carry its zone: `fe80::1%eth0`.
                let ip = ip.split_once('%').map_or(ip, |(ip, _)| ip);
                ip.parse::<std::net::Ipv6Addr>().is_ok()
                    && (port.is_empty() || port.strip_prefix(':').is_some_and(is_port))
            }
            None => false,
        };
    } else {
        match host.split_once(':') {
            Some((name, port)) if is_port(port) => name,
            Some(_) => return false,
            None => host,
        }
    };
    let name = name.strip_suffix('.').unwrap_or(name).to_ascii_lowercase();
    name.parse::<std::net::Ipv4Addr>().is_ok()
        || name == "localhost"
        || name.ends_with(".localhost")
        || allowed.contains(&name)
}

/// A port number: digits that fit 16 bits (regression, HTTP fuzzing:
/// `Host: 127.0.0.1:99999` was served).
fn is_port(p: &str) -> bool {
    !p.is_empty() && p.bytes().all(|b| b.is_ascii_digit()) && p.parse::<u16>().is_ok()
}

/// Answer one request. `stream` is the connection's stream state
/// ([`live::STREAM_NONE`]…): an event stream sets it live (the server then
/// lets the connection outlive its usual limit) and ended when it ends.
pub async fn handle(req: Request<Incoming>, shared: &Arc<Shared>, stream: &Arc<AtomicU8>) -> Reply {
    // The head limit, counted here too: hyper caps its read buffer, but
    // a head that arrived behind a body on a reused connection could pass
    // it (regression, HTTP fuzzing: 2.7 % of 20 KB heads got 404, not 431).
    let uri = req.uri();
    let head = req.method().as_str().len()
        + uri.authority().map_or(0, |a| a.as_str().len())
        + uri.path_and_query().map_or(0, |p| p.as_str().len())
        + req
            .headers()
            .iter()
            .map(|(k, v)| k.as_str().len() + v.len() + 4)
            .sum::<usize>();
    if head > super::server::MAX_HEADER_BYTES {
        return error(
            431,
            &format!(
                "the request head is over {} KiB",
                super::server::MAX_HEADER_BYTES >> 10
            ),
        );
    }
    let path = req.uri().path().to_string();
    let method = req.method().clone();
    // One Host at most (RFC 9112: 400); the first alone was checked, so
    // `Host: 127.0.0.1` then a foreign name passed (hostile probe).
    if req.headers().get_all(hyper::header::HOST).iter().count() > 1 {
        return error(400, "more than one Host header");
    }
    // Both the header and an absolute-form target's authority are checked;
    // a request with neither (not a browser's) is served.
    let named = [
        req.headers()
            .get(hyper::header::HOST)
            .map(|h| h.to_str().unwrap_or("\u{fffd}")),
        req.uri().authority().map(|a| a.as_str()),
    ];
    if let Some(bad) = named
        .into_iter()
        .flatten()
        .find(|h| !host_allowed(h, &shared.hosts))
    {
        return error(
            403,
            &format!(
                "Host '{}' is not served (a guard against DNS rebinding): use an IP address or localhost, or add the name to [control] hosts",
                shown(&bad.escape_debug().to_string())
            ),
        );
    }
    // Until the world is loaded there is nothing to show or change:
    // `/status` answered made-up defaults (tick 0, not paused, no scripts,
    // even for a resumed or paused world) and commands were checked
    // against them (regression, concurrency probe). The viewer's page and
    // its event stream (which waits) are served.
    // `/auth` only checks the token, which is this engine's from the
    // start: a viewer reconnecting to a restarted engine learns at once
    // that its old token is stale (review).
    if !shared.started.load(std::sync::atomic::Ordering::Acquire)
        && path != "/"
        && path != "/events"
        && path != "/auth"
        && allowed_method(&path).is_some()
    {
        return error(
            503,
            "the engine is starting (loading the world): try again shortly",
        );
    }
    // HEAD is GET without the body (hyper leaves the body out); an event
    // stream is not opened for it.
    let as_get = method == Method::HEAD && path != "/events";
    let routed = if as_get { &Method::GET } else { &method };
    match (routed, path.as_str()) {
        (&Method::GET, "/status") => json(200, &*shared.status.lock().expect("status lock")),
        (&Method::GET, "/frame.png") => match shared.frame.lock().expect("frame lock").clone() {
            Some(png) => {
                let mut r = reply(200, "image/png", png);
                r.headers_mut().insert(
                    hyper::header::CACHE_CONTROL,
                    hyper::header::HeaderValue::from_static("no-store"),
                );
                r
            }
            None => error(404, "no frame rendered yet"),
        },
        (&Method::GET, "/events") => {
            let Some(slot) = shared.viewers.admit().await else {
                return error(
                    503,
                    &format!(
                        "{} viewers are already watching; try again later",
                        live::MAX_VIEWERS
                    ),
                );
            };
            let mut r = Response::new(live::stream(shared.clone(), slot, stream.clone()).boxed());
            let h = r.headers_mut();
            h.insert(
                CONTENT_TYPE,
                hyper::header::HeaderValue::from_static("text/event-stream"),
            );
            h.insert(
                hyper::header::CACHE_CONTROL,
                hyper::header::HeaderValue::from_static("no-store"),
            );
            r
        }
        (&Method::GET, "/timeline") => timeline(req.uri().query().unwrap_or(""), shared),
        (&Method::GET, "/") => reply(200, "text/html; charset=utf-8", super::VIEWER),
        (&Method::POST, p) if allowed_method(p) == Some("GET") => {
            method_not_allowed(&method, p, "GET")
        }
        (&Method::POST, _) => post(req, &path, shared).await,
        // A known route asked with the wrong method: 405 naming the right
        // one (it was 404, as if the route did not exist).
        _ => match allowed_method(&path) {
            Some(allowed) => method_not_allowed(&method, &path, allowed),
            None => error(404, &format!("no route {method} {}", shown(&path))),
        },
    }
}

/// `GET /timeline?QUERY`: the rows the query asks for, a large answer
/// shared with the requests it serves or refused with 503 while others'
/// are still being sent (see [`super::inflight`]).
fn timeline(query: &str, shared: &Shared) -> Reply {
    let (since, epoch) = match timeline_query(query) {
        Ok(q) => q,
        Err(msg) => return error(400, &msg),
    };
    let busy = || {
        error(
            503,
            &format!(
                "other clients' timeline answers are still being sent (over {} MiB): try again shortly",
                super::inflight::MAX_IN_FLIGHT >> 20
            ),
        )
    };
    // Copy the rows out and let go of the lock before encoding: the
    // engine pushes a row every tick under the same lock, and an open
    // route must not make it wait on a client's megabytes of JSON.
    // A large answer is shared by the clients that ask for the same
    // rows, and refused while others' are still being sent, before
    // it is built (memory probe, review).
    let ring = shared.timeline.lock().unwrap_or_else(|p| p.into_inner());
    let (key, estimate) = ring.answer_of(since, epoch);
    if estimate > super::inflight::SMALL {
        let asked = (if epoch == ring.epoch { since } else { 0 }, ring.epoch);
        if let Some(body) = shared.in_flight.shared(asked) {
            drop(ring);
            return reply(200, "application/json", body);
        }
        if !shared.in_flight.may_build(estimate) {
            drop(ring);
            return busy();
        }
    }
    let rows = ring.since(since, epoch);
    drop(ring);
    let body = serde_json::to_string(&rows).unwrap_or_else(|_| "{}".into());
    match shared.in_flight.admit(key, body.into_bytes()) {
        Some(body) => reply(200, "application/json", body),
        None => busy(),
    }
}

/// 405 for a known route asked with the wrong method, with `Allow`.
fn method_not_allowed(method: &Method, path: &str, allowed: &'static str) -> Reply {
    let mut r = error(
        405,
        &format!("{method} is not allowed on {}: use {allowed}", shown(path)),
    );
    r.headers_mut().insert(
        hyper::header::ALLOW,
        hyper::header::HeaderValue::from_static(allowed),
    );
    r
}

/// The method a known route takes, if `path` is one.
fn allowed_method(path: &str) -> Option<&'static str> {
    match path {
        "/status" | "/frame.png" | "/events" | "/timeline" | "/" => Some("GET"),
        "/pause" | "/resume" | "/step" | "/commit" | "/checkpoint" | "/camera" | "/camera/path"
        | "/auth" => Some("POST"),
        p if p.starts_with("/scripts/") && p.ends_with("/params") => Some("POST"),
        _ => None,
    }
}

async fn post(req: Request<Incoming>, path: &str, shared: &Shared) -> Reply {
    // The scheme's name is case-insensitive (RFC 9110 §11.1); the token
    // is compared in constant time.
    let authorized = req.headers().get(AUTHORIZATION).is_some_and(|v| {
        let v = v.as_bytes();
        v.len() > 7
            && v[..7].eq_ignore_ascii_case(b"bearer ")
            && same_secret(&v[7..], shared.token.as_bytes())
    });
    if !authorized {
        return error(
            401,
            "missing or wrong token (send Authorization: Bearer TOKEN, from STATE/control.token)",
        );
    }
    // Refuse an oversized body from its declared length, before reading it.
    if let Some(len) = req.headers().get(CONTENT_LENGTH) {
        match len.to_str().ok().and_then(|s| s.trim().parse::<u64>().ok()) {
            Some(n) if n > MAX_BODY as u64 => {
                return error(
                    413,
                    &format!("request body of {n} bytes is over the {MAX_BODY}-byte limit"),
                );
            }
            Some(_) => {}
            None => return error(400, "Content-Length is not a number"),
        }
    }
    let body = Limited::new(req.into_body(), MAX_BODY);
    let bytes = match tokio::time::timeout(BODY_TIMEOUT, body.collect()).await {
        Err(_) => {
            return error(
                408,
                &format!(
                    "the body did not arrive within {} s",
                    BODY_TIMEOUT.as_secs()
                ),
            );
        }
        Ok(Err(e)) if e.is::<http_body_util::LengthLimitError>() => {
            return error(
                413,
                &format!("request body is over the {MAX_BODY}-byte limit"),
            );
        }
        Ok(Err(e)) => return error(400, &format!("cannot read the body: {e}")),
        Ok(Ok(c)) => c.to_bytes(),
    };
    let Ok(body) = std::str::from_utf8(&bytes) else {
        return error(400, "the body is not UTF-8 text");
    };
    if path == "/auth" {
        return json(200, &serde_json::json!({ "ok": true }));
    }
    let cmd = {
        let status = shared.status.lock().expect("status lock");
        parse_command(path, body, &status)
    };
    match cmd {
        Ok(mut cmd) => {
            let mut wait = None;
            if let Command::Params { verdict, .. } | Command::Checkpoint { verdict } = &mut cmd {
                let (slot, rx) = VerdictSlot::new();
                *verdict = slot;
                wait = Some(rx);
            }
            let commit = matches!(cmd, Command::Checkpoint { .. });
            // One decision under the queue's lock: a full queue refuses
            // before the camera lease is taken or renewed.
            let refused = {
                let mut q = shared.commands.lock().expect("command lock");
                // Decided under the queue's lock: the engine takes the
                // queue for the last time under it, after setting the flag,
                // so a command either is applied or is told it was not
                // (regression, concurrency probe: commands answered 200
                // while the engine was stopping were never applied).
                if shared.shutdown.load(std::sync::atomic::Ordering::Acquire) {
                    Some((
                        503,
                        "the engine is stopping: the command was not applied".to_string(),
                    ))
                } else if q.len() >= MAX_QUEUED_COMMANDS {
                    Some((
                        503,
                        format!(
                            "{MAX_QUEUED_COMMANDS} commands are already waiting for the engine; try again"
                        ),
                    ))
                } else if let Some(viewer) = lease_claim(&cmd)
                    && let Err(msg) = shared
                        .camera_lease
                        .lock()
                        .expect("lease lock")
                        .take(viewer, Instant::now())
                {
                    Some((409, msg))
                } else {
                    q.push(cmd);
                    None
                }
            };
            if let Some((code, msg)) = refused {
                return error(code, &msg);
            }
            let Some(rx) = wait else {
                return json(200, &serde_json::json!({ "ok": true }));
            };
            match tokio::time::timeout(VERDICT_WAIT, rx).await {
                Ok(Ok(Ok(()))) => json(200, &serde_json::json!({ "ok": true, "applied": true })),
                // A commit that failed (a full disk): the server's fault,
                // not the request's; the engine retries at every commit.
                Ok(Ok(Err(reason))) if commit => {
                    error(500, &format!("the commit failed: {reason}"))
                }
                Ok(Ok(Err(reason))) => error(409, &reason),
                // The engine let the command go unapplied: it stopped in
                // the middle of a step, whose world is not kept.
                Ok(Err(_)) => error(503, "the engine stopped before it could apply the command"),
                // The engine is busy (a long step) or stopping: queued.
                _ => json(
                    202,
                    &serde_json::json!({ "ok": true, "applied": false, "note": "queued: the engine has not applied it yet; see /status" }),
                ),
            }
        }
        Err((code, msg)) => error(code, &msg),
    }
}

/// `/timeline`'s query: `since` (default 0) and `epoch` (default: any),
/// whole numbers. Another key, a key without a value, or a key given twice
/// is refused, naming it (regression, code-habits audit: `?sinse=5` was
/// ignored and every row sent, and a bad value did not say which key).
fn timeline_query(q: &str) -> Result<(u64, u64), String> {
    let (mut since, mut epoch) = (None, None);
    for kv in q.split('&').filter(|kv| !kv.is_empty()) {
        let Some((k, v)) = kv.split_once('=') else {
            return Err(format!(
                "query parameter '{}' has no value (expected since=N or epoch=N)",
                crate::text::shown(kv, 40)
            ));
        };
        let slot = match k {
            "since" => &mut since,
            "epoch" => &mut epoch,
            _ => {
                return Err(format!(
                    "unknown query parameter '{}' (expected since or epoch)",
                    crate::text::shown(k, 40)
                ));
            }
        };
        if slot.is_some() {
            return Err(format!("query parameter {k} is given twice"));
        }
        *slot = Some(v.parse::<u64>().map_err(|_| {
            format!(
                "{k} must be a whole number, not '{}'",
                crate::text::shown(v, 40)
            )
        })?);
    }
    Ok((since.unwrap_or(0), epoch.unwrap_or(u64::MAX)))
}

#[cfg(test)]
mod tests {
    use super::super::inflight::{MAX_IN_FLIGHT, SMALL};
    use super::{Shared, timeline, timeline_query};

    /// Claims audit: the 503 of `/timeline` was held only by the unit test
    /// of [`super::super::inflight::InFlight`]; a route that skipped its
    /// checks passed. The route shares a large answer with a request it
    /// serves, refuses one that would take what is in flight past the
    /// bound (counting nothing for it), and builds it once there is room.
    #[test]
    fn a_large_timeline_answer_is_shared_or_refused_with_503_past_the_bound() {
        let body = |r: super::Reply| {
            let rt = tokio::runtime::Builder::new_current_thread()
                .build()
                .unwrap();
            let bytes = rt.block_on(http_body_util::BodyExt::collect(r.into_body()));
            String::from_utf8(bytes.unwrap().to_bytes().to_vec()).unwrap()
        };
        let shared = Shared::new("t".into(), Vec::new());
        let columns: Vec<String> = (0..20).map(|i| format!("c{i}")).collect();
        {
            let mut ring = shared.timeline.lock().unwrap();
            for i in 0..4096 {
                // Long decimals, so the answer really is over 1 MiB.
                ring.push(&columns, vec![i as f64 / 7.0; 20]);
            }
            assert!(ring.answer_of(0, ring.epoch).1 > SMALL);
        }
        let first = timeline("since=0", &shared);
        assert_eq!(first.status(), 200);
        let one = shared.in_flight.bytes();
        assert!(one > SMALL, "{one}");
        // A request the answer serves shares it: nothing more is counted.
        let again = timeline("", &shared);
        assert_eq!(again.status(), 200);
        assert_eq!(shared.in_flight.bytes(), one);
        // Other answers in flight up to the bound: a large one is refused.
        let held = shared
            .in_flight
            .admit((0, 0), vec![0u8; (MAX_IN_FLIGHT - one) as usize])
            .unwrap();
        let refused = timeline("since=0", &shared);
        assert_eq!(refused.status(), 503);
        assert!(body(refused).contains("try again shortly"));
        assert_eq!(
            shared.in_flight.bytes(),
            MAX_IN_FLIGHT,
            "a refusal builds nothing"
        );
        // Room again: it is built (not shared: the last was let go).
        drop(held);
        let built = timeline("since=0", &shared);
        assert_eq!(built.status(), 200);
        assert_eq!(shared.in_flight.bytes(), 2 * one);
        assert!(body(built).starts_with("{\"columns\":[\"c0\""));
        drop((first, again));
    }

    #[test]
    fn timeline_queries_name_what_is_wrong() {
        assert_eq!(timeline_query(""), Ok((0, u64::MAX)));
        assert_eq!(timeline_query("since=5&epoch=2"), Ok((5, 2)));
        assert_eq!(timeline_query("epoch=3&"), Ok((0, 3)));
        for (q, said) in [
            (
                "sinse=5",
                "unknown query parameter 'sinse' (expected since or epoch)",
            ),
            ("since", "query parameter 'since' has no value"),
            ("since=5&since=6", "query parameter since is given twice"),
            ("epoch=-1", "epoch must be a whole number, not '-1'"),
            ("since=1e3", "since must be a whole number, not '1e3'"),
        ] {
            let e = timeline_query(q).unwrap_err();
            assert!(e.starts_with(said), "{q}: {e}");
        }
    }
}
