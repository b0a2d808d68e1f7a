//! The control server's transport: hyper (HTTP/1.1) on a single-threaded
//! tokio runtime of its own, built for hostile clients.
//!
//! What no request can do, and the limit that stops it:
//! - **Exhaust memory with a body**: a declared `Content-Length` over
//!   [`MAX_BODY`](super::MAX_BODY) is refused with 413 before a byte of it is
//!   read; a chunked body is read through a cap ([`http_body_util::Limited`]).
//! - **Exhaust memory with headers**: hyper's read buffer is capped at
//!   [`MAX_HEADER_BYTES`]; larger headers get 431.
//! - **Block others by being slow**: every connection is its own task, headers
//!   must arrive within [`HEADER_TIMEOUT`], a body within [`BODY_TIMEOUT`]
//!   (else 408), and no connection lives longer than [`CONNECTION_LIFETIME`].
//! - **Exhaust descriptors**: at most [`MAX_CONNECTIONS`] are served at once;
//!   a new one then takes the slot of the oldest connection that is between
//!   requests (it is closed), and only when every one is busy with a
//!   request is the new one closed. An accept error (EMFILE, ENFILE…)
//!   pauses the accept loop briefly and never ends it, so the listener
//!   survives.
//! - **Lock others out with silent connections**: see the line above
//!   (regression, HTTP fuzzing: 600 connections that sent nothing, each
//!   reopened when closed, kept the slots full and `ctl` was refused 26
//!   times in 30).
//! - **Hold a connection for ever**: only a live viewer's event stream
//!   outlives [`CONNECTION_LIFETIME`]; at most
//!   [`MAX_VIEWERS`](super::live::MAX_VIEWERS) are served and one that
//!   reads nothing for [`STALL_LIMIT`](super::live::STALL_LIMIT) is closed;
//!   the kernel buffers at most about [`SEND_BUFFER`] twice for a client
//!   that does not read (long-run probe: with Linux's own sizing a stalled
//!   viewer pinned up to 4 MB, and its stall began to count only once that
//!   had filled, minutes later).
//! - **Hold up shutdown**: [`ControlServer::stop`] drops every connection
//!   task without waiting for its client.

use std::convert::Infallible;
use std::net::SocketAddr;
use std::sync::Arc;
use std::sync::atomic::{AtomicU8, Ordering};
use std::time::Duration;

use hyper::server::conn::http1;
use hyper::service::service_fn;
use hyper_util::rt::{TokioIo, TokioTimer};
use tokio::sync::oneshot;

use super::Shared;

/// Largest request head (request line plus headers), in bytes.
pub const MAX_HEADER_BYTES: usize = 16 << 10;
/// Time a client has to send its request head.
pub const HEADER_TIMEOUT: Duration = Duration::from_secs(5);
/// Time a client has to send its body once the head has arrived.
pub const BODY_TIMEOUT: Duration = Duration::from_secs(5);
/// Longest a connection is kept, keep-alive included.
pub const CONNECTION_LIFETIME: Duration = Duration::from_secs(60);
/// Connections served at once (see the module's notes for what happens
/// to the next).
pub const MAX_CONNECTIONS: usize = 512;

/// One connection being served: whether it is in a request, and how to
/// close it from the accept loop.
struct Conn {
    /// Requests in progress.
    busy: std::sync::atomic::AtomicUsize,
    /// The connection's event stream, if it answered with one (see
    /// [`super::live`]): an open stream keeps its connection busy.
    streaming: Arc<AtomicU8>,
    close: tokio::sync::Notify,
}

impl Conn {
    fn idle(&self) -> bool {
        self.busy.load(Ordering::Relaxed) == 0
            && self.streaming.load(Ordering::Relaxed) != super::live::STREAM_LIVE
    }
}

/// The connections being served, oldest first.
#[derive(Default)]
struct Conns {
    next: u64,
    live: std::collections::BTreeMap<u64, Arc<Conn>>,
}

impl Conns {
    /// A slot for a new connection: free, or the oldest idle connection's
    /// (closed); `None` when all are in a request.
    fn admit(&mut self) -> Option<(u64, Arc<Conn>)> {
        if self.live.len() >= MAX_CONNECTIONS {
            let idle = self
                .live
                .iter()
                .find(|(_, c)| c.idle())
                .map(|(id, _)| *id)?;
            if let Some(c) = self.live.remove(&idle) {
                c.close.notify_one();
            }
        }
        let id = self.next;
        self.next += 1;
        let c = Arc::new(Conn {
            busy: Default::default(),
            streaming: Arc::new(AtomicU8::new(super::live::STREAM_NONE)),
            close: Default::default(),
        });
        self.live.insert(id, c.clone());
        Some((id, c))
    }
}

