//! Crash-safe checkpoints of a whole world: bricks, simulation channels,
//! tick and script parameters.
//!
//! **File format** (`ckpt-<tick>.bwc`, little-endian):
//!
//! | bytes | field |
//! |---|---|
//! | 4 | magic `BWCK` |
//! | 4 | format version (1) |
//! | 8 | tick |
//! | 8 | world hash (bricks + channels), checked on load |
//! | 8 | compressed payload length |
//! | 4 | CRC-32 of the payload |
//! | 4 | CRC-32 of the 36 bytes above |
//! | … | payload: LZ4 (`lz4_flex`, size-prepended) of the state |
//!
//! **Writing** is atomic: a temp file is written and fsynced, renamed over
//! the final name, and the directory is fsynced. A `kill -9` at any moment
//! leaves either the old set of checkpoints or the new one, never a torn
//! file under a final name. The last two checkpoints are kept.
//!
//! **Loading** takes the newest checkpoint whose header, checksums and world
//! hash all verify; a corrupt one is reported and the previous one is used.

use std::fs::{self, File};
use std::io::Write;
use std::path::{Path, PathBuf};

use glam::{IVec2, IVec3};
use thiserror::Error;

use crate::sim::ChannelStore;
use crate::sim::tile::TILE_CELLS;
use crate::world::{BRICK_VOXELS, BrickContent, BrickStore, Palette};

const MAGIC: &[u8; 4] = b"BWCK";
const VERSION: u32 = 1;
const HEADER: usize = 40;
/// Checkpoints kept on disk.
pub const KEEP: usize = 2;

/// Errors of checkpointing.
#[derive(Debug, Error)]
pub enum CheckpointError {
    /// Reading or writing failed (a full disk, permissions…).
    #[error("checkpoint I/O on {}: {error}", path.display())]
    Io {
        /// The file or directory.
        path: PathBuf,
        /// The error.
        error: std::io::Error,
    },
    /// A checkpoint file is damaged.
    #[error("checkpoint {} is corrupt: {msg}", path.display())]
    Corrupt {
        /// The file.
        path: PathBuf,
        /// What failed to verify.
        msg: String,
    },
}

fn io(path: &Path, error: std::io::Error) -> CheckpointError {
    CheckpointError::Io {
        path: path.to_path_buf(),
        error,
    }
}

/// Everything a checkpoint holds.
#[derive(Debug)]
pub struct WorldState {
    /// Simulation tick.
    pub tick: u64,
    /// The voxels.
    pub store: BrickStore,
    /// Voxel bounds `[min, max)`.
    pub bounds: (IVec3, IVec3),
    /// Simulation channels.
    pub channels: ChannelStore,
    /// Script parameters: (script, [(name, value)]).
    pub params: Vec<(String, Vec<(String, f64)>)>,
}

/// Hash of the bricks (sorted by coordinate) and the channels.
pub fn world_hash(store: &BrickStore, channels: &ChannelStore) -> u64 {
    let mut keys: Vec<IVec3> = store.iter().map(|(b, _)| b).collect();
    keys.sort_by_key(|k| (k.z, k.y, k.x));
    let mut h = 0xcbf2_9ce4_8422_2325u64;
    let mut mix = |v: u64| {
        h ^= v;
        h = h.wrapping_mul(0x0100_0000_01b3);
    };
    let mut dense = [0u8; BRICK_VOXELS];
    for k in keys {
        mix(((k.x as u32 as u64) << 32) | k.y as u32 as u64);
        mix(k.z as u32 as u64);
        store.read_dense(k, &mut dense);
        for c in dense.chunks(8) {
            mix(u64::from_le_bytes(c.try_into().expect("8 bytes")));
        }
    }
    mix(channels.hash());
    h
}

struct Writer(Vec<u8>);

impl Writer {
    fn u32(&mut self, v: u32) {
        self.0.extend_from_slice(&v.to_le_bytes());
    }
    fn i32(&mut self, v: i32) {
        self.0.extend_from_slice(&v.to_le_bytes());
    }
    fn f64(&mut self, v: f64) {
        self.0.extend_from_slice(&v.to_le_bytes());
    }
    fn str(&mut self, s: &str) {
        self.u32(s.len() as u32);
        self.0.extend_from_slice(s.as_bytes());
    }
}

struct Reader<'a> {
    data: &'a [u8],
    at: usize,
}

