//! `brickworld bench sim`: column updates per second of each shipped script
//! (Lua, and the native reference where one exists) on terrains of two sizes,
//! plus a sweep showing that a step's cost follows the active tiles.

use std::sync::Arc;
use std::time::Instant;

use anyhow::Result;
use glam::{IVec2, IVec3};
use serde::Serialize;

use crate::scene::{Heightfield, Terrain};
use crate::sim::native::ShallowWater;
use crate::sim::tile::{TILE, TILE_CELLS, cell};
use crate::sim::{Kernel, Limits, ScriptSource, Simulation};
use crate::verify::sims::{EROSION, SNOW, WATER};

/// One script's figures at one size.
#[derive(Debug, Clone, Serialize)]
pub struct ScriptFigures {
    /// Script name.
    pub name: String,
    /// Columns per side.
    pub size: i32,
    /// Lua column updates per second (all passes of the script).
    pub lua_cells_per_s: f64,
    /// Native reference, where one exists.
    pub native_cells_per_s: Option<f64>,
    /// Lua ÷ native.
    pub lua_over_native: Option<f64>,
    /// Worker threads.
    pub threads: usize,
    /// Active tiles (brick columns) per step.
    pub active_bricks: usize,
}

/// A point of the active-set sweep.
#[derive(Debug, Clone, Serialize)]
pub struct ScalingPoint {
    /// Fraction of the world that is wet.
    pub wet_fraction: f64,
    /// Active tiles per step.
    pub active_bricks: usize,
    /// Milliseconds per step.
    pub step_ms: f64,
}

/// The report.
#[derive(Debug, Clone, Serialize)]
pub struct SimBench {
    /// Per script and size.
    pub scripts: Vec<ScriptFigures>,
    /// Step cost against active tiles (water, Lua, 1024² world).
    pub scaling: Vec<ScalingPoint>,
    /// The voxel grid: water3d's update rate and what sleeping costs.
    pub voxels: super::voxels::VoxelBench,
}

fn setup(size: i32, scripts: &[(&str, &str, Kernel)], wet: f64) -> Result<Simulation> {
    let tiles = IVec2::splat(size / TILE);
    let mut sim = Simulation::new(IVec2::ZERO, tiles);
    for (name, text, kernel) in scripts {
        let src = ScriptSource {
            name: (*name).into(),
            text: (*text).into(),
        };
        sim.add_script(src, kernel.clone(), Limits::default())?;
    }
    let terrain = Terrain::new(IVec3::new(size, 96, size), 7, false);
    let (g, w, s) = {
        let ch = sim.channels_mut();
        (
            ch.channel("ground"),
            ch.channel("water"),
            ch.channel("snow"),
        )
    };
    let wet_edge = (size as f64 * wet.sqrt()) as i32;
    for tz in 0..tiles.y {
        for tx in 0..tiles.x {
            let (mut gd, mut wd, mut sd) =
                ([0.0; TILE_CELLS], [0.0; TILE_CELLS], [0.0; TILE_CELLS]);
            for z in 0..TILE {
                for x in 0..TILE {
                    let (gx, gz) = (tx * TILE + x, tz * TILE + z);
                    let h = terrain.height(gx, gz) as f64;
                    gd[cell(x, z)] = h;
                    if gx < wet_edge && gz < wet_edge {
                        wd[cell(x, z)] = (40.0 - h).max(0.0) + 0.5;
                        sd[cell(x, z)] = if h > 50.0 { 1.0 } else { 0.0 };
                    }
                }
            }
            let t = IVec2::new(tx, tz);
            sim.channels_mut().set(t, g, &gd);
            sim.channels_mut().set(t, w, &wd);
            sim.channels_mut().set(t, s, &sd);
        }
    }
    Ok(sim)
}

