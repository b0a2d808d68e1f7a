//! The window's cache of columns that left it: each column's bricks packed
//! into one LZ4-compressed allocation of exactly its size (van Wingerden
//! §3.2.3 keeps its chunk cache the same way), so the cache's byte count
//! is the memory it really holds.

use glam::{IVec2, IVec3};

use super::Bricks;
use crate::scene::CHUNK_BRICKS;
use crate::world::BrickContent;

pub(super) struct Cached {
    /// [`pack`]ed bricks, in one allocation of exactly their size.
    pub(super) packed: Box<[u8]>,
    pub(super) used: u64,
}

impl Cached {
    pub(super) fn bytes(&self) -> u64 {
        // The allocation plus the map entry.
        self.packed.len() as u64 + 64
    }
}

/// Buffers [`pack`] reuses: packing allocates only its exact-size result
/// (no over-sized compression buffer shrunk in place, which would leave
/// the heap fragmented by every cached column).
#[derive(Default)]
pub(super) struct PackScratch {
    raw: Vec<u8>,
    out: Vec<u8>,
}

/// A column's bricks as LZ4-compressed bytes: per brick its column-local
/// position (`u8` x, `u16` y, `u8` z) and `u8` tag, then the uniform
/// material or the 512 dense materials of a mixed brick.
pub(super) fn pack(col: IVec2, bricks: &Bricks, scratch: &mut PackScratch) -> Box<[u8]> {
    let raw = &mut scratch.raw;
    raw.clear();
    let mut dense = [0u8; crate::world::BRICK_VOXELS];
    let base = col * CHUNK_BRICKS;
    for (b, c) in bricks {
        raw.push((b.x - base.x) as u8);
        raw.extend_from_slice(&(b.y as u16).to_le_bytes());
        raw.push((b.z - base.y) as u8);
        match c {
            BrickContent::Empty => raw.push(0),
            BrickContent::Uniform(m) => raw.extend_from_slice(&[1, *m]),
            BrickContent::Mixed(_) => {
                raw.push(2);
                c.to_dense(&mut dense);
                raw.extend_from_slice(&dense);
            }
        }
    }
    let out = &mut scratch.out;
    out.resize(4 + lz4_flex::block::get_maximum_output_size(raw.len()), 0);
    out[..4].copy_from_slice(&(raw.len() as u32).to_le_bytes());
    // The buffer holds the largest output, so this cannot fail; if it did,
    // the column would fail to unpack and be generated again.
    let n = lz4_flex::block::compress_into(raw, &mut out[4..]).unwrap_or(0);
    out[..4 + n].into()
}

/// The bricks [`pack`] packed (None if the bytes are not a packed column).
pub(super) fn unpack(col: IVec2, packed: &[u8], palette: &crate::world::Palette) -> Option<Bricks> {
    let raw = lz4_flex::decompress_size_prepended(packed).ok()?;
    let base = col * CHUNK_BRICKS;
    let mut out = Vec::new();
    let mut i = 0;
    let mut dense = [0u8; crate::world::BRICK_VOXELS];
    while i < raw.len() {
        let h = raw.get(i..i + 5)?;
        let b = IVec3::new(
            base.x + h[0] as i32,
            u16::from_le_bytes([h[1], h[2]]) as i32,
            base.y + h[3] as i32,
        );
        i += 5;
        let content = match h[4] {
            0 => BrickContent::Empty,
            1 => {
                i += 1;
                BrickContent::Uniform(*raw.get(i - 1)?)
            }
            2 => {
                let n = crate::world::BRICK_VOXELS;
                dense.copy_from_slice(raw.get(i..i + n)?);
                i += n;
                BrickContent::from_dense(&dense, palette)
            }
            _ => return None,
        };
        out.push((b, content));
    }
    Some(out)
}
