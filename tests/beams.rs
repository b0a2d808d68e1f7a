//! Beam starts and level of detail against the plain walk: the same image
//! bit for bit, and beam starts that are safe (never past any pixel's hit)
//! and useful (well into the empty space in front of most blocks of the
//! overview).

mod common;

use brickworld::trace::{
    BEAM, Camera, RenderOptions, Tracer, beam_of, ray_start, render, trace_hits,
};
use glam::DVec3;

fn cameras(b: &common::Built) -> Vec<Camera> {
    b.world
        .default_views()
        .iter()
        .map(|v| Camera::new(DVec3::from(v.eye), DVec3::from(v.target), v.fov, 200, 136).unwrap())
        .collect()
}

/// Beams change nothing: exact, with level of detail and with occlusion.
#[test]
fn beam_starts_give_bit_identical_images() {
    for (name, b) in [
        ("terrain", common::terrain()),
        ("caves", common::caves()),
        ("balls", common::balls()),
        ("hairball", common::hairball()),
    ] {
        let bm = b.brickmap();
        let palette = b.world.store().palette();
        for (vi, cam) in cameras(b).iter().enumerate() {
            for (lod, ao) in [(0.0, false), (4.0, true)] {
                let plain = RenderOptions {
                    lod,
                    ao,
                    ..Default::default()
                };
                let beamed = RenderOptions {
                    beam: true,
                    ..plain
                };
                let a = render(&bm, cam, palette, &plain);
                let z = render(&bm, cam, palette, &beamed);
                let hits = a.hits.iter().zip(&z.hits).filter(|(x, y)| x != y).count();
                assert_eq!(hits, 0, "{name} view {vi} lod {lod}: {hits} hits differ");
                assert!(a.rgb == z.rgb, "{name} view {vi} lod {lod}: colours differ");
            }
        }
    }
}

/// Every block's start is at or before every one of its pixels' hits, and
/// on the terrain most blocks start well into the empty space.
#[test]
fn beam_starts_are_safe_and_useful() {
    let b = common::terrain();
    let bm = b.brickmap();
    let palette = b.world.store().palette();
    for (vi, cam) in cameras(b).iter().enumerate() {
        let out = render(&bm, cam, palette, &RenderOptions::default());
        let origin = bm.frame().to_local(cam.eye);
        let (bw, bh) = (cam.width.div_ceil(BEAM), cam.height.div_ceil(BEAM));
        let (mut useful, mut blocks) = (0, 0);
        for by in 0..bh {
            for bx in 0..bw {
                let (c, spread) = beam_of(cam, bx, by);
                let centre = brickworld::trace::Ray::new(origin, c.as_vec3());
                let start = ray_start(Tracer::beam_start(&bm, &centre, spread, 0.0));
                let mut nearest = f32::INFINITY;
                for j in by * BEAM..((by + 1) * BEAM).min(cam.height) {
                    for i in bx * BEAM..((bx + 1) * BEAM).min(cam.width) {
                        if let Some(h) = out.hits[(j * cam.width + i) as usize] {
                            nearest = nearest.min(h.t);
                        }
                    }
                }
                assert!(
                    start <= nearest,
                    "view {vi} block ({bx}, {by}): start {start} past a hit at {nearest}"
                );
                if nearest.is_finite() {
                    blocks += 1;
                    useful += (start >= 0.5 * nearest) as u32;
                }
            }
        }
        eprintln!("view {vi}: {useful} of {blocks} blocks start halfway to their hits");
        // From the overview, most blocks look down through empty air; the
        // nearer views start close to the ground, where beams buy little.
        assert!(
            vi != 0 || useful * 2 >= blocks,
            "view {vi}: only {useful} of {blocks} blocks start halfway to their hits"
        );
    }
}

/// `trace_hits` (what the Embree peer bench times: hits alone, no shading)
/// finds `render`'s hits bit for bit: exact and with level of detail, in
/// the default views and from an eye 2^25 voxels away (rays started where
/// they enter the exact range).
#[test]
fn trace_hits_are_the_rendered_hits() {
    for (name, b) in [
        ("terrain", common::terrain()),
        ("hairball", common::hairball()),
    ] {
        let bm = b.brickmap();
        let palette = b.world.store().palette();
        let mut cams = cameras(b);
        let far = DVec3::new(-3.3e7, 2.0e7, 1.7e7);
        cams.push(Camera::new(far, DVec3::new(64.0, 32.0, 64.0), 0.001, 64, 48).unwrap());
        for (vi, cam) in cams.iter().enumerate() {
            for lod in [0.0, 2.0] {
                let opts = RenderOptions {
                    lod,
                    ..Default::default()
                };
                let want = render(&bm, cam, palette, &opts).hits;
                let got = trace_hits(&bm, cam, &opts);
                let hit = got.iter().filter(|h| h.is_some()).count();
                assert!(hit > 0, "{name} view {vi}: nothing hit");
                let differ = want.iter().zip(&got).filter(|(a, b)| a != b).count();
                assert_eq!(
                    differ, 0,
                    "{name} view {vi} lod {lod}: {differ} hits differ"
                );
            }
        }
    }
}
