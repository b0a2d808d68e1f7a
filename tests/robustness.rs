//! Robustness: watertight shells, a proptest over origins and directions
//! covering every edge case (axis-aligned, grazing, −0.0, inside solid,
//! outside the volume, mid-brick), and worlds ±10⁶ voxels from the origin.

mod common;

use brickworld::scene::SceneWorld;
use brickworld::trace::{Ray, Tracer};
use brickworld::world::{BrickStore, Palette};
use common::Built;
use glam::{DVec3, IVec3, Vec3};
use proptest::prelude::*;
use std::sync::OnceLock;

/// A hollow box (1 voxel walls) and, inside it, a hollow sphere (2 voxel
/// shell), both closed.
fn shells(offset: IVec3) -> Built {
    let mut s = BrickStore::new(Palette::grey_ramp());
    let lo = offset + IVec3::new(3, 2, 5);
    let hi = offset + IVec3::new(61, 43, 50);
    s.fill_box(lo, hi, 40);
    s.fill_box(lo + 1, hi - 1, 0);
    let c = (offset + IVec3::new(30, 22, 27)).as_dvec3() + 0.3;
    s.fill_sphere(c, 12.0, 80);
    s.fill_sphere(c, 10.0, 0);
    Built::from_world(SceneWorld::new(s, offset, offset + IVec3::new(64, 48, 56)).unwrap())
}

fn shells_at_origin() -> &'static Built {
    static S: OnceLock<Built> = OnceLock::new();
    S.get_or_init(|| shells(IVec3::ZERO))
}

fn check_inside(b: &Built, origin: Vec3, dir: Vec3) {
    let bm = b.brickmap();
    let tracers: [&dyn Tracer; 3] = [&b.dense, &b.svo, &bm];
    let ray = Ray::new(origin, dir);
    for t in tracers {
        let h = t.trace(&ray, f32::INFINITY);
        let h = h.unwrap_or_else(|| panic!("{} let {ray:?} escape the shell", t.name()));
        assert!(
            h.material == 40 || h.material == 80,
            "hit a non-shell voxel"
        );
    }
}

#[test]
fn rays_from_inside_a_closed_shell_never_escape() {
    let b = shells_at_origin();
    let c = Vec3::new(30.3, 22.3, 27.3);
    let mut x = 0x1234_5678_9abc_def0u64;
    let mut rnd = || {
        x ^= x << 13;
        x ^= x >> 7;
        x ^= x << 17;
        (x >> 40) as f32 / (1u64 << 24) as f32 * 2.0 - 1.0
    };
    let n = if cfg!(debug_assertions) {
        20_000
    } else {
        300_000
    };
    for i in 0..n {
        // Inside the sphere, and between the sphere and the box.
        let o = if i % 2 == 0 {
            c + Vec3::new(rnd(), rnd(), rnd()) * 6.0
        } else {
            Vec3::new(
                5.0 + (rnd() + 1.0) * 5.0,
                3.5 + (rnd() + 1.0) * 3.0,
                7.0 + (rnd() + 1.0) * 3.0,
            )
        };
        let o = if i % 3 == 0 { o.floor() } else { o };
        let mut d = Vec3::new(rnd(), rnd(), rnd());
        match i % 7 {
            0 => d = Vec3::new(1.0, 1.0, 1.0) * d.x.signum(),
            1 => d = Vec3::new(0.0, -0.0, d.z.signum()),
            2 => d.y = -0.0,
            _ => {}
        }
        check_inside(b, o, d.normalize_or(Vec3::Y));
    }
}

fn component() -> impl Strategy<Value = f32> {
    prop_oneof![
        Just(0.0f32),
        Just(-0.0f32),
        Just(1.0f32),
        Just(-1.0f32),
        Just(1e-7f32),
        Just(-3e-8f32),
        -1.0f32..1.0,
    ]
}

fn coordinate(ext: f32) -> impl Strategy<Value = f32> {
    prop_oneof![
        (-8i32..(ext as i32 + 8)).prop_map(|v| v as f32),
        (0i32..(ext as i32)).prop_map(|v| v as f32 + 0.5),
        (-0.5 * ext)..(1.5 * ext),
        Just(-1000.0f32),
        Just(ext + 777.25),
    ]
}

proptest! {
    #![proptest_config(ProptestConfig { cases: if cfg!(debug_assertions) { 2_000 } else { 50_000 }, failure_persistence: None, ..ProptestConfig::default() })]

    /// Every tracer returns the same hit for any origin and direction.
    #[test]
    fn tracers_agree_for_any_origin_and_direction(
        ox in coordinate(64.0), oy in coordinate(48.0), oz in coordinate(56.0),
        dx in component(), dy in component(), dz in component(),
        t_max in prop_oneof![Just(f32::INFINITY), 0.0f32..80.0],
    ) {
        let b = shells_at_origin();
        // A zero direction is a valid input too: every tracer must report a miss.
        let d = Vec3::new(dx, dy, dz).normalize_or_zero();
        let ray = Ray::new(Vec3::new(ox, oy, oz), d);
        let bm = b.brickmap();
        let r0 = b.dense.trace(&ray, t_max);
        prop_assert_eq!(r0, b.svo.trace(&ray, t_max));
        prop_assert_eq!(r0, bm.trace(&ray, t_max));
        if d == Vec3::ZERO {
            prop_assert!(r0.is_none());
        }
        if let Some(h) = r0 {
            prop_assert!(h.t <= t_max && h.t >= 0.0);
            prop_assert!(h.material != 0);
        }
    }
}

#[test]
fn worlds_a_million_voxels_from_the_origin_trace_identically() {
    let near = shells_at_origin();
    for off in [
        IVec3::new(1_000_000, -1_000_000, 1_000_000),
        IVec3::new(-1_000_008, 999_992, -1_000_000),
    ] {
        let far = shells(off);
        let (bm_near, bm_far) = (near.brickmap(), far.brickmap());
        let pairs: [(&dyn Tracer, &dyn Tracer); 3] = [
            (&near.dense, &far.dense),
            (&near.svo, &far.svo),
            (&bm_near, &bm_far),
        ];
        let mut x = 77u64;
        for _ in 0..20_000 {
            x = x
                .wrapping_mul(6364136223846793005)
                .wrapping_add(1442695040888963407);
            let f = |s: u32| ((x >> s) & 0xffff) as f64 / 65536.0;
            let eye = DVec3::new(
                f(0) * 100.0 - 20.0,
                f(16) * 80.0 - 10.0,
                f(32) * 90.0 - 15.0,
            );
            let dir = DVec3::new(f(48) - 0.5, f(8) - 0.5, f(24) - 0.5);
            if dir.length() == 0.0 {
                continue;
            }
            for (a, b) in pairs {
                let ra = a.frame().ray(eye, dir);
                let rb = b.frame().ray(eye + off.as_dvec3(), dir);
                assert_eq!(ra, rb, "local rays must be bit-identical");
                let (ha, hb) = (a.trace(&ra, f32::INFINITY), b.trace(&rb, f32::INFINITY));
                assert_eq!(
                    ha.map(|h| (h.t, h.voxel + off, h.normal)),
                    hb.map(|h| (h.t, h.voxel, h.normal))
                );
            }
        }
    }
}
