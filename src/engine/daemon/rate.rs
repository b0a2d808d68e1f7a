//! The engine's step rate: steps per second over one-second windows, and,
//! until the first window has filled, the rate so far (a run shorter than a
//! second reported 0). Once no step has ended for a while (the engine is
//! paused, or held up), it reads 0.

use std::time::{Duration, Instant};

/// How long one measuring window lasts.
const WINDOW: Duration = Duration::from_secs(1);

/// With no step for this long, or for three of the shown rate's steps
/// if that is longer, the rate reads 0.
const QUIET: Duration = Duration::from_secs(2);

/// Steps per second, measured over [`WINDOW`]s.
#[derive(Clone, Copy, Debug)]
pub(super) struct StepRate {
    started: Instant,
    steps: u64,
    /// The last full window's rate, once one has filled.
    full: Option<f64>,
    /// What [`per_s`](Self::per_s) answers while steps go on.
    shown: f64,
    /// When the last step ended.
    last: Instant,
}

impl StepRate {
    /// A rate with no steps yet, its first window opening at `now`.
    pub(super) fn new(now: Instant) -> Self {
        StepRate {
            started: now,
            steps: 0,
            full: None,
            shown: 0.0,
            last: now,
        }
    }

    /// Count a step that ended at `now`.
    pub(super) fn step(&mut self, now: Instant) {
        self.steps += 1;
        self.last = now;
        let elapsed = now.saturating_duration_since(self.started);
        if elapsed >= WINDOW {
            let rate = self.steps as f64 / elapsed.as_secs_f64();
            self.full = Some(rate);
            self.shown = rate;
            self.started = now;
            self.steps = 0;
        } else if self.full.is_none() && !elapsed.is_zero() {
            // The first window is still filling: the rate so far.
            self.shown = self.steps as f64 / elapsed.as_secs_f64();
        }
    }

    /// Open a new window at `now`, keeping what is shown until it fills:
    /// for a resume, so the time spent paused is not counted as time the
    /// steps took (regression: the first window after a minute's pause
    /// showed a fraction of a step per second).
    pub(super) fn restart(&mut self, now: Instant) {
        self.started = now;
        self.steps = 0;
    }

    /// Steps per second at `now`: the last full window's, or the first
    /// window's so far; 0 once no step has ended for [`QUIET`] or three of
    /// its steps (regression, long-run probe: a paused engine showed the
    /// rate of its last second of running for as long as it stayed paused).
    pub(super) fn per_s(&self, now: Instant) -> f64 {
        if self.shown <= 0.0 {
            return 0.0;
        }
        let quiet = now.saturating_duration_since(self.last).as_secs_f64();
        if quiet > QUIET.as_secs_f64().max(3.0 / self.shown) {
            0.0
        } else {
            self.shown
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn a_run_shorter_than_a_second_reports_its_step_rate() {
        // Regression: a run of under a second reported 0 steps/s.
        let t0 = Instant::now();
        let mut r = StepRate::new(t0);
        assert_eq!(r.per_s(r.last), 0.0);
        for i in 1..=4 {
            r.step(t0 + Duration::from_millis(100 * i));
        }
        assert!((r.per_s(r.last) - 10.0).abs() < 1e-9, "{}", r.per_s(r.last));
    }

    #[test]
    fn time_spent_paused_is_not_counted_after_a_resume() {
        let t0 = Instant::now();
        let mut r = StepRate::new(t0);
        for i in 1..=5 {
            r.step(t0 + Duration::from_millis(200 * i));
        }
        // Paused for a minute, then resumed: 5 steps a second again.
        let t1 = t0 + Duration::from_secs(61);
        r.restart(t1);
        for i in 1..=5 {
            r.step(t1 + Duration::from_millis(200 * i));
        }
        assert!((r.per_s(r.last) - 5.0).abs() < 1e-9, "{}", r.per_s(r.last));
    }

    #[test]
    fn full_windows_replace_the_first_estimate_and_hold_between_windows() {
        let t0 = Instant::now();
        let mut r = StepRate::new(t0);
        for i in 1..=5 {
            r.step(t0 + Duration::from_millis(200 * i));
        }
        assert!((r.per_s(r.last) - 5.0).abs() < 1e-9, "{}", r.per_s(r.last));
        // A slower second window: the rate holds until it is full.
        let t1 = t0 + Duration::from_secs(1);
        r.step(t1 + Duration::from_millis(500));
        assert!((r.per_s(r.last) - 5.0).abs() < 1e-9, "{}", r.per_s(r.last));
        r.step(t1 + Duration::from_millis(1000));
        assert!((r.per_s(r.last) - 2.0).abs() < 1e-9, "{}", r.per_s(r.last));
    }

    #[test]
    fn a_paused_engine_reads_zero_steps_a_second() {
        let t0 = Instant::now();
        let mut r = StepRate::new(t0);
        for i in 1..=10 {
            r.step(t0 + Duration::from_millis(100 * i));
        }
        let t1 = r.last;
        assert!((r.per_s(t1 + QUIET) - 10.0).abs() < 1e-9);
        assert_eq!(r.per_s(t1 + QUIET + Duration::from_millis(1)), 0.0);
        // A slow world (a step every 4 s) is not taken for a paused one
        // between its steps, only after three of them.
        let mut slow = StepRate::new(t0);
        slow.step(t0 + Duration::from_secs(4));
        let t2 = slow.last;
        assert!((slow.per_s(t2 + Duration::from_secs(11)) - 0.25).abs() < 1e-9);
        assert_eq!(slow.per_s(t2 + Duration::from_secs(13)), 0.0);
    }
}
