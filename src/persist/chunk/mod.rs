//! Chunks: the unit the world is stored, committed and (later) paged in.
//!
//! A chunk is 8³ bricks (64³ voxels), keyed by [`ChunkKey`]. Its blob holds
//! the chunk's bricks and the voxel scripts' per-voxel channels of those
//! bricks. The column simulation's per-tile channels are 2-D, so they are
//! stored per chunk *column* ([`ColumnKey`], 8×8 tiles), in their own blob.
//!
//! **Why 8³ bricks.** A commit rewrites whole chunks, so a chunk should be
//! small enough that one edit costs little (at most 512 bricks, 256 KiB of
//! raw voxels, typically a few KiB after LZ4 for a terrain surface), and
//! large enough that the store's per-key overhead and the LRU's bookkeeping
//! stay negligible: an 8192×256×8192 world has 128×4×128 = 65 536 chunk
//! keys. A 16³-brick chunk (128³ voxels) would make a one-voxel edit
//! rewrite up to 2 MiB and a 256-tall world only two chunks tall.
//!
//! **Blob format** (little-endian): magic `BWCH`, a `u32` CRC-32 of the
//! rest, then the LZ4 (`lz4_flex`, size-prepended) payload:
//!
//! | payload | |
//! |---|---|
//! | `u32` bricks, each `u16` local index (`x + 8y + 64z`), `u8` tag | 1: uniform + `u8` material; 2: mixed + 512 material bytes |
//! | `u32` channels, each name, `u32` bricks, each `u16` local index + 512 `f32` | voxel channels |
//!
//! A column blob (magic `BWCO`) holds `u32` channels, each a name, a `u32`
//! tile count, and per tile a `u8` local index (`x + 8z`) and 64 `f64`.
//!
//! Decoding never panics and never allocates more than a chunk can hold:
//! the size prefix is checked before decompression, every count against
//! the chunk's capacity.

mod column;
mod key;

pub use column::{
    ColumnData, TileArrays, apply_column, column_payload, decode_column, decode_column_payload,
    encode_column,
};
pub use key::{ChunkKey, ColumnKey};

use glam::IVec3;
use rustc_hash::FxHashSet;

use super::bytes::{Reader, Writer};
use crate::sim::voxels::VoxelChannels;
use crate::world::{BRICK_VOXELS, BrickContent, BrickStore, Cell, Palette};

/// Bricks along a chunk's edge.
pub const CHUNK_BRICKS: i32 = 8;
/// log2 of [`CHUNK_BRICKS`].
pub const CHUNK_SHIFT: i32 = 3;
/// Bricks in a chunk.
pub const CHUNK_CELLS: usize = 512;
/// Channels one chunk or column blob may carry (more is a corrupt blob):
/// the world registry's bound, so every blob the engine writes reads back.
pub const MAX_CHANNELS: usize = crate::sim::MAX_CHANNELS;
/// The largest payload a chunk blob can decompress to: every brick mixed
/// and every channel present, with room for names.
const MAX_CHUNK_PAYLOAD: usize = 8
    + CHUNK_CELLS * (3 + BRICK_VOXELS)
    + MAX_CHANNELS * (8 + 256 + CHUNK_CELLS * (2 + 4 * BRICK_VOXELS));

/// One voxel channel's arrays in a chunk, by brick.
pub type VoxelArrays = Vec<(IVec3, Box<[f32; BRICK_VOXELS]>)>;

/// A decoded chunk: its bricks (absent = empty) and voxel channels.
#[derive(Clone, Debug, Default, PartialEq)]
pub struct ChunkData {
    /// Non-empty bricks, by brick coordinate.
    pub bricks: Vec<(IVec3, BrickContent)>,
    /// Per channel name, the bricks holding an array.
    pub voxel: Vec<(String, VoxelArrays)>,
}

const CHUNK_MAGIC: &[u8; 4] = b"BWCH";

fn seal(magic: &[u8; 4], payload: &[u8]) -> Vec<u8> {
    let packed = lz4_flex::compress_prepend_size(payload);
    let mut out = Vec::with_capacity(8 + packed.len());
    out.extend_from_slice(magic);
    out.extend_from_slice(&crc32fast::hash(&packed).to_le_bytes());
    out.extend_from_slice(&packed);
    out
}

/// The most bytes `packed` LZ4 bytes (with their 4-byte size prefix) can
/// decompress to.
pub(crate) fn lz4_bound(packed: usize) -> usize {
    packed.saturating_sub(4).saturating_mul(255) + 16
}

