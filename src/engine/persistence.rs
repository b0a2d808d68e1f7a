//! The engine's side of the world store ([`crate::persist`]): which chunks
//! changed ([`DirtyChunks`]), restoring a world from the store
//! ([`restore_chunks`], [`apply_state`]), committing ([`commit`]), and the
//! single-file backups: [`export`], [`import`] and the migration of a
//! state directory written by the whole-world checkpoints of earlier
//! versions ([`migrate_legacy`]).
//!
//! **Restoring** regenerates the world from its source, then overlays every
//! stored chunk and chunk column (a stored chunk replaces the generated one
//! whole), then applies the state blob. Only what was ever edited is on
//! disk. A corrupt chunk is reported with its coordinates and regenerated
//! from the source (and rewritten at the next commit); the rest of the world
//! loads as stored.

use std::path::Path;

use anyhow::{Context, Result, bail};
use glam::{IVec2, IVec3};
use rayon::prelude::*;
use rustc_hash::FxHashSet;

use super::checkpoint::{self, CameraOverride, SimExtras, WorldIdentity, WorldRef, WorldState};
use super::world_config::WorldConfig;
use crate::persist::chunk::{self, CHUNK_SHIFT};
use crate::persist::{ChunkKey, ColumnKey, CommitStats, StoreError, WorldDb, state};
use crate::scene::SceneWorld;
use crate::sim::WorldSim;

/// Chunks and chunk columns changed since the last commit. Bricks arrive in
/// one hop from the step's dirty batches; channel writes are recorded by the
/// channel stores themselves and collected at commit time.
#[derive(Debug, Default)]
pub struct DirtyChunks {
    chunks: FxHashSet<ChunkKey>,
    columns: FxHashSet<ColumnKey>,
}

impl DirtyChunks {
    /// Record changed bricks.
    pub fn bricks(&mut self, bricks: &[IVec3]) {
        self.chunks
            .extend(bricks.iter().map(|b| ChunkKey::of_brick(*b)));
    }

    /// Collect the channel writes the simulation recorded.
    pub fn collect(&mut self, ws: &mut WorldSim) {
        for t in ws.sim.channels_mut().take_dirty() {
            self.columns.insert(ColumnKey::of_tile(t));
        }
        for b in ws.vox.channels_mut().take_dirty() {
            self.chunks.insert(ChunkKey::of_brick(b));
        }
    }

    /// Mark every chunk and chunk column of the world dirty (an import).
    pub fn everything(&mut self, world: &SceneWorld, ws: &WorldSim) {
        let (lo, hi) = world.bounds();
        let bmin = lo.div_euclid(IVec3::splat(8));
        let bmax = (hi - 1).div_euclid(IVec3::splat(8));
        let (cmin, cmax) = (bmin >> CHUNK_SHIFT, bmax >> CHUNK_SHIFT);
        for z in cmin.z..=cmax.z {
            for y in cmin.y..=cmax.y {
                for x in cmin.x..=cmax.x {
                    self.chunks.insert(ChunkKey(IVec3::new(x, y, z)));
                }
            }
        }
        let (tmin, tmax) = ws.sim.tile_bounds();
        for z in (tmin.y >> CHUNK_SHIFT)..=((tmax.y - 1) >> CHUNK_SHIFT) {
            for x in (tmin.x >> CHUNK_SHIFT)..=((tmax.x - 1) >> CHUNK_SHIFT) {
                self.columns.insert(ColumnKey(IVec2::new(x, z)));
            }
        }
    }

    /// The dirty chunks' keys (in no particular order).
    pub fn chunk_keys(&self) -> Vec<ChunkKey> {
        self.chunks.iter().copied().collect()
    }

    /// Dirty chunks plus dirty chunk columns.
    pub fn len(&self) -> usize {
        self.chunks.len() + self.columns.len()
    }

    /// Whether nothing changed.
    pub fn is_empty(&self) -> bool {
        self.len() == 0
    }
}

/// Each script's parameters: (script, [(name, value)]).
pub type ScriptParams = Vec<(String, Vec<(String, f64)>)>;

