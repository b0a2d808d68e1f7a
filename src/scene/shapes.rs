//! The `balls` (random spheres) and `hairball` (random thick tubes) scenes,
//! rasterised brick by brick in parallel through a coarse bucket grid.

use glam::{DVec3, IVec3};
use indicatif::ProgressBar;
use rayon::prelude::*;
use rustc_hash::FxHashMap;

use super::noise::hash64;
use crate::world::{BRICK_EDGE, BRICK_VOXELS, BrickContent, BrickStore, Palette, voxel_index};

/// A solid primitive; a voxel is inside when its centre is.
#[derive(Clone, Copy, Debug)]
pub enum Prim {
    /// Sphere.
    Sphere {
        /// Centre.
        c: DVec3,
        /// Radius.
        r: f64,
        /// Material.
        m: u8,
    },
    /// Capsule: points within `r` of the segment a–b.
    Capsule {
        /// One end.
        a: DVec3,
        /// Other end.
        b: DVec3,
        /// Radius.
        r: f64,
        /// Material.
        m: u8,
    },
}

impl Prim {
    fn aabb(&self) -> (DVec3, DVec3) {
        match *self {
            Prim::Sphere { c, r, .. } => (c - r, c + r),
            Prim::Capsule { a, b, r, .. } => (a.min(b) - r, a.max(b) + r),
        }
    }

    fn material(&self) -> u8 {
        match *self {
            Prim::Sphere { m, .. } | Prim::Capsule { m, .. } => m,
        }
    }

    #[inline]
    fn contains(&self, p: DVec3) -> bool {
        match *self {
            Prim::Sphere { c, r, .. } => p.distance_squared(c) <= r * r,
            Prim::Capsule { a, b, r, .. } => {
                let ab = b - a;
                let t = ((p - a).dot(ab) / ab.length_squared().max(1e-12)).clamp(0.0, 1.0);
                p.distance_squared(a + ab * t) <= r * r
            }
        }
    }
}

/// Deterministic SplitMix64 stream.
#[derive(Clone, Debug)]
pub struct Rng(u64);

impl Rng {
    /// Stream for `seed`.
    pub fn new(seed: u64) -> Self {
        Rng(hash64(seed ^ 0xb0b5))
    }
    /// Next 64 bits.
    pub fn next_u64(&mut self) -> u64 {
        self.0 = self.0.wrapping_add(0x9e37_79b9_7f4a_7c15);
        hash64(self.0)
    }
    /// Uniform in [0, 1).
    pub fn unit(&mut self) -> f64 {
        (self.next_u64() >> 11) as f64 / (1u64 << 53) as f64
    }
    /// Uniform in [lo, hi).
    pub fn range(&mut self, lo: f64, hi: f64) -> f64 {
        lo + (hi - lo) * self.unit()
    }
}

/// Twelve distinct colours for shapes, materials 1..=12.
pub fn palette() -> Palette {
    let mut p = Palette::grey_ramp();
    let colors = [
        [230, 85, 70],
        [240, 170, 60],
        [235, 220, 90],
        [120, 200, 90],
        [70, 180, 160],
        [80, 140, 230],
        [140, 100, 220],
        [220, 110, 190],
        [200, 200, 200],
        [150, 110, 80],
        [90, 90, 100],
        [250, 240, 220],
    ];
    for (i, c) in colors.iter().enumerate() {
        p.set(1 + i as u8, *c);
    }
    p
}

/// Random spheres filling `size`.
pub fn balls(size: IVec3, seed: u64) -> Vec<Prim> {
    let mut rng = Rng::new(seed);
    let min = size.min_element() as f64;
    let vol = size.as_dvec3().element_product();
    let n = ((vol / 100f64.powi(3)) as usize).clamp(24, 20_000);
    (0..n)
        .map(|i| {
            let r = rng.range(min / 64.0, min / 16.0).max(1.5);
            let c = DVec3::new(
                rng.range(0.0, size.x as f64),
                rng.range(0.0, size.y as f64),
                rng.range(0.0, size.z as f64),
            );
            Prim::Sphere {
                c,
                r,
                m: 1 + (i % 12) as u8,
            }
        })
        .collect()
}

