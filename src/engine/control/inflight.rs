//! A bound on the bytes of built answers still being sent (the timeline's:
//! megabytes with many channels). An answer is held until its client has
//! read it, and a client that never reads would otherwise pin one copy per
//! connection (memory probe: 120 clients pipelining `GET /timeline` and
//! reading nothing held 2.8 GB).
//!
//! - A request that the last large answer serves shares its one copy: the
//!   same timeline (epoch), asked for from no later than the answer's first
//!   row (everything kept), within [`FRESH`] of its building. Its `next`
//!   tells the client where to go on, so rows added meanwhile come with its
//!   next request. (Keyed on the exact rows instead, an answer was never
//!   shared: a row is added every frame.)
//! - Answers up to [`SMALL`] (a poll for the rows since the last one) always
//!   pass: the connection cap bounds them.
//! - A larger answer that would take what is in flight past
//!   [`MAX_IN_FLIGHT`] is refused (the route answers 503), decided from its
//!   estimated size before it is built, so refusals cost no encoding; one
//!   alone always passes.

use std::sync::atomic::{AtomicU64, Ordering};
use std::sync::{Arc, Mutex};
use std::time::{Duration, Instant};

use bytes::Bytes;

/// Most bytes of large answers in flight at once, across clients.
pub const MAX_IN_FLIGHT: u64 = 256 << 20;
/// Answers up to this size are never refused.
pub const SMALL: u64 = 1 << 20;
/// How long a large answer is shared with later requests it serves.
pub const FRESH: Duration = Duration::from_secs(2);

/// Which rows an answer holds: from row `from` of timeline `epoch`.
pub type AnswerKey = (u64, u64);

/// The bytes of large answers in flight, and the last one built.
#[derive(Debug, Default)]
pub struct InFlight {
    bytes: AtomicU64,
    last: Mutex<Option<(AnswerKey, Instant, Bytes)>>,
}

impl InFlight {
    /// The last large answer, if it serves a request for the rows from
    /// `since` of timeline `epoch` (see the module's notes); if not, it is
    /// let go (a large answer is about to be built), so that only the
    /// clients still sending it count it.
    pub fn shared(&self, (since, epoch): AnswerKey) -> Option<Bytes> {
        let mut last = self.last.lock().unwrap_or_else(|p| p.into_inner());
        match last.as_ref() {
            Some(((from, e), at, b)) if *e == epoch && since <= *from && at.elapsed() < FRESH => {
                Some(b.clone())
            }
            _ => {
                *last = None;
                None
            }
        }
    }

    /// Whether an answer of about `estimate` bytes may be built now.
    pub fn may_build(&self, estimate: u64) -> bool {
        let now = self.bytes();
        estimate <= SMALL || now == 0 || now.saturating_add(estimate) <= MAX_IN_FLIGHT
    }

    /// `body`, built for `key`, as bytes that count (when large) until the
    /// last reference to them is dropped: hyper holds them in its write
    /// queue until the client has read them or its connection closes. `None`
    /// if it is large and would take the total past [`MAX_IN_FLIGHT`].
    pub fn admit(self: &Arc<Self>, key: AnswerKey, body: Vec<u8>) -> Option<Bytes> {
        let n = body.len() as u64;
        if n <= SMALL {
            return Some(Bytes::from(body));
        }
        let mut last = self.last.lock().unwrap_or_else(|p| p.into_inner());
        // The previous answer is no longer shared: only the clients still
        // sending it hold (and count) it.
        *last = None;
        let before = self.bytes.fetch_add(n, Ordering::AcqRel);
        if before > 0 && before.saturating_add(n) > MAX_IN_FLIGHT {
            self.bytes.fetch_sub(n, Ordering::AcqRel);
            return None;
        }
        let bytes = Bytes::from_owner(Counted {
            body,
            n,
            owner: self.clone(),
        });
        *last = Some((key, Instant::now(), bytes.clone()));
        Some(bytes)
    }

    /// Bytes of large answers in flight now (the shared one included).
    pub fn bytes(&self) -> u64 {
        self.bytes.load(Ordering::Acquire)
    }

    /// Make the shared answer `by` older (tests of [`FRESH`]).
    #[cfg(test)]
    fn age(&self, by: Duration) {
        if let Some((_, at, _)) = self.last.lock().unwrap().as_mut() {
            *at = at.checked_sub(by).expect("the clock has run that long");
        }
    }
}

/// An answer's bytes, counted in their [`InFlight`] until dropped. (A count
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
        self.owner.bytes.fetch_sub(self.n, Ordering::AcqRel);
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// Claims audit: nothing held the 2 s for which an answer is shared.
    #[test]
    fn a_large_answer_is_shared_for_fresh_and_not_after() {
        let f = Arc::new(InFlight::default());
        let a = f.admit((0, 1), vec![0u8; SMALL as usize + 1]).unwrap();
        f.age(FRESH - Duration::from_millis(100));
        assert!(f.shared((0, 1)).is_some(), "shared within FRESH");
        f.age(Duration::from_millis(200));
        assert!(f.shared((0, 1)).is_none(), "shared past FRESH");
        assert_eq!(f.bytes(), SMALL + 1, "its client still counts it");
        drop(a);
        assert_eq!(f.bytes(), 0);
    }

    #[test]
    fn large_answers_are_shared_and_count_until_their_last_reference_drops() {
        let f = Arc::new(InFlight::default());
        let half = (MAX_IN_FLIGHT / 2) as usize;
        let a = f.admit((5, 1), vec![0u8; half]).unwrap();
        // A request it serves shares it: from no later than its first row.
        let a2 = f.shared((0, 1)).unwrap();
        assert_eq!(a2.as_ptr(), a.as_ptr());
        assert!(f.shared((5, 1)).is_some());
        // Another one (later rows, or another timeline) lets it go; its
        // clients still count it.
        assert!(f.shared((6, 1)).is_none());
        assert!(f.shared((0, 1)).is_none(), "let go");
        assert_eq!(f.bytes(), MAX_IN_FLIGHT / 2);
        let b = f.admit((0, 2), vec![0u8; half]).unwrap();
        let b2 = f.shared((0, 2)).unwrap();
        assert_eq!(f.bytes(), MAX_IN_FLIGHT);
        assert!(!f.may_build(SMALL + 1));
        assert!(f.may_build(SMALL), "small answers always pass");
        assert!(f.admit((0, 3), vec![1; SMALL as usize]).is_some());
        assert!(f.admit((0, 3), vec![1; SMALL as usize + 1]).is_none());
        assert_eq!(f.bytes(), MAX_IN_FLIGHT, "a refusal counts nothing");
        // A slice (as a partial write leaves) keeps the whole counted.
        let tail = a.slice(half - 10..);
        drop((a, a2));
        assert_eq!(f.bytes(), MAX_IN_FLIGHT);
        drop(tail);
        assert_eq!(f.bytes(), MAX_IN_FLIGHT / 2);
        drop((b, b2));
        assert_eq!(f.bytes(), 0, "nothing held: no count is left behind");
        // One answer alone always passes; kept shared, it counts until
        // another large answer is asked for.
        drop(
            f.admit((0, 4), vec![0u8; (MAX_IN_FLIGHT + 1) as usize])
                .unwrap(),
        );
        assert_eq!(f.bytes(), MAX_IN_FLIGHT + 1);
        assert!(!f.may_build(SMALL + 1));
        assert!(f.shared((0, 5)).is_none());
        assert!(f.may_build(MAX_IN_FLIGHT));
        assert!(f.admit((0, 5), vec![0u8; half]).is_some());
    }
}