/// The script parameters and the rest of the simulation state, as the
/// state blob and the checkpoint format hold them.
pub fn sim_state(world: &SceneWorld, ws: &WorldSim) -> (ScriptParams, SimExtras) {
    let params = (0..ws.script_count())
        .map(|i| {
            let spec = ws.spec(i);
            (
                spec.name.clone(),
                spec.params
                    .iter()
                    .zip(ws.params(i))
                    .map(|(p, v)| (p.name.clone(), *v))
                    .collect(),
            )
        })
        .collect();
    let extras = SimExtras {
        drained: ws.drained,
        sleep: Some(ws.sim.sleep_state()),
        voxel_channels: Default::default(),
        voxel_sleep: Some(ws.vox.sleep_state(world.store())),
        materials: world.materials.entries(),
        camera: None,
        health: script_health(ws),
    };
    (params, extras)
}

/// Commit what changed (and the simulation state) in one transaction. On
/// failure nothing is written and `dirty` keeps everything for the next try.
pub fn commit(
    db: &mut WorldDb,
    dirty: &mut DirtyChunks,
    world: &SceneWorld,
    ws: &mut WorldSim,
    camera: Option<CameraOverride>,
) -> Result<CommitStats, StoreError> {
    dirty.collect(ws);
    let store = world.store();
    let voxel = ws.vox.channels();
    let columns = ws.sim.channels();
    let chunks: Vec<(ChunkKey, Vec<u8>)> = dirty
        .chunks
        .par_iter()
        .map(|k| (*k, chunk::encode_chunk(*k, store, voxel)))
        .collect();
    let cols: Vec<(ColumnKey, Vec<u8>)> = dirty
        .columns
        .par_iter()
        .map(|k| (*k, chunk::encode_column(*k, columns)))
        .collect();
    let (params, mut extras) = sim_state(world, ws);
    extras.camera = camera;
    let blob = state::encode(
        ws.sim.tick(),
        world.store().palette(),
        world.bounds(),
        &params,
        &extras,
    );
    let stats = db.commit(&chunks, &cols, &blob)?;
    dirty.chunks.clear();
    dirty.columns.clear();
    Ok(stats)
}

/// A stored world's palette and voxel bounds `[min, max)`.
pub type StoredFrame = (crate::world::Palette, (IVec3, IVec3));

/// The palette and bounds of the world the store last committed (None:
/// never committed), read before the world is built: an imported world is
/// rebuilt from the store alone.
pub fn stored_frame(db: &WorldDb) -> Result<Option<StoredFrame>, StoreError> {
    let Some(blob) = db.state()? else {
        return Ok(None);
    };
    let st = state::decode(&blob).map_err(|msg| StoreError::Db {
        path: db.path().to_path_buf(),
        msg,
    })?;
    Ok(Some((st.store.palette().clone(), st.bounds)))
}

/// What [`restore_chunks`] found besides the chunks.
#[derive(Debug)]
pub struct Restored {
    /// The decoded state blob (its store holds only the palette).
    pub state: WorldState,
    /// Chunks and columns overlaid.
    pub chunks: usize,
    /// Corrupt chunks and columns, regenerated from the source: marked
    /// dirty so the next commit replaces them.
    pub corrupt: Vec<String>,
}

/// How [`restore_chunks`] reads the store.
#[derive(Clone, Copy, Debug, Default)]
pub struct RestoreScope {
    /// A procedural world: a corrupt chunk is regenerated from the source.
    pub regenerable: bool,
    /// A streamed world's simulated region: the store holds more than the
    /// region, so the chunks and columns inside it are looked up one by one
    /// (a move or a resume costs the region, not the store).
    pub region: bool,
    /// A region with closed edges (one that follows the camera): take only
    /// whole stored columns. A region that drains keeps a moat of tiles in
    /// its neighbours' columns; such a column's blob holds only those tiles
    /// and fictitious ground, and restoring it would zero the real column.
    pub whole_columns: bool,
}

