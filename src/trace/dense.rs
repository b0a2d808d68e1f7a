//! The cartesian baseline: a dense bit grid (one bit per voxel) walked with
//! the Amanatides–Woo 3D-DDA, plus one material byte per voxel for shading.

use glam::IVec3;
use rayon::prelude::*;

use super::dda::DdaRay;
use super::ray::{Frame, Hit, Ray};
use super::{TraceError, Tracer};
use crate::world::{BRICK_EDGE, BRICK_VOXELS, BrickStore};

/// Dense occupancy bits and materials over a box of voxels.
#[derive(Debug)]
pub struct DenseGrid {
    frame: Frame,
    dims: [i32; 3],
    row_words: usize,
    bits: Vec<u64>,
    mats: Vec<u8>,
}

impl DenseGrid {
    /// Bytes a dense grid of `dims` voxels needs.
    pub fn bytes_for(dims: IVec3) -> u64 {
        let row_words = (dims.x as u64).div_ceil(64);
        let rows = dims.y as u64 * dims.z as u64;
        rows * row_words * 8 + dims.x as u64 * rows
    }

    /// Copy the voxels of `store` inside `[anchor, anchor + dims)` into a
    /// dense grid. Refuses with [`TraceError::DenseTooLarge`] over `limit` bytes.
    pub fn build(
        store: &BrickStore,
        frame: Frame,
        dims: IVec3,
        limit: u64,
    ) -> Result<Self, TraceError> {
        let bytes = Self::bytes_for(dims);
        if bytes > limit {
            return Err(TraceError::DenseTooLarge { dims, bytes, limit });
        }
        // Under the limit is not enough (regression: a grid under the
        // default 8 GiB limit aborted a machine with less).
        let available = crate::scene::budget::available_bytes();
        if bytes > available {
            return Err(TraceError::DenseOutOfMemory {
                dims,
                bytes,
                available,
            });
        }
        let (dx, dy, dz) = (dims.x as usize, dims.y as usize, dims.z as usize);
        let row_words = dx.div_ceil(64);
        let mut bits = vec![0u64; row_words * dy * dz];
        let mut mats = vec![0u8; dx * dy * dz];
        let slabs = dz.div_ceil(BRICK_EDGE as usize);
        let mut by_slab: Vec<Vec<IVec3>> = vec![Vec::new(); slabs];
        let origin_brick = frame.anchor / BRICK_EDGE;
        for (b, _) in store.iter() {
            let l = b - origin_brick;
            if l.cmpge(IVec3::ZERO).all() && (l * BRICK_EDGE).cmplt(dims).all() {
                by_slab[l.z as usize].push(b);
            }
        }
        let slab_voxels = dx * dy * BRICK_EDGE as usize;
        let slab_words = row_words * dy * BRICK_EDGE as usize;
        mats.par_chunks_mut(slab_voxels)
            .zip(bits.par_chunks_mut(slab_words))
            .zip(by_slab.par_iter())
            .for_each(|((mats, bits), bricks)| {
                let mut dense = [0u8; BRICK_VOXELS];
                for &b in bricks {
                    store.read_dense(b, &mut dense);
                    let base = (b - origin_brick) * BRICK_EDGE;
                    for (i, &m) in dense.iter().enumerate() {
                        if m == 0 {
                            continue;
                        }
                        let x = base.x as usize + (i & 7);
                        let y = base.y as usize + ((i >> 3) & 7);
                        let zl = (i >> 6) & 7;
                        if x >= dx || y >= dy || (base.z as usize + zl) >= dz {
                            continue;
                        }
                        mats[x + dx * (y + dy * zl)] = m;
                        bits[(y + dy * zl) * row_words + (x >> 6)] |= 1 << (x & 63);
                    }
                }
            });
        Ok(DenseGrid {
            frame,
            dims: dims.to_array(),
            row_words,
            bits,
            mats,
        })
    }

    #[inline(always)]
    fn solid(&self, c: [i32; 3]) -> bool {
        let (x, y, z) = (c[0] as usize, c[1] as usize, c[2] as usize);
        let w = (y + self.dims[1] as usize * z) * self.row_words + (x >> 6);
        (self.bits[w] >> (x & 63)) & 1 != 0
    }

    #[inline(always)]
    fn inside(&self, c: [i32; 3]) -> bool {
        (c[0] as u32) < self.dims[0] as u32
            && (c[1] as u32) < self.dims[1] as u32
            && (c[2] as u32) < self.dims[2] as u32
    }
}

impl Tracer for DenseGrid {
    fn name(&self) -> &'static str {
        "dense"
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
            if self.solid(st.cell) {
                let c = st.cell;
                let (dx, dy) = (self.dims[0] as usize, self.dims[1] as usize);
                let m = self.mats[c[0] as usize + dx * (c[1] as usize + dy * c[2] as usize)];
                return Some(Hit {
                    t: st.t,
                    voxel: self.frame.to_world(c),
                    normal: IVec3::from(r.normal(&st)),
                    material: m,
                    level: 0,
                });
            }
            r.step_fine(&mut st);
            if !self.inside(st.cell) {
                return None;
            }
        }
    }

    fn bytes(&self) -> usize {
        self.bits.len() * 8 + self.mats.len()
    }

    fn nodes_or_bricks(&self) -> u64 {
        self.mats.len() as u64
    }
}
