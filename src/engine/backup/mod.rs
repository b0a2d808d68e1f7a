//! Single-file backups of a world store: [`export`](fn@export) (the committed world as
//! one checkpoint file), [`import`](fn@import) (one into an empty state directory),
//! and the migration of a state directory written by the whole-world
//! checkpoints of earlier versions ([`migrate_legacy`]).
//!
//! `export.rs` writes a backup, `import.rs` reads one into a state
//! directory (`interrupt.rs`: what Ctrl-C does meanwhile); both write through [`write_everything`] or the checkpoint
//! format (`super::checkpoint`).

mod export;
mod import;
mod interrupt;

use std::path::Path;

use anyhow::{Context, Result, bail};

pub use export::{export, export_world};
pub use import::{IMPORT_MARKER, import, import_world, refuse_interrupted_import};
pub use interrupt::say_interrupted_imports;

use super::checkpoint::{self, WorldIdentity, WorldState};
use super::persistence::DirtyChunks;
use crate::persist::{CommitStats, WorldDb, state};
use crate::scene::SceneWorld;
use crate::sim::WorldSim;

/// Write the whole of a store's world into a fresh store: every chunk and
/// chunk column of its bounds (an empty chunk overrides the source's) and
/// the state. Used by [`import`](fn@import) and [`migrate_legacy`].
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
