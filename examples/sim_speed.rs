//! Times the water script in Lua and its native reference on a 512×512 grid
//! of wet columns (every tile active), cell updates per second.
//!
//! `cargo run --release --example sim_speed`

use std::sync::Arc;
use std::time::Instant;

use brickworld::sim::native::ShallowWater;
use brickworld::sim::tile::{TILE_CELLS, cell};
use brickworld::sim::{Kernel, Limits, ScriptSource, Simulation};
use glam::IVec2;

fn main() {
    let n = 64;
    for (name, kernel) in [
        ("lua", Kernel::Lua),
        ("native", Kernel::Native(Arc::new(ShallowWater))),
    ] {
        let mut sim = Simulation::new(IVec2::ZERO, IVec2::splat(n));
        let src = ScriptSource {
            name: "water".into(),
            text: include_str!("../scripts/water.lua").into(),
        };
        sim.add_script(src, kernel, Limits::default()).unwrap();
        let ch = sim.channels_mut();
        let (g, w) = (ch.channel("ground"), ch.channel("water"));
        for tz in 0..n {
            for tx in 0..n {
                let mut ground = [0.0; TILE_CELLS];
                let mut water = [0.0; TILE_CELLS];
                for z in 0..8 {
                    for x in 0..8 {
                        let (gx, gz) = ((tx * 8 + x) as f64, (tz * 8 + z) as f64);
                        ground[cell(x, z)] = 10.0 + 5.0 * (gx * 0.05).sin() * (gz * 0.07).cos();
                        water[cell(x, z)] = 1.0 + (gx * 0.01).cos();
                    }
                }
                ch.set(IVec2::new(tx, tz), g, &ground);
                ch.set(IVec2::new(tx, tz), w, &water);
            }
        }
        sim.step(0.01);
        let steps = 10;
        let t = Instant::now();
        for _ in 0..steps {
            let r = sim.step(0.01);
            assert!(r.errors.is_empty());
        }
        let s = t.elapsed().as_secs_f64();
        let cells = (n * n * 64) as f64 * steps as f64;
        println!(
            "{name:>6}: {:.1} M cell updates/s ({} threads)",
            cells / s / 1e6,
            rayon::current_num_threads()
        );
    }
}
