//! Times bare primary-ray tracing (no shading, one thread) for each tracer on
//! a terrain, to separate traversal cost from rendering overhead.
//!
//! `cargo run --release --example trace_speed -- [SIZE] [WIDTH]`

use std::time::Instant;

use brickworld::scene::{SceneSpec, build_scene};
use brickworld::trace::{Camera, Tracer};
use glam::{DVec3, IVec3};
use indicatif::ProgressBar;

fn main() {
    let args: Vec<String> = std::env::args().collect();
    let size: i32 = args.get(1).and_then(|s| s.parse().ok()).unwrap_or(512);
    let w: u32 = args.get(2).and_then(|s| s.parse().ok()).unwrap_or(1024);
    let h = w * 3 / 4;
    let world = build_scene(
        &SceneSpec::Terrain { caves: false },
        IVec3::new(size, 128, size),
        1,
        &ProgressBar::hidden(),
    )
    .unwrap();
    let svo = world.svo(&ProgressBar::hidden()).unwrap();
    let bm = world.brickmap();
    let dense = world.dense(1 << 33).unwrap();
    let tracers: [&dyn Tracer; 3] = [&dense, &svo, &bm];
    for view in world.default_views() {
        let cam = Camera::new(
            DVec3::from(view.eye),
            DVec3::from(view.target),
            view.fov,
            w,
            h,
        )
        .unwrap();
        let rays: Vec<_> = (0..h)
            .flat_map(|j| (0..w).map(move |i| (i, j)))
            .map(|(i, j)| {
                brickworld::trace::Ray::new(
                    world.frame().to_local(cam.eye),
                    cam.direction(i, j).as_vec3(),
                )
            })
            .collect();
        for t in tracers {
            let t0 = Instant::now();
            let mut hits = 0usize;
            for r in &rays {
                hits += t.trace(r, f32::INFINITY).is_some() as usize;
            }
            let s = t0.elapsed().as_secs_f64();
            println!(
                "{:>9}: {:6.2} Mrays/s ({:.0} ns/ray), {hits} hits",
                t.name(),
                rays.len() as f64 / s / 1e6,
                s * 1e9 / rays.len() as f64
            );
        }
    }
}
