//! Streamed worlds (`[stream]` in the world config) at the engine's edge:
//! which part of the world stays resident, and whether the memory budget
//! can hold one view.
//!
//! A streamed world keeps two things in memory:
//! - the **simulated region** (`[sim] region`, rounded outward to whole
//!   chunk columns of 64 × 64 voxels, or `[sim] radius`, a square that
//!   follows the camera: [`RegionRule`]): the engine's world, stepped,
//!   edited, committed and resumed exactly like a small world, plus the
//!   render thread's copy of it;
//! - the **render window**: the chunk columns within the view distance of
//!   the camera, generated on first touch by fetcher threads, with a
//!   byte-budgeted LRU cache of the columns that left it
//!   ([`crate::scene::RenderWindow`]).
//!
//! Everything else is never built: far terrain is a pure function of the
//! seed, regenerated when the camera comes back, with the chunks the store
//! holds laid over it ([`store_overlay`]). Only the simulated region is
//! edited, so only chunks it covered ever reach the store.
//!
//! A region that follows the camera **moves** at a step boundary: the
//! engine commits, then rebuilds the region at its new place exactly as a
//! resume would (generate, lay the stored chunks and columns over it, apply
//! the state). Moving therefore costs a commit and a rebuild, not a copy
//! of anything far, and a run that stops and resumes moves at the same
//! ticks to the same places: where the region is, is part of the committed
//! state (the state blob's bounds).

use std::sync::Arc;

use anyhow::{Context, Result, bail};
use glam::{DVec3, IVec2, IVec3};
use rustc_hash::FxHashSet;

use super::world_config::{SimRegion, StreamSettings, WorldConfig};
use crate::persist::{ChunkKey, StoreReader, chunk};
use crate::scene::{CHUNK_VOXELS, ChunkGen, ColumnOverlay, SceneWorld, WindowSettings, budget};
use crate::world::BrickContent;

/// What the render thread needs to stream a world.
#[derive(Clone)]
pub struct StreamPlan {
    /// The generator of far columns.
    pub gen_: Arc<ChunkGen>,
    /// Chunk columns `[min, max)` of the simulated region (the engine's
    /// world), copied from it rather than generated.
    pub live: (IVec2, IVec2),
    /// The window's size and its share of the budget.
    pub window: WindowSettings,
    /// The stored edits the fetchers lay over generated columns.
    pub overlay: Option<ColumnOverlay>,
}

impl std::fmt::Debug for StreamPlan {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("StreamPlan")
            .field("live", &self.live)
            .field("window", &self.window)
            .field("overlay", &self.overlay.is_some())
            .finish()
    }
}

/// Bytes a world's bricks and grid hold (the same measure the window uses).
pub fn world_bytes(world: &SceneWorld) -> u64 {
    crate::scene::store_bytes(world.store()) + world.grid().bytes() as u64
}

/// Where a streamed world's simulated region lies, in chunk columns.
#[derive(Clone, Copy, Debug, PartialEq)]
pub enum RegionRule {
    /// A fixed region `[min, max)` (`[sim] region`).
    Fixed(IVec2, IVec2),
    /// A square that follows the camera (`[sim] radius`): `2 half + 1`
    /// columns across, re-centred on the camera's column once the camera
    /// is more than [`FOLLOW_SLACK`] columns from the region's centre (and
    /// kept inside a bounded world).
    Follow {
        /// Columns from the centre column to the region's edge.
        half: i32,
        /// A bounded world's chunk columns `[min, max)`.
        world: Option<(IVec2, IVec2)>,
    },
}

/// How far (in chunk columns) the camera may stray from the centre of a
/// region that follows it before the region moves: moving costs a commit
/// and a rebuild of the region, so it happens every few columns of flight,
/// not at every one.
pub const FOLLOW_SLACK: i32 = 1;

