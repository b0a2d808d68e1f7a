//! What the live viewer is pushed, and how: server-sent events.
//!
//! `GET /events` is a `text/event-stream` with three kinds of event:
//! - `frame`: a frame was rendered (its sequence number, tick, size and the
//!   wall-clock time it was finished, so a page can measure its latency);
//!   the page then fetches `/frame.png`, one fetch at a time;
//! - `status`: what `/status` shows, at most [`STATUS_EVERY`] apart and
//!   only when it changed;
//! - `rows`: timeline rows the client has not had yet (the charts).
//!
//! **Why server-sent events.** They need nothing beyond HTTP/1.1 and the
//! hyper already serving the control API (no WebSocket handshake or crate),
//! pass through the same token-free read-only rule as `GET /status`, and
//! the browser's `EventSource` reconnects by itself. Frames stay binary
//! PNGs behind a plain GET instead of base64 inside the stream (a third
//! more bytes and a decode in script).
//!
//! **A slow browser never slows the engine.** Each stream is a task that
//! hands its events to the connection through a channel of
//! [`QUEUE`] events with `try_send`: when the client does not read, the
//! channel fills and newer events are dropped for that client alone (a
//! frame event only says "the latest frame is N", so a skipped one loses
//! nothing). The engine and the render thread only ever store values
//! ([`tokio::sync::watch`], a mutex held for a copy); they never wait for a
//! viewer. A stream with nothing to say sends a comment every
//! [`KEEPALIVE`], which finds a viewer that left. A client that has read nothing for [`STALL_LIMIT`] is
//! disconnected, and at most [`MAX_VIEWERS`] streams are served at once;
//! past that a new viewer takes the longest-connected one's slot
//! ([`Viewers`]).

use std::collections::VecDeque;
use std::convert::Infallible;
use std::pin::Pin;
use std::sync::Arc;
use std::sync::atomic::{AtomicU8, Ordering};
use std::task::{Context, Poll};
use std::time::{Duration, Instant};

use bytes::Bytes;
use hyper::body::{Body, Frame};
use serde::Serialize;
use tokio::sync::mpsc;

use super::Shared;

/// Event streams served at once; a newer one takes the longest-connected
/// one's slot (503 only if none frees within [`EVICT_WAIT`]).
pub const MAX_VIEWERS: usize = 16;
/// Least time between two `status` events on one stream.
pub const STATUS_EVERY: Duration = Duration::from_millis(250);
/// Events waiting for one slow client before newer ones are dropped.
pub const QUEUE: usize = 8;
/// A client that reads nothing for this long is disconnected.
pub const STALL_LIMIT: Duration = Duration::from_secs(30);
/// A stream with nothing else to send sends a comment this often, so that
/// a viewer that left is found by a write failing (the server lets
/// clients half-close, so it does not learn of a close by reading): the
/// first write after the close draws a reset, the second fails, so a
/// viewer that left is found within about two of these. A host that
/// vanishes without a word is found only by TCP's retransmission limit.
pub const KEEPALIVE: Duration = Duration::from_secs(5);

/// A rendered frame, as announced to viewers.
#[derive(Clone, Copy, Debug, Default, Serialize, PartialEq)]
pub struct FrameEvent {
    /// Frames rendered so far (0: none yet).
    pub seq: u64,
    /// The tick it shows.
    pub tick: u64,
    /// Width and height in pixels.
    pub width: u32,
    /// Height.
    pub height: u32,
    /// When it was finished (PNG encoded), in ms since the Unix epoch.
    pub rendered_unix_ms: f64,
}

/// Milliseconds since the Unix epoch, now.
pub fn unix_ms() -> f64 {
    std::time::SystemTime::now()
        .duration_since(std::time::UNIX_EPOCH)
        .map_or(0.0, |d| d.as_secs_f64() * 1e3)
}

/// The response body of an event stream: what the stream's task sends.
pub struct EventBody(mpsc::Receiver<Bytes>);

impl Body for EventBody {
    type Data = Bytes;
    type Error = Infallible;

    fn poll_frame(
        mut self: Pin<&mut Self>,
        cx: &mut Context<'_>,
    ) -> Poll<Option<Result<Frame<Bytes>, Infallible>>> {
        self.0.poll_recv(cx).map(|m| m.map(|b| Ok(Frame::data(b))))
    }
}

fn event(kind: &str, data: &impl Serialize) -> Bytes {
    let json = serde_json::to_string(data).unwrap_or_else(|_| "{}".into());
    Bytes::from(format!("event: {kind}\ndata: {json}\n\n"))
}

