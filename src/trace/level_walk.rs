//! The level walk, kept as the reference that the CPU's level of detail
//! ([`BrickmapTracer::walk`] with level checks) is tested against; the GPU
//! shader walks the same way. Test-only: see [`super::lod`] for why the
//! CPU's walk reports the same hits at less cost.

use glam::IVec3;

use super::brickmap::BrickmapTracer;
use super::lod::lod_level;
use super::ray::{Hit, Ray};
use crate::world::{BrickRef, TOP_LEVEL, UNIFORM, block_solid};

/// The level walk: the reference that [`BrickmapTracer::walk`] is held to.
/// It walks each level's cells as a coarse DDA, one level at a time; the
/// exact walk with level checks reports the same, faster.
impl BrickmapTracer<'_> {
    /// The level walk from `t_start`; `first`: the cells holding the start
    /// were entered earlier with a footprint that allowed voxels only.
    fn level_walk(&self, ray: &Ray, t_start: f32, t_max: f32, k: f32, first: bool) -> Option<Hit> {
        let (r, st) = self.start(ray, t_start)?;
        // A ray that enters the grid after `t_start` enters its cells then.
        let first = first && st.t <= t_start;
        self.walk_levels(&r, st, t_max, k, first)
    }

    /// The level walk of `r` from the exact state `st`; `first`: the cells
    /// holding `st` were entered earlier with a footprint that allowed
    /// voxels only.
    fn walk_levels(
        &self,
        r: &super::dda::DdaRay,
        st: super::dda::DdaState,
        t_max: f32,
        k: f32,
        first: bool,
    ) -> Option<Hit> {
        self.walk_levels_as::<true>(r, st, t_max, k, first)
    }

    /// The level walk, restoring the exact state after each coarse run
    /// only when needed (`LAZY`) or at once (the reference that tests hold
    /// the lazy walk to).
    #[inline(always)]
    fn walk_levels_as<const LAZY: bool>(
        &self,
        r: &super::dda::DdaRay,
        mut st: super::dda::DdaState,
        t_max: f32,
        k: f32,
        mut first: bool,
    ) -> Option<Hit> {
        let ring = self.grid.ring().to_array();
        let coarse = self.grid.coarse();
        let mut top = TOP_LEVEL;
        // The current brick's pointer and, if mixed, the brick: read when
        // level 3 is checked, valid below it while the brick is unchanged.
        let mut p = 0u32;
        let mut brick: Option<BrickRef<'_>> = None;
        // After a coarse run the exact voxel state is restored only when
        // it is needed (a hit, or a descent below the run's level): until
        // then the walk knows time `t` and its level-`l` cell `cc`, which is
        // all a climb needs. Restoring later is exact: the state after every
        // crossing up to `t` does not depend on where the walk restores from.
        let mut lazy: Option<(f32, [i32; 3], u32)> = None;
        loop {
            let now = lazy.map_or(st.t, |(t, _, _)| t);
            if now > t_max {
                return None;
            }
            let allowed = if first { 0 } else { lod_level(now * k) };
            first = false;
            let mut level = top;
            let solid_at = loop {
                if let Some((t, _, l)) = lazy
                    && level < l
                {
                    r.advance_to(&mut st, t);
                    lazy = None;
                }
                // A voxel of the current cell at this level (its low
                // corner while the state is lazy).
                let c = lazy.map_or(st.cell, |(_, cc, l)| cc.map(|v| v << l));
                let solid = match level {
                    4 | 5 => coarse.get(level, c.map(|v| v >> level), ring) != 0,
                    3 => {
                        p = self.grid.pointer(IVec3::from(c.map(|v| v >> 3)));
                        brick = if p != 0 && p & UNIFORM == 0 {
                            self.pool.slot(p - 1)
                        } else {
                            None
                        };
                        p != 0
                    }
                    _ => match brick {
                        Some(b) => block_solid(b.mask(), level, c.map(|v| v & 7)),
                        None => p != 0,
                    },
                };
                if !solid {
                    break None;
                }
                if level <= allowed {
                    break Some(level);
                }
                // Levels 1 and 2 only skip empty space: where the footprint
                // allows no level above voxels, the voxel walk below is as
                // fast and gives the same hits.
                level = if level <= 3 && allowed == 0 {
                    0
                } else {
                    level - 1
                };
            };
            if let Some((t, _, _)) = lazy.filter(|_| solid_at.is_some()) {
                r.advance_to(&mut st, t);
                lazy = None;
            }
            let c = lazy.map_or(st.cell, |(_, cc, l)| cc.map(|v| v << l));
            if let Some(level) = solid_at {
                let material = self.lod_material(level, c, p, brick);
                return Some(Hit {
                    t: st.t,
                    voxel: self.frame.to_world(c),
                    normal: IVec3::from(r.normal(&st)),
                    material,
                    level: level as u8,
                });
            }
            // The level-`level` cell is empty: walk that level's cells as a
            // coarse DDA (the exact crossing formula, no voxel state) while
            // they are empty; the exact state is restored later, when needed
            // (see `lazy` above). The walk climbs
            // (breaks) when it leaves its brick (levels 0–2, whose cells
            // come from the brick) or its 32³ cell (levels 3, 4), or when it
            // enters a new parent cell that the footprint may now take whole.
            // Walking on at a fine level through an empty coarse cell is
            // exact: "any solid" means its cells are all empty too.
            if level == 0 {
                // Voxels: step the exact state itself (no restore needed).
                const FULL: [u64; 8] = [u64::MAX; 8];
                let mask = brick.map_or(&FULL, |b| b.mask());
                let climbed = loop {
                    let prev = st.cell;
                    r.step_fine(&mut st);
                    if st.t > t_max {
                        return None;
                    }
                    let x =
                        (prev[0] ^ st.cell[0]) | (prev[1] ^ st.cell[1]) | (prev[2] ^ st.cell[2]);
                    let climbed = 31 - (x as u32).leading_zeros();
                    if climbed >= 3 || (climbed > 0 && lod_level(st.t * k) > 0) {
                        break climbed;
                    }
                    if block_solid(mask, 0, st.cell.map(|v| v & 7)) {
                        break climbed;
                    }
                };
                if !self.inside(st.cell) {
                    return None;
                }
                // Only the cells entered at this last step are new: coarser
                // ones crossed earlier in the run were descended into then.
                top = climbed.min(TOP_LEVEL);
                continue;
            }
            let run_limit = match level {
                0..=2 => 3,
                3 | 4 => TOP_LEVEL,
                _ => TOP_LEVEL + 1,
            };
            let mut cc = c.map(|v| v >> level);
            let mut ct = r.coarse_tmax(cc, level);
            let (t, climbed) = loop {
                let prev = cc;
                let t = r.coarse_step(&mut cc, &mut ct, level);
                if t > t_max {
                    return None;
                }
                let x = (prev[0] ^ cc[0]) | (prev[1] ^ cc[1]) | (prev[2] ^ cc[2]);
                let climbed = level + (31 - (x as u32).leading_zeros());
                if climbed >= run_limit {
                    break (t, climbed);
                }
                if climbed > level && lod_level(t * k) > level {
                    break (t, climbed);
                }
                if level == TOP_LEVEL && !self.inside_level(cc, level) {
                    return None;
                }
                let solid = match level {
                    4 | 5 => coarse.get(level, cc, ring) != 0,
                    3 => self.grid.pointer(IVec3::from(cc)) != 0,
                    _ => brick.is_some_and(|b| {
                        block_solid(b.mask(), level, cc.map(|v| (v << level) & 7))
                    }),
                };
                if solid {
                    break (t, climbed);
                }
            };
            if LAZY {
                if !self.inside_level(cc, level) {
                    return None;
                }
                lazy = Some((t, cc, level));
            } else {
                r.advance_to(&mut st, t);
                if !self.inside(st.cell) {
                    return None;
                }
            }
            // As above: the levels entered at the last step, no coarser.
            top = climbed.min(TOP_LEVEL);
        }
    }

    /// Whether level-`level` cell `c` is inside the grid.
    #[inline(always)]
    fn inside_level(&self, c: [i32; 3], level: u32) -> bool {
        (0..3).all(|a| (c[a] as u32) < (self.dims[a] >> level) as u32)
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::trace::Tracer;
    use crate::world::{BrickGrid, BrickStore, Palette};
    use glam::{DVec3, Vec3};

    pub(super) fn scene() -> (BrickStore, BrickGrid) {
        let mut s = BrickStore::new(Palette::grey_ramp());
        s.fill_box(IVec3::new(0, 0, 0), IVec3::new(200, 20, 150), 3);
        s.fill_box(IVec3::new(0, 20, 0), IVec3::new(200, 21, 150), 7);
        s.fill_sphere(DVec3::new(60.0, 40.0, 70.0), 18.5, 9);
        let mut x = 0x9e37_79b9u32;
        for _ in 0..3000 {
            x ^= x << 13;
            x ^= x >> 17;
            x ^= x << 5;
            let p = IVec3::new(
                (x % 200) as i32,
                21 + (x >> 8) as i32 % 60,
                (x >> 16) as i32 % 150,
            );
            s.set_voxel(p, 1 + (x >> 24) as u8 % 200);
        }
        let (lo, hi) = s.brick_bounds().unwrap();
        let g = BrickGrid::build(&s, lo, hi - lo + IVec3::ONE).unwrap();
        (s, g)
    }

    pub(super) fn rays() -> Vec<Ray> {
        let mut out = Vec::new();
        let mut x = 0x1234_5677u32;
        let mut f = || {
            x ^= x << 13;
            x ^= x >> 17;
            x ^= x << 5;
            (x >> 8) as f32 / (1 << 24) as f32
        };
        for _ in 0..20_000 {
            let o = Vec3::new(f() * 300.0 - 50.0, f() * 120.0, f() * 250.0 - 50.0);
            let d = Vec3::new(f() - 0.5, f() - 0.6, f() - 0.5);
            // Some axis-aligned and diagonal rays, the DDA's edge cases.
            let d = match out.len() % 7 {
                0 => Vec3::new(d.x, 0.0, 0.0),
                1 => Vec3::new(1.0, -1.0, 1.0),
                _ => d,
            };
            out.push(Ray::new(o, d.normalize_or(Vec3::X)));
        }
        out
    }

    /// With `k = 0` the level walk is the exact tracer, bit for bit.
    #[test]
    fn lod_off_is_the_exact_walk_bit_for_bit() {
        let (s, g) = scene();
        let t = BrickmapTracer::new(&g, s.pool());
        let mut hits = 0;
        for ray in rays() {
            let local = Ray::new(ray.origin, ray.dir);
            let exact = t.trace(&local, f32::INFINITY);
            // The level walk itself (not the exact prefix trace_lod uses).
            assert_eq!(
                t.level_walk(&local, 0.0, f32::INFINITY, 0.0, false),
                exact,
                "{ray:?}"
            );
            assert_eq!(
                t.level_walk(&local, 0.0, 40.0, 0.0, false),
                t.trace(&local, 40.0)
            );
            hits += exact.is_some() as u32;
        }
        assert!(hits > 5_000, "the rays must hit something ({hits})");
    }

    /// A coarse hit is never behind the exact one (any-solid levels only
    /// grow the solid), lies on a solid coarse cell, and a footprint of a
    /// whole level picks that level.
    #[test]
    fn lod_hits_come_no_later_than_exact_ones() {
        let (s, g) = scene();
        let t = BrickmapTracer::new(&g, s.pool());
        let mut coarser = 0;
        for ray in rays() {
            let exact = t.trace(&ray, f32::INFINITY);
            let lod = t.trace_lod(&ray, f32::INFINITY, 0.2);
            match (exact, lod) {
                (Some(e), Some(l)) => {
                    assert!(l.t <= e.t, "{ray:?}: lod {} after exact {}", l.t, e.t);
                    assert_ne!(l.material, 0);
                    coarser += (l.t < e.t) as u32;
                }
                (Some(e), None) => panic!("{ray:?}: lod missed the exact hit {e:?}"),
                _ => {}
            }
        }
        assert!(coarser > 100, "some hits must be coarse ({coarser})");
        assert_eq!(lod_level(1.99), 0);
        assert_eq!(lod_level(2.0), 1);
        assert_eq!(lod_level(31.9), 4);
        assert_eq!(lod_level(1e9), TOP_LEVEL);
    }
}
#[cfg(test)]
mod walk_tests {
    use super::*;
    use crate::trace::{Camera, Tracer};
    use glam::{DVec3, IVec3};

