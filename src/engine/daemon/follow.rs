//! The stage that moves a streamed world's simulated region after the
//! camera (`[sim] radius` with `[stream]`).
//!
//! The region is the engine's whole world, so moving it means building a
//! new one: at a step boundary the engine commits, then builds the region
//! at its new place the way a resume builds it (generate the columns, lay
//! the stored chunks and chunk columns over them, apply the state blob just
//! committed), with the scripts it was running (hot reloads and health
//! included). Columns the region leaves sleep on disk; columns it enters
//! wake, as every column of a fresh world does. Because a resume runs the
//! same code, a run stopped anywhere and resumed moves at the same ticks to
//! the same places and stays bit-identical.
//!
//! The region's edges are **closed** (a wall, not the drain of a fixed
//! region): water that reaches them stays in the world and is stored with
//! the chunk column it is in, so nothing a moving region simulated is lost,
//! and no fictitious moat tile is ever stored in a real column.

use std::sync::Arc;
use std::time::Instant;

use anyhow::{Result, bail};
use glam::IVec2;
use rustc_hash::FxHashSet;

use super::super::persistence;
use super::super::streaming::{self, RegionRule};
use super::Engine;
use crate::scene::{CHUNK_BRICKS, ChunkGen};
use crate::sim::WorldSim;

/// What a region that follows the camera needs between moves.
pub(super) struct Follow {
    gen_: Arc<ChunkGen>,
    rule: RegionRule,
    /// Moves so far (this run).
    pub(super) moves: u64,
    /// Milliseconds the last move took (commit and rebuild).
    pub(super) move_ms: f64,
    /// The last failure to move, reported once.
    error: Option<String>,
    /// When a failed move may be tried again.
    retry_at: Option<Instant>,
    /// Chunk columns the region left since the render thread last got it
    /// whole.
    left: FxHashSet<IVec2>,
}

impl Follow {
    pub(super) fn new(gen_: Arc<ChunkGen>, rule: RegionRule) -> Self {
        Follow {
            gen_,
            rule,
            moves: 0,
            move_ms: 0.0,
            error: None,
            retry_at: None,
            left: FxHashSet::default(),
        }
    }

    /// The columns the region left since the last whole world the render
    /// thread took, sorted.
    pub(super) fn left(&self) -> Vec<IVec2> {
        let mut v: Vec<IVec2> = self.left.iter().copied().collect();
        v.sort_by_key(|c| (c.y, c.x));
        v
    }

    /// The render thread took a whole world (and [`left`](Self::left)).
    pub(super) fn delivered(&mut self) {
        self.left.clear();
    }
}

impl Engine {
    /// Stage: move the simulated region if the camera has left its middle.
    /// Returns whether the tick may be stepped: a move that fails (the
    /// commit before it, or building the new region) leaves the region
    /// where it is, is reported once, and holds the simulation (a step in
    /// the wrong place would differ from a resumed run) until a retry, at
    /// most once a second, succeeds.
    pub(super) fn follow_camera(&mut self) -> bool {
        let Some(f) = self.follow.as_ref() else {
            return true;
        };
        let Ok(cam) = self.camera_at(self.ws.sim.tick()) else {
            return true;
        };
        let now = streaming::columns_of(&self.world);
        let Some(to) = f.rule.follow(now, cam.eye) else {
            return true;
        };
        if f.retry_at.is_some_and(|t| Instant::now() < t) {
            return false;
        }
        let t = Instant::now();
        let result = self.move_region(now, to);
        let f = self.follow.as_mut().expect("checked above");
        match result {
            Ok(()) => {
                f.moves += 1;
                f.move_ms = t.elapsed().as_secs_f64() * 1e3;
                f.error = None;
                f.retry_at = None;
                let inside = |c: IVec2| c.cmpge(to.0).all() && c.cmplt(to.1).all();
                for cz in now.0.y..now.1.y {
                    for cx in now.0.x..now.1.x {
                        let c = IVec2::new(cx, cz);
                        if !inside(c) {
                            f.left.insert(c);
                        }
                    }
                }
                f.left.retain(|c| !inside(*c));
                true
            }
            Err(e) => {
                let msg = format!("{e:#}");
                if f.error.as_deref() != Some(msg.as_str()) {
                    crate::say!(
                        "warning: the simulated region cannot move from chunk columns {} .. {}: {msg}; the simulation waits and tries again every second",
                        now.0,
                        now.1
                    );
                }
                f.error = Some(msg);
                f.retry_at = Some(Instant::now() + std::time::Duration::from_secs(1));
                false
            }
        }
    }