impl RegionRule {
    /// The rule of `cfg`'s (validated) simulated region.
    pub fn of(cfg: &WorldConfig, gen_: &ChunkGen) -> Result<Self> {
        match cfg.sim_region {
            SimRegion::Box { min, max } => {
                let lo = IVec2::new(
                    min.x.div_euclid(CHUNK_VOXELS),
                    min.y.div_euclid(CHUNK_VOXELS),
                );
                let hi = IVec2::new(
                    (max.x + CHUNK_VOXELS - 1).div_euclid(CHUNK_VOXELS),
                    (max.y + CHUNK_VOXELS - 1).div_euclid(CHUNK_VOXELS),
                );
                // Clipped to a bounded world's columns, so that its size and
                // memory are those of what is built (regression, world
                // review: a region reaching far past the world was refused
                // for the terabytes of its unclipped box). Validation holds
                // it to overlap the world.
                Ok(match gen_.columns() {
                    Some((a, b)) => RegionRule::Fixed(lo.max(a), hi.min(b)),
                    None => RegionRule::Fixed(lo, hi),
                })
            }
            SimRegion::AroundCamera { radius } => Ok(RegionRule::Follow {
                half: (radius / CHUNK_VOXELS as f64).ceil() as i32,
                world: gen_.columns(),
            }),
            SimRegion::Everywhere => {
                bail!("sim.region: a streamed world needs a region or a radius (validated config)")
            }
        }
    }

    /// Whether the region follows the camera.
    pub fn follows(&self) -> bool {
        matches!(self, RegionRule::Follow { .. })
    }

    /// The region for a camera at `eye` (a fixed region's own).
    pub fn around(&self, eye: DVec3) -> (IVec2, IVec2) {
        match *self {
            RegionRule::Fixed(lo, hi) => (lo, hi),
            RegionRule::Follow { half, world } => {
                let c = column_of(eye);
                let mut lo = c - half;
                let mut hi = c + half + 1;
                if let Some((wlo, whi)) = world {
                    // Inside the world where it fits; the whole world where
                    // it does not.
                    let side = hi - lo;
                    lo = lo.min(whi - side).max(wlo);
                    hi = (lo + side).min(whi);
                }
                (lo, hi)
            }
        }
    }

    /// Where the region `now` should move for a camera at `eye`: None while
    /// the camera is within [`FOLLOW_SLACK`] columns of its centre (or the
    /// region is fixed, or moving would not change it).
    pub fn follow(&self, now: (IVec2, IVec2), eye: DVec3) -> Option<(IVec2, IVec2)> {
        if !self.follows() {
            return None;
        }
        let centre = (now.0 + now.1 - 1).div_euclid(IVec2::splat(2));
        if (column_of(eye) - centre).abs().max_element() <= FOLLOW_SLACK {
            return None;
        }
        let to = self.around(eye);
        (to != now).then_some(to)
    }
}

fn column_of(eye: DVec3) -> IVec2 {
    let clamp = |v: f64| v.floor().clamp(-1e9, 1e9) as i32;
    crate::scene::chunk_column_of(clamp(eye.x), clamp(eye.z))
}

/// The region's voxel bounds in chunk columns (a world built by
/// [`build_columns`] has whole ones).
pub fn columns_of(world: &SceneWorld) -> (IVec2, IVec2) {
    let (lo, hi) = world.bounds();
    columns_of_bounds(lo, hi)
}

/// The chunk columns covering voxel bounds `[lo, hi)` (a stored region's).
pub fn columns_of_bounds(lo: IVec3, hi: IVec3) -> (IVec2, IVec2) {
    (
        IVec2::new(lo.x, lo.z).div_euclid(IVec2::splat(CHUNK_VOXELS)),
        (IVec2::new(hi.x, hi.z) + (CHUNK_VOXELS - 1)).div_euclid(IVec2::splat(CHUNK_VOXELS)),
    )
}

/// Build chunk columns `[lo, hi)` of a streamed world (its simulated
/// region), refusing a region the machine cannot hold.
pub fn build_columns(gen_: &ChunkGen, cols: (IVec2, IVec2)) -> Result<SceneWorld> {
    build_columns_within(gen_, cols, u64::MAX, &indicatif::ProgressBar::hidden())
}