/// The viewer slots: at most [`MAX_VIEWERS`] event streams at once. When
/// all are taken, a new viewer takes the slot of the longest-connected one,
/// whose stream ends (a browser's `EventSource` reconnects by itself), so
/// clients that open streams and never read cannot shut viewers out
/// (regression: sixteen of them got every later viewer a 503 for minutes,
/// and for ever while the engine was paused, as nothing was sent to fill
/// their buffers).
pub struct Viewers {
    slots: Arc<tokio::sync::Semaphore>,
    /// The streams' ids and stop signals, oldest first.
    order: std::sync::Mutex<VecDeque<(u64, Arc<tokio::sync::Notify>)>>,
    next: std::sync::atomic::AtomicU64,
}

/// How long a new viewer waits for an evicted stream's slot.
pub const EVICT_WAIT: Duration = Duration::from_secs(2);

impl Default for Viewers {
    fn default() -> Self {
        Viewers {
            slots: Arc::new(tokio::sync::Semaphore::new(MAX_VIEWERS)),
            order: std::sync::Mutex::new(VecDeque::new()),
            next: std::sync::atomic::AtomicU64::new(0),
        }
    }
}

impl Viewers {
    /// A slot for a new stream: a free one, or the longest-connected
    /// stream's, which is told to end. `None` if no slot came free within
    /// [`EVICT_WAIT`].
    pub async fn admit(self: &Arc<Self>) -> Option<ViewerSlot> {
        let permit = match self.slots.clone().try_acquire_owned() {
            Ok(p) => p,
            Err(_) => {
                let oldest = self.order.lock().ok().and_then(|mut o| o.pop_front());
                if let Some((_, stop)) = oldest {
                    stop.notify_one();
                }
                tokio::time::timeout(EVICT_WAIT, self.slots.clone().acquire_owned())
                    .await
                    .ok()?
                    .ok()?
            }
        };
        let id = self.next.fetch_add(1, std::sync::atomic::Ordering::Relaxed);
        let stop = Arc::new(tokio::sync::Notify::new());
        if let Ok(mut o) = self.order.lock() {
            o.push_back((id, stop.clone()));
        }
        Some(ViewerSlot {
            _permit: permit,
            id,
            stop,
            viewers: self.clone(),
        })
    }
}

/// One stream's slot, freed when dropped.
pub struct ViewerSlot {
    _permit: tokio::sync::OwnedSemaphorePermit,
    id: u64,
    /// Told when a newer viewer takes the slot.
    stop: Arc<tokio::sync::Notify>,
    viewers: Arc<Viewers>,
}

impl Drop for ViewerSlot {
    fn drop(&mut self) {
        if let Ok(mut o) = self.viewers.order.lock() {
            o.retain(|(id, _)| *id != self.id);
        }
    }
}

/// A connection's state as the server watches it: no event stream, a live
/// one (which may outlive the connection lifetime), or one that ended.
pub const STREAM_NONE: u8 = 0;
/// See [`STREAM_NONE`].
pub const STREAM_LIVE: u8 = 1;
/// See [`STREAM_NONE`]: the server then closes the connection, even one
/// whose client reads nothing (hyper would wait for ever to flush into its
/// full socket: regression, hostile probe).
pub const STREAM_ENDED: u8 = 2;

/// Sets its connection's state to [`STREAM_ENDED`] when the stream's task
/// ends, however it ends.
struct Ended(Arc<AtomicU8>);

impl Drop for Ended {
    fn drop(&mut self) {
        self.0.store(STREAM_ENDED, Ordering::Relaxed);
    }
}

