//! `brickworld verify sims`: the shipped scripts against analytic solutions
//! and invariants (SWASHES-style), with speed-against-accuracy charts.
//!
//! Cases: `ritter_dam_break`, `lake_at_rest`, `mass_conservation`,
//! `talus_angle`, `stability_sweep`, `determinism`.

use std::time::Instant;

use glam::IVec2;
use serde::Serialize;
use serde_json::{Value, json};

use crate::sim::tile::{TILE, TILE_CELLS, cell};
use crate::sim::{Kernel, Limits, ScriptSource, SimError, Simulation};

/// The shipped scripts, embedded so that `verify` checks what ships.
pub const WATER: &str = include_str!("../../scripts/water.lua");
/// The shipped erosion script.
pub const EROSION: &str = include_str!("../../scripts/erosion.lua");
/// The shipped snow script.
pub const SNOW: &str = include_str!("../../scripts/snow.lua");

const G: f64 = 9.81;

/// One verification case.
#[derive(Debug, Clone, Serialize)]
pub struct Case {
    /// Case name.
    pub name: &'static str,
    /// Script(s) exercised.
    pub script: &'static str,
    /// Whether it met its criterion.
    pub passed: bool,
    /// Measured figures.
    pub metrics: Value,
}

fn source(name: &str, text: &str) -> ScriptSource {
    ScriptSource {
        name: name.into(),
        text: text.into(),
    }
}

fn water_sim(tiles: IVec2, dx: f64) -> Result<Simulation, SimError> {
    let mut sim = Simulation::new(IVec2::ZERO, tiles);
    sim.add_script(source("water", WATER), Kernel::Lua, Limits::default())?;
    sim.set_param(0, "dx", dx)?;
    sim.set_param(0, "gravity", G)?;
    // The analytic cases are frictionless.
    sim.set_param(0, "friction", 0.0)?;
    Ok(sim)
}

/// Fill channel `name` from a function of the column's (x, z) index.
fn fill(sim: &mut Simulation, name: &str, f: impl Fn(i32, i32) -> f64) {
    let (lo, hi) = sim.tile_bounds();
    let ch = sim.channels_mut().channel(name);
    for tz in lo.y..hi.y {
        for tx in lo.x..hi.x {
            let mut d = [0.0; TILE_CELLS];
            for z in 0..TILE {
                for x in 0..TILE {
                    d[cell(x, z)] = f(tx * TILE + x, tz * TILE + z);
                }
            }
            sim.channels_mut().set(IVec2::new(tx, tz), ch, &d);
        }
    }
}

fn column(sim: &Simulation, name: &str, x: i32, z: i32) -> f64 {
    let Some(ch) = sim.channels().find(name) else {
        return 0.0;
    };
    let t = IVec2::new(x.div_euclid(TILE), z.div_euclid(TILE));
    sim.channels()
        .get(t, ch)
        .map_or(0.0, |d| d[cell(x.rem_euclid(TILE), z.rem_euclid(TILE))])
}

/// Ritter's dam break on a dry bed: exact depth at (x, t).
pub fn ritter(x: f64, t: f64, h0: f64) -> f64 {
    let c0 = (G * h0).sqrt();
    let s = x / t;
    if s < -c0 {
        h0
    } else if s <= 2.0 * c0 {
        (2.0 * c0 - s).powi(2) / (9.0 * G)
    } else {
        0.0
    }
}

