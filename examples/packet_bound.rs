//! How much could SIMD packets of primary rays buy the exact brickmap walk?
//! An upper bound, measured from the walk's own steps (issue 11: the one
//! candidate not yet tried for "2× Embree").
//!
//! Each primary ray of the default views is walked by a counting copy of
//! the exact walk (`BrickmapTracer::walk` with LOD off), which records its
//! operations in order: set-up, occupancy steps, brick steps, voxel steps,
//! exact restorations and the hit. Every ray's hit is checked against the
//! tracer's own, bit for bit, so the counts are the walk's.
//!
//! Packets are then simulated in lockstep, as SIMD lanes run: at each
//! iteration every live lane does its next operation, and the iteration
//! costs the sum, over the kinds of operation some lane does, of that
//! kind's cost (masked lanes wait). Steps of all three levels are taken as
//! one kind: a packet walk would run one step code with the level as data.
//! Costs per operation are the scalar walk's, from the regression of per-ray
//! time in docs/tracing-experiments.md (set-up 75 ns, occupancy step 12,
//! brick step 10.5, voxel step 12, restoration 52, hit 72), and a SIMD
//! operation over all lanes is taken to cost what one scalar operation
//! costs. That is generous (gathers of occupancy bits, pointers and mask
//! words are one load a lane), so the modelled speed-ups are upper bounds.
//!
//! Two packet disciplines:
//! - **fixed**: a packet is a tile of `w × h` pixels, run to its last
//!   ray (as Embree's ray packets and Wald's coherent grid traversal);
//! - **refill**: `n` lanes, each taking the next ray of the image (in
//!   8 × 8 tiles) as soon as its ray ends (a wavefront with compaction;
//!   its set-up is then an operation like the others).
//!
//! A speed-up of S at `n` lanes means: packets pay only while one SIMD
//! operation over the `n` lanes costs less than S scalar ones, and they
//! give a gain G only if it costs at most S / G.
//!
//! `cargo run --release --example packet_bound -- [SCENE] [SIZE] [WIDTH]`
//! (SCENE as `bench tracers --scene`, default `terrain`; SIZE the side,
//! default 1024, height 256 (`HEIGHT=H` to change); WIDTH default 1024,
//! height ¾ of it.)

use brickworld::scene::{SceneSpec, build_scene};
use brickworld::trace::dda::{DdaRay, DdaState};
use brickworld::trace::{Camera, Hit, Ray, Tracer};
use brickworld::world::{BRICK_SHIFT, BrickGrid, BrickPool, OCC_SHIFT, UNIFORM, voxel_index};
use glam::{DVec3, IVec3};
use indicatif::ProgressBar;

/// One operation of the walk.
#[derive(Clone, Copy, PartialEq, Eq, Debug)]
enum Op {
    Setup,
    Occ,
    Brick,
    Voxel,
    Restore,
    Hit,
}

/// The scalar walk's cost of an operation, ns (docs/tracing-experiments.md).
fn cost(op: Op) -> f64 {
    match op {
        Op::Setup => 75.0,
        Op::Occ => 12.0,
        Op::Brick => 10.5,
        Op::Voxel => 12.0,
        Op::Restore => 52.0,
        Op::Hit => 72.0,
    }
}

/// The kind a packet runs an operation as: the three steps are one.
fn kind(op: Op) -> usize {
    match op {
        Op::Setup => 0,
        Op::Occ | Op::Brick | Op::Voxel => 1,
        Op::Restore => 2,
        Op::Hit => 3,
    }
}

/// The cost of one SIMD operation of each kind (the scalar step's, 12 ns,
/// for the unified step).
const KIND_COST: [f64; 4] = [75.0, 12.0, 52.0, 72.0];

const OCC_VOXEL_SHIFT: i32 = OCC_SHIFT + BRICK_SHIFT;