impl Reader<'_> {
    fn take(&mut self, n: usize) -> Result<&[u8], String> {
        if self.at + n > self.data.len() {
            return Err(format!("payload ends early at byte {}", self.at));
        }
        let s = &self.data[self.at..self.at + n];
        self.at += n;
        Ok(s)
    }
    fn u32(&mut self) -> Result<u32, String> {
        Ok(u32::from_le_bytes(self.take(4)?.try_into().expect("4")))
    }
    fn i32(&mut self) -> Result<i32, String> {
        Ok(i32::from_le_bytes(self.take(4)?.try_into().expect("4")))
    }
    fn f64(&mut self) -> Result<f64, String> {
        Ok(f64::from_le_bytes(self.take(8)?.try_into().expect("8")))
    }
    fn str(&mut self) -> Result<String, String> {
        let n = self.u32()? as usize;
        String::from_utf8(self.take(n)?.to_vec()).map_err(|_| "a name is not UTF-8".to_string())
    }
    fn count(&mut self, max: usize, what: &str) -> Result<usize, String> {
        let n = self.u32()? as usize;
        if n > max {
            return Err(format!("{what} count {n} exceeds {max}"));
        }
        Ok(n)
    }
}

/// A world to checkpoint, borrowed from a running engine.
#[derive(Clone, Copy, Debug)]
pub struct WorldRef<'a> {
    /// Simulation tick.
    pub tick: u64,
    /// The voxels.
    pub store: &'a BrickStore,
    /// Voxel bounds `[min, max)`.
    pub bounds: (IVec3, IVec3),
    /// Simulation channels.
    pub channels: &'a ChannelStore,
    /// Script parameters.
    pub params: &'a [(String, Vec<(String, f64)>)],
}

fn encode(state: WorldRef<'_>) -> Vec<u8> {
    let mut w = Writer(Vec::new());
    for m in 0..=255u8 {
        w.0.extend_from_slice(&state.store.palette().rgb(m));
    }
    for v in [state.bounds.0, state.bounds.1] {
        w.i32(v.x);
        w.i32(v.y);
        w.i32(v.z);
    }
    let mut keys: Vec<IVec3> = state.store.iter().map(|(b, _)| b).collect();
    keys.sort_by_key(|k| (k.z, k.y, k.x));
    w.u32(keys.len() as u32);
    let mut dense = [0u8; BRICK_VOXELS];
    for k in keys {
        w.i32(k.x);
        w.i32(k.y);
        w.i32(k.z);
        state.store.read_dense(k, &mut dense);
        w.0.extend_from_slice(&dense);
    }
    let names: Vec<(crate::sim::ChannelId, String)> = state
        .channels
        .channels()
        .map(|(id, n)| (id, n.to_string()))
        .collect();
    w.u32(names.len() as u32);
    for (_, n) in &names {
        w.str(n);
    }
    let tiles = state.channels.tiles();
    w.u32(tiles.len() as u32);
    for t in tiles {
        w.i32(t.x);
        w.i32(t.y);
        let present: Vec<&(crate::sim::ChannelId, String)> = names
            .iter()
            .filter(|(id, _)| state.channels.get(t, *id).is_some())
            .collect();
        w.u32(present.len() as u32);
        for (id, _) in present {
            w.u32(id.index() as u32);
            for v in state.channels.get(t, *id).expect("present").iter() {
                w.f64(*v);
            }
        }
    }
    w.u32(state.params.len() as u32);
    for (script, ps) in state.params {
        w.str(script);
        w.u32(ps.len() as u32);
        for (n, v) in ps {
            w.str(n);
            w.f64(*v);
        }
    }
    w.0
}

