//! The brick pool: compact storage for mixed bricks, addressed by small
//! `Copy` ids with generation counters so that a stale id can never read a
//! reused slot.
//!
//! **Layout** (structure of arrays, what tracers read):
//! - `masks`: one 64-byte occupancy mask per slot;
//! - `meta`: 20 bytes per slot — a `u32` that is either the single material
//!   of a one-material brick or an offset into the material arena, the LOD
//!   colour as RGB565, flags, and the materials of the brick's coarser
//!   levels ([`BrickLod`]: 8 octants and the whole brick);
//! - `arena`: for multi-material bricks, `[palette_len, bits, size_class,
//!   palette…, packed indices…]`, allocated in 16-byte size classes with a free list per
//!   class (the thesis' colour allocator, simplified), so edits reuse holes,
//!   and compacted when holes pass half of it (`arena.rs`).
//!
//! A one-material brick therefore costs 84 bytes in total. Generations and
//! the free slot list are editing bookkeeping, reported by
//! [`BrickPool::index_bytes`], not by [`BrickPool::bytes`]. Reading one
//! brick (its mask and materials) is [`BrickRef`], in `brick_ref.rs`.

mod arena;
mod brick_ref;

pub use arena::ARENA_LIMIT;
use arena::{MaterialArena, at};
pub use brick_ref::BrickRef;

use super::brick::Brick;
use super::mip::BrickLod;

/// Words of metadata per slot in [`BrickPool::raw`].
pub const GPU_META_WORDS: usize = 4;

fn gpu_meta(m: &Meta) -> [u32; GPU_META_WORDS] {
    let o = m.lod.octants;
    // A multi-material brick's block as a byte offset: what the shader
    // reads. An arena past 4 GiB is past every GPU's buffer limit, which
    // the uploads check first.
    let data = if m.flags & FLAG_MULTI != 0 {
        u32::try_from(at(m.data)).unwrap_or(u32::MAX)
    } else {
        m.data
    };
    [
        data,
        m.flags as u32 | (m.lod.whole as u32) << 8,
        u32::from_le_bytes([o[0], o[1], o[2], o[3]]),
        u32::from_le_bytes([o[4], o[5], o[6], o[7]]),
    ]
}

/// Handle to a brick in a [`BrickPool`]. Stale handles are detected.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Hash)]
pub struct BrickId {
    index: u32,
    generation: u32,
}

impl BrickId {
    /// Slot index (what the brick grid stores).
    pub fn index(self) -> u32 {
        self.index
    }
}

const FLAG_LIVE: u16 = 1;
const FLAG_MULTI: u16 = 2;
/// Arena block header: palette length, bits per index, size class.
const HEADER: usize = 3;

#[derive(Clone, Copy, Debug, Default)]
struct Meta {
    /// Single material, or for multi-material bricks the arena offset of
    /// the block in 16-byte units (`arena::at`).
    data: u32,
    lod565: u16,
    flags: u16,
    /// Materials of the coarser levels.
    lod: BrickLod,
}

fn to565(c: [u8; 3]) -> u16 {
    ((c[0] as u16 >> 3) << 11) | ((c[1] as u16 >> 2) << 5) | (c[2] as u16 >> 3)
}

/// Slots of bricks with a free list; freed slots and arena blocks are reused.
#[derive(Clone, Debug, Default)]
pub struct BrickPool {
    masks: Vec<[u64; 8]>,
    meta: Vec<Meta>,
    generations: Vec<u32>,
    free: Vec<u32>,
    arena: MaterialArena,
    live: usize,
}

impl BrickPool {
    fn free_arena(&mut self, m: Meta) {
        if m.flags & FLAG_MULTI != 0 {
            self.arena.free(m.data);
        }
    }

    /// Bytes of the material arena in freed blocks that only a block of
    /// the same size class can reuse.
    pub fn arena_holes(&self) -> usize {
        self.arena.holes()
    }

    /// Of [`arena_holes`](Self::arena_holes), the bytes in blocks that end
    /// at or below `limit`: what compaction frees in a copy of the arena
    /// that holds only its first `limit` bytes (a GPU's).
    pub fn arena_holes_below(&self, limit: usize) -> usize {
        self.arena.holes_below(limit)
    }

    /// Whether the arena's holes are over half of it (and at least
    /// 64 KiB), the point where [`compact_arena`](Self::compact_arena)
    /// pays.
    pub fn arena_fragmented(&self) -> bool {
        self.arena.fragmented()
    }