/// Overlay the store's chunks and columns on a freshly generated world and
/// simulation, and restore the palette and material registry. `None` if the
/// store was never committed. The edits the overlay makes are not dirty;
/// corrupt chunks are (they were regenerated).
///
/// A corrupt chunk of a procedural world is regenerated (and rewritten at
/// the next commit); an imported world (`regenerable` false) cannot
/// regenerate it, so it stays empty in this run and its stored blob is
/// left alone, for a backup or a repair to restore.
pub fn restore_chunks(
    db: &WorldDb,
    world: &mut SceneWorld,
    ws: &mut WorldSim,
    dirty: &mut DirtyChunks,
    scope: RestoreScope,
) -> Result<Option<Restored>, StoreError> {
    let regenerable = scope.regenerable;
    let Some(blob) = db.state()? else {
        return Ok(None);
    };
    let st = state::decode(&blob).map_err(|msg| StoreError::Db {
        path: db.path().to_path_buf(),
        msg: format!("{msg}; the chunks are intact, but the world cannot resume without it"),
    })?;
    // The overlay is the stored state, not a change: the grid is patched
    // and the changed bricks forgotten; only the regenerated chunks must be
    // written again.
    // Only what lies in the world: a streamed world's store also holds
    // chunks its simulated region covered before it moved.
    let (lo, hi) = world.bounds();
    let (bmin, bmax) = (
        lo.div_euclid(IVec3::splat(8)),
        (hi - 1).div_euclid(IVec3::splat(8)),
    );
    let in_world = |k: &ChunkKey| {
        let (a, b) = (k.min_brick(), k.min_brick() + (chunk::CHUNK_BRICKS - 1));
        a.cmple(bmax).all() && b.cmpge(bmin).all()
    };
    let (tmin, tmax) = ws.sim.tile_bounds();
    let in_sim = |k: &ColumnKey| {
        let a = k.tile(0);
        let b = a + (chunk::CHUNK_BRICKS - 1);
        a.cmplt(tmax).all() && b.cmpge(tmin).all()
    };
    let (chunk_keys, column_keys) = if scope.region {
        let (cmin, cmax) = (bmin >> CHUNK_SHIFT, bmax >> CHUNK_SHIFT);
        let chunks = (cmin.z..=cmax.z)
            .flat_map(|z| {
                (cmin.y..=cmax.y).flat_map(move |y| {
                    (cmin.x..=cmax.x).map(move |x| ChunkKey(IVec3::new(x, y, z)))
                })
            })
            .collect();
        let (kmin, kmax) = (tmin >> CHUNK_SHIFT, (tmax - 1) >> CHUNK_SHIFT);
        let columns = (kmin.y..=kmax.y)
            .flat_map(|z| (kmin.x..=kmax.x).map(move |x| ColumnKey(IVec2::new(x, z))))
            .collect();
        (chunks, columns)
    } else {
        (db.chunk_keys()?, db.column_keys()?)
    };
    let (overlay, _) = world.edit(|store, materials| -> Result<_, StoreError> {
        *store.palette_mut() = st.store.palette().clone();
        let mut keys = chunk_keys;
        keys.retain(in_world);
        let mut corrupt = Vec::new();
        let mut regenerated = Vec::new();
        let mut n = 0;
        for k in &keys {
            let Some(blob) = db.chunk(*k)? else { continue };
            match chunk::decode_chunk(*k, &blob, store.palette()) {
                Ok(mut data) => {
                    let v = ws.vox.channels();
                    let known = |n: &str| v.find(n).is_some();
                    let dropped = chunk::fit_channels(&mut data.voxel, known, v.names().len());
                    corrupt.extend(too_many_channels(&k.to_string(), &dropped));
                    chunk::apply_chunk(*k, &data, store, ws.vox.channels_mut());
                    n += 1;
                }
                Err(e) => {
                    if regenerable {
                        corrupt.push(format!("{k} is corrupt ({e}): regenerated from the source"));
                        regenerated.push(*k);
                    } else {
                        corrupt.push(format!(
                            "{k} is corrupt ({e}): an imported world cannot regenerate it, so it is empty in this run; its stored blob is left as it is (restore it from a backup)"
                        ));
                    }
                }
            }
        }
        let mut bad_columns = Vec::new();
        for k in column_keys.into_iter().filter(in_sim) {
            let Some(blob) = db.column(k)? else { continue };
            match chunk::decode_column(k, &blob) {
                Ok(data) if scope.whole_columns && !whole(&data) => {}
                Ok(mut data) => {
                    let c = ws.sim.channels();
                    let known = |n: &str| c.find(n).is_some();
                    let dropped = chunk::fit_channels(&mut data.channels, known, c.channels().count());
                    corrupt.extend(too_many_channels(&k.to_string(), &dropped));
                    chunk::apply_column(k, &data, ws.sim.channels_mut());
                    n += 1;
                }
                Err(e) => {
                    if regenerable {
                        corrupt.push(format!("{k} is corrupt ({e}): regenerated from the source"));
                        bad_columns.push(k);
                    } else {
                        corrupt.push(format!(
                            "{k} is corrupt ({e}): an imported world cannot regenerate it, so its columns start from the ground in this run; its stored blob is left as it is"
                        ));
                    }
                }
            }
        }
        if !st.extras.materials.is_empty() {
            *materials =
                crate::world::MaterialRegistry::from_entries(&st.extras.materials, store.palette());
        }
        Ok((corrupt, regenerated, bad_columns, n))
    });
    let (corrupt, regenerated, bad_columns, n) = overlay?;
    ws.sim.channels_mut().take_dirty();
    ws.vox.channels_mut().take_dirty();
    dirty.chunks.extend(regenerated);
    dirty.columns.extend(bad_columns);
    Ok(Some(Restored {
        state: st,
        chunks: n,
        corrupt,
    }))
}

