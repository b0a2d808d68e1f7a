//! Times bare primary-ray tracing (no shading, one thread) of the brickmap
//! tracer, per default view, to separate traversal cost from rendering
//! overhead; `--all` adds the dense grid and the octree.
//!
//! `cargo run --release --example trace_speed -- [SCENE] [SIZE] [WIDTH] [--all]`
//! (environment: `LOD=C` traces with level of detail, `HEIGHT=H` sets the
//! procedural height (default 128), `REPS=N` takes the best of N, default 3)
//! (SCENE as `bench tracers --scene`, default `terrain`; SIZE is the
//! procedural side, default 512; WIDTH default 1024, height ¾ of it).

use std::time::Instant;

use brickworld::scene::{SceneSpec, build_scene};
use brickworld::trace::{Camera, Tracer};
use glam::{DVec3, IVec3};
use indicatif::ProgressBar;

fn main() {
    let lod: Option<f32> = std::env::var("LOD").ok().map(|v| v.parse().expect("LOD"));
    let args: Vec<String> = std::env::args().filter(|a| a != "--all").collect();
    let all = std::env::args().any(|a| a == "--all");
    let spec: SceneSpec = args
        .get(1)
        .map_or("terrain", |s| s.as_str())
        .parse()
        .expect("scene");
    let size: i32 = args.get(2).and_then(|s| s.parse().ok()).unwrap_or(512);
    let w: u32 = args.get(3).and_then(|s| s.parse().ok()).unwrap_or(1024);
    let h = w * 3 / 4;
    let world = build_scene(
        &spec,
        IVec3::new(
            size,
            std::env::var("HEIGHT").map_or(128, |v| v.parse().expect("HEIGHT")),
            size,
        ),
        1,
        &ProgressBar::hidden(),
    )
    .unwrap();
    let bm = world.brickmap();
    let svo = all.then(|| world.svo(&ProgressBar::hidden()).unwrap());
    let dense = all.then(|| world.dense(1 << 33).unwrap());
    let mut tracers: Vec<&dyn Tracer> = Vec::new();
    if let (Some(d), Some(s)) = (&dense, &svo) {
        tracers.push(d);
        tracers.push(s);
    }
    tracers.push(&bm);
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
        for &t in &tracers {
            let mut best = f64::INFINITY;
            let mut hits = 0usize;
            let reps: usize = std::env::var("REPS").map_or(3, |v| v.parse().expect("REPS"));
            for _ in 0..reps {
                let t0 = Instant::now();
                hits = 0;
                let k = lod.map_or(0.0, |c| c * cam.pixel_angle() as f32);
                for r in &rays {
                    hits += t.trace_lod(r, f32::INFINITY, k).is_some() as usize;
                }
                best = best.min(t0.elapsed().as_secs_f64());
            }
            println!(
                "{:>9}: {:6.2} Mrays/s ({:.0} ns/ray), {hits} hits",
                t.name(),
                rays.len() as f64 / best / 1e6,
                best * 1e9 / rays.len() as f64
            );
        }
    }
}
