//! The brick grid: a dense array of 32-bit brick pointers over a region of the
//! store, with the occupancy layer above it (one bit per 4³ bricks,
//! van Wingerden §3.4). Both are patched incrementally from the store's
//! modified list, never rebuilt on edit.
//!
//! Pointer encoding: `0` empty, `UNIFORM | m` uniform material `m`, otherwise
//! the pool slot index plus one.
//!
//! The grid is addressed toroidally: local brick `l` lives at physical cell
//! `(l + ring) mod dims`. A world that streams keeps a window of the world
//! around the camera in one grid and [`slide`](BrickGrid::slide)s it: only the
//! slabs that enter are rewritten, O(entering cells), and the tracers, which
//! only ever ask for local coordinates, never notice. A grid that never
//! slides has `ring = 0` and the plain layout.

use glam::IVec3;
use thiserror::Error;

use super::mip::CoarseLevels;
use super::pool::BrickPool;
use super::store::{BrickStore, Cell};

/// Pointer flag for a uniform brick; the low byte is the material.
pub const UNIFORM: u32 = 1 << 31;
/// Bricks per occupancy cell along each axis.
pub const OCC_EDGE: i32 = 4;
/// log2 of [`OCC_EDGE`].
pub const OCC_SHIFT: i32 = 2;

/// Errors building world structures.
#[derive(Debug, Error, PartialEq, Eq)]
pub enum WorldError {
    /// The requested grid has more cells than the limit allows.
    #[error("brick grid of {dims} bricks ({cells} cells) exceeds the limit of {limit} cells")]
    RegionTooLarge {
        /// Grid size in bricks.
        dims: IVec3,
        /// Cell count.
        cells: u64,
        /// Limit.
        limit: u64,
    },
}

/// Most cells a grid may have (4 GiB of pointers).
pub const MAX_GRID_CELLS: u64 = 1 << 30;

/// Dense brick pointers over a region, plus the occupancy layer.
#[derive(Debug, Clone)]
pub struct BrickGrid {
    origin: IVec3,
    dims: IVec3,
    /// Physical cell of local brick (0, 0, 0); a multiple of [`OCC_EDGE`].
    ring: IVec3,
    /// Whether `ring` is zero: lookups then skip the wrap (tracers read the
    /// grid once per coarse step).
    flat: bool,
    cells: Vec<u32>,
    occ_dims: IVec3,
    occ: Vec<u64>,
    /// Levels 4 and 5 (16 and 32 voxels per cell) for level of detail.
    coarse: CoarseLevels,
}

/// The level-3 material of the brick behind grid pointer `p` (0 if empty).
#[inline]
pub fn brick_material(pool: &BrickPool, p: u32) -> u8 {
    match p {
        0 => 0,
        p if p & UNIFORM != 0 => p as u8,
        p => pool.slot(p - 1).map_or(0, |b| b.lod().whole),
    }
}

#[inline]
fn encode(cell: Cell) -> u32 {
    match cell {
        Cell::Empty => 0,
        Cell::Uniform(m) => UNIFORM | m as u32,
        Cell::Mixed(id) => id.index() + 1,
    }
}

impl BrickGrid {
    /// Build the grid for bricks `origin .. origin + dims` (brick coordinates).
    /// `dims` is rounded up to whole occupancy cells.
    pub fn build(store: &BrickStore, origin: IVec3, dims: IVec3) -> Result<Self, WorldError> {
        let dims = ((dims.max(IVec3::ONE) + IVec3::splat(OCC_EDGE - 1)) >> OCC_SHIFT) << OCC_SHIFT;
        let cells_n = dims.x as u64 * dims.y as u64 * dims.z as u64;
        if cells_n > MAX_GRID_CELLS {
            return Err(WorldError::RegionTooLarge {
                dims,
                cells: cells_n,
                limit: MAX_GRID_CELLS,
            });
        }
        let occ_dims = dims >> OCC_SHIFT;
        let occ_n = (occ_dims.x * occ_dims.y * occ_dims.z) as usize;
        let mut grid = BrickGrid {
            origin,
            dims,
            ring: IVec3::ZERO,
            flat: true,
            cells: vec![0; cells_n as usize],
            occ_dims,
            occ: vec![0; occ_n.div_ceil(64)],
            coarse: CoarseLevels::new(dims.to_array()),
        };
        for (b, cell) in store.iter() {
            if let Some(i) = grid.index(b - origin) {
                grid.cells[i] = encode(cell);
                grid.set_occ((b - origin) >> OCC_SHIFT, true);
            }
        }
        grid.update_coarse(store.pool(), IVec3::ZERO, dims);
        Ok(grid)
    }