/// The exact walk of `BrickmapTracer` (LOD off, no `t_max`), recording
/// its operations in `ops`; returns its hit as (t, local cell, normal,
/// material).
fn walk(
    grid: &BrickGrid,
    pool: &BrickPool,
    dims: [i32; 3],
    ray: &Ray,
    ops: &mut Vec<Op>,
) -> Option<(f32, [i32; 3], [i32; 3], u8)> {
    let inside = |c: [i32; 3]| (0..3).all(|a| (c[a] as u32) < dims[a] as u32);
    let inside_occ =
        |o: [i32; 3]| (0..3).all(|a| (o[a] as u32) < (dims[a] >> OCC_VOXEL_SHIFT) as u32);
    let hit = |r: &DdaRay, st: &DdaState, m: u8, ops: &mut Vec<Op>| {
        ops.push(Op::Hit);
        Some((st.t, st.cell, r.normal(st), m))
    };
    ops.push(Op::Setup);
    let r = DdaRay::new(ray)?;
    let mut st = r.enter([0; 3], dims)?;
    'occupancy: loop {
        let mut oc = st.cell.map(|v| v >> OCC_VOXEL_SHIFT);
        if !grid.occupied(IVec3::from(oc)) {
            let shift = OCC_VOXEL_SHIFT as u32;
            let mut ot = r.coarse_tmax(oc, shift);
            loop {
                let t = r.coarse_step(&mut oc, &mut ot, shift);
                ops.push(Op::Occ);
                if !inside_occ(oc) {
                    return None;
                }
                if grid.occupied(IVec3::from(oc)) {
                    r.advance_to(&mut st, t);
                    ops.push(Op::Restore);
                    break;
                }
            }
        }
        let mut bc = st.cell.map(|v| v >> BRICK_SHIFT);
        loop {
            let p = grid.pointer(IVec3::from(bc));
            if p == 0 {
                let shift = BRICK_SHIFT as u32;
                let mut bt = r.coarse_tmax(bc, shift);
                loop {
                    let t = r.coarse_step(&mut bc, &mut bt, shift);
                    ops.push(Op::Brick);
                    if bc.map(|v| v >> OCC_SHIFT) != oc {
                        r.advance_to(&mut st, t);
                        ops.push(Op::Restore);
                        if !inside(st.cell) {
                            return None;
                        }
                        continue 'occupancy;
                    }
                    if grid.pointer(IVec3::from(bc)) != 0 {
                        r.advance_to(&mut st, t);
                        ops.push(Op::Restore);
                        break;
                    }
                }
                continue;
            }
            if p & UNIFORM != 0 {
                return hit(&r, &st, p as u8, ops);
            }
            let brick = pool.slot(p - 1)?;
            let mask = brick.mask();
            loop {
                let l = st.cell.map(|v| v & 7);
                let i = voxel_index(l[0], l[1], l[2]);
                if (mask[i >> 6] >> (i & 63)) & 1 != 0 {
                    return hit(&r, &st, brick.material_index(i), ops);
                }
                r.step_fine(&mut st);
                ops.push(Op::Voxel);
                if st.cell.map(|v| v >> BRICK_SHIFT) != bc {
                    break;
                }
            }
            if !inside(st.cell) {
                return None;
            }
            if st.cell.map(|v| v >> OCC_VOXEL_SHIFT) != oc {
                continue 'occupancy;
            }
            bc = st.cell.map(|v| v >> BRICK_SHIFT);
        }
    }
}

/// The kinds of operation the lanes do in one lockstep iteration.
#[derive(Default)]
struct Iteration([bool; 4]);

impl Iteration {
    /// A lane does `op`; 1 if it is a step.
    fn add(&mut self, op: Op) -> usize {
        self.0[kind(op)] = true;
        (kind(op) == 1) as usize
    }

    /// What the iteration costs: each kind some lane does, once.
    fn cost(&self) -> f64 {
        (0..4).filter(|&i| self.0[i]).map(|i| KIND_COST[i]).sum()
    }
}

/// Lockstep cost of running `seqs` together, one operation a lane per
/// iteration; returns (cost in ns, iterations, lane-steps done).
fn lockstep(seqs: &[&[Op]]) -> (f64, usize, usize) {
    let len = seqs.iter().map(|s| s.len()).max().unwrap_or(0);
    let mut total = 0.0;
    let mut steps = 0;
    for k in 0..len {
        let mut it = Iteration::default();
        for s in seqs {
            if let Some(&op) = s.get(k) {
                steps += it.add(op);
            }
        }
        total += it.cost();
    }
    (total, len, steps)
}

/// `n` lanes refilled from `order` as rays end; returns (cost, iterations,
/// lane-steps done).
fn refill(seqs: &[Vec<Op>], order: &[usize], n: usize) -> (f64, usize, usize) {
    let mut next = 0;
    let mut lanes: Vec<Option<(usize, usize)>> = vec![None; n];
    let (mut total, mut iters, mut steps) = (0.0, 0, 0);
    loop {
        for lane in lanes.iter_mut() {
            while lane.is_none() && next < order.len() {
                let r = order[next];
                next += 1;
                if !seqs[r].is_empty() {
                    *lane = Some((r, 0));
                }
            }
        }
        if lanes.iter().all(|l| l.is_none()) {
            return (total, iters, steps);
        }
        let mut it = Iteration::default();
        for lane in lanes.iter_mut() {
            if let Some((r, k)) = *lane {
                steps += it.add(seqs[r][k]);
                *lane = (k + 1 < seqs[r].len()).then_some((r, k + 1));
            }
        }
        total += it.cost();
        iters += 1;
    }
}

