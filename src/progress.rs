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
