//! A script's health, shared by column and voxel scripts: its failed steps
//! in a row, counted once a tick however many CFL sub-steps the tick took,
//! and why it is suspended once [`SUSPEND_AFTER`] of them follow each other.

use super::SimError;

/// Failed steps in a row that suspend a script (a reload resumes it).
pub const SUSPEND_AFTER: u32 = 3;

/// A script's failed steps in a row and its suspension.
///
/// ```
/// use brickworld::sim::{Health, Rejection, SimError};
/// let boom = SimError::Unstable {
///     script: "s".into(),
///     kind: Rejection::NotFinite,
///     msg: "boom".into(),
/// };
/// let mut h = Health::default();
/// h.failed(1, &boom);
/// h.failed(1, &boom); // a second sub-step of tick 1: still one failure
/// h.succeeded(1); // nor does a later sub-step of a failed tick clear it
/// assert_eq!(h.failures(), 1);
/// h.failed(2, &boom);
/// h.failed(3, &boom);
/// assert!(h.suspended().is_some());
/// ```
#[derive(Clone, Debug, Default)]
pub struct Health {
    failures: u32,
    /// The tick whose step last failed, so that a tick's sub-steps count
    /// one failure between them.
    failed_tick: Option<u64>,
    suspended: Option<SimError>,
}

impl Health {
    /// The health a rebuilt or resumed simulation carries over.
    pub fn restored(failures: u32, suspended: Option<SimError>) -> Self {
        Health {
            failures,
            failed_tick: None,
            suspended,
        }
    }

    /// Failed steps (ticks) in a row.
    pub fn failures(&self) -> u32 {
        self.failures
    }

    /// Why the script is suspended, if it is.
    pub fn suspended(&self) -> Option<&SimError> {
        self.suspended.as_ref()
    }

    /// A step at `tick` that ran on some work succeeded: the streak ends,
    /// unless an earlier sub-step of the same tick failed.
    pub fn succeeded(&mut self, tick: u64) {
        if self.failed_tick != Some(tick) {
            self.failures = 0;
        }
    }

    /// A step at `tick` failed with `e`: one failure a tick (regression:
    /// each CFL sub-step counted, so a script failing in every sub-step
    /// was suspended within one tick); the [`SUSPEND_AFTER`]th suspends
    /// the script.
    pub fn failed(&mut self, tick: u64, e: &SimError) {
        if self.failed_tick != Some(tick) {
            self.failures = self.failures.saturating_add(1);
            self.failed_tick = Some(tick);
        }
        if self.failures >= SUSPEND_AFTER && self.suspended.is_none() {
            self.suspended = Some(e.clone());
        }
    }
}