fn main() {
    let args: Vec<String> = std::env::args().collect();
    let spec: SceneSpec = args
        .get(1)
        .map_or("terrain", |s| s.as_str())
        .parse()
        .expect("scene");
    let size: i32 = args.get(2).and_then(|s| s.parse().ok()).unwrap_or(1024);
    let w: u32 = args.get(3).and_then(|s| s.parse().ok()).unwrap_or(1024);
    let h = w * 3 / 4;
    let height = std::env::var("HEIGHT").map_or(256, |v| v.parse().expect("HEIGHT"));
    let world = build_scene(
        &spec,
        IVec3::new(size, height, size),
        1,
        &ProgressBar::hidden(),
    )
    .unwrap();
    let bm = world.brickmap();
    let grid = world.grid();
    let pool = world.store().pool();
    let dims = (grid.dims() << BRICK_SHIFT).to_array();
    let frame = world.frame();
    println!(
        "{spec:?} {size}x{height}x{size}, {w}x{h}; modelled speed-up of packets over the scalar walk (upper bounds)"
    );
    for (vi, view) in world.default_views().iter().enumerate() {
        let cam = Camera::new(
            DVec3::from(view.eye),
            DVec3::from(view.target),
            view.fov,
            w,
            h,
        )
        .unwrap();
        let mut seqs: Vec<Vec<Op>> = Vec::with_capacity((w * h) as usize);
        let mut counts = [0usize; 6];
        for j in 0..h {
            for i in 0..w {
                let ray = Ray::new(frame.to_local(cam.eye), cam.direction(i, j).as_vec3());
                let mut ops = Vec::new();
                let got = walk(grid, pool, dims, &ray, &mut ops);
                let want = bm.trace(&ray, f32::INFINITY).map(|h: Hit| {
                    (
                        h.t,
                        (h.voxel - frame.anchor).to_array(),
                        h.normal.to_array(),
                        h.material,
                    )
                });
                assert_eq!(got, want, "view {vi}, pixel ({i}, {j})");
                for &op in &ops {
                    counts[op as usize] += 1;
                }
                seqs.push(ops);
            }
        }
        let rays = seqs.len() as f64;
        let scalar: f64 = seqs.iter().flatten().map(|&op| cost(op)).sum();
        println!(
            "view {vi}: per ray {:.1} occupancy, {:.1} brick, {:.1} voxel steps, {:.2} restorations, {:.2} hits; scalar model {:.0} ns a ray",
            counts[1] as f64 / rays,
            counts[2] as f64 / rays,
            counts[3] as f64 / rays,
            counts[4] as f64 / rays,
            counts[5] as f64 / rays,
            scalar / rays
        );
        let index = |i: u32, j: u32| (j * w + i) as usize;
        for (tw, th) in [(2u32, 2u32), (4, 1), (4, 2), (8, 1), (4, 4)] {
            let (mut total, mut lane_iters, mut steps) = (0.0, 0usize, 0usize);
            for ty in (0..h).step_by(th as usize) {
                for tx in (0..w).step_by(tw as usize) {
                    let members: Vec<&[Op]> = (ty..(ty + th).min(h))
                        .flat_map(|j| (tx..(tx + tw).min(w)).map(move |i| (i, j)))
                        .map(|(i, j)| seqs[index(i, j)].as_slice())
                        .collect();
                    let (c, iters, s) = lockstep(&members);
                    total += c;
                    lane_iters += iters * members.len();
                    steps += s;
                }
            }
            println!(
                "  fixed {tw}x{th} ({:2} lanes): lanes stepping {:4.1} % of lane-iterations, speed-up ≤ {:.2}×",
                tw * th,
                100.0 * steps as f64 / lane_iters as f64,
                scalar / total
            );
        }
        // Image order in 8 × 8 tiles, for the refill lanes.
        let mut order = Vec::with_capacity(seqs.len());
        for ty in (0..h).step_by(8) {
            for tx in (0..w).step_by(8) {
                for j in ty..(ty + 8).min(h) {
                    for i in tx..(tx + 8).min(w) {
                        order.push(index(i, j));
                    }
                }
            }
        }
        for n in [4usize, 8, 16] {
            let (total, iters, steps) = refill(&seqs, &order, n);
            println!(
                "  refill {n:2} lanes: lanes stepping {:4.1} % of lane-iterations, speed-up ≤ {:.2}×",
                100.0 * steps as f64 / (iters * n) as f64,
                scalar / total
            );
        }
    }
}
