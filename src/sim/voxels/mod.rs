//! The voxel grid: scripts with `grid = "voxels"` run over the world's raw
//! bricks. A kernel sees its brick's materials and declared per-voxel
//! channels with a one-voxel halo (10³) and writes its own 8³ cells;
//! materials it changes go through the store's recorded edit path, so they
//! reach the step report's bricks and the renderer like any edit.
//!
//! - [`halo`]: gathering a brick's halo from its 27-brick neighbourhood.
//! - [`channels`]: sparse per-brick `f32` channels.
//! - [`native`]: native (Rust) reference kernels of shipped scripts.
//! - `exec`: one script's step: the dense working set, the parallel
//!   passes (Lua or native kernels) and their validated commit.
//! - `memory`: what a step may allocate, checked before it does (its
//!   working set, and what its changed bricks add to the world).
//! - `scripts`: loading, smoke-testing and replacing voxel scripts, and
//!   their rates, parameters and health.
//! - [`schedule`]: which bricks a step runs and which sleep (the active
//!   set, wakes, material presence, candidates).
//! - [`step`]: the step itself: rates, each script's parallel
//!   double-buffered run, validation and commit, then sleep and wake.

pub mod channels;
mod exec;
pub mod halo;
mod memory;
pub mod native;
pub mod schedule;
mod scripts;
pub mod step;

pub use channels::{VoxelChannelId, VoxelChannels};
pub use exec::VoxelKernel;
pub use native::{NativeBrick, VoxelNativeKernel, Water3d};
pub use step::{BOUNDARY, VoxelSim, VoxelStepReport};