/// The warning for channels of a stored blob left out because the world
/// has its [`chunk::MAX_CHANNELS`] channels already (none if none were).
fn too_many_channels(blob: &str, dropped: &[String]) -> Option<String> {
    if dropped.is_empty() {
        return None;
    }
    let shown: Vec<&str> = dropped.iter().take(3).map(|s| s.as_str()).collect();
    Some(format!(
        "{blob} names {} channels the world has no room for ({}{}; the world holds {} channels at most): they are left out of this run, and the stored blob keeps them until the {blob} is written again",
        dropped.len(),
        shown.join(", "),
        if dropped.len() > shown.len() {
            ", …"
        } else {
            ""
        },
        chunk::MAX_CHANNELS
    ))
}

/// Whether a stored column holds the ground of all its 64 tiles (what a
/// region that covered it writes; a moat's few tiles do not).
fn whole(data: &crate::persist::ColumnData) -> bool {
    data.channels
        .iter()
        .any(|(name, tiles)| name == "ground" && tiles.len() == 64)
}

/// The failing and suspended scripts' health, for the state blob. A
/// suspension for the wall-clock limit is not kept: it depends on the
/// machine's load when it happened, and a restart is the way to try again.
fn script_health(ws: &WorldSim) -> Vec<checkpoint::ScriptHealth> {
    (0..ws.script_count())
        .filter(|&i| ws.failures(i) > 0 || ws.suspended(i).is_some())
        .filter(|&i| !ws.suspended(i).is_some_and(|e| e.is_time_budget()))
        .map(|i| checkpoint::ScriptHealth {
            script: ws.spec(i).name.clone(),
            source: crate::persist::bytes::fnv1a(ws.source(i).text.as_bytes()),
            failures: ws.failures(i),
            suspended: ws.suspended(i).map(|e| e.to_string()),
        })
        .collect()
}

/// Apply a restored state blob once the scripts are loaded: tick, sleep
/// states, the drained total, the parameters and the scripts' health.
/// Returns warnings (parameters a changed script no longer accepts, a
/// suspension lifted because its script changed).
pub fn apply_state(st: &WorldState, ws: &mut WorldSim) -> Vec<String> {
    let mut warnings = Vec::new();
    // Health: a script that failed or was suspended when the state was
    // committed is so again, unless its source changed (a reload).
    for h in &st.extras.health {
        let Some(i) = ws.script_index(&h.script) else {
            continue;
        };
        if crate::persist::bytes::fnv1a(ws.source(i).text.as_bytes()) != h.source {
            if h.suspended.is_some() {
                warnings.push(format!(
                    "{}.lua changed while the engine was stopped: it was suspended, and runs again",
                    h.script
                ));
            }
            continue;
        }
        let suspended = h
            .suspended
            .as_ref()
            .map(|msg| crate::sim::SimError::Recorded {
                script: h.script.clone(),
                msg: msg.clone(),
            });
        ws.set_health(i, h.failures, suspended);
    }
    // Parameters first: setting one wakes everything, and the sleep states
    // restored after it must be the stored ones.
    for (script, values) in &st.params {
        if let Some(i) = ws.script_index(script) {
            for (k, v) in values {
                if let Err(e) = ws.set_param(i, k, *v) {
                    warnings.push(format!("the stored {script}.{k} = {v} is not kept: {e}"));
                }
            }
        }
    }
    let extras = &st.extras;
    if let Some((active, quiet)) = &extras.voxel_sleep {
        ws.vox.restore_sleep_state(active, quiet);
    }
    ws.vox.set_tick(st.tick);
    ws.resync_columns();
    ws.sim.set_tick(st.tick);
    ws.drained = extras.drained;
    match &extras.sleep {
        Some(s) => ws.sim.restore_sleep_state(s),
        None => ws.sim.wake_all(),
    }
    warnings
}

