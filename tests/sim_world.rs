//! Simulations on real scenes: water drains over every edge of the world and
//! is accounted for; the `sim`, `verify sims` and `bench sim` commands.

use brickworld::scene::{SceneSpec, build_scene};
use brickworld::sim::{Limits, ScriptSource, WorldSim};
use glam::{IVec2, IVec3};
use indicatif::ProgressBar;

/// The procedural terrain of `size` and `seed`, without caves.
fn terrain(size: IVec3, seed: u64) -> brickworld::scene::SceneWorld {
    build_scene(
        &SceneSpec::Terrain { caves: false },
        size,
        seed,
        &ProgressBar::hidden(),
    )
    .unwrap()
}

/// Load the shipped column script `scripts/NAME.lua` into `ws`; its index.
fn add_shipped(ws: &mut WorldSim, name: &str) -> usize {
    let text =
        std::fs::read_to_string(format!("{}/scripts/{name}.lua", env!("CARGO_MANIFEST_DIR")))
            .unwrap();
    let src = ScriptSource {
        name: name.into(),
        text: text.into(),
    };
    ws.add_lua(src, Limits::default()).unwrap()
}

#[test]
fn water_drains_over_every_edge_and_world_plus_drained_is_conserved() {
    let mut world = terrain(IVec3::new(32, 32, 32), 2);
    let mut ws = WorldSim::with_edges(&mut world, true);
    add_shipped(&mut ws, "water");
    let w = ws.sim.channels_mut().channel("water");
    // A uniform sheet of water 3 deep over the whole world, nothing else.
    for tz in 0..4 {
        for tx in 0..4 {
            ws.sim.channels_mut().set(IVec2::new(tx, tz), w, &[3.0; 64]);
        }
    }
    let start = ws.sim.channels().total(w);
    for _ in 0..400 {
        let (r, _) = ws.step_within_cfl(&mut world, 0.05, 0.5);
        assert!(r.errors.is_empty(), "{:?}", r.errors);
    }
    let now = ws.sim.channels().total(w);
    assert!(
        ws.drained > 0.1 * start,
        "water left the world: {} of {start}",
        ws.drained
    );
    assert!(
        ((now + ws.drained) - start).abs() < 1e-9 * start,
        "world {now} + drained {} != {start}",
        ws.drained
    );
}

/// Regression (known gap, docs walk): a column script's CFL sub-steps each
/// counted as a failed step, so a script failing in every sub-step was
/// suspended within one tick. A tick counts one failure, however many of
/// its sub-steps failed: the script is suspended at its third failed tick.
#[test]
fn a_script_failing_in_every_cfl_sub_step_counts_one_failed_step_a_tick() {
    let mut world = terrain(IVec3::new(32, 32, 32), 2);
    let mut ws = WorldSim::with_edges(&mut world, false);
    let text = std::fs::read_to_string(concat!(env!("CARGO_MANIFEST_DIR"), "/scripts/water.lua"))
        .unwrap()
        .replacen(
            "kernel = function(c)",
            "kernel = function(c) if c.tick > 0 then error('late boom') end",
            1,
        );
    let i = ws
        .add_lua(
            ScriptSource {
                name: "water".into(),
                text: text.into(),
            },
            Limits::default(),
        )
        .unwrap();
    let (r, _) = ws.step_within_cfl(&mut world, 0.05, 0.5);
    assert!(r.errors.is_empty(), "tick 0 runs: {:?}", r.errors);
    // A tiny dx and a sheet of water: many sub-steps from tick 1 on.
    ws.set_param(i, "dx", 0.001).unwrap();
    let w = ws.sim.channels_mut().channel("water");
    for tz in 0..4 {
        for tx in 0..4 {
            ws.sim.channels_mut().set(IVec2::new(tx, tz), w, &[3.0; 64]);
        }
    }
    for tick in 1..=3u32 {
        let (r, n) = ws.step_within_cfl(&mut world, 0.05, 0.5);
        assert!(n > 3, "tick {tick}: only {n} sub-steps");
        assert!(!r.errors.is_empty(), "tick {tick} did not fail");
        assert_eq!(ws.failures(i), tick, "tick {tick}, {n} sub-steps");
        assert_eq!(ws.suspended(i).is_some(), tick == 3, "tick {tick}");
    }
}