    /// Restoring the exact state lazily after coarse runs changes no hit:
    /// every bench view at C = 0.5 to 16, rays from the eye and from beam
    /// starts half way.
    #[test]
    fn lazy_restoration_changes_no_hit() {
        let spec: crate::scene::SceneSpec = "terrain:caves".parse().unwrap();
        let hidden = indicatif::ProgressBar::hidden();
        let w = crate::scene::build_scene(&spec, IVec3::new(192, 96, 160), 3, &hidden).unwrap();
        let t = w.brickmap();
        let mut coarse = 0;
        for v in w.default_views() {
            let cam =
                Camera::new(DVec3::from(v.eye), DVec3::from(v.target), v.fov, 96, 72).unwrap();
            let o = Tracer::frame(&t).to_local(cam.eye);
            for c in [0.5f32, 1.0, 4.0, 16.0] {
                let k = c * cam.pixel_angle() as f32;
                for j in 0..72 {
                    for i in 0..96 {
                        let ray = Ray::new(o, cam.direction(i, j).as_vec3());
                        for t0 in [0.0, 20.0] {
                            let Some((r, st)) = t.start(&ray, t0) else {
                                continue;
                            };
                            let lazy = t.walk_levels_as::<true>(&r, st, f32::INFINITY, k, false);
                            let eager = t.walk_levels_as::<false>(&r, st, f32::INFINITY, k, false);
                            assert_eq!(lazy, eager, "view {v:?}, C = {c}, pixel {i},{j}");
                            coarse += lazy.is_some_and(|h| h.level > 0) as u32;
                        }
                    }
                }
            }
        }
        assert!(coarse > 1000, "the test needs coarse hits: {coarse}");
    }

