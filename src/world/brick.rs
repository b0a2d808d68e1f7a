//! One 8³ brick: a 512-bit occupancy mask plus palette-compressed materials.
//!
//! Voxel `(x, y, z)` inside a brick (each 0..8) has linear index
//! `x + 8·y + 64·z`, so mask word `z` is the 8×8 slice at that depth and bit
//! `x + 8·y` inside it is the voxel.
//!
//! **Materials.** A material is a `u8` index into the world [`Palette`]; 0 means
//! empty and is never stored. Only solid voxels carry a material, and they are
//! stored in *rank order* (the n-th set bit of the mask owns the n-th entry).
//! Each brick keeps a small local palette of the distinct materials it uses and
//! packs one local index per solid voxel with 0, 1, 2, 4 or 8 bits. A brick of
//! a single material stores no per-voxel data at all. This is lossless (unlike
//! the thesis' DXT1 colours) and usually smaller: a half-full surface brick
//! with four materials costs 64 B of mask plus 64 B of indices.
//!
//! [`Brick`] is the exchange form that scene builders and edits produce; the
//! [`super::BrickPool`] stores the same encoding compactly (masks, 8-byte
//! metadata and a shared material arena) and hands out [`super::BrickRef`]s.

use super::mip::BrickLod;
use super::palette::Palette;

/// Edge length of a brick in voxels.
pub const BRICK_EDGE: i32 = 8;
/// log2 of [`BRICK_EDGE`].
pub const BRICK_SHIFT: i32 = 3;
/// Voxels in one brick.
pub const BRICK_VOXELS: usize = 512;

/// Linear index of a voxel inside a brick; each coordinate must be in 0..8.
#[inline(always)]
pub fn voxel_index(x: i32, y: i32, z: i32) -> usize {
    debug_assert!((0..8).contains(&x) && (0..8).contains(&y) && (0..8).contains(&z));
    (x | (y << 3) | (z << 6)) as usize
}

/// A brick's content, as the store and the scene builders exchange it.
#[derive(Clone, Debug, PartialEq, Eq)]
pub enum BrickContent {
    /// No solid voxel: costs nothing.
    Empty,
    /// All 512 voxels solid with this one material: costs no brick storage.
    Uniform(u8),
    /// Anything else.
    Mixed(Brick),
}

impl BrickContent {
    /// Classify a dense 512-entry material array (0 = empty).
    pub fn from_dense(dense: &[u8; BRICK_VOXELS], palette: &Palette) -> Self {
        let first = dense[0];
        if dense.iter().all(|&m| m == first) {
            return if first == 0 {
                BrickContent::Empty
            } else {
                BrickContent::Uniform(first)
            };
        }
        BrickContent::Mixed(Brick::from_dense_mixed(dense, palette))
    }

    /// Write this content as a dense material array.
    pub fn to_dense(&self, out: &mut [u8; BRICK_VOXELS]) {
        match self {
            BrickContent::Empty => out.fill(0),
            BrickContent::Uniform(m) => out.fill(*m),
            BrickContent::Mixed(b) => b.to_dense(out),
        }
    }

    /// Number of solid voxels.
    pub fn solid_voxels(&self) -> u32 {
        match self {
            BrickContent::Empty => 0,
            BrickContent::Uniform(_) => BRICK_VOXELS as u32,
            BrickContent::Mixed(b) => b.solid_voxels(),
        }
    }
}

/// A non-uniform brick: occupancy mask, compressed materials and a LOD colour.
///
/// ```
/// use brickworld::world::{Brick, BrickContent, Palette, voxel_index};
/// let palette = Palette::grey_ramp();
/// let mut dense = [0u8; 512];
/// dense[voxel_index(1, 2, 3)] = 7;
/// dense[voxel_index(4, 4, 4)] = 9;
/// let BrickContent::Mixed(brick) = BrickContent::from_dense(&dense, &palette) else { panic!() };
/// assert_eq!(brick.material(1, 2, 3), 7);
/// assert_eq!(brick.material(4, 4, 4), 9);
/// assert_eq!(brick.material(0, 0, 0), 0);
/// assert_eq!(brick.solid_voxels(), 2);
/// ```
#[derive(Clone, Debug, PartialEq, Eq)]
pub struct Brick {
    mask: [u64; 8],
    /// Distinct materials used, at most 255 (0 is never stored).
    local_palette: Box<[u8]>,
    /// Packed local indices in rank order, `bits` each (never straddling words).
    indices: Box<[u64]>,
    bits: u8,
    /// Average RGB of the solid voxels, for level of detail.
    lod_rgb: [u8; 3],
    /// Materials of the coarser levels (octants and the whole brick).
    lod: BrickLod,
}