/// Audit: two claims of `sim` had no test. With closed edges (`sim
/// --closed-edges`, the ground's boundary of 1e9 a wall) no water leaves and
/// the total is conserved to round-off; and the CFL sub-steps keep
/// dt·(|u| + √(g·h))/dx under the limit in every step, measured here from
/// the channels before each step.
#[test]
fn closed_edges_conserve_water_and_sub_steps_keep_the_cfl_limit() {
    let mut world = terrain(IVec3::new(32, 32, 32), 2);
    let mut ws = WorldSim::with_edges(&mut world, false);
    add_shipped(&mut ws, "water");
    let w = ws.sim.channels_mut().channel("water");
    // A dam break: 12 deep over the western half, dry to the east.
    for tz in 0..4 {
        for tx in 0..2 {
            ws.sim
                .channels_mut()
                .set(IVec2::new(tx, tz), w, &[12.0; 64]);
        }
    }
    let start = ws.sim.channels().total(w);
    let (dt, limit) = (0.05, 0.5);
    let mut most = 1;
    for step in 0..200 {
        let ch = ws.sim.channels();
        let m = |name: &str| ch.find(name).map_or(0.0, |id| ch.max_abs(id));
        let speed = m("u").max(m("v")) + (9.81 * m("water")).sqrt();
        let (r, n) = ws.step_within_cfl(&mut world, dt, limit);
        assert!(r.errors.is_empty(), "{:?}", r.errors);
        let courant = dt / n as f64 * speed / 1.0;
        assert!(
            courant <= limit,
            "step {step}: {n} sub-steps, Courant {courant}"
        );
        most = most.max(n);
    }
    assert!(most > 1, "the dam break never needed a sub-step");
    let now = ws.sim.channels().total(w);
    assert_eq!(ws.drained, 0.0, "water left a closed world");
    assert!(
        ((now - start) / start).abs() < 1e-12,
        "{now} against {start}"
    );
}

/// The voxels of the 37 × 32 × 44 world's partial tiles that lie past its
/// edge (x 37..40, z 44..48): never drawn into.
fn past_the_edge(world: &brickworld::scene::SceneWorld) -> Vec<u8> {
    (0..32)
        .flat_map(|y| (0..40).flat_map(move |x| (0..48).map(move |z| IVec3::new(x, y, z))))
        .filter(|v| v.x >= 37 || v.z >= 44)
        .map(|v| world.store().voxel(v))
        .collect()
}

/// Regression (hostile probe): on a world whose x or z is not a multiple
/// of 8 the partial tiles' outer cells read as ground 0, the moat sank to
/// 2 below that, and the shipped erosion failed ("sediment" negative in the
/// moat) on every such world, whatever dt. Now the outer cells are moat,
/// drained each step and never written into voxels: water and erosion run,
/// world water plus drained water is conserved, and nothing is drawn
/// outside the world.
#[test]
fn a_world_whose_size_is_not_a_multiple_of_8_runs_water_and_erosion() {
    let size = IVec3::new(37, 32, 44);
    let mut world = terrain(size, 7);
    let before = past_the_edge(&world);
    let mut ws = WorldSim::with_edges(&mut world, true);
    for name in ["water", "erosion"] {
        add_shipped(&mut ws, name);
    }
    let w = ws.sim.channels_mut().channel("water");
    // 2 deep over the world's own columns.
    for tz in 0..6 {
        for tx in 0..5 {
            let mut sheet = [0.0; 64];
            for (c, v) in sheet.iter_mut().enumerate() {
                let (x, z) = (tx * 8 + (c % 8) as i32, tz * 8 + (c / 8) as i32);
                if x < size.x && z < size.z {
                    *v = 2.0;
                }
            }
            ws.sim.channels_mut().set(IVec2::new(tx, tz), w, &sheet);
        }
    }
    let start = ws.sim.channels().total(w);
    for step in 0..150 {
        let (r, _) = ws.step_within_cfl(&mut world, 0.05, 0.5);
        assert!(r.errors.is_empty(), "step {step}: {:?}", r.errors);
    }
    let now = ws.sim.channels().total(w);
    assert!(ws.drained > 0.0, "nothing left over the edges");
    assert!(
        ((now + ws.drained) - start).abs() < 1e-9 * start,
        "world {now} + drained {} != {start}",
        ws.drained
    );
    let after = past_the_edge(&world);
    assert!(before == after, "voxels outside the world were written");
}

