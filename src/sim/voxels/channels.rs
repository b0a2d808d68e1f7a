//! Per-voxel `f32` channels, stored sparsely per brick: a brick with no
//! water holds no water array, and writing all zeros frees it.
//!
//! `f32` is enough for fill levels, temperatures and the like (7 digits),
//! halves the memory and the data crossing into Lua of `f64`, and Luau's
//! `buffer.readf32`/`writef32` read it directly.

use glam::IVec3;
use rustc_hash::{FxHashMap, FxHashSet};

use crate::persist::bytes::{Mixing, StateHasher};
use crate::sim::script::VOXEL_CELLS;

/// A channel id (index into [`VoxelChannels`]).
pub type VoxelChannelId = usize;

/// Named per-voxel channels.
#[derive(Clone, Debug, Default)]
pub struct VoxelChannels {
    names: Vec<String>,
    data: Vec<FxHashMap<IVec3, Box<[f32; VOXEL_CELLS]>>>,
    /// Bricks written since the last [`take_dirty`](Self::take_dirty): the
    /// only way to write ([`set`](Self::set)) records the brick.
    dirty: FxHashSet<IVec3>,
}

/// Equal names and values (what was written when does not count).
impl PartialEq for VoxelChannels {
    fn eq(&self, other: &Self) -> bool {
        self.names == other.names && self.data == other.data
    }
}

impl VoxelChannels {
    /// The id of channel `name`, created empty if new.
    pub fn channel(&mut self, name: &str) -> VoxelChannelId {
        if let Some(i) = self.find(name) {
            return i;
        }
        self.names.push(name.to_string());
        self.data.push(FxHashMap::default());
        self.names.len() - 1
    }

    /// The id of `name`, if it exists.
    pub fn find(&self, name: &str) -> Option<VoxelChannelId> {
        self.names.iter().position(|n| n == name)
    }

    /// Every channel's name, by id.
    pub fn names(&self) -> &[String] {
        &self.names
    }

    /// Brick `b`'s values (None: all zero).
    pub fn get(&self, id: VoxelChannelId, b: IVec3) -> Option<&[f32; VOXEL_CELLS]> {
        self.data[id].get(&b).map(|d| &**d)
    }

    /// The value at voxel `p` (0 where its brick holds none).
    pub fn at(&self, id: VoxelChannelId, p: IVec3) -> f32 {
        let b = crate::world::brick_of(p);
        let l = p - b * crate::world::BRICK_EDGE;
        self.get(id, b)
            .map_or(0.0, |v| v[crate::world::voxel_index(l.x, l.y, l.z)])
    }

    /// Set brick `b`'s values; all zeros frees the array.
    pub fn set(&mut self, id: VoxelChannelId, b: IVec3, v: &[f32; VOXEL_CELLS]) {
        self.dirty.insert(b);
        if v.iter().all(|x| x.to_bits() == 0) {
            self.data[id].remove(&b);
        } else {
            self.data[id].insert(b, Box::new(*v));
        }
    }

    /// Every brick holding an array of any channel (unordered, possibly
    /// repeated).
    pub fn all_bricks(&self) -> impl Iterator<Item = IVec3> + '_ {
        self.data.iter().flat_map(|m| m.keys().copied())
    }

    /// The bricks written since the last call (see the `dirty` field).
    pub fn take_dirty(&mut self) -> FxHashSet<IVec3> {
        std::mem::take(&mut self.dirty)
    }

    /// The bricks holding an array of channel `id`, sorted.
    pub fn sorted_bricks(&self, id: VoxelChannelId) -> Vec<IVec3> {
        let mut k: Vec<IVec3> = self.data[id].keys().copied().collect();
        k.sort_by_key(|b| (b.z, b.y, b.x));
        k
    }

    /// Bricks holding an array of channel `id`.
    pub fn bricks(&self, id: VoxelChannelId) -> usize {
        self.data[id].len()
    }

    /// Sum of channel `id` over the world, in f64.
    pub fn total(&self, id: VoxelChannelId) -> f64 {
        let mut keys: Vec<&IVec3> = self.data[id].keys().collect();
        keys.sort_by_key(|k| (k.z, k.y, k.x));
        keys.iter()
            .map(|k| self.data[id][*k].iter().map(|&v| v as f64).sum::<f64>())
            .sum()
    }

    /// A hash of the channels' data, for determinism checks: channels in
    /// name order, bricks in coordinate order, and only channels that hold
    /// data. Ids are left out: they follow the order channels were
    /// registered in, which a hot reload that renames a channel changes
    /// and a restart does not repeat (regression: a world stopped after
    /// such a reload printed one hash at the stop and another when it
    /// resumed).
    pub fn hash(&self) -> u64 {
        let mut h = StateHasher::new(Mixing::Xxh3);
        let mut mix = |v: u64| h.word(v);
        let mut order: Vec<usize> = (0..self.names.len())
            .filter(|&i| !self.data[i].is_empty())
            .collect();
        order.sort_by(|&a, &b| self.names[a].cmp(&self.names[b]));
        for i in order {
            let (name, d) = (&self.names[i], &self.data[i]);
            mix(name.len() as u64);
            name.bytes().for_each(|b| mix(b as u64));
            let mut keys: Vec<&IVec3> = d.keys().collect();
            keys.sort_by_key(|k| (k.z, k.y, k.x));
            for k in keys {
                mix(((k.x as u32 as u64) << 32) | k.y as u32 as u64);
                mix(k.z as u32 as u64);
                for v in d[k].iter() {
                    mix(v.to_bits() as u64);
                }
            }
        }
        h.finish()
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// A voxel's value, on either side of brick edges and below zero.
    #[test]
    fn a_value_is_read_at_its_voxel() {
        let mut ch = VoxelChannels::default();
        let id = ch.channel("water");
        let mut v = [0.0; VOXEL_CELLS];
        v[crate::world::voxel_index(7, 0, 3)] = 2.5;
        ch.set(id, IVec3::new(-1, 2, 0), &v);
        assert_eq!(ch.at(id, IVec3::new(-1, 16, 3)), 2.5);
        assert_eq!(ch.at(id, IVec3::new(-2, 16, 3)), 0.0);
        assert_eq!(ch.at(id, IVec3::new(0, 16, 3)), 0.0);
    }

    /// Regression: the hash followed the order channels were registered
    /// in and counted channels without data; a reload that renamed a
    /// channel left the old name registered, so a world hashed one way at
    /// its stop and another when it resumed.
    #[test]
    fn the_hash_does_not_depend_on_the_order_channels_were_registered_in() {
        let b = IVec3::new(1, -2, 3);
        let (mut v1, mut v2) = ([0f32; VOXEL_CELLS], [0f32; VOXEL_CELLS]);
        v1[3] = 1.25;
        v2[500] = -2.0;
        let mut a = VoxelChannels::default();
        let (old, x, y) = (a.channel("old"), a.channel("x"), a.channel("y"));
        a.set(x, b, &v1);
        a.set(y, b, &v2);
        let mut c = VoxelChannels::default();
        let (y, x) = (c.channel("y"), c.channel("x"));
        c.set(y, b, &v2);
        c.set(x, b, &v1);
        assert_eq!(
            a.hash(),
            c.hash(),
            "an empty channel and the order do not count"
        );
        a.set(old, b, &v1);
        assert_ne!(a.hash(), c.hash(), "data in another channel counts");
        let mut d = VoxelChannels::default();
        let (x, y) = (d.channel("x"), d.channel("y"));
        d.set(x, b, &v2);
        d.set(y, b, &v1);
        assert_ne!(d.hash(), c.hash(), "which channel holds what counts");
    }
}
