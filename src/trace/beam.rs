//! Beam starts (Laine & Karras 2010, §4.2): a coarse pass finds, for each
//! 8×8 block of pixels, a distance before which no ray of the block meets
//! anything, and the block's rays start there.
//!
//! **Why it is safe.** The coarse pass walks the block's centre ray over
//! cells of level `s` (8, 16 or 32 voxels), choosing `s` so that the
//! block's frustum, at every distance the cell spans, is narrower than one
//! cell: every point of the frustum whose projection on the centre ray
//! falls in the cell then lies in the cell's 3×3×3 neighbourhood. While
//! those neighbourhoods are empty, so is the frustum; the first non-empty
//! one ends the walk. A pixel's point at distance `r` projects to at most
//! `r` on the centre ray, so every ray of the block may start at that
//! distance (less a small margin).
//!
//! **Why it stays exact.** A ray that starts at `t` restores its exact DDA
//! state there ([`DdaRay::advance_to`]), the state its walk from the eye
//! would have had, and finds the same voxel, face and `t`. With level of
//! detail the walk also stops where the footprint would allow a level
//! coarser than the one checked, so no coarse hit is skipped. A test holds
//! beams to bit-identical images.

use glam::{DVec3, IVec3};

use super::brickmap::BrickmapTracer;
use super::camera::Camera;
use super::dda::{DdaRay, floor_i32};
use super::lod::lod_level;
use super::ray::Ray;
use crate::world::TOP_LEVEL;

/// Beam block edge in pixels.
pub const BEAM: u32 = 8;

/// Most cells a beam walk visits (a far eye outside the grid walks its
/// empty approach at up to 32 voxels a step).
const MAX_BEAM_STEPS: u32 = 4096;

/// Safety factor on the frustum's width (f32 rounding, pixel-centre rays
/// reaching slightly past the block's corner rays never matter).
const MARGIN: f32 = 1.5;

/// The centre ray direction and the frustum's spread (tangent of the
/// largest angle between the centre ray and the block's corner rays) of
/// block `(bx, by)`.
pub fn beam_of(camera: &Camera, bx: u32, by: u32) -> (DVec3, f32) {
    let (x0, y0) = ((bx * BEAM) as f64, (by * BEAM) as f64);
    let x1 = ((bx + 1) * BEAM).min(camera.width) as f64;
    let y1 = ((by + 1) * BEAM).min(camera.height) as f64;
    let c = camera.direction_at((x0 + x1) * 0.5, (y0 + y1) * 0.5);
    let spread = [(x0, y0), (x1, y0), (x0, y1), (x1, y1)]
        .iter()
        .map(|&(x, y)| {
            let d = camera.direction_at(x, y);
            d.cross(c).length() / d.dot(c).max(1e-9)
        })
        .fold(0.0f64, f64::max);
    (c, spread as f32)
}

impl BrickmapTracer<'_> {
    /// A distance before which every ray of the beam around `centre`
    /// (spread `spread`, see [`beam_of`]) meets nothing, at level-of-detail
    /// `k` (0: exact). 0 when nothing can be said.
    pub fn beam_start(&self, centre: &Ray, spread: f32, k: f32) -> f32 {
        let Some(r) = DdaRay::new(centre) else {
            return 0.0;
        };
        // The walk starts at the eye, even outside the grid: the block's
        // other rays may enter the grid before its centre ray does.
        let o = centre.origin.to_array();
        let mut level = 3u32;
        let mut cc = o.map(|v| floor_i32(v) >> level);
        let mut ct = r.coarse_tmax(cc, level);
        let mut t_in = 0.0f32;
        let step = r.step();
        let widen = (1.0 + spread * spread).sqrt();
        for _ in 0..MAX_BEAM_STEPS {
            let mut t_out = ct[0].min(ct[1]).min(ct[2]);
            // Widen the cells until the frustum is narrower than one.
            while t_out * spread * MARGIN >= (1u32 << level) as f32 {
                if level == TOP_LEVEL {
                    return t_in;
                }
                level += 1;
                cc = cc.map(|v| v >> 1);
                ct = r.coarse_tmax(cc, level);
                t_out = ct[0].min(ct[1]).min(ct[2]);
            }
            // An off-centre ray is at distance t_out · sqrt(1 + spread²)
            // when it projects to t_out: its footprint is that much wider.
            if lod_level(t_out * k * widen) > level || !self.neighbourhood_empty(cc, level) {
                return t_in;
            }
            t_in = r.coarse_step(&mut cc, &mut ct, level);
            // Outside the grid and moving away on some axis: no later
            // cell of this walk has a neighbourhood to check.
            let n: [i32; 3] = std::array::from_fn(|a| self.dims[a] >> level);
            if (0..3).any(|a| (cc[a] < -1 && step[a] <= 0) || (cc[a] > n[a] && step[a] >= 0)) {
                return t_in;
            }
        }
        t_in
    }

    /// Whether the 3×3×3 level-`level` cells around `c` (level 3, 4 or 5)
    /// are all empty (cells outside the grid are).
    fn neighbourhood_empty(&self, c: [i32; 3], level: u32) -> bool {
        let ring = self.grid.ring().to_array();
        let n: [i32; 3] = std::array::from_fn(|a| self.dims[a] >> level);
        for dz in -1..=1 {
            for dy in -1..=1 {
                for dx in -1..=1 {
                    let q = [c[0] + dx, c[1] + dy, c[2] + dz];
                    if (0..3).any(|a| q[a] < 0 || q[a] >= n[a]) {
                        continue;
                    }
                    let solid = if level == 3 {
                        self.grid.pointer(IVec3::from(q)) != 0
                    } else {
                        self.grid.coarse().get(level, q, ring) != 0
                    };
                    if solid {
                        return false;
                    }
                }
            }
        }
        true
    }
}

/// Where a block's rays may start, given its beam's safe distance: a little
/// before it, so that rounding never starts a ray inside what it must find.
#[inline]
pub fn ray_start(beam_t: f32) -> f32 {
    (beam_t * (1.0 - 1e-3) - 0.05).max(0.0)
}