/// The mean colour of a dense brick's solid voxels under `palette` (black
/// for an empty one): a mixed brick's LOD colour.
fn mean_rgb(dense: &[u8; BRICK_VOXELS], palette: &Palette) -> [u8; 3] {
    let (mut sum, mut solid) = ([0u64; 3], 0u64);
    for &m in dense.iter().filter(|&&m| m != 0) {
        let c = palette.rgb(m);
        for k in 0..3 {
            sum[k] += c[k] as u64;
        }
        solid += 1;
    }
    sum.map(|c| c.checked_div(solid).unwrap_or(0) as u8)
}

impl Brick {
    fn from_dense_mixed(dense: &[u8; BRICK_VOXELS], palette: &Palette) -> Self {
        let mut mask = [0u64; 8];
        let mut seen = [false; 256];
        let mut local: Vec<u8> = Vec::new();
        let mut solid = 0u64;
        for (i, &m) in dense.iter().enumerate() {
            if m != 0 {
                mask[i >> 6] |= 1u64 << (i & 63);
                if !seen[m as usize] {
                    seen[m as usize] = true;
                    local.push(m);
                }
                solid += 1;
            }
        }
        local.sort_unstable();
        let bits: u8 = match local.len() {
            0 | 1 => 0,
            2 => 1,
            3..=4 => 2,
            5..=16 => 4,
            _ => 8,
        };
        let mut lookup = [0u8; 256];
        for (i, &m) in local.iter().enumerate() {
            lookup[m as usize] = i as u8;
        }
        let per_word = if bits == 0 { 0 } else { 64 / bits as usize };
        let words = if bits == 0 {
            0
        } else {
            (solid as usize).div_ceil(per_word)
        };
        let mut indices = vec![0u64; words];
        if bits > 0 {
            let mut rank = 0usize;
            for &m in dense.iter() {
                if m != 0 {
                    let v = lookup[m as usize] as u64;
                    indices[rank / per_word] |= v << ((rank % per_word) * bits as usize);
                    rank += 1;
                }
            }
        }
        let lod_rgb = mean_rgb(dense, palette);
        Brick {
            mask,
            local_palette: local.into_boxed_slice(),
            indices: indices.into_boxed_slice(),
            bits,
            lod_rgb,
            lod: BrickLod::of_dense(dense),
        }
    }

    /// The 512-bit occupancy mask, word `z` holding the slice at depth `z`.
    #[inline(always)]
    pub fn mask(&self) -> &[u64; 8] {
        &self.mask
    }

    /// Whether voxel `index` (see [`voxel_index`]) is solid.
    #[inline(always)]
    pub fn is_solid_index(&self, index: usize) -> bool {
        (self.mask[index >> 6] >> (index & 63)) & 1 != 0
    }

    /// Material of voxel `index`, 0 if empty.
    #[inline]
    pub fn material_index(&self, index: usize) -> u8 {
        if !self.is_solid_index(index) {
            return 0;
        }
        if self.bits == 0 {
            return self.local_palette[0];
        }
        let word = index >> 6;
        let mut rank = 0u32;
        for w in &self.mask[..word] {
            rank += w.count_ones();
        }
        rank += (self.mask[word] & ((1u64 << (index & 63)) - 1)).count_ones();
        let bits = self.bits as usize;
        let per_word = 64 / bits;
        let rank = rank as usize;
        let packed = self.indices[rank / per_word] >> ((rank % per_word) * bits);
        self.local_palette[(packed & ((1u64 << bits) - 1)) as usize]
    }

