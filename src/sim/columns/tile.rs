//! Tiles: the unit of simulation work. A tile is the 8×8 footprint of one
//! brick column (brick coordinates `bx, bz`); column models (water, erosion,
//! snow) hold one value per column per channel, so a tile holds 64 cells.
//!
//! Kernels see their tile plus a one-cell halo: a 10×10 array whose cell
//! (x, z), x and z in −1..=8, sits at index `(z + 1) · 10 + (x + 1)`.
//! Outputs are 8×8 arrays indexed `z · 8 + x`.

use glam::IVec2;

/// Columns per tile side.
pub const TILE: i32 = 8;
/// Cells per tile.
pub const TILE_CELLS: usize = 64;
/// Side of a tile with its halo.
pub const HALO: i32 = 10;
/// Cells of a tile with its halo.
pub const HALO_CELLS: usize = 100;

/// Tile coordinate: brick column (bx, bz).
pub type TileCoord = IVec2;

/// Index of own cell (x, z), both 0..8, in an 8×8 array.
#[inline(always)]
pub fn cell(x: i32, z: i32) -> usize {
    (z * TILE + x) as usize
}

/// Index of cell (x, z), both −1..=8, in a 10×10 halo array.
#[inline(always)]
pub fn halo(x: i32, z: i32) -> usize {
    ((z + 1) * HALO + (x + 1)) as usize
}

/// The tiles whose cells appear in `t`'s halo (itself and its 8 neighbours).
pub fn neighbourhood(t: TileCoord) -> impl Iterator<Item = TileCoord> {
    (-1..=1).flat_map(move |dz| (-1..=1).map(move |dx| t + IVec2::new(dx, dz)))
}