fn unseal(magic: &[u8; 4], blob: &[u8], max: usize) -> Result<Vec<u8>, String> {
    if blob.len() < 12 || &blob[..4] != magic {
        return Err("not a brickworld chunk blob (bad magic)".into());
    }
    let crc = u32::from_le_bytes(blob[4..8].try_into().expect("4"));
    let packed = &blob[8..];
    if crc32fast::hash(packed) != crc {
        return Err("checksum mismatch".into());
    }
    let claimed = u32::from_le_bytes(packed[..4].try_into().expect("4")) as usize;
    if claimed > max {
        return Err(format!(
            "claims {claimed} bytes, more than a chunk can hold ({max})"
        ));
    }
    // LZ4 expands at most about 255 to 1: a larger claim is a lie, and
    // would allocate before decompression fails.
    if claimed > lz4_bound(packed.len()) {
        return Err(format!(
            "claims {claimed} bytes from {} packed bytes, more than LZ4 can expand to",
            packed.len()
        ));
    }
    lz4_flex::decompress_size_prepended(packed).map_err(|e| format!("LZ4: {e}"))
}

/// Encode chunk `key` of `store` and `voxel`'s channels.
pub fn encode_chunk(key: ChunkKey, store: &BrickStore, voxel: &VoxelChannels) -> Vec<u8> {
    seal(CHUNK_MAGIC, &chunk_payload(key, store, voxel))
}

/// A chunk blob's payload, before LZ4 and the checksum.
pub fn chunk_payload(key: ChunkKey, store: &BrickStore, voxel: &VoxelChannels) -> Vec<u8> {
    let mut w = Writer::default();
    let mut dense = [0u8; BRICK_VOXELS];
    let count_at = w.0.len();
    w.u32(0);
    let mut n = 0u32;
    for i in 0..CHUNK_CELLS {
        let b = key.brick(i);
        match store.cell(b) {
            Cell::Empty => continue,
            Cell::Uniform(m) => {
                w.u16(i as u16);
                w.u8(1);
                w.u8(m);
            }
            Cell::Mixed(_) => {
                w.u16(i as u16);
                w.u8(2);
                store.read_dense(b, &mut dense);
                w.0.extend_from_slice(&dense);
            }
        }
        n += 1;
    }
    w.0[count_at..count_at + 4].copy_from_slice(&n.to_le_bytes());
    let names = voxel.names();
    let present: Vec<(usize, Vec<usize>)> = (0..names.len())
        .map(|id| {
            let locals: Vec<usize> = (0..CHUNK_CELLS)
                .filter(|&i| voxel.get(id, key.brick(i)).is_some())
                .collect();
            (id, locals)
        })
        .filter(|(_, l)| !l.is_empty())
        .collect();
    w.u32(present.len() as u32);
    for (id, locals) in present {
        w.str(&names[id]);
        w.u32(locals.len() as u32);
        for i in locals {
            w.u16(i as u16);
            for v in voxel.get(id, key.brick(i)).expect("listed").iter() {
                w.0.extend_from_slice(&v.to_le_bytes());
            }
        }
    }
    w.0
}

/// Decode a chunk blob; `palette` colours mixed bricks' LOD colour.
pub fn decode_chunk(key: ChunkKey, blob: &[u8], palette: &Palette) -> Result<ChunkData, String> {
    decode_chunk_payload(key, &unseal(CHUNK_MAGIC, blob, MAX_CHUNK_PAYLOAD)?, palette)
}

/// Decode a chunk blob's payload (after the checksum and LZ4).
pub fn decode_chunk_payload(
    key: ChunkKey,
    payload: &[u8],
    palette: &Palette,
) -> Result<ChunkData, String> {
    let mut r = Reader::new(payload);
    let mut seen = [false; CHUNK_CELLS];
    let local = |r: &mut Reader, seen: &mut [bool; CHUNK_CELLS]| -> Result<usize, String> {
        let i = r.u16()? as usize;
        if i >= CHUNK_CELLS || std::mem::replace(&mut seen[i], true) {
            return Err(format!("brick index {i} is out of range or repeated"));
        }
        Ok(i)
    };
    let n = r.count(CHUNK_CELLS, "brick")?;
    let mut data = ChunkData::default();
    let mut dense = [0u8; BRICK_VOXELS];
    for _ in 0..n {
        let i = local(&mut r, &mut seen)?;
        let content = match read_brick(&mut r)? {
            RawBrick::Uniform(m) => BrickContent::Uniform(m),
            RawBrick::Dense(raw) => {
                dense.copy_from_slice(raw);
                BrickContent::from_dense(&dense, palette)
            }
        };
        data.bricks.push((key.brick(i), content));
    }
    let channels = r.count(MAX_CHANNELS, "channel")?;
    let mut names = FxHashSet::default();
    for _ in 0..channels {
        let name = r.str()?;
        if !names.insert(name.clone()) {
            return Err(format!("channel {name} appears twice"));
        }
        let m = r.count(CHUNK_CELLS, "channel brick")?;
        let mut seen = [false; CHUNK_CELLS];
        let mut arrays = Vec::with_capacity(m);
        for _ in 0..m {
            let i = local(&mut r, &mut seen)?;
            let raw = r.take(4 * BRICK_VOXELS)?;
            let mut v = Box::new([0f32; BRICK_VOXELS]);
            for (d, c) in v.iter_mut().zip(raw.chunks_exact(4)) {
                *d = f32::from_le_bytes(c.try_into().expect("4"));
            }
            arrays.push((key.brick(i), v));
        }
        data.voxel.push((name, arrays));
    }
    r.finish()?;
    Ok(data)
}