/// One Ritter run: `n` columns over [−L, L), CFL number `cfl`, `substeps`
/// sub-steps per step. Returns (relative L1 error, front error, max depth,
/// steps per second, error if the runtime rejected a step).
fn ritter_run(n: i32, cfl: f64, substeps: u32) -> (f64, f64, f64, f64, Option<String>) {
    let (half, h0, t_end) = (100.0, 1.0, 10.0);
    let dx = 2.0 * half / n as f64;
    let mut sim = match water_sim(IVec2::new(n / TILE, 1), dx) {
        Ok(s) => s,
        Err(e) => return (f64::NAN, f64::NAN, f64::NAN, 0.0, Some(e.to_string())),
    };
    let xc = |i: i32| -half + (i as f64 + 0.5) * dx;
    fill(&mut sim, "ground", |_, _| 0.0);
    fill(&mut sim, "water", |x, _| if xc(x) < 0.0 { h0 } else { 0.0 });
    let dt_target = cfl * dx / (G * h0).sqrt();
    let steps = (t_end / dt_target).ceil() as u64;
    let dt = t_end / steps as f64 / substeps as f64;
    let t0 = Instant::now();
    let mut failure = None;
    'run: for _ in 0..steps * substeps as u64 {
        let r = sim.step(dt);
        if let Some(e) = r.errors.into_iter().next() {
            failure = Some(e.to_string());
            break 'run;
        }
    }
    let secs = t0.elapsed().as_secs_f64().max(1e-9);
    let (mut err, mut norm, mut hmax, mut front) = (0.0, 0.0, 0.0f64, -half);
    for i in 0..n {
        let h = column(&sim, "water", i, 0);
        let ex = ritter(xc(i), t_end, h0);
        err += (h - ex).abs();
        norm += ex;
        hmax = hmax.max(h);
        if h > 1e-3 * h0 {
            front = xc(i) + dx * 0.5;
        }
    }
    // The exact front measured like the numerical one: where h falls to 1e-3 h0.
    let front_exact = t_end * (2.0 * (G * h0).sqrt() - (9.0 * G * 1e-3 * h0).sqrt());
    (
        err / norm,
        (front - front_exact).abs(),
        hmax,
        steps as f64 * substeps as f64 / secs,
        failure,
    )
}

/// (x, L1, wall-clock seconds of the run) points of a sweep.
type Sweep = Vec<(f64, f64, f64)>;

fn ritter_case() -> (Case, Sweep, Sweep) {
    let mut res = Vec::new();
    let mut chart_res = Vec::new();
    for n in [64, 128, 256, 512] {
        let (l1, front, _, sps, fail) = ritter_run(n, 0.25, 1);
        let steps = (10.0 / (0.25 * (200.0 / n as f64) / G.sqrt())).ceil();
        res.push(json!({"cells": n, "dx": 200.0 / n as f64, "l1_rel": l1, "front_error_m": front, "steps_per_s": sps, "seconds": steps / sps, "error": fail}));
        chart_res.push((200.0 / n as f64, l1, steps / sps));
    }
    let orders: Vec<f64> = chart_res
        .windows(2)
        .map(|w| (w[0].1 / w[1].1).log2())
        .collect();
    let front_orders: Vec<f64> = res
        .windows(2)
        .map(|w| {
            (w[0]["front_error_m"].as_f64().unwrap_or(f64::NAN)
                / w[1]["front_error_m"].as_f64().unwrap_or(f64::NAN))
            .log2()
        })
        .collect();
    let mut dts = Vec::new();
    let mut chart_dt = Vec::new();
    for cfl in [0.05, 0.1, 0.25, 0.5] {
        let (l1, front, _, sps, fail) = ritter_run(256, cfl, 1);
        let steps = (10.0 / (cfl * (200.0 / 256.0) / G.sqrt())).ceil();
        dts.push(json!({"cfl": cfl, "l1_rel": l1, "front_error_m": front, "steps_per_s": sps, "seconds": steps / sps, "error": fail}));
        chart_dt.push((cfl, l1, steps / sps));
    }
    let finest = chart_res.last().map_or(f64::NAN, |r| r.1);
    let passed = finest < 0.1 && orders.iter().all(|o| *o > 0.0);
    let case = Case {
        name: "ritter_dam_break",
        script: "water.lua",
        passed,
        metrics: json!({
            "h0": 1.0, "t": 10.0, "domain_m": 200.0, "gravity": G,
            "criterion": "relative L1 < 0.1 at the finest resolution and error falling with every refinement",
            "resolutions": res, "observed_order_l1": orders, "observed_order_front": front_orders, "dt_sweep_256": dts,
        }),
    };
    (case, chart_res, chart_dt)
}