/// Random thick tubes (random walks of capsules) filling `size`.
pub fn hairball(size: IVec3, seed: u64) -> Vec<Prim> {
    let mut rng = Rng::new(seed ^ 0x4a1b);
    let s = size.as_dvec3();
    let min = size.min_element() as f64;
    // About 3000 tubes at 1024³, fewer (by surface) at smaller sizes.
    let n = ((s.element_product() / 1024f64.powi(3)).powf(2.0 / 3.0) * 3000.0) as usize;
    let n = n.clamp(24, 50_000);
    let r = (min / 200.0).max(1.5);
    let seg = min / 10.0;
    let mut prims = Vec::new();
    for i in 0..n {
        let mut p = DVec3::new(
            rng.range(0.0, s.x),
            rng.range(0.0, s.y),
            rng.range(0.0, s.z),
        );
        let mut d = DVec3::new(
            rng.range(-1.0, 1.0),
            rng.range(-1.0, 1.0),
            rng.range(-1.0, 1.0),
        )
        .normalize_or(DVec3::X);
        for _ in 0..8 {
            let turn = DVec3::new(
                rng.range(-1.0, 1.0),
                rng.range(-1.0, 1.0),
                rng.range(-1.0, 1.0),
            );
            d = (d + turn * 0.6).normalize_or(d);
            let q = (p + d * seg).clamp(DVec3::ZERO, s - 1.0);
            prims.push(Prim::Capsule {
                a: p,
                b: q,
                r,
                m: 1 + (i % 6) as u8 * 2,
            });
            p = q;
        }
    }
    prims
}

const BUCKET_SHIFT: i32 = 6; // 64-voxel buckets = 8³ bricks

/// Rasterise primitives (clipped to `[0, size)`) into a new store.
pub fn rasterize(
    prims: &[Prim],
    size: IVec3,
    palette: Palette,
    progress: &ProgressBar,
) -> BrickStore {
    let mut buckets: FxHashMap<IVec3, Vec<u32>> = FxHashMap::default();
    for (i, p) in prims.iter().enumerate() {
        let (lo, hi) = p.aabb();
        let lo = lo.max(DVec3::ZERO).floor().as_ivec3() >> BUCKET_SHIFT;
        let hi = hi.min(size.as_dvec3() - 1.0).floor().as_ivec3() >> BUCKET_SHIFT;
        for z in lo.z..=hi.z {
            for y in lo.y..=hi.y {
                for x in lo.x..=hi.x {
                    buckets
                        .entry(IVec3::new(x, y, z))
                        .or_default()
                        .push(i as u32);
                }
            }
        }
    }
    let mut keys: Vec<IVec3> = buckets.keys().copied().collect();
    keys.sort_by_key(|k| (k.z, k.y, k.x));
    progress.set_length(keys.len() as u64);
    let store_palette = palette.clone();
    let results: Vec<Vec<(IVec3, BrickContent)>> = keys
        .par_iter()
        .map(|key| {
            let ids = &buckets[key];
            let mut out = Vec::new();
            let mut dense = [0u8; BRICK_VOXELS];
            let mut local: Vec<Prim> = Vec::new();
            let per = 1 << (BUCKET_SHIFT - 3);
            for bz in 0..per {
                for by in 0..per {
                    for bx in 0..per {
                        let b = (*key << (BUCKET_SHIFT - 3)) + IVec3::new(bx, by, bz);
                        let lo = (b * BRICK_EDGE).as_dvec3();
                        let hi = lo + BRICK_EDGE as f64;
                        if (b * BRICK_EDGE).cmpge(size).any() {
                            continue;
                        }
                        local.clear();
                        local.extend(ids.iter().map(|&i| prims[i as usize]).filter(|p| {
                            let (a, c) = p.aabb();
                            a.cmplt(hi).all() && c.cmpge(lo).all()
                        }));
                        if local.is_empty() {
                            continue;
                        }
                        for (i, d) in dense.iter_mut().enumerate() {
                            let l =
                                IVec3::new((i & 7) as i32, ((i >> 3) & 7) as i32, (i >> 6) as i32);
                            let v = b * BRICK_EDGE + l;
                            *d = 0;
                            if v.cmpge(size).any() {
                                continue;
                            }
                            let p = v.as_dvec3() + 0.5;
                            if let Some(prim) = local.iter().find(|q| q.contains(p)) {
                                *d = prim.material();
                            }
                        }
                        debug_assert_eq!(voxel_index(1, 0, 0), 1);
                        match BrickContent::from_dense(&dense, &store_palette) {
                            BrickContent::Empty => {}
                            c => out.push((b, c)),
                        }
                    }
                }
            }
            progress.inc(1);
            out
        })
        .collect();
    let mut store = BrickStore::new(palette);
    for list in results {
        for (b, c) in list {
            store.set_brick(b, c);
        }
    }
    store
}
