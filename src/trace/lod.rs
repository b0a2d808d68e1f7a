//! Level of detail on the brickmap: a ray stops descending when a cell's
//! footprint falls below `C` pixels (Áfra 2012 §6.2, R ≤ t·C).
//!
//! **Footprint.** A pixel at distance `t` covers `t · θ` voxels, θ being
//! [`Camera::pixel_angle`](super::Camera::pixel_angle). With `k = C · θ`, a
//! cell of edge `2^s` may be taken whole when `2^s ≤ t·k`: it covers at most
//! `C` pixels. [`lod_level`] is that rule, in `f32` comparisons the GPU
//! shader repeats exactly.
//!
//! **The level walk** (the GPU shader's, and here the reference tests
//! hold the CPU to) is one stackless loop over the levels of
//! `world/mip.rs` ([`crate::world::CoarseLevels`]): at the current voxel it checks levels from the
//! highest one whose cell changed down to the allowed level; the first
//! empty level is walked as a coarse DDA, and a solid cell at the allowed
//! level is the hit. Levels above the highest changed bit of the cell
//! coordinates were solid when the ray entered them and still are, so they
//! are not read again. A coarse hit is the coarse cube's entry face: its
//! `t`, its normal, and the voxel through which the ray entered it.
//!
//! **The CPU's walk** is the exact walk with a level check at each step
//! ([`BrickmapTracer::walk`]): a step that entered cells up to level
//! `climbed` checks the cell of level `min(climbed, allowed)`, which is the
//! level walk's decision, while empty space is skipped and voxels stepped
//! as in the exact walk. It reports what the level walk reports, bit for
//! bit (tested on every pixel of six views at six values of C and on
//! random rays), at about the exact walk's cost per ray, where the level
//! walk cost 1.3 times as much; with `k = 0` it is the exact walk.

use glam::IVec3;

use super::brickmap::BrickmapTracer;
use super::dda::{DdaRay, DdaState};
use super::ray::{Hit, Ray};
use crate::world::{BrickRef, TOP_LEVEL, UNIFORM, voxel_index};

/// The level whose cells a ray may take whole at footprint `w = t·k`
/// voxels: the largest `s ≤ 5` with `2^s ≤ w` (0 below 2).
#[inline(always)]
pub fn lod_level(w: f32) -> u32 {
    if w < 2.0 {
        0
    } else if w < 4.0 {
        1
    } else if w < 8.0 {
        2
    } else if w < 16.0 {
        3
    } else if w < 32.0 {
        4
    } else {
        TOP_LEVEL
    }
}

/// Where along a ray the footprint allows each level: `at[l - 1]` is the
/// least `t` whose footprint `t·k` allows level `l` (1 to 5), the same
/// `f32` product [`lod_level`] sees, so that [`allowed`](Self::allowed)`(t)`
/// is `lod_level(t·k)` without a multiplication; `+inf` for exact tracing.
#[derive(Clone, Copy, Debug, PartialEq)]
pub(super) struct Footprint {
    pub(super) at: [f32; TOP_LEVEL as usize],
}

impl Footprint {
    /// No level above voxels anywhere.
    pub(super) const EXACT: Footprint = Footprint {
        at: [f32::INFINITY; TOP_LEVEL as usize],
    };

    /// The footprint of `k = C ·` pixel angle (0: exact).
    pub(super) fn new(k: f32) -> Self {
        // Every ray of a frame asks with the same `k`: remember the last.
        thread_local!(static LAST: std::cell::Cell<(u32, Footprint)> =
            const { std::cell::Cell::new((0, Footprint::EXACT)) });
        let (bits, fp) = LAST.get();
        if bits == k.to_bits() {
            return fp;
        }
        let fp = Footprint {
            at: std::array::from_fn(|l| least_t(k, (2 << l) as f32)),
        };
        LAST.set((k.to_bits(), fp));
        fp
    }

    /// The footprint of `k` for a ray whose `t` counts from `skipped`
    /// voxels past the eye: each level's distance moves that much closer
    /// (regression, review: a far eye's rays took levels as if their walk
    /// started at the eye, finer than the GPU's).
    pub(super) fn skipped(k: f32, skipped: f32) -> Self {
        let fp = Footprint::new(k);
        Footprint {
            at: fp.at.map(|a| {
                if a.is_finite() {
                    (a as f64 - skipped as f64).max(0.0) as f32
                } else {
                    a
                }
            }),
        }
    }

    /// The level whose cells a ray may take whole at distance `t`.
    #[inline(always)]
    pub(super) fn allowed(&self, t: f32) -> u32 {
        self.at.iter().map(|&a| (t >= a) as u32).sum()
    }
}