fn lake_at_rest() -> Case {
    let run = || -> Result<(f64, f64), SimError> {
        let mut sim = water_sim(IVec2::new(4, 4), 1.0)?;
        let bed = |x: i32, z: i32| {
            1.0 + 0.6 * (x as f64 / 3.0).sin() * (z as f64 / 4.0).cos()
                + 0.3 * ((x * z) as f64 * 0.05).sin()
        };
        fill(&mut sim, "ground", bed);
        fill(&mut sim, "water", |x, z| 3.0 - bed(x, z));
        for _ in 0..500 {
            if let Some(e) = sim.step(0.05).errors.into_iter().next() {
                return Err(e);
            }
        }
        let (mut dev, mut flux) = (0.0f64, 0.0f64);
        for z in 0..32 {
            for x in 0..32 {
                dev = dev
                    .max((column(&sim, "ground", x, z) + column(&sim, "water", x, z) - 3.0).abs());
                for p in ["u", "v", "qx", "qz"] {
                    flux = flux.max(column(&sim, p, x, z).abs());
                }
            }
        }
        Ok((dev, flux))
    };
    match run() {
        Ok((dev, flux)) => Case {
            name: "lake_at_rest",
            script: "water.lua",
            passed: dev <= 1e-12 && flux <= 1e-12,
            metrics: json!({"steps": 500, "max_surface_deviation": dev, "max_face_velocity_or_discharge": flux, "criterion": "both <= 1e-12"}),
        },
        Err(e) => failed("lake_at_rest", "water.lua", e),
    }
}

fn failed(name: &'static str, script: &'static str, e: SimError) -> Case {
    Case {
        name,
        script,
        passed: false,
        metrics: json!({"error": e.to_string()}),
    }
}

fn all_scripts(tiles: IVec2) -> Result<Simulation, SimError> {
    let mut sim = Simulation::new(IVec2::ZERO, tiles);
    sim.add_script(source("water", WATER), Kernel::Lua, Limits::default())?;
    sim.add_script(source("erosion", EROSION), Kernel::Lua, Limits::default())?;
    sim.add_script(source("snow", SNOW), Kernel::Lua, Limits::default())?;
    Ok(sim)
}

fn mass_conservation(steps: u64) -> Case {
    let run = || -> Result<Value, SimError> {
        let mut sim = all_scripts(IVec2::new(8, 8))?;
        let terrain = crate::scene::Noise::new(5);
        let bed =
            move |x: i32, z: i32| 20.0 + 12.0 * terrain.fbm2(x as f64 / 40.0, z as f64 / 40.0, 4);
        fill(&mut sim, "ground", bed);
        fill(&mut sim, "water", move |x, z| {
            (22.0 - bed(x, z)).max(0.0) + 0.2
        });
        fill(
            &mut sim,
            "snow",
            move |x, z| if bed(x, z) > 24.0 { 1.5 } else { 0.0 },
        );
        let ch = |sim: &Simulation, n: &str| {
            sim.channels()
                .total(sim.channels().find(n).expect("channel"))
        };
        let w0 = ch(&sim, "water");
        let gs0 = ch(&sim, "ground") + ch(&sim, "sediment");
        let s0 = ch(&sim, "snow");
        let t = Instant::now();
        for _ in 0..steps {
            if let Some(e) = sim.step(0.02).errors.into_iter().next() {
                return Err(e);
            }
        }
        let secs = t.elapsed().as_secs_f64();
        let dw = ((ch(&sim, "water") - w0) / w0).abs();
        let dgs = ((ch(&sim, "ground") + ch(&sim, "sediment") - gs0) / gs0).abs();
        let ds = ((ch(&sim, "snow") - s0) / s0).abs();
        Ok(json!({
            "steps": steps, "columns": 64 * 64, "dt": 0.02, "seconds": secs,
            "drift_water": dw, "drift_ground_plus_sediment": dgs, "drift_snow": ds,
            "sediment_moved": ch(&sim, "sediment"), "criterion": "each drift <= 1e-9 (relative)",
        }))
    };
    match run() {
        Ok(m) => {
            let ok = ["drift_water", "drift_ground_plus_sediment", "drift_snow"]
                .iter()
                .all(|k| m[*k].as_f64().is_some_and(|v| v <= 1e-9));
            Case {
                name: "mass_conservation",
                script: "water.lua + erosion.lua + snow.lua",
                passed: ok,
                metrics: m,
            }
        }
        Err(e) => failed("mass_conservation", "water.lua + erosion.lua + snow.lua", e),
    }
}

