//! The brickmap tracer: a stackless three-level DDA, occupancy layer (32³
//! voxels) → brick grid (8³) → brick mask (1³), after van Wingerden §3.3–3.4.
//!
//! No stack and no restart: the level is re-derived from the current cell.
//! Through empty space the walk is a coarse DDA over occupancy cells (32³
//! voxels) or bricks (8³), whose next crossing is a function of the coarse
//! cell alone, computed with the shared exact crossing formula; the exact
//! voxel state is restored with [`DdaRay::advance_to`] only when the walk
//! descends into a non-empty cell. Inside a brick the walk steps voxel by
//! voxel against the 512-bit mask and touches material data only at the hit.

use glam::IVec3;

use super::dda::{DdaRay, DdaState};
use super::lod::Footprint;
use super::ray::{Frame, Hit, Ray};
use super::{FaceSums, Tracer};
use crate::world::{
    BRICK_SHIFT, BrickGrid, BrickPool, OCC_SHIFT, Palette, TOP_LEVEL, UNIFORM, block_solid,
    voxel_index,
};

/// A tracer over a [`BrickGrid`] and the pool its pointers index.
#[derive(Clone, Copy, Debug)]
pub struct BrickmapTracer<'w> {
    pub(super) grid: &'w BrickGrid,
    pub(super) pool: &'w BrickPool,
    pub(super) frame: Frame,
    pub(super) dims: [i32; 3],
}

const OCC_VOXEL_SHIFT: i32 = OCC_SHIFT + BRICK_SHIFT;