/// Regression (long-run probe): a value out of bounds in the ring of tiles
/// around the world (where drained water and slid snow collect) was named
/// by a column outside the world, with nothing to say what it was. The
/// error says so there, and only there.
#[test]
fn a_bound_error_in_the_ring_around_the_world_says_where_that_is() {
    let error_at = |tile: &str| {
        let mut world = terrain(IVec3::new(16, 32, 16), 3);
        let mut ws = WorldSim::with_edges(&mut world, true);
        let text = format!(
            "return {{ channels = {{ \"h\" }}, passes = {{ {{ name = \"p\", reads = {{}}, writes = {{ \"h\" }},\n\
             kernel = function(c, tx, tz) if {tile} then buffer.writef64(c.w.h, 0, 1e9) end end }} }} }}"
        );
        let src = ScriptSource {
            name: "spike".into(),
            text: text.into(),
        };
        ws.add_lua(src, Limits::default()).unwrap();
        let (r, _) = ws.step_within_cfl(&mut world, 0.05, 0.5);
        r.errors[0].to_string()
    };
    let ring = error_at("tx == -1 and tz == 0");
    assert!(
        ring.contains("column (-8, 0)") && ring.contains("the ring of tiles around the world"),
        "{ring}"
    );
    let inside = error_at("tx == 0 and tz == 0");
    assert!(
        inside.contains("column (0, 0)") && !inside.contains("ring"),
        "{inside}"
    );
}

/// Claim (README): column and voxel scripts run in one world, *columns
/// first, in the same tick* (claims audit: nothing noticed the order). The
/// water a column script's write-back draws in a step is seen by a voxel
/// script in that same step, at that step's tick: it turns every water
/// voxel it sees at tick 0 into sand, and after one step there is sand
/// where the first step drew water.
#[test]
fn column_scripts_run_before_voxel_scripts_in_the_same_tick() {
    let mut world = terrain(IVec3::new(16, 32, 16), 3);
    let sand = world.materials.id("sand").unwrap();
    let count = |world: &brickworld::scene::SceneWorld, m: u8| {
        (0..16)
            .flat_map(|x| (0..32).flat_map(move |y| (0..16).map(move |z| IVec3::new(x, y, z))))
            .filter(|&v| world.store().voxel(v) == m)
            .count()
    };
    let sand_before = count(&world, sand);
    let mut ws = WorldSim::with_edges(&mut world, false);
    let water = world.materials.id("water").unwrap();
    assert_eq!(count(&world, water), 0, "water before the first step");
    add_shipped(&mut ws, "water");
    let mark = ScriptSource {
        name: "mark".into(),
        text: r#"return { grid = "voxels", materials = { "water", "sand" },
          passes = { { name = "p", reads = {}, writes = { "mat" },
            kernel = function(c, bx, by, bz)
              if c.tick ~= 0 then return end
              for z = 0, 7 do for y = 0, 7 do for x = 0, 7 do
                if buffer.readu8(c.r.mat, (x + 1) + (y + 1) * 10 + (z + 1) * 100) == c.m.water then
                  buffer.writeu8(c.w.mat, x + y * 8 + z * 64, c.m.sand)
                end
              end end end
            end } } }"#
            .into(),
    };
    ws.add_script(&world, mark, Limits::default()).unwrap();
    let w = ws.sim.channels_mut().channel("water");
    for tz in 0..2 {
        for tx in 0..2 {
            ws.sim.channels_mut().set(IVec2::new(tx, tz), w, &[3.0; 64]);
        }
    }
    ws.sim.wake_all();
    let r = ws.step(&mut world, 0.05);
    assert!(r.errors.is_empty(), "{:?}", r.errors);
    let marked = count(&world, sand) - sand_before;
    assert!(
        marked > 500,
        "the voxel script saw {marked} water voxels the columns drew"
    );
}

