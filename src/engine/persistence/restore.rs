//! Restoring a world from the store at start: the stored frame of an
//! imported world, the stored material ids, the chunks and chunk columns
//! laid over the regenerated world, and the state blob applied once the
//! scripts are loaded (see the parent module for the order and why).

use glam::{IVec2, IVec3};
use rustc_hash::FxHashSet;

use super::DirtyChunks;
use crate::engine::checkpoint::WorldState;
use crate::persist::chunk::{self, CHUNK_SHIFT};
use crate::persist::{ChunkKey, ColumnKey, StoreError, WorldDb, state};
use crate::scene::SceneWorld;
use crate::sim::WorldSim;

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

/// Put the store's material registry under the world's (see
/// [`MaterialRegistry::under`](crate::world::MaterialRegistry::under)),
/// before `materials.lua` and the scripts load: a stored name keeps its
/// id, and the scripts resolve the ids the stored voxels hold. Nothing
/// changes for a store never committed, or one whose state names no
/// materials (older files).
pub fn seed_materials(db: &WorldDb, world: &mut SceneWorld) -> Result<(), StoreError> {
    let Some(blob) = db.state()? else {
        return Ok(());
    };
    let st = state::decode(&blob).map_err(|msg| StoreError::Db {
        path: db.path().to_path_buf(),
        msg: format!("{msg}; the chunks are intact, but the world cannot resume without it"),
    })?;
    if st.extras.materials.is_empty() {
        return Ok(());
    }
    let stored =
        crate::world::MaterialRegistry::from_entries(&st.extras.materials, st.store.palette());
    world.materials = world.materials.under(&stored);
    // Stored colours first (`materials.lua` recolours over them later);
    // generated bricks get their LOD colours.
    let mut palette = st.store.palette().clone();
    world.materials.apply(&mut palette);
    world.set_palette(palette);
    Ok(())
}

/// Below this many free material ids, a start looks for ids to reclaim
/// (see [`reclaim_materials`]), as it does whenever `materials.lua` asks
/// for more new ids than are free; otherwise the scan of the store is not
/// worth its time.
pub const RECLAIM_BELOW: usize = 32;

/// What [`reclaim_materials`] did.
#[derive(Debug, Default, PartialEq)]
pub struct Reclaimed {
    /// Names forgotten, their ids free for new names.
    pub freed: Vec<String>,
    /// Names nothing declares that stored voxels still hold: kept.
    pub held: usize,
    /// Why nothing was reclaimed although names could have been (a chunk
    /// that could not be read may hold any of them).
    pub skipped: Option<String>,
}

