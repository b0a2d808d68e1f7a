//! Simulation channels: named per-column fields (water, sediment, snow, flux
//! pipes…) stored sparsely per tile. A tile holds a channel's 64 values only
//! once something non-zero was written there: a dry tile has no water array.
//!
//! Values are `f64`, so that conserved totals drift only by round-off
//! (≈1e-16 relative per operation) over long runs.

use rustc_hash::{FxHashMap, FxHashSet};

use crate::persist::bytes::{Mixing, StateHasher};
use crate::sim::tile::{TILE_CELLS, TileCoord};

/// Small `Copy` handle to a channel in a [`ChannelStore`].
#[derive(Clone, Copy, Debug, PartialEq, Eq, Hash, PartialOrd, Ord)]
pub struct ChannelId(pub(crate) u16);

impl ChannelId {
    /// Position in the store's channel list.
    pub fn index(self) -> usize {
        self.0 as usize
    }
}

/// One tile's values of one channel.
pub type TileData = Box<[f64; TILE_CELLS]>;

/// Every channel of every tile, sparse.
#[derive(Clone, Debug, Default)]
pub struct ChannelStore {
    names: Vec<String>,
    tiles: FxHashMap<TileCoord, Vec<Option<TileData>>>,
    /// Tiles written since the last [`take_dirty`](Self::take_dirty): the
    /// only way to write ([`set`](Self::set)) records the tile, so the
    /// world store can commit exactly what changed.
    dirty: FxHashSet<TileCoord>,
}

impl ChannelStore {
    /// The channel called `name`, registering it if new.
    pub fn channel(&mut self, name: &str) -> ChannelId {
        if let Some(i) = self.names.iter().position(|n| n == name) {
            return ChannelId(i as u16);
        }
        self.names.push(name.to_string());
        ChannelId((self.names.len() - 1) as u16)
    }

    /// The channel called `name`, if registered.
    pub fn find(&self, name: &str) -> Option<ChannelId> {
        self.names
            .iter()
            .position(|n| n == name)
            .map(|i| ChannelId(i as u16))
    }

    /// Name of a channel.
    pub fn name(&self, ch: ChannelId) -> &str {
        &self.names[ch.0 as usize]
    }

    /// Registered channels.
    pub fn channels(&self) -> impl Iterator<Item = (ChannelId, &str)> {
        self.names
            .iter()
            .enumerate()
            .map(|(i, n)| (ChannelId(i as u16), n.as_str()))
    }

    /// Values of `ch` on tile `t`, `None` where never written (all zero).
    #[inline]
    pub fn get(&self, t: TileCoord, ch: ChannelId) -> Option<&[f64; TILE_CELLS]> {
        self.tiles.get(&t)?.get(ch.0 as usize)?.as_deref()
    }

    /// Store values of `ch` on tile `t`; an all-zero array frees the storage.
    pub fn set(&mut self, t: TileCoord, ch: ChannelId, data: &[f64; TILE_CELLS]) {
        self.dirty.insert(t);
        let all_zero = data.iter().all(|&v| v == 0.0);
        if all_zero {
            if let Some(v) = self.tiles.get_mut(&t)
                && let Some(slot) = v.get_mut(ch.0 as usize)
            {
                *slot = None;
                if v.iter().all(|s| s.is_none()) {
                    self.tiles.remove(&t);
                }
            }
            return;
        }
        let v = self.tiles.entry(t).or_default();
        if v.len() <= ch.0 as usize {
            v.resize(ch.0 as usize + 1, None);
        }
        match &mut v[ch.0 as usize] {
            Some(b) => **b = *data,
            slot => *slot = Some(Box::new(*data)),
        }
    }

    /// The tiles written since the last call (see the `dirty` field).
    pub fn take_dirty(&mut self) -> FxHashSet<TileCoord> {
        std::mem::take(&mut self.dirty)
    }

    /// Number of tiles holding `ch`.
    pub fn allocated(&self, ch: ChannelId) -> usize {
        self.tiles
            .values()
            .filter(|v| v.get(ch.0 as usize).is_some_and(|s| s.is_some()))
            .count()
    }

    /// Sum of `ch` over the world, in a fixed order (deterministic).
    pub fn total(&self, ch: ChannelId) -> f64 {
        let mut keys: Vec<&TileCoord> = self.tiles.keys().collect();
        keys.sort_by_key(|k| (k.y, k.x));
        // Neumaier summation: the total itself must not add drift.
        let (mut sum, mut comp) = (0.0f64, 0.0f64);
        for k in keys {
            if let Some(d) = self.get(*k, ch) {
                for &v in d.iter() {
                    let t = sum + v;
                    comp += if sum.abs() >= v.abs() {
                        (sum - t) + v
                    } else {
                        (v - t) + sum
                    };
                    sum = t;
                }
            }
        }
        sum + comp
    }

