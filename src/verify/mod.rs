//! `brickworld verify …`: checks of accuracy against analytic solutions and
//! invariants, written as JSON (and charts) that other tools read.

pub mod sims;
pub mod voxels;
pub mod water3d;

use std::path::Path;

use anyhow::{Context, Result};
use plotters::style::RGBColor;

use crate::bench::chart::{Series, xy_chart};
use crate::progress::bar;

/// Run `verify sims`: write the JSON report (and charts into `chart_dir`).
/// Fails (non-zero exit) if any case did not pass.
pub fn run_sims(json: &Path, chart_dir: Option<&Path>, conservation_steps: u64) -> Result<()> {
    let pb = bar("verifying", 6);
    let (cases, charts) = sims::run_all(conservation_steps, &pb);
    pb.finish_and_clear();
    let report = serde_json::json!({ "cases": cases });
    let text = serde_json::to_string_pretty(&report)? + "\n";
    crate::bench::write_outputs(json, &text, None, |_| Ok(()))?;
    for c in &cases {
        println!(
            "{:<18} {:<34} {}",
            c.name,
            c.script,
            if c.passed { "passed" } else { "FAILED" }
        );
    }
    if let Some(dir) = chart_dir {
        std::fs::create_dir_all(dir).with_context(|| format!("cannot create {}", dir.display()))?;
        // (JSON was written above; charts go into their own directory.)
        let blue = RGBColor(60, 110, 200);
        let green = RGBColor(40, 150, 80);
        let red = RGBColor(200, 70, 60);
        xy_chart(
            &dir.join("ritter_convergence.svg"),
            "Ritter dam break: error against cell size",
            "cell size dx (m, log)",
            "relative L1 error of depth (log)",
            &[Series {
                name: "water.lua, CFL 0.25",
                color: blue,
                points: charts.resolution.iter().map(|r| (r.0, r.1)).collect(),
            }],
        )?;
        xy_chart(
            &dir.join("speed_accuracy.svg"),
            "Ritter dam break: speed against accuracy",
            "wall-clock seconds to simulate 10 s (log)",
            "relative L1 error of depth (log)",
            &[
                Series {
                    name: "resolution sweep (64..512 cells)",
                    color: blue,
                    points: charts.resolution.iter().map(|r| (r.2, r.1)).collect(),
                },
                Series {
                    name: "dt sweep (CFL 0.05..0.5, 256 cells)",
                    color: green,
                    points: charts.dt.iter().map(|r| (r.2, r.1)).collect(),
                },
            ],
        )?;
        xy_chart(
            &dir.join("error_vs_steps_per_s.svg"),
            "Ritter dam break: error against steps per second",
            "steps per second (log)",
            "relative L1 error of depth (log)",
            &[
                Series {
                    name: "resolution sweep (64..512 cells)",
                    color: blue,
                    points: charts.steps_per_s.0.clone(),
                },
                Series {
                    name: "dt sweep (CFL 0.05..0.5, 256 cells)",
                    color: green,
                    points: charts.steps_per_s.1.clone(),
                },
            ],
        )?;
        xy_chart(
            &dir.join("stability.svg"),
            "Stability sweep: error against CFL number (128 cells)",
            "CFL number dt * sqrt(g h0) / dx (log)",
            "relative L1 error (log)",
            &[
                Series {
                    name: "one step per dt",
                    color: red,
                    points: charts.stability.iter().map(|r| (r.0, r.1)).collect(),
                },
                Series {
                    name: "sub-stepped to CFL 0.25",
                    color: green,
                    points: charts.stability.iter().map(|r| (r.0, r.3)).collect(),
                },
            ],
        )?;
    }
    if let Some(dir) = chart_dir {
        water3d_charts(dir, &charts)?;
    }
    let failed: Vec<&str> = cases.iter().filter(|c| !c.passed).map(|c| c.name).collect();
    if !failed.is_empty() {
        anyhow::bail!(
            "{} case(s) failed: {} (see {})",
            failed.len(),
            failed.join(", "),
            json.display()
        );
    }
    Ok(())
}

/// water3d's charts: the U-tube's error against cost and updates per
/// second, and the dam break's surface against the spread rate.
fn water3d_charts(dir: &Path, charts: &sims::ChartData) -> Result<()> {
    let colors = [
        RGBColor(60, 110, 200),
        RGBColor(40, 150, 80),
        RGBColor(200, 70, 60),
    ];
    let names = ["compress 0.05", "compress 0.1", "compress 0.2"];
    let series = |x: fn(&(f64, f64, f64, f64)) -> f64| -> Vec<Series<'static>> {
        [0.05, 0.1, 0.2]
            .iter()
            .enumerate()
            .map(|(i, c)| Series {
                name: names[i],
                color: colors[i],
                points: charts
                    .u_tube
                    .iter()
                    .filter(|r| r.0 == *c)
                    .map(|r| (x(r), r.2.max(1e-3)))
                    .collect(),
            })
            .collect()
    };
    xy_chart(
        &dir.join("u_tube_speed_accuracy.svg"),
        "water3d U-tube: level error against wall-clock time (250..2000 steps)",
        "wall-clock seconds (log)",
        "level difference between the arms, voxels (log; 1e-3 = level)",
        &series(|r| r.1),
    )?;
    xy_chart(
        &dir.join("u_tube_error_vs_updates_per_s.svg"),
        "water3d U-tube: level error against voxel updates per second",
        "active-voxel updates per second (log)",
        "level difference between the arms, voxels (log; 1e-3 = level)",
        &series(|r| r.3),
    )?;
    xy_chart(
        &dir.join("voxel_stability.svg"),
        "water3d dam break (fall 0.5): the 1500th step's largest change against spread",
        "spread (fraction per tick, log)",
        "largest change of a cell's fill in the last step (log; 1e-6 = none)",
        &[
            Series {
                name: "without the stability margin",
                color: colors[2],
                points: charts
                    .voxel_stability
                    .iter()
                    .filter(|r| r.1.is_finite())
                    .map(|r| (r.0, r.1.max(1e-6)))
                    .collect(),
            },
            Series {
                name: "shipped (rates scaled past 2s + f/2 = 0.45)",
                color: colors[1],
                points: charts
                    .voxel_stability
                    .iter()
                    .filter(|r| r.2.is_finite())
                    .map(|r| (r.0, r.2.max(1e-6)))
                    .collect(),
            },
        ],
    )?;
    Ok(())
}
