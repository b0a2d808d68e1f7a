//! What a render window may cost: its size checked against what the
//! process may still allocate, the rest of the process measured (and
//! measured again as it grows), and the column cache kept to what the
//! budget leaves.

use std::time::Instant;

use glam::{IVec2, IVec3};

use super::{REMEASURE, RenderWindow};
use crate::scene::SceneError;

impl RenderWindow {
    /// `budget`, or less where the machine has less: the window (a box of
    /// `size` voxels, estimated as a built world of that size is: its grid
    /// and every column's bricks) must fit what this process may still
    /// allocate, and the budget must not promise the cache more than that
    /// (regression, scale probe: a view distance whose window could not
    /// fit, or a budget of 1 TiB on a machine of a few GiB, aborted the
    /// engine and `bench flight` with "memory allocation failed", or had
    /// them killed out of memory).
    pub(super) fn affordable(budget: u64, size: IVec3) -> Result<u64, SceneError> {
        Self::check_size(size)?;
        Ok(crate::scene::budget::within_reach(budget))
    }

    /// Refuse a window of `radius` chunk columns over a world of `height`
    /// voxels that would not fit what this process may still allocate
    /// (the engine asks at start, before the renderer opens it).
    pub fn check_fits(radius: i32, height: i32) -> Result<(), SceneError> {
        let (lo, hi) = Self::bounds(IVec2::ZERO, radius.max(1), height);
        Self::check_size(hi - lo)
    }

    fn check_size(size: IVec3) -> Result<(), SceneError> {
        use crate::scene::budget::{headroom_bytes, human, world_bytes};
        let (need, room) = (world_bytes(size), headroom_bytes());
        if need > room {
            return Err(SceneError::OutOfMemory {
                what: "the view window".into(),
                msg: format!(
                    "a window of {} by {} voxels needs about {}; {} is available: lower [stream] view_distance",
                    size.x,
                    size.z,
                    human(need),
                    human(room)
                ),
            });
        }
        Ok(())
    }

    /// The memory budget the window keeps to: the one asked for, or less
    /// where the machine has less.
    pub fn budget_bytes(&self) -> u64 {
        self.settings.budget_bytes
    }

    pub(super) fn window_bytes(&self) -> u64 {
        let store = &self.world.store;
        (store.pool().bytes()
            + store.pool().index_bytes()
            + self.world.grid.bytes()
            + store.non_empty_bricks() * 24) as u64
    }

    /// Measure what the process holds besides the window and its cache
    /// (code, threads, the simulation, its own world copy…) from its
    /// resident memory now; the cache's allowance is the budget less this
    /// and the window. Call it once the first window is exact.
    pub fn measure_overhead(&mut self) {
        let rss = crate::scene::budget::rss_kb() * 1024;
        self.stats.overhead_bytes = rss.saturating_sub(self.window_bytes() + self.cache.bytes());
        let share = self
            .settings
            .budget_bytes
            .saturating_sub(self.window_bytes() + self.stats.overhead_bytes);
        self.measured = Some((share, Instant::now()));
        self.evict();
    }

    /// Measure the rest again every [`REMEASURE`]: what it holds grows as
    /// the process runs (region moves, the store's pages, the allocator's
    /// arenas after many slides), and a share sized by the first figure
    /// let the daemon end 49 to 60 % over its budget (memory probe: the
    /// rest grew from 117 to 330 MB under half an hour of teleports). Only
    /// growth is taken, and the cache keeps at least a quarter of its first
    /// share: memory the allocator keeps after an eviction reads as "the
    /// rest" too, and would otherwise shrink the cache to nothing.
    pub(super) fn remeasure(&mut self) {
        let Some((share, at)) = self.measured else {
            return;
        };
        if at.elapsed() < REMEASURE {
            return;
        }
        self.measured = Some((share, Instant::now()));
        let rss = crate::scene::budget::rss_kb() * 1024;
        let window = self.window_bytes();
        self.stats.overhead_bytes = grown_rest(
            self.stats.overhead_bytes,
            rss.saturating_sub(window + self.cache.bytes()),
            self.settings.budget_bytes.saturating_sub(window),
            share,
        );
    }

    pub(super) fn evict(&mut self) {
        let allowance = self
            .settings
            .budget_bytes
            .saturating_sub(self.window_bytes() + self.stats.overhead_bytes);
        self.stats.evicted += self.cache.evict_to(allowance);
    }
}

/// The rest of the process as a window counts it: `rest` (measured now)
/// where it grew past `was`, but never so much that the cache's share of
/// `room` (the budget less the window) falls below a quarter of its first
/// `share`.
pub(super) fn grown_rest(was: u64, rest: u64, room: u64, share: u64) -> u64 {
    was.max(rest.min(room.saturating_sub(share / 4)))
}