    /// Commit, then rebuild the region at chunk columns `to` from the
    /// store, as a resume would.
    fn move_region(&mut self, from: (IVec2, IVec2), to: (IVec2, IVec2)) -> Result<()> {
        self.commit();
        if let Some(e) = &self.commit_error {
            bail!("the commit before moving failed ({e})");
        }
        let gen_ = self
            .follow
            .as_ref()
            .expect("a region that follows")
            .gen_
            .clone();
        let mut world = streaming::build_columns(&gen_, to)?;
        let mut ws = WorldSim::with_edges(&mut world, false);
        // The registry the scripts were loaded against (materials.lua's
        // names); the palette and registry of the state follow.
        world.materials = self.world.materials.clone();
        // Generated bricks get the LOD colours of the world's palette.
        world.set_palette(self.world.store().palette().clone());
        ws.sim.channels_mut().take_dirty();
        ws.set_seed(self.cfg.seed);
        ws.rebuild_scripts(&world, &self.ws.script_states())?;
        let mut dirty = std::mem::take(&mut self.dirty_chunks);
        let restored = persistence::restore_chunks(
            &self.db,
            &mut world,
            &mut ws,
            &mut dirty,
            persistence::RestoreScope {
                regenerable: self.cfg.source.is_procedural(),
                region: true,
                whole_columns: true,
            },
        );
        self.dirty_chunks = dirty;
        let Some(r) = restored? else {
            bail!("the store holds no state after a commit");
        };
        for c in &r.corrupt {
            crate::say!("warning: {c}");
        }
        for w in persistence::apply_state(&r.state, &mut ws) {
            crate::say!("warning: {w}");
        }
        wake_entered(&world, &mut ws, from, to);
        self.world = world;
        self.ws = ws;
        // The render thread gets the new region whole with the next frame.
        self.mirror_sent = false;
        self.dirty_pending.clear();
        Ok(())
    }
}

/// Wake what entered the region (chunk columns in `to`, not in `from`):
/// every tile, and every non-empty brick for the voxel scripts, as in a
/// fresh world. What stayed keeps its committed sleep state.
fn wake_entered(
    world: &crate::scene::SceneWorld,
    ws: &mut WorldSim,
    from: (IVec2, IVec2),
    to: (IVec2, IVec2),
) {
    let inside = |c: IVec2, r: (IVec2, IVec2)| c.cmpge(r.0).all() && c.cmplt(r.1).all();
    for cz in to.0.y..to.1.y {
        for cx in to.0.x..to.1.x {
            let c = IVec2::new(cx, cz);
            if inside(c, from) {
                continue;
            }
            let t0 = c * CHUNK_BRICKS;
            for tz in 0..CHUNK_BRICKS {
                for tx in 0..CHUNK_BRICKS {
                    ws.sim.wake(t0 + IVec2::new(tx, tz));
                }
            }
        }
    }
    let entered = |b: glam::IVec3| {
        let c = IVec2::new(b.x, b.z).div_euclid(IVec2::splat(CHUNK_BRICKS));
        !inside(c, from)
    };
    let mut bricks: Vec<glam::IVec3> = world
        .store()
        .iter()
        .map(|(b, _)| b)
        .filter(|b| entered(*b))
        .collect();
    if ws.vox.script_count() > 0 {
        bricks.sort_by_key(|b| (b.z, b.y, b.x));
        ws.vox.notify_edited(&bricks);
    }
}
