//! Criterion benchmarks of the traversal inner loops: a fixed batch of
//! primary rays over a small terrain, per tracer (brickmap is the one the
//! engine renders with; dense and svo are for comparison), and the
//! brickmap's level-of-detail walk at C = 1 and 4 pixels.
//!
//! `cargo bench --bench brickmap_trace`

use std::hint::black_box;

use brickworld::scene::{SceneSpec, build_scene};
use brickworld::trace::{Camera, Ray, Tracer};
use criterion::{Criterion, Throughput, criterion_group, criterion_main};
use glam::{DVec3, IVec3};
use indicatif::ProgressBar;

/// The view's primary rays and its pixel angle.
fn rays(world: &brickworld::scene::SceneWorld, view: usize) -> (Vec<Ray>, f32) {
    let v = world.default_views()[view];
    let cam = Camera::new(DVec3::from(v.eye), DVec3::from(v.target), v.fov, 256, 192).unwrap();
    let o = world.frame().to_local(cam.eye);
    let rays = (0..192)
        .flat_map(|j| (0..256).map(move |i| (i, j)))
        .map(|(i, j)| Ray::new(o, cam.direction(i, j).as_vec3()))
        .collect();
    (rays, cam.pixel_angle() as f32)
}

fn bench(c: &mut Criterion) {
    let world = build_scene(
        &SceneSpec::Terrain { caves: false },
        IVec3::new(256, 96, 256),
        1,
        &ProgressBar::hidden(),
    )
    .unwrap();
    let svo = world.svo(&ProgressBar::hidden()).unwrap();
    let dense = world.dense(1 << 30).unwrap();
    let bm = world.brickmap();
    let tracers: [&dyn Tracer; 3] = [&bm, &svo, &dense];
    let mut g = c.benchmark_group("primary_rays_terrain_256");
    for (view, name) in [(0, "overview"), (2, "closeup")] {
        let (batch, pixel_angle) = rays(&world, view);
        g.throughput(Throughput::Elements(batch.len() as u64));
        for t in tracers {
            g.bench_function(format!("{}/{name}", t.name()), |b| {
                b.iter(|| {
                    let mut hits = 0u32;
                    for r in &batch {
                        hits += t.trace(black_box(r), f32::INFINITY).is_some() as u32;
                    }
                    hits
                })
            });
        }
        for c in [1.0f32, 4.0] {
            let k = c * pixel_angle;
            g.bench_function(format!("brickmap_lod{c}/{name}"), |b| {
                b.iter(|| {
                    let mut hits = 0u32;
                    for r in &batch {
                        hits += bm.trace_lod(black_box(r), f32::INFINITY, k).is_some() as u32;
                    }
                    hits
                })
            });
        }
    }
    g.finish();
}

criterion_group! {
    name = benches;
    config = Criterion::default().sample_size(20);
    targets = bench
}
criterion_main!(benches);
