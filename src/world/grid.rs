//! The brick grid: a dense array of 32-bit brick pointers over a region of the
//! store, with the occupancy layer above it (one bit per 4³ bricks,
//! van Wingerden §3.4). Both are patched incrementally from the store's
//! modified list, never rebuilt on edit.
//!
//! Pointer encoding: `0` empty, `UNIFORM | m` uniform material `m`, otherwise
//! the pool slot index plus one.

use glam::IVec3;
use thiserror::Error;

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
    cells: Vec<u32>,
    occ_dims: IVec3,
    occ: Vec<u64>,
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
            cells: vec![0; cells_n as usize],
            occ_dims,
            occ: vec![0; occ_n.div_ceil(64)],
        };
        for (b, cell) in store.iter() {
            if let Some(i) = grid.index(b - origin) {
                grid.cells[i] = encode(cell);
                grid.set_occ((b - origin) >> OCC_SHIFT, true);
            }
        }
        Ok(grid)
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
        }
    }

    fn occ_group_non_empty(&self, o: IVec3) -> bool {
        let base = o << OCC_SHIFT;
        for z in 0..OCC_EDGE {
            for y in 0..OCC_EDGE {
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

    #[inline(always)]
    fn index(&self, l: IVec3) -> Option<usize> {
        if l.cmplt(IVec3::ZERO).any() || l.cmpge(self.dims).any() {
            return None;
        }
        Some((l.x + self.dims.x * (l.y + self.dims.y * l.z)) as usize)
    }

    fn set_occ(&mut self, o: IVec3, on: bool) {
        let i = (o.x + self.occ_dims.x * (o.y + self.occ_dims.y * o.z)) as usize;
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

    /// Pointer of local brick `l`, which must be inside the grid.
    #[inline(always)]
    pub fn pointer(&self, l: IVec3) -> u32 {
        self.cells[(l.x + self.dims.x * (l.y + self.dims.y * l.z)) as usize]
    }

    /// Occupancy bit of local occupancy cell `o`, which must be inside.
    #[inline(always)]
    pub fn occupied(&self, o: IVec3) -> bool {
        let i = (o.x + self.occ_dims.x * (o.y + self.occ_dims.y * o.z)) as usize;
        (self.occ[i >> 6] >> (i & 63)) & 1 != 0
    }

    /// The pointer array (x fastest, then y, then z).
    pub fn pointers(&self) -> &[u32] {
        &self.cells
    }

    /// The occupancy bits as 64-bit words (bit i = occupancy cell i, x fastest).
    pub fn occupancy_words(&self) -> &[u64] {
        &self.occ
    }

    /// Bytes of the pointer array and the occupancy layer.
    pub fn bytes(&self) -> usize {
        self.cells.len() * 4 + self.occ.len() * 8
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
        assert!(g.occupied(IVec3::new(1, 0, 0)));
        assert!(!g.occupied(IVec3::ZERO));
    }

    #[test]
    fn oversized_grid_is_refused() {
        let s = BrickStore::new(Palette::grey_ramp());
        let e = BrickGrid::build(&s, IVec3::ZERO, IVec3::new(4096, 4096, 4096)).unwrap_err();
        assert!(matches!(e, WorldError::RegionTooLarge { .. }));
    }
}