/// The least `t ≥ 0` with `t·k ≥ w` in `f32`; infinite when there is none
/// (or `k` is 0).
fn least_t(k: f32, w: f32) -> f32 {
    // Also refuses a NaN `k`: every comparison with it is false.
    if k.partial_cmp(&0.0) != Some(std::cmp::Ordering::Greater) {
        return f32::INFINITY;
    }
    let mut t = w / k;
    if !t.is_finite() {
        return f32::INFINITY;
    }
    while t > 0.0 && t.next_down() * k >= w {
        t = t.next_down();
    }
    while t * k < w {
        t = t.next_up();
    }
    t
}

impl BrickmapTracer<'_> {
    /// First cell along `ray` (entry `t ≤ t_max`) that is solid at the level
    /// its footprint allows, with `k = C ·` pixel angle (0: exact).
    pub fn trace_lod(&self, ray: &Ray, t_max: f32, k: f32) -> Option<Hit> {
        self.trace_lod_from(ray, 0.0, t_max, k)
    }

    /// [`trace_lod`](Self::trace_lod) from distance `t_start`, which must be
    /// a beam start for `k` (see [`super::beam`]).
    pub fn trace_lod_from(&self, ray: &Ray, t_start: f32, t_max: f32, k: f32) -> Option<Hit> {
        let fp = Footprint::new(k);
        // A beam start past where the footprint first allows a level would
        // start the walk where the walk from the eye checks cells entered
        // earlier with a smaller footprint: the walk always starts from
        // where only voxels are allowed, so beams change nothing.
        let t_start = t_start.min(fp.at[0].next_down());
        let (r, st) = self.start(ray, t_start)?;
        self.walk::<true>(&r, st, t_max, &fp)
    }

    /// A hit on the level-`level` cell holding the current voxel of `st`
    /// (level 0: the voxel), in the brick of grid pointer `p`.
    pub(super) fn lod_hit(&self, r: &DdaRay, st: &DdaState, level: u32, p: u32) -> Hit {
        let brick = (p != 0 && p & UNIFORM == 0)
            .then(|| self.pool.slot(p - 1))
            .flatten();
        Hit {
            t: st.t,
            voxel: self.frame.to_world(st.cell),
            normal: IVec3::from(r.normal(st)),
            material: self.lod_material(level, st.cell, p, brick),
            level: level as u8,
        }
    }

    /// A hit on the level-`level` (4 or 5) cell holding the current voxel
    /// of `st`, if it is solid.
    pub(super) fn coarse_hit(&self, r: &DdaRay, st: &DdaState, level: u32) -> Option<Hit> {
        let m = self.coarse_material(level, st.cell.map(|v| v >> level));
        (m != 0).then(|| Hit {
            t: st.t,
            voxel: self.frame.to_world(st.cell),
            normal: IVec3::from(r.normal(st)),
            material: m,
            level: level as u8,
        })
    }

    /// The material of level-`level` (4 or 5) cell `c` (in that level's
    /// cells), 0 if it is empty.
    #[inline]
    pub(super) fn coarse_material(&self, level: u32, c: [i32; 3]) -> u8 {
        let ring = self.grid.ring().to_array();
        self.grid.coarse().get(level, c, ring)
    }

    /// Material of the level-`level` cell holding local voxel `c`, whose
    /// brick has pointer `p` (and is `brick` when mixed).
    pub(super) fn lod_material(
        &self,
        level: u32,
        c: [i32; 3],
        p: u32,
        brick: Option<BrickRef<'_>>,
    ) -> u8 {
        if level >= 4 {
            return self.coarse_material(level, c.map(|v| v >> level));
        }
        let Some(b) = brick else {
            return p as u8; // uniform
        };
        let l = c.map(|v| v & 7);
        match level {
            0 => b.material_index(voxel_index(l[0], l[1], l[2])),
            _ => b.lod().at(level, l),
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// The footprint's distances give the level `lod_level` gives, at and
    /// around every threshold, for footprints from tiny to huge.
    #[test]
    fn footprint_distances_agree_with_lod_level() {
        assert_eq!(Footprint::new(0.0), Footprint::EXACT);
        for k in [1e-6f32, 3.7e-4, 0.001, 0.0123, 0.5, 1.0, 7.3, 1e4] {
            let fp = Footprint::new(k);
            for &a in &fp.at {
                for t in [a.next_down(), a, a.next_up(), a * 0.5, a * 2.0, 0.0] {
                    assert_eq!(fp.allowed(t), lod_level(t * k), "k {k}, t {t}");
                }
            }
        }
    }
}
