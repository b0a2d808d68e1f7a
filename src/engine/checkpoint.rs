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
//! on their first start (`engine::persistence::migrate_legacy`).
//!
//! **File format** (`ckpt-<tick>.bwc`, little-endian):
//!
//! | bytes | field |
//! |---|---|
//! | 4 | magic `BWCK` |
//! | 4 | format version (3; versions 1 and 2 are still read) |
//! | 8 | tick |
//! | 8 | world hash (bricks + channels), checked on load |
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

use std::fs::{self, File};
use std::io::Write;
use std::path::{Path, PathBuf};

use glam::{IVec2, IVec3};
use thiserror::Error;

use crate::persist::bytes::{Reader, Writer};
use crate::sim::ChannelStore;
use crate::sim::tile::TILE_CELLS;
use crate::world::{BRICK_VOXELS, BrickContent, BrickStore, Palette};

const MAGIC: &[u8; 4] = b"BWCK";
/// 4: a trailing section with the scripts' health (tag 2) may follow.
const VERSION: u32 = 4;
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

pub(crate) fn encode(state: WorldRef<'_>) -> Vec<u8> {
    let mut w = Writer::default();
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
    // Version 2: the rest of the simulation state.
    w.f64(state.extras.drained);
    match &state.extras.sleep {
        None => w.u32(0),
        Some(sl) => {
            w.u32(1);
            w.u32(sl.active.len() as u32);
            for t in &sl.active {
                w.i32(t.x);
                w.i32(t.y);
            }
            w.u32(sl.quiet.len() as u32);
            for (t, q) in &sl.quiet {
                w.i32(t.x);
                w.i32(t.y);
                w.0.push(*q);
            }
        }
    }
    // Version 3: the voxel scripts' channels.
    let vc = &state.extras.voxel_channels;
    w.u32(vc.names().len() as u32);
    for (id, name) in vc.names().iter().enumerate() {
        w.str(name);
        let bricks = vc.sorted_bricks(id);
        w.u32(bricks.len() as u32);
        for b in bricks {
            w.i32(b.x);
            w.i32(b.y);
            w.i32(b.z);
            for v in vc.get(id, b).expect("listed").iter() {
                w.0.extend_from_slice(&v.to_le_bytes());
            }
        }
    }
    w.u32(state.extras.materials.len() as u32);
    for (id, name, kind, density) in &state.extras.materials {
        w.0.push(*id);
        w.str(name);
        w.0.push(*kind as u8);
        w.0.extend_from_slice(&density.to_le_bytes());
    }
    match &state.extras.voxel_sleep {
        None => w.u32(0),
        Some((active, quiet)) => {
            w.u32(1);
            w.u32(active.len() as u32);
            for b in active {
                w.i32(b.x);
                w.i32(b.y);
                w.i32(b.z);
            }
            w.u32(quiet.len() as u32);
            for (b, q) in quiet {
                w.i32(b.x);
                w.i32(b.y);
                w.i32(b.z);
                w.0.push(*q);
            }
        }
    }
    // Optional trailing sections, each behind its tag.
    if let Some(c) = &state.extras.camera {
        w.u32(SECTION_CAMERA);
        for v in c.eye.iter().chain(&c.target).chain([&c.fov]) {
            w.f64(*v);
        }
    }
    if !state.extras.health.is_empty() {
        w.u32(SECTION_HEALTH);
        w.u32(state.extras.health.len() as u32);
        for h in &state.extras.health {
            w.str(&h.script);
            w.u64(h.source);
            w.u32(h.failures);
            match &h.suspended {
                None => w.u8(0),
                Some(why) => {
                    w.u8(1);
                    w.str(why);
                }
            }
        }
    }
    w.0
}

/// Tags of the optional sections that may follow a state.
const SECTION_CAMERA: u32 = 1;
const SECTION_HEALTH: u32 = 2;

/// Highest tick a stored state may claim: 2^53, where a tick stops being
/// exact as the `f64` of simulated time (285 000 years at 1 000 ticks a
/// second). A larger one is forged or corrupt.
pub const MAX_TICK: u64 = 1 << 53;

