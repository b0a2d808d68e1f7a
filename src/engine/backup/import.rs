//! `brickworld import`: a backup file into an empty state directory,
//! guarded by the marker an interrupted import leaves ([`IMPORT_MARKER`]),
//! and the contents checked against the world's bounds first.

use std::path::Path;

use anyhow::{Context, Result, bail};

use super::interrupt::{self, Phase};
use super::write_everything;
use crate::engine::checkpoint::{self, WorldIdentity, WorldState};
use crate::engine::world_config::WorldConfig;
use crate::persist::{CommitStats, WorldDb};

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
/// The command it prints names the world's config (`world_file`, as the
/// config's errors name it) unless it is the embedded default, and quotes
/// both paths for a shell (regression, stop-path probe: it left out
/// `--world`, so followed for another world it was refused).
pub fn refuse_interrupted_import(dir: &Path, world_file: &str) -> Result<()> {
    let marker = dir.join(IMPORT_MARKER);
    if std::fs::symlink_metadata(&marker).is_ok() {
        if WorldDb::has_state(dir) {
            let _ = std::fs::remove_file(&marker);
            return Ok(());
        }
        let world = if world_file == "<embedded default>" {
            String::new()
        } else {
            format!(" --world {}", crate::shell_quoted(Path::new(world_file)))
        };
        bail!(
            "an import into {} was interrupted ({} is there): run brickworld import FILE{world} --state {} again",
            dir.display(),
            marker.display(),
            crate::shell_quoted(dir)
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
    // `BRICKWORLD_TEST_IMPORT_CHECK_STALL_MS`: a pause once the backup is
    // read, before anything is written, so a test can interrupt the
    // import there. Unset in normal use.
    if let Some(ms) = std::env::var("BRICKWORLD_TEST_IMPORT_CHECK_STALL_MS")
        .ok()
        .and_then(|v| v.parse().ok())
    {
        crate::say!("test hook: the import is stalled before it writes");
        std::thread::sleep(std::time::Duration::from_millis(ms));
    }
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
    // this import's to replace. Its marker stays (written again below):
    // removed first, a cut before the new one was written left a directory
    // that `run` took for a fresh world (found by review).
    if replace {
        interrupt::enter(Phase::Writing {
            dir: dir.to_path_buf(),
        });
        for p in [&store_file, &manifest_file] {
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
    // The phase says "writing" once the marker is there (review: said
    // before, an interrupt then claimed a refusal no marker made, and
    // left the folders the import had made).
    interrupt::enter_after(
        Phase::Writing {
            dir: dir.to_path_buf(),
        },
        || write_durable_marker(&marker),
    )
    .with_context(|| format!("cannot write {}", marker.display()))?;
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
            interrupt::enter_after(Phase::Done, || std::fs::remove_file(&marker))
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
            // Redoing a cut import, the marker stays: removed, a cut before
            // `import` wrote it again left a directory `run` took for a
            // fresh world (review).
            if !replace {
                let _ = interrupt::back_to_checking_after(|| std::fs::remove_file(&marker));
            }
            Err(e)
        }
    }
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
    let (lock, created) = crate::engine::state_dir::claim(dir)?;
    interrupt::enter(Phase::Checking {
        made: created.clone(),
        lock_file: (created.is_empty() && !had_lock).then(|| lock_file.clone()),
        marker: dir.join(IMPORT_MARKER),
    });
    let result = import(file, dir, &cfg.identity());
    if result.is_err() {
        // An interrupt during the cleanup finishes it (review: it said
        // "did not finish" and left the folders made).
        interrupt::back_to_checking();
        if !created.is_empty() {
            crate::files::remove_made(&created);
        } else if !had_lock {
            let _ = std::fs::remove_file(&lock_file);
        }
        // As it was found, or refused with the marker an earlier cut left.
        interrupt::enter(Phase::Idle);
    }
    drop(lock);
    result
}
