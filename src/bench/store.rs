//! `brickworld bench store`: what the world store costs on a real terrain —
//! encoding and committing N dirty chunks in one transaction, the bytes that
//! takes, and restoring (regenerate-and-overlay) a world from the store.

use std::path::Path;
use std::time::Instant;

use anyhow::Result;
use glam::IVec3;
use serde::Serialize;

use crate::engine::checkpoint::WorldIdentity;
use crate::engine::persistence::{DirtyChunks, commit, restore_chunks};
use crate::persist::WorldDb;
use crate::scene::{SceneSpec, build_scene};
use crate::sim::WorldSim;

/// The report.
#[derive(Debug, Clone, Serialize)]
pub struct StoreBench {
    /// World size in voxels.
    pub size: [i32; 3],
    /// Chunks of the world (8³ bricks each).
    pub world_chunks: usize,
    /// Chunks per commit.
    pub chunks: usize,
    /// Chunk columns per commit.
    pub columns: usize,
    /// Wall time of each commit (encoding, transaction, fsync), ms.
    pub commit_ms: Vec<f64>,
    /// Best commit, ms.
    pub commit_best_ms: f64,
    /// Bytes one commit wrote (blobs).
    pub commit_bytes: usize,
    /// Mean blob bytes per chunk.
    pub bytes_per_chunk: f64,
    /// The store file after the commits, bytes.
    pub store_file_bytes: u64,
    /// Regenerating the world from its source, ms.
    pub generate_ms: f64,
    /// Reading, decoding and overlaying every stored chunk, ms.
    pub restore_ms: f64,
}

/// Commit the first `chunks` chunks of a `size` terrain (every chunk of the
/// world if fewer) `repeats` times into a fresh store under `dir`, then
/// restore the world from it.
pub fn run(size: IVec3, chunks: usize, repeats: usize, dir: &Path) -> Result<StoreBench> {
    let spec = SceneSpec::Terrain { caves: false };
    let identity = WorldIdentity {
        source: "terrain".into(),
        size: size.to_array(),
        seed: 1,
        config_hash: 0,
    };
    let scratch =
        crate::files::fresh_scratch_dir(dir).map_err(|e| anyhow::anyhow!("invalid --dir: {e}"))?;
    let hidden = indicatif::ProgressBar::hidden();
    let t = Instant::now();
    let mut world = build_scene(&spec, size, 1, &hidden)?;
    let generate_ms = t.elapsed().as_secs_f64() * 1e3;
    let mut ws = WorldSim::with_edges(&mut world, true);
    ws.sim.channels_mut().take_dirty();
    let (mut db, _) = WorldDb::open(dir, &identity)?;
    let mut all = DirtyChunks::default();
    all.everything(&world, &ws);
    let world_chunks = all.chunk_keys().len();
    let mut keys = all.chunk_keys();
    keys.sort_by_key(|k| (k.0.z, k.0.y, k.0.x));
    keys.truncate(chunks);
    let mut commit_ms = Vec::new();
    let mut last = Default::default();
    for _ in 0..repeats.max(1) {
        let mut dirty = DirtyChunks::default();
        // Every brick of the chosen chunks, as an edit would mark them.
        for k in &keys {
            dirty.bricks(&[k.min_brick()]);
        }
        // And their columns' channels, as the simulation's writes would.
        for k in &keys {
            let t0 = glam::IVec2::new(k.0.x, k.0.z) << crate::persist::chunk::CHUNK_SHIFT;
            if let Some(g) = ws.sim.channels().find("ground")
                && let Some(v) = ws.sim.channels().get(t0, g).copied()
            {
                ws.sim.channels_mut().set(t0, g, &v);
            }
        }
        let t = Instant::now();
        last = commit(&mut db, &mut dirty, &world, &mut ws, None)?;
        commit_ms.push(t.elapsed().as_secs_f64() * 1e3);
    }
    let store_file_bytes = db.file_bytes();
    drop(db);
    let (db, _) = WorldDb::open(dir, &identity)?;
    let mut fresh = build_scene(&spec, size, 1, &hidden)?;
    let mut ws2 = WorldSim::with_edges(&mut fresh, true);
    let t = Instant::now();
    let mut dirty = DirtyChunks::default();
    let scope = crate::engine::persistence::RestoreScope {
        regenerable: true,
        ..Default::default()
    };
    restore_chunks(&db, &mut fresh, &mut ws2, &mut dirty, scope)?;
    let restore_ms = t.elapsed().as_secs_f64() * 1e3;
    drop(scratch);
    Ok(StoreBench {
        size: size.to_array(),
        world_chunks,
        chunks: last.chunks,
        columns: last.columns,
        commit_best_ms: commit_ms.iter().copied().fold(f64::INFINITY, f64::min),
        commit_ms,
        commit_bytes: last.bytes,
        bytes_per_chunk: last.bytes as f64 / (last.chunks + last.columns).max(1) as f64,
        store_file_bytes,
        generate_ms,
        restore_ms,
    })
}
