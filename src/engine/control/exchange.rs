//! What the control server and the engine hand each other besides the
//! event stream: the timeline's last rows for the viewer's charts, the
//! camera lease between viewers, and the slot a command's verdict comes
//! back through.

use std::collections::VecDeque;
use std::sync::Arc;
use std::time::{Duration, Instant};

use serde::Serialize;

use super::live::unix_ms;

/// Timeline rows kept for the charts.
pub const TIMELINE_ROWS: usize = 4096;
/// A viewer keeps the camera this long after its last move.
pub const CAMERA_LEASE: Duration = Duration::from_secs(3);

/// The timeline's last [`TIMELINE_ROWS`] rows, for the viewer's charts.
#[derive(Debug, Default)]
pub struct TimelineRing {
    /// Column names (the timeline CSV's header).
    pub columns: Vec<String>,
    rows: VecDeque<(u64, Vec<f64>)>,
    next: u64,
    /// Changed when the columns change (a reload) and at every start:
    /// clients start over. The first is the start's time in ms since the
    /// Unix epoch, so an engine started again numbers its rows afresh under
    /// another epoch (regression, long-run probe: a restart numbered them
    /// from the rows read back under the same epoch 1, and a client that
    /// kept its `since` got nothing until the count passed it).
    pub epoch: u64,
}

/// Rows for one client: everything after `since`.
#[derive(Debug, Serialize)]
pub struct Rows {
    /// Column names.
    pub columns: Vec<String>,
    /// Column set; a change means "clear your charts".
    pub epoch: u64,
    /// The rows, oldest first.
    pub rows: Vec<Vec<f64>>,
    /// Pass this as `since` next time.
    pub next: u64,
}

impl TimelineRing {
    /// Append a row under `columns` (a different column set starts over).
    pub fn push(&mut self, columns: &[String], values: Vec<f64>) {
        if self.columns != columns {
            self.columns = columns.to_vec();
            self.rows.clear();
            self.epoch = (self.epoch + 1).max(unix_ms() as u64);
        }
        self.rows.push_back((self.next, values));
        self.next += 1;
        while self.rows.len() > TIMELINE_ROWS {
            self.rows.pop_front();
        }
    }

    /// The rows the answer for `since` and `epoch` starts from (the first
    /// kept one if `since` is older, or of another epoch) with the epoch,
    /// and about its size in JSON (24 bytes a value).
    pub fn answer_of(&self, since: u64, epoch: u64) -> (super::inflight::AnswerKey, u64) {
        let since = if epoch == self.epoch { since } else { 0 };
        let first = self.rows.front().map_or(self.next, |r| r.0);
        let from = since.clamp(first, self.next);
        let values = (self.next - from).saturating_mul(self.columns.len() as u64);
        ((from, self.epoch), values.saturating_mul(24))
    }

    /// The rows numbered `since` or later (all kept ones if `since` is
    /// older than the ring, or from another epoch).
    pub fn since(&self, since: u64, epoch: u64) -> Rows {
        let since = if epoch == self.epoch { since } else { 0 };
        Rows {
            columns: self.columns.clone(),
            epoch: self.epoch,
            rows: self
                .rows
                .iter()
                .filter(|(n, _)| *n >= since)
                .map(|(_, v)| v.clone())
                .collect(),
            next: self.next,
        }
    }
}

/// Who holds the camera: the viewer that moved it last, for
/// [`CAMERA_LEASE`] after its last move. Others' moves are refused (409)
/// meanwhile; `ctl` and calls without a viewer id always win.
#[derive(Debug, Default)]
pub struct CameraLease {
    holder: Option<(String, Instant)>,
}

impl CameraLease {
    /// Take or renew the camera for `viewer` (None: an administrative
    /// move, which always wins and holds nothing). `Err` says who holds it
    /// and for how long.
    pub fn take(&mut self, viewer: Option<&str>, now: Instant) -> Result<(), String> {
        let Some(v) = viewer else {
            self.holder = None;
            return Ok(());
        };
        if let Some((h, at)) = &self.holder {
            let left = CAMERA_LEASE.saturating_sub(now.saturating_duration_since(*at));
            if h != v && !left.is_zero() {
                return Err(format!(
                    "another viewer is moving the camera; it is free {:.1} s after their last move",
                    left.as_secs_f64()
                ));
            }
        }
        self.holder = Some((v.to_string(), now));
        Ok(())
    }