    /// Recompute the level-4 cells (2³ bricks) touching local bricks
    /// `[lo, hi)` and their level-5 parents.
    fn update_coarse(&mut self, pool: &BrickPool, lo: IVec3, hi: IVec3) {
        let (clo, chi): (IVec3, IVec3) = (lo >> 1i32, (hi + IVec3::ONE) >> 1i32);
        let (cells, dims, ring) = (&self.cells, self.dims, self.ring);
        let material = |l: [i32; 3]| {
            let p = Self::wrap(IVec3::from(l), ring, dims);
            brick_material(pool, cells[(p.x + dims.x * (p.y + dims.y * p.z)) as usize])
        };
        for z in clo.z..chi.z {
            for y in clo.y..chi.y {
                for x in clo.x..chi.x {
                    self.coarse.update([x, y, z], ring.to_array(), material);
                }
            }
        }
    }

    /// The grid's levels 4 and 5 (see [`crate::world::mip`]).
    pub fn coarse(&self) -> &CoarseLevels {
        &self.coarse
    }

    /// Patch the grid after edits to bricks `changed` (world brick coordinates).
    pub fn apply_edits(&mut self, store: &BrickStore, changed: &[IVec3]) {
        for &b in changed {
            let local = b - self.origin;
            let Some(i) = self.index(local) else { continue };
            self.cells[i] = encode(store.cell(b));
            let o = local >> OCC_SHIFT;
            let any = self.occ_group_non_empty(o);
            self.set_occ(o, any);
            self.update_coarse(store.pool(), local, local + IVec3::ONE);
        }
    }

    /// Move the grid to cover bricks `origin .. origin + dims()`, reading the
    /// cells that enter from `store` (which must already hold them). Costs
    /// O(entering cells); a move of a whole grid or more rewrites it all.
    /// Every component of the move must be a multiple of [`OCC_EDGE`].
    pub fn slide(&mut self, store: &BrickStore, origin: IVec3) {
        let d = origin - self.origin;
        assert!(
            d.x % OCC_EDGE == 0 && d.y % OCC_EDGE == 0 && d.z % OCC_EDGE == 0,
            "a grid slides by whole occupancy cells (moved by {d})"
        );
        if d == IVec3::ZERO {
            return;
        }
        self.origin = origin;
        self.ring = (self.ring + d).rem_euclid(self.dims);
        self.flat = self.ring == IVec3::ZERO;
        let dims = self.dims;
        // The entering slab of each axis, as local ranges.
        for axis in 0..3 {
            if d[axis] == 0 {
                continue;
            }
            let n = d[axis].abs().min(dims[axis]);
            let mut lo = IVec3::ZERO;
            let mut hi = dims;
            if d[axis] > 0 {
                lo[axis] = dims[axis] - n;
            } else {
                hi[axis] = n;
            }
            self.refill(store, lo, hi);
        }
    }

    /// Re-read local bricks `[lo, hi)` from the store and recompute the
    /// occupancy cells they touch.
    fn refill(&mut self, store: &BrickStore, lo: IVec3, hi: IVec3) {
        for z in lo.z..hi.z {
            for y in lo.y..hi.y {
                for x in lo.x..hi.x {
                    let l = IVec3::new(x, y, z);
                    let i = self.index(l).expect("inside");
                    self.cells[i] = encode(store.cell(self.origin + l));
                }
            }
        }
        let (olo, ohi) = (
            lo >> OCC_SHIFT,
            (hi + IVec3::splat(OCC_EDGE - 1)) >> OCC_SHIFT,
        );
        for z in olo.z..ohi.z {
            for y in olo.y..ohi.y {
                for x in olo.x..ohi.x {
                    let o = IVec3::new(x, y, z);
                    let any = self.occ_group_non_empty(o);
                    self.set_occ(o, any);
                }
            }
        }
        self.update_coarse(store.pool(), lo, hi);
    }

    fn occ_group_non_empty(&self, o: IVec3) -> bool {
        let base = o << OCC_SHIFT;
        for z in 0..OCC_EDGE {
            for y in 0..OCC_EDGE {
                // Rows of an occupancy cell stay contiguous: the ring is a
                // multiple of the cell edge.
                let row = self.index(base + IVec3::new(0, y, z)).unwrap();
                if self.cells[row..row + OCC_EDGE as usize]
                    .iter()
                    .any(|&c| c != 0)
                {
                    return true;
                }
            }
        }
        false
    }

