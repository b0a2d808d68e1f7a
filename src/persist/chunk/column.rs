//! Column blobs: the column simulation's per-tile channels of one chunk
//! column ([`ColumnKey`], 8×8 tiles), sealed like chunk blobs (magic
//! `BWCO`; the format is in the parent module's header).

use glam::IVec2;
use rustc_hash::FxHashSet;

use super::{ColumnKey, MAX_CHANNELS, seal, unseal};
use crate::persist::bytes::{Reader, Writer};
use crate::sim::ChannelStore;
use crate::sim::tile::TILE_CELLS;

/// The largest payload a column blob can decompress to.
const MAX_COLUMN_PAYLOAD: usize = 4 + MAX_CHANNELS * (8 + 256 + 64 * (1 + 8 * TILE_CELLS));

/// One column channel's values in a chunk column, by tile.
pub type TileArrays = Vec<(IVec2, Box<[f64; TILE_CELLS]>)>;

/// A decoded chunk column: per channel name, the tiles holding values.
#[derive(Clone, Debug, Default, PartialEq)]
pub struct ColumnData {
    /// Per channel name, (tile, values).
    pub channels: Vec<(String, TileArrays)>,
}

const COLUMN_MAGIC: &[u8; 4] = b"BWCO";

/// Encode chunk column `key` of the column channels.
pub fn encode_column(key: ColumnKey, channels: &ChannelStore) -> Vec<u8> {
    seal(COLUMN_MAGIC, &column_payload(key, channels))
}

/// A column blob's payload, before LZ4 and the checksum.
pub fn column_payload(key: ColumnKey, channels: &ChannelStore) -> Vec<u8> {
    let mut w = Writer::default();
    let present: Vec<(crate::sim::ChannelId, &str, Vec<usize>)> = channels
        .channels()
        .map(|(id, name)| {
            let tiles = (0..64)
                .filter(|&i| channels.get(key.tile(i), id).is_some())
                .collect();
            (id, name, tiles)
        })
        .filter(|(_, _, t): &(_, _, Vec<usize>)| !t.is_empty())
        .collect();
    w.u32(present.len() as u32);
    for (id, name, tiles) in present {
        w.str(name);
        w.u32(tiles.len() as u32);
        for i in tiles {
            w.u8(i as u8);
            for v in channels.get(key.tile(i), id).expect("listed").iter() {
                w.f64(*v);
            }
        }
    }
    w.0
}

/// Decode a chunk column blob.
pub fn decode_column(key: ColumnKey, blob: &[u8]) -> Result<ColumnData, String> {
    decode_column_payload(key, &unseal(COLUMN_MAGIC, blob, MAX_COLUMN_PAYLOAD)?)
}

/// Decode a column blob's payload (after the checksum and LZ4).
pub fn decode_column_payload(key: ColumnKey, payload: &[u8]) -> Result<ColumnData, String> {
    let mut r = Reader::new(payload);
    let n = r.count(MAX_CHANNELS, "channel")?;
    let mut data = ColumnData::default();
    let mut names = FxHashSet::default();
    for _ in 0..n {
        let name = r.str()?;
        if !names.insert(name.clone()) {
            return Err(format!("channel {name} appears twice"));
        }
        let m = r.count(64, "tile")?;
        let mut seen = [false; 64];
        let mut tiles = Vec::with_capacity(m);
        for _ in 0..m {
            let i = r.u8()? as usize;
            if i >= 64 || std::mem::replace(&mut seen[i], true) {
                return Err(format!("tile index {i} is out of range or repeated"));
            }
            let mut v = Box::new([0f64; TILE_CELLS]);
            for d in v.iter_mut() {
                *d = r.f64()?;
            }
            tiles.push((key.tile(i), v));
        }
        data.channels.push((name, tiles));
    }
    r.finish()?;
    Ok(data)
}

/// Replace the tiles of chunk column `key` that `keep` accepts by `data`'s
/// (those the column does not hold are cleared); the others are left as
/// they are.
pub fn apply_column(
    key: ColumnKey,
    data: &ColumnData,
    channels: &mut ChannelStore,
    keep: impl Fn(crate::sim::tile::TileCoord) -> bool,
) {
    let zero = [0f64; TILE_CELLS];
    let ids: Vec<crate::sim::ChannelId> = channels.channels().map(|(id, _)| id).collect();
    for id in ids {
        for i in 0..64 {
            if keep(key.tile(i)) && channels.get(key.tile(i), id).is_some() {
                channels.set(key.tile(i), id, &zero);
            }
        }
    }
    for (name, tiles) in &data.channels {
        let id = channels.channel(name);
        for (t, v) in tiles.iter().filter(|(t, _)| keep(*t)) {
            channels.set(*t, id, v);
        }
    }
}