fn talus_angle() -> Case {
    let run = || -> Result<Value, SimError> {
        let mut sim = Simulation::new(IVec2::ZERO, IVec2::new(4, 4));
        sim.add_script(source("erosion", EROSION), Kernel::Lua, Limits::default())?;
        let talus = 1.2;
        fill(&mut sim, "ground", |x, z| {
            if (8..24).contains(&x) && (10..20).contains(&z) {
                30.0
            } else {
                2.0 + 0.1 * x as f64
            }
        });
        let total0 = sim
            .channels()
            .total(sim.channels().find("ground").expect("ground"));
        let mut steps = 0;
        let mut excess = f64::INFINITY;
        while steps < 20_000 {
            for _ in 0..100 {
                if let Some(e) = sim.step(0.05).errors.into_iter().next() {
                    return Err(e);
                }
            }
            steps += 100;
            excess = 0.0;
            for z in 0..32 {
                for x in 0..32 {
                    let g = column(&sim, "ground", x, z);
                    for (nx, nz) in [(x + 1, z), (x, z + 1)] {
                        if nx < 32 && nz < 32 {
                            excess = excess.max((g - column(&sim, "ground", nx, nz)).abs() - talus);
                        }
                    }
                }
            }
            if excess <= 1e-3 {
                break;
            }
        }
        let total = sim
            .channels()
            .total(sim.channels().find("ground").expect("ground"));
        Ok(
            json!({"talus": talus, "steps": steps, "max_slope_excess": excess, "ground_drift": ((total - total0) / total0).abs(), "criterion": "every slope <= talus + 1e-3"}),
        )
    };
    match run() {
        Ok(m) => Case {
            name: "talus_angle",
            script: "erosion.lua",
            passed: m["max_slope_excess"].as_f64().is_some_and(|v| v <= 1e-3),
            metrics: m,
        },
        Err(e) => failed("talus_angle", "erosion.lua", e),
    }
}

fn stability_sweep() -> (Case, Vec<(f64, f64, bool, f64)>) {
    let mut rows = Vec::new();
    let mut chart = Vec::new();
    let reference = ritter_run(128, 0.25, 1).0;
    let mut handled = true;
    for factor in [0.1, 0.25, 0.5, 1.0, 2.0, 4.0, 8.0] {
        let (l1, _, hmax, _, fail) = ritter_run(128, factor, 1);
        // A dam break never deepens water beyond h0: more is a blow-up.
        let blew_up = fail.is_some() || !l1.is_finite() || hmax > 1.05;
        let sub = (factor / 0.25).ceil().max(1.0) as u32;
        let (l1_sub, _, hmax_sub, _, fail_sub) = ritter_run(128, factor, sub);
        let sub_ok = fail_sub.is_none() && hmax_sub <= 1.05 && l1_sub <= 2.0 * reference.max(1e-12);
        // A NaN that got past the runtime without an error would be a failure.
        handled &= (l1.is_finite() || fail.is_some()) && sub_ok;
        rows.push(json!({"cfl": factor, "l1_rel": l1, "max_depth": hmax, "blew_up": blew_up, "runtime_error": fail, "substeps": sub, "l1_rel_substepped": l1_sub}));
        chart.push((factor, l1, blew_up, l1_sub));
    }
    let case = Case {
        name: "stability_sweep",
        script: "water.lua",
        passed: handled,
        metrics: json!({
            "cells": 128, "reference_l1_cfl_0_25": reference, "runs": rows,
            "criterion": "no NaN or negative water is ever written (rejected steps are reported), and sub-stepping to CFL 0.25 keeps L1 within 2x the reference at every dt",
        }),
    };
    (case, chart)
}

