//! The engine's side of the world store ([`crate::persist`]): which chunks
//! changed ([`DirtyChunks`]), restoring a world from the store
//! ([`restore_chunks`], [`apply_state`]) and committing ([`commit`]).
//! Single-file backups are [`super::backup`]'s.
//!
//! **Restoring** regenerates the world from its source, then overlays every
//! stored chunk and chunk column (a stored chunk replaces the generated one
//! whole), then applies the state blob. Only what was ever edited is on
//! disk. A corrupt chunk is reported with its coordinates and regenerated
//! from the source (and rewritten at the next commit); the rest of the world
//! loads as stored.

mod restore;
pub use restore::{
    RECLAIM_BELOW, Reclaimed, RestoreScope, Restored, StoredFrame, apply_state, reclaim_materials,
    restore_chunks, seed_materials, stored_frame,
};

use glam::{IVec2, IVec3};
use rayon::prelude::*;
use rustc_hash::FxHashSet;

use super::checkpoint::{self, CameraOverride, SimExtras};
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

/// Encoded chunk and chunk-column blobs, ready for one commit.
pub type Blobs = (Vec<(ChunkKey, Vec<u8>)>, Vec<(ColumnKey, Vec<u8>)>);

impl DirtyChunks {
    /// Every chunk and chunk column recorded, encoded (in parallel).
    pub fn encode(&self, world: &SceneWorld, ws: &WorldSim) -> Blobs {
        let (store, voxel, columns) = (world.store(), ws.vox.channels(), ws.sim.channels());
        let chunks = self
            .chunks
            .par_iter()
            .map(|k| (*k, chunk::encode_chunk(*k, store, voxel)))
            .collect();
        let cols = self
            .columns
            .par_iter()
            .map(|k| (*k, chunk::encode_column(*k, columns)))
            .collect();
        (chunks, cols)
    }

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
        sources: (0..ws.script_count())
            .map(|i| {
                let text = ws.source(i).text;
                (
                    ws.spec(i).name.clone(),
                    crate::persist::bytes::fnv1a(text.as_bytes()),
                )
            })
            .collect(),
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
    let (chunks, cols) = dirty.encode(world, ws);
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

/// The hash a run reports when it resumes and when it stops: the bricks,
/// the column channels and the voxel channels (O(world): not per commit).
pub fn engine_hash(world: &SceneWorld, ws: &WorldSim) -> u64 {
    checkpoint::world_hash(world.store(), ws.sim.channels())
        ^ ws.vox.channels().hash().rotate_left(17)
}
