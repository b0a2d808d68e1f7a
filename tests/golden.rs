//! Image tests: the three tracers render byte-identical frames (their hits
//! are bit-identical), and each frame matches a small golden PNG within a
//! stated tolerance. Regenerate goldens on purpose with
//! `BRICKWORLD_BLESS=1 cargo test --release --test golden`.

use std::path::PathBuf;

use brickworld::scene::{SceneSpec, build_scene};
use brickworld::trace::{Camera, RenderOptions, Tracer, render, write_png};
use glam::{DVec3, IVec3};
use indicatif::ProgressBar;

/// Largest per-channel difference allowed against a golden image.
const MAX_CHANNEL_DIFF: u8 = 2;
/// Largest fraction of channels allowed to differ at all.
const MAX_DIFF_FRACTION: f64 = 0.002;

fn golden_path(name: &str) -> PathBuf {
    PathBuf::from(env!("CARGO_MANIFEST_DIR"))
        .join("tests/golden")
        .join(name)
}

fn read_png(path: &PathBuf) -> (u32, u32, Vec<u8>) {
    let dec = png::Decoder::new(std::io::BufReader::new(std::fs::File::open(path).unwrap()));
    let mut r = dec.read_info().unwrap();
    let mut buf = vec![0; r.output_buffer_size().unwrap()];
    let info = r.next_frame(&mut buf).unwrap();
    buf.truncate(info.buffer_size());
    (info.width, info.height, buf)
}

fn check(name: &str, spec: &str, size: IVec3, shadows: bool) {
    let spec: SceneSpec = spec.parse().unwrap();
    let world = build_scene(&spec, size, 3, &ProgressBar::hidden()).unwrap();
    let view = world.default_views()[1];
    let cam = Camera::new(
        DVec3::from(view.eye),
        DVec3::from(view.target),
        view.fov,
        96,
        72,
    )
    .unwrap();
    let opts = RenderOptions {
        shadows,
        ..Default::default()
    };
    let svo = world.svo(&ProgressBar::hidden()).unwrap();
    let dense = world.dense(1 << 30).unwrap();
    let bm = world.brickmap();
    let tracers: [&dyn Tracer; 3] = [&dense, &svo, &bm];
    let frames: Vec<_> = tracers
        .iter()
        .map(|t| render(*t, &cam, world.store.palette(), &opts))
        .collect();
    for (t, f) in tracers.iter().zip(&frames).skip(1) {
        assert!(
            f.rgb == frames[0].rgb,
            "{name}: {} differs from dense",
            t.name()
        );
        assert!(
            f.depth
                .iter()
                .zip(&frames[0].depth)
                .all(|(a, b)| a.to_bits() == b.to_bits()),
            "{name}: depth differs"
        );
    }
    let path = golden_path(name);
    if std::env::var_os("BRICKWORLD_BLESS").is_some() {
        write_png(&path, 96, 72, &frames[0].rgb).unwrap();
        return;
    }
    let (w, h, gold) = read_png(&path);
    assert_eq!((w, h), (96, 72));
    let diffs: Vec<u8> = gold
        .iter()
        .zip(&frames[0].rgb)
        .map(|(a, b)| a.abs_diff(*b))
        .collect();
    let max = *diffs.iter().max().unwrap();
    let frac = diffs.iter().filter(|&&d| d > 0).count() as f64 / diffs.len() as f64;
    assert!(
        max <= MAX_CHANNEL_DIFF && frac <= MAX_DIFF_FRACTION,
        "{name}: max channel diff {max}, {:.3}% of channels differ",
        frac * 100.0
    );
}

#[test]
fn terrain_matches_golden() {
    check("terrain_96x72.png", "terrain", IVec3::new(96, 48, 96), true);
}

#[test]
fn caves_match_golden() {
    check(
        "caves_96x72.png",
        "terrain:caves",
        IVec3::new(64, 48, 64),
        false,
    );
}

#[test]
fn balls_match_golden() {
    check("balls_96x72.png", "balls", IVec3::new(80, 64, 80), true);
}

#[test]
fn hairball_matches_golden() {
    check(
        "hairball_96x72.png",
        "hairball",
        IVec3::new(64, 64, 64),
        false,
    );
}