fn decode(tick: u64, payload: &[u8]) -> Result<WorldState, String> {
    let mut r = Reader {
        data: payload,
        at: 0,
    };
    let mut colors = [[0u8; 3]; 256];
    for c in colors.iter_mut() {
        c.copy_from_slice(r.take(3)?);
    }
    let mut store = BrickStore::new(Palette::new(colors));
    let lo = IVec3::new(r.i32()?, r.i32()?, r.i32()?);
    let hi = IVec3::new(r.i32()?, r.i32()?, r.i32()?);
    let bricks = r.count(1 << 28, "brick")?;
    for _ in 0..bricks {
        let b = IVec3::new(r.i32()?, r.i32()?, r.i32()?);
        let dense: [u8; BRICK_VOXELS] = r.take(BRICK_VOXELS)?.try_into().expect("512 bytes");
        let content = BrickContent::from_dense(&dense, store.palette());
        store.set_brick(b, content);
    }
    store.take_modified();
    let mut channels = ChannelStore::default();
    let n = r.count(4096, "channel")?;
    let ids: Vec<crate::sim::ChannelId> = (0..n)
        .map(|_| r.str().map(|s| channels.channel(&s)))
        .collect::<Result<_, _>>()?;
    let tiles = r.count(1 << 28, "tile")?;
    for _ in 0..tiles {
        let t = IVec2::new(r.i32()?, r.i32()?);
        let k = r.count(n, "channel in a tile")?;
        for _ in 0..k {
            let c = r.u32()? as usize;
            let id = *ids
                .get(c)
                .ok_or_else(|| format!("channel index {c} out of range"))?;
            let mut d = [0.0; TILE_CELLS];
            for v in d.iter_mut() {
                *v = r.f64()?;
            }
            channels.set(t, id, &d);
        }
    }
    let scripts = r.count(1024, "script")?;
    let mut params = Vec::new();
    for _ in 0..scripts {
        let name = r.str()?;
        let k = r.count(1024, "parameter")?;
        let mut ps = Vec::new();
        for _ in 0..k {
            ps.push((r.str()?, r.f64()?));
        }
        params.push((name, ps));
    }
    if r.at != payload.len() {
        return Err(format!(
            "{} unexpected bytes after the state",
            payload.len() - r.at
        ));
    }
    Ok(WorldState {
        tick,
        store,
        bounds: (lo, hi),
        channels,
        params,
    })
}

fn file_name(tick: u64) -> String {
    format!("ckpt-{tick:016}.bwc")
}

/// The checkpoint files in `dir`, newest first.
pub fn list(dir: &Path) -> Result<Vec<PathBuf>, CheckpointError> {
    let mut out: Vec<PathBuf> = match fs::read_dir(dir) {
        Ok(rd) => rd
            .filter_map(|e| e.ok().map(|e| e.path()))
            .filter(|p| {
                p.file_name()
                    .and_then(|n| n.to_str())
                    .is_some_and(|n| n.starts_with("ckpt-") && n.ends_with(".bwc"))
            })
            .collect(),
        Err(e) if e.kind() == std::io::ErrorKind::NotFound => Vec::new(),
        Err(e) => return Err(io(dir, e)),
    };
    out.sort();
    out.reverse();
    Ok(out)
}

/// Write a checkpoint of `state` into `dir` atomically and keep the newest
/// [`KEEP`]. Returns its path and world hash. On any error (a full disk, say)
/// the previous checkpoints are untouched.
pub fn write(dir: &Path, state: &WorldState) -> Result<(PathBuf, u64), CheckpointError> {
    write_ref(
        dir,
        WorldRef {
            tick: state.tick,
            store: &state.store,
            bounds: state.bounds,
            channels: &state.channels,
            params: &state.params,
        },
    )
}

/// [`write`] for a world borrowed from a running engine.
pub fn write_ref(dir: &Path, state: WorldRef<'_>) -> Result<(PathBuf, u64), CheckpointError> {
    fs::create_dir_all(dir).map_err(|e| io(dir, e))?;
    let hash = world_hash(state.store, state.channels);
    let payload = lz4_flex::compress_prepend_size(&encode(state));
    let mut header = Vec::with_capacity(HEADER);
    header.extend_from_slice(MAGIC);
    header.extend_from_slice(&VERSION.to_le_bytes());
    header.extend_from_slice(&state.tick.to_le_bytes());
    header.extend_from_slice(&hash.to_le_bytes());
    header.extend_from_slice(&(payload.len() as u64).to_le_bytes());
    header.extend_from_slice(&crc32fast::hash(&payload).to_le_bytes());
    let hcrc = crc32fast::hash(&header);
    header.extend_from_slice(&hcrc.to_le_bytes());
    let path = dir.join(file_name(state.tick));
    let tmp = dir.join(format!(".{}.tmp", file_name(state.tick)));
    let result = (|| -> std::io::Result<()> {
        let mut f = File::create(&tmp)?;
        f.write_all(&header)?;
        match write_stall() {
            // Test hook: stop half-way through the payload so a test can
            // kill -9 the process in the middle of a write.
            Some(stall) => {
                let half = payload.len() / 2;
                f.write_all(&payload[..half])?;
                f.sync_all()?;
                std::thread::sleep(stall);
                f.write_all(&payload[half..])?;
            }
            None => f.write_all(&payload)?,
        }
        f.sync_all()?;
        fs::rename(&tmp, &path)?;
        File::open(dir)?.sync_all()
    })();
    if let Err(e) = result {
        let _ = fs::remove_file(&tmp);
        return Err(io(&path, e));
    }
    for old in list(dir)?.into_iter().skip(KEEP) {
        let _ = fs::remove_file(old);
    }
    // Temp files left by a process killed mid-write never load; drop them.
    if let Ok(rd) = fs::read_dir(dir) {
        for e in rd.flatten() {
            let n = e.file_name();
            let n = n.to_string_lossy();
            if n.starts_with(".ckpt-") && n.ends_with(".tmp") {
                let _ = fs::remove_file(e.path());
            }
        }
    }
    Ok((path, hash))
}

