//! The engine's step rate: steps per second over one-second windows, and,
//! until the first window has filled, the rate so far (a run shorter than a
//! second reported 0).

use std::time::{Duration, Instant};

/// How long one measuring window lasts.
const WINDOW: Duration = Duration::from_secs(1);

/// Steps per second, measured over [`WINDOW`]s.
#[derive(Clone, Copy, Debug)]
pub(super) struct StepRate {
    started: Instant,
    steps: u64,
    /// The last full window's rate, once one has filled.
    full: Option<f64>,
    /// What [`per_s`](Self::per_s) answers.
    shown: f64,
}

impl StepRate {
    /// A rate with no steps yet, its first window opening at `now`.
    pub(super) fn new(now: Instant) -> Self {
        StepRate {
            started: now,
            steps: 0,
            full: None,
            shown: 0.0,
        }
    }

    /// Count a step that ended at `now`.
    pub(super) fn step(&mut self, now: Instant) {
        self.steps += 1;
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

    /// Steps per second: the last full window's, or the first window's so far.
    pub(super) fn per_s(&self) -> f64 {
        self.shown
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
        assert_eq!(r.per_s(), 0.0);
        for i in 1..=4 {
            r.step(t0 + Duration::from_millis(100 * i));
        }
        assert!((r.per_s() - 10.0).abs() < 1e-9, "{}", r.per_s());
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
        assert!((r.per_s() - 5.0).abs() < 1e-9, "{}", r.per_s());
    }

    #[test]
    fn full_windows_replace_the_first_estimate_and_hold_between_windows() {
        let t0 = Instant::now();
        let mut r = StepRate::new(t0);
        for i in 1..=5 {
            r.step(t0 + Duration::from_millis(200 * i));
        }
        assert!((r.per_s() - 5.0).abs() < 1e-9, "{}", r.per_s());
        // A slower second window: the rate holds until it is full.
        let t1 = t0 + Duration::from_secs(1);
        r.step(t1 + Duration::from_millis(500));
        assert!((r.per_s() - 5.0).abs() < 1e-9, "{}", r.per_s());
        r.step(t1 + Duration::from_millis(1000));
        assert!((r.per_s() - 2.0).abs() < 1e-9, "{}", r.per_s());
    }
}
