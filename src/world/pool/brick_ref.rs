//! A read-only view of one brick in a [`BrickPool`]: its occupancy mask,
//! the material of a voxel (decoded from the brick's palette and packed
//! indices in the pool's arena), its LOD colour and coarser levels.

use super::{BrickPool, FLAG_MULTI, HEADER, to565};
use crate::world::brick::BRICK_VOXELS;
use crate::world::mip::BrickLod;

/// A read-only view of one brick in a pool.
#[derive(Clone, Copy, Debug)]
pub struct BrickRef<'p> {
    pub(super) pool: &'p BrickPool,
    pub(super) slot: usize,
}

/// The material of the `rank`-th solid voxel of a multi-material brick
/// whose arena block is `block`: its index in the block's packed indices,
/// then the block's palette.
#[inline]
fn palette_entry(block: &[u8], rank: u32) -> u8 {
    let (pal_len, width) = (block[0] as usize, block[1] as usize);
    let bit = rank as usize * width;
    let local = (block[HEADER + pal_len + bit / 8] >> (bit % 8)) & ((1u16 << width) - 1) as u8;
    block[HEADER + local as usize]
}

impl<'p> BrickRef<'p> {
    /// The 512-bit occupancy mask, word `z` holding the slice at depth `z`.
    #[inline(always)]
    pub fn mask(&self) -> &'p [u64; 8] {
        &self.pool.masks[self.slot]
    }

    /// Material of voxel `index` (see [`crate::world::voxel_index`]), 0 if empty.
    #[inline]
    pub fn material_index(&self, index: usize) -> u8 {
        let mask = self.mask();
        if (mask[index >> 6] >> (index & 63)) & 1 == 0 {
            return 0;
        }
        let m = self.pool.meta[self.slot];
        if m.flags & FLAG_MULTI == 0 {
            return m.data as u8;
        }
        let word = index >> 6;
        let mut rank = 0u32;
        for w in &mask[..word] {
            rank += w.count_ones();
        }
        rank += (mask[word] & ((1u64 << (index & 63)) - 1)).count_ones();
        palette_entry(&self.pool.arena.bytes[super::at(m.data)..], rank)
    }

    /// Call `f` with the material of each solid voxel of word `z` set in
    /// `bits` (a subset of the mask's word `z`), in ascending bit order:
    /// what [`material_index`](Self::material_index) gives for each, with
    /// the rank of the word's first voxel counted once instead of per voxel.
    pub fn for_each_material(&self, z: usize, bits: u64, mut f: impl FnMut(u8)) {
        let mask = self.mask();
        debug_assert_eq!(bits & !mask[z], 0, "bits outside the mask");
        let m = self.pool.meta[self.slot];
        if m.flags & FLAG_MULTI == 0 {
            for _ in 0..bits.count_ones() {
                f(m.data as u8);
            }
            return;
        }
        let base: u32 = mask[..z].iter().map(|w| w.count_ones()).sum();
        let block = &self.pool.arena.bytes[super::at(m.data)..];
        let mut rest = bits;
        while rest != 0 {
            let b = rest.trailing_zeros();
            rest &= rest - 1;
            f(palette_entry(
                block,
                base + (mask[z] & ((1u64 << b) - 1)).count_ones(),
            ));
        }
    }

    /// Whether any of the brick's materials is one `wanted` marks, read
    /// from its local palette (no voxel is decoded).
    pub fn holds_any(&self, wanted: &[bool; 256]) -> bool {
        let m = self.pool.meta[self.slot];
        if m.flags & FLAG_MULTI == 0 {
            return wanted[m.data as u8 as usize];
        }
        let block = &self.pool.arena.bytes[super::at(m.data)..];
        block[HEADER..HEADER + block[0] as usize]
            .iter()
            .any(|&id| wanted[id as usize])
    }

    /// The LOD colour (RGB565) the brick would have if it were encoded
    /// afresh with `palette`: its solid voxels' mean colour, as
    /// [`Brick`](crate::world::Brick)'s encoding computes it.
    pub fn lod565_with(&self, palette: &crate::world::Palette) -> u16 {
        let mask = self.mask();
        let (mut sum, mut solid) = ([0u64; 3], 0u64);
        for (z, &word) in mask.iter().enumerate() {
            self.for_each_material(z, word, |m| {
                let c = palette.rgb(m);
                for k in 0..3 {
                    sum[k] += c[k] as u64;
                }
                solid += 1;
            });
        }
        to565(sum.map(|c| c.checked_div(solid).unwrap_or(0) as u8))
    }

    /// Material at brick-local `(x, y, z)`, 0 if empty.
    pub fn material(&self, x: i32, y: i32, z: i32) -> u8 {
        self.material_index(crate::world::voxel_index(x, y, z))
    }

    /// Expand into a dense material array.
    pub fn to_dense(&self, out: &mut [u8; BRICK_VOXELS]) {
        out.fill(0);
        let m = self.pool.meta[self.slot];
        let multi = m.flags & FLAG_MULTI != 0;
        let block = if multi {
            &self.pool.arena.bytes[super::at(m.data)..]
        } else {
            &[][..]
        };
        let (pal_len, bits) = if multi {
            (block[0] as usize, block[1] as usize)
        } else {
            (0, 0)
        };
        let mut rank = 0usize;
        for (w, &word) in self.mask().iter().enumerate() {
            let mut bitset = word;
            while bitset != 0 {
                let b = bitset.trailing_zeros() as usize;
                bitset &= bitset - 1;
                out[(w << 6) | b] = if multi {
                    let bit = rank * bits;
                    let local = (block[HEADER + pal_len + bit / 8] >> (bit % 8))
                        & ((1u16 << bits) - 1) as u8;
                    block[HEADER + local as usize]
                } else {
                    m.data as u8
                };
                rank += 1;
            }
        }
    }

    /// Number of solid voxels.
    pub fn solid_voxels(&self) -> u32 {
        self.mask().iter().map(|w| w.count_ones()).sum()
    }

    /// Average colour of the solid voxels (stored as RGB565).
    pub fn lod_rgb(&self) -> [u8; 3] {
        from565(self.pool.meta[self.slot].lod565)
    }

    /// Materials of the brick's coarser levels (see [`crate::world::mip`]).
    #[inline(always)]
    pub fn lod(&self) -> BrickLod {
        self.pool.meta[self.slot].lod
    }
}

fn from565(v: u16) -> [u8; 3] {
    let r = ((v >> 11) & 31) as u8;
    let g = ((v >> 5) & 63) as u8;
    let b = (v & 31) as u8;
    [
        (r << 3) | (r >> 2),
        (g << 2) | (g >> 4),
        (b << 3) | (b >> 2),
    ]
}
