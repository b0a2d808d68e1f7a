//! Whole-world checkpoint files: bricks, simulation channels, tick, script
//! parameters, and everything else that defines the world's future (the
//! drained total, which tiles sleep), under the identity of the world they
//! belong to.
//!
//! Since issue 10 the engine persists to the chunked world store
//! ([`crate::persist`]), committing only what changed. This format lives on
//! as the **single-file backup** of `brickworld export` / `import`, as the
//! payload of the store's simulation-state blob (with no bricks), and as the
//! state directories of earlier versions, which are migrated into the store
//! on their first start (`engine::backup::migrate_legacy`).
//!
//! **File format** (`ckpt-<tick>.bwc`, little-endian):
//!
//! | bytes | field |
//! |---|---|
//! | 4 | magic `BWCK` |
//! | 4 | format version (6; versions 1 to 5 are still read) |
//! | 8 | tick |
//! | 8 | world hash (bricks + channels; XXH3 since 6, FNV-1a over words before, channels by id before 5), checked on load |
//! | 8 | compressed payload length |
//! | 4 | CRC-32 of the payload |
//! | 4 | CRC-32 of the 36 bytes above |
//! | 4 + n + 4 | (v2) identity: length, JSON [`WorldIdentity`], CRC-32 |
//! | … | payload: LZ4 (`lz4_flex`, size-prepended) of the state |
//!
//! **Writing** is atomic: a temp file is written and fsynced, renamed over
//! the final name, and the directory is fsynced. A `kill -9` at any moment
//! leaves either the old set of checkpoints or the new one, never a torn
//! file under a final name.
//!
//! **Retention** ([`Checkpoints`]) keeps the newest [`KEEP`] checkpoints of
//! *this* world that verified (written by this process, or checked when it
//! started); the file just written is always one of them. A corrupt file is
//! renamed `*.corrupt` (kept for inspection, never counted), and a foreign
//! world's checkpoint is left alone: neither can take a slot.
//!
//! **Loading** takes the newest checkpoint of this world whose header,
//! checksums and world hash all verify; a corrupt one is reported and the
//! previous one is used; another world's is skipped with a warning.

//!
//! The parts: [`payload`] encodes and decodes the state itself, [`file`](mod@file)
//! frames it as one verified file, and [`dir`] keeps a state directory's
//! set of them.

use std::path::{Path, PathBuf};

use glam::IVec3;
use thiserror::Error;

use crate::persist::bytes::{Mixing, StateHasher};
use crate::sim::ChannelStore;
use crate::world::{BRICK_VOXELS, BrickStore};

pub mod dir;
pub mod file;
pub mod landing;
pub mod payload;

pub use dir::{Checkpoints, Latest, Opened, latest, list, write};
pub use file::{parse, read, write_at};
pub use landing::{BackupTarget, backup_target, write_backup};
pub(crate) use payload::encode;
pub use payload::{MAX_TICK, decode};

const MAGIC: &[u8; 4] = b"BWCK";
/// 4: a trailing section with the scripts' health (tag 2) may follow.
/// 5: the header's world hash takes channels by name, in name order, and
/// only those holding data; files of 1 to 4 are checked against the hash
/// they were written with ([`world_hash_by_id`]).
/// 6: the same words mixed by XXH3 ([`world_hash`]); files of 5 are checked
/// against FNV-1a's ([`world_hash_v5`]).
const VERSION: u32 = 6;
/// Largest LZ4 expansion (LZ4's worst-case ratio is about 255:1): a size
/// prefix claiming more is corrupt, refused before anything is allocated.
const MAX_LZ4_RATIO: usize = 255;
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
    /// A file that is not a checkpoint at all: another kind of file.
    #[error("{} is not a brickworld checkpoint or backup (it does not begin with BWCK): `brickworld export` makes backups, and a world store (world.redb) is copied, not imported", path.display())]
    NotACheckpoint {
        /// The file.
        path: PathBuf,
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

/// Which world a checkpoint belongs to.
#[derive(Clone, Debug, PartialEq, Eq, serde::Serialize, serde::Deserialize)]
#[serde(deny_unknown_fields)]
pub struct WorldIdentity {
    /// The world's source, as the config writes it (`terrain`, `vox:…`).
    pub source: String,
    /// The world's size.
    pub size: [i32; 3],
    /// The world's seed.
    pub seed: u64,
    /// A hash of the config text: a change is reported, not refused (a
    /// world may be given new scripts or frame settings).
    pub config_hash: u64,
}

impl WorldIdentity {
    /// Whether `other` is the same world (source, size and seed).
    pub fn same_world(&self, other: &WorldIdentity) -> bool {
        self.source == other.source && self.size == other.size && self.seed == other.seed
    }
}

impl std::fmt::Display for WorldIdentity {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        write!(
            f,
            "{} {}x{}x{} seed {}",
            self.source, self.size[0], self.size[1], self.size[2], self.seed
        )
    }
}