/// Claim (README, `sim`): with closed edges, a world whose x and z are not
/// multiples of 8 keeps its partial tiles' outer cells in the simulation:
/// rain falls there too and is conserved with the rest, nothing drains,
/// and nothing is drawn outside the world (claims audit: every odd-size
/// test drained its edges).
#[test]
fn closed_edges_keep_a_partial_tiles_outer_cells_and_conserve_their_rain() {
    let size = IVec3::new(37, 32, 44);
    let mut world = terrain(size, 7);
    let before = past_the_edge(&world);
    let mut ws = WorldSim::with_edges(&mut world, false);
    let water = add_shipped(&mut ws, "water");
    let rain = 0.25;
    ws.set_param(water, "rain", rain).unwrap();
    let w = ws.sim.channels_mut().channel("water");
    let start = ws.sim.channels().total(w);
    let (steps, dt) = (60, 0.05);
    for step in 0..steps {
        let (r, _) = ws.step_within_cfl(&mut world, dt, 0.5);
        assert!(r.errors.is_empty(), "step {step}: {:?}", r.errors);
    }
    assert_eq!(ws.drained, 0.0, "closed edges drained");
    // Every cell of the 5 × 6 tiles, the 1 628 in the world and the 292
    // past its edge, took its rain.
    let fell = rain * dt * steps as f64 * (40.0 * 48.0);
    let now = ws.sim.channels().total(w);
    assert!(
        (now - (start + fell)).abs() < 1e-9 * now,
        "world {now} != {start} + rain {fell} (over the world's own cells alone: {})",
        rain * dt * steps as f64 * (37.0 * 44.0)
    );
    assert!(
        before == past_the_edge(&world),
        "voxels outside the world were written"
    );
}

/// Regression (hostile probe): on a world whose edge columns are at height
/// 0 or 1 (a heightmap with a black sea border) the moat lies below 0, and
/// the shipped erosion "dissolved" a negative amount of ground there once
/// it rained, driving sediment below 0 and failing every step.
#[test]
fn erosion_runs_on_a_world_whose_edge_is_at_height_0() {
    use brickworld::world::{BrickStore, Palette};
    let mut store = BrickStore::new(Palette::grey_ramp());
    for x in 0..32 {
        for z in 0..32 {
            let h = (x + z) / 4;
            if h > 0 {
                store.fill_box(IVec3::new(x, 0, z), IVec3::new(x + 1, h, z + 1), 1);
            }
        }
    }
    store.take_modified();
    let mut world =
        brickworld::scene::SceneWorld::new(store, IVec3::ZERO, IVec3::new(32, 32, 32)).unwrap();
    let mut ws = WorldSim::with_edges(&mut world, true);
    for name in ["water", "erosion"] {
        add_shipped(&mut ws, name);
    }
    ws.set_param(0, "rain", 0.3).unwrap();
    for step in 0..40 {
        let (r, _) = ws.step_within_cfl(&mut world, 0.05, 0.5);
        assert!(r.errors.is_empty(), "step {step}: {:?}", r.errors);
    }
    let s = ws.sim.channels().find("sediment").unwrap();
    assert!(ws.sim.channels().total(s) >= 0.0);
}

