//! Mip levels of bricks and of the brick grid, for level of detail.
//!
//! A cell of level `s` is an aligned cube of `2^s` voxels on a side:
//!
//! | level | edge (voxels) | occupancy from | material from |
//! |---|---|---|---|
//! | 0 | 1 | the brick mask | the brick |
//! | 1 | 2 | 8 mask bits ([`block_solid`]) | the brick's 8 octant materials |
//! | 2 | 4 | 64 mask bits ([`block_solid`]) | the brick's 8 octant materials |
//! | 3 | 8 | the grid pointer | the brick's material |
//! | 4 | 16 | [`CoarseLevels`] | [`CoarseLevels`] |
//! | 5 | 32 | [`CoarseLevels`] (= the occupancy bit) | [`CoarseLevels`] |
//!
//! **Occupancy is reduced by "any solid".** A coarse cell is solid when any
//! voxel in it is, so a level never loses a thin wall or a fence post: far
//! silhouettes *dilate* by less than one coarse cell (which the footprint
//! rule keeps under `C` pixels) instead of breaking up into holes, which a
//! majority rule does to every feature thinner than half a cell.
//!
//! **Materials are reduced by "most common top".** A coarse cell's material is
//! the most common, over its columns of children, of the material of the
//! topmost solid child (ties go to the lowest material id). A majority over
//! all voxels would paint a far grassy hill the colour of the stone under
//! its one-voxel turf; what a view of terrain sees is the top of each column.
//!
//! The two levels inside a brick need no storage: their occupancy is a few
//! masked words of the brick's own mask, so the GPU and the CPU read the
//! same 64 bytes. Levels 4 and 5 are one byte per cell (the material, 0 when
//! empty) kept beside the grid and patched from the dirty set like it.

/// Highest level a tracer descends from (32 voxels per cell).
pub const TOP_LEVEL: u32 = 5;

/// Whether the level-`level` cell (`level` 0, 1 or 2) at brick-local voxel
/// `l` (any voxel inside the cell) holds a solid voxel of `mask`.
///
/// ```
/// use brickworld::world::{block_solid, voxel_index};
/// let mut mask = [0u64; 8];
/// let i = voxel_index(5, 2, 7);
/// mask[i >> 6] |= 1 << (i & 63);
/// assert!(block_solid(&mask, 0, [5, 2, 7]));
/// assert!(block_solid(&mask, 1, [4, 3, 6]));
/// assert!(block_solid(&mask, 2, [7, 0, 4]));
/// assert!(!block_solid(&mask, 2, [0, 0, 4]));
/// ```
#[inline(always)]
pub fn block_solid(mask: &[u64; 8], level: u32, l: [i32; 3]) -> bool {
    match level {
        0 => (mask[l[2] as usize] >> (l[0] + 8 * l[1])) & 1 != 0,
        1 => {
            let z = (l[2] & !1) as usize;
            let bits = 0x303u64 << ((l[0] & !1) + 8 * (l[1] & !1));
            (mask[z] | mask[z + 1]) & bits != 0
        }
        _ => {
            let z = (l[2] & !3) as usize;
            let bits = 0x0F0F_0F0Fu64 << ((l[0] & !3) + 8 * (l[1] & !3));
            (mask[z] | mask[z + 1] | mask[z + 2] | mask[z + 3]) & bits != 0
        }
    }
}

/// The "most common top" of the cube `[lo, lo + edge)`: for each column
/// `(x, z)`, the material of the topmost cell whose `at` is non-zero; the
/// most common of those (ties to the lowest id), or 0 if the cube is empty.
pub fn representative(lo: [i32; 3], edge: i32, at: impl Fn(i32, i32, i32) -> u8) -> u8 {
    // At most edge² distinct tops; a small linear tally allocates nothing.
    let mut tally: [(u8, u16); 64] = [(0, 0); 64];
    let mut used = 0usize;
    for z in lo[2]..lo[2] + edge {
        for x in lo[0]..lo[0] + edge {
            let top = (lo[1]..lo[1] + edge)
                .rev()
                .map(|y| at(x, y, z))
                .find(|&m| m != 0);
            let Some(m) = top else { continue };
            match tally[..used].iter_mut().find(|(k, _)| *k == m) {
                Some(e) => e.1 += 1,
                None if used < 64 => {
                    tally[used] = (m, 1);
                    used += 1;
                }
                // More distinct tops than slots: the rest cannot win a tie
                // against a counted one, and 64 slots cover every 8×8 cube.
                None => {}
            }
        }
    }
    tally[..used]
        .iter()
        .max_by(|a, b| a.1.cmp(&b.1).then(b.0.cmp(&a.0)))
        .map_or(0, |e| e.0)
}