/// The hash a run reports when it resumes and when it stops: the bricks,
/// the column channels and the voxel channels (O(world): not per commit).
pub fn engine_hash(world: &SceneWorld, ws: &WorldSim) -> u64 {
    checkpoint::world_hash(world.store(), ws.sim.channels())
        ^ ws.vox.channels().hash().rotate_left(17)
}

/// Write the whole of a store's world into a fresh store: every chunk and
/// chunk column of its bounds (an empty chunk overrides the source's) and
/// the state. Used by [`import`] and [`migrate_legacy`].
fn write_everything(db: &mut WorldDb, st: WorldState) -> Result<CommitStats> {
    let mut world = SceneWorld::new(st.store, st.bounds.0, st.bounds.1)
        .context("the imported world does not fit a brick grid")?;
    if !st.extras.materials.is_empty() {
        world.materials = crate::world::MaterialRegistry::from_entries(
            &st.extras.materials,
            world.store().palette(),
        );
    }
    let mut ws = WorldSim::with_edges(&mut world, true);
    ws.sim.set_channels(st.channels);
    ws.vox.set_channels(st.extras.voxel_channels.clone());
    let mut dirty = DirtyChunks::default();
    dirty.everything(&world, &ws);
    let (params, extras) = (st.params, st.extras);
    let store = world.store();
    let chunks: Vec<(ChunkKey, Vec<u8>)> = dirty
        .chunks
        .par_iter()
        .map(|k| (*k, chunk::encode_chunk(*k, store, ws.vox.channels())))
        .collect();
    let cols: Vec<(ColumnKey, Vec<u8>)> = dirty
        .columns
        .par_iter()
        .map(|k| (*k, chunk::encode_column(*k, ws.sim.channels())))
        .collect();
    let blob = state::encode(st.tick, store.palette(), world.bounds(), &params, &extras);
    Ok(db.commit(&chunks, &cols, &blob)?)
}

/// `brickworld import`: load a single-file backup (a checkpoint file) into
/// the empty store of state directory `dir`. The file must belong to the
/// world `identity` describes; a store that already holds a world is refused.
pub fn import(file: &Path, dir: &Path, identity: &WorldIdentity) -> Result<CommitStats> {
    let st = checkpoint::read(file).with_context(|| format!("cannot import {}", file.display()))?;
    match &st.identity {
        Some(id) if !id.same_world(identity) => bail!(
            "{} is a backup of another world ({id}); the config describes {identity}",
            file.display()
        ),
        Some(_) => {}
        None => bail!(
            "{} does not say which world it belongs to (a checkpoint from before world identities); it cannot be checked against {identity}, so it is not imported",
            file.display()
        ),
    }
    // The bounds a backup claims decide the grid built from it: an inverted,
    // overflowing or larger-than-memory box is refused before anything is
    // allocated (regression: forged bounds panicked in the grid, or
    // aborted it out of memory).
    let (lo, hi) = st.bounds;
    let extent = hi.as_i64vec3() - lo.as_i64vec3();
    if extent.cmple(glam::I64Vec3::ZERO).any() || extent.cmpgt(glam::I64Vec3::splat(1 << 24)).any()
    {
        bail!(
            "{} claims world bounds {lo} .. {hi}, which no world has (nothing was changed)",
            file.display()
        );
    }
    crate::scene::budget::check_world("the imported world", extent.as_ivec3())?;
    let store_file = dir.join(crate::persist::db::DB_FILE);
    if store_file.exists() && !WorldDb::readable(dir) {
        bail!(
            "{} exists but cannot be read (locked by a running engine, or damaged); import into an empty --state directory (nothing was changed)",
            store_file.display()
        );
    }
    // Only the lock this import holds may be there (regression: a
    // directory holding other files was imported into, against the docs).
    if !store_file.exists()
        && let Some(other) = std::fs::read_dir(dir)
            .with_context(|| format!("cannot list {}", dir.display()))?
            .filter_map(|e| e.ok().map(|e| e.file_name()))
            .find(|n| n != "engine.lock")
    {
        bail!(
            "{} is not empty (it holds {:?}): import into a new or empty --state directory (nothing was changed)",
            dir.display(),
            other
        );
    }
    if WorldDb::has_state(dir) {
        bail!(
            "{} already holds this world; import into an empty --state directory (nothing was changed)",
            dir.display()
        );
    }
    let (mut db, _) = WorldDb::open(dir, identity)?;
    // Checked again on the open store: nothing may be overwritten.
    if db.state()?.is_some() {
        bail!(
            "{} already holds this world; import into an empty --state directory (nothing was changed)",
            dir.display()
        );
    }
    write_everything(&mut db, st)
}