/// Start an event stream for one viewer, holding its `slot` for as long as
/// the stream lives; `state` is its connection's (set to
/// [`STREAM_ENDED`] when the stream ends).
pub fn stream(shared: Arc<Shared>, slot: ViewerSlot, state: Arc<AtomicU8>) -> EventBody {
    let (tx, rx) = mpsc::channel::<Bytes>(QUEUE);
    state.store(STREAM_LIVE, Ordering::Relaxed);
    tokio::spawn(async move {
        let _ended = Ended(state);
        let stop = slot.stop.clone();
        let _slot = slot;
        let mut frames = shared.frame_events.subscribe();
        let mut last_status = String::new();
        let (mut since, mut epoch) = (0u64, u64::MAX);
        let mut stalled_since: Option<Instant> = None;
        let mut last_sent = Instant::now();
        let mut tick = tokio::time::interval(STATUS_EVERY);
        tick.set_missed_tick_behavior(tokio::time::MissedTickBehavior::Skip);
        // Reconnect quickly after a restart of the engine.
        let mut pending = vec![Bytes::from_static(b"retry: 1000\n\n")];
        let first = *frames.borrow_and_update();
        if first.seq > 0 {
            pending.push(event("frame", &first));
        }
        loop {
            for e in pending.drain(..) {
                match tx.try_send(e) {
                    Ok(()) => {
                        stalled_since = None;
                        last_sent = Instant::now();
                    }
                    Err(mpsc::error::TrySendError::Full(_)) => {
                        // This client is slow: drop the event for it alone.
                        let s = *stalled_since.get_or_insert_with(Instant::now);
                        if s.elapsed() > STALL_LIMIT {
                            return;
                        }
                    }
                    Err(mpsc::error::TrySendError::Closed(_)) => return,
                }
            }
            if tx.is_closed() || shared.shutdown.load(std::sync::atomic::Ordering::Relaxed) {
                return;
            }
            tokio::select! {
                // A newer viewer took this slot.
                _ = stop.notified() => return,
                changed = frames.changed() => {
                    if changed.is_err() {
                        return;
                    }
                    let f = *frames.borrow_and_update();
                    pending.push(event("frame", &f));
                }
                _ = tick.tick() => {
                    // Nothing before the world is loaded but keep-alives:
                    // the status then is made-up defaults (concurrency
                    // probe).
                    if shared.started.load(std::sync::atomic::Ordering::Acquire) {
                        // A copy under the lock, encoded outside it: the engine
                        // publishing status never waits for a viewer's encoding.
                        let copy = shared.status.lock().expect("status lock").clone();
                        let status = serde_json::to_string(&copy).unwrap_or_default();
                        if status != last_status {
                            pending.push(Bytes::from(format!("event: status\ndata: {status}\n\n")));
                            last_status = status;
                        }
                        let rows = shared.timeline.lock().expect("timeline lock").since(since, epoch);
                        if !rows.columns.is_empty() && (!rows.rows.is_empty() || rows.epoch != epoch) {
                            (since, epoch) = (rows.next, rows.epoch);
                            pending.push(event("rows", &rows));
                        }
                    }
                    if pending.is_empty() && last_sent.elapsed() >= KEEPALIVE {
                        pending.push(Bytes::from_static(b": keep-alive\n\n"));
                    }
                }
            }
        }
    });
    EventBody(rx)
}

#[cfg(test)]
mod tests {
    use super::*;

    /// Whether `slot`'s stream was told to end (without waiting).
    async fn told_to_end(slot: &ViewerSlot) -> bool {
        tokio::time::timeout(Duration::from_millis(1), slot.stop.notified())
            .await
            .is_ok()
    }

    /// Audit: "closing a stream frees its slot" could not fail in the
    /// viewer test, where a new stream takes the oldest one's slot anyway.
    /// Here: a closed stream's slot is taken with no one told to end; past
    /// the limit exactly the longest-connected stream is told.
    #[test]
    fn a_closed_streams_slot_is_free_and_past_the_limit_the_oldest_is_told_to_end() {
        let rt = tokio::runtime::Builder::new_current_thread()
            .enable_time()
            .build()
            .unwrap();
        rt.block_on(async {
            let viewers = Arc::new(Viewers::default());
            let mut slots = Vec::new();
            for _ in 0..MAX_VIEWERS {
                slots.push(viewers.admit().await.expect("a free slot"));
            }
            // Two streams close: two new ones take their slots, and no
            // stream is told to end.
            slots.remove(3);
            slots.remove(7);
            for _ in 0..2 {
                slots.push(viewers.admit().await.expect("a freed slot"));
            }
            for (i, s) in slots.iter().enumerate() {
                assert!(!told_to_end(s).await, "stream {i} was told to end");
            }
            // One more: the longest-connected stream is told to end, and
            // its slot passes on once it does.
            let oldest_id = slots[0].id;
            let next = {
                let v = viewers.clone();
                tokio::spawn(async move { v.admit().await.map(|s| s.id) })
            };
            tokio::task::yield_now().await;
            assert!(told_to_end(&slots[0]).await, "the oldest was not told");
            for s in &slots[1..] {
                assert!(!told_to_end(s).await);
            }
            assert!(!next.is_finished(), "admitted before a slot was free");
            let oldest = slots.remove(0);
            assert_eq!(oldest.id, oldest_id);
            drop(oldest);
            assert!(
                next.await.unwrap().is_some(),
                "the freed slot was not taken"
            );
        });
    }
}