/// Directions of [`exposed_faces`], in order: +x, −x, +y, −y, +z, −z.
pub const FACE_DIRS: [[i32; 3]; 6] = [
    [1, 0, 0],
    [-1, 0, 0],
    [0, 1, 0],
    [0, -1, 0],
    [0, 0, 1],
    [0, 0, -1],
];

/// A full mask (a uniform neighbour) and an empty one (no neighbour).
pub const FULL_MASK: [u64; 8] = [u64::MAX; 8];
/// See [`FULL_MASK`].
pub const EMPTY_MASK: [u64; 8] = [0; 8];

/// Exposed voxel faces of the level-`level` cell (1, 2 or 3) holding
/// brick-local voxel `l`, per direction of [`FACE_DIRS`]: solid voxels of
/// the cell whose neighbour that way is empty. `nb[d]` is the mask of the
/// neighbouring brick in direction `d` ([`FULL_MASK`] for a uniform one,
/// [`EMPTY_MASK`] for none). A handful of shifts and popcounts per slice:
/// what a coarse hit needs to be shaded as the average of its faces.
///
/// ```
/// use brickworld::world::{EMPTY_MASK, exposed_faces};
/// // One solid voxel alone: one exposed face each way, at every level.
/// let mut m = [0u64; 8];
/// m[3] = 1 << (2 + 8 * 5);
/// assert_eq!(exposed_faces(&m, [&EMPTY_MASK; 6], 3, [0, 0, 0]), [1; 6]);
/// assert_eq!(exposed_faces(&m, [&EMPTY_MASK; 6], 1, [2, 4, 2]), [1; 6]);
/// assert_eq!(exposed_faces(&m, [&EMPTY_MASK; 6], 1, [0, 0, 0]), [0; 6]);
/// ```
pub fn exposed_faces(m: &[u64; 8], nb: [&[u64; 8]; 6], level: u32, l: [i32; 3]) -> [u32; 6] {
    let mut out = [0u32; 6];
    for_each_exposed(m, nb, level, l, |_, d, bits| out[d] += bits.count_ones());
    out
}

/// Call `f(z, d, bits)` for each slice `z` of the cell of
/// [`exposed_faces`] and direction `d` with the bits (`x + 8y`) of its
/// voxels whose face that way is exposed (never with no bits).
pub fn for_each_exposed(
    m: &[u64; 8],
    nb: [&[u64; 8]; 6],
    level: u32,
    l: [i32; 3],
    mut f: impl FnMut(usize, usize, u64),
) {
    const COL0: u64 = 0x0101_0101_0101_0101;
    const COL7: u64 = COL0 << 7;
    const ROW0: u64 = 0xFF;
    const ROW7: u64 = 0xFF << 56;
    let e = 1i32 << level.min(3);
    let b = l.map(|v| v & !(e - 1));
    let row = ((1u64 << e) - 1) << b[0];
    let mut cell = 0u64;
    for y in b[1]..b[1] + e {
        cell |= row << (8 * y);
    }
    for z in b[2] as usize..(b[2] + e) as usize {
        let w = m[z] & cell;
        if w == 0 {
            continue;
        }
        let nbr = [
            ((m[z] >> 1) & !COL7) | ((nb[0][z] & COL0) << 7),
            ((m[z] << 1) & !COL0) | ((nb[1][z] & COL7) >> 7),
            (m[z] >> 8) | ((nb[2][z] & ROW0) << 56),
            (m[z] << 8) | ((nb[3][z] & ROW7) >> 56),
            if z < 7 { m[z + 1] } else { nb[4][0] },
            if z > 0 { m[z - 1] } else { nb[5][7] },
        ];
        for (d, n) in nbr.iter().enumerate() {
            let bits = w & !n;
            if bits != 0 {
                f(z, d, bits);
            }
        }
    }
}

/// The level-of-detail materials of one mixed brick: one per 4³ octant
/// (index `x + 2y + 4z` of the octant) and one for the whole brick.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq)]
pub struct BrickLod {
    /// Material of each 4³ octant (0 when the octant is empty).
    pub octants: [u8; 8],
    /// Material of the whole brick.
    pub whole: u8,
}