/// A state directory of an earlier version holds whole-world checkpoints
/// and no store: write the newest good one into the store. Returns what was
/// migrated (None: nothing to migrate). The old files are left in place.
pub fn migrate_legacy(
    db: &mut WorldDb,
    dir: &Path,
    identity: &WorldIdentity,
) -> Result<Option<(std::path::PathBuf, u64)>> {
    if db.state()?.is_some() || checkpoint::list(dir)?.is_empty() {
        return Ok(None);
    }
    let (_, found, warnings) = checkpoint::Checkpoints::open(dir, identity.clone())?;
    for w in warnings {
        eprintln!("warning: {w}");
    }
    let Some((path, st)) = found else {
        return Ok(None);
    };
    let tick = st.tick;
    write_everything(db, st)?;
    Ok(Some((path, tick)))
}

/// `brickworld export`: the world as restored from the store (regenerated,
/// overlaid, with the state blob `st`) as one checkpoint file at `out`.
/// Returns the world hash.
pub fn export(
    world: &SceneWorld,
    ws: &WorldSim,
    st: &WorldState,
    identity: &WorldIdentity,
    out: &Path,
) -> Result<u64> {
    let extras = SimExtras {
        voxel_channels: ws.vox.channels().clone(),
        ..st.extras.clone()
    };
    let hash = checkpoint::write_at(
        out,
        WorldRef {
            tick: st.tick,
            store: world.store(),
            bounds: world.bounds(),
            channels: ws.sim.channels(),
            params: &st.params,
            identity: Some(identity),
            extras: &extras,
        },
    )?;
    Ok(hash)
}

/// Refuse an export whose file would replace something that is not a
/// backup: a file of the state directory other than a `NAME.bwc` backup
/// (the world store itself, before this was checked), or anything but a
/// regular file (a device, a pipe, a directory: the write replaces the
/// path with a new file).
fn check_export_target(dir: &Path, out: &Path) -> Result<()> {
    if let Ok(meta) = std::fs::metadata(out)
        && !meta.is_file()
    {
        bail!(
            "{} exists and is not a regular file: export writes a new file there, so name another path (nothing was written)",
            out.display()
        );
    }
    // Where the file would land: its parent resolved, plus its name.
    let parent = match out.parent() {
        Some(p) if !p.as_os_str().is_empty() => p,
        _ => Path::new("."),
    };
    // Inside the state directory only a backup's own kind of name may be
    // written: every other file there is the engine's.
    let name = out.file_name().map(|n| n.to_string_lossy().to_string());
    let backup_name = name
        .as_deref()
        .is_some_and(|n| n.ends_with(".bwc") && !n.starts_with("ckpt-"));
    if let (Ok(state), Ok(parent)) = (dir.canonicalize(), parent.canonicalize())
        && parent.starts_with(&state)
        && !backup_name
    {
        bail!(
            "{} lies inside the state directory {} and is not a NAME.bwc backup: export there could replace the world it reads; name a .bwc file or write elsewhere (nothing was written)",
            out.display(),
            dir.display()
        );
    }
    Ok(())
}