    /// Physical position of local `l` (inside) under the ring.
    #[inline(always)]
    fn wrap(l: IVec3, ring: IVec3, dims: IVec3) -> IVec3 {
        let p = l + ring;
        IVec3::new(
            if p.x >= dims.x { p.x - dims.x } else { p.x },
            if p.y >= dims.y { p.y - dims.y } else { p.y },
            if p.z >= dims.z { p.z - dims.z } else { p.z },
        )
    }

    #[inline(always)]
    fn index(&self, l: IVec3) -> Option<usize> {
        if l.cmplt(IVec3::ZERO).any() || l.cmpge(self.dims).any() {
            return None;
        }
        Some(self.brick_index(l))
    }

    /// Index in `cells` of local brick `l` (inside): the ring's wrap,
    /// skipped while the grid has not slid.
    #[inline(always)]
    fn brick_index(&self, l: IVec3) -> usize {
        let p = if self.flat {
            l
        } else {
            Self::wrap(l, self.ring, self.dims)
        };
        (p.x + self.dims.x * (p.y + self.dims.y * p.z)) as usize
    }

    #[inline(always)]
    fn occ_index(&self, o: IVec3) -> usize {
        let p = if self.flat {
            o
        } else {
            Self::wrap(o, self.ring >> OCC_SHIFT, self.occ_dims)
        };
        (p.x + self.occ_dims.x * (p.y + self.occ_dims.y * p.z)) as usize
    }

    fn set_occ(&mut self, o: IVec3, on: bool) {
        let i = self.occ_index(o);
        if on {
            self.occ[i >> 6] |= 1 << (i & 63);
        } else {
            self.occ[i >> 6] &= !(1 << (i & 63));
        }
    }

    /// World brick coordinate of local brick (0, 0, 0).
    pub fn origin(&self) -> IVec3 {
        self.origin
    }

    /// Size in bricks (a multiple of [`OCC_EDGE`]).
    pub fn dims(&self) -> IVec3 {
        self.dims
    }

    /// Index in [`pointers`](Self::pointers) of local brick `l` (None
    /// outside the grid).
    pub fn cell_index(&self, l: IVec3) -> Option<usize> {
        self.index(l)
    }

    /// The local brick whose pointer is at index `i` of
    /// [`pointers`](Self::pointers) (which must be in range).
    pub fn local_of_index(&self, i: usize) -> IVec3 {
        let d = self.dims;
        let i = i as i32;
        let p = IVec3::new(i % d.x, (i / d.x) % d.y, i / (d.x * d.y));
        (p - self.ring).rem_euclid(d)
    }

    /// Physical cell of local brick (0, 0, 0): zero until the grid slides.
    pub fn ring(&self) -> IVec3 {
        self.ring
    }

    /// Pointer of local brick `l`, which must be inside the grid.
    #[inline(always)]
    pub fn pointer(&self, l: IVec3) -> u32 {
        self.cells[self.brick_index(l)]
    }

    /// Occupancy bit of local occupancy cell `o`, which must be inside.
    #[inline(always)]
    pub fn occupied(&self, o: IVec3) -> bool {
        let i = self.occ_index(o);
        (self.occ[i >> 6] >> (i & 63)) & 1 != 0
    }

    /// The pointer array in physical order (x fastest, then y, then z):
    /// local order only while [`ring`](Self::ring) is zero.
    pub fn pointers(&self) -> &[u32] {
        &self.cells
    }

    /// Bytes of the pointer array and the occupancy layer.
    pub fn bytes(&self) -> usize {
        self.cells.len() * 4 + self.occ.len() * 8 + self.coarse.bytes()
    }