impl BrickLod {
    /// Reduce a dense brick (`voxel_index` order).
    pub fn of_dense(dense: &[u8; super::BRICK_VOXELS]) -> Self {
        let at = |x: i32, y: i32, z: i32| dense[super::voxel_index(x, y, z)];
        let octants = std::array::from_fn(|o| {
            let o = o as i32;
            representative([(o & 1) * 4, ((o >> 1) & 1) * 4, (o >> 2) * 4], 4, at)
        });
        BrickLod {
            octants,
            whole: representative([0; 3], 8, at),
        }
    }

    /// The material of the level-`level` cell holding brick-local voxel `l`
    /// (`level` 1, 2 or 3). Level 1 (2³ voxels) takes its octant's
    /// material: storing 64 more bytes per brick for it would grow the pool
    /// by 75 %, and its cells are at most `C` pixels wide.
    #[inline]
    pub fn at(&self, level: u32, l: [i32; 3]) -> u8 {
        if level >= 3 {
            self.whole
        } else {
            self.octants[((l[0] >> 2) | ((l[1] >> 2) << 1) | ((l[2] >> 2) << 2)) as usize]
        }
    }
}

/// Levels 4 and 5 of a brick grid: one material byte per cell (0 when
/// empty), addressed toroidally like the grid itself.
#[derive(Clone, Debug, Default)]
pub struct CoarseLevels {
    /// `levels[k]` is level `4 + k`.
    levels: [Vec<u8>; 2],
    dims: [[i32; 3]; 2],
}

impl CoarseLevels {
    /// Empty levels over a grid of `dims` bricks (a multiple of 4).
    pub fn new(dims: [i32; 3]) -> Self {
        let d1 = dims.map(|d| d >> 1);
        let d2 = dims.map(|d| d >> 2);
        let n = |d: [i32; 3]| (d[0] * d[1] * d[2]) as usize;
        CoarseLevels {
            levels: [vec![0; n(d1)], vec![0; n(d2)]],
            dims: [d1, d2],
        }
    }

    #[inline(always)]
    fn index(&self, k: usize, c: [i32; 3], ring_bricks: [i32; 3]) -> usize {
        let d = self.dims[k];
        let r = ring_bricks.map(|v| v >> (k + 1));
        let p: [i32; 3] = std::array::from_fn(|a| {
            let v = c[a] + r[a];
            if v >= d[a] { v - d[a] } else { v }
        });
        (p[0] + d[0] * (p[1] + d[1] * p[2])) as usize
    }

    /// Material of level-`level` cell `c` (local cell coordinates, inside;
    /// `level` 4 or 5) under the grid's ring (in bricks).
    #[inline(always)]
    pub fn get(&self, level: u32, c: [i32; 3], ring_bricks: [i32; 3]) -> u8 {
        let k = (level - 4) as usize;
        self.levels[k][self.index(k, c, ring_bricks)]
    }

    /// Recompute level-4 cell `c` from its 2³ bricks (`brick(l)` is a
    /// brick's material, 0 if empty), then its level-5 parent.
    pub fn update(&mut self, c4: [i32; 3], ring_bricks: [i32; 3], brick: impl Fn([i32; 3]) -> u8) {
        let lo = c4.map(|v| v * 2);
        let m4 = representative(lo, 2, |x, y, z| brick([x, y, z]));
        let i4 = self.index(0, c4, ring_bricks);
        self.levels[0][i4] = m4;
        let c5 = c4.map(|v| v >> 1);
        let lo5 = c5.map(|v| v * 2);
        let m5 = representative(lo5, 2, |x, y, z| self.get(4, [x, y, z], ring_bricks));
        let i5 = self.index(1, c5, ring_bricks);
        self.levels[1][i5] = m5;
    }

    /// The level arrays in physical order (level 4, then level 5), for upload.
    pub fn raw(&self) -> (&[u8], &[u8]) {
        (&self.levels[0], &self.levels[1])
    }

