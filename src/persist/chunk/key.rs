//! Chunk and chunk-column keys, and their byte form in the store: each
//! coordinate as a big-endian `u32` with its sign bit flipped, so keys sort
//! by coordinate, and decoding refuses coordinates no engine writes.

use glam::{IVec2, IVec3};

use super::CHUNK_SHIFT;

/// A chunk's coordinate: brick coordinate `>> 3` on every axis.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Hash)]
pub struct ChunkKey(pub IVec3);

impl ChunkKey {
    /// The chunk holding brick `b`.
    #[inline]
    pub fn of_brick(b: IVec3) -> Self {
        ChunkKey(b >> CHUNK_SHIFT)
    }

    /// The chunk's first brick.
    pub fn min_brick(self) -> IVec3 {
        self.0 << CHUNK_SHIFT
    }

    /// Brick coordinate of local index `i` (`x + 8y + 64z`).
    #[inline]
    pub fn brick(self, i: usize) -> IVec3 {
        let i = i as i32;
        self.min_brick() + IVec3::new(i & 7, (i >> 3) & 7, i >> 6)
    }

    /// The store key: big-endian with the sign bit flipped, so keys sort by
    /// (x, y, z) as signed numbers.
    pub fn to_bytes(self) -> [u8; 12] {
        key_bytes(&[self.0.x, self.0.y, self.0.z])
    }

    /// The inverse of [`to_bytes`](Self::to_bytes).
    pub fn from_bytes(b: &[u8]) -> Option<Self> {
        let v = key_from_bytes::<3>(b)?;
        Some(ChunkKey(IVec3::new(v[0], v[1], v[2])))
    }
}

impl std::fmt::Display for ChunkKey {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        let v = self.min_brick() * crate::world::BRICK_EDGE;
        write!(
            f,
            "chunk ({}, {}, {}) at voxel ({}, {}, {})",
            self.0.x, self.0.y, self.0.z, v.x, v.y, v.z
        )
    }
}

/// A chunk column's coordinate: tile (brick column) coordinate `>> 3`.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Hash)]
pub struct ColumnKey(pub IVec2);

impl ColumnKey {
    /// The chunk column holding tile `t`.
    #[inline]
    pub fn of_tile(t: IVec2) -> Self {
        ColumnKey(t >> CHUNK_SHIFT)
    }

    /// Tile of local index `i` (`x + 8z`).
    pub fn tile(self, i: usize) -> IVec2 {
        let i = i as i32;
        (self.0 << CHUNK_SHIFT) + IVec2::new(i & 7, i >> 3)
    }

    /// The store key (see [`ChunkKey::to_bytes`]).
    pub fn to_bytes(self) -> [u8; 8] {
        key_bytes(&[self.0.x, self.0.y])
    }

    /// The inverse of [`to_bytes`](Self::to_bytes).
    pub fn from_bytes(b: &[u8]) -> Option<Self> {
        let v = key_from_bytes::<2>(b)?;
        Some(ColumnKey(IVec2::new(v[0], v[1])))
    }
}

impl std::fmt::Display for ColumnKey {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        write!(f, "chunk column ({}, {})", self.0.x, self.0.y)
    }
}

fn key_bytes<const N: usize, const B: usize>(v: &[i32; N]) -> [u8; B] {
    let mut out = [0u8; B];
    for (i, x) in v.iter().enumerate() {
        out[i * 4..i * 4 + 4].copy_from_slice(&((*x as u32) ^ 0x8000_0000).to_be_bytes());
    }
    out
}

/// The largest chunk (or chunk column) coordinate a key may hold.
const MAX_KEY: u32 = 1 << 24;

fn key_from_bytes<const N: usize>(b: &[u8]) -> Option<[i32; N]> {
    if b.len() != N * 4 {
        return None;
    }
    let mut v = [0i32; N];
    for (i, x) in v.iter_mut().enumerate() {
        let u = u32::from_be_bytes(b[i * 4..i * 4 + 4].try_into().ok()?);
        *x = (u ^ 0x8000_0000) as i32;
        // Chunks (64 voxels) of a world within ±2^30 voxels: anything
        // larger is not a key this engine wrote, and would overflow the
        // brick and voxel coordinates computed from it.
        if x.unsigned_abs() > MAX_KEY {
            return None;
        }
    }
    Some(v)
}
