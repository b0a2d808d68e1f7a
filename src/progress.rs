//! Progress bars for long work (scene building, octree building, benches).
//! They draw on stderr and hide themselves when stderr is not a terminal.

use indicatif::{ProgressBar, ProgressStyle};

/// A bar with a message; `len` may be set later by the work itself.
pub fn bar(msg: &'static str, len: u64) -> ProgressBar {
    let pb = ProgressBar::new(len);
    pb.set_style(
        ProgressStyle::with_template(
            "{msg:>14} [{bar:36}] {pos}/{len} {elapsed_precise} eta {eta}",
        )
        .unwrap_or_else(|_| ProgressStyle::default_bar())
        .progress_chars("=> "),
    );
    pb.set_message(msg);
    pb
}

/// A spinner for work with no count. It ticks on a thread of its own
/// only where it is drawn and a thread can start: indicatif's ticker
/// panics when it cannot start its thread (regression, hostile environment
/// probe: `bench store` at a low `ulimit -u` ended in a panic).
pub fn spinner(msg: &'static str) -> ProgressBar {
    let pb = ProgressBar::new_spinner().with_message(msg);
    let can_start = || {
        std::thread::Builder::new()
            .spawn(|| {})
            .is_ok_and(|h| h.join().is_ok())
    };
    if !pb.is_hidden() && can_start() {
        pb.enable_steady_tick(std::time::Duration::from_millis(200));
    }
    pb
}