/// The highest bit in which two cells' coordinates differ (0 if only the
/// lowest, or none): the coarsest level whose cell a step from `a` to `b`
/// entered.
#[inline(always)]
fn highest_change(a: [i32; 3], b: [i32; 3]) -> u32 {
    let x = (a[0] ^ b[0]) | (a[1] ^ b[1]) | (a[2] ^ b[2]);
    31u32.saturating_sub((x as u32).leading_zeros())
}

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
    pub(super) fn inside(&self, c: [i32; 3]) -> bool {
        (c[0] as u32) < self.dims[0] as u32
            && (c[1] as u32) < self.dims[1] as u32
            && (c[2] as u32) < self.dims[2] as u32
    }

    #[inline(always)]
    fn inside_occ(&self, o: [i32; 3]) -> bool {
        (o[0] as u32) < (self.dims[0] >> OCC_VOXEL_SHIFT) as u32
            && (o[1] as u32) < (self.dims[1] >> OCC_VOXEL_SHIFT) as u32
            && (o[2] as u32) < (self.dims[2] >> OCC_VOXEL_SHIFT) as u32
    }

    /// The exact walk from distance `t_start` (0: the eye), which must be
    /// a distance before which the ray meets nothing (a beam start): the
    /// exact state there is restored, so the answer is the walk's from 0.
    pub fn trace_exact_from(&self, ray: &Ray, t_start: f32, t_max: f32) -> Option<Hit> {
        let (r, st) = self.start(ray, t_start)?;
        self.walk_exact(&r, st, t_max)
    }

    /// The exact walk of `r` from the exact state `st` up to `t_max`.
    #[inline(always)]
    pub(super) fn walk_exact(&self, r: &DdaRay, st: DdaState, t_max: f32) -> Option<Hit> {
        self.walk::<false>(r, st, t_max, &Footprint::EXACT)
    }

    /// The walk of `r` from the exact state `st` up to `t_max`: exact, or
    /// with level of detail (`LOD`), stopping at the first cell that is
    /// solid at the level its footprint allows (see [`super::lod`]).
    ///
    /// **Level of detail in the exact walk.** Each step of the walk enters
    /// new cells at every level up to some `climbed` (the highest bit in
    /// which the cell coordinates changed). The cells the footprint may
    /// take whole at that time are those up to `allowed`; so the level walk
    /// of [`super::lod`] checks the cell of level `min(climbed, allowed)`
    /// there, and hits it if it is solid (any solid: a solid cell's
    /// ancestors are solid too). This walk does exactly that at each of its
    /// steps, while it skips empty space and steps voxels as the exact walk
    /// does: walking an empty coarse cell voxel by voxel finds nothing, as
    /// skipping it does. So it reports what the level walk reports, at
    /// about the exact walk's cost (tests hold the two walks to each other).
    #[inline(always)]
    pub(super) fn walk<const LOD: bool>(
        &self,
        r: &DdaRay,
        mut st: DdaState,
        t_max: f32,
        fp: &Footprint,
    ) -> Option<Hit> {
        // `st` is the exact voxel state whenever a cell's content is read.
        // Across empty space only the coarse cell is stepped: its next
        // crossing depends on the coarse cell alone, so no voxel state is
        // kept there, and `advance_to` restores it exactly on descent.
        // With LOD, `climbed`: every level whose cell was entered at `st.t`
        // (all of them at the start).
        let mut climbed = TOP_LEVEL;
        'occupancy: loop {
            if st.t > t_max {
                return None;
            }
            let mut oc = st.cell.map(|v| v >> OCC_VOXEL_SHIFT);
            if !self.grid.occupied(IVec3::from(oc)) {
                let shift = OCC_VOXEL_SHIFT as u32;
                let mut ot = r.coarse_tmax(oc, shift);
                loop {
                    let t = r.coarse_step(&mut oc, &mut ot, shift);
                    if t > t_max {
                        return None;
                    }
                    if !self.inside_occ(oc) {
                        return None;
                    }
                    if self.grid.occupied(IVec3::from(oc)) {
                        r.advance_to(&mut st, t);
                        climbed = TOP_LEVEL;
                        break;
                    }
                }
            }
            if LOD
                && climbed >= TOP_LEVEL
                && fp.allowed(st.t) >= TOP_LEVEL
                && let Some(hit) = self.coarse_hit(r, &st, TOP_LEVEL)
            {
                return Some(hit);
            }
            let mut bc = st.cell.map(|v| v >> BRICK_SHIFT);
            loop {
                let p = self.grid.pointer(IVec3::from(bc));
                // Bricks and 16³ cells the footprint takes whole.
                if LOD && st.t >= fp.at[2] && climbed >= 3 {
                    let a = fp.allowed(st.t).min(climbed);
                    if a == 4
                        && let Some(hit) = self.coarse_hit(r, &st, 4)
                    {
                        return Some(hit);
                    }
                    if a == 3 && p != 0 {
                        return Some(self.lod_hit(r, &st, 3, p));
                    }
                }
                if p == 0 {
                    let shift = BRICK_SHIFT as u32;
                    let mut bt = r.coarse_tmax(bc, shift);
                    loop {
                        let prev = bc;
                        let t = r.coarse_step(&mut bc, &mut bt, shift);
                        if t > t_max {
                            return None;
                        }
                        if bc.map(|v| v >> OCC_SHIFT) != oc {
                            // Left the occupancy cell: resume one level up.
                            r.advance_to(&mut st, t);
                            if !self.inside(st.cell) {
                                return None;
                            }
                            climbed = TOP_LEVEL;
                            continue 'occupancy;
                        }
                        // Only where a level above voxels is allowed does it
                        // matter which levels this step entered.
                        let far = LOD && t >= fp.at[2];
                        let entered = if far { 3 + highest_change(prev, bc) } else { 3 };
                        // A 16³ cell entered here: the state is restored only
                        // if it is solid (its cell is the brick's, halved).
                        if far
                            && entered >= 4
                            && t >= fp.at[3]
                            && self.coarse_material(4, bc.map(|v| v >> 1)) != 0
                        {
                            let mut at = st;
                            r.advance_to(&mut at, t);
                            return self.coarse_hit(r, &at, 4);
                        }
                        if self.grid.pointer(IVec3::from(bc)) != 0 {
                            r.advance_to(&mut st, t);
                            climbed = entered;
                            break;
                        }
                    }
                    continue;
                }
                if p & UNIFORM != 0 {
                    if LOD {
                        let a = fp.allowed(st.t).min(climbed);
                        return Some(self.lod_hit(r, &st, a, p));
                    }
                    return Some(self.hit(r, &st, p as u8));
                }
                let brick = self.pool.slot(p - 1)?;
                let mask = brick.mask();
                // The cell before the last voxel step; at the brick's first
                // voxel, `climbed` says what was entered.
                let mut prev: Option<[i32; 3]> = None;
                loop {
                    let l = st.cell.map(|v| v & 7);
                    if LOD && st.t >= fp.at[0] {
                        // Levels 0 to 2 come from the brick's own mask.
                        let entered = prev.map_or(climbed, |p| highest_change(p, st.cell));
                        let a = fp.allowed(st.t).min(entered);
                        if block_solid(mask, a, l) {
                            return Some(self.lod_hit(r, &st, a, p));
                        }
                    } else {
                        let i = voxel_index(l[0], l[1], l[2]);
                        if (mask[i >> 6] >> (i & 63)) & 1 != 0 {
                            return Some(self.hit(r, &st, brick.material_index(i)));
                        }
                    }
                    let before = st.cell;
                    r.step_fine(&mut st);
                    if st.t > t_max {
                        return None;
                    }
                    if st.cell.map(|v| v >> BRICK_SHIFT) != bc {
                        if LOD {
                            climbed = highest_change(before, st.cell);
                        }
                        break;
                    }
                    if LOD {
                        prev = Some(before);
                    }
                }
                if !self.inside(st.cell) {
                    return None;
                }
                if st.cell.map(|v| v >> OCC_VOXEL_SHIFT) != oc {
                    continue 'occupancy;
                }
                bc = st.cell.map(|v| v >> BRICK_SHIFT);
            }
        }
    }

    /// The ray's DDA and its exact state on entering the grid, or at
    /// `t_start` if that is later (a beam start); `None` if it misses.
    pub(super) fn start(&self, ray: &Ray, t_start: f32) -> Option<(DdaRay, DdaState)> {
        let r = DdaRay::new(ray)?;
        let mut st = r.enter([0; 3], self.dims)?;
        if t_start > st.t {
            r.advance_to(&mut st, t_start);
            if !self.inside(st.cell) {
                return None;
            }
        }
        Some((r, st))
    }

    /// The grid pointer of brick `b` (local bricks), 0 outside the grid.
    fn brick_pointer(&self, b: IVec3) -> u32 {
        if self.inside((b << BRICK_SHIFT).to_array()) {
            self.grid.pointer(b)
        } else {
            0
        }
    }

    fn hit(&self, r: &DdaRay, st: &DdaState, material: u8) -> Hit {
        Hit {
            t: st.t,
            voxel: self.frame.to_world(st.cell),
            normal: IVec3::from(r.normal(st)),
            material,
            level: 0,
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
        self.trace_exact_from(ray, 0.0, t_max)
    }

    fn trace_lod(&self, ray: &Ray, t_max: f32, k: f32) -> Option<Hit> {
        Tracer::trace_from(self, ray, 0.0, t_max, k)
    }

    fn trace_from(&self, ray: &Ray, t_start: f32, t_max: f32, k: f32) -> Option<Hit> {
        // Exact tracing keeps its specialised walk (same answers, faster).
        if k == 0.0 {
            self.trace_exact_from(ray, t_start, t_max)
        } else {
            self.trace_lod_from(ray, t_start, t_max, k)
        }
    }

    fn trace_skipped(&self, ray: &Ray, t_max: f32, k: f32, skipped: f32) -> Option<Hit> {
        if k == 0.0 {
            self.trace_exact_from(ray, 0.0, t_max)
        } else {
            let (r, st) = self.start(ray, 0.0)?;
            self.walk::<true>(&r, st, t_max, &Footprint::skipped(k, skipped))
        }
    }

    fn beam_start(&self, centre: &Ray, spread: f32, k: f32) -> f32 {
        BrickmapTracer::beam_start(self, centre, spread, k)
    }

    fn coarse_faces(&self, hit: &Hit, facing: u8, palette: &Palette) -> Option<FaceSums> {
        use crate::world::{EMPTY_MASK, FACE_DIRS, FULL_MASK, for_each_exposed};
        if hit.level == 0 || hit.level > 2 {
            return None;
        }
        let c = (hit.voxel - self.frame.anchor).to_array();
        let b = IVec3::from(c.map(|v| v >> BRICK_SHIFT));
        // A uniform brick's cells are full: its faces are the brick's,
        // shaded as a voxel's are.
        let p = self.brick_pointer(b);
        if p == 0 || p & UNIFORM != 0 {
            return None;
        }
        let r = self.pool.slot(p - 1)?;
        let level = hit.level as u32;
        let l = c.map(|v| v & 7);
        let lo = l.map(|v| v & !((1 << level) - 1));
        let hi = lo.map(|v| v + (1 << level) - 1);
        // A neighbouring brick is read only where its faces can show: the
        // direction faces the viewer and the cell touches that side.
        let nb: [&[u64; 8]; 6] = std::array::from_fn(|d| {
            let dir = FACE_DIRS[d];
            let touches = (0..3).all(|a| match dir[a] {
                1 => hi[a] == 7,
                -1 => lo[a] == 0,
                _ => true,
            });
            if facing & (1 << d) == 0 || !touches {
                return &EMPTY_MASK;
            }
            match self.brick_pointer(b + IVec3::from(dir)) {
                0 => &EMPTY_MASK,
                q if q & UNIFORM != 0 => &FULL_MASK,
                q => self.pool.slot(q - 1).map_or(&EMPTY_MASK, |n| n.mask()),
            }
        });
        let mut sums = FaceSums::default();
        for_each_exposed(r.mask(), nb, level, l, |z, d, bits| {
            if facing & (1 << d) != 0 {
                sums.faces[d] += bits.count_ones();
                let rgb = &mut sums.rgb[d];
                r.for_each_material(z, bits, |m| {
                    let c = palette.rgb(m);
                    for k in 0..3 {
                        rgb[k] += c[k] as u32;
                    }
                });
            }
        });
        Some(sums)
    }

    fn solid_local(&self, c: [i32; 3]) -> bool {
        if !self.inside(c) {
            return false;
        }
        let p = self.grid.pointer(IVec3::from(c.map(|v| v >> BRICK_SHIFT)));
        match p {
            0 => false,
            p if p & UNIFORM != 0 => true,
            p => self
                .pool
                .slot(p - 1)
                .is_some_and(|b| crate::world::block_solid(b.mask(), 0, c.map(|v| v & 7))),
        }
    }

    fn bytes(&self) -> usize {
        self.grid.bytes() + self.pool.bytes()
    }

    fn nodes_or_bricks(&self) -> u64 {
        self.grid.non_empty() as u64
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::world::{BrickStore, FACE_DIRS};

    /// `coarse_faces` counts and colours each exposed voxel face of a 2³
    /// or 4³ cell as a voxel-by-voxel count does, for every direction
    /// subset: across brick sides (mixed, uniform and empty neighbours,
    /// and the grid's edge), with neighbour bricks read only where the
    /// cell touches them.
    #[test]
    fn coarse_faces_count_what_a_voxel_by_voxel_count_counts() {
        let mut s = BrickStore::new(Palette::grey_ramp());
        let mut x = 0x2545_f491u32;
        for _ in 0..2500 {
            x ^= x << 13;
            x ^= x >> 17;
            x ^= x << 5;
            let p = IVec3::new((x % 24) as i32, (x >> 8) as i32 % 24, (x >> 16) as i32 % 16);
            s.set_voxel(p, 1 + (x >> 24) as u8 % 250);
        }
        // A uniform brick beside mixed ones.
        s.fill_box(IVec3::new(24, 8, 0), IVec3::new(31, 15, 7), 200);
        let (lo, hi) = s.brick_bounds().unwrap();
        let g = BrickGrid::build(&s, lo, hi - lo + IVec3::ONE).unwrap();
        let t = BrickmapTracer::new(&g, s.pool());
        let palette = Palette::grey_ramp();
        let solid = |p: IVec3| s.voxel(p) != 0;
        let mut checked = 0;
        for level in 1..=2u8 {
            let e = 1i32 << level;
            for cz in (0..16).step_by(e as usize) {
                for cy in (0..24).step_by(e as usize) {
                    for cx in (0..32).step_by(e as usize) {
                        let corner = IVec3::new(cx, cy, cz);
                        let hit = Hit {
                            t: 0.0,
                            voxel: corner + IVec3::new(1, 0, 1) * (e - 1),
                            normal: IVec3::ZERO,
                            material: 1,
                            level,
                        };
                        let mixed = matches!(s.cell(corner >> 3), crate::world::Cell::Mixed(_));
                        for facing in [0b11_1111u8, 0b01_0101, 0b10_1010, 0b00_0100] {
                            let got = t.coarse_faces(&hit, facing, &palette);
                            if !mixed {
                                assert_eq!(got, None, "{corner} is not in a mixed brick");
                                continue;
                            }
                            let mut want = FaceSums::default();
                            for d in (0..6).filter(|d| facing & (1 << d) != 0) {
                                for v in 0..e * e * e {
                                    let p = corner + IVec3::new(v % e, v / e % e, v / (e * e));
                                    if solid(p) && !solid(p + IVec3::from(FACE_DIRS[d])) {
                                        want.faces[d] += 1;
                                        let c = palette.rgb(s.voxel(p));
                                        for k in 0..3 {
                                            want.rgb[d][k] += c[k] as u32;
                                        }
                                    }
                                }
                            }
                            assert_eq!(
                                got,
                                Some(want),
                                "cell {corner}, level {level}, {facing:06b}"
                            );
                            checked += want.faces.iter().sum::<u32>();
                        }
                    }
                }
            }
        }
        assert!(checked > 2000, "too few faces checked: {checked}");
    }
}
