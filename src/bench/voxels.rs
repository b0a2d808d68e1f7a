//! `bench voxels` (and `bench sim`'s voxel figures): water3d's active-voxel
//! updates per second in Lua, against its native Rust reference
//! ([`Water3d`]) and against Lua kernels that do nothing (what gathering the
//! halos and crossing into the VM cost), all on one fully active pool in
//! the same run; and what sleeping bricks cost: the same world at rest but
//! for a walled basin of about 1 % of its bricks.

use std::sync::Arc;
use std::time::Instant;

use glam::IVec3;
use serde::Serialize;

use crate::sim::voxels::{VoxelSim, Water3d};
use crate::sim::{Limits, ScriptSource};
use crate::verify::voxels::{STONE, registry};
use crate::world::{BrickStore, MaterialRegistry, Palette};

/// water3d's declarations with kernels that do nothing: the cost of
/// gathering halos and crossing buffers into the VM and back.
const NOOP: &str = r#"
return {
  grid = "voxels",
  channels = { "water", "k" },
  materials = { "water" },
  only = { "water" },
  params = {
    compress = { default = 0.02, min = 0.0, max = 0.2 },
    fall = { default = 0.5, min = 0.0, max = 1.0 },
    spread = { default = 0.2, min = 0.0, max = 0.5 },
    still = { default = 1e-5, min = 0.0, max = 0.01 },
  },
  passes = {
    { name = "limit", reads = { "water" }, writes = { "k" }, kernel = function(c, bx, by, bz) end },
    { name = "flow", reads = { "water", "k" }, writes = { "water", "mat" }, kernel = function(c, bx, by, bz) end },
  },
}
"#;

/// One way of running the rule on the fully active world.
#[derive(Debug, Clone, Serialize)]
pub struct Throughput {
    /// Milliseconds per step.
    pub step_ms: f64,
    /// Active-voxel updates per second (candidate bricks × 512 per step).
    pub updates_per_s: f64,
    /// Candidate bricks per step.
    pub candidates: usize,
}

/// The mostly sleeping world.
#[derive(Debug, Clone, Serialize)]
pub struct Sparse {
    /// Awake bricks over the world's bricks, averaged over the timed steps.
    pub active_fraction: f64,
    /// Candidate bricks per step, averaged.
    pub candidates: f64,
    /// Milliseconds per step.
    pub step_ms: f64,
    /// step_ms over the fully active Lua step (target ≤ 0.02 at 1 % active).
    pub over_full: f64,
}

/// The voxel benchmark's figures.
#[derive(Debug, Clone, Serialize)]
pub struct VoxelBench {
    /// World size in voxels (x, y, z).
    pub world: [i32; 3],
    /// Bricks in the world's bounds.
    pub bricks: usize,
    /// Timed steps per measurement.
    pub steps: usize,
    /// Worker threads.
    pub threads: usize,
    /// water3d.lua.
    pub lua: Throughput,
    /// The native reference of the same rule.
    pub native: Throughput,
    /// Lua kernels that do nothing (halo gathering and buffer crossing).
    pub crossing: Throughput,
    /// lua.updates_per_s / native.updates_per_s (target ≥ 1/3).
    pub lua_over_native: f64,
    /// crossing.step_ms / lua.step_ms: the share of a Lua step that is not
    /// the kernel's own work.
    pub crossing_share: f64,
    /// The Lua and native runs ended bit-identical.
    pub native_matches_lua: bool,
    /// The mostly sleeping world.
    pub sparse: Sparse,
}

/// Water's surface height in the bench world: a pool from y = 1 to 40.
const SURFACE: i32 = 40;

/// A stone floor and water to y = 40 under air to y = 48, at exact
/// hydrostatic rest (a cell d below the surface holds 1 + d·compress).
fn pool(size: IVec3, kernel: Kernel) -> (BrickStore, VoxelSim, MaterialRegistry) {
    let reg = registry();
    let water = reg.id("water").unwrap_or(252);
    let mut store = BrickStore::new(Palette::grey_ramp());
    store.fill_box(IVec3::ZERO, IVec3::new(size.x, 1, size.z), STONE);
    store.fill_box(
        IVec3::new(0, 1, 0),
        IVec3::new(size.x, SURFACE, size.z),
        water,
    );
    store.take_modified();
    let mut sim = VoxelSim::new(&store, IVec3::ZERO, size, 1);
    let src = |text: &str| ScriptSource {
        name: "water3d".into(),
        text: text.into(),
    };
    let water3d = include_str!("../../scripts/water3d.lua");
    let added = match kernel {
        Kernel::Lua => sim.add_script(src(water3d), Limits::default(), &reg),
        Kernel::Native => sim.add_native(
            src(water3d),
            Limits::default(),
            &reg,
            Arc::new(Water3d::default()),
        ),
        Kernel::Noop => sim.add_script(src(NOOP), Limits::default(), &reg),
    };
    added.expect("the bench's scripts load");
    let comp = 0.02f32;
    let id = sim.channels_mut().channel("water");
    let mut bricks: Vec<IVec3> = store.iter().map(|(b, _)| b).collect();
    bricks.sort_by_key(|b| (b.z, b.y, b.x));
    for b in bricks {
        let mut d = [0u8; 512];
        store.read_dense(b, &mut d);
        let v: [f32; 512] = std::array::from_fn(|i| {
            let y = b.y * 8 + (i as i32 / 8) % 8;
            if d[i] == water {
                1.0 + (SURFACE - 1 - y) as f32 * comp
            } else {
                0.0
            }
        });
        sim.channels_mut().set(id, b, &v);
    }
    (store, sim, reg)
}