    /// Number of non-empty pointers.
    pub fn non_empty(&self) -> usize {
        self.cells.iter().filter(|&&c| c != 0).count()
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::world::Palette;

    #[test]
    fn incremental_updates_match_a_rebuild() {
        let mut s = BrickStore::new(Palette::grey_ramp());
        s.fill_box(IVec3::ZERO, IVec3::new(40, 9, 17), 3);
        s.take_modified();
        let mut g = BrickGrid::build(&s, IVec3::ZERO, IVec3::new(8, 4, 4)).unwrap();
        s.fill_box(IVec3::ZERO, IVec3::new(40, 9, 17), 0);
        s.set_voxel(IVec3::new(50, 3, 3), 5);
        s.set_voxel(IVec3::new(-5, 3, 3), 5); // outside the grid: ignored
        let changed = s.take_modified();
        g.apply_edits(&s, &changed);
        let fresh = BrickGrid::build(&s, IVec3::ZERO, IVec3::new(8, 4, 4)).unwrap();
        assert_eq!(g.cells, fresh.cells);
        assert_eq!(g.occ, fresh.occ);
        assert_eq!(g.coarse().raw(), fresh.coarse().raw());
        assert!(g.occupied(IVec3::new(1, 0, 0)));
        assert!(!g.occupied(IVec3::ZERO));
    }

    /// Slides in every direction, with the store changing in between, leave
    /// the grid equal (through its local accessors) to a fresh build.
    #[test]
    fn slides_match_a_fresh_build() {
        let mut s = BrickStore::new(Palette::grey_ramp());
        for i in 0..400 {
            let p = IVec3::new((i * 37) % 190 - 60, (i * 11) % 40, (i * 53) % 170 - 50);
            s.set_voxel(p, 1 + (i % 7) as u8);
        }
        s.take_modified();
        let dims = IVec3::new(16, 8, 12);
        let mut g = BrickGrid::build(&s, IVec3::new(-8, 0, -4), dims).unwrap();
        let moves = [
            IVec3::new(4, 0, 0),
            IVec3::new(8, 0, -4),
            IVec3::new(-12, 4, 8),
            IVec3::new(0, -4, 0),
            IVec3::new(40, 0, 40),
            IVec3::new(-4, 0, 4),
        ];
        for (k, m) in moves.into_iter().enumerate() {
            // An edit inside the grid, one outside; then slide.
            s.set_voxel(g.origin() * 8 + IVec3::new(9, 3, 9), 9);
            s.set_voxel(g.origin() * 8 - IVec3::splat(30), 9);
            let changed = s.take_modified();
            g.apply_edits(&s, &changed);
            g.slide(&s, g.origin() + m);
            let fresh = BrickGrid::build(&s, g.origin(), dims).unwrap();
            for z in 0..dims.z {
                for y in 0..dims.y {
                    for x in 0..dims.x {
                        let l = IVec3::new(x, y, z);
                        assert_eq!(g.pointer(l), fresh.pointer(l), "move {k} brick {l}");
                        let i = g.cell_index(l).unwrap();
                        assert_eq!(g.local_of_index(i), l);
                        assert_eq!(g.pointers()[i], g.pointer(l));
                        if l % OCC_EDGE == IVec3::ZERO {
                            let o = l >> OCC_SHIFT;
                            assert_eq!(g.occupied(o), fresh.occupied(o), "move {k} occ {o}");
                            let m5 = g.coarse().get(5, o.to_array(), g.ring().to_array());
                            assert_eq!(m5 != 0, g.occupied(o), "level 5 is the occupancy");
                        }
                        assert_same_coarse(&g, &fresh, l);
                    }
                }
            }
            assert_eq!(g.non_empty(), fresh.non_empty());
        }
        assert_ne!(g.ring(), IVec3::ZERO);
    }

    /// Levels 4 and 5 over local brick `l` agree between two grids.
    fn assert_same_coarse(g: &BrickGrid, fresh: &BrickGrid, l: IVec3) {
        for level in [4u32, 5] {
            if l % (1 << (level - 3)) == IVec3::ZERO {
                let c = (l >> (level as i32 - 3)).to_array();
                assert_eq!(
                    g.coarse().get(level, c, g.ring().to_array()),
                    fresh.coarse().get(level, c, fresh.ring().to_array()),
                    "level {level} at brick {l}"
                );
            }
        }
    }

    /// Levels 4 and 5 hold the most common top of their bricks' materials.
    #[test]
    fn coarse_levels_hold_the_most_common_top() {
        let mut s = BrickStore::new(Palette::grey_ramp());
        // Stone bricks under a grass layer in brick row y = 1.
        s.fill_box(IVec3::ZERO, IVec3::new(32, 12, 32), 3);
        s.fill_box(IVec3::new(0, 12, 0), IVec3::new(32, 13, 32), 7);
        let g = BrickGrid::build(&s, IVec3::ZERO, IVec3::new(4, 4, 4)).unwrap();
        let r = g.ring().to_array();
        assert_eq!(g.coarse().get(4, [0, 0, 0], r), 7);
        assert_eq!(g.coarse().get(4, [1, 1, 1], r), 0);
        assert_eq!(g.coarse().get(5, [0, 0, 0], r), 7);
    }

    #[test]
    fn oversized_grid_is_refused() {
        let s = BrickStore::new(Palette::grey_ramp());
        let e = BrickGrid::build(&s, IVec3::ZERO, IVec3::new(4096, 4096, 4096)).unwrap_err();
        assert!(matches!(e, WorldError::RegionTooLarge { .. }));
    }
}
