//! The sparse voxel octree: flat ESVO-style 64-bit child descriptors (Laine &
//! Karras 2010 §3.1), traversed with a stack of parents per scale (§4).
//!
//! **Descriptor** (`u64`), low word as in ESVO:
//!
//! | bits  | field |
//! |-------|-------|
//! | 0–7   | leaf mask: child is a leaf (a uniform solid cube) |
//! | 8–15  | valid mask: child is non-empty |
//! | 16    | far flag: the child pointer names a far-pointer slot |
//! | 17–31 | child pointer (15 bits, relative to this descriptor) |
//! | 32–63 | attributes: with ≤ 4 leaf children their materials inline, one byte each by leaf rank; otherwise the relative index of a `u64` attribute word holding up to 8 |
//!
//! ESVO uses the high word for contours; brickworld's voxels are cubes, so it
//! holds materials instead. The descriptors of a node's non-leaf children are
//! stored contiguously in child order; a relative offset that does not fit in
//! 15 bits goes through a far-pointer slot placed right after the block, as
//! in ESVO. Uniform solid cubes of any size collapse into one leaf.
//!
//! Traversal keeps one descriptor index per scale. Skipping an empty child
//! uses the shared exact [`DdaRay::skip`]; the new parent is found from the
//! highest bit in which the old and new cell differ (ESVO's POP), so results
//! match the other tracers bit for bit.

use glam::IVec3;
use indicatif::ProgressBar;
use rayon::prelude::*;

use super::dda::DdaRay;
use super::ray::{Frame, Hit, Ray};
use super::{TraceError, Tracer};
use crate::world::{
    BRICK_SHIFT, BRICK_VOXELS, BrickGrid, BrickPool, OCC_SHIFT, UNIFORM, voxel_index,
};

const LEAF_SHIFT: u32 = 0;
const VALID_SHIFT: u32 = 8;
const FAR_BIT: u64 = 1 << 16;
const PTR_SHIFT: u32 = 17;
const PTR_MAX: usize = (1 << 15) - 1;
const INLINE_LEAVES: u32 = 4;

/// A flat sparse voxel octree.
#[derive(Debug)]
pub struct Svo {
    frame: Frame,
    root_shift: u32,
    nodes: Vec<u64>,
    descriptors: u64,
}

/// A subtree while building: empty, one solid material, or a node.
enum Built {
    Empty,
    Solid(u8),
    Node(NodeBuf),
}

/// A node not yet placed: its masks, leaf materials and body (its children
/// block, far slots, attribute words and the children's bodies). All pointers
/// inside a body are relative, so bodies move freely.
struct NodeBuf {
    valid: u8,
    leaf: u8,
    leaf_mats: [u8; 8],
    body: Vec<u64>,
    descriptors: u64,
}

impl NodeBuf {
    fn leaf_count(&self) -> u32 {
        self.leaf.count_ones()
    }

    fn inline_attr(&self) -> u64 {
        let mut v = 0u64;
        for r in 0..self.leaf_count().min(INLINE_LEAVES) {
            v |= (self.leaf_mats[r as usize] as u64) << (8 * r);
        }
        v
    }

    fn attr_word(&self) -> u64 {
        let mut v = 0u64;
        for r in 0..self.leaf_count() {
            v |= (self.leaf_mats[r as usize] as u64) << (8 * r);
        }
        v
    }
}

fn combine(children: [Built; 8]) -> Built {
    if let Built::Solid(m) = children[0]
        && children
            .iter()
            .all(|c| matches!(c, Built::Solid(x) if *x == m))
    {
        return Built::Solid(m);
    }
    if children.iter().all(|c| matches!(c, Built::Empty)) {
        return Built::Empty;
    }
    let mut valid = 0u8;
    let mut leaf = 0u8;
    let mut leaf_mats = [0u8; 8];
    let mut inner: Vec<NodeBuf> = Vec::new();
    for (k, c) in children.into_iter().enumerate() {
        match c {
            Built::Empty => {}
            Built::Solid(m) => {
                valid |= 1 << k;
                leaf_mats[leaf.count_ones() as usize] = m;
                leaf |= 1 << k;
            }
            Built::Node(n) => {
                valid |= 1 << k;
                inner.push(n);
            }
        }
    }
    let n = inner.len();
    let attrs: Vec<usize> = (0..n)
        .filter(|&i| inner[i].leaf_count() > INLINE_LEAVES)
        .collect();
    let a = attrs.len();
    // Decide which children need far pointers; adding slots can only push
    // offsets further, so iterate until stable (at most n rounds).
    let mut far = vec![false; n];
    loop {
        let m = far.iter().filter(|&&f| f).count();
        let mut start = n + m + a;
        let mut changed = false;
        for (i, child) in inner.iter().enumerate() {
            if !far[i] && start - i > PTR_MAX {
                far[i] = true;
                changed = true;
            }
            start += child.body.len();
        }
        if !changed {
            break;
        }
    }
    let m = far.iter().filter(|&&f| f).count();
    let total: usize = n + m + a + inner.iter().map(|c| c.body.len()).sum::<usize>();
    let mut body = vec![0u64; n + m + a];
    body.reserve(total - body.len());
    let mut descriptors = n as u64;
    let mut start = n + m + a;
    let mut far_slot = n;
    let mut attr_slot = n + m;
    for (i, child) in inner.iter().enumerate() {
        let mut d = ((child.leaf as u64) << LEAF_SHIFT) | ((child.valid as u64) << VALID_SHIFT);
        if far[i] {
            d |= FAR_BIT | (((far_slot - i) as u64) << PTR_SHIFT);
            body[far_slot] = (start - i) as u64;
            far_slot += 1;
        } else if !child.body.is_empty() {
            d |= ((start - i) as u64) << PTR_SHIFT;
        }
        if child.leaf_count() > INLINE_LEAVES {
            body[attr_slot] = child.attr_word();
            d |= ((attr_slot - i) as u64) << 32;
            attr_slot += 1;
        } else {
            d |= child.inline_attr() << 32;
        }
        body[i] = d;
        start += child.body.len();
        descriptors += child.descriptors;
    }
    for child in inner {
        body.extend_from_slice(&child.body);
    }
    Built::Node(NodeBuf {
        valid,
        leaf,
        leaf_mats,
        body,
        descriptors,
    })
}

