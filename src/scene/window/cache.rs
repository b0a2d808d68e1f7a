//! The window's cache of columns that left it: packed columns by chunk
//! column, their bytes counted, and the least recently used dropped first
//! when the budget the window leaves is exceeded. Recency is a clock the
//! window advances once per update, so entries put in one update age
//! together and evictions among them follow the column order.

use glam::IVec2;
use rustc_hash::FxHashMap;

use super::Bricks;
use super::pack::{Cached, PackScratch, pack, unpack};
use crate::world::Palette;

/// Columns that left the window, LZ4-packed, with their byte count.
#[derive(Default)]
pub(super) struct ColumnCache {
    entries: FxHashMap<IVec2, Cached>,
    /// What the entries hold, map entries included.
    bytes: u64,
    /// Advanced once per window update; an entry remembers its put.
    clock: u64,
    scratch: PackScratch,
}

impl ColumnCache {
    /// One more window update: later puts count as more recent.
    pub(super) fn tick(&mut self) {
        self.clock += 1;
    }

    /// Keep column `col`'s bricks, replacing any entry it had.
    pub(super) fn put(&mut self, col: IVec2, bricks: &Bricks) {
        let entry = Cached {
            packed: pack(col, bricks, &mut self.scratch),
            used: self.clock,
        };
        self.bytes += entry.bytes();
        if let Some(old) = self.entries.insert(col, entry) {
            self.bytes -= old.bytes();
        }
    }

    /// Remove column `col`'s entry and return its bricks: `None` if it had
    /// none, or if its bytes did not unpack (it is dropped either way).
    pub(super) fn take(&mut self, col: IVec2, palette: &Palette) -> Option<Bricks> {
        let e = self.entries.remove(&col)?;
        self.bytes -= e.bytes();
        unpack(col, &e.packed, palette)
    }

    /// Drop every entry whose column `stale` says is stale.
    pub(super) fn drop_where(&mut self, stale: impl Fn(IVec2) -> bool) {
        let bytes = &mut self.bytes;
        self.entries.retain(|c, e| {
            let keep = !stale(*c);
            if !keep {
                *bytes -= e.bytes();
            }
            keep
        });
    }

    /// Drop the least recently put entries (ties by column) until the
    /// cache holds at most `allowance` bytes; returns how many went.
    pub(super) fn evict_to(&mut self, allowance: u64) -> u64 {
        if self.bytes <= allowance {
            return 0;
        }
        let mut by_age: Vec<(u64, IVec2)> =
            self.entries.iter().map(|(c, e)| (e.used, *c)).collect();
        by_age.sort_by_key(|(used, c)| (*used, c.x, c.y));
        let mut evicted = 0;
        for (_, c) in by_age {
            if self.bytes <= allowance {
                break;
            }
            if let Some(e) = self.entries.remove(&c) {
                self.bytes -= e.bytes();
                evicted += 1;
            }
        }
        evicted
    }

    /// Bytes held.
    pub(super) fn bytes(&self) -> u64 {
        self.bytes
    }

    /// Columns held.
    pub(super) fn len(&self) -> usize {
        self.entries.len()
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::world::BrickContent;
    use glam::IVec3;

    fn column(col: IVec2, m: u8) -> Bricks {
        let b = IVec3::new(
            col.x * crate::scene::CHUNK_BRICKS,
            0,
            col.y * crate::scene::CHUNK_BRICKS,
        );
        vec![
            (b, BrickContent::Uniform(m)),
            (b + IVec3::Y, BrickContent::Uniform(m)),
        ]
    }

    /// Bytes follow every put, replacement, take and drop; eviction takes
    /// the least recently put first (ties by column) and stops within the
    /// allowance; a take gives the bricks back and forgets them.
    #[test]
    fn the_cache_counts_its_bytes_and_evicts_the_oldest_first() {
        let palette = Palette::default();
        let mut c = ColumnCache::default();
        let (a, b, d) = (IVec2::new(0, 0), IVec2::new(1, 0), IVec2::new(-1, 2));
        c.put(b, &column(b, 3));
        c.tick();
        c.put(a, &column(a, 4));
        c.put(d, &column(d, 5));
        let one = c.bytes() / 3;
        assert_eq!((c.len(), c.bytes()), (3, 3 * one));
        c.put(a, &column(a, 6)); // replaced, not added
        assert_eq!((c.len(), c.bytes()), (3, 3 * one));
        assert_eq!(c.evict_to(2 * one), 1);
        assert_eq!(c.take(b, &palette), None, "the oldest went first");
        assert_eq!(c.evict_to(one), 1);
        assert_eq!(c.take(d, &palette), None, "then (-1, 2) before (0, 0)");
        assert_eq!(c.take(a, &palette), Some(column(a, 6)));
        assert_eq!((c.len(), c.bytes()), (0, 0));
        c.put(a, &column(a, 1));
        c.put(b, &column(b, 2));
        c.drop_where(|col| col == a);
        assert_eq!((c.len(), c.bytes()), (1, one));
        assert_eq!(c.evict_to(u64::MAX), 0);
    }
}
