//! Single-file backups of a world store: [`export`] (the committed world as
//! one checkpoint file), [`import`] (one into an empty state directory),
//! and the migration of a state directory written by the whole-world
//! checkpoints of earlier versions ([`migrate_legacy`]).

use std::path::Path;

use anyhow::{Context, Result, bail};

use super::checkpoint::{self, SimExtras, WorldIdentity, WorldRef, WorldState};
use super::persistence::{DirtyChunks, RestoreScope, engine_hash, restore_chunks};
use super::world_config::WorldConfig;
use crate::persist::{CommitStats, WorldDb, state};
use crate::scene::SceneWorld;
use crate::sim::WorldSim;

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
    // A simulation re-registers ids 252 to 254 as water, snow and
    // sediment: stored materials there would change names in the copy, and
    // the start would refuse the world anyway (regression: only the start
    // refused such a world, after the import had said it succeeded).
    if let Some(msg) = crate::sim::run::reserved_conflicts(&world.materials) {
        bail!("{msg} (nothing was changed)");
    }
    let mut ws = WorldSim::with_edges(&mut world, true);
    ws.sim.set_channels(st.channels);
    ws.vox.set_channels(st.extras.voxel_channels.clone());
    let mut dirty = DirtyChunks::default();
    dirty.everything(&world, &ws);
    let (params, extras) = (st.params, st.extras);
    let (chunks, cols) = dirty.encode(&world, &ws);
    let blob = state::encode(
        st.tick,
        world.store().palette(),
        world.bounds(),
        &params,
        &extras,
    );
    Ok(db.commit(&chunks, &cols, &blob)?)
}

/// The file an import keeps in its state directory until the imported world
/// is committed: the store is created (with its manifest) before the world
/// is written into it, and a kill in between left a directory that `run`
/// took for a fresh world, dropping the backup without a word (regression,
/// hostile probe). `run` and `export` refuse a directory holding it; an
/// import again replaces what the interrupted one left.
pub const IMPORT_MARKER: &str = "import.incomplete";

/// Refuse state directory `dir` if an import into it was interrupted.
/// Call it holding the directory's lock: a running import holds it too.
/// A store that holds its state with the marker beside it is a finished
/// import cut before it removed the marker: the marker goes.
pub fn refuse_interrupted_import(dir: &Path) -> Result<()> {
    let marker = dir.join(IMPORT_MARKER);
    if std::fs::symlink_metadata(&marker).is_ok() {
        if WorldDb::has_state(dir) {
            let _ = std::fs::remove_file(&marker);
            return Ok(());
        }
        bail!(
            "an import into {} was interrupted ({} is there): run brickworld import FILE --state {} again",
            dir.display(),
            marker.display(),
            dir.display()
        );
    }
    Ok(())
}

/// Write `path` empty and make it durable (the file, then its directory).
fn write_durable_marker(path: &Path) -> std::io::Result<()> {
    let f = std::fs::File::create(path)?;
    f.sync_all()?;
    if let Some(d) = path.parent()
        && let Ok(d) = std::fs::File::open(d)
    {
        d.sync_all()?;
    }
    Ok(())
}

/// `brickworld import`: load a single-file backup (a checkpoint file) into
/// the empty store of state directory `dir`. The file must belong to the
/// world `identity` describes; a store that already holds a world is refused.
/// What an interrupted import left ([`IMPORT_MARKER`]) is replaced.
pub fn import(file: &Path, dir: &Path, identity: &WorldIdentity) -> Result<CommitStats> {
    // A FIFO, folder or device is no backup, not a damaged one
    // (regression, hostile probe 2: "checkpoint FIFO is corrupt").
    if crate::files::is_there_but_not_a_file(file) {
        bail!(
            "cannot import {}: not a regular file (a backup is a file `brickworld export` wrote)",
            file.display()
        );
    }
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
    refuse_contents_outside(file, &st)?;
    let marker = dir.join(IMPORT_MARKER);
    let had_marker = std::fs::symlink_metadata(&marker).is_ok();
    if had_marker && WorldDb::has_state(dir) {
        // The state is written in the same transaction as the world: the
        // cut import had finished all but removing its marker.
        let _ = std::fs::remove_file(&marker);
        bail!(
            "{} already holds this world (an earlier import into it had finished); import into an empty --state directory (nothing was changed)",
            dir.display()
        );
    }
    let result = import_into(dir, identity, st, had_marker);
    if result.is_err() && had_marker {
        // What the cut import left is gone, and this one failed too: the
        // directory must still read as interrupted, never as a fresh world
        // (found by review).
        let _ = write_durable_marker(&marker);
    }
    result
}

/// Refuse a backup holding a brick, a voxel channel's brick or a column
/// channel's tile (past the moat's ring) outside the bounds it claims: the world built from it
/// would drop them without a word (regression, fuzzing: bounds forged to
/// miss part of the world imported with exit 0, losing bricks and every
/// voxel channel).
fn refuse_contents_outside(file: &Path, st: &WorldState) -> Result<()> {
    use crate::world::BRICK_SHIFT;
    let (lo, hi) = st.bounds;
    let (blo, bhi) = (lo >> BRICK_SHIFT, (hi - glam::IVec3::ONE) >> BRICK_SHIFT);
    let brick = st
        .store
        .iter()
        .map(|(b, _)| b)
        .chain(st.extras.voxel_channels.all_bricks())
        .find(|b| b.cmplt(blo).any() || b.cmpgt(bhi).any());
    if let Some(b) = brick {
        bail!(
            "{} holds brick {b}, outside the world bounds {lo} .. {hi} it claims: the file is forged or corrupt (nothing was changed)",
            file.display()
        );
    }
    // Column channels hold a one-tile moat around the world's tiles
    // (drained edges).
    let (tmin, tmax) = crate::sim::writeback::tiles_of(lo, hi);
    let (tmin, tmax) = (tmin - glam::IVec2::ONE, tmax + glam::IVec2::ONE);
    if let Some(t) = st
        .channels
        .tiles()
        .into_iter()
        .find(|t| t.cmplt(tmin).any() || t.cmpge(tmax).any())
    {
        bail!(
            "{} holds channel data for column tile {t}, outside the world bounds {lo} .. {hi} it claims: the file is forged or corrupt (nothing was changed)",
            file.display()
        );
    }
    Ok(())
}

