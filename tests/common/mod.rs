//! Shared helpers for integration tests: small scenes built once per test
//! binary, and ray generators.
#![allow(dead_code)]

pub mod cli;
pub mod daemon;
pub mod scratch;

use std::sync::OnceLock;

use brickworld::scene::{SceneSpec, SceneWorld, build_scene};
use brickworld::trace::{BrickmapTracer, DenseGrid, Ray, Svo};
use glam::{IVec3, Vec3};
use indicatif::ProgressBar;

/// A scene with all three tracers built.
pub struct Built {
    pub world: SceneWorld,
    pub svo: Svo,
    pub dense: DenseGrid,
}

impl Built {
    pub fn new(spec: &str, size: IVec3, seed: u64) -> Self {
        let spec: SceneSpec = spec.parse().unwrap();
        let world = build_scene(&spec, size, seed, &ProgressBar::hidden()).unwrap();
        Self::from_world(world)
    }

    pub fn from_world(world: SceneWorld) -> Self {
        let svo = world.svo(&ProgressBar::hidden()).unwrap();
        let dense = world.dense(1 << 32).unwrap();
        Built { world, svo, dense }
    }

    /// The brickmap tracer view (borrows the world).
    pub fn brickmap(&self) -> BrickmapTracer<'_> {
        self.world.brickmap()
    }
}

/// Small cached scenes, built once per test binary.
pub fn terrain() -> &'static Built {
    static S: OnceLock<Built> = OnceLock::new();
    S.get_or_init(|| Built::new("terrain", IVec3::new(160, 64, 136), 7))
}

pub fn caves() -> &'static Built {
    static S: OnceLock<Built> = OnceLock::new();
    S.get_or_init(|| Built::new("terrain:caves", IVec3::new(96, 64, 96), 3))
}

pub fn balls() -> &'static Built {
    static S: OnceLock<Built> = OnceLock::new();
    S.get_or_init(|| Built::new("balls", IVec3::new(120, 96, 104), 11))
}

pub fn hairball() -> &'static Built {
    static S: OnceLock<Built> = OnceLock::new();
    S.get_or_init(|| Built::new("hairball", IVec3::new(96, 96, 96), 5))
}

/// Deterministic xorshift for test rays.
pub struct TestRng(pub u64);

impl TestRng {
    pub fn next(&mut self) -> u64 {
        self.0 ^= self.0 << 13;
        self.0 ^= self.0 >> 7;
        self.0 ^= self.0 << 17;
        self.0
    }
    pub fn unit(&mut self) -> f32 {
        (self.next() >> 40) as f32 / (1u64 << 24) as f32
    }
    pub fn range(&mut self, lo: f32, hi: f32) -> f32 {
        lo + (hi - lo) * self.unit()
    }
}

/// A random local-frame ray around a box of `ext` voxels: origins inside and
/// outside, on integer planes, corners and edges; directions random, axis
/// aligned, diagonal, with exact and negative zeros.
pub fn random_ray(rng: &mut TestRng, ext: Vec3) -> Ray {
    let mut o = Vec3::new(
        rng.range(-0.3 * ext.x, 1.3 * ext.x),
        rng.range(-0.3 * ext.y, 1.3 * ext.y),
        rng.range(-0.3 * ext.z, 1.3 * ext.z),
    );
    match rng.next() % 4 {
        0 => o = o.floor(),
        1 => o.x = o.x.floor(),
        _ => {}
    }
    let mut d = Vec3::new(
        rng.range(-1.0, 1.0),
        rng.range(-1.0, 1.0),
        rng.range(-1.0, 1.0),
    );
    match rng.next() % 8 {
        0 => {
            let a = (rng.next() % 3) as usize;
            d = Vec3::ZERO;
            d[a] = if rng.next().is_multiple_of(2) {
                1.0
            } else {
                -1.0
            };
            let b = (a + 1) % 3;
            d[b] = -0.0;
        }
        1 => {
            d = Vec3::new(1.0, -1.0, 1.0)
                * if rng.next().is_multiple_of(2) {
                    1.0
                } else {
                    -1.0
                }
        }
        2 => d.y = -0.0,
        3 => d.x = 1e-8,
        _ => {}
    }
    Ray::new(o, d.normalize_or(Vec3::X))
}

/// The GPU context, or `None` (reported) when the machine has no adapter and
/// `BRICKWORLD_REQUIRE_GPU` is not `1`; with it set, no adapter is a failure.
pub fn gpu_context() -> Option<brickworld::gpu::GpuContext> {
    use brickworld::gpu::{GpuContext, GpuError};
    match GpuContext::new() {
        Ok(c) => Some(c),
        Err(GpuError::NoAdapter)
            if std::env::var("BRICKWORLD_REQUIRE_GPU").as_deref() != Ok("1") =>
        {
            eprintln!("no GPU adapter: skipping (set BRICKWORLD_REQUIRE_GPU=1 to fail instead)");
            None
        }
        Err(e) => panic!("GPU required but unavailable: {e}"),
    }
}

/// Run `f` on a rayon pool of `threads` workers (the tests that pin a
/// result for 1, 2 and N threads).
pub fn on_threads<R: Send>(threads: usize, f: impl FnOnce() -> R + Send) -> R {
    rayon::ThreadPoolBuilder::new()
        .num_threads(threads)
        .build()
        .expect("a thread pool")
        .install(f)
}

/// Send signal `sig` (as `kill` names it: `-INT`, `-RTMIN+3`) to process
/// `pid`.
pub fn signal(sig: &str, pid: u32) {
    let sent = std::process::Command::new("kill")
        .args([sig, &pid.to_string()])
        .status()
        .unwrap();
    assert!(sent.success(), "kill {sig} {pid} failed");
}