/// Octree over one dense brick, cube of edge `1 << shift` at `o` (brick-local).
fn build_dense(dense: &[u8; BRICK_VOXELS], shift: u32, o: [i32; 3]) -> Built {
    if shift == 0 {
        let m = dense[voxel_index(o[0], o[1], o[2])];
        return if m == 0 {
            Built::Empty
        } else {
            Built::Solid(m)
        };
    }
    let h = 1 << (shift - 1);
    combine(std::array::from_fn(|k| {
        let k = k as i32;
        build_dense(
            dense,
            shift - 1,
            [
                o[0] + (k & 1) * h,
                o[1] + ((k >> 1) & 1) * h,
                o[2] + ((k >> 2) & 1) * h,
            ],
        )
    }))
}

struct Source<'a> {
    grid: &'a BrickGrid,
    pool: &'a BrickPool,
    dims_vox: IVec3,
    progress: &'a ProgressBar,
}

impl Source<'_> {
    fn build(&self, shift: u32, o: IVec3) -> Built {
        if o.cmpge(self.dims_vox).any() {
            return Built::Empty;
        }
        let occ_shift = (OCC_SHIFT + BRICK_SHIFT) as u32;
        if shift == occ_shift {
            self.progress.inc(1);
            if !self.grid.occupied(o >> occ_shift as i32) {
                return Built::Empty;
            }
        }
        if shift == BRICK_SHIFT as u32 {
            let p = self.grid.pointer(o >> BRICK_SHIFT);
            if p == 0 {
                return Built::Empty;
            }
            if p & UNIFORM != 0 {
                return Built::Solid(p as u8);
            }
            let mut dense = [0u8; BRICK_VOXELS];
            if let Some(b) = self.pool.slot(p - 1) {
                b.to_dense(&mut dense);
            }
            return build_dense(&dense, BRICK_SHIFT as u32, [0; 3]);
        }
        let h = 1i32 << (shift - 1);
        let child = |k: i32| {
            self.build(
                shift - 1,
                o + IVec3::new(k & 1, (k >> 1) & 1, (k >> 2) & 1) * h,
            )
        };
        let children: Vec<Built> = if shift >= 8 {
            (0..8).into_par_iter().map(child).collect()
        } else {
            (0..8).map(child).collect()
        };
        let arr: [Built; 8] = children.try_into().unwrap_or_else(|_| unreachable!());
        combine(arr)
    }
}

impl Svo {
    /// Build the octree over the region of `grid` (mixed bricks from `pool`).
    pub fn build(
        grid: &BrickGrid,
        pool: &BrickPool,
        progress: &ProgressBar,
    ) -> Result<Self, TraceError> {
        let dims_vox = grid.dims() << BRICK_SHIFT;
        let edge = dims_vox.max_element().max(8) as u32;
        let root_shift = edge.next_power_of_two().trailing_zeros();
        let occ = grid.dims() >> OCC_SHIFT;
        progress.set_length((occ.x as u64) * (occ.y as u64) * (occ.z as u64));
        let src = Source {
            grid,
            pool,
            dims_vox,
            progress,
        };
        let built = src.build(root_shift, IVec3::ZERO);
        let root = match built {
            Built::Empty => return Ok(Svo::from_root(grid, root_shift, vec![0], 1)),
            Built::Solid(m) => {
                let leaves: [Built; 8] = std::array::from_fn(|_| Built::Solid(m));
                // A fully solid root: eight leaf children under one descriptor.
                match combine_no_collapse(leaves) {
                    Built::Node(n) => n,
                    _ => unreachable!(),
                }
            }
            Built::Node(n) => n,
        };
        let mut nodes = Vec::with_capacity(2 + root.body.len());
        let mut d = ((root.leaf as u64) << LEAF_SHIFT) | ((root.valid as u64) << VALID_SHIFT);
        let body_start = if root.leaf_count() > INLINE_LEAVES {
            2
        } else {
            1
        };
        if !root.body.is_empty() {
            d |= (body_start as u64) << PTR_SHIFT;
        }
        if root.leaf_count() > INLINE_LEAVES {
            d |= 1u64 << 32;
            nodes.push(d);
            nodes.push(root.attr_word());
        } else {
            d |= root.inline_attr() << 32;
            nodes.push(d);
        }
        nodes.extend_from_slice(&root.body);
        Ok(Svo::from_root(
            grid,
            root_shift,
            nodes,
            root.descriptors + 1,
        ))
    }

