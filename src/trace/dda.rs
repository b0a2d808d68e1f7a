//! The exact hierarchical DDA that every tracer shares.
//!
//! **The canonical answer.** A ray visits the cells `floor(o + t·d)` for
//! `t ≥ 0`: its origin cell, then every cell in which it spends a positive
//! length. The crossing time of the plane `k` on axis `a` is always computed
//! by one formula, [`DdaRay::crossing_into`]: `(k − o[a]) · (1 / d[a])` in
//! `f32`. When several axes cross at the same time (the ray passes exactly
//! through an edge or corner) they step *together*, so a ray that only touches
//! a voxel at a corner does not hit it. Axes whose direction component is 0
//! (or −0.0, or so small that its reciprocal is not finite) are switched off
//! and never step: no `inf · 0 = NaN` can arise.
//!
//! **Why it is exact across structures.** Crossing times are monotone along
//! the ray on each axis, so the state after "every crossing with time ≤ T"
//! is a pure function of `T`. A coarse skip over an empty aligned cube of
//! edge 2ˢ computes the cube's exit time T by the same formula and then the
//! per-axis cell after T ([`DdaRay::cell_after`]). That is bit-for-bit the
//! state the voxel-by-voxel walk would reach, so the dense grid, the octree
//! and the brickmap report the same voxel, face and `t` for every ray. No
//! face-bias epsilon is used anywhere.

use super::ray::Ray;

/// Per-ray constants of the DDA (local frame).
#[derive(Clone, Copy, Debug)]
pub struct DdaRay {
    /// The true origin.
    o: [f32; 3],
    /// Origin used in crossing times: `-inf` on switched-off axes, so that
    /// `(k − o) · inv = +inf · +inf = +inf` there, branch-free and NaN-free.
    o_cross: [f32; 3],
    d: [f32; 3],
    inv: [f32; 3],
    step: [i32; 3],
    /// 0 when stepping up (enter cell c through plane c), 1 when stepping down
    /// (through plane c + 1).
    plane: [i32; 3],
    active: [bool; 3],
}

/// `floor(x)` as an integer without a libm call (baseline x86-64 has no
/// SSE4.1 rounding instruction); exact for |x| < 2³¹.
#[inline(always)]
pub fn floor_i32(x: f32) -> i32 {
    let i = x as i32;
    if (i as f32) > x { i - 1 } else { i }
}

/// The least of three crossing times, which are never NaN (a switched-off
/// axis's is `+inf`): one `minss` each, where `f32::min` adds the code
/// that IEEE's NaN rules need. On ties of `+0` and `−0`, which compare equal,
/// the first wins.
#[inline(always)]
pub fn min3(t: [f32; 3]) -> f32 {
    let a = if t[1] < t[0] { t[1] } else { t[0] };
    if t[2] < a { t[2] } else { a }
}

/// The walk's state: the current cell and the next crossing on each axis.
#[derive(Clone, Copy, Debug)]
pub struct DdaState {
    /// Current cell (local voxel coordinates).
    pub cell: [i32; 3],
    /// Time of the next plane crossing on each axis (`+inf` when switched off).
    pub tmax: [f32; 3],
    /// Time at which the current cell was entered (0 for the origin cell).
    pub t: f32,
    /// Axes that stepped at `t` (bit a), 0 for the origin cell.
    pub axes: u8,
}

/// Largest local coordinate magnitude the DDA accepts (f32 integers stay exact).
pub const MAX_LOCAL: f32 = 16_777_216.0;

impl DdaRay {
    /// Prepare a ray, or `None` if its origin or direction is unusable
    /// (non-finite, zero direction, or an origin beyond [`MAX_LOCAL`]).
    pub fn new(ray: &Ray) -> Option<Self> {
        let o = ray.origin.to_array();
        let d = ray.dir.to_array();
        if o.iter().chain(d.iter()).any(|v| !v.is_finite()) || o.iter().any(|v| v.abs() > MAX_LOCAL)
        {
            return None;
        }
        let mut inv = [f32::INFINITY; 3];
        let mut step = [0; 3];
        let mut plane = [0; 3];
        let mut active = [false; 3];
        let mut o_cross = [f32::NEG_INFINITY; 3];
        for a in 0..3 {
            let r = 1.0 / d[a];
            if d[a] != 0.0 && r.is_finite() {
                inv[a] = r;
                step[a] = if d[a] > 0.0 { 1 } else { -1 };
                plane[a] = (d[a] < 0.0) as i32;
                active[a] = true;
                o_cross[a] = o[a];
            }
        }
        if !active.iter().any(|&x| x) {
            return None;
        }
        Some(DdaRay {
            o,
            o_cross,
            d,
            inv,
            step,
            plane,
            active,
        })
    }

    /// Step direction per axis (−1, 0 or +1).
    #[inline(always)]
    pub fn step(&self) -> [i32; 3] {
        self.step
    }