/// Time `steps` steps after two warm-up steps; returns (cells/s, active tiles, ms/step).
fn time(sim: &mut Simulation, steps: u32) -> Result<(f64, usize, f64)> {
    for _ in 0..2 {
        sim.step(0.02);
    }
    let t = Instant::now();
    let mut cells = 0u64;
    let mut active = 0;
    for _ in 0..steps {
        let r = sim.step(0.02);
        if let Some(e) = r.errors.first() {
            anyhow::bail!("benchmark step failed: {e}");
        }
        cells += r.active_tiles as u64 * TILE_CELLS as u64;
        active = r.active_tiles;
    }
    let secs = t.elapsed().as_secs_f64();
    Ok((cells as f64 / secs, active, secs * 1e3 / steps as f64))
}

/// Run the benchmark and write its JSON.
pub fn run(
    json: &std::path::Path,
    sizes: &[i32],
    steps: u32,
    progress: &indicatif::ProgressBar,
) -> Result<SimBench> {
    let threads = rayon::current_num_threads();
    let mut scripts = Vec::new();
    progress.set_length((sizes.len() * 4 + 4) as u64);
    for &size in sizes {
        for (name, text) in [("water", WATER), ("erosion", EROSION), ("snow", SNOW)] {
            // Erosion reads water's channels: run water first, and count erosion alone.
            let mut list: Vec<(&str, &str, Kernel)> = Vec::new();
            if name == "erosion" {
                list.push(("water", WATER, Kernel::Native(Arc::new(ShallowWater))));
            }
            list.push((name, text, Kernel::Lua));
            // Best of three, Lua and native timed alternately: this machine's
            // throughput varies by ±30 % from run to run.
            let mut sim = setup(size, &list, 1.0)?;
            let (mut lua, active, _) = time(&mut sim, steps)?;
            let mut native_sim = if name == "water" {
                Some(setup(
                    size,
                    &[("water", WATER, Kernel::Native(Arc::new(ShallowWater)))],
                    1.0,
                )?)
            } else {
                None
            };
            let mut native_best: Option<f64> = None;
            for round in 0..3 {
                if round > 0 {
                    lua = lua.max(time(&mut sim, steps)?.0);
                }
                if let Some(n) = native_sim.as_mut() {
                    let v = time(n, steps)?.0;
                    native_best = Some(native_best.map_or(v, |b: f64| b.max(v)));
                }
            }
            if name == "erosion" {
                // Subtract the native water share measured alone.
                let mut w = setup(
                    size,
                    &[("water", WATER, Kernel::Native(Arc::new(ShallowWater)))],
                    1.0,
                )?;
                let mut wn = 0.0f64;
                for _ in 0..3 {
                    wn = wn.max(time(&mut w, steps)?.0);
                }
                lua = 1.0 / (1.0 / lua - 1.0 / wn);
            }
            progress.inc(1);
            let native = if name == "water" {
                let mut sim = setup(
                    size,
                    &[("water", WATER, Kernel::Native(Arc::new(ShallowWater)))],
                    1.0,
                )?;
                progress.inc(1);
                Some(time(&mut sim, steps)?.0)
            } else {
                None
            };
            scripts.push(ScriptFigures {
                name: name.into(),
                size,
                lua_cells_per_s: lua,
                native_cells_per_s: native,
                lua_over_native: native.map(|n| lua / n),
                threads,
                active_bricks: active,
            });
        }
    }
    let mut scaling = Vec::new();
    let big = *sizes.iter().max().unwrap_or(&512);
    for wet in [1.0 / 64.0, 1.0 / 16.0, 0.25, 1.0] {
        let mut sim = setup(big, &[("water", WATER, Kernel::Lua)], wet)?;
        // Let the dry tiles fall asleep first.
        for _ in 0..3 {
            sim.step(0.02);
        }
        let (_, active, ms) = time(&mut sim, steps)?;
        scaling.push(ScalingPoint {
            wet_fraction: wet,
            active_bricks: active,
            step_ms: ms,
        });
        progress.inc(1);
    }
    // The voxel pool: as wide as the largest column world, 32..=256.
    let side = (big / 16 * 16).clamp(32, 256);
    let voxels = super::voxels::run(
        glam::IVec3::new(side, 48, side),
        steps.clamp(3, 20) as usize,
        || (),
    );
    progress.inc(1);
    let report = SimBench {
        scripts,
        scaling,
        voxels,
    };
    super::write_json(json, &report)?;
    Ok(report)
}
