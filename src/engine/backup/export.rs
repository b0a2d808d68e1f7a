//! `brickworld export`: the committed world of a state directory as one
//! checkpoint file, written only where nothing is or over an earlier backup
//! of the same world, never over the files it reads.

use std::path::Path;

use anyhow::{Result, bail};

use super::import::refuse_interrupted_import;
use crate::engine::checkpoint::{self, SimExtras, WorldIdentity, WorldRef, WorldState};
use crate::engine::persistence::{DirtyChunks, RestoreScope, engine_hash, restore_chunks};
use crate::engine::world_config::WorldConfig;
use crate::persist::WorldDb;
use crate::scene::SceneWorld;
use crate::sim::WorldSim;

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
    if let Err(why) = crate::engine::checkpoint::backup_target(out, &cfg.identity()) {
        bail!("{} {why} (nothing was written)", out.display());
    }
    if cfg.stream.is_some()
        && matches!(
            cfg.sim_region,
            crate::engine::world_config::SimRegion::AroundCamera { .. }
        )
    {
        bail!(
            "export writes one region, and this world's simulated region follows the camera: its store holds every place the region has been. Back it up by copying {} and {} while the engine is stopped (nothing was written)",
            dir.join(crate::persist::db::DB_FILE).display(),
            dir.join(crate::persist::db::MANIFEST_FILE).display()
        );
    }
    let _lock = crate::engine::state_dir::lock(dir)?;
    // Under the lock: a running import holds it (found by review: export
    // called a live import "interrupted").
    refuse_interrupted_import(dir, &cfg.file)?;
    let identity = cfg.identity();
    let (db, _) = WorldDb::open(dir, &identity)?;
    let mut world = match &cfg.stream {
        // A streamed world's backup is its fixed simulated region.
        Some(_) => {
            let (gen_, rule) = crate::engine::streaming::generator(cfg)?;
            let columns = rule.around(glam::DVec3::ZERO);
            crate::engine::streaming::build_columns(&gen_, columns)?
        }
        None => crate::engine::daemon::fixed_world(cfg, &db)?,
    };
    let mut ws = WorldSim::with_edges(&mut world, true);
    ws.sim.channels_mut().take_dirty();
    ws.set_seed(cfg.seed);
    // The scripts register their channels before the stored chunks go
    // over the world, as at start, so channel ids and the world hash are
    // those `run` prints. A world whose scripts no longer load is still
    // exported (its data is stored by channel name); only the hash is
    // left out.
    crate::engine::persistence::seed_materials(&db, &mut world)?;
    let comparable = match crate::engine::daemon::load_scripts(cfg, &mut world, &mut ws) {
        Ok(()) => true,
        Err(e) => {
            crate::say!(
                "warning: {e:#}: exported all the same; the world hash is left out, as it would not match run's"
            );
            ws = WorldSim::with_edges(&mut world, true);
            ws.sim.channels_mut().take_dirty();
            // The simulation's colours again as stored.
            crate::engine::persistence::seed_materials(&db, &mut world)?;
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