    /// The first voxel the ray enters on axis `a` when it leaves the aligned
    /// coarse cell `c` of edge `1 << shift` (coarse DDAs step with it:
    /// `crossing_into(a, coarse_exit(a, c, shift))` is the exact time).
    #[inline(always)]
    pub fn coarse_exit(&self, a: usize, c: i32, shift: u32) -> i32 {
        if self.step[a] > 0 {
            (c + 1) << shift
        } else {
            (c << shift) - 1
        }
    }

    /// Next crossing time on each axis out of coarse cell `c` (edge `1 << shift`).
    #[inline(always)]
    pub fn coarse_tmax(&self, c: [i32; 3], shift: u32) -> [f32; 3] {
        std::array::from_fn(|a| self.crossing_into(a, self.coarse_exit(a, c[a], shift)))
    }

    /// One step of a coarse DDA: every axis whose crossing is next steps
    /// (ties together); returns the crossing time.
    #[inline(always)]
    pub fn coarse_step(&self, c: &mut [i32; 3], ct: &mut [f32; 3], shift: u32) -> f32 {
        let t = min3(*ct);
        for a in 0..3 {
            if ct[a] == t {
                c[a] += self.step[a];
                ct[a] = self.crossing_into(a, self.coarse_exit(a, c[a], shift));
            }
        }
        t
    }

    /// Time at which the ray enters cell `c` along axis `a` (the crossing of
    /// the plane between `c − step` and `c`). `+inf` for a switched-off axis.
    #[inline(always)]
    pub fn crossing_into(&self, a: usize, c: i32) -> f32 {
        ((c + self.plane[a]) as f32 - self.o_cross[a]) * self.inv[a]
    }

    /// The cell on axis `a` after every crossing with time ≤ `t`, walking
    /// forward from `start`.
    #[inline]
    pub fn cell_after(&self, a: usize, t: f32, start: i32) -> i32 {
        self.axis_after(a, t, start).0
    }

    /// [`cell_after`](Self::cell_after) plus the next crossing time on that
    /// axis and whether the axis stepped exactly at `t`.
    #[inline(always)]
    fn axis_after(&self, a: usize, t: f32, start: i32) -> (i32, f32, bool) {
        if !self.active[a] {
            return (start, f32::INFINITY, false);
        }
        let s = self.step[a];
        let est = floor_i32((self.o[a] + t * self.d[a]).clamp(-MAX_LOCAL * 2.0, MAX_LOCAL * 2.0));
        let mut c = if s > 0 {
            est.max(start)
        } else {
            est.min(start)
        };
        let mut next = self.crossing_into(a, c + s);
        let mut guard = 0;
        while next <= t && guard < 1 << 12 {
            c += s;
            next = self.crossing_into(a, c + s);
            guard += 1;
        }
        let mut at = false;
        while c != start && guard < 1 << 13 {
            let cur = self.crossing_into(a, c);
            if cur > t {
                next = cur;
                c -= s;
                guard += 1;
            } else {
                at = cur == t;
                break;
            }
        }
        (c, next, at)
    }

    /// Move `st` to the state after every crossing with time ≤ `t`, walking
    /// forward from its current cell; updated in place (no struct copy).
    #[inline(always)]
    pub fn advance_to(&self, st: &mut DdaState, t: f32) {
        let mut axes = 0u8;
        for a in 0..3 {
            // An axis whose next crossing is later than `t` stays put: the
            // common case, and free. (`tmax` is exact for the current cell.)
            if st.tmax[a] > t {
                continue;
            }
            let (c, next, at) = self.axis_after(a, t, st.cell[a]);
            st.cell[a] = c;
            st.tmax[a] = next;
            axes |= (at as u8) << a;
        }
        st.t = t;
        st.axes = axes;
    }

    /// Start the walk in the box `[lo, hi)` (local voxels): the origin cell if
    /// it is inside, else the first cell inside along the ray. `None` if the
    /// ray never spends positive length inside the box.
    #[inline]
    pub fn enter(&self, lo: [i32; 3], hi: [i32; 3]) -> Option<DdaState> {
        let start = [
            floor_i32(self.o[0]),
            floor_i32(self.o[1]),
            floor_i32(self.o[2]),
        ];
        let mut t_enter = 0.0f32;
        let mut outside = false;
        for a in 0..3 {
            if start[a] < lo[a] || start[a] >= hi[a] {
                outside = true;
                let first = if start[a] < lo[a] { lo[a] } else { hi[a] - 1 };
                let moving_in = (start[a] < lo[a] && self.step[a] > 0)
                    || (start[a] >= hi[a] && self.step[a] < 0);
                if !moving_in {
                    return None;
                }
                t_enter = t_enter.max(self.crossing_into(a, first));
            }
        }
        if !outside {
            let mut tmax = [0.0; 3];
            for (a, tm) in tmax.iter_mut().enumerate() {
                *tm = self.crossing_into(a, start[a] + self.step[a]);
            }
            return Some(DdaState {
                cell: start,
                tmax,
                t: 0.0,
                axes: 0,
            });
        }
        let mut st = DdaState {
            cell: start,
            tmax: [0.0; 3],
            t: 0.0,
            axes: 0,
        };
        for a in 0..3 {
            st.tmax[a] = self.crossing_into(a, start[a] + self.step[a]);
        }
        self.advance_to(&mut st, t_enter);
        for a in 0..3 {
            if st.cell[a] < lo[a] || st.cell[a] >= hi[a] {
                return None;
            }
        }
        Some(st)
    }