/// `brickworld export`: open the store of state directory `dir` (locked, so
/// a running engine is a clear error), restore its world, and write it to
/// `out`. Returns the tick and the world hash ([`engine_hash`], as `run`
/// prints it), unless the world's scripts no longer load.
pub fn export_world(cfg: &WorldConfig, dir: &Path, out: &Path) -> Result<(u64, Option<u64>)> {
    if !dir.join(crate::persist::db::DB_FILE).is_file() {
        bail!("{} holds no world store (nothing to export)", dir.display());
    }
    check_export_target(dir, out)?;
    if cfg.stream.is_some()
        && matches!(
            cfg.sim_region,
            super::world_config::SimRegion::AroundCamera { .. }
        )
    {
        bail!(
            "export writes one region, and this world's simulated region follows the camera: its store holds every place the region has been. Back it up by copying {} and {} while the engine is stopped (nothing was written)",
            dir.join(crate::persist::db::DB_FILE).display(),
            dir.join(crate::persist::db::MANIFEST_FILE).display()
        );
    }
    let _lock = super::state_dir::lock(dir)?;
    let identity = cfg.identity();
    let (db, _) = WorldDb::open(dir, &identity)?;
    let mut world = match &cfg.stream {
        // A streamed world's backup is its fixed simulated region.
        Some(_) => {
            let (gen_, rule) = super::streaming::generator(cfg)?;
            let columns = rule.around(glam::DVec3::ZERO);
            super::streaming::build_columns(&gen_, columns)?
        }
        None => {
            let pb = crate::progress::bar("scene", 0);
            let w = crate::scene::build_scene(&cfg.source, cfg.size, cfg.seed, &pb)
                .context("cannot build the world")?;
            pb.finish_and_clear();
            w
        }
    };
    let mut ws = WorldSim::with_edges(&mut world, true);
    ws.sim.channels_mut().take_dirty();
    ws.set_seed(cfg.seed);
    // The scripts register their channels before the stored chunks go
    // over the world, as at start, so channel ids and the world hash are
    // those `run` prints. A world whose scripts no longer load is still
    // exported (its data is stored by channel name); only the hash is
    // left out.
    let comparable = match super::daemon::load_scripts(cfg, &mut world, &mut ws) {
        Ok(()) => true,
        Err(e) => {
            eprintln!(
                "warning: {e:#}: exported all the same; the world hash is left out, as it would not match run's"
            );
            ws = WorldSim::with_edges(&mut world, true);
            ws.sim.channels_mut().take_dirty();
            false
        }
    };
    let mut dirty = DirtyChunks::default();
    let scope = RestoreScope {
        regenerable: cfg.source.is_procedural(),
        region: cfg.stream.is_some(),
        whole_columns: false,
    };
    let Some(r) = restore_chunks(&db, &mut world, &mut ws, &mut dirty, scope)? else {
        bail!("{} was never committed (nothing to export)", dir.display());
    };
    for c in &r.corrupt {
        eprintln!("warning: {c}");
    }
    export(&world, &ws, &r.state, &identity, out)?;
    // The hash `run` prints when it stops and `resumed` at start (the
    // file's own hash, which its reader checks, covers less).
    Ok((r.state.tick, comparable.then(|| engine_hash(&world, &ws))))
}

/// `brickworld import`: lock state directory `dir` and [`import`] `file`.
pub fn import_world(cfg: &WorldConfig, dir: &Path, file: &Path) -> Result<CommitStats> {
    // A failed import leaves the directory as it found it (regression: it
    // created `--state` and its lock file even when refusing the backup).
    // Whether this import made the directory is decided by `create_dir`
    // itself, and nothing is removed unless this import holds the lock
    // (regression: an import that lost the lock to another removed the
    // directory the other was importing into).
    let lock_file = dir.join("engine.lock");
    let had_lock = lock_file.exists();
    let (lock, created) = super::state_dir::claim(dir)?;
    let result = import(file, dir, &cfg.identity());
    if result.is_err() {
        if created {
            let _ = std::fs::remove_dir_all(dir);
        } else if !had_lock {
            let _ = std::fs::remove_file(&lock_file);
        }
    }
    drop(lock);
    result
}