/// Decode a decompressed payload of format `version` (1 to 4). Never
/// panics, whatever the bytes: every count is checked against what is left,
/// and a tick past [`MAX_TICK`] is refused.
pub fn decode(tick: u64, version: u32, payload: &[u8]) -> Result<WorldState, String> {
    if tick > MAX_TICK {
        // A forged tick near u64::MAX wrapped on the next step (regression).
        return Err(format!(
            "tick {tick} is past 2^53, which no world reaches: the file is forged or corrupt"
        ));
    }
    let mut r = Reader::new(payload);
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
    let n = r.count(crate::sim::MAX_CHANNELS, "channel")?;
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
    let mut extras = SimExtras::default();
    if version >= 2 {
        extras.drained = r.f64()?;
        if r.u32()? == 1 {
            let left = |r: &Reader, per: usize| (r.data.len() - r.at) / per;
            let n = r.count(left(&r, 8), "awake tile")?;
            let mut active = Vec::with_capacity(n);
            for _ in 0..n {
                active.push(IVec2::new(r.i32()?, r.i32()?));
            }
            let n = r.count(left(&r, 9), "quiet tile")?;
            let mut quiet = Vec::with_capacity(n);
            for _ in 0..n {
                quiet.push((IVec2::new(r.i32()?, r.i32()?), r.take(1)?[0]));
            }
            extras.sleep = Some(crate::sim::step::SleepState { active, quiet });
        }
    }
    if version >= 3 {
        let n = r.count(crate::sim::MAX_CHANNELS, "voxel channel")?;
        for _ in 0..n {
            let name = r.str()?;
            let id = extras.voxel_channels.channel(&name);
            let left = (r.data.len() - r.at) / (12 + 2048);
            let k = r.count(left, "voxel channel brick")?;
            for _ in 0..k {
                let b = IVec3::new(r.i32()?, r.i32()?, r.i32()?);
                let raw = r.take(2048)?;
                let v: [f32; 512] = std::array::from_fn(|i| {
                    f32::from_le_bytes(raw[i * 4..i * 4 + 4].try_into().expect("4"))
                });
                extras.voxel_channels.set(id, b, &v);
            }
        }
        let n = r.count(256, "material")?;
        for _ in 0..n {
            let id = r.take(1)?[0];
            let name = r.str()?;
            let kind = match r.take(1)?[0] {
                0 => crate::world::MaterialKind::Solid,
                1 => crate::world::MaterialKind::Liquid,
                2 => crate::world::MaterialKind::Granular,
                3 => crate::world::MaterialKind::Gas,
                k => return Err(format!("material kind {k} is unknown")),
            };
            let density = f32::from_le_bytes(r.take(4)?.try_into().expect("4"));
            extras.materials.push((id, name, kind, density));
        }
        if r.u32()? == 1 {
            let left = |r: &Reader, per: usize| (r.data.len() - r.at) / per;
            let n = r.count(left(&r, 12), "awake brick")?;
            let mut active = Vec::with_capacity(n);
            for _ in 0..n {
                active.push(IVec3::new(r.i32()?, r.i32()?, r.i32()?));
            }
            let n = r.count(left(&r, 13), "quiet brick")?;
            let mut quiet = Vec::with_capacity(n);
            for _ in 0..n {
                quiet.push((IVec3::new(r.i32()?, r.i32()?, r.i32()?), r.take(1)?[0]));
            }
            extras.voxel_sleep = Some((active, quiet));
        }
        let (mut camera, mut health) = (false, false);
        while r.at < payload.len() {
            match r.u32()? {
                SECTION_CAMERA if !camera => {
                    camera = true;
                    extras.camera = Some(read_camera(&mut r)?)
                }
                SECTION_HEALTH if !health && version >= 4 => {
                    health = true;
                    extras.health = read_health(&mut r)?
                }
                tag => {
                    return Err(format!(
                        "section {tag} after the state is unknown or repeated"
                    ));
                }
            }
        }
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
        identity: None,
        extras,
    })
}

fn read_camera(r: &mut Reader) -> Result<CameraOverride, String> {
    let mut v = [0f64; 7];
    for x in v.iter_mut() {
        *x = r.f64()?;
    }
    if v.iter().any(|x| !x.is_finite()) || !(v[6] > 0.0 && v[6] < 180.0) {
        return Err(
            "the stored camera is not finite or its field of view is outside (0, 180)".into(),
        );
    }
    Ok(CameraOverride {
        eye: [v[0], v[1], v[2]],
        target: [v[3], v[4], v[5]],
        fov: v[6],
    })
}