    /// Advance one cell (every axis whose crossing is next steps together).
    #[inline(always)]
    pub fn step_fine(&self, st: &mut DdaState) {
        let t = min3(st.tmax);
        let mut axes = 0u8;
        for a in 0..3 {
            if st.tmax[a] == t {
                st.cell[a] += self.step[a];
                st.tmax[a] = self.crossing_into(a, st.cell[a] + self.step[a]);
                axes |= 1 << a;
            }
        }
        st.t = t;
        st.axes = axes;
    }

    /// Skip the empty aligned cube of edge `1 << shift` holding the current
    /// cell: the state becomes exactly what [`step_fine`](Self::step_fine)
    /// would reach on leaving the cube.
    #[inline(always)]
    pub fn skip(&self, st: &mut DdaState, shift: u32) {
        if shift == 0 {
            return self.step_fine(st);
        }
        let size = 1i32 << shift;
        let mut t = f32::INFINITY;
        for a in 0..3 {
            let base = (st.cell[a] >> shift) << shift;
            let exit = if self.step[a] > 0 {
                base + size
            } else {
                base - 1
            };
            t = t.min(self.crossing_into(a, exit));
        }
        self.advance_to(st, t);
    }

    /// Outward face normal for a hit on the cell entered at `st` (the lowest
    /// axis that stepped into it); zero for the origin cell.
    #[inline]
    pub fn normal(&self, st: &DdaState) -> [i32; 3] {
        let mut n = [0; 3];
        if st.axes != 0 {
            let a = st.axes.trailing_zeros() as usize;
            n[a] = -self.step[a];
        }
        n
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use glam::Vec3;

    fn ray(o: [f32; 3], d: [f32; 3]) -> DdaRay {
        DdaRay::new(&Ray::new(Vec3::from(o), Vec3::from(d))).unwrap()
    }

    #[test]
    fn zero_and_negative_zero_components_never_step() {
        let r = ray([0.5, 1.0, 0.5], [1.0, -0.0, 0.0]);
        let mut st = r.enter([0; 3], [8; 3]).unwrap();
        for _ in 0..7 {
            r.step_fine(&mut st);
            assert_eq!(st.cell[1], 1);
            assert_eq!(st.cell[2], 0);
        }
        assert_eq!(st.cell[0], 7);
    }

    #[test]
    fn skip_equals_the_fine_walk() {
        let dirs = [
            [0.3f32, -0.7, 0.2],
            [1.0, 1.0, 1.0],
            [-1.0, 0.0, 0.5],
            [1e-7, 1.0, -1e-7],
        ];
        for d in dirs {
            let r = ray([3.25, 9.5, 4.0], d);
            let start = r.enter([-64; 3], [64; 3]).unwrap();
            for shift in 1..5 {
                let mut coarse = start;
                r.skip(&mut coarse, shift);
                let mut fine = start;
                let base: Vec<i32> = (0..3).map(|a| start.cell[a] >> shift).collect();
                while (0..3).all(|a| fine.cell[a] >> shift == base[a]) {
                    r.step_fine(&mut fine);
                }
                assert_eq!(coarse.cell, fine.cell, "dir {d:?} shift {shift}");
                assert_eq!(coarse.t, fine.t);
                assert_eq!(coarse.axes, fine.axes);
                assert_eq!(coarse.tmax, fine.tmax);
            }
        }
    }

    #[test]
    fn corner_touch_steps_all_axes_together() {
        let r = ray([1.0, 1.0, 0.0], [-1.0, -1.0, -1.0]);
        let mut st = r.enter([-4; 3], [4; 3]).unwrap();
        assert_eq!(st.cell, [1, 1, 0]);
        r.step_fine(&mut st);
        assert_eq!(st.cell, [0, 0, -1]);
        assert_eq!(st.axes, 0b111);
    }

    #[test]
    fn entering_from_outside_lands_on_the_first_inside_cell() {
        let r = ray([-10.0, 0.5, 0.5], [1.0, 0.0, 0.0]);
        let st = r.enter([0; 3], [4; 3]).unwrap();
        assert_eq!(st.cell, [0, 0, 0]);
        assert_eq!(st.t, 10.0);
        assert_eq!(r.normal(&st), [-1, 0, 0]);
        // Moving away, or parallel outside: no entry.
        let away = ray([-10.0, 0.5, 0.5], [-1.0, 0.0, 0.0]);
        assert!(away.enter([0; 3], [4; 3]).is_none());
        let parallel = ray([-10.0, 5.0, 0.5], [1.0, 0.0, 0.0]);
        assert!(parallel.enter([0; 3], [4; 3]).is_none());
    }
}