/// Counts a request in progress on a connection while it lives.
struct Busy(Arc<Conn>);

impl Busy {
    fn new(c: &Arc<Conn>) -> Self {
        c.busy.fetch_add(1, Ordering::Relaxed);
        Busy(c.clone())
    }
}

impl Drop for Busy {
    fn drop(&mut self) {
        self.0.busy.fetch_sub(1, Ordering::Relaxed);
    }
}
/// Pause of the accept loop after an accept error (out of descriptors…).
const ACCEPT_BACKOFF: Duration = Duration::from_millis(50);

/// The send buffer asked of the kernel for each connection (Linux doubles
/// it for its bookkeeping): enough for a frame or the timeline to flow at
/// full speed to a local viewer, little for one that reads nothing.
pub const SEND_BUFFER: usize = 128 << 10;

/// Ask the kernel for a send buffer of [`SEND_BUFFER`] on `socket` (best
/// effort: a refusal leaves the kernel's own size).
fn bound_send_buffer(socket: &impl std::os::fd::AsFd) {
    #[cfg(target_os = "linux")]
    let _ = nix::sys::socket::setsockopt(socket, nix::sys::socket::sockopt::SndBuf, &SEND_BUFFER);
}

/// Why the control server did not start.
#[derive(Debug, thiserror::Error)]
pub enum ServerError {
    /// The address could not be bound.
    #[error("cannot listen on {addr}: {error}")]
    Listen {
        /// The address asked for.
        addr: SocketAddr,
        /// What the OS said.
        error: std::io::Error,
    },
    /// Its runtime or thread could not start.
    #[error("{0}")]
    Start(String),
}

impl ServerError {
    /// Whether the address is to blame (a taken port, an address not of
    /// this machine), not the process's limits: out of file handles or
    /// threads, the config's field was named as the cause (review).
    pub fn blames_addr(&self) -> bool {
        match self {
            ServerError::Listen { error, .. } => !matches!(
                error.raw_os_error(),
                Some(libc::EMFILE | libc::ENFILE | libc::ENOMEM | libc::ENOBUFS)
            ),
            ServerError::Start(_) => false,
        }
    }
}

/// A running control server.
pub struct ControlServer {
    stop: Option<oneshot::Sender<()>>,
    thread: Option<std::thread::JoinHandle<()>>,
    /// The address actually bound (port 0 picks a free one).
    pub addr: SocketAddr,
}

impl ControlServer {
    /// Bind `addr` (a taken port is a clear error) and serve on a thread of
    /// its own until [`stop`](Self::stop).
    pub fn start(addr: SocketAddr, shared: Arc<Shared>) -> Result<Self, ServerError> {
        let listen = |error| ServerError::Listen { addr, error };
        let listener = std::net::TcpListener::bind(addr).map_err(listen)?;
        let bound = listener.local_addr().map_err(listen)?;
        listener.set_nonblocking(true).map_err(listen)?;
        let rt = tokio::runtime::Builder::new_current_thread()
            .enable_all()
            .build()
            .map_err(|e| ServerError::Start(format!("cannot start the control server: {e}")))?;
        let (stop, stopped) = oneshot::channel();
        let thread = std::thread::Builder::new()
            .name("control".into())
            .spawn(move || {
                rt.block_on(accept_loop(listener, shared, stopped));
                // Drop every connection task now: no client is waited for.
                rt.shutdown_timeout(Duration::ZERO);
            })
            .map_err(|e| {
                ServerError::Start(format!("cannot start the control server thread: {e}"))
            })?;
        Ok(ControlServer {
            stop: Some(stop),
            thread: Some(thread),
            addr: bound,
        })
    }

    /// Stop serving: closes the listener and every connection at once.
    pub fn stop(mut self) {
        self.shutdown();
    }

    fn shutdown(&mut self) {
        if let Some(s) = self.stop.take() {
            let _ = s.send(());
        }
        if let Some(t) = self.thread.take() {
            let _ = t.join();
        }
    }
}

impl Drop for ControlServer {
    fn drop(&mut self) {
        self.shutdown();
    }
}

