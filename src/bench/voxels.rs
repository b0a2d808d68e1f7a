//! `bench sim`'s voxel figures: water3d's active-voxel updates per second
//! on a fully active pool, and what sleeping bricks cost: a world with about
//! 1 % of its bricks disturbed against the same world fully active.

use std::time::Instant;

use glam::IVec3;
use serde::Serialize;

use crate::sim::voxels::VoxelSim;
use crate::sim::{Limits, ScriptSource};
use crate::verify::voxels::{STONE, registry};
use crate::world::{BrickStore, Palette};

/// The voxel benchmark's figures.
#[derive(Debug, Clone, Serialize)]
pub struct VoxelBench {
    /// Side of the cubic water pool, voxels.
    pub pool: i32,
    /// water3d (Lua): active-voxel updates per second (candidate bricks ×
    /// 512 per step), pool fully awake.
    pub water3d_updates_per_s: f64,
    /// Milliseconds per step, fully active.
    pub full_step_ms: f64,
    /// Milliseconds per step with only a small disturbance awake.
    pub sparse_step_ms: f64,
    /// Bricks the sparse steps ran on, against the full ones.
    pub sparse_candidates: usize,
    /// Candidate bricks of a full step.
    pub full_candidates: usize,
    /// sparse_step_ms / full_step_ms (target ≤ 0.02 at 1 % active).
    pub sparse_over_full: f64,
}

fn pool_world(side: i32) -> (BrickStore, VoxelSim, crate::world::MaterialRegistry) {
    let reg = registry();
    let water = reg.id("water").unwrap_or(252);
    let mut store = BrickStore::new(Palette::grey_ramp());
    let h = side + 8;
    store.fill_box(IVec3::ZERO, IVec3::new(side, 1, side), STONE);
    store.fill_box(IVec3::new(0, 1, 0), IVec3::new(side, side / 2, side), water);
    store.take_modified();
    let mut sim = VoxelSim::new(&store, IVec3::ZERO, IVec3::new(side, h, side), 1);
    let _ = sim.add_script(
        ScriptSource {
            name: "water3d".into(),
            text: include_str!("../../scripts/water3d.lua").into(),
        },
        Limits::default(),
        &reg,
    );
    sim.apply_fills(&store, &reg);
    (store, sim, reg)
}

/// Run the voxel benchmark on a `side`³ pool for `steps` timed steps.
pub fn run(side: i32, steps: usize) -> VoxelBench {
    // Fully active: a pool whose surface is sloshing (fills perturbed).
    let (mut store, mut sim, reg) = pool_world(side);
    let id = sim.channels().find("water").expect("declared");
    for b in sim.channels().sorted_bricks(id) {
        let mut v = *sim.channels().get(id, b).expect("listed");
        for (i, x) in v.iter_mut().enumerate() {
            *x *= 1.0 + 0.01 * ((i * 7 + b.x as usize * 13) % 5) as f32;
        }
        sim.channels_mut().set(id, b, &v);
    }
    sim.notify_edited(&sim.channels().sorted_bricks(id));
    let (mut cands, t0) = (0, Instant::now());
    for _ in 0..steps {
        cands = cands.max(sim.step(&mut store, &reg, 0.05).candidates);
    }
    let full_ms = t0.elapsed().as_secs_f64() * 1e3 / steps as f64;
    // At rest, then one small disturbance: only its neighbourhood runs.
    let (mut store, mut sim, reg) = pool_world(side);
    for _ in 0..400 {
        sim.step(&mut store, &reg, 0.05);
        if sim.active_bricks() == 0 {
            break;
        }
    }
    let poke = IVec3::new(side / 2, side / 2 - 1, side / 2).div_euclid(IVec3::splat(8));
    let id = sim.channels().find("water").expect("declared");
    if let Some(mut v) = sim.channels().get(id, poke).copied() {
        v[0] += 0.5;
        sim.channels_mut().set(id, poke, &v);
    }
    sim.notify_edited(&[poke]);
    let (mut sparse_cands, t0) = (0, Instant::now());
    for _ in 0..steps {
        sparse_cands = sparse_cands.max(sim.step(&mut store, &reg, 0.05).candidates);
    }
    let sparse_ms = t0.elapsed().as_secs_f64() * 1e3 / steps as f64;
    VoxelBench {
        pool: side,
        water3d_updates_per_s: cands as f64 * 512.0 / (full_ms / 1e3),
        full_step_ms: full_ms,
        sparse_step_ms: sparse_ms,
        sparse_candidates: sparse_cands,
        full_candidates: cands,
        sparse_over_full: sparse_ms / full_ms,
    }
}
