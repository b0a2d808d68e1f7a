//! Criterion benchmark of a daemon frame's PNG encoding: the engine's
//! `png_bytes` (fast deflate) against the png crate's default level, on a
//! 640×360 frame of the default world's terrain as the daemon draws it
//! (ambient occlusion, shadows, fog). Each also reports the bytes it
//! writes.
//!
//! `cargo bench --bench frame_png`

use std::hint::black_box;

use brickworld::engine::frames::png_bytes;
use brickworld::scene::{SceneSpec, build_scene};
use brickworld::trace::{Camera, RenderOptions, render};
use criterion::{Criterion, Throughput, criterion_group, criterion_main};
use glam::{DVec3, IVec3};
use indicatif::ProgressBar;

/// The png crate's default level, as frames were encoded before.
fn png_default(w: u32, h: u32, rgb: &[u8]) -> Vec<u8> {
    let mut out = Vec::new();
    let mut enc = png::Encoder::new(&mut out, w, h);
    enc.set_color(png::ColorType::Rgb);
    enc.set_depth(png::BitDepth::Eight);
    let mut wr = enc.write_header().unwrap();
    wr.write_image_data(rgb).unwrap();
    drop(wr);
    out
}

fn bench(c: &mut Criterion) {
    let world = build_scene(
        &SceneSpec::Terrain { caves: false },
        IVec3::new(256, 96, 256),
        1,
        &ProgressBar::hidden(),
    )
    .unwrap();
    let (w, h) = (640, 360);
    let v = world.default_views()[1];
    let cam = Camera::new(DVec3::from(v.eye), DVec3::from(v.target), v.fov, w, h).unwrap();
    let opts = RenderOptions {
        ao: true,
        shadows: true,
        fog: 256.0,
        ..Default::default()
    };
    let frame = render(&world.brickmap(), &cam, world.store().palette(), &opts).rgb;
    eprintln!(
        "frame png: fast {} bytes, default level {} bytes",
        png_bytes(w, h, &frame).unwrap().len(),
        png_default(w, h, &frame).len()
    );
    let mut g = c.benchmark_group("frame_png_640x360");
    g.throughput(Throughput::Bytes(frame.len() as u64));
    g.bench_function("png_bytes (fast)", |b| {
        b.iter(|| png_bytes(w, h, black_box(&frame)).unwrap())
    });
    g.bench_function("default level", |b| {
        b.iter(|| png_default(w, h, black_box(&frame)))
    });
    g.finish();
}

criterion_group!(benches, bench);
criterion_main!(benches);