/// [`build_columns`], refused as soon as its bricks pass `limit` bytes.
fn build_columns_within(
    gen_: &ChunkGen,
    (lo, hi): (IVec2, IVec2),
    limit: u64,
    pb: &indicatif::ProgressBar,
) -> Result<SceneWorld> {
    let cols = (hi - lo).as_i64vec2();
    budget::check_world(
        "sim.region (or radius)",
        IVec3::new(
            (cols.x * CHUNK_VOXELS as i64).min(1 << 20) as i32,
            gen_.height(),
            (cols.y * CHUNK_VOXELS as i64).min(1 << 20) as i32,
        ),
    )?;
    gen_.build_region_within(lo, hi, limit, pb)
        .context("cannot build the simulated region")
}

/// The generator of a streamed world and the rule its region follows.
pub fn generator(cfg: &WorldConfig) -> Result<(Arc<ChunkGen>, RegionRule)> {
    let size = (!cfg.unbounded).then_some(cfg.size);
    let gen_ = ChunkGen::new(&cfg.source, size, cfg.size.y, cfg.seed)?;
    let rule = RegionRule::of(cfg, &gen_)?;
    Ok((Arc::new(gen_), rule))
}

/// Build the simulated region of a streamed world, chunk columns
/// `[lo, hi)`, and the plan for streaming the rest.
///
/// A region that cannot fit in the memory budget is refused while it is
/// built, once its bricks pass what the budget leaves for them (what the
/// process holds now, and the region twice where it `follows` the camera,
/// are counted as [`check_budget`] counts them), rather than after the
/// whole region is built (regression, scale probe: a 6144² region under a
/// 512 MiB budget grew the process to 1.8 GiB before its refusal).
pub fn build_region(
    gen_: Arc<ChunkGen>,
    (lo, hi): (IVec2, IVec2),
    stream: &StreamSettings,
    follows: bool,
) -> Result<(SceneWorld, StreamPlan)> {
    let copies = if follows { 2 } else { 1 };
    let held = budget::rss_kb() * 1024;
    let limit = stream.memory_budget.saturating_sub(held) / copies;
    let pb = crate::progress::bar("region", 0);
    let built = build_columns_within(&gen_, (lo, hi), limit, &pb);
    pb.finish_and_clear();
    let world = match built {
        Ok(world) => world,
        Err(e) => match e.downcast_ref::<crate::scene::SceneError>() {
            Some(&crate::scene::SceneError::RegionOverLimit {
                built,
                columns,
                bytes,
                ..
            }) => {
                // What the whole region would take, from its first columns,
                // and the least budget that could then hold it as
                // `check_budget` counts (the engine's copy and the
                // renderer's), which names the exact minimum once the
                // region is whole (review: a part-way refusal named none).
                let whole = (bytes as f64 * columns as f64 / built.max(1) as f64) as u64;
                // A lower bound: the process holds its copy with tables and
                // the allocator's slack (about twice its bytes, measured).
                let least = held
                    + (1 + copies) * whole
                    + RUNTIME_MARGIN
                    + crate::persist::db::STORE_CACHE_BYTES as u64;
                bail!(
                    "memory budget {} is too small for the simulated region: after {built} of its {columns} chunk columns its bricks took {}, so the whole region would take about {}, held {}, beside the {} the engine holds; raise --memory-budget or [stream] memory_budget well past {} (once the region is built, the start names the exact minimum), or shrink [sim] region (or radius)",
                    budget::human(stream.memory_budget),
                    budget::human(bytes),
                    budget::human(whole),
                    if follows {
                        "three times (the engine's copy, the renderer's, and a second while it moves)"
                    } else {
                        "twice (the engine's copy and the renderer's)"
                    },
                    budget::human(held),
                    budget::human(least.next_multiple_of(1 << 20)),
                )
            }
            _ => return Err(e),
        },
    };
    let plan = StreamPlan {
        gen_,
        live: (lo, hi),
        window: WindowSettings {
            radius: WindowSettings::radius_for(stream.view_distance),
            budget_bytes: stream.memory_budget,
            fetchers: stream.fetchers,
        },
        overlay: None,
    };
    Ok((world, plan))
}