#[derive(Clone, Copy)]
enum Kernel {
    Lua,
    Native,
    Noop,
}

/// Disturb every water voxel (fills off by up to 4 %), waking everything.
fn disturb_all(sim: &mut VoxelSim) {
    let id = sim.channels().find("water").expect("declared");
    let bricks = sim.channels().sorted_bricks(id);
    for &b in &bricks {
        let mut v = *sim.channels().get(id, b).expect("listed");
        for (i, x) in v.iter_mut().enumerate() {
            *x *= 1.0 + 0.01 * ((i * 7 + b.x as usize * 13) % 5) as f32;
        }
        sim.channels_mut().set(id, b, &v);
    }
    sim.notify_edited(&bricks);
}

fn timed(
    store: &mut BrickStore,
    sim: &mut VoxelSim,
    reg: &MaterialRegistry,
    steps: usize,
) -> (f64, f64, f64) {
    let (mut cands, mut active, t0) = (0usize, 0usize, Instant::now());
    for _ in 0..steps {
        active += sim.active_bricks();
        let r = sim.step(store, reg, 0.05);
        assert!(r.errors.is_empty(), "bench step failed: {:?}", r.errors);
        cands += r.candidates;
    }
    let ms = t0.elapsed().as_secs_f64() * 1e3 / steps as f64;
    (
        ms,
        cands as f64 / steps as f64,
        active as f64 / steps as f64,
    )
}

fn throughput(size: IVec3, kernel: Kernel, steps: usize) -> (Throughput, u64) {
    let (mut store, mut sim, reg) = pool(size, kernel);
    disturb_all(&mut sim);
    // One untimed step builds each worker's VM.
    sim.step(&mut store, &reg, 0.05);
    let (ms, cands, _) = timed(&mut store, &mut sim, &reg, steps);
    let hash =
        sim.channels().hash() ^ crate::engine::checkpoint::world_hash(&store, &Default::default());
    (
        Throughput {
            step_ms: ms,
            updates_per_s: cands * 512.0 / (ms / 1e3),
            candidates: cands.round() as usize,
        },
        hash,
    )
}

/// Run the voxel benchmark on a world of `size` voxels (y ≥ 48) for
/// `steps` timed steps; `progress` is called after each measurement.
pub fn run(size: IVec3, steps: usize, mut progress: impl FnMut()) -> VoxelBench {
    let size = IVec3::new(size.x, size.y.max(SURFACE + 8), size.z);
    let bricks = ((size.x / 8) * (size.y / 8) * (size.z / 8)) as usize;
    let (lua, lua_hash) = throughput(size, Kernel::Lua, steps);
    progress();
    // The native run does the same steps (its untimed one included).
    let (native, native_hash) = throughput(size, Kernel::Native, steps);
    progress();
    let (crossing, _) = throughput(size, Kernel::Noop, steps);
    progress();
    // At rest but for a walled basin of 2x2x2 bricks at the surface, its
    // water heaped on one side.
    let (mut store, mut sim, reg) = pool(size, Kernel::Lua);
    let water = reg.id("water").unwrap_or(252);
    let c = IVec3::new(size.x / 16 * 8, SURFACE - 16, size.z / 16 * 8);
    let id = sim.channels().find("water").expect("declared");
    store.fill_box(c, c + IVec3::new(16, 1, 16), STONE);
    for (a, b) in [
        (IVec3::ZERO, IVec3::new(1, 24, 16)),
        (IVec3::new(15, 0, 0), IVec3::new(16, 24, 16)),
        (IVec3::ZERO, IVec3::new(16, 24, 1)),
        (IVec3::new(0, 0, 15), IVec3::new(16, 24, 16)),
    ] {
        store.fill_box(c + a, c + b, STONE);
    }
    store.fill_box(c + IVec3::new(1, 1, 1), c + IVec3::new(8, 16, 15), 0);
    store.fill_box(c + IVec3::new(8, 1, 1), c + IVec3::new(15, 23, 15), water);
    let mut touched = Vec::new();
    for bz in 0..2 {
        for by in 0..3 {
            for bx in 0..2 {
                let b = c.div_euclid(IVec3::splat(8)) + IVec3::new(bx, by, bz);
                let mut d = [0u8; 512];
                store.read_dense(b, &mut d);
                let v: [f32; 512] = std::array::from_fn(|i| if d[i] == water { 1.0 } else { 0.0 });
                sim.channels_mut().set(id, b, &v);
                touched.push(b);
            }
        }
    }
    store.take_modified();
    sim.notify_edited(&touched);
    // Let the pool outside the basin fall asleep.
    for _ in 0..3 {
        sim.step(&mut store, &reg, 0.05);
    }
    let (ms, cands, active) = timed(&mut store, &mut sim, &reg, steps);
    progress();
    VoxelBench {
        world: size.to_array(),
        bricks,
        steps,
        threads: rayon::current_num_threads(),
        lua_over_native: lua.updates_per_s / native.updates_per_s,
        crossing_share: crossing.step_ms / lua.step_ms,
        native_matches_lua: lua_hash == native_hash,
        sparse: Sparse {
            active_fraction: active / bricks as f64,
            candidates: cands,
            step_ms: ms,
            over_full: ms / lua.step_ms,
        },
        lua,
        native,
        crossing,
    }
}