    /// `trace_lod`, the exact walk with level checks at each step, reports
    /// what the level walk reports from the eye: every pixel of every bench
    /// view of two scenes at C = 0.5 to 64, and 20 000 random rays (inside
    /// and outside the volume, axis-aligned and diagonal) at five
    /// footprints. (Regression, from the walk it replaced: rays entering
    /// the grid after the footprint first allowed a level had their first
    /// cells forced to voxels, 897 of 19 200 pixels differed.)
    #[test]
    fn the_exact_walk_with_level_checks_is_the_level_walk() {
        let hidden = indicatif::ProgressBar::hidden();
        let mut coarse = [0u32; 6];
        for (scene, size) in [
            ("terrain", IVec3::new(160, 64, 136)),
            ("terrain:caves", IVec3::new(192, 96, 160)),
        ] {
            let spec: crate::scene::SceneSpec = scene.parse().unwrap();
            let w = crate::scene::build_scene(&spec, size, 7, &hidden).unwrap();
            let t = w.brickmap();
            for v in w.default_views() {
                let cam = Camera::new(DVec3::from(v.eye), DVec3::from(v.target), v.fov, 160, 120)
                    .unwrap();
                let o = Tracer::frame(&t).to_local(cam.eye);
                for c in [0.5f32, 1.0, 2.0, 4.0, 16.0, 64.0] {
                    let k = c * cam.pixel_angle() as f32;
                    for j in 0..120 {
                        for i in 0..160 {
                            let ray = Ray::new(o, cam.direction(i, j).as_vec3());
                            let walk = t.level_walk(&ray, 0.0, f32::INFINITY, k, false);
                            let lod = t.trace_lod(&ray, f32::INFINITY, k);
                            assert_eq!(lod, walk, "{scene}, view {v:?}, C = {c}, pixel {i},{j}");
                            if let Some(h) = lod {
                                coarse[h.level as usize] += 1;
                            }
                        }
                    }
                }
            }
        }
        let (s, g) = super::tests::scene();
        let t = BrickmapTracer::new(&g, s.pool());
        for ray in super::tests::rays() {
            for k in [0.003f32, 0.02, 0.1, 0.5, 3.0] {
                for t_max in [f32::INFINITY, 60.0] {
                    let walk = t.level_walk(&ray, 0.0, t_max, k, false);
                    assert_eq!(
                        t.trace_lod(&ray, t_max, k),
                        walk,
                        "{ray:?}, k = {k}, t_max {t_max}"
                    );
                    if let Some(h) = walk {
                        coarse[h.level as usize] += 1;
                    }
                }
            }
        }
        // Every level is exercised.
        assert!(
            coarse.iter().all(|&n| n > 100),
            "hits per level: {coarse:?}"
        );
    }
}