/// Free the ids of materials that nothing declares and no stored voxel
/// holds; run at a start once fewer than [`RECLAIM_BELOW`] ids are free or
/// `materials.lua` needs more than are free, after [`seed_materials`] and
/// before `materials.lua` and the scripts load.
///
/// A name keeps its id while the engine runs, even once no file declares
/// it, since voxels may hold it (and a running script may have resolved
/// it); renaming materials often enough would otherwise fill the registry
/// for the world's life. At a start the store holds every voxel that was
/// not generated (generated voxels hold the scene's materials, which are
/// `declared`), so a name that is neither declared nor held by a stored
/// chunk can go. The commit after writes the registry without it. Any
/// chunk that cannot be read stops the reclaim: it may hold any id.
pub fn reclaim_materials(
    db: &WorldDb,
    world: &mut SceneWorld,
    declared: &FxHashSet<String>,
) -> Result<Reclaimed, StoreError> {
    let mut out = Reclaimed::default();
    let orphans: Vec<(u8, String)> = world
        .materials
        .names()
        .into_iter()
        .filter(|(_, n)| !declared.contains(n))
        .collect();
    if orphans.is_empty() {
        return Ok(out);
    }
    let mut held = [false; 256];
    for k in db.chunk_keys()? {
        let Some(blob) = db.chunk(k)? else { continue };
        if let Err(e) = chunk::held_materials(&blob, &mut held) {
            out.skipped = Some(format!("{k} cannot be read ({e})"));
            return Ok(out);
        }
    }
    for (id, name) in orphans {
        if held[id as usize] {
            out.held += 1;
        } else {
            world.materials.remove(&name);
            out.freed.push(name);
        }
    }
    Ok(out)
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
    // Which stored tiles apply. With the same simulated area as the store's
    // world, all of them: its moat is this run's moat. With another (a
    // streamed region elsewhere, or none), only the tiles that world
    // simulated as its own, and none onto this run's moat: the stored moat
    // ring is made-up ground that must not land on real columns, which
    // keep the ground read from their voxels (regression, panic audit: a
    // region's backup imported into the whole world, or a region moved in
    // the config, zeroed the ground of 8 chunk columns under intact
    // voxels). A stored tile outside this run's area is kept as it was, so
    // it is committed again with its column, not lost.
    let same_area = st.bounds == (lo, hi);
    let inside = |t: crate::sim::tile::TileCoord, (a, b): (IVec2, IVec2)| {
        t.cmpge(a).all() && t.cmplt(b).all()
    };
    let stored_tiles = crate::sim::writeback::tiles_of(st.bounds.0, st.bounds.1);
    let own_tiles = crate::sim::writeback::tiles_of(lo, hi);
    let (tmin, tmax) = ws.sim.tile_bounds();
    let stored_area = |t: crate::sim::tile::TileCoord| {
        let moat = inside(t, (tmin, tmax)) && !inside(t, own_tiles);
        same_area || (inside(t, stored_tiles) && !moat)
    };
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
    // The registry the scripts were loaded against must give every stored
    // name its stored id ([`seed_materials`] saw to that); it is kept, so
    // that `materials.lua`'s new names and colours stay. Its colours go
    // over the stored palette before any brick is decoded, so that far
    // bricks' LOD colours are the new ones.
    let stored_materials = (!st.extras.materials.is_empty()).then(|| {
        crate::world::MaterialRegistry::from_entries(&st.extras.materials, st.store.palette())
    });
    if let Some(m) = stored_materials
        .as_ref()
        .and_then(|s| world.materials.disagreement(s))
    {
        return Err(StoreError::Db {
            path: db.path().to_path_buf(),
            msg: format!(
                "the stored material {m} has another id in the registry the scripts were loaded against (the store's registry was not put under it first)"
            ),
        });
    }
    let mut palette = st.store.palette().clone();
    if stored_materials.is_some() {
        world.materials.apply(&mut palette);
    }
    // (An older state names no materials: its palette as stored.)
    world.set_palette(palette);
    let (overlay, _) = world.edit(|store, _| -> Result<_, StoreError> {
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
                    chunk::apply_column(k, &data, ws.sim.channels_mut(), stored_area);
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

/// Apply a restored state blob once the scripts are loaded: tick, sleep
/// states, the drained total, the parameters and the scripts' health.
/// Returns warnings (parameters a changed script no longer accepts, a
/// suspension lifted because its script changed).
pub fn apply_state(st: &WorldState, ws: &mut WorldSim) -> Vec<String> {
    use crate::persist::bytes::fnv1a;
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
                    // A tiny or huge value in scientific notation (regression,
                    // fuzzing: 1e-320 was printed with 320 digits).
                    warnings.push(format!(
                        "the stored {script}.{k} = {} is not kept: {e}",
                        crate::sim::fmt_num(*v)
                    ));
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
    // A script whose file changed while the engine was stopped is a
    // reload: what it runs on wakes, as a hot reload wakes it (regression,
    // determinism probe: a rule changed while stopped found every brick
    // asleep, and the world differed from one reloaded live at that tick).
    // A script the state does not name was added (or renamed) while it
    // was stopped: what it runs on wakes too (regression, review: an added
    // rule found every brick asleep). States written before the sources
    // were kept name none, and wake nothing more than they did.
    if !extras.sources.is_empty() {
        for i in 0..ws.script_count() {
            let script = ws.spec(i).name.clone();
            let source = fnv1a(ws.source(i).text.as_bytes());
            let said = match extras.sources.iter().find(|(s, _)| *s == script) {
                Some((_, stored)) if *stored == source => continue,
                Some(_) => format!("{script}.lua changed while the engine was stopped"),
                None => format!("{script}.lua is new to this world"),
            };
            ws.wake_for_reload(i);
            // A suspension lifted has said it already.
            if !warnings.iter().any(|w| w.starts_with(&said)) {
                warnings.push(format!("{said}: what it runs on wakes, as at a reload"));
            }
        }
    }
    warnings
}
