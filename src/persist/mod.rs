//! The world on disk: chunks of bricks and their simulation channels in an
//! embedded transactional store ([`db`]), their blob format ([`chunk`]),
//! the simulation-state blob ([`state`]) and the byte helpers they share.
//!
//! The engine commits what changed every interval in one transaction
//! (see `engine::daemon`); a resume regenerates the world from its source and
//! overlays the stored chunks, so only edited chunks cost disk.

pub mod bytes;
pub mod chunk;
pub mod db;
pub mod state;

pub use chunk::{ChunkData, ChunkKey, ColumnData, ColumnKey};
pub use db::{CommitStats, Manifest, StoreError, StoreReader, WorldDb};