async fn accept_loop(
    listener: std::net::TcpListener,
    shared: Arc<Shared>,
    mut stopped: oneshot::Receiver<()>,
) {
    let listener = match tokio::net::TcpListener::from_std(listener) {
        Ok(l) => l,
        Err(e) => {
            crate::say!("error: the control server cannot use its socket: {e}");
            return;
        }
    };
    let conns = Arc::new(std::sync::Mutex::new(Conns::default()));
    // Accept errors are reported at most once per ten seconds.
    let mut last_report: Option<std::time::Instant> = None;
    loop {
        tokio::select! {
            _ = &mut stopped => break,
            accepted = listener.accept() => match accepted {
                Ok((stream, _)) => {
                    // Every slot in a request: close at once, freeing the
                    // descriptor.
                    let admitted = conns.lock().unwrap_or_else(|p| p.into_inner()).admit();
                    let Some((id, conn)) = admitted else { continue };
                    let (shared, conns) = (shared.clone(), conns.clone());
                    tokio::spawn(async move {
                        serve(stream, shared, conn).await;
                        conns.lock().unwrap_or_else(|p| p.into_inner()).live.remove(&id);
                    });
                }
                Err(e) => {
                    // Out of descriptors (or a connection reset before accept):
                    // wait for clients to leave; the listener stays.
                    if last_report.is_none_or(|t| t.elapsed() >= Duration::from_secs(10)) {
                        crate::say!("warning: the control server cannot accept a connection ({e}); retrying");
                        last_report = Some(std::time::Instant::now());
                    }
                    tokio::time::sleep(ACCEPT_BACKOFF).await;
                }
            }
        }
    }
}

async fn serve(stream: tokio::net::TcpStream, shared: Arc<Shared>, me: Arc<Conn>) {
    let _ = stream.set_nodelay(true);
    bound_send_buffer(&stream);
    // Set once this connection answers with an event stream: a live viewer
    // may stay longer than CONNECTION_LIFETIME (the stream has its own
    // limits, see `live`), and once the stream ends the connection closes.
    let streaming = me.streaming.clone();
    let flag = streaming.clone();
    let mine = me.clone();
    let service = service_fn(move |req| {
        let (shared, flag) = (shared.clone(), flag.clone());
        let busy = Busy::new(&mine);
        async move {
            let r = super::routes::handle(req, &shared, &flag).await;
            drop(busy);
            Ok::<_, Infallible>(r)
        }
    });
    let conn = http1::Builder::new()
        .timer(TokioTimer::new())
        .header_read_timeout(HEADER_TIMEOUT)
        .max_buf_size(MAX_HEADER_BYTES)
        // A client may shut its sending side and still read the answer
        // (regression: one that did so after `/checkpoint` got none,
        // though the command ran). With half-close on, hyper no longer
        // learns of a close by reading, so a viewer that left an event
        // stream on a paused engine held its slot for ever (found by
        // review): streams now send a comment every `live::KEEPALIVE`,
        // and the failed write ends the connection.
        .half_close(true)
        .serve_connection(TokioIo::new(stream), service);
    tokio::pin!(conn);
    let born = tokio::time::Instant::now();
    loop {
        let waited = tokio::select! {
            r = tokio::time::timeout(WATCH_EVERY, &mut conn) => r,
            // A new client took this idle connection's slot.
            _ = me.close.notified() => return,
        };
        match waited {
            Ok(_) => return,
            Err(_) => match streaming.load(Ordering::Relaxed) {
                super::live::STREAM_LIVE => continue,
                // The stream ended (its client stalled, left, or a newer
                // viewer took its slot): shut the connection down, letting
                // a request already on it finish, but never wait longer
                // than ENDED_GRACE on hyper flushing into a socket nobody
                // reads (regression, hostile probe: such connections stayed
                // for ever, each holding a connection slot and megabytes of
                // socket buffer; review: closing at once cut a keep-alive
                // request that followed the stream).
                super::live::STREAM_ENDED => {
                    conn.as_mut().graceful_shutdown();
                    let _ = tokio::time::timeout(ENDED_GRACE, &mut conn).await;
                    return;
                }
                _ if born.elapsed() >= CONNECTION_LIFETIME => return,
                _ => continue,
            },
        }
    }
}

/// How often a connection's limits are looked at.
const WATCH_EVERY: Duration = Duration::from_secs(1);

/// How long a connection whose event stream ended may finish what it is
/// doing before it is dropped.
const ENDED_GRACE: Duration = Duration::from_secs(2);

#[cfg(test)]
mod tests {
    /// Each connection's send buffer is bounded (Linux reports twice what
    /// was asked), so a client that reads nothing pins little memory and
    /// is found stalled soon (long-run probe).
    #[cfg(target_os = "linux")]
    #[test]
    fn a_connections_send_buffer_is_bounded() {
        use nix::sys::socket::{getsockopt, sockopt::SndBuf};
        let l = std::net::TcpListener::bind("127.0.0.1:0").unwrap();
        let _client = std::net::TcpStream::connect(l.local_addr().unwrap()).unwrap();
        let (server_end, _) = l.accept().unwrap();
        super::bound_send_buffer(&server_end);
        let got = getsockopt(&server_end, SndBuf).unwrap();
        assert!(got <= 2 * super::SEND_BUFFER, "{got}");
        assert!(got >= super::SEND_BUFFER, "{got}");
    }
}