    /// The holder, while its lease lasts.
    pub fn holder(&self, now: Instant) -> Option<&str> {
        self.holder
            .as_ref()
            .filter(|(_, at)| now.saturating_duration_since(*at) < CAMERA_LEASE)
            .map(|(h, _)| h.as_str())
    }
}

/// The engine's answer to a command that waits for one (a parameter
/// change): applied, or refused with the reason.
pub type Verdict = Result<(), String>;

/// Where the engine sends a [`Verdict`]; comparing or cloning one compares
/// or clones nothing (commands are compared by what they ask).
#[derive(Clone, Default)]
pub struct VerdictSlot(Arc<std::sync::Mutex<Option<tokio::sync::oneshot::Sender<Verdict>>>>);

impl VerdictSlot {
    /// A slot and the receiver of its verdict.
    pub fn new() -> (Self, tokio::sync::oneshot::Receiver<Verdict>) {
        let (tx, rx) = tokio::sync::oneshot::channel();
        (VerdictSlot(Arc::new(std::sync::Mutex::new(Some(tx)))), rx)
    }

    /// Deliver the verdict (once; nobody waiting is fine).
    pub fn send(&self, v: Verdict) {
        if let Some(tx) = self.0.lock().ok().and_then(|mut s| s.take()) {
            let _ = tx.send(v);
        }
    }
}

impl std::fmt::Debug for VerdictSlot {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.write_str("VerdictSlot")
    }
}

impl PartialEq for VerdictSlot {
    fn eq(&self, _: &Self) -> bool {
        true
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn the_camera_lease_holds_off_other_viewers_until_it_lapses() {
        let mut l = CameraLease::default();
        let t0 = Instant::now();
        assert!(l.take(Some("a"), t0).is_ok());
        assert!(l.take(Some("a"), t0 + Duration::from_secs(1)).is_ok());
        let refused = l.take(Some("b"), t0 + Duration::from_secs(2)).unwrap_err();
        assert!(refused.contains("another viewer"), "{refused}");
        assert_eq!(l.holder(t0 + Duration::from_secs(2)), Some("a"));
        // Free once "a" has not moved for the lease.
        assert!(l.take(Some("b"), t0 + Duration::from_secs(5)).is_ok());
        // An administrative move always wins and frees the camera.
        assert!(l.take(None, t0 + Duration::from_secs(5)).is_ok());
        assert!(l.take(Some("c"), t0 + Duration::from_secs(5)).is_ok());
    }

    #[test]
    fn timeline_rows_are_handed_out_once_and_a_new_column_set_starts_over() {
        let mut r = TimelineRing::default();
        let cols = vec!["tick".to_string()];
        r.push(&cols, vec![1.0]);
        r.push(&cols, vec![2.0]);
        let a = r.since(0, u64::MAX);
        assert_eq!(a.rows, vec![vec![1.0], vec![2.0]]);
        r.push(&cols, vec![3.0]);
        let b = r.since(a.next, a.epoch);
        assert_eq!(b.rows, vec![vec![3.0]]);
        let cols2 = vec!["tick".to_string(), "ms:lava".to_string()];
        r.push(&cols2, vec![4.0, 0.5]);
        let c = r.since(b.next, b.epoch);
        assert_ne!(c.epoch, b.epoch);
        assert_eq!(c.rows, vec![vec![4.0, 0.5]]);
        for i in 0..TIMELINE_ROWS + 10 {
            r.push(&cols2, vec![i as f64, 0.0]);
        }
        assert_eq!(r.since(0, c.epoch).rows.len(), TIMELINE_ROWS);
    }

    /// Two starts of the engine hand out rows under different epochs, so
    /// a client's `since` from before a restart is not read against the
    /// new numbering (regression, long-run probe).
    #[test]
    fn a_restart_starts_a_new_timeline_epoch() {
        let cols = vec!["tick".to_string()];
        let mut before = TimelineRing::default();
        before.push(&cols, vec![1.0]);
        std::thread::sleep(std::time::Duration::from_millis(3));
        let mut after = TimelineRing::default();
        after.push(&cols, vec![1.0]);
        let (a, b) = (before.since(0, u64::MAX), after.since(0, u64::MAX));
        assert_ne!(a.epoch, b.epoch);
        // A client of the first start gets all of the second's rows.
        let c = after.since(a.next + 100, a.epoch);
        assert_eq!(c.rows.len(), 1);
    }
}
