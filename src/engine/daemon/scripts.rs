//! What a start reads of the scripts folder: the folder's watch (begun
//! before anything is read), `materials.lua` and the stored material ids
//! reconciled, and the config's scripts loaded with their rates and
//! parameters.

use anyhow::{Context, Result};
use rustc_hash::FxHashSet;

use super::super::persistence;
use super::super::world_config::WorldConfig;
use super::load_source;
use super::materials_source;
use crate::persist::WorldDb;
use crate::scene::SceneWorld;
use crate::sim::{Limits, ScriptWatcher, WorldSim};

/// Hot reload: the scripts directory is watched; a changed script is
/// compiled and smoke-tested in a fresh VM and swapped in between steps; a
/// broken one keeps the last good version running. The watch starts
/// before `materials.lua` and the scripts are read, so a save during the
/// start is reloaded once it is done (regression, hot-edit probe: it was
/// never seen, and the old rule ran on).
/// A folder that cannot be watched is said once the scripts have loaded
/// (review: a missing folder's "hot reload is off" came before the error
/// that named the missing script).
pub(super) fn start_watcher(
    cfg: &WorldConfig,
) -> Result<Option<ScriptWatcher>, crate::sim::SimError> {
    if cfg.scripts_embedded {
        crate::say!(
            "note: the default world's scripts are built in; `brickworld init DIR` writes editable copies (hot reload watches them)"
        );
        Ok(None)
    } else {
        ScriptWatcher::new(&cfg.scripts_dir, std::time::Duration::from_millis(150)).map(Some)
    }
}

/// Names no file declares any more keep their stored ids; once few ids
/// are left, or `materials.lua` needs more new ones than are free, those
/// that no stored voxel holds are freed before it loads (else a file that
/// needs more ids could never start again; regression, review: a rename
/// of 40 names with 34 ids free failed at every start, as only the first
/// rule was checked). `scene`: the names the scene itself declares.
pub(super) fn reconcile_materials(
    cfg: &WorldConfig,
    db: &WorldDb,
    world: &mut SceneWorld,
    scene: Vec<(u8, String)>,
) -> Result<()> {
    let listed = materials_lua_names(cfg)?;
    let wanted = listed
        .iter()
        .filter(|n| world.materials.id(n).is_none())
        .count();
    let free = world.materials.free_ids();
    if free < persistence::RECLAIM_BELOW || wanted > free {
        let mut declared = declared_materials(cfg, listed)?;
        declared.extend(scene.into_iter().map(|(_, n)| n));
        say_reclaimed(&persistence::reclaim_materials(db, world, &declared)?);
    }
    Ok(())
}

/// `materials.lua`, then the config's scripts with their rates and
/// parameters.
pub(crate) fn load_scripts(
    cfg: &WorldConfig,
    world: &mut SceneWorld,
    ws: &mut WorldSim,
) -> Result<()> {
    // materials.lua (optional) names the materials voxel scripts use.
    if let Some(src) = materials_source(cfg)? {
        // Its errors name materials.lua and the line already.
        ws.load_materials(world, &src)?;
    }
    for (i, s) in cfg.scripts.iter().enumerate() {
        let id = ws
            .add_script(world, script_source(cfg, i)?, Limits::default())
            .with_context(|| format!("cannot load script {}", s.file))?;
        ws.set_every(id, s.every);
        for (k, v) in &s.params {
            ws.set_param(id, k, *v)
                .with_context(|| format!("{}: scripts[{i}].params", cfg.file))?;
        }
    }
    Ok(())
}

/// The source of the config's script `i`; a file that cannot be read is
/// named with the config and field that name it (docs walk: "cannot read
/// …/wter.lua" said neither).
fn script_source(cfg: &WorldConfig, i: usize) -> Result<crate::sim::ScriptSource> {
    load_source(cfg, &cfg.scripts[i].file)
        .with_context(|| format!("{}: scripts[{i}].file", cfg.file))
}

/// The names `materials.lua` declares (none without one), read without
/// registering anything; its errors are those [`load_scripts`] gives.
/// Only it can ask for new ids: scripts name registered materials only.
fn materials_lua_names(cfg: &WorldConfig) -> Result<Vec<String>> {
    let Some(src) = materials_source(cfg)? else {
        return Ok(Vec::new());
    };
    let mut scratch = crate::world::MaterialRegistry::new();
    Ok(crate::sim::runtime::materials::load_materials(
        &src,
        &mut scratch,
    )?)
}

/// The material names declared by `materials.lua` (`listed`, from
/// [`materials_lua_names`]) and the config's scripts (a script's
/// `materials`, `only`, `keep_awake` and `fills`), read without
/// registering anything: a dry pass of [`load_scripts`], whose errors are
/// the same.
fn declared_materials(cfg: &WorldConfig, listed: Vec<String>) -> Result<FxHashSet<String>> {
    let mut declared: FxHashSet<String> = listed.into_iter().collect();
    for (i, s) in cfg.scripts.iter().enumerate() {
        let (_, spec) = crate::sim::ScriptVm::load(&script_source(cfg, i)?, Limits::default())
            .with_context(|| format!("cannot load script {}", s.file))?;
        declared.extend(
            (spec.materials.into_iter())
                .chain(spec.only)
                .chain(spec.keep_awake)
                .chain(spec.fills.into_iter().map(|(_, m)| m)),
        );
    }
    Ok(declared)
}

/// Say what [`persistence::reclaim_materials`] did, if anything.
fn say_reclaimed(r: &persistence::Reclaimed) {
    if let Some(why) = &r.skipped {
        crate::say!(
            "warning: material ids were not reclaimed: {why}; names no file declares keep their ids"
        );
    }
    if !r.freed.is_empty() {
        let n = r.freed.len();
        let listed = if n <= 10 {
            r.freed.join(", ")
        } else {
            format!("{} and {} more", r.freed[..10].join(", "), n - 10)
        };
        crate::say!(
            "materials: freed {n} id{} of names that nothing declares and no stored voxel holds ({listed}); {} such name{} still held by voxels keep{} theirs",
            if n == 1 { "" } else { "s" },
            r.held,
            if r.held == 1 { "" } else { "s" },
            if r.held == 1 { "s" } else { "" },
        );
    }
}
