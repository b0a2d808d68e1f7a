//! A bound on the bytes of built responses still being sent: a body made
//! for one client (the whole timeline, megabytes with many channels) is
//! held until that client has read it, and a client that never reads
//! would otherwise pin one such copy per connection (memory probe: 120
//! clients pipelining `GET /timeline` and reading nothing held 2.8 GB).
//! A response over the bound is refused with 503 instead.

use std::convert::Infallible;
use std::pin::Pin;
use std::sync::Arc;
use std::sync::atomic::{AtomicU64, Ordering};
use std::task::{Context, Poll};

use bytes::Bytes;
use http_body_util::Full;
use hyper::body::{Body, Frame, SizeHint};

/// Most bytes of counted responses in flight at once, across clients.
pub const MAX_IN_FLIGHT: u64 = 64 << 20;

/// The bytes of counted responses in flight (shared by the server).
#[derive(Debug, Default)]
pub struct InFlight(AtomicU64);

impl InFlight {
    /// A body for `bytes`, counted until the client has it (or goes away),
    /// or `None` if it would take the total past [`MAX_IN_FLIGHT`].
    pub fn body(self: &Arc<Self>, bytes: Bytes) -> Option<Counted> {
        let n = bytes.len() as u64;
        let before = self.0.fetch_add(n, Ordering::AcqRel);
        if before.saturating_add(n) > MAX_IN_FLIGHT && before > 0 {
            self.0.fetch_sub(n, Ordering::AcqRel);
            return None;
        }
        Some(Counted {
            inner: Full::new(bytes),
            n,
            owner: self.clone(),
        })
    }

    /// Bytes in flight now.
    pub fn bytes(&self) -> u64 {
        self.0.load(Ordering::Acquire)
    }
}

/// A whole body whose bytes count in its [`InFlight`] until it is dropped
/// (sent, or its connection closed).
#[derive(Debug)]
pub struct Counted {
    inner: Full<Bytes>,
    n: u64,
    owner: Arc<InFlight>,
}

impl Drop for Counted {
    fn drop(&mut self) {
        self.owner.0.fetch_sub(self.n, Ordering::AcqRel);
    }
}

impl Body for Counted {
    type Data = Bytes;
    type Error = Infallible;

    fn poll_frame(
        mut self: Pin<&mut Self>,
        cx: &mut Context<'_>,
    ) -> Poll<Option<Result<Frame<Bytes>, Infallible>>> {
        Pin::new(&mut self.inner).poll_frame(cx)
    }

    fn is_end_stream(&self) -> bool {
        self.inner.is_end_stream()
    }

    fn size_hint(&self) -> SizeHint {
        self.inner.size_hint()
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn bodies_count_until_dropped_and_the_bound_refuses_more() {
        let f = Arc::new(InFlight::default());
        let big = Bytes::from(vec![0u8; (MAX_IN_FLIGHT / 2) as usize]);
        let a = f.body(big.clone()).unwrap();
        let b = f.body(big.clone()).unwrap();
        assert_eq!(f.bytes(), MAX_IN_FLIGHT);
        assert!(f.body(Bytes::from_static(b"x")).is_none(), "over the bound");
        assert_eq!(f.bytes(), MAX_IN_FLIGHT, "a refusal counts nothing");
        drop(a);
        assert_eq!(f.bytes(), MAX_IN_FLIGHT / 2);
        assert!(f.body(Bytes::from_static(b"x")).is_some());
        drop(b);
        assert_eq!(f.bytes(), 0);
        // One body larger than the bound alone is still sent.
        let huge = Bytes::from(vec![0u8; (MAX_IN_FLIGHT + 1) as usize]);
        assert!(f.body(huge).is_some());
        assert_eq!(f.bytes(), 0);
    }
}