    /// Material at brick-local `(x, y, z)`, 0 if empty.
    pub fn material(&self, x: i32, y: i32, z: i32) -> u8 {
        self.material_index(voxel_index(x, y, z))
    }

    /// Expand into a dense material array.
    pub fn to_dense(&self, out: &mut [u8; BRICK_VOXELS]) {
        out.fill(0);
        let bits = self.bits as usize;
        let per_word = 64usize.checked_div(bits).unwrap_or(1);
        let mut rank = 0usize;
        for (w, &word) in self.mask.iter().enumerate() {
            let mut m = word;
            while m != 0 {
                let b = m.trailing_zeros() as usize;
                m &= m - 1;
                let local = if bits == 0 {
                    0
                } else {
                    ((self.indices[rank / per_word] >> ((rank % per_word) * bits))
                        & ((1u64 << bits) - 1)) as usize
                };
                out[(w << 6) | b] = self.local_palette[local];
                rank += 1;
            }
        }
    }

    /// Number of solid voxels.
    pub fn solid_voxels(&self) -> u32 {
        self.mask.iter().map(|w| w.count_ones()).sum()
    }

    /// Average colour of the solid voxels.
    pub fn lod_rgb(&self) -> [u8; 3] {
        self.lod_rgb
    }

    /// Materials of the brick's coarser levels.
    pub fn lod(&self) -> BrickLod {
        self.lod
    }

    /// The same brick with the coarser levels' materials of another: for a
    /// copy whose hidden voxels were recoloured, which must still look,
    /// from afar, like its original.
    pub fn with_lod(mut self, lod: BrickLod) -> Self {
        self.lod = lod;
        self
    }

    /// The same brick with its LOD colour computed from `palette`: for a
    /// brick encoded with another palette (a terrain generator's) that
    /// enters a world coloured by the engine's.
    pub fn with_palette(mut self, palette: &Palette) -> Self {
        let mut dense = [0u8; BRICK_VOXELS];
        self.to_dense(&mut dense);
        self.lod_rgb = mean_rgb(&dense, palette);
        self
    }

    /// Distinct materials used, sorted.
    pub fn local_palette(&self) -> &[u8] {
        &self.local_palette
    }

    /// Bits per packed local index (0, 1, 2, 4 or 8).
    pub fn bits(&self) -> u8 {
        self.bits
    }

    /// Packed local indices in rank order, little-endian within each word.
    pub fn index_words(&self) -> &[u64] {
        &self.indices
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn roundtrip(dense: &[u8; BRICK_VOXELS]) {
        let palette = Palette::grey_ramp();
        let c = BrickContent::from_dense(dense, &palette);
        let mut out = [0u8; BRICK_VOXELS];
        c.to_dense(&mut out);
        assert_eq!(&out[..], &dense[..]);
        if let BrickContent::Mixed(b) = &c {
            for i in 0..BRICK_VOXELS {
                assert_eq!(b.material_index(i), dense[i], "voxel {i}");
            }
        }
    }

    #[test]
    fn uniform_and_empty_bricks_cost_no_storage() {
        let palette = Palette::grey_ramp();
        assert_eq!(
            BrickContent::from_dense(&[0; 512], &palette),
            BrickContent::Empty
        );
        assert_eq!(
            BrickContent::from_dense(&[3; 512], &palette),
            BrickContent::Uniform(3)
        );
    }

    #[test]
    fn every_palette_width_roundtrips() {
        for distinct in [1usize, 2, 3, 4, 5, 16, 17, 255] {
            let mut dense = [0u8; BRICK_VOXELS];
            for (i, d) in dense.iter_mut().enumerate() {
                if (i * 7919) % 3 != 0 {
                    *d = 1 + ((i * 31) % distinct) as u8;
                }
            }
            roundtrip(&dense);
        }
    }

    #[test]
    fn full_brick_with_two_materials_is_mixed() {
        let mut dense = [5u8; BRICK_VOXELS];
        dense[511] = 6;
        roundtrip(&dense);
    }
}
