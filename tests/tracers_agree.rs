//! The three tracers agree on the hit voxel, face, t and material for random
//! rays of every kind (10⁶ per scene in release builds).

mod common;

use brickworld::trace::Tracer;
use common::*;

fn rays_per_scene() -> usize {
    if cfg!(debug_assertions) {
        50_000
    } else {
        1_000_000
    }
}

fn check(name: &str, b: &Built, seed: u64) {
    let bm = b.brickmap();
    let tracers: [&dyn Tracer; 3] = [&b.dense, &b.svo, &bm];
    let ext = (b.world.bounds().1 - b.world.frame().anchor).as_vec3();
    let mut rng = TestRng(seed);
    let mut hits = 0usize;
    let n = rays_per_scene();
    for i in 0..n {
        let ray = random_ray(&mut rng, ext);
        let t_max = if i % 5 == 0 {
            rng.range(0.0, ext.x)
        } else {
            f32::INFINITY
        };
        let r0 = tracers[0].trace(&ray, t_max);
        for t in &tracers[1..] {
            let r = t.trace(&ray, t_max);
            assert_eq!(
                r0,
                r,
                "{name}: ray #{i} {ray:?} t_max {t_max}: dense vs {}",
                t.name()
            );
        }
        hits += r0.is_some() as usize;
    }
    assert!(
        hits > n / 50,
        "{name}: too few hits ({hits}) for a meaningful test"
    );
    assert!(hits < n, "{name}: every ray hit; the generator is broken");
}

#[test]
fn tracers_agree_on_terrain() {
    check("terrain", terrain(), 0x1234_5678);
}

#[test]
fn tracers_agree_on_terrain_with_caves() {
    check("caves", caves(), 0x2345_6789);
}

#[test]
fn tracers_agree_on_balls() {
    check("balls", balls(), 0x3456_789a);
}

#[test]
fn tracers_agree_on_hairball() {
    check("hairball", hairball(), 0x4567_89ab);
}

/// A scene big enough that some child blocks lie more than 2^15 descriptors
/// away from their parent, so ESVO far pointers are built and traversed.
#[test]
fn far_pointers_are_built_and_traced_exactly() {
    let b = Built::new("hairball", glam::IVec3::new(192, 192, 192), 9);
    assert!(
        b.svo.far_pointers() > 0,
        "scene too small to need far pointers"
    );
    check("hairball-192", &b, 0x5678_9abc);
}