    fn from_root(grid: &BrickGrid, root_shift: u32, nodes: Vec<u64>, descriptors: u64) -> Self {
        Svo {
            frame: Frame {
                anchor: grid.origin() << BRICK_SHIFT,
            },
            root_shift,
            nodes,
            descriptors,
        }
    }

    #[inline(always)]
    fn children_block(&self, idx: usize, d: u64) -> usize {
        let ptr = ((d >> PTR_SHIFT) & PTR_MAX as u64) as usize;
        if d & FAR_BIT != 0 {
            idx + self.nodes[idx + ptr] as usize
        } else {
            idx + ptr
        }
    }

    #[inline(always)]
    fn leaf_material(&self, idx: usize, d: u64, k: u32) -> u8 {
        let leaf = (d >> LEAF_SHIFT) as u8;
        let rank = (leaf & ((1u16 << k) - 1) as u8).count_ones();
        if leaf.count_ones() <= INLINE_LEAVES {
            (d >> (32 + 8 * rank)) as u8
        } else {
            (self.nodes[idx + (d >> 32) as usize] >> (8 * rank)) as u8
        }
    }

    /// Number of descriptors that reach their children through a far pointer.
    pub fn far_pointers(&self) -> usize {
        // Walk the tree from the root so that only descriptors are inspected
        // (far slots and attribute words are not descriptors).
        let mut count = 0;
        let mut stack = vec![0usize];
        while let Some(idx) = stack.pop() {
            let d = self.nodes[idx];
            count += (d & FAR_BIT != 0) as usize;
            let inner = ((d >> VALID_SHIFT) as u8) & !((d >> LEAF_SHIFT) as u8);
            if inner != 0 {
                let block = self.children_block(idx, d);
                stack.extend((0..inner.count_ones() as usize).map(|i| block + i));
            }
        }
        count
    }
}

/// Like [`combine`] but never collapses: used only for a fully solid root.
fn combine_no_collapse(children: [Built; 8]) -> Built {
    let mut leaf_mats = [0u8; 8];
    for (k, c) in children.iter().enumerate() {
        if let Built::Solid(m) = c {
            leaf_mats[k] = *m;
        }
    }
    Built::Node(NodeBuf {
        valid: 0xff,
        leaf: 0xff,
        leaf_mats,
        body: Vec::new(),
        descriptors: 0,
    })
}

impl Tracer for Svo {
    fn name(&self) -> &'static str {
        "svo"
    }

    fn frame(&self) -> Frame {
        self.frame
    }

    fn trace(&self, ray: &Ray, t_max: f32) -> Option<Hit> {
        let r = DdaRay::new(ray)?;
        let edge = 1i32 << self.root_shift;
        let mut st = r.enter([0; 3], [edge; 3])?;
        let mut stack = [0u32; 26];
        let mut s = self.root_shift;
        stack[s as usize] = 0;
        loop {
            if st.t > t_max {
                return None;
            }
            let idx = stack[s as usize] as usize;
            let d = self.nodes[idx];
            let cs = s - 1;
            let c = st.cell;
            let k =
                (((c[0] >> cs) & 1) | (((c[1] >> cs) & 1) << 1) | (((c[2] >> cs) & 1) << 2)) as u32;
            let valid = (d >> VALID_SHIFT) as u8;
            let leaf = (d >> LEAF_SHIFT) as u8;
            if valid & (1 << k) == 0 {
                r.skip(&mut st, cs);
                let n = st.cell;
                if (n[0] as u32 | n[1] as u32 | n[2] as u32) >= edge as u32 {
                    return None;
                }
                let diff = (c[0] ^ n[0]) | (c[1] ^ n[1]) | (c[2] ^ n[2]);
                s = 32 - (diff as u32).leading_zeros();
                continue;
            }
            if leaf & (1 << k) != 0 {
                return Some(Hit {
                    t: st.t,
                    voxel: self.frame.to_world(c),
                    normal: IVec3::from(r.normal(&st)),
                    material: self.leaf_material(idx, d, k),
                    level: 0,
                });
            }
            let inner = valid & !leaf;
            let child = self.children_block(idx, d)
                + (inner & ((1u16 << k) - 1) as u8).count_ones() as usize;
            s = cs;
            stack[s as usize] = child as u32;
        }
    }

    fn bytes(&self) -> usize {
        self.nodes.len() * 8
    }

    fn nodes_or_bricks(&self) -> u64 {
        self.descriptors
    }
}