    /// Bytes held.
    pub fn bytes(&self) -> usize {
        self.levels[0].len() + self.levels[1].len()
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::world::{BRICK_VOXELS, voxel_index};

    #[test]
    fn block_solid_matches_a_scan_of_the_cube() {
        let mut state = 0x1234_5678_9abc_def0u64;
        for _ in 0..200 {
            let mut mask = [0u64; 8];
            for _ in 0..3 {
                state = state
                    .wrapping_mul(6364136223846793005)
                    .wrapping_add(1442695040888963407);
                let i = (state >> 40) as usize % BRICK_VOXELS;
                mask[i >> 6] |= 1 << (i & 63);
            }
            for level in 0..3u32 {
                let e = 1 << level;
                for i in 0..BRICK_VOXELS {
                    let l = [(i & 7) as i32, ((i >> 3) & 7) as i32, (i >> 6) as i32];
                    let base = l.map(|v| v & !(e - 1));
                    let mut any = false;
                    for z in 0..e {
                        for y in 0..e {
                            for x in 0..e {
                                let j = voxel_index(base[0] + x, base[1] + y, base[2] + z);
                                any |= (mask[j >> 6] >> (j & 63)) & 1 != 0;
                            }
                        }
                    }
                    assert_eq!(block_solid(&mask, level, l), any, "level {level} {l:?}");
                }
            }
        }
    }

    /// Exposed faces by shifts and popcounts equal a voxel-by-voxel count,
    /// neighbour bricks included.
    #[test]
    fn exposed_faces_match_a_voxel_by_voxel_count() {
        let mut state = 0x2545_f491_4f6c_dd1du64;
        let mut next = || {
            state ^= state << 13;
            state ^= state >> 7;
            state ^= state << 17;
            state
        };
        for _ in 0..50 {
            let masks: Vec<[u64; 8]> = (0..7)
                .map(|_| std::array::from_fn(|_| next() & next()))
                .collect();
            let solid = |b: usize, x: i32, y: i32, z: i32| {
                let i = voxel_index(x, y, z);
                (masks[b][i >> 6] >> (i & 63)) & 1 != 0
            };
            // Voxel (x, y, z) relative to the centre brick 0; neighbours 1..7.
            let at = |x: i32, y: i32, z: i32| -> bool {
                let inside = |v: i32| (0..8).contains(&v);
                match (inside(x), inside(y), inside(z)) {
                    (true, true, true) => solid(0, x, y, z),
                    _ => {
                        let d = FACE_DIRS
                            .iter()
                            .position(|d| {
                                [x, y, z].iter().zip(d).all(|(v, &k)| {
                                    (k == 0 && inside(*v))
                                        || (k == 1 && *v == 8)
                                        || (k == -1 && *v == -1)
                                })
                            })
                            .unwrap();
                        solid(1 + d, x.rem_euclid(8), y.rem_euclid(8), z.rem_euclid(8))
                    }
                }
            };
            let nb: [&[u64; 8]; 6] = std::array::from_fn(|d| &masks[1 + d]);
            for level in 1..=3u32 {
                let e = 1 << level;
                for cz in (0..8).step_by(e) {
                    for cy in (0..8).step_by(e) {
                        for cx in (0..8).step_by(e) {
                            let mut want = [0u32; 6];
                            for z in cz..cz + e as i32 {
                                for y in cy..cy + e as i32 {
                                    for x in cx..cx + e as i32 {
                                        if !at(x, y, z) {
                                            continue;
                                        }
                                        for (d, n) in FACE_DIRS.iter().enumerate() {
                                            want[d] += !at(x + n[0], y + n[1], z + n[2]) as u32;
                                        }
                                    }
                                }
                            }
                            let got = exposed_faces(&masks[0], nb, level, [cx, cy, cz]);
                            assert_eq!(got, want, "level {level} cell {cx},{cy},{cz}");
                        }
                    }
                }
            }
        }
    }

    #[test]
    fn the_representative_is_the_most_common_top_not_the_bulk() {
        // Grass over stone: the tops are grass though stone is the bulk.
        let mut dense = [0u8; BRICK_VOXELS];
        for z in 0..8 {
            for x in 0..8 {
                for y in 0..5 {
                    dense[voxel_index(x, y, z)] = 3;
                }
                dense[voxel_index(x, 5, z)] = 7;
            }
        }
        let lod = BrickLod::of_dense(&dense);
        assert_eq!(lod.whole, 7);
        assert_eq!(lod.octants[0], 3, "the lower octants see stone on top");
        assert_eq!(lod.octants[2], 7, "the upper octants see the grass");
        // Ties go to the lowest id; an empty cube is 0.
        assert_eq!(
            representative([0; 3], 2, |x, _, _| if x == 0 { 9 } else { 4 }),
            4
        );
        assert_eq!(representative([0; 3], 4, |_, _, _| 0), 0);
    }
}