/// A stored brick as its blob holds it.
enum RawBrick<'a> {
    /// Every voxel of one material (never air).
    Uniform(u8),
    /// One material byte per voxel.
    Dense(&'a [u8]),
}

/// Read one brick's tag and materials.
fn read_brick<'a>(r: &mut Reader<'a>) -> Result<RawBrick<'a>, String> {
    match r.u8()? {
        1 => match r.u8()? {
            0 => Err("a uniform brick of material 0".into()),
            m => Ok(RawBrick::Uniform(m)),
        },
        2 => Ok(RawBrick::Dense(r.take(BRICK_VOXELS)?)),
        t => Err(format!("unknown brick tag {t}")),
    }
}

/// Mark in `held` every material a chunk blob's voxels hold (air
/// included where a brick is mixed), reading only its bricks: what a
/// scan of the store for materials still in use needs.
pub fn held_materials(blob: &[u8], held: &mut [bool; 256]) -> Result<(), String> {
    let payload = unseal(CHUNK_MAGIC, blob, MAX_CHUNK_PAYLOAD)?;
    let mut r = Reader::new(&payload);
    let n = r.count(CHUNK_CELLS, "brick")?;
    for _ in 0..n {
        let _index = r.u16()?;
        match read_brick(&mut r)? {
            RawBrick::Uniform(m) => held[m as usize] = true,
            RawBrick::Dense(raw) => raw.iter().for_each(|&m| held[m as usize] = true),
        }
    }
    Ok(())
}

/// Keep, of a blob's channels `(name, data)`, those whose names the
/// registry knows (`known`) and as many new ones as fit beside its
/// `registered` names under [`MAX_CHANNELS`]; returns the names dropped.
/// Each blob is bounded alone; this bounds them together, so that a store
/// of many blobs, each naming new channels, cannot grow a registry
/// without end (the column registry's ids are 16-bit).
///
/// ```
/// use brickworld::persist::chunk::{MAX_CHANNELS, fit_channels};
/// let mut ch = vec![("water".to_string(), 1), ("lava".to_string(), 2), ("sand".to_string(), 3)];
/// let dropped = fit_channels(&mut ch, |n| n == "water", MAX_CHANNELS - 1);
/// assert_eq!(dropped, ["sand"]);
/// assert_eq!(ch.iter().map(|c| c.1).collect::<Vec<_>>(), [1, 2]);
/// ```
pub fn fit_channels<T>(
    channels: &mut Vec<(String, T)>,
    known: impl Fn(&str) -> bool,
    registered: usize,
) -> Vec<String> {
    let mut room = MAX_CHANNELS.saturating_sub(registered);
    let mut dropped = Vec::new();
    channels.retain(|(name, _)| {
        if known(name) {
            true
        } else if room > 0 {
            room -= 1;
            true
        } else {
            dropped.push(name.clone());
            false
        }
    });
    dropped
}

/// Replace chunk `key` of `store` and `voxel` by `data` (bricks and channel
/// arrays the chunk does not hold are cleared). The edits are recorded in
/// the store's modified list like any other.
pub fn apply_chunk(
    key: ChunkKey,
    data: &ChunkData,
    store: &mut BrickStore,
    voxel: &mut VoxelChannels,
) {
    let mut keep = [false; CHUNK_CELLS];
    let local = |b: IVec3| {
        let l = b - key.min_brick();
        (l.x + 8 * l.y + 64 * l.z) as usize
    };
    for (b, _) in &data.bricks {
        keep[local(*b)] = true;
    }
    for i in 0..CHUNK_CELLS {
        let b = key.brick(i);
        if !keep[i] && store.cell(b) != Cell::Empty {
            store.set_brick(b, BrickContent::Empty);
        }
    }
    for (b, content) in &data.bricks {
        store.set_brick(*b, content.clone());
    }
    let zero = [0f32; BRICK_VOXELS];
    for id in 0..voxel.names().len() {
        for i in 0..CHUNK_CELLS {
            if voxel.get(id, key.brick(i)).is_some() {
                voxel.set(id, key.brick(i), &zero);
            }
        }
    }
    for (name, arrays) in &data.voxel {
        let id = voxel.channel(name);
        for (b, v) in arrays {
            voxel.set(id, *b, v);
        }
    }
}