fn determinism() -> Case {
    let mut hashes = Vec::new();
    for threads in [1usize, 2, 8] {
        let pool = match rayon::ThreadPoolBuilder::new().num_threads(threads).build() {
            Ok(p) => p,
            Err(e) => {
                return failed(
                    "determinism",
                    "water.lua + erosion.lua + snow.lua",
                    SimError::Internal(e.to_string()),
                );
            }
        };
        let h = pool.install(|| -> Result<u64, SimError> {
            let mut sim = all_scripts(IVec2::new(4, 4))?;
            fill(&mut sim, "ground", |x, z| {
                10.0 + ((x * 7 + z * 13) % 11) as f64 * 0.7
            });
            fill(&mut sim, "water", |x, _| if x < 12 { 4.0 } else { 0.0 });
            fill(&mut sim, "snow", |_, z| if z > 20 { 1.0 } else { 0.0 });
            for _ in 0..100 {
                if let Some(e) = sim.step(0.02).errors.into_iter().next() {
                    return Err(e);
                }
            }
            Ok(sim.channels().hash())
        });
        match h {
            Ok(h) => hashes.push(h),
            Err(e) => return failed("determinism", "water.lua + erosion.lua + snow.lua", e),
        }
    }
    Case {
        name: "determinism",
        script: "water.lua + erosion.lua + snow.lua",
        passed: hashes.windows(2).all(|w| w[0] == w[1]),
        metrics: json!({"threads": [1, 2, 8], "hashes": hashes.iter().map(|h| format!("{h:#018x}")).collect::<Vec<_>>()}),
    }
}

/// (x, y) points of a chart series.
pub type Points = Vec<(f64, f64)>;

/// Chart data gathered while verifying.
#[derive(Debug, Default)]
pub struct ChartData {
    /// (dx, L1, seconds) for the resolution sweep.
    pub resolution: Vec<(f64, f64, f64)>,
    /// (CFL, L1, seconds) for the dt sweep.
    pub dt: Vec<(f64, f64, f64)>,
    /// (steps per second, L1) for the resolution sweep and the dt sweep.
    pub steps_per_s: (Points, Points),
    /// (CFL, L1 raw, blew up, L1 sub-stepped) for the stability sweep.
    pub stability: Vec<(f64, f64, bool, f64)>,
    /// water3d's U-tube: (compress, seconds, level difference, voxel
    /// updates per second) over step budgets.
    pub u_tube: Vec<(f64, f64, f64, f64)>,
    /// water3d's dam break: (spread, the last step's largest change
    /// without the stability margin, with it).
    pub voxel_stability: Vec<(f64, f64, f64)>,
}

/// Run every case. `conservation_steps` is 10⁴ for the full check.
pub fn run_all(
    conservation_steps: u64,
    progress: &indicatif::ProgressBar,
) -> (Vec<Case>, ChartData) {
    progress.set_length(13);
    let (ritter, resolution, dt) = ritter_case();
    progress.inc(1);
    let lake = lake_at_rest();
    progress.inc(1);
    let mass = mass_conservation(conservation_steps);
    progress.inc(1);
    let talus = talus_angle();
    progress.inc(1);
    let (stab, stability) = stability_sweep();
    progress.inc(1);
    let det = determinism();
    progress.inc(1);
    let u_tube = super::voxels::u_tube();
    progress.inc(1);
    let sand = super::voxels::sand_pile();
    progress.inc(1);
    let lava = super::voxels::lava_cools();
    progress.inc(1);
    let vdet = super::voxels::voxel_determinism();
    progress.inc(1);
    let cave = super::water3d::cave_fill();
    progress.inc(1);
    let (vstab, voxel_stability) = super::water3d::voxel_stability();
    progress.inc(1);
    let u_tube_chart = super::water3d::u_tube_speed_accuracy();
    progress.inc(1);
    let sps = |c: &Case, key: &str| -> Vec<(f64, f64)> {
        c.metrics[key]
            .as_array()
            .map(|a| {
                a.iter()
                    .map(|r| {
                        (
                            r["steps_per_s"].as_f64().unwrap_or(0.0),
                            r["l1_rel"].as_f64().unwrap_or(0.0),
                        )
                    })
                    .collect()
            })
            .unwrap_or_default()
    };
    let steps_per_s = (sps(&ritter, "resolutions"), sps(&ritter, "dt_sweep_256"));
    (
        vec![
            ritter, lake, mass, talus, stab, det, u_tube, sand, lava, vdet, cave, vstab,
        ],
        ChartData {
            resolution,
            dt,
            steps_per_s,
            stability,
            u_tube: u_tube_chart,
            voxel_stability,
        },
    )
}