/// `BRICKWORLD_TEST_CHECKPOINT_STALL_MS`: a pause half-way through writing
/// each checkpoint's temp file, so the crash tests can kill the process
/// mid-write. Unset in normal use.
fn write_stall() -> Option<std::time::Duration> {
    std::env::var("BRICKWORLD_TEST_CHECKPOINT_STALL_MS")
        .ok()
        .and_then(|v| v.parse().ok())
        .map(std::time::Duration::from_millis)
}

/// Read and verify one checkpoint file.
pub fn read(path: &Path) -> Result<WorldState, CheckpointError> {
    let corrupt = |msg: String| CheckpointError::Corrupt {
        path: path.to_path_buf(),
        msg,
    };
    let bytes = fs::read(path).map_err(|e| io(path, e))?;
    if bytes.len() < HEADER {
        return Err(corrupt(format!(
            "{} bytes is shorter than the header",
            bytes.len()
        )));
    }
    let h = &bytes[..HEADER];
    if &h[0..4] != MAGIC {
        return Err(corrupt("not a brickworld checkpoint (bad magic)".into()));
    }
    if crc32fast::hash(&h[..36]) != u32::from_le_bytes(h[36..40].try_into().expect("4")) {
        return Err(corrupt("header checksum mismatch".into()));
    }
    let version = u32::from_le_bytes(h[4..8].try_into().expect("4"));
    if version != VERSION {
        return Err(corrupt(format!(
            "format version {version}, this build reads {VERSION}"
        )));
    }
    let tick = u64::from_le_bytes(h[8..16].try_into().expect("8"));
    let hash = u64::from_le_bytes(h[16..24].try_into().expect("8"));
    let len = u64::from_le_bytes(h[24..32].try_into().expect("8")) as usize;
    let crc = u32::from_le_bytes(h[32..36].try_into().expect("4"));
    let payload = &bytes[HEADER..];
    if payload.len() != len {
        return Err(corrupt(format!(
            "payload is {} bytes, the header says {len}",
            payload.len()
        )));
    }
    if crc32fast::hash(payload) != crc {
        return Err(corrupt("payload checksum mismatch".into()));
    }
    let raw =
        lz4_flex::decompress_size_prepended(payload).map_err(|e| corrupt(format!("LZ4: {e}")))?;
    let state = decode(tick, &raw).map_err(corrupt)?;
    let got = world_hash(&state.store, &state.channels);
    if got != hash {
        return Err(corrupt(format!(
            "world hash {got:#x} differs from the recorded {hash:#x}"
        )));
    }
    Ok(state)
}

/// What [`latest`] found.
#[derive(Debug)]
pub struct Latest {
    /// The newest checkpoint that verified, and its state.
    pub found: Option<(PathBuf, WorldState)>,
    /// Newer checkpoints that failed to verify (to report).
    pub skipped: Vec<CheckpointError>,
}

/// The newest checkpoint in `dir` that verifies, with the problems of any
/// newer ones skipped on the way.
pub fn latest(dir: &Path) -> Result<Latest, CheckpointError> {
    let mut skipped = Vec::new();
    for path in list(dir)? {
        match read(&path) {
            Ok(s) => {
                return Ok(Latest {
                    found: Some((path, s)),
                    skipped,
                });
            }
            Err(e) => skipped.push(e),
        }
    }
    Ok(Latest {
        found: None,
        skipped,
    })
}
