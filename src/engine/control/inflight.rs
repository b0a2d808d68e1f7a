//! A bound on the bytes of built responses still being sent: a body made
//! for one client (the whole timeline, megabytes with many channels) is
//! held until that client has read it, and a client that never reads
//! would otherwise pin one such copy per connection (memory probe: 120
//! clients pipelining `GET /timeline` and reading nothing held 2.8 GB).
//! A response over the bound is refused with 503 instead.

use std::sync::Arc;
use std::sync::atomic::{AtomicU64, Ordering};

use bytes::Bytes;

/// Most bytes of counted responses in flight at once, across clients.
pub const MAX_IN_FLIGHT: u64 = 64 << 20;

/// The bytes of counted responses in flight (shared by the server).
#[derive(Debug, Default)]
pub struct InFlight(AtomicU64);

impl InFlight {
    /// `body` as bytes that count until the last reference to them is
    /// dropped (hyper holds them in its write queue until the client has
    /// read them, or its connection closes), or `None` if they would take
    /// the total past [`MAX_IN_FLIGHT`] (one body alone always passes).
    pub fn bytes_of(self: &Arc<Self>, body: Vec<u8>) -> Option<Bytes> {
        let n = body.len() as u64;
        let before = self.0.fetch_add(n, Ordering::AcqRel);
        if before.saturating_add(n) > MAX_IN_FLIGHT && before > 0 {
            self.0.fetch_sub(n, Ordering::AcqRel);
            return None;
        }
        Some(Bytes::from_owner(Counted {
            body,
            n,
            owner: self.clone(),
        }))
    }

    /// Bytes in flight now.
    pub fn bytes(&self) -> u64 {
        self.0.load(Ordering::Acquire)
    }
}

/// A body's bytes, counted in their [`InFlight`] until dropped. (A count
/// kept by the response body instead fell to 0 as soon as hyper took the
/// bytes into its write queue, which is where a client that reads nothing
/// leaves them: the first version of this bound held nothing.)
struct Counted {
    body: Vec<u8>,
    n: u64,
    owner: Arc<InFlight>,
}

impl AsRef<[u8]> for Counted {
    fn as_ref(&self) -> &[u8] {
        &self.body
    }
}

impl Drop for Counted {
    fn drop(&mut self) {
        self.owner.0.fetch_sub(self.n, Ordering::AcqRel);
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn bytes_count_until_their_last_reference_drops_and_the_bound_refuses_more() {
        let f = Arc::new(InFlight::default());
        let half = (MAX_IN_FLIGHT / 2) as usize;
        let a = f.bytes_of(vec![0u8; half]).unwrap();
        let b = f.bytes_of(vec![0u8; half]).unwrap();
        assert_eq!(f.bytes(), MAX_IN_FLIGHT);
        assert!(f.bytes_of(vec![1]).is_none(), "over the bound");
        assert_eq!(f.bytes(), MAX_IN_FLIGHT, "a refusal counts nothing");
        // A slice (as a partial write leaves) keeps the whole counted.
        let tail = a.slice(half - 10..);
        drop(a);
        assert_eq!(f.bytes(), MAX_IN_FLIGHT);
        drop(tail);
        assert_eq!(f.bytes(), MAX_IN_FLIGHT / 2);
        assert!(f.bytes_of(vec![1]).is_some());
        drop(b);
        assert_eq!(f.bytes(), 0);
        // One body larger than the bound alone is still sent.
        assert!(
            f.bytes_of(vec![0u8; (MAX_IN_FLIGHT + 1) as usize])
                .is_some()
        );
        assert_eq!(f.bytes(), 0);
    }
}
