//! Streamed worlds (`[stream]` in the world config) at the engine's edge:
//! which part of the world stays resident, and whether the memory budget
//! can hold one view.
//!
//! A streamed world keeps two things in memory:
//! - the **simulated region** (`[sim] region`, rounded outward to whole
//!   chunk columns of 64 × 64 voxels): the engine's world, stepped, edited,
//!   committed and resumed exactly like a small world, plus the render
//!   thread's copy of it;
//! - the **render window**: the chunk columns within the view distance of
//!   the camera, generated on first touch by fetcher threads, with a
//!   byte-budgeted LRU cache of the columns that left it
//!   ([`crate::scene::RenderWindow`]).
//!
//! Everything else is never built: far terrain is a pure function of the
//! seed, regenerated when the camera comes back, and stored only once
//! edited (only the simulated region is edited, so only its chunks ever
//! reach the world store).

use std::sync::Arc;

use anyhow::{Context, Result, bail};
use glam::{IVec2, IVec3};

use super::world_config::{SimRegion, StreamSettings, WorldConfig};
use crate::scene::{CHUNK_VOXELS, ChunkGen, SceneWorld, WindowSettings, budget};

/// What the render thread needs to stream a world.
#[derive(Clone, Debug)]
pub struct StreamPlan {
    /// The generator of far columns.
    pub gen_: Arc<ChunkGen>,
    /// Chunk columns `[min, max)` of the simulated region (the engine's
    /// world), copied from it rather than generated.
    pub live: (IVec2, IVec2),
    /// The window's size and its share of the budget.
    pub window: WindowSettings,
}

/// Bytes a world's bricks and grid hold (the same measure the window uses).
pub fn world_bytes(world: &SceneWorld) -> u64 {
    let store = world.store();
    (store.pool().bytes()
        + store.pool().index_bytes()
        + world.grid().bytes()
        + store.non_empty_bricks() * 24) as u64
}

/// Build the simulated region of a streamed world and the plan for
/// streaming the rest.
pub fn build_region(
    cfg: &WorldConfig,
    stream: &StreamSettings,
) -> Result<(SceneWorld, StreamPlan)> {
    let SimRegion::Box { min, max } = cfg.sim_region else {
        bail!("sim.region: a streamed world needs a region (validated config)");
    };
    let size = (!cfg.unbounded).then_some(cfg.size);
    let gen_ = ChunkGen::new(&cfg.source, size, cfg.size.y, cfg.seed)?;
    let lo = IVec2::new(
        min.x.div_euclid(CHUNK_VOXELS),
        min.y.div_euclid(CHUNK_VOXELS),
    );
    let hi = IVec2::new(
        (max.x + CHUNK_VOXELS - 1).div_euclid(CHUNK_VOXELS),
        (max.y + CHUNK_VOXELS - 1).div_euclid(CHUNK_VOXELS),
    );
    let cols = (hi - lo).as_i64vec2();
    budget::check_world(
        "sim.region",
        IVec3::new(
            (cols.x * CHUNK_VOXELS as i64).min(1 << 20) as i32,
            cfg.size.y,
            (cols.y * CHUNK_VOXELS as i64).min(1 << 20) as i32,
        ),
    )?;
    let world = gen_
        .build_region(lo, hi)
        .context("cannot build the simulated region")?;
    let plan = StreamPlan {
        gen_: Arc::new(gen_),
        live: (lo, hi),
        window: WindowSettings {
            radius: WindowSettings::radius_for(stream.view_distance),
            budget_bytes: stream.memory_budget,
            fetchers: stream.fetchers,
        },
    };
    Ok((world, plan))
}

/// Memory the scripts, their Luau VMs and the simulation's channels are
/// allowed for in the start-up check (they are measured, not estimated,
/// once the first window is exact).
const RUNTIME_MARGIN: u64 = 64 << 20;

/// Check that `budget`, the process's resident-memory target, holds what
/// the process holds now (the engine's simulated region among it), the
/// renderer's copy of the region, one full window (its columns estimated
/// from the region's own) and [`RUNTIME_MARGIN`]; on success the budget
/// goes to the window, whose cache gets what is left. The error names the
/// minimum.
pub fn check_budget(region: &SceneWorld, plan: &mut StreamPlan, budget: u64) -> Result<()> {
    let now = budget::rss_kb() * 1024;
    let region_bytes = world_bytes(region);
    let region_cols = {
        let d = plan.live.1 - plan.live.0;
        (d.x as u64 * d.y as u64).max(1)
    };
    let per_col = (region_bytes - region.grid().bytes() as u64) / region_cols;
    let side = 2 * plan.window.radius as u64 + 1;
    let window_cols = side * side;
    let y_bricks = region.grid().dims().y as u64;
    let window_grid = window_cols * 64 * y_bricks * 4 + window_cols * y_bricks;
    let window_min = window_cols * per_col + window_grid;
    let need = now + region_bytes + window_min + RUNTIME_MARGIN;
    if budget < need {
        bail!(
            "memory budget {} is too small for one view: the engine holds {} with the simulated region, the renderer's copy of the region needs {}, a window of {} chunk columns for the view distance about {}, and the scripts {}: at least {}; raise --memory-budget or [stream] memory_budget to {}, or lower [stream] view_distance or shrink [sim] region",
            budget::human(budget),
            budget::human(now),
            budget::human(region_bytes),
            window_cols,
            budget::human(window_min),
            budget::human(RUNTIME_MARGIN),
            budget::human(need),
            // A little above the minimum: what the process holds varies.
            budget::human((need + need / 16).next_multiple_of(1 << 20)),
        );
    }
    plan.window.budget_bytes = budget;
    Ok(())
}