    /// Move every many-material brick's block to the front of the arena,
    /// in slot order, and drop the holes. Slots, ids and every brick's
    /// contents stay as they were; only arena offsets change, so a copy of
    /// the arena (a GPU's) must be uploaded whole afterwards.
    pub fn compact_arena(&mut self) {
        let live = self
            .meta
            .iter_mut()
            .filter(|m| m.flags & FLAG_LIVE != 0 && m.flags & FLAG_MULTI != 0)
            .map(|m| &mut m.data);
        self.arena.compact(live);
    }

    fn encode(&mut self, brick: &Brick) -> Meta {
        let lod565 = to565(brick.lod_rgb());
        let palette = brick.local_palette();
        if palette.len() <= 1 {
            return Meta {
                data: palette.first().copied().unwrap_or(0) as u32,
                lod565,
                flags: FLAG_LIVE,
                lod: brick.lod(),
            };
        }
        let bits = brick.bits();
        let solid = brick.solid_voxels() as usize;
        let index_bytes = (solid * bits as usize).div_ceil(8);
        let len = HEADER + palette.len() + index_bytes;
        let unit = self.arena.alloc(len);
        let block = &mut self.arena.bytes[at(unit)..at(unit) + len];
        block[0] = palette.len() as u8;
        block[1] = bits;
        block[HEADER..HEADER + palette.len()].copy_from_slice(palette);
        let idx = &mut block[HEADER + palette.len()..];
        for (i, b) in idx.iter_mut().enumerate() {
            *b = (brick.index_words()[i / 8] >> ((i % 8) * 8)) as u8;
        }
        Meta {
            data: unit,
            lod565,
            flags: FLAG_LIVE | FLAG_MULTI,
            lod: brick.lod(),
        }
    }

    /// Store a brick, returning its id.
    pub fn insert(&mut self, brick: Brick) -> BrickId {
        self.live += 1;
        let meta = self.encode(&brick);
        if let Some(index) = self.free.pop() {
            let i = index as usize;
            self.generations[i] = self.generations[i].wrapping_add(1);
            self.masks[i] = *brick.mask();
            self.meta[i] = meta;
            BrickId {
                index,
                generation: self.generations[i],
            }
        } else {
            let index = u32::try_from(self.masks.len()).expect("brick pool exceeds 2^32 slots");
            assert!(index < (1 << 31), "brick pool exceeds 2^31 slots");
            self.masks.push(*brick.mask());
            self.meta.push(meta);
            self.generations.push(0);
            BrickId {
                index,
                generation: 0,
            }
        }
    }

    fn valid(&self, id: BrickId) -> bool {
        self.generations.get(id.index as usize) == Some(&id.generation)
            && self.meta[id.index as usize].flags & FLAG_LIVE != 0
    }