/// The most failures in a row a stored health may claim (a script is
/// suspended after a few; far more is a damaged or forged state).
const MAX_STORED_FAILURES: u32 = 1 << 20;

fn read_health(r: &mut Reader) -> Result<Vec<ScriptHealth>, String> {
    let n = r.count(1024, "script health")?;
    let mut health: Vec<ScriptHealth> = Vec::with_capacity(n);
    for _ in 0..n {
        let script = r.str()?;
        let source = r.u64()?;
        let failures = r.u32()?;
        let suspended = match r.u8()? {
            0 => None,
            1 => Some(r.str()?),
            f => {
                return Err(format!(
                    "script {script}'s suspension flag is {f}, not 0 or 1"
                ));
            }
        };
        // Only failing or suspended scripts are stored, once each; a
        // streak long enough to suspend is stored suspended.
        let limit =
            crate::sim::columns::step::SUSPEND_AFTER.min(crate::sim::voxels::step::SUSPEND_AFTER);
        if failures == 0
            || failures > MAX_STORED_FAILURES
            || (suspended.is_none() && failures >= limit)
            || health.iter().any(|h| h.script == script)
        {
            return Err(format!(
                "script {script}'s stored health ({failures} failures in a row, {}) is not one a run can leave",
                if suspended.is_some() {
                    "suspended"
                } else {
                    "not suspended"
                }
            ));
        }
        health.push(ScriptHealth {
            script,
            source,
            failures,
            suspended,
        });
    }
    Ok(health)
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

/// Write a checkpoint of `state` into `dir` atomically, keeping the newest
/// [`KEEP`] that verify (see [`Checkpoints`]). Returns its path and world
/// hash. On any error (a full disk, say) the previous checkpoints are
/// untouched.
pub fn write(dir: &Path, state: &WorldState) -> Result<(PathBuf, u64), CheckpointError> {
    let mut set = Checkpoints::scan(dir, state.identity.clone())?;
    set.write(WorldRef {
        tick: state.tick,
        store: &state.store,
        bounds: state.bounds,
        channels: &state.channels,
        params: &state.params,
        identity: state.identity.as_ref(),
        extras: &state.extras,
    })
}

/// What [`Checkpoints::open`] returns: the set, the newest of this world's
/// checkpoints that verified (with its path), and warnings to show.
pub type Opened = (Checkpoints, Option<(PathBuf, WorldState)>, Vec<String>);

/// A state directory's checkpoints, as one engine sees them: which files
/// verified as this world's, so retention never counts a corrupt, foreign
/// or stray file, and never deletes the file it just wrote.
#[derive(Debug)]
pub struct Checkpoints {
    dir: PathBuf,
    identity: Option<WorldIdentity>,
    /// This world's verified checkpoints, oldest first.
    good: Vec<PathBuf>,
}

impl Checkpoints {
    /// Scan `dir`: files whose header, identity and payload checksum verify
    /// (and belong to `identity`, when given) count for retention; corrupt
    /// files are renamed `*.corrupt`; foreign ones are left alone.
    pub fn scan(dir: &Path, identity: Option<WorldIdentity>) -> Result<Self, CheckpointError> {
        let mut good = Vec::new();
        for path in list(dir)?.into_iter().rev() {
            match read_checked(&path, false) {
                Ok((_, id)) if matches_world(identity.as_ref(), id.as_ref()) => good.push(path),
                Ok(_) => {}
                Err(CheckpointError::Corrupt { .. }) => quarantine(&path),
                Err(_) => {}
            }
        }
        Ok(Checkpoints {
            dir: dir.to_path_buf(),
            identity,
            good,
        })
    }

    /// The newest checkpoint of this world that fully verifies, with the
    /// problems met on the way (newer corrupt files, renamed `*.corrupt`,
    /// and other worlds' checkpoints, skipped). Files found good count for
    /// retention.
    pub fn open(dir: &Path, identity: WorldIdentity) -> Result<Opened, CheckpointError> {
        let mut warnings = Vec::new();
        let mut found = None;
        let mut good = Vec::new();
        for path in list(dir)? {
            if found.is_some() {
                // Older files: a cheap check is enough to count them.
                if let Ok((_, id)) = read_checked(&path, false)
                    && matches_world(Some(&identity), id.as_ref())
                {
                    good.push(path);
                }
                continue;
            }
            match read(&path) {
                Ok(st) => match &st.identity {
                    Some(id) if !id.same_world(&identity) => warnings.push(format!(
                        "{} belongs to another world ({id}, this is {identity}); skipped and left alone",
                        path.display()
                    )),
                    id => {
                        match id {
                            None => warnings.push(format!(
                                "{} predates world identities (format 1); assuming it is this world",
                                path.display()
                            )),
                            Some(id) if id.config_hash != identity.config_hash => warnings.push(format!(
                                "the world config changed since {} was written; resuming with the new config",
                                path.display()
                            )),
                            Some(_) => {}
                        }
                        good.push(path.clone());
                        found = Some((path, st));
                    }
                },
                Err(e @ CheckpointError::Corrupt { .. }) => {
                    warnings.push(format!("{e}; renamed to *.corrupt and skipped"));
                    quarantine(&path);
                }
                Err(e) => warnings.push(format!("{e}; skipped")),
            }
        }
        good.reverse();
        Ok((
            Checkpoints {
                dir: dir.to_path_buf(),
                identity: Some(identity),
                good,
            },
            found,
            warnings,
        ))
    }

    /// The verified checkpoints retention counts, oldest first.
    pub fn good(&self) -> &[PathBuf] {
        &self.good
    }

    /// Write a checkpoint atomically, then delete this world's verified
    /// checkpoints beyond the newest [`KEEP`] (never the one just written).
    pub fn write(&mut self, state: WorldRef<'_>) -> Result<(PathBuf, u64), CheckpointError> {
        let state = WorldRef {
            identity: state.identity.or(self.identity.as_ref()),
            ..state
        };
        let (path, hash) = write_file(&self.dir, state)?;
        self.good.retain(|p| p != &path);
        self.good.push(path.clone());
        while self.good.len() > KEEP {
            let old = self.good.remove(0);
            let _ = fs::remove_file(old);
        }
        Ok((path, hash))
    }
}

fn matches_world(want: Option<&WorldIdentity>, got: Option<&WorldIdentity>) -> bool {
    match (want, got) {
        (Some(w), Some(g)) => w.same_world(g),
        _ => true,
    }
}

/// Rename a corrupt checkpoint out of the way (kept for inspection).
fn quarantine(path: &Path) {
    let mut to = path.as_os_str().to_owned();
    to.push(".corrupt");
    let _ = fs::rename(path, PathBuf::from(to));
}

fn write_file(dir: &Path, state: WorldRef<'_>) -> Result<(PathBuf, u64), CheckpointError> {
    fs::create_dir_all(dir).map_err(|e| io(dir, e))?;
    let path = dir.join(file_name(state.tick));
    let hash = write_at(&path, state)?;
    Ok((path, hash))
}

/// Write a checkpoint file at `path` (atomically: a temp file beside it,
/// fsynced, renamed, the directory fsynced). Returns the world hash. This is
/// also `brickworld export`'s single-file backup.
pub fn write_at(path: &Path, state: WorldRef<'_>) -> Result<u64, CheckpointError> {
    let dir = match path.parent() {
        Some(d) if !d.as_os_str().is_empty() => d,
        _ => Path::new("."),
    };
    let name = path
        .file_name()
        .map(|n| n.to_string_lossy().to_string())
        .unwrap_or_else(|| "backup.bwc".into());
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
    let id = serde_json::to_vec(&state.identity).unwrap_or_else(|_| b"null".to_vec());
    header.extend_from_slice(&(id.len() as u32).to_le_bytes());
    header.extend_from_slice(&id);
    header.extend_from_slice(&crc32fast::hash(&id).to_le_bytes());
    let tmp = dir.join(format!(".{name}.tmp"));
    let result = (|| -> std::io::Result<()> {
        let mut f = File::create(&tmp)?;
        f.write_all(&header)?;
        f.write_all(&payload)?;
        f.sync_all()?;
        fs::rename(&tmp, path)
    })();
    if let Err(e) = result {
        let _ = fs::remove_file(&tmp);
        return Err(io(path, e));
    }
    // The file has landed under its final name: it is this checkpoint, and
    // retention must count it even if the directory's fsync fails (out of
    // descriptors, say; regression: such files were orphaned for ever).
    if let Err(e) = File::open(dir).and_then(|d| d.sync_all()) {
        eprintln!(
            "warning: checkpoint {} written, but syncing its directory failed: {e}",
            path.display()
        );
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
    Ok(hash)
}

/// Header, identity and payload checksum; with `full`, also decode and the
/// world hash. Returns the state (when `full`) and the identity.
///
/// Nothing is allocated for the payload before the header has verified and
/// the file's size agrees with it; the payload checksum of a cheap check is
/// streamed; a full read needs the payload and its claimed decompressed
/// size to fit in the memory the OS says is available.
fn read_checked(
    path: &Path,
    full: bool,
) -> Result<(Option<WorldState>, Option<WorldIdentity>), CheckpointError> {
    use std::io::Read;
    let corrupt = |msg: String| CheckpointError::Corrupt {
        path: path.to_path_buf(),
        msg,
    };
    let meta = fs::metadata(path).map_err(|e| io(path, e))?;
    if !meta.is_file() {
        return Err(corrupt("not a regular file".into()));
    }
    let mut f = File::open(path).map_err(|e| io(path, e))?;
    // The header and the identity block (at most 64 KiB) first.
    let mut head = Vec::with_capacity(HEADER + 8);
    (&mut f)
        .take(HEADER as u64 + 4)
        .read_to_end(&mut head)
        .map_err(|e| io(path, e))?;
    let (version, payload_len) = check_header(&head).map_err(corrupt)?;
    let mut id_block = Vec::new();
    if version >= 2 {
        let n = u32::from_le_bytes(head[HEADER..HEADER + 4].try_into().expect("4")) as u64;
        if n > 64 << 10 {
            return Err(corrupt(format!("identity block of {n} bytes is too large")));
        }
        (&mut f)
            .take(n + 4)
            .read_to_end(&mut id_block)
            .map_err(|e| io(path, e))?;
    } else {
        head.truncate(HEADER);
    }
    let prefix = head.len() as u64 + id_block.len() as u64;
    if meta.len() != prefix + payload_len {
        return Err(corrupt(format!(
            "the file is {} bytes, its header says {}",
            meta.len(),
            prefix + payload_len
        )));
    }
    if !full {
        let mut head_and_id = head.clone();
        head_and_id.extend_from_slice(&id_block);
        let (_, identity) = parse_prefix(&head_and_id).map_err(corrupt)?;
        let want = u32::from_le_bytes(head[32..36].try_into().expect("4"));
        let mut crc = crc32fast::Hasher::new();
        let mut buf = vec![0u8; 1 << 20];
        loop {
            let n = f.read(&mut buf).map_err(|e| io(path, e))?;
            if n == 0 {
                break;
            }
            crc.update(&buf[..n]);
        }
        if crc.finalize() != want {
            return Err(corrupt("payload checksum mismatch".into()));
        }
        return Ok((None, identity));
    }
    let have = crate::scene::budget::available_bytes();
    if payload_len > have / 2 {
        return Err(corrupt(format!(
            "a {payload_len}-byte payload does not fit in the {have} bytes available"
        )));
    }
    let mut bytes = head;
    bytes.extend_from_slice(&id_block);
    f.read_to_end(&mut bytes).map_err(|e| io(path, e))?;
    parse(&bytes, true).map_err(corrupt)
}

/// Verify the fixed header; returns (version, payload length).
fn check_header(h: &[u8]) -> Result<(u32, u64), String> {
    if h.len() < HEADER {
        return Err(format!("{} bytes is shorter than the header", h.len()));
    }
    if &h[0..4] != MAGIC {
        return Err("not a brickworld checkpoint (bad magic)".into());
    }
    if crc32fast::hash(&h[..36]) != u32::from_le_bytes(h[36..40].try_into().expect("4")) {
        return Err("header checksum mismatch".into());
    }
    let version = u32::from_le_bytes(h[4..8].try_into().expect("4"));
    if !(1..=VERSION).contains(&version) {
        return Err(format!(
            "format version {version}, this build reads 1 to {VERSION}"
        ));
    }
    if version >= 2 && h.len() < HEADER + 4 {
        return Err("the identity block is missing".into());
    }
    Ok((
        version,
        u64::from_le_bytes(h[24..32].try_into().expect("8")),
    ))
}

/// The header and identity block at the start of `bytes`: returns the
/// prefix length and the identity.
fn parse_prefix(bytes: &[u8]) -> Result<(usize, Option<WorldIdentity>), String> {
    let (version, _) = check_header(bytes)?;
    if version < 2 {
        return Ok((HEADER, None));
    }
    let rest = &bytes[HEADER..];
    let n = u32::from_le_bytes(rest[..4].try_into().expect("4")) as usize;
    if n > 64 << 10 || rest.len() < 8 + n {
        return Err(format!("identity block of {n} bytes does not fit"));
    }
    let id = &rest[4..4 + n];
    let icrc = u32::from_le_bytes(rest[4 + n..8 + n].try_into().expect("4"));
    if crc32fast::hash(id) != icrc {
        return Err("identity checksum mismatch".into());
    }
    let identity = serde_json::from_slice::<Option<WorldIdentity>>(id)
        .map_err(|e| format!("identity: {e}"))?;
    Ok((HEADER + 8 + n, identity))
}

/// Parse a whole checkpoint file from bytes (the fuzz target): never panics
/// and never allocates more than the bytes justify.
pub fn parse(
    bytes: &[u8],
    full: bool,
) -> Result<(Option<WorldState>, Option<WorldIdentity>), String> {
    let (version, len) = check_header(bytes)?;
    let h = &bytes[..HEADER];
    let tick = u64::from_le_bytes(h[8..16].try_into().expect("8"));
    let hash = u64::from_le_bytes(h[16..24].try_into().expect("8"));
    let crc = u32::from_le_bytes(h[32..36].try_into().expect("4"));
    let (prefix, identity) = parse_prefix(bytes)?;
    let payload = &bytes[prefix..];
    if payload.len() as u64 != len {
        return Err(format!(
            "payload is {} bytes, the header says {len}",
            payload.len()
        ));
    }
    if crc32fast::hash(payload) != crc {
        return Err("payload checksum mismatch".into());
    }
    if !full {
        return Ok((None, identity));
    }
    let claimed = payload
        .get(..4)
        .map(|b| u32::from_le_bytes(b.try_into().expect("4")) as usize)
        .ok_or("the payload has no size prefix")?;
    if claimed > payload.len().saturating_mul(MAX_LZ4_RATIO) + 64 {
        return Err(format!(
            "the payload claims {claimed} bytes uncompressed, more than {} compressed bytes can hold",
            payload.len()
        ));
    }
    let have = crate::scene::budget::available_bytes();
    if claimed as u64 > have / 2 {
        return Err(format!(
            "the payload claims {claimed} bytes uncompressed; only {have} bytes are available"
        ));
    }
    let raw = lz4_flex::decompress_size_prepended(payload).map_err(|e| format!("LZ4: {e}"))?;
    let mut state = decode(tick, version, &raw)?;
    let got = world_hash(&state.store, &state.channels);
    if got != hash {
        return Err(format!(
            "world hash {got:#x} differs from the recorded {hash:#x}"
        ));
    }
    state.identity = identity.clone();
    Ok((Some(state), identity))
}

/// Read and verify one checkpoint file.
pub fn read(path: &Path) -> Result<WorldState, CheckpointError> {
    let (state, _) = read_checked(path, true)?;
    Ok(state.expect("full read returns the state"))
}

/// What [`latest`] found.
#[derive(Debug)]
pub struct Latest {
    /// The newest checkpoint that verified, and its state.
    pub found: Option<(PathBuf, WorldState)>,
    /// Newer checkpoints that failed to verify (to report).
    pub skipped: Vec<CheckpointError>,
}

/// The newest checkpoint in `dir` that verifies, whatever its world, with
/// the problems of any newer ones skipped on the way (files are not
/// renamed: this only reads).
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
