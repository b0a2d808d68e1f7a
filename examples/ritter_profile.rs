//! Prints the water depth profile of a Ritter dam break next to the exact
//! solution (debugging aid for scripts/water.lua).
//!
//! `cargo run --release --example ritter_profile -- [CELLS]`

use std::sync::Arc;

use brickworld::sim::native::ShallowWater;
use brickworld::sim::tile::{TILE_CELLS, cell};
use brickworld::sim::{Kernel, Limits, ScriptSource, Simulation};
use brickworld::verify::sims::{WATER, ritter};
use glam::IVec2;

fn main() {
    let n: i32 = std::env::args()
        .nth(1)
        .and_then(|s| s.parse().ok())
        .unwrap_or(256);
    let (half, h0, t_end) = (100.0, 1.0, 10.0);
    let dx = 2.0 * half / n as f64;
    let mut sim = Simulation::new(IVec2::ZERO, IVec2::new(n / 8, 1));
    let src = ScriptSource {
        name: "water".into(),
        text: WATER.into(),
    };
    sim.add_script(
        src,
        Kernel::Native(Arc::new(ShallowWater)),
        Limits::default(),
    )
    .unwrap();
    sim.set_param(0, "dx", dx).unwrap();
    let w = sim.channels_mut().channel("water");
    for tx in 0..n / 8 {
        let mut d = [0.0; TILE_CELLS];
        for z in 0..8 {
            for x in 0..8 {
                let xc = -half + ((tx * 8 + x) as f64 + 0.5) * dx;
                d[cell(x, z)] = if xc < 0.0 { h0 } else { 0.0 };
            }
        }
        sim.channels_mut().set(IVec2::new(tx, 0), w, &d);
    }
    let dt_target = 0.25 * dx / (9.81f64 * h0).sqrt();
    let steps = (t_end / dt_target).ceil() as u64;
    let dt = t_end / steps as f64;
    for _ in 0..steps {
        let r = sim.step(dt);
        assert!(r.errors.is_empty(), "{:?}", r.errors);
    }
    let u = sim.channels().find("u").unwrap();
    for i in (0..n).step_by((n / 40).max(1) as usize) {
        let xc = -half + (i as f64 + 0.5) * dx;
        let t = IVec2::new(i / 8, 0);
        let h = sim.channels().get(t, w).map_or(0.0, |d| d[cell(i % 8, 0)]);
        let uu = sim.channels().get(t, u).map_or(0.0, |d| d[cell(i % 8, 0)]);
        println!(
            "x {xc:8.2}  h {h:.5}  exact {:.5}  u {uu:.3}  exact u {:.3}",
            ritter(xc, t_end, h0),
            if ritter(xc, t_end, h0) > 0.0 && xc / t_end > -(9.81f64).sqrt() {
                2.0 / 3.0 * ((9.81f64).sqrt() + xc / t_end)
            } else {
                0.0
            }
        );
    }
}