/// The fetchers' overlay for a streamed world whose store holds chunks
/// outside the simulated region (it moved on): each chunk of a column that
/// the store holds replaces the generated one. A store that cannot be read
/// is an error (the column keeps its stand-in and is asked for again); a
/// chunk that does not decode is reported once and drawn as generated.
pub fn store_overlay(reader: StoreReader, gen_: &ChunkGen) -> ColumnOverlay {
    let palette = gen_.palette().clone();
    let chunks_y = (gen_.height() + CHUNK_VOXELS - 1) / CHUNK_VOXELS;
    let reported = Arc::new(std::sync::Mutex::new(FxHashSet::<ChunkKey>::default()));
    Arc::new(move |col: IVec2, bricks: &mut Vec<(IVec3, BrickContent)>| {
        for y in 0..chunks_y {
            let key = ChunkKey(IVec3::new(col.x, y, col.y));
            let Some(blob) = reader.chunk(key).map_err(|e| e.to_string())? else {
                continue;
            };
            match chunk::decode_chunk(key, &blob, &palette) {
                Ok(data) => {
                    let lo = key.min_brick();
                    let hi = lo + IVec3::splat(chunk::CHUNK_BRICKS);
                    bricks.retain(|(b, _)| !(b.cmpge(lo).all() && b.cmplt(hi).all()));
                    bricks.extend(data.bricks);
                }
                Err(e) => {
                    let mut seen = reported.lock().unwrap_or_else(|p| p.into_inner());
                    if seen.insert(key) {
                        crate::say!(
                            "warning: {key} cannot be shown as stored ({e}): drawn as generated"
                        );
                    }
                }
            }
        }
        Ok(())
    })
}

/// Memory the scripts, their Luau VMs and the simulation's channels are
/// allowed for in the start-up check (they are measured, not estimated,
/// once the first window is exact).
pub const RUNTIME_MARGIN: u64 = 64 << 20;

/// Check that `budget`, the process's resident-memory target, holds what
/// the process holds now (the engine's simulated region among it), the
/// renderer's copy of the region, one full window (its columns estimated
/// from the region's own) and [`RUNTIME_MARGIN`]; on success the budget
/// goes to the window, whose cache gets what is left. The error names the
/// minimum.
pub fn check_budget(
    region: &SceneWorld,
    plan: &mut StreamPlan,
    budget: u64,
    follows: bool,
) -> Result<()> {
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
    // A region that follows the camera is built anew while the old one
    // still stands (a move); and the store's page cache fills as it works.
    let copies = if follows { 2 } else { 1 };
    let need = now
        + copies * region_bytes
        + window_min
        + RUNTIME_MARGIN
        + crate::persist::db::STORE_CACHE_BYTES as u64;
    if budget < need {
        bail!(
            "memory budget {} is too small for one view: the engine holds {} with the simulated region, the renderer's copy of the region{} needs {}, a window of {} chunk columns for the view distance about {}, and the scripts and the store's cache {}: at least {}; raise --memory-budget or [stream] memory_budget to {}, or lower [stream] view_distance or shrink [sim] region (or radius)",
            budget::human(budget),
            budget::human(now),
            if follows {
                " (and a second while it moves)"
            } else {
                ""
            },
            budget::human(copies * region_bytes),
            window_cols,
            budget::human(window_min),
            budget::human(RUNTIME_MARGIN + crate::persist::db::STORE_CACHE_BYTES as u64),
            budget::human(need),
            // A little above the minimum: what the process holds varies.
            budget::human((need + need / 16).next_multiple_of(1 << 20)),
        );
    }
    crate::scene::RenderWindow::check_fits(plan.window.radius, plan.gen_.height())?;
    // The machine must have it too, whatever the budget says (regression,
    // scale probe: the minimum's advice, followed on a smaller machine,
    // aborted the engine with "memory allocation failed").
    let have = now + budget::headroom_bytes();
    if need > have {
        bail!(
            "one view needs at least {} (with a window of {} chunk columns for the view distance), more than this process can have: {} ({} held, {} more available); lower [stream] view_distance or shrink [sim] region (or radius)",
            budget::human(need),
            window_cols,
            budget::human(have),
            budget::human(now),
            budget::human(have - now)
        );
    }
    // A budget past what the process can have is lowered to it (the
    // window does the same; here so the start says the budget kept to).
    plan.window.budget_bytes = budget::within_reach(budget).max(need);
    Ok(())
}
