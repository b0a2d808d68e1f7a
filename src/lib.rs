//! brickworld: a voxel world engine built on sparse 8³ bricks.
//!
//! - [`world`]: bricks, the sparse store with edit tracking, the brick grid.
//! - [`scene`]: deterministic scene sources (terrain, balls, hairball,
//!   heightmap PNGs, MagicaVoxel files).
//! - [`trace`]: the exact DDA, three interchangeable CPU tracers (dense grid,
//!   sparse voxel octree, brickmap), the camera and the tiled renderer.
//! - [`bench`]: the `bench tracers` comparison and its chart.
#![warn(missing_docs)]

pub mod scene;
pub mod trace;
pub mod world;