    /// The brick behind `id`, or `None` if the id is stale.
    pub fn get(&self, id: BrickId) -> Option<BrickRef<'_>> {
        self.valid(id).then_some(BrickRef {
            pool: self,
            slot: id.index as usize,
        })
    }

    /// Give brick `id` the LOD colour `lod565` (see
    /// [`BrickRef::lod565_with`]); false for a stale id.
    pub fn set_lod565(&mut self, id: BrickId, lod565: u16) -> bool {
        if !self.valid(id) {
            return false;
        }
        self.meta[id.index as usize].lod565 = lod565;
        true
    }

    /// Replace the brick behind `id` in place. Returns false for a stale id.
    pub fn replace(&mut self, id: BrickId, brick: Brick) -> bool {
        if !self.valid(id) {
            return false;
        }
        let i = id.index as usize;
        let old = self.meta[i];
        self.free_arena(old);
        self.meta[i] = self.encode(&brick);
        self.masks[i] = *brick.mask();
        true
    }

    /// Free the slot behind `id`. Returns false if the id is stale.
    pub fn remove(&mut self, id: BrickId) -> bool {
        if !self.valid(id) {
            return false;
        }
        let i = id.index as usize;
        self.free_arena(self.meta[i]);
        self.meta[i] = Meta::default();
        self.masks[i] = [0; 8];
        self.live -= 1;
        self.generations[i] = self.generations[i].wrapping_add(1);
        self.free.push(id.index);
        true
    }

    /// Brick in slot `index` without a generation check: for tracers that
    /// hold slot indices in a grid kept in sync with the store.
    #[inline(always)]
    pub fn slot(&self, index: u32) -> Option<BrickRef<'_>> {
        let i = index as usize;
        (i < self.meta.len() && self.meta[i].flags & FLAG_LIVE != 0).then_some(BrickRef {
            pool: self,
            slot: i,
        })
    }

    /// Raw arrays for uploading to a GPU: masks (one per slot), metadata as
    /// [`GPU_META_WORDS`] words per slot — data, flags with the brick's
    /// material in bits 8..16, and the eight octant materials — and the
    /// material arena.
    pub fn raw(&self) -> (&[[u64; 8]], Vec<[u32; GPU_META_WORDS]>, &[u8]) {
        let meta = self.meta.iter().map(gpu_meta).collect();
        (&self.masks, meta, &self.arena.bytes)
    }

    /// One slot's part of [`raw`](Self::raw): its mask, its metadata
    /// words and its material block (empty for a one-material brick), for
    /// uploading a single brick without converting every slot's metadata
    /// (regression: the GPU's streaming path did that for every brick it
    /// uploaded, about 1 MiB made and dropped per brick with a full pool).
    /// `None` for a slot past the pool's end.
    pub fn raw_slot(&self, index: u32) -> Option<(&[u64; 8], [u32; GPU_META_WORDS], &[u8])> {
        let i = index as usize;
        let m = self.meta.get(i)?;
        let block = self
            .arena_block(index)
            .map_or(&[][..], |(off, len)| &self.arena.bytes[off..off + len]);
        Some((&self.masks[i], gpu_meta(m), block))
    }

    /// Byte range `(offset, len)` of slot `index`'s material block in the
    /// arena, `None` for a one-material brick (or a free slot).
    pub fn arena_block(&self, index: u32) -> Option<(usize, usize)> {
        let m = self.meta.get(index as usize)?;
        if m.flags & FLAG_LIVE == 0 || m.flags & FLAG_MULTI == 0 {
            return None;
        }
        Some((at(m.data), self.arena.block_len(m.data)))
    }

    /// Slot capacity in use (live and free slots).
    pub fn slots(&self) -> usize {
        self.masks.len()
    }

    /// Number of live bricks.
    pub fn len(&self) -> usize {
        self.live
    }

    /// Whether no brick is live.
    pub fn is_empty(&self) -> bool {
        self.live == 0
    }

    /// Bytes a tracer reads: masks, metadata and the material arena
    /// (free holes included).
    pub fn bytes(&self) -> usize {
        self.masks.len() * 64
            + self.meta.len() * std::mem::size_of::<Meta>()
            + self.arena.bytes.len()
    }

    /// Bytes the material arena holds (free holes included), against
    /// [`ARENA_LIMIT`].
    pub fn arena_len(&self) -> usize {
        self.arena.bytes.len()
    }

    /// Bytes that storing `bricks` more bricks with `blocks` more bytes of
    /// material blocks may allocate beyond those bytes: each of the pool's
    /// arrays doubles when full, and while it moves the old one is still
    /// held, so crossing a capacity asks for the new one whole (growth
    /// probe: a step of a few MB aborted the engine asking for 1.2 GB of
    /// arena). Counts every brick as a new slot: an upper bound.
    pub fn growth_reserve(&self, bricks: usize, blocks: usize) -> u64 {
        fn regrown<T>(v: &Vec<T>, more: usize) -> u64 {
            let need = v.len() + more;
            if need <= v.capacity() {
                return 0;
            }
            (need.max(v.capacity() * 2) * std::mem::size_of::<T>()) as u64
        }
        regrown(&self.masks, bricks)
            + regrown(&self.meta, bricks)
            + regrown(&self.generations, bricks)
            + regrown(&self.arena.bytes, blocks)
    }

    /// Bytes of editing bookkeeping: generations and free lists.
    pub fn index_bytes(&self) -> usize {
        self.generations.len() * 4 + self.free.len() * 4 + self.arena.index_bytes()
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    use crate::world::{BrickContent, Palette};

    fn brick_from(f: impl Fn(usize) -> u8) -> Brick {
        let d: [u8; 512] = std::array::from_fn(f);
        match BrickContent::from_dense(&d, &Palette::grey_ramp()) {
            BrickContent::Mixed(b) => b,
            _ => unreachable!(),
        }
    }

    /// Blocks are addressed in 16-byte units: a `u32` reaches 64 GiB, past
    /// the 4 GiB at which byte offsets panicked (growth probe).
    #[test]
    fn arena_offsets_in_units_reach_64_gib() {
        assert_eq!(ARENA_LIMIT, 64 << 30);
        assert_eq!(at(u32::MAX), (64usize << 30) - 16);
        assert_eq!(at(1 << 28), 4usize << 30, "past 4 GiB");
    }

    /// Regression (growth probe): the guard of a voxel step counts an
    /// array's move to a larger capacity, not only the bytes added.
    #[test]
    fn the_growth_reserve_counts_an_array_moving_to_a_larger_capacity() {
        let mut pool = BrickPool::default();
        pool.insert(brick_from(|i| (i % 3) as u8));
        let cap = pool.arena.bytes.capacity();
        let len = pool.arena.bytes.len();
        assert_eq!(pool.growth_reserve(0, cap - len), 0, "fits: nothing moves");
        let moved = pool.growth_reserve(0, cap - len + 1);
        assert!(moved >= (2 * cap) as u64, "{moved} for a capacity of {cap}");
        assert!(pool.growth_reserve(1 << 20, 0) >= ((1 << 20) * 64) as u64);
    }

    /// Bricks of one to 200 materials.
    const PATTERNS: [fn(usize) -> u8; 4] = [
        |i| (i % 3 != 0) as u8 * 7,
        |i| if i % 5 == 0 { 0 } else { 1 + (i % 2) as u8 },
        |i| if i % 7 == 0 { 0 } else { 1 + (i % 13) as u8 },
        |i| if i % 2 == 0 { 0 } else { 1 + (i % 200) as u8 },
    ];

    /// Each slot's `raw_slot` is its part of `raw`: mask, metadata and
    /// material block, for one- and many-material bricks and free slots.
    #[test]
    fn raw_slot_is_the_slots_part_of_raw() {
        let mut pool = BrickPool::default();
        let ids: Vec<BrickId> = (0..12)
            .map(|k| pool.insert(brick_from(PATTERNS[k % PATTERNS.len()])))
            .collect();
        pool.remove(ids[5]);
        let (masks, meta, arena) = pool.raw();
        for i in 0..meta.len() as u32 {
            let (mask, words, block) = pool.raw_slot(i).unwrap();
            assert_eq!(mask, &masks[i as usize]);
            assert_eq!(words, meta[i as usize]);
            let want = pool
                .arena_block(i)
                .map_or(&[][..], |(o, l)| &arena[o..o + l]);
            assert_eq!(block, want);
        }
        assert!(
            pool.arena_block(ids[2].index()).is_some(),
            "a block is checked"
        );
        assert!(pool.raw_slot(meta.len() as u32).is_none());
    }

    #[test]
    fn stale_ids_are_rejected_after_slot_reuse() {
        let mut pool = BrickPool::default();
        let a = pool.insert(brick_from(|i| (i == 3) as u8));
        assert!(pool.remove(a));
        let b = pool.insert(brick_from(|i| 2 * (i == 3) as u8));
        assert_eq!(a.index(), b.index(), "slot is reused");
        assert!(
            pool.get(a).is_none(),
            "stale id must not read the new brick"
        );
        assert_eq!(pool.get(b).unwrap().material_index(3), 2);
        assert!(!pool.remove(a));
        assert_eq!(pool.len(), 1);
    }

    #[test]
    fn pooled_bricks_read_back_exactly_and_arena_blocks_are_reused() {
        let mut pool = BrickPool::default();
        let patterns = PATTERNS;
        let mut ids = Vec::new();
        for p in patterns {
            let b = brick_from(p);
            let id = pool.insert(b.clone());
            let r = pool.get(id).unwrap();
            let mut dense = [0u8; 512];
            r.to_dense(&mut dense);
            for i in 0..512 {
                assert_eq!(dense[i], p(i));
                assert_eq!(r.material_index(i), p(i));
            }
            ids.push(id);
        }
        let arena = pool.arena.bytes.len();
        for id in &ids {
            assert!(pool.replace(*id, brick_from(patterns[3])));
        }
        assert!(
            pool.arena.bytes.len() <= arena + 3 * 544,
            "replacing reuses freed blocks"
        );
        let before = pool.arena.bytes.len();
        let id = pool.insert(brick_from(patterns[2]));
        let block = pool.arena.bytes.len() - before;
        assert!(pool.remove(id));
        for _ in 0..10 {
            let id = pool.insert(brick_from(patterns[2]));
            assert!(pool.remove(id));
        }
        assert_eq!(
            pool.arena.bytes.len(),
            before + block,
            "one block, then reused"
        );
    }

    /// `for_each_material` gives what `material_index` gives for every
    /// subset of every word, in bit order, for one- to 200-material bricks.
    #[test]
    fn materials_of_a_word_are_those_of_its_voxels() {
        let mut pool = BrickPool::default();
        for p in PATTERNS {
            let id = pool.insert(brick_from(p));
            let b = pool.get(id).unwrap();
            for z in 0..8 {
                for keep in [u64::MAX, 0xF0F0_F0F0_0F0F_0F0F, 1 << 63, 0] {
                    let bits = b.mask()[z] & keep;
                    let mut got = Vec::new();
                    b.for_each_material(z, bits, |m| got.push(m));
                    let want: Vec<u8> = (0..64)
                        .filter(|k| bits >> k & 1 != 0)
                        .map(|k| b.material_index(z * 64 + k))
                        .collect();
                    assert_eq!(got, want, "word {z}, bits {bits:#x}");
                }
            }
        }
    }

    /// Compaction after random churn of bricks of every size keeps every
    /// live brick's voxels and every id, and leaves no hole: the arena is
    /// exactly the live blocks. Fragmentation is what triggers it.
    #[test]
    fn compaction_keeps_every_brick_and_drops_every_hole() {
        let mut pool = BrickPool::default();
        let mut live: Vec<(BrickId, usize)> = Vec::new();
        let mut seed = 0x9E37_79B9_7F4A_7C15u64;
        let mut next = move || {
            seed ^= seed << 13;
            seed ^= seed >> 7;
            seed ^= seed << 17;
            seed
        };
        let mut was_fragmented = false;
        for _ in 0..4000 {
            let r = next();
            let p = (r >> 8) as usize % PATTERNS.len();
            match r % 4 {
                0 | 1 => live.push((pool.insert(brick_from(PATTERNS[p])), p)),
                2 if !live.is_empty() => {
                    let k = (r >> 16) as usize % live.len();
                    assert!(pool.replace(live[k].0, brick_from(PATTERNS[p])));
                    live[k].1 = p;
                }
                _ if !live.is_empty() => {
                    let k = (r >> 16) as usize % live.len();
                    assert!(pool.remove(live.swap_remove(k).0));
                }
                _ => {}
            }
            was_fragmented |= pool.arena_fragmented();
        }
        // Keep only the one-material and smallest bricks: most bytes are holes.
        live.retain(|&(id, p)| p < 2 || !pool.remove(id));
        assert!(was_fragmented || pool.arena_fragmented(), "churn fragments");
        assert!(
            pool.arena_fragmented(),
            "{} of {}",
            pool.arena_holes(),
            pool.arena.bytes.len()
        );
        pool.compact_arena();
        assert_eq!(pool.arena_holes(), 0);
        let blocks: usize = (0..pool.slots() as u32)
            .filter_map(|i| pool.arena_block(i).map(|(_, l)| l))
            .sum();
        assert_eq!(
            pool.arena.bytes.len(),
            blocks,
            "the arena is its live blocks"
        );
        for &(id, p) in &live {
            let mut dense = [0u8; 512];
            pool.get(id).expect("ids survive").to_dense(&mut dense);
            assert!((0..512).all(|i| dense[i] == PATTERNS[p](i)), "pattern {p}");
        }
        // And the compacted arena is still an arena: the surviving blocks
        // free into their classes (regression: the free lists were
        // dropped, and freeing a surviving block indexed past them), and
        // churn goes on.
        for &(id, _) in &live {
            assert!(pool.remove(id));
        }
        let id = pool.insert(brick_from(PATTERNS[3]));
        assert!(pool.replace(id, brick_from(PATTERNS[2])));
        assert!(pool.remove(id));
        assert!(pool.is_empty());
    }

    #[test]
    fn one_material_bricks_cost_84_bytes() {
        let mut pool = BrickPool::default();
        pool.insert(brick_from(|i| (i % 2) as u8 * 9));
        assert_eq!(
            pool.bytes(),
            84,
            "64 mask + 20 meta (8 of them level-of-detail materials)"
        );
        assert_eq!(
            pool.get(BrickId {
                index: 0,
                generation: 0
            })
            .unwrap()
            .lod_rgb(),
            [8, 8, 8]
        );
    }
}
