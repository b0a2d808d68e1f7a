//! The editing queue: after each step, the ids of exactly the bricks whose
//! voxels changed are published, each once.

use std::collections::{BTreeMap, BTreeSet};

use brickworld::scene::{SceneSpec, build_scene};
use brickworld::sim::{Limits, ScriptSource, WorldSim};
use glam::IVec3;
use indicatif::ProgressBar;

fn snapshot(
    store: &brickworld::world::BrickStore,
    lo: IVec3,
    hi: IVec3,
) -> BTreeMap<(i32, i32, i32), Vec<u8>> {
    let mut out = BTreeMap::new();
    let mut dense = [0u8; 512];
    for bz in lo.z..hi.z {
        for by in lo.y..hi.y {
            for bx in lo.x..hi.x {
                store.read_dense(IVec3::new(bx, by, bz), &mut dense);
                out.insert((bx, by, bz), dense.to_vec());
            }
        }
    }
    out
}

#[test]
fn every_changed_brick_is_published_exactly_once_per_step_and_nothing_else() {
    let mut world = build_scene(
        &SceneSpec::Terrain { caves: false },
        IVec3::new(64, 48, 64),
        4,
        &ProgressBar::hidden(),
    )
    .unwrap();
    let mut ws = WorldSim::new(&mut world);
    let src = ScriptSource {
        name: "water".into(),
        text: include_str!("../scripts/water.lua").into(),
    };
    ws.add_lua(src, Limits::default()).unwrap();
    ws.sim.set_param(0, "rain", 2.0).unwrap();
    let (lo, hi) = (IVec3::new(0, 0, 0), IVec3::new(8, 8, 8));
    let mut published_any = false;
    for _ in 0..12 {
        let before = snapshot(world.store(), lo, hi);
        let r = ws.step(&mut world, 0.1);
        assert!(r.errors.is_empty(), "{:?}", r.errors);
        let after = snapshot(world.store(), lo, hi);
        let changed: BTreeSet<(i32, i32, i32)> = before
            .keys()
            .filter(|k| before[k] != after[k])
            .copied()
            .collect();
        let ids: Vec<(i32, i32, i32)> = r.bricks.iter().map(|b| (b.x, b.y, b.z)).collect();
        let set: BTreeSet<_> = ids.iter().copied().collect();
        assert_eq!(set.len(), ids.len(), "no brick twice in a step");
        assert_eq!(set, changed, "exactly the changed bricks");
        published_any |= !ids.is_empty();
    }
    assert!(published_any, "the rain must have changed some bricks");
}

/// The render thread's copy of the world is kept current by deltas of the
/// published bricks alone: after steps of a simulation that writes bricks,
/// the copy's voxels, grid and palette equal the world's, and each delta
/// costs only the bricks it names.
#[test]
fn a_copy_fed_only_deltas_of_the_published_bricks_stays_identical() {
    let spec: SceneSpec = "terrain".parse().unwrap();
    let mut world = build_scene(&spec, IVec3::new(64, 48, 64), 7, &ProgressBar::hidden()).unwrap();
    let mut ws = WorldSim::new(&mut world);
    let src = ScriptSource {
        name: "water".into(),
        text: std::fs::read_to_string(concat!(env!("CARGO_MANIFEST_DIR"), "/scripts/water.lua"))
            .unwrap()
            .into(),
    };
    let id = ws.add_lua(src, Limits::default()).unwrap();
    ws.set_param(id, "rain", 0.5).unwrap();
    let mut copy = world.clone();
    let mut sent = 0;
    for _ in 0..12 {
        let bricks = ws.step(&mut world, 0.05).bricks;
        let delta = world.delta(&bricks);
        assert_eq!(delta.bricks.len(), bricks.len());
        sent += bricks.len();
        copy.apply_delta(delta);
    }
    assert!(sent > 0, "the rain changed no brick");
    let (lo, hi) = (
        world.grid().origin(),
        world.grid().origin() + world.grid().dims(),
    );
    assert_eq!(
        snapshot(copy.store(), lo, hi),
        snapshot(world.store(), lo, hi)
    );
    for z in 0..world.grid().dims().z {
        for y in 0..world.grid().dims().y {
            for x in 0..world.grid().dims().x {
                let l = IVec3::new(x, y, z);
                let (a, b) = (copy.grid().pointer(l), world.grid().pointer(l));
                // Pool slots may differ; emptiness and uniform materials may not.
                assert_eq!(a == 0, b == 0, "{l}");
                if a & brickworld::world::UNIFORM != 0 || b & brickworld::world::UNIFORM != 0 {
                    assert_eq!(a, b, "{l}");
                }
            }
        }
    }
    for m in 0..=255u8 {
        assert_eq!(
            copy.store().palette().rgb(m),
            world.store().palette().rgb(m)
        );
    }
}

/// A recolour (a hot reload of `materials.lua`) travels as the palette
/// alone: the copy recolours its own bricks, which `apply_delta` reports,
/// and every brick's LOD colour then equals the world's.
#[test]
fn a_new_palette_recolours_the_copy_without_sending_its_bricks() {
    let spec: SceneSpec = "terrain".parse().unwrap();
    let mut world = build_scene(&spec, IVec3::new(64, 48, 64), 7, &ProgressBar::hidden()).unwrap();
    let mut copy = world.clone();
    let mut palette = world.store().palette().clone();
    for m in 1..=255u8 {
        let c = palette.rgb(m);
        palette.set(m, [c[2], 255 - c[0], c[1]]);
    }
    let recoloured = world.set_palette(palette);
    assert!(recoloured.len() > 10, "{} bricks", recoloured.len());
    let delta = world.delta(&[]);
    assert!(delta.bricks.is_empty());
    let mut reported = copy.apply_delta(delta);
    reported.sort_by_key(|b| (b.z, b.y, b.x));
    let mut expected = recoloured.clone();
    expected.sort_by_key(|b| (b.z, b.y, b.x));
    assert_eq!(reported, expected);
    let lod = |w: &brickworld::scene::SceneWorld, b: IVec3| match w.store().cell(b) {
        brickworld::world::Cell::Mixed(id) => w.store().pool().get(id).map(|r| r.lod_rgb()),
        _ => None,
    };
    for (b, _) in world.store().iter() {
        assert_eq!(lod(&copy, b), lod(&world, b), "{b}");
    }
}