/// [`import`] once the backup is checked: replace what an interrupted
/// import left (`replace`), refuse a directory holding anything else,
/// then write the world under the marker.
fn import_into(
    dir: &Path,
    identity: &WorldIdentity,
    st: WorldState,
    replace: bool,
) -> Result<CommitStats> {
    let store_file = dir.join(crate::persist::db::DB_FILE);
    let manifest_file = dir.join(crate::persist::db::MANIFEST_FILE);
    let marker = dir.join(IMPORT_MARKER);
    // An interrupted import's store and manifest hold no world: they are
    // this import's to replace.
    if replace {
        for p in [&store_file, &manifest_file, &marker] {
            match std::fs::remove_file(p) {
                Err(e) if e.kind() != std::io::ErrorKind::NotFound => {
                    return Err(e).with_context(|| format!("cannot remove {}", p.display()));
                }
                _ => {}
            }
        }
    }
    if store_file.exists() && !WorldDb::readable(dir) {
        bail!(
            "{} exists but cannot be read (locked by a running engine, left unclosed by an engine stopped before its first commit, or damaged); import into an empty --state directory (nothing was changed)",
            store_file.display()
        );
    }
    // Only the lock this import holds may be there (regression: a
    // directory holding other files was imported into, against the docs).
    if !store_file.exists()
        && let Some(other) = std::fs::read_dir(dir)
            .with_context(|| format!("cannot list {}", dir.display()))?
            .filter_map(|e| e.ok().map(|e| e.file_name()))
            .find(|n| n != "engine.lock" && n != IMPORT_MARKER)
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
    let made_store = std::fs::symlink_metadata(&store_file).is_err();
    write_durable_marker(&marker).with_context(|| format!("cannot write {}", marker.display()))?;
    let written = (|| {
        let (mut db, _) = WorldDb::open(dir, identity)?;
        // Checked again on the open store: nothing may be overwritten.
        if db.state()?.is_some() {
            bail!(
                "{} already holds this world; import into an empty --state directory (nothing was changed)",
                dir.display()
            );
        }
        write_everything(&mut db, st)
            .with_context(|| format!("cannot import into {}", dir.display()))
    })();
    match written {
        Ok(stats) => {
            std::fs::remove_file(&marker)
                .with_context(|| format!("cannot remove {}", marker.display()))?;
            if let Ok(d) = std::fs::File::open(dir) {
                let _ = d.sync_all();
            }
            Ok(stats)
        }
        Err(e) => {
            // As it was found: a store and manifest this import made go
            // (never one that was there before it).
            if made_store {
                let _ = std::fs::remove_file(&store_file);
                let _ = std::fs::remove_file(&manifest_file);
            }
            let _ = std::fs::remove_file(&marker);
            Err(e)
        }
    }
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
        crate::say!("warning: {w}");
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
    let hash = checkpoint::write_backup(
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
        identity,
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
    // Nor over what it reads: the config, its scripts, the world's source
    // (regression, odd-paths probe: `export world.toml --world world.toml`
    // replaced the config with the backup, exit 0).
    let config = Path::new(&cfg.file);
    let mut inputs: Vec<(&str, &Path)> = vec![("world config", config)];
    if let Some(f) = cfg.source.file() {
        inputs.push(("world's source file", f));
    }
    for (what, input) in &inputs {
        if crate::config::same_file(out, input) {
            bail!(
                "{} is the {what} export reads: name another file (nothing was written)",
                out.display()
            );
        }
    }
    if !cfg.scripts_embedded
        && let (Ok(scripts), Some(parent)) = (cfg.scripts_dir.canonicalize(), out.parent())
        && (if parent.as_os_str().is_empty() {
            Path::new(".")
        } else {
            parent
        })
        .canonicalize()
        .is_ok_and(|p| p == scripts)
    {
        bail!(
            "{} lies in the scripts directory {}: name a file elsewhere (nothing was written)",
            out.display(),
            cfg.scripts_dir.display()
        );
    }
    // Nor over anything but an earlier backup of this world.
    if let Err(why) = super::checkpoint::backup_target(out, &cfg.identity()) {
        bail!("{} {why} (nothing was written)", out.display());
    }
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
    // Under the lock: a running import holds it (found by review: export
    // called a live import "interrupted").
    refuse_interrupted_import(dir)?;
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
    super::persistence::seed_materials(&db, &mut world)?;
    let comparable = match super::daemon::load_scripts(cfg, &mut world, &mut ws) {
        Ok(()) => true,
        Err(e) => {
            crate::say!(
                "warning: {e:#}: exported all the same; the world hash is left out, as it would not match run's"
            );
            ws = WorldSim::with_edges(&mut world, true);
            ws.sim.channels_mut().take_dirty();
            // The simulation's colours again as stored.
            super::persistence::seed_materials(&db, &mut world)?;
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
        crate::say!("warning: {c}");
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