/// Known gap, closed: the columns read their ground once, at the start,
/// so their water flowed through what a voxel script piled as if it were
/// not there. A voxel script raises a sand tower in a shallow lake at tick
/// 0, and digs a pit: the column under the tower takes its top as its
/// ground, the water that sat there is drawn on the tower and runs off it,
/// the pit's column takes the pit's floor and fills, and none is lost.
#[test]
fn the_columns_ground_follows_a_tower_a_voxel_script_raises() {
    use brickworld::world::{BrickStore, Palette};
    let mut store = BrickStore::new(Palette::grey_ramp());
    store.fill_box(IVec3::ZERO, IVec3::new(16, 4, 16), 1);
    store.take_modified();
    let mut world =
        brickworld::scene::SceneWorld::new(store, IVec3::ZERO, IVec3::new(16, 32, 16)).unwrap();
    let def = brickworld::world::MaterialDef {
        color: [200, 180, 120],
        kind: brickworld::world::MaterialKind::Granular,
        density: 1.5,
    };
    world.materials.register("sand", def).unwrap();
    let mut ws = WorldSim::with_edges(&mut world, false);
    add_shipped(&mut ws, "water");
    let tower = ScriptSource {
        name: "tower".into(),
        text: r#"return { grid = "voxels", materials = { "sand" },
          passes = { { name = "p", reads = {}, writes = { "mat" },
            kernel = function(c, bx, by, bz)
              if c.tick ~= 0 or by ~= 0 then return end
              if bx == 0 and bz == 0 then
                for y = 4, 7 do buffer.writeu8(c.w.mat, 5 + y * 8 + 5 * 64, c.m.sand) end
              elseif bx == 1 and bz == 1 then
                for y = 2, 3 do buffer.writeu8(c.w.mat, 2 + y * 8 + 2 * 64, 0) end
              end
            end } } }"#
            .into(),
    };
    ws.add_script(&world, tower, Limits::default()).unwrap();
    let sand = world.materials.id("sand").unwrap();
    let w = ws.sim.channels_mut().channel("water");
    for tz in 0..2 {
        for tx in 0..2 {
            ws.sim.channels_mut().set(IVec2::new(tx, tz), w, &[2.0; 64]);
        }
    }
    ws.sim.wake_all();
    let start = ws.sim.channels().total(w);
    let r = ws.step(&mut world, 0.05);
    assert!(r.errors.is_empty(), "{:?}", r.errors);
    let g = ws.sim.channels().find("ground").unwrap();
    let ground = |ws: &WorldSim| ws.sim.channels().get(IVec2::ZERO, g).unwrap()[5 + 5 * 8];
    assert_eq!(ground(&ws), 8.0, "the column under the tower");
    let pit = IVec2::new(1, 1);
    assert_eq!(
        ws.sim.channels().get(pit, g).unwrap()[2 + 2 * 8],
        2.0,
        "the pit's column"
    );
    assert_eq!(world.store().voxel(IVec3::new(5, 7, 5)), sand);
    // Its water is drawn on the tower, not inside it.
    assert_eq!(
        world.store().voxel(IVec3::new(5, 8, 5)),
        world.materials.id("water").unwrap()
    );
    for step in 0..200 {
        let r = ws.step(&mut world, 0.05);
        assert!(r.errors.is_empty(), "step {step}: {:?}", r.errors);
    }
    assert_eq!(ground(&ws), 8.0);
    let on_top = ws.sim.channels().get(IVec2::ZERO, w).unwrap()[5 + 5 * 8];
    assert!(on_top < 0.05, "{on_top} of water stays on the tower");
    assert_eq!(world.store().voxel(IVec3::new(5, 8, 5)), 0);
    // The pit holds the lake's depth and its own, water to its floor.
    let in_pit = ws.sim.channels().get(pit, w).unwrap()[2 + 2 * 8];
    assert!(in_pit > 3.5, "{in_pit} of water in the pit");
    let water = world.materials.id("water").unwrap();
    for y in 2..5 {
        assert_eq!(world.store().voxel(IVec3::new(10, y, 10)), water, "y = {y}");
    }
    for y in 4..8 {
        assert_eq!(world.store().voxel(IVec3::new(5, y, 5)), sand, "y = {y}");
    }
    let now = ws.sim.channels().total(w);
    assert!((now - start).abs() < 1e-9 * start, "water {start} -> {now}");
}

mod common;
use common::cli::{assert_clear_failure, assert_success, bin, read_json};

fn tmp(name: &str) -> common::scratch::Scratch {
    common::cli::tmp("simcli", name)
}

#[test]
fn sim_command_runs_all_scripts_and_renders() {
    let png = tmp("s.png");
    let root = env!("CARGO_MANIFEST_DIR");
    let out = bin()
        .args([
            "sim", "--scene", "terrain", "--size", "32x32x32", "--steps", "5", "--width", "32",
            "--height", "24",
        ])
        .args([
            "--script",
            &format!("{root}/scripts/water.lua"),
            "--script",
            &format!("{root}/scripts/erosion.lua"),
        ])
        .args([
            "--script",
            &format!("{root}/scripts/snow.lua"),
            "--param",
            "water.rain=0.5",
            "--param",
            "snow.snowfall=0.5",
        ])
        .arg("--out")
        .arg(&png)
        .output()
        .unwrap();
    let err = String::from_utf8_lossy(&out.stderr);
    assert!(out.status.success(), "{err}");
    assert!(err.contains("total water"), "{err}");
    assert!(std::fs::metadata(&png).unwrap().len() > 100);
}

