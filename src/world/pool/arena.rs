//! The material arena of a [`BrickPool`](super::BrickPool): the blocks
//! that hold a many-material brick's palette and packed indices,
//! allocated in 16-byte size classes with a free list per class, and
//! compacted when holes outweigh what is live.
//!
//! A block is `[palette_len, bits, size_class, palette…, packed indices…]`.
//! Freed blocks are reused only by blocks of their own class, so a pool
//! whose bricks change size (a simulation adding a material to a brick,
//! a GPU mirror cycling through the bricks of new views) leaves holes the
//! other classes cannot use. [`MaterialArena::compact`] moves every live
//! block to the front, in slot order, and drops the holes; its callers
//! decide when ([`MaterialArena::fragmented`]) because every block's
//! offset changes.

/// Bytes per size class step: class `k` holds blocks of `16·(k+1)` bytes.
const CLASS: usize = 16;

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
    /// Length of the block at `off` (its size class's).
    pub(super) fn block_len(&self, off: u32) -> usize {
        (self.bytes[off as usize + 2] as usize + 1) * CLASS
    }

    /// A block of at least `len` bytes, its third byte set to its size
    /// class; returns its offset.
    pub(super) fn alloc(&mut self, len: usize) -> u32 {
        let class = len.div_ceil(CLASS) - 1;
        if self.free.len() <= class {
            self.free.resize(class + 1, Vec::new());
        }
        let off = match self.free[class].pop() {
            Some(off) => {
                self.holes -= (class + 1) * CLASS;
                off
            }
            None => {
                let off = self.bytes.len();
                self.bytes.resize(off + (class + 1) * CLASS, 0);
                u32::try_from(off).expect("material arena exceeds 4 GiB")
            }
        };
        self.bytes[off as usize + 2] = class as u8;
        off
    }

    /// Return the block at `off` to its class's free list.
    pub(super) fn free(&mut self, off: u32) {
        let class = self.bytes[off as usize + 2] as usize;
        self.free[class].push(off);
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
            sum += offs.iter().filter(|&&o| o as usize + len <= limit).count() * len;
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
    /// offset, each exactly once, and each is rewritten to the new one.
    pub(super) fn compact<'a>(&mut self, live: impl Iterator<Item = &'a mut u32>) {
        let mut bytes = Vec::with_capacity(self.bytes.len() - self.holes);
        for off in live {
            let len = self.block_len(*off);
            let new = bytes.len();
            bytes.extend_from_slice(&self.bytes[*off as usize..*off as usize + len]);
            *off = u32::try_from(new).expect("compaction never grows the arena");
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
