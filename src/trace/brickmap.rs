//! The brickmap tracer: a stackless three-level DDA, occupancy layer (32³
//! voxels) → brick grid (8³) → brick mask (1³), after van Wingerden §3.3–3.4.
//!
//! Each iteration re-derives its level from the current cell: no stack, no
//! restart. Empty occupancy cells and empty bricks are skipped in one exact
//! [`DdaRay::skip`]; inside a brick the walk steps voxel by voxel against the
//! 512-bit mask and only touches material data at the hit.

use glam::IVec3;

use super::Tracer;
use super::dda::DdaRay;
use super::ray::{Frame, Hit, Ray};
use crate::world::{BRICK_SHIFT, BrickGrid, BrickPool, OCC_SHIFT, UNIFORM, voxel_index};

/// A tracer over a [`BrickGrid`] and the pool its pointers index.
#[derive(Clone, Copy, Debug)]
pub struct BrickmapTracer<'w> {
    grid: &'w BrickGrid,
    pool: &'w BrickPool,
    frame: Frame,
    dims: [i32; 3],
}

const OCC_VOXEL_SHIFT: i32 = OCC_SHIFT + BRICK_SHIFT;

impl<'w> BrickmapTracer<'w> {
    /// Trace `grid`, whose mixed-brick pointers index `pool`.
    pub fn new(grid: &'w BrickGrid, pool: &'w BrickPool) -> Self {
        let frame = Frame {
            anchor: grid.origin() << BRICK_SHIFT,
        };
        BrickmapTracer {
            grid,
            pool,
            frame,
            dims: (grid.dims() << BRICK_SHIFT).to_array(),
        }
    }

    #[inline(always)]
    fn inside(&self, c: [i32; 3]) -> bool {
        (c[0] as u32) < self.dims[0] as u32
            && (c[1] as u32) < self.dims[1] as u32
            && (c[2] as u32) < self.dims[2] as u32
    }

    fn hit(&self, r: &DdaRay, st: &super::dda::DdaState, material: u8) -> Hit {
        Hit {
            t: st.t,
            voxel: self.frame.to_world(st.cell),
            normal: IVec3::from(r.normal(st)),
            material,
        }
    }
}

impl Tracer for BrickmapTracer<'_> {
    fn name(&self) -> &'static str {
        "brickmap"
    }

    fn frame(&self) -> Frame {
        self.frame
    }

    fn trace(&self, ray: &Ray, t_max: f32) -> Option<Hit> {
        let r = DdaRay::new(ray)?;
        let mut st = r.enter([0; 3], self.dims)?;
        loop {
            if st.t > t_max {
                return None;
            }
            let c = IVec3::from(st.cell);
            if !self.grid.occupied(c >> OCC_VOXEL_SHIFT) {
                r.skip(&mut st, OCC_VOXEL_SHIFT as u32);
            } else {
                let brick_cell = c >> BRICK_SHIFT;
                let p = self.grid.pointer(brick_cell);
                if p == 0 {
                    r.skip(&mut st, BRICK_SHIFT as u32);
                } else if p & UNIFORM != 0 {
                    return Some(self.hit(&r, &st, p as u8));
                } else {
                    let brick = self.pool.slot(p - 1)?;
                    let mask = brick.mask();
                    let bc = st.cell.map(|v| v >> BRICK_SHIFT);
                    loop {
                        let l = st.cell.map(|v| v & 7);
                        let i = voxel_index(l[0], l[1], l[2]);
                        if (mask[i >> 6] >> (i & 63)) & 1 != 0 {
                            return Some(self.hit(&r, &st, brick.material_index(i)));
                        }
                        r.step_fine(&mut st);
                        if st.t > t_max {
                            return None;
                        }
                        if st.cell.map(|v| v >> BRICK_SHIFT) != bc {
                            break;
                        }
                    }
                }
            }
            if !self.inside(st.cell) {
                return None;
            }
        }
    }

    fn bytes(&self) -> usize {
        self.grid.bytes() + self.pool.bytes()
    }

    fn nodes_or_bricks(&self) -> u64 {
        self.grid.non_empty() as u64
    }
}