/// Regression (stop-path probe): time the process spent stopped (Ctrl-Z,
/// SIGSTOP, a paused VM) counted against a kernel call's 5 s time budget,
/// so a 100 ms kernel failed its step after a suspend of 6 s, and `sim`
/// exited 1. The budget counts the thread's own running time now.
#[cfg(target_os = "linux")]
#[test]
fn a_suspend_longer_than_the_time_budget_fails_no_kernel() {
    let script = tmp("slow.lua");
    std::fs::write(
        &script,
        r#"return { channels = { "acc" },
  params = { spin = { default = 15000000, min = 0, max = 20000000 } },
  passes = { { name = "p", reads = { "acc" }, writes = { "acc" },
    kernel = function(c)
      local x = 0
      for i = 1, c.p.spin do x = x + 1 end
      buffer.writef64(c.w.acc, 0, buffer.readf64(c.w.acc, 0) + x * 1e-9)
    end } } }"#,
    )
    .unwrap();
    let png = tmp("slow.png");
    let child = bin()
        .args([
            "sim", "--scene", "terrain", "--size", "16x16x16", "--steps", "20", "--width", "16",
            "--height", "12",
        ])
        .arg("--script")
        .arg(&script)
        .arg("--out")
        .arg(&png)
        .stdout(std::process::Stdio::null())
        .stderr(std::process::Stdio::piped())
        .spawn()
        .unwrap();
    std::thread::sleep(std::time::Duration::from_millis(1500));
    common::signal("-STOP", child.id());
    std::thread::sleep(std::time::Duration::from_secs(6));
    common::signal("-CONT", child.id());
    let out = child.wait_with_output().unwrap();
    let err = String::from_utf8_lossy(&out.stderr);
    assert!(out.status.success(), "{err}");
    assert!(!err.contains("budget"), "{err}");
}

#[test]
fn sim_command_rejects_bad_input_clearly() {
    let root = env!("CARGO_MANIFEST_DIR");
    let water = format!("{root}/scripts/water.lua");
    let bad = tmp("broken.lua");
    std::fs::write(&bad, "return {\n  channels = { \"water\" \n").unwrap();
    // Regression (hostile probe 2): a script named with a dot could not be
    // reached (`--param my.water.rain=…` looked for script `my`). The name
    // ends at the last dot: this override reaches it and is range-checked.
    let dotted = tmp("my.water.lua");
    std::fs::write(&dotted, std::fs::read_to_string(&water).unwrap()).unwrap();
    let dotted = dotted.to_str().unwrap().to_string();
    for (args, needle) in [
        (
            vec!["sim", "--script", &dotted, "--param", "my.water.rain=99"],
            "outside [0, 10]",
        ),
        (
            vec!["sim", "--script", "/nonexistent/x.lua"],
            "cannot read /nonexistent/x.lua",
        ),
        (
            vec!["sim", "--script", bad.to_str().unwrap()],
            "broken.lua:",
        ),
        (
            vec!["sim", "--script", &water, "--param", "water.rain=99"],
            "outside [0, 10]",
        ),
        (
            vec!["sim", "--script", &water, "--param", "lava.heat=1"],
            "not loaded",
        ),
        (
            vec!["sim", "--script", &water, "--param", "water.rain"],
            "invalid --param",
        ),
        // Regression (hostile probe): the second value silently won.
        (
            vec![
                "sim",
                "--script",
                &water,
                "--param",
                "water.rain=1",
                "--param",
                "water.rain=2",
            ],
            "water.rain is given more than once",
        ),
        (
            vec!["sim", "--script", &water, "--steps", "0"],
            "invalid --steps",
        ),
        (
            vec!["sim", "--script", &water, "--dt", "-1"],
            "invalid --dt",
        ),
        (vec!["sim"], "--script"),
        (
            vec!["bench", "sim", "--json", "/tmp/x.json", "--sizes", "12"],
            "invalid --sizes",
        ),
        (
            vec![
                "bench",
                "voxels",
                "--json",
                "/tmp/x.json",
                "--size",
                "100x48x100",
            ],
            "multiples of 16",
        ),
        (
            vec![
                "bench",
                "voxels",
                "--json",
                "/tmp/x.json",
                "--size",
                "8192x256x8192",
            ],
            "bricks; at most",
        ),
        (
            vec!["bench", "voxels", "--json", "/tmp/x.json", "--steps", "0"],
            "invalid --steps",
        ),
    ] {
        let out = bin()
            .args(&args)
            .args(["--size", "16x16x16"].iter().filter(|_| args[0] == "sim"))
            .output()
            .unwrap();
        assert_clear_failure(&out, &format!("{args:?}"), needle);
    }
}