/// The voxel grid's awake bricks and their quiet counters.
pub type VoxelSleep = (Vec<IVec3>, Vec<(IVec3, u8)>);

/// A camera set through the control API (`/camera`). It replaces the
/// configured camera path, and a simulation region that follows the camera
/// follows it, so a resume must restore it.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct CameraOverride {
    /// Eye.
    pub eye: [f64; 3],
    /// Look-at point.
    pub target: [f64; 3],
    /// Vertical field of view, degrees.
    pub fov: f64,
}

/// Simulation state beyond the channels that a resume needs to continue
/// exactly as if it had not stopped.
#[derive(Clone, Debug, Default, PartialEq)]
pub struct SimExtras {
    /// Water drained over the world's edges so far.
    pub drained: f64,
    /// Which tiles sleep (None in version-1 files: everything wakes).
    pub sleep: Option<crate::sim::step::SleepState>,
    /// The voxel scripts' per-voxel channels (empty before version 3).
    pub voxel_channels: crate::sim::voxels::VoxelChannels,
    /// The voxel grid's awake bricks and quiet counters (None before
    /// version 3: every brick wakes).
    pub voxel_sleep: Option<VoxelSleep>,
    /// The material registry: (id, name, kind, density); colours are the
    /// palette's. Empty before version 3 (names are then derived).
    pub materials: Vec<(u8, String, crate::world::MaterialKind, f32)>,
    /// The camera set through `/camera`, if any (an optional trailing
    /// section: states without one read as before).
    pub camera: Option<CameraOverride>,
    /// Scripts that were failing or suspended (an optional trailing
    /// section; empty when every script was healthy).
    pub health: Vec<ScriptHealth>,
    /// Every script's name and the [`fnv1a`](crate::persist::bytes::fnv1a)
    /// of the source it ran (an optional trailing section; empty in states
    /// written before it): a resume wakes what a script whose file changed
    /// while the engine was stopped runs on, as a hot reload does.
    pub sources: Vec<(String, u64)>,
}

/// A failing or suspended script's health at a commit. A resume restores
/// it, so a suspended script stays suspended and a failing one goes on
/// counting, as in a run that never stopped; but only if the script's
/// source is unchanged: a changed source is a reload, which clears it.
#[derive(Clone, Debug, PartialEq)]
pub struct ScriptHealth {
    /// Script name.
    pub script: String,
    /// [`fnv1a`](crate::persist::bytes::fnv1a) of the source it ran.
    pub source: u64,
    /// Failed steps in a row.
    pub failures: u32,
    /// Why it is suspended (the error's text), if it is.
    pub suspended: Option<String>,
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
    /// The world it belongs to (None in version-1 files).
    pub identity: Option<WorldIdentity>,
    /// The rest of the simulation state.
    pub extras: SimExtras,
}

/// Hash of the bricks (sorted by coordinate) and the channels.
pub fn world_hash(store: &BrickStore, channels: &ChannelStore) -> u64 {
    bricks_hash(store, channels.hash(), Mixing::Xxh3)
}

/// [`world_hash`] as format version 5 recorded it: the same words, mixed
/// by FNV-1a ([`Mixing::Words`]). Kept to check those files.
pub fn world_hash_v5(store: &BrickStore, channels: &ChannelStore) -> u64 {
    bricks_hash(store, channels.hash_with(Mixing::Words), Mixing::Words)
}

/// [`world_hash`] as format versions 1 to 4 recorded it: the channels
/// hashed by id ([`ChannelStore::hash_by_id`]), mixed by FNV-1a. Kept to
/// check those files (regression, hostile probe: when the hash came to
/// take channels by name, every earlier backup was called corrupt).
pub fn world_hash_by_id(store: &BrickStore, channels: &ChannelStore) -> u64 {
    bricks_hash(store, channels.hash_by_id(), Mixing::Words)
}

/// The bricks (sorted by coordinate) hashed, then `channels`.
fn bricks_hash(store: &BrickStore, channels: u64, mixing: Mixing) -> u64 {
    let mut keys: Vec<IVec3> = store.iter().map(|(b, _)| b).collect();
    keys.sort_by_key(|k| (k.z, k.y, k.x));
    let mut h = StateHasher::new(mixing);
    let mut dense = [0u8; BRICK_VOXELS];
    for k in keys {
        h.word(((k.x as u32 as u64) << 32) | k.y as u32 as u64);
        h.word(k.z as u32 as u64);
        store.read_dense(k, &mut dense);
        h.words(&dense);
    }
    h.word(channels);
    h.finish()
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
    /// The world it belongs to.
    pub identity: Option<&'a WorldIdentity>,
    /// The rest of the simulation state.
    pub extras: &'a SimExtras,
}
