//! Gathering a brick's one-voxel halo (10³ cells) from its 27-brick
//! neighbourhood, a row of ten cells at a time.
//!
//! Halo index: `(x + 1) + (y + 1)·10 + (z + 1)·100` for x, y, z in −1..=8
//! (x fastest, as in a brick). Neighbour index: `(dx + 1) + (dy + 1)·3 +
//! (dz + 1)·9`, so 13 is the brick itself.

#[cfg(test)]
use std::sync::OnceLock;

use glam::IVec3;

use crate::sim::script::{VOXEL_CELLS, VOXEL_HALO};
use crate::world::BRICK_EDGE;
#[cfg(test)]
use crate::world::voxel_index;

/// The brick itself in a neighbourhood.
pub const SELF: usize = 13;

/// Halo index of local voxel (x, y, z) (each −1..=8).
#[inline(always)]
pub fn halo_index(x: i32, y: i32, z: i32) -> usize {
    ((x + 1) + (y + 1) * 10 + (z + 1) * 100) as usize
}

/// Offset of neighbour `n` (0..27).
pub fn neighbour_offset(n: usize) -> IVec3 {
    IVec3::new(n as i32 % 3 - 1, (n as i32 / 3) % 3 - 1, n as i32 / 9 - 1)
}

#[cfg(test)]
fn table() -> &'static [(u8, u16); VOXEL_HALO] {
    static T: OnceLock<[(u8, u16); VOXEL_HALO]> = OnceLock::new();
    T.get_or_init(|| {
        let mut t = [(0u8, 0u16); VOXEL_HALO];
        for z in -1i32..9 {
            for y in -1i32..9 {
                for x in -1i32..9 {
                    let (bx, lx) = (x.div_euclid(8), x.rem_euclid(8));
                    let (by, ly) = (y.div_euclid(8), y.rem_euclid(8));
                    let (bz, lz) = (z.div_euclid(8), z.rem_euclid(8));
                    let n = (bx + 1) + (by + 1) * 3 + (bz + 1) * 9;
                    t[halo_index(x, y, z)] = (n as u8, voxel_index(lx, ly, lz) as u16);
                }
            }
        }
        t
    })
}

/// Fill `out` from the neighbourhood `nbr` (None: use `missing`), a row of
/// ten cells at a time: the brick's own eight are one copy.
pub fn gather<T: Copy>(
    nbr: &[Option<&[T; VOXEL_CELLS]>; 27],
    missing: T,
    out: &mut [T; VOXEL_HALO],
) {
    for hz in 0..10 {
        let (bz, lz) = split(hz);
        for hy in 0..10 {
            let (by, ly) = split(hy);
            let n = 1 + by * 3 + bz * 9;
            let row = &mut out[hy * 10 + hz * 100..][..10];
            let base = ly * 8 + lz * 64;
            row[0] = nbr[n - 1].map_or(missing, |d| d[base + 7]);
            match nbr[n] {
                Some(d) => row[1..9].copy_from_slice(&d[base..base + 8]),
                None => row[1..9].fill(missing),
            }
            row[9] = nbr[n + 1].map_or(missing, |d| d[base]);
        }
    }
}

/// Halo cells of brick `b` outside the world's voxel box `[lo, hi)` read
/// `wall`: a world whose size is not a multiple of 8 ends inside its edge
/// bricks, whose voxels past it read as air before (growth probe: a 9³
/// world's scripts read and wrote voxel (13, 13, 13)). A brick whose halo
/// lies inside the box is left at once.
pub fn wall_off<T: Copy>(b: IVec3, (lo, hi): (IVec3, IVec3), wall: T, out: &mut [T; VOXEL_HALO]) {
    let o = b * BRICK_EDGE - IVec3::ONE;
    if o.cmpge(lo).all() && (o + IVec3::splat(10)).cmple(hi).all() {
        return;
    }
    for z in 0..10 {
        for y in 0..10 {
            for x in 0..10 {
                let p = o + IVec3::new(x, y, z);
                if p.cmplt(lo).any() || p.cmpge(hi).any() {
                    out[(x + y * 10 + z * 100) as usize] = wall;
                }
            }
        }
    }
}

/// Voxels of brick `b` outside the world's voxel box `[lo, hi)` keep what
/// `before` holds there (air, or a channel's stored values): a kernel's
/// writes past the world's edge are dropped.
pub fn keep_outside<T: Copy>(
    b: IVec3,
    (lo, hi): (IVec3, IVec3),
    before: &[T; VOXEL_CELLS],
    out: &mut [T; VOXEL_CELLS],
) {
    let o = b * BRICK_EDGE;
    if o.cmpge(lo).all() && (o + IVec3::splat(BRICK_EDGE)).cmple(hi).all() {
        return;
    }
    for (i, v) in out.iter_mut().enumerate() {
        let p = o + IVec3::new(i as i32 & 7, (i as i32 >> 3) & 7, i as i32 >> 6);
        if p.cmplt(lo).any() || p.cmpge(hi).any() {
            *v = before[i];
        }
    }
}

/// Halo coordinate (0..10) to (neighbour step 0..3, local coordinate).
#[inline(always)]
fn split(h: usize) -> (usize, usize) {
    match h {
        0 => (0, 7),
        9 => (2, 0),
        _ => (1, h - 1),
    }
}

/// The per-cell reference of [`gather`], through the table.
#[cfg(test)]
fn gather_by_table<T: Copy>(
    nbr: &[Option<&[T; VOXEL_CELLS]>; 27],
    missing: T,
    out: &mut [T; VOXEL_HALO],
) {
    for (o, &(n, l)) in out.iter_mut().zip(table().iter()) {
        *o = match nbr[n as usize] {
            Some(d) => d[l as usize],
            None => missing,
        };
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn the_halo_comes_from_the_right_neighbours() {
        // Neighbour n holds the value n everywhere; the brick itself holds
        // its local index.
        let bricks: Vec<[u16; VOXEL_CELLS]> = (0..27)
            .map(|n| {
                if n == SELF {
                    std::array::from_fn(|i| 1000 + i as u16)
                } else {
                    [n as u16; VOXEL_CELLS]
                }
            })
            .collect();
        let nbr: [Option<&[u16; VOXEL_CELLS]>; 27] = std::array::from_fn(|n| Some(&bricks[n]));
        let mut out = [0u16; VOXEL_HALO];
        gather(&nbr, 0, &mut out);
        assert_eq!(out[halo_index(0, 0, 0)], 1000);
        assert_eq!(out[halo_index(7, 7, 7)], 1000 + voxel_index(7, 7, 7) as u16);
        assert_eq!(out[halo_index(-1, 3, 3)], 12); // −x neighbour
        assert_eq!(out[halo_index(3, 8, 3)], 16); // +y
        assert_eq!(out[halo_index(3, 3, -1)], 4); // −z
        assert_eq!(out[halo_index(-1, -1, -1)], 0);
        assert_eq!(out[halo_index(8, 8, 8)], 26);
        assert_eq!(neighbour_offset(SELF), IVec3::ZERO);
        // The row copy agrees with the per-cell table, missing bricks too.
        let mut holes = nbr;
        for n in [0, 5, 13, 22] {
            holes[n] = None;
        }
        for nb in [nbr, holes] {
            let (mut a, mut b) = ([0u16; VOXEL_HALO], [0u16; VOXEL_HALO]);
            gather(&nb, 9999, &mut a);
            gather_by_table(&nb, 9999, &mut b);
            assert_eq!(a, b);
        }
        assert_eq!(neighbour_offset(0), IVec3::splat(-1));
    }
}