#[test]
fn verify_and_bench_sim_write_the_documented_json() {
    let json = tmp("v.json");
    let out = bin()
        .args(["verify", "sims", "--conservation-steps", "50", "--json"])
        .arg(&json)
        .output()
        .unwrap();
    assert_success(&out);
    let v: serde_json::Value = read_json(&json);
    let names: Vec<&str> = v["cases"]
        .as_array()
        .unwrap()
        .iter()
        .map(|c| c["name"].as_str().unwrap())
        .collect();
    for n in [
        "ritter_dam_break",
        "lake_at_rest",
        "mass_conservation",
        "talus_angle",
        "stability_sweep",
        "determinism",
        "u_tube",
        "sand_pile",
        "lava_cools",
        "voxel_determinism",
        "cave_fill",
        "voxel_stability",
    ] {
        assert!(names.contains(&n), "missing case {n}");
    }
    for c in v["cases"].as_array().unwrap() {
        assert_eq!(c["passed"], true, "{c}");
        assert!(c["script"].is_string() && c["metrics"].is_object());
    }
    let json = tmp("b.json");
    let out = bin()
        .args(["bench", "sim", "--sizes", "32", "--steps", "2", "--json"])
        .arg(&json)
        .output()
        .unwrap();
    assert_success(&out);
    let v: serde_json::Value = read_json(&json);
    for s in v["scripts"].as_array().unwrap() {
        for k in [
            "name",
            "lua_cells_per_s",
            "native_cells_per_s",
            "threads",
            "active_bricks",
        ] {
            assert!(s.get(k).is_some(), "missing scripts[].{k}");
        }
    }
    let v = &v["voxels"];
    for k in ["lua", "native", "crossing", "sparse"] {
        assert!(v[k].is_object(), "missing voxels.{k} in {v}");
    }
    assert!(v["lua"]["updates_per_s"].as_f64().unwrap() > 0.0);
    assert_eq!(v["native_matches_lua"], true, "{v}");
}

/// Column scripts see one surface per column, so their write-back must
/// only ever touch voxels above the topmost solid one: rain on a mesa with a
/// sealed cave inside and an overhang along one side leaves the cave and the
/// air under the overhang dry, while water stands on the mesa.
///
/// Regression: the write-back walked the tile's span of heights (down to its
/// lowest column's ground) for every changed column, and filled the air
/// under the overhang with sediment.
#[test]
fn column_write_back_never_fills_a_cave_or_an_overhangs_underside() {
    use brickworld::scene::SceneWorld;
    use brickworld::world::{BrickStore, Palette};
    const ROCK: u8 = 6;
    let mut store = BrickStore::new(Palette::grey_ramp());
    store.fill_box(IVec3::ZERO, IVec3::new(32, 4, 32), ROCK);
    // The mesa, with a rim so that rain pools on top.
    store.fill_box(IVec3::new(4, 4, 4), IVec3::new(28, 16, 28), ROCK);
    store.fill_box(IVec3::new(6, 16, 6), IVec3::new(26, 18, 26), ROCK);
    store.fill_box(IVec3::new(8, 16, 8), IVec3::new(24, 18, 24), 0);
    let cave = (IVec3::new(8, 6, 8), IVec3::new(20, 12, 20));
    let under = (IVec3::new(22, 4, 4), IVec3::new(28, 10, 28));
    store.fill_box(cave.0, cave.1, 0);
    store.fill_box(under.0, under.1, 0);
    let mut world = SceneWorld::new(store, IVec3::ZERO, IVec3::splat(32)).unwrap();
    let mut ws = WorldSim::with_edges(&mut world, true);
    let i = add_shipped(&mut ws, "water");
    ws.set_param(i, "rain", 4.0).unwrap();
    for _ in 0..300 {
        let (r, _) = ws.step_within_cfl(&mut world, 0.05, 0.5);
        assert!(r.errors.is_empty(), "{:?}", r.errors);
    }
    let count_in = |(lo, hi): (IVec3, IVec3), pred: &dyn Fn(u8) -> bool| {
        let mut n = 0;
        for z in lo.z..hi.z {
            for y in lo.y..hi.y {
                for x in lo.x..hi.x {
                    n += pred(world.store().voxel(IVec3::new(x, y, z))) as usize;
                }
            }
        }
        n
    };
    let water = brickworld::sim::columns::writeback::WATER;
    let pooled = count_in((IVec3::new(8, 16, 8), IVec3::new(24, 18, 24)), &|m| {
        m == water
    });
    assert!(
        pooled > 100,
        "rain pools on the mesa: {pooled} water voxels"
    );
    assert_eq!(
        count_in(cave, &|m| m != 0),
        0,
        "the cave stays dry and empty"
    );
    assert_eq!(
        count_in(under, &|m| m != 0),
        0,
        "nothing under the overhang"
    );
}

