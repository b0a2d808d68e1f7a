//! The world core: bricks, the brick pool, the sparse store with edit
//! tracking, the palette, the material registry, and the brick grid with
//! its occupancy layer.

mod brick;
mod grid;
mod materials;
mod mip;
mod palette;
mod pool;
mod store;

pub use brick::{BRICK_EDGE, BRICK_SHIFT, BRICK_VOXELS, Brick, BrickContent, voxel_index};
pub use grid::{BrickGrid, MAX_GRID_CELLS, OCC_EDGE, OCC_SHIFT, UNIFORM, WorldError};
pub use materials::{MaterialDef, MaterialError, MaterialId, MaterialKind, MaterialRegistry};
pub use mip::{
    BrickLod, CoarseLevels, EMPTY_MASK, FACE_DIRS, FULL_MASK, TOP_LEVEL, block_solid,
    exposed_faces, for_each_exposed, representative,
};
pub use palette::Palette;
pub use pool::{ARENA_LIMIT, BrickId, BrickPool, BrickRef, GPU_META_WORDS};
pub use store::{BrickStore, Cell, brick_of};