    /// Tiles holding any channel, sorted (z, then x).
    pub fn tiles(&self) -> Vec<TileCoord> {
        let mut keys: Vec<TileCoord> = self.tiles.keys().copied().collect();
        keys.sort_by_key(|k| (k.y, k.x));
        keys
    }

    /// Largest absolute value of `ch` (0 where nothing is stored).
    pub fn max_abs(&self, ch: ChannelId) -> f64 {
        self.tiles
            .values()
            .filter_map(|v| v.get(ch.0 as usize).and_then(|s| s.as_deref()))
            .flat_map(|d| d.iter())
            .fold(0.0f64, |m, v| m.max(v.abs()))
    }

    /// The hash checkpoint files of format versions 1 to 4 recorded: tiles
    /// in coordinate order, channels by id. Kept only to check those files;
    /// [`hash`](Self::hash) is the world's.
    pub fn hash_by_id(&self) -> u64 {
        let order: Vec<usize> = (0..self.names.len()).collect();
        self.hash_in(&order, |i| i as u64, Mixing::Words)
    }

    /// Hash of every channel's bits: tiles in coordinate order, channels in
    /// name order within a tile, each named by its name's hash. Ids are
    /// left out: they follow the order channels were registered in, which
    /// a hot reload that renames a channel changes and a restart does not
    /// repeat (regression: a world stopped after such a reload printed one
    /// hash at the stop, another at resume).
    pub fn hash(&self) -> u64 {
        self.hash_with(Mixing::Xxh3)
    }

    /// [`hash`](Self::hash) with the given mixing ([`Mixing::Words`] is
    /// what checkpoint files of format 5 recorded).
    pub fn hash_with(&self, mixing: Mixing) -> u64 {
        let mut order: Vec<usize> = (0..self.names.len()).collect();
        order.sort_by(|&a, &b| self.names[a].cmp(&self.names[b]));
        let named: Vec<u64> = self
            .names
            .iter()
            .map(|n| crate::persist::bytes::fnv1a(n.as_bytes()))
            .collect();
        self.hash_in(&order, |i| named[i], mixing)
    }

    /// The tiles (in coordinate order) and, within each, the channels of
    /// `order` that hold data, each mixed in as `key(id)` then its bits.
    fn hash_in(&self, order: &[usize], key: impl Fn(usize) -> u64, mixing: Mixing) -> u64 {
        let mut keys: Vec<&TileCoord> = self.tiles.keys().collect();
        keys.sort_by_key(|k| (k.y, k.x));
        let mut h = StateHasher::new(mixing);
        for k in keys {
            let slots = &self.tiles[k];
            for &i in order {
                if let Some(Some(d)) = slots.get(i) {
                    h.word(((k.x as u32 as u64) << 32) | k.y as u32 as u64);
                    h.word(key(i));
                    for v in d.iter() {
                        h.word(v.to_bits());
                    }
                }
            }
        }
        h.finish()
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::sim::tile::TILE_CELLS;
    use glam::IVec2;

    /// Regression: the hash mixed channel ids, which follow the order of
    /// registration; a reload that renamed a channel registered the new
    /// name after the old, a restart before it, and the same world hashed
    /// two ways.
    #[test]
    fn the_hash_does_not_depend_on_the_order_channels_were_registered_in() {
        let t = IVec2::new(2, -1);
        let (mut d1, mut d2) = ([0.0; TILE_CELLS], [0.0; TILE_CELLS]);
        d1[3] = 1.25;
        d2[7] = -2.0;
        let mut a = ChannelStore::default();
        let (old, x, y) = (a.channel("old"), a.channel("x"), a.channel("y"));
        a.set(t, x, &d1);
        a.set(t, y, &d2);
        let mut b = ChannelStore::default();
        let (y, x) = (b.channel("y"), b.channel("x"));
        b.set(t, y, &d2);
        b.set(t, x, &d1);
        assert_eq!(
            a.hash(),
            b.hash(),
            "an empty channel and the order do not count"
        );
        a.set(t, old, &d1);
        assert_ne!(a.hash(), b.hash(), "data in another channel counts");
        let mut c = ChannelStore::default();
        let (x, y) = (c.channel("x"), c.channel("y"));
        c.set(t, x, &d2);
        c.set(t, y, &d1);
        assert_ne!(c.hash(), b.hash(), "which channel holds what counts");
    }

    #[test]
    fn dry_tiles_hold_no_array_and_zeroing_frees_it() {
        let mut s = ChannelStore::default();
        let w = s.channel("water");
        let t = IVec2::new(-3, 4);
        assert!(s.get(t, w).is_none());
        let mut d = [0.0; TILE_CELLS];
        d[5] = 1.5;
        s.set(t, w, &d);
        assert_eq!(s.get(t, w).unwrap()[5], 1.5);
        assert_eq!(s.allocated(w), 1);
        s.set(t, w, &[0.0; TILE_CELLS]);
        assert!(s.get(t, w).is_none());
        assert_eq!(s.allocated(w), 0);
        assert_eq!(s.total(w), 0.0);
    }
}