/// A simulation region: only its tiles step, everything outside keeps its
/// exact values, and its edge is a wall, so the rain that fell inside is
/// all the water there is.
#[test]
fn a_simulation_region_steps_only_inside_and_its_edge_is_a_wall() {
    let mut world = terrain(IVec3::new(64, 48, 64), 5);
    let mut ws = WorldSim::with_edges(&mut world, true);
    let id = add_shipped(&mut ws, "water");
    ws.set_param(id, "rain", 0.5).unwrap();
    let (lo, hi) = (glam::IVec2::new(2, 1), glam::IVec2::new(6, 4));
    ws.sim.set_region(Some((lo, hi)));
    let water = ws.sim.channels().find("water").unwrap();
    let ground = ws.sim.channels().find("ground").unwrap();
    let (tmin, tmax) = ws.sim.tile_bounds();
    let outside = |ws: &WorldSim| {
        let mut v = Vec::new();
        for z in tmin.y..tmax.y {
            for x in tmin.x..tmax.x {
                let t = glam::IVec2::new(x, z);
                if !(t.cmpge(lo).all() && t.cmplt(hi).all()) {
                    for ch in [water, ground] {
                        v.push(ws.sim.channels().get(t, ch).copied());
                    }
                }
            }
        }
        v
    };
    let before = outside(&ws);
    let (steps, dt) = (20, 0.05);
    for _ in 0..steps {
        let r = ws.step(&mut world, dt);
        assert!(r.errors.is_empty(), "{:?}", r.errors);
        assert!(r.active_tiles <= ((hi - lo).x * (hi - lo).y) as usize);
    }
    assert!(outside(&ws) == before, "a tile outside the region changed");
    let total = ws.sim.channels().total(water);
    let rained = steps as f64 * 0.5 * dt * ((hi - lo).x * (hi - lo).y * 64) as f64;
    assert!(
        (total - rained).abs() <= 1e-9 * rained,
        "water {total} against {rained} rained inside: it crossed the edge"
    );
    assert_eq!(ws.drained, 0.0);
}

/// Regression (hostile probe): a script file name with a newline or a
/// terminal escape printed them raw in every message about the script.
#[test]
fn a_script_file_name_with_control_characters_is_refused() {
    let water =
        std::fs::read_to_string(concat!(env!("CARGO_MANIFEST_DIR"), "/scripts/water.lua")).unwrap();
    for name in ["we\nird.lua", "red\u{1b}[31m.lua", "rtl\u{202e}.lua"] {
        let path = tmp(name);
        std::fs::write(&path, &water).unwrap();
        let out = std::process::Command::new(env!("CARGO_BIN_EXE_brickworld"))
            .args(["sim", "--size", "32x32x32", "--steps", "1", "--script"])
            .arg(&path)
            .arg("--out")
            .arg(&tmp("names.png"))
            .output()
            .unwrap();
        common::cli::assert_clear_failure(
            &out,
            &format!("{name:?}"),
            "must not contain control characters",
        );
        let err = String::from_utf8_lossy(&out.stderr);
        assert!(
            !err.contains('\u{1b}') && !err.contains('\u{202e}'),
            "{err:?}"
        );
    }
}

/// A water script run every 2 ticks steps by 2·dt, so its CFL sub-steps
/// are those of a step twice as long (they were counted for dt, so its
/// sub-steps could break the CFL limit by 2×).
#[test]
fn a_script_run_every_n_ticks_is_sub_stepped_for_n_times_the_step() {
    let mut world = terrain(IVec3::new(32, 32, 32), 2);
    let mut ws = WorldSim::with_edges(&mut world, false);
    let i = add_shipped(&mut ws, "water");
    let w = ws.sim.channels_mut().channel("water");
    for tz in 0..4 {
        ws.sim.channels_mut().set(IVec2::new(0, tz), w, &[12.0; 64]);
    }
    let once = ws.substeps_for(0.4, 0.5);
    assert!(once > 2, "{once}");
    ws.set_every(i, 2);
    assert_eq!(ws.substeps_for(0.2, 0.5), once);
}
