//! The material arena of a [`BrickPool`](super::BrickPool): the blocks
//! that hold a many-material brick's palette and packed indices,
//! allocated in 16-byte size classes with a free list per class, and
//! compacted when holes outweigh what is live.
//!
//! A block is `[palette_len, bits, size_class, palette…, packed indices…]`,
//! and starts on a 16-byte boundary: it is addressed by its offset in
//! 16-byte units ([`at`]), so a `u32` reaches 64 GiB of blocks (as bytes
//! it reached 4 GiB, which a voxel script filling a 4096² world with many
//! materials passed, and the engine panicked: growth probe).
//! Freed blocks are reused only by blocks of their own class, so a pool
//! whose bricks change size (a simulation adding a material to a brick,
//! a GPU mirror cycling through the bricks of new views) leaves holes the
//! other classes cannot use. [`MaterialArena::compact`] moves every live
//! block to the front, in slot order, and drops the holes; its callers
//! decide when ([`MaterialArena::fragmented`]) because every block's
//! offset changes.

/// Bytes per size class step: class `k` holds blocks of `16·(k+1)` bytes.
const CLASS: usize = 16;

/// Most bytes the arena may hold: 2³² blocks' starts of 16 bytes.
pub const ARENA_LIMIT: u64 = (u32::MAX as u64 + 1) * CLASS as u64;

/// Byte offset of the block at `unit` (its offset in 16-byte units).
#[inline]
pub(super) fn at(unit: u32) -> usize {
    unit as usize * CLASS
}

/// Holes below this many bytes are never worth a compaction.
const MIN_HOLES: usize = 64 << 10;

/// Size-classed blocks of bytes with free lists and compaction.
#[derive(Clone, Debug, Default)]
pub(super) struct MaterialArena {
    /// The blocks, holes included (what a tracer reads and a GPU holds).
    pub(super) bytes: Vec<u8>,
    /// Free block offsets per size class.
    free: Vec<Vec<u32>>,
    /// Bytes in freed blocks.
    holes: usize,
}

impl MaterialArena {
    /// Length of the block at `unit` (its size class's).
    pub(super) fn block_len(&self, unit: u32) -> usize {
        (self.bytes[at(unit) + 2] as usize + 1) * CLASS
    }

    /// A block of at least `len` bytes, its third byte set to its size
    /// class; returns its offset in 16-byte units. Past [`ARENA_LIMIT`] it
    /// panics: the simulations that grow the world check their edits
    /// against it first (`crate::sim::voxels`).
    pub(super) fn alloc(&mut self, len: usize) -> u32 {
        let class = len.div_ceil(CLASS) - 1;
        if self.free.len() <= class {
            self.free.resize(class + 1, Vec::new());
        }
        let unit = match self.free[class].pop() {
            Some(unit) => {
                self.holes -= (class + 1) * CLASS;
                unit
            }
            None => {
                let off = self.bytes.len();
                let unit = u32::try_from(off / CLASS).expect("material arena exceeds 64 GiB");
                self.bytes.resize(off + (class + 1) * CLASS, 0);
                unit
            }
        };
        self.bytes[at(unit) + 2] = class as u8;
        unit
    }

    /// Return the block at `unit` to its class's free list.
    pub(super) fn free(&mut self, unit: u32) {
        let class = self.bytes[at(unit) + 2] as usize;
        self.free[class].push(unit);
        self.holes += (class + 1) * CLASS;
    }

    /// Bytes in freed blocks, waiting for a block of their class.
    pub(super) fn holes(&self) -> usize {
        self.holes
    }

    /// Bytes in freed blocks that end at or below `limit` (a copy of the
    /// arena that holds only its first `limit` bytes sees only these).
    pub(super) fn holes_below(&self, limit: usize) -> usize {
        let mut sum = 0;
        for (class, offs) in self.free.iter().enumerate() {
            let len = (class + 1) * CLASS;
            sum += offs.iter().filter(|&&u| at(u) + len <= limit).count() * len;
        }
        sum
    }

    /// Whether holes are over half the arena (and at least 64 KiB): the
    /// point where [`compact`](Self::compact) at least halves it. Checked
    /// after each free, compaction costs amortised O(1) a freed byte.
    pub(super) fn fragmented(&self) -> bool {
        self.holes >= MIN_HOLES && self.holes * 2 > self.bytes.len()
    }

    /// Move every live block to the front, in the order given, and drop
    /// the holes: `live` yields a mutable reference to each live block's
    /// offset (in units), each exactly once, and each is rewritten to the
    /// new one.
    pub(super) fn compact<'a>(&mut self, live: impl Iterator<Item = &'a mut u32>) {
        let mut bytes = Vec::with_capacity(self.bytes.len() - self.holes);
        for unit in live {
            let len = self.block_len(*unit);
            let new = bytes.len() / CLASS;
            bytes.extend_from_slice(&self.bytes[at(*unit)..at(*unit) + len]);
            *unit = u32::try_from(new).expect("compaction never grows the arena");
        }
        debug_assert_eq!(bytes.len(), self.bytes.len() - self.holes);
        self.bytes = bytes;
        // Every class a live block has stays indexable for its `free`.
        self.free = vec![Vec::new(); self.free.len()];
        self.holes = 0;
    }

    /// Bytes of free-list bookkeeping.
    pub(super) fn index_bytes(&self) -> usize {
        self.free.iter().map(|v| v.len() * 4).sum()
    }
}
