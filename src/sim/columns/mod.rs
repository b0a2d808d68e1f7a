//! The column grid (2.5D): per-tile channels over 8×8 columns, the
//! race-free parallel step, the native reference kernel, and the write-back
//! of ground, snow and water surfaces into bricks. The right model for open
//! terrain, the Ritter dam break and the lake at rest.

pub mod channels;
mod exec;
pub mod native;
pub mod run;
pub mod step;
pub mod tile;
mod world_step;
pub mod writeback;
