//! The clock of a kernel call's time budget: the calling thread's own CPU
//! time, so that time the thread did not run (the process stopped by
//! Ctrl-Z or SIGSTOP, a paused VM or container, a machine with more busy
//! threads than cores) is not counted against the script. The wall clock
//! stays the fast first check: the CPU clock, a system call, is read only
//! once a call's wall-clock deadline has passed, and to refresh a
//! per-thread reference at most every [`REFRESH`].
//!
//! Regression (stop-path probe): a suspend of 5 s or more made a 100 ms
//! kernel trip its 5 s budget, so the step failed, and the world parted
//! from one that never stopped.

use std::cell::Cell;
use std::time::{Duration, Instant};

/// How stale a thread's CPU reference may be when a call is armed: the
/// CPU time a call is charged is over-counted by at most this much (the
/// thread's running time between the reference and the call's start).
pub const REFRESH: Duration = Duration::from_millis(10);

thread_local! {
    /// The last reading of this thread's CPU time, and when it was taken.
    static REFERENCE: Cell<Option<(Instant, Option<Duration>)>> = const { Cell::new(None) };
}

/// This thread's CPU time so far, where the system can say (Linux and
/// other Unix systems with per-thread CPU clocks).
pub fn thread_cpu() -> Option<Duration> {
    #[cfg(unix)]
    {
        use nix::time::{ClockId, clock_gettime};
        let t = clock_gettime(ClockId::CLOCK_THREAD_CPUTIME_ID).ok()?;
        Some(Duration::new(
            u64::try_from(t.tv_sec()).ok()?,
            u32::try_from(t.tv_nsec()).ok()?,
        ))
    }
    #[cfg(not(unix))]
    {
        None
    }
}

/// A reading of this thread's CPU time taken at most [`REFRESH`] before
/// `now` (taken afresh when the last one is older): the CPU time a call
/// armed at `now` starts from, give or take what ran since.
pub fn reference(now: Instant) -> Option<Duration> {
    REFERENCE.with(|r| match r.get() {
        Some((at, cpu)) if now.saturating_duration_since(at) <= REFRESH => cpu,
        _ => {
            let cpu = thread_cpu();
            r.set(Some((now, cpu)));
            cpu
        }
    })
}

/// Called once a call's wall-clock `deadline` has passed: whether the call
/// has also run for its `budget` of CPU time since `start` (its
/// [`reference`]). If it has not, the deadline moves to when it would, and
/// the call goes on. Without a CPU clock, the wall clock decides.
pub fn spent(deadline: &mut Instant, budget: Duration, start: Option<Duration>) -> bool {
    let (Some(start), Some(now)) = (start, thread_cpu()) else {
        return true;
    };
    let used = now.saturating_sub(start);
    if used >= budget {
        return true;
    }
    *deadline = Instant::now() + (budget - used);
    false
}

#[cfg(test)]
mod tests {
    use super::*;

    /// A thread that sleeps past its wall-clock deadline has not spent its
    /// budget (the deadline moves on); one that runs past it has.
    #[cfg(target_os = "linux")]
    #[test]
    fn sleeping_is_not_spending_and_running_is() {
        let budget = Duration::from_millis(40);
        let start = reference(Instant::now());
        assert!(start.is_some(), "no per-thread CPU clock on Linux");
        let mut deadline = Instant::now() + budget;
        std::thread::sleep(Duration::from_millis(80));
        assert!(Instant::now() > deadline);
        assert!(!spent(&mut deadline, budget, start));
        assert!(deadline > Instant::now(), "the deadline moved on");
        // Now burn the CPU past the budget.
        let t = Instant::now();
        let mut x = 0u64;
        while t.elapsed() < Duration::from_millis(60) {
            x = std::hint::black_box(x.wrapping_add(1));
        }
        assert!(spent(&mut deadline, budget, start));
    }
}
