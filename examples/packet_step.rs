//! What does one SIMD step of a packet of rays cost against one scalar
//! step? A measurement of the assumption behind `packet_bound` (issue 11).
//!
//! `packet_bound` bounds what packets of coherent primary rays could buy
//! the exact walk, taking one SIMD operation over all lanes to cost what
//! one scalar operation costs. This example measures that cost ratio on
//! the walk's inner step, the one kind of operation a packet walk would run
//! most: a voxel DDA step (the least crossing, the axes that cross then,
//! each stepped axis's next crossing by the shared formula) and the test
//! of the voxel entered against an occupancy bitset.
//!
//! The same rays are walked three ways over a dense `N³` bitset terrain
//! (`N` = 128, 256 KiB, in L2 as a brick's masks are):
//! - **scalar**: one ray at a time, as the tracer's voxel level walks;
//! - **packets of 8**: 4 × 2 pixel tiles in lockstep, lanes as arrays that
//!   the compiler vectorises in a function built for AVX2 (8 `f32` wide);
//! - **packets of 16**: 4 × 4 tiles, built for AVX-512.
//!
//! Every lane's hit (voxel, axes and `t`) is checked against the scalar
//! walk's, bit for bit. A packet runs until its last lane ends; a lane that
//! ended keeps stepping, masked. The output gives ns per ray, the lanes'
//! utilisation and the cost of a packet iteration against a scalar step:
//! a packet of `n` lanes pays only while that ratio is below `n ×`
//! utilisation.
//!
//! `cargo run --release --example packet_step [-- WIDTH PASSES]` (default
//! 512 and 5). Runs only where the CPU has AVX2 (AVX-512 is reported as
//! missing where absent).

use std::time::Instant;

/// Grid edge in voxels (a power of two).
const N: i32 = 128;
const MASK: i32 = N - 1;

/// Words of the terrain's bitset.
const WORDS: usize = (N * N * N) as usize / 32;

/// The terrain: voxel (x, y, z) is solid below a rolling height.
struct Grid {
    /// One bit a voxel, 32 to a word (the unit an AVX2 gather loads).
    bits: Box<[u32; WORDS]>,
}

impl Grid {
    fn terrain() -> Self {
        let mut bits: Box<[u32; WORDS]> = vec![0u32; WORDS].into_boxed_slice().try_into().unwrap();
        for z in 0..N {
            for x in 0..N {
                let (fx, fz) = (x as f32, z as f32);
                let h = 30.0
                    + 12.0 * (fx * 0.07).sin() * (fz * 0.05).cos()
                    + 5.0 * ((fx + 2.0 * fz) * 0.21).sin()
                    + ((x * 7 + z * 13) % 5) as f32;
                for y in 0..(h as i32).min(N) {
                    let i = Self::index(x, y, z);
                    bits[i >> 5] |= 1 << (i & 31);
                }
            }
        }
        Grid { bits }
    }

    /// Bit index of a cell (coordinates wrapped, so masked lanes that left
    /// the grid still read memory inside it).
    #[inline(always)]
    fn index(x: i32, y: i32, z: i32) -> usize {
        ((x & MASK) | (y & MASK) << 7 | (z & MASK) << 14) as usize
    }

    #[inline(always)]
    fn solid(&self, x: i32, y: i32, z: i32) -> bool {
        let i = Self::index(x, y, z);
        self.bits[(i >> 5) & (WORDS - 1)] >> (i & 31) & 1 != 0
    }
}

/// A ray's DDA constants, prepared as `DdaRay::new` prepares them.
#[derive(Clone, Copy)]
struct Ray {
    o: [f32; 3],
    o_cross: [f32; 3],
    inv: [f32; 3],
    step: [i32; 3],
    plane: [i32; 3],
}

impl Ray {
    fn new(o: [f32; 3], d: [f32; 3]) -> Self {
        let mut r = Ray {
            o,
            o_cross: [f32::NEG_INFINITY; 3],
            inv: [f32::INFINITY; 3],
            step: [0; 3],
            plane: [0; 3],
        };
        for a in 0..3 {
            let inv = 1.0 / d[a];
            if d[a] != 0.0 && inv.is_finite() {
                r.inv[a] = inv;
                r.step[a] = if d[a] > 0.0 { 1 } else { -1 };
                r.plane[a] = (d[a] < 0.0) as i32;
                r.o_cross[a] = o[a];
            }
        }
        r
    }

    /// The shared crossing formula: the time the ray enters cell `c` on
    /// axis `a`.
    #[inline(always)]
    fn crossing_into(&self, a: usize, c: i32) -> f32 {
        ((c + self.plane[a]) as f32 - self.o_cross[a]) * self.inv[a]
    }
}

/// Where a ray ended: the voxel it hit (or the cell past the grid), the
/// axes that stepped into it, its entry time, and whether it hit.
#[derive(Clone, Copy, Debug, PartialEq, Default)]
struct End {
    cell: [i32; 3],
    axes: u8,
    t: f32,
    hit: bool,
    steps: u32,
}

/// Whether a coordinate lies outside `0..N` (`N` a power of two).
#[inline(always)]
fn outside(c: i32) -> bool {
    c & !MASK != 0
}

/// The scalar walk: the exact DDA, one voxel at a time.
#[inline(never)]
fn walk(grid: &Grid, r: &Ray) -> End {
    let mut cell: [i32; 3] = std::array::from_fn(|a| r.o[a].floor() as i32);
    let mut tmax: [f32; 3] = std::array::from_fn(|a| r.crossing_into(a, cell[a] + r.step[a]));
    let (mut t, mut axes, mut steps) = (0.0f32, 0u8, 0u32);
    loop {
        if grid.solid(cell[0], cell[1], cell[2]) {
            return End {
                cell,
                axes,
                t,
                hit: true,
                steps,
            };
        }
        let a = if tmax[1] < tmax[0] { tmax[1] } else { tmax[0] };
        t = if tmax[2] < a { tmax[2] } else { a };
        axes = 0;
        for a in 0..3 {
            if tmax[a] == t {
                cell[a] += r.step[a];
                tmax[a] = r.crossing_into(a, cell[a] + r.step[a]);
                axes |= 1 << a;
            }
        }
        steps += 1;
        if outside(cell[0]) || outside(cell[1]) || outside(cell[2]) {
            return End {
                cell,
                axes,
                t,
                hit: false,
                steps,
            };
        }
    }
}

/// `L` lanes of rays in structure-of-arrays form.
struct Lanes<const L: usize> {
    o_cross: [[f32; L]; 3],
    inv: [[f32; L]; 3],
    step: [[i32; L]; 3],
    plane: [[i32; L]; 3],
    cell: [[i32; L]; 3],
    tmax: [[f32; L]; 3],
}

impl<const L: usize> Lanes<L> {
    fn new(rays: &[Ray; L]) -> Self {
        let f = |g: &dyn Fn(&Ray, usize) -> f32| -> [[f32; L]; 3] {
            std::array::from_fn(|a| std::array::from_fn(|l| g(&rays[l], a)))
        };
        let i = |g: &dyn Fn(&Ray, usize) -> i32| -> [[i32; L]; 3] {
            std::array::from_fn(|a| std::array::from_fn(|l| g(&rays[l], a)))
        };
        let cell = i(&|r, a| r.o[a].floor() as i32);
        Lanes {
            o_cross: f(&|r, a| r.o_cross[a]),
            inv: f(&|r, a| r.inv[a]),
            step: i(&|r, a| r.step[a]),
            plane: i(&|r, a| r.plane[a]),
            tmax: std::array::from_fn(|a| {
                std::array::from_fn(|l| rays[l].crossing_into(a, cell[a][l] + rays[l].step[a]))
            }),
            cell,
        }
    }
}

/// The packet walk: every lane steps every iteration; a lane's end is
/// recorded the first time it hits or leaves. Returns the iterations.
#[inline(always)]
fn walk_packet<const L: usize>(grid: &Grid, lanes: &mut Lanes<L>, ends: &mut [End; L]) -> u32 {
    let mut live: u32 = if L == 32 { u32::MAX } else { (1 << L) - 1 };
    let mut t = [0.0f32; L];
    let mut axes = [0u8; L];
    let mut iterations = 0;
    loop {
        // The lookup, lane-wise (a gather of one word a lane).
        let mut done = 0u32;
        for l in 0..L {
            let (x, y, z) = (lanes.cell[0][l], lanes.cell[1][l], lanes.cell[2][l]);
            let out = outside(x | y | z);
            let hit = grid.solid(x, y, z);
            done |= ((hit | out) as u32) << l;
        }
        // Lanes that end now, recorded one by one (rare).
        let mut ending = live & done;
        while ending != 0 {
            let l = ending.trailing_zeros() as usize;
            ending &= ending - 1;
            let c = [lanes.cell[0][l], lanes.cell[1][l], lanes.cell[2][l]];
            ends[l] = End {
                cell: c,
                axes: axes[l],
                t: t[l],
                hit: !outside(c[0] | c[1] | c[2]),
                steps: iterations,
            };
        }
        live &= !done;
        if live == 0 {
            return iterations;
        }
        // The step, lane-wise with masks: what the compiler vectorises.
        for l in 0..L {
            let (x, y, z) = (lanes.tmax[0][l], lanes.tmax[1][l], lanes.tmax[2][l]);
            let m = if y < x { y } else { x };
            let tl = if z < m { z } else { m };
            t[l] = tl;
            let mut bits = 0u8;
            for a in 0..3 {
                let stepped = lanes.tmax[a][l] == tl;
                let c = lanes.cell[a][l] + if stepped { lanes.step[a][l] } else { 0 };
                lanes.cell[a][l] = c;
                let next = ((c + lanes.step[a][l] + lanes.plane[a][l]) as f32
                    - lanes.o_cross[a][l])
                    * lanes.inv[a][l];
                lanes.tmax[a][l] = if stepped { next } else { lanes.tmax[a][l] };
                bits |= (stepped as u8) << a;
            }
            axes[l] = bits;
        }
        iterations += 1;
    }
}

#[cfg(target_arch = "x86_64")]
#[target_feature(enable = "avx2,fma")]
fn walk_packet_avx2(grid: &Grid, lanes: &mut Lanes<8>, ends: &mut [End; 8]) -> u32 {
    walk_packet(grid, lanes, ends)
}

/// The packet walk of 8 lanes written with AVX2 intrinsics: the lookup a
/// gather of one 32-bit word a lane, the step 3 compares, 3 blends and
/// 3 conversions over all lanes, no lane-wise branch.
#[cfg(target_arch = "x86_64")]
#[target_feature(enable = "avx2,fma")]
fn walk_packet_avx2_by_hand(grid: &Grid, lanes: &Lanes<8>, ends: &mut [End; 8]) -> u32 {
    use std::arch::x86_64::*;
    // SAFETY (both): unaligned loads of 8 lanes from arrays of 8.
    let ld = |v: &[f32; 8]| unsafe { _mm256_loadu_ps(v.as_ptr()) };
    let ldi = |v: &[i32; 8]| unsafe { _mm256_loadu_si256(v.as_ptr().cast()) };
    let (ox, oy, oz) = (
        ld(&lanes.o_cross[0]),
        ld(&lanes.o_cross[1]),
        ld(&lanes.o_cross[2]),
    );
    let (ix, iy, iz) = (ld(&lanes.inv[0]), ld(&lanes.inv[1]), ld(&lanes.inv[2]));
    let (sx, sy, sz) = (
        ldi(&lanes.step[0]),
        ldi(&lanes.step[1]),
        ldi(&lanes.step[2]),
    );
    // Step plus plane: the next crossing of cell c is at plane c + s + p.
    let (qx, qy, qz) = (
        _mm256_add_epi32(sx, ldi(&lanes.plane[0])),
        _mm256_add_epi32(sy, ldi(&lanes.plane[1])),
        _mm256_add_epi32(sz, ldi(&lanes.plane[2])),
    );
    let (mut cx, mut cy, mut cz) = (
        ldi(&lanes.cell[0]),
        ldi(&lanes.cell[1]),
        ldi(&lanes.cell[2]),
    );
    let (mut tx, mut ty, mut tz) = (ld(&lanes.tmax[0]), ld(&lanes.tmax[1]), ld(&lanes.tmax[2]));
    let mask = _mm256_set1_epi32(MASK);
    let not_mask = _mm256_set1_epi32(!MASK);
    let one = _mm256_set1_epi32(1);
    let zero = _mm256_setzero_si256();
    let mut t = _mm256_setzero_ps();
    let (mut mx, mut my, mut mz) = (
        _mm256_setzero_ps(),
        _mm256_setzero_ps(),
        _mm256_setzero_ps(),
    );
    let mut live: u32 = 0xff;
    let mut iterations = 0;
    loop {
        // The lookup.
        let or = _mm256_or_si256(_mm256_or_si256(cx, cy), cz);
        let inside = _mm256_cmpeq_epi32(_mm256_and_si256(or, not_mask), zero);
        let idx = _mm256_or_si256(
            _mm256_and_si256(cx, mask),
            _mm256_or_si256(
                _mm256_slli_epi32::<7>(_mm256_and_si256(cy, mask)),
                _mm256_slli_epi32::<14>(_mm256_and_si256(cz, mask)),
            ),
        );
        let word_at = _mm256_srli_epi32::<5>(idx);
        // SAFETY: every index is below N³ / 32 = WORDS (coordinates are
        // masked to 0..N), the length of `grid.bits`.
        let words =
            unsafe { _mm256_i32gather_epi32::<4>(grid.bits.as_ptr() as *const i32, word_at) };
        let bit = _mm256_and_si256(
            _mm256_srlv_epi32(words, _mm256_and_si256(idx, _mm256_set1_epi32(31))),
            one,
        );
        let hit = _mm256_cmpeq_epi32(bit, one);
        // Done: hit inside, or outside.
        let done = _mm256_or_si256(
            _mm256_and_si256(hit, inside),
            _mm256_andnot_si256(inside, _mm256_set1_epi32(-1)),
        );
        let done = _mm256_movemask_ps(_mm256_castsi256_ps(done)) as u32;
        let mut ending = live & done;
        if ending != 0 {
            let mut c = [[0i32; 8]; 3];
            let mut tt = [0f32; 8];
            let mut m = [[0f32; 8]; 3];
            // SAFETY: unaligned stores of 8 lanes into arrays of 8.
            unsafe {
                _mm256_storeu_si256(c[0].as_mut_ptr().cast(), cx);
                _mm256_storeu_si256(c[1].as_mut_ptr().cast(), cy);
                _mm256_storeu_si256(c[2].as_mut_ptr().cast(), cz);
                _mm256_storeu_ps(tt.as_mut_ptr(), t);
                _mm256_storeu_ps(m[0].as_mut_ptr(), mx);
                _mm256_storeu_ps(m[1].as_mut_ptr(), my);
                _mm256_storeu_ps(m[2].as_mut_ptr(), mz);
            }
            while ending != 0 {
                let l = ending.trailing_zeros() as usize;
                ending &= ending - 1;
                let cell = [c[0][l], c[1][l], c[2][l]];
                let axes = (0..3).fold(0u8, |b, a| b | ((m[a][l].to_bits() != 0) as u8) << a);
                ends[l] = End {
                    cell,
                    axes,
                    t: tt[l],
                    hit: !outside(cell[0] | cell[1] | cell[2]),
                    steps: iterations,
                };
            }
        }
        live &= !done;
        if live == 0 {
            return iterations;
        }
        // The step.
        t = _mm256_min_ps(_mm256_min_ps(tx, ty), tz);
        mx = _mm256_cmp_ps::<_CMP_EQ_OQ>(tx, t);
        my = _mm256_cmp_ps::<_CMP_EQ_OQ>(ty, t);
        mz = _mm256_cmp_ps::<_CMP_EQ_OQ>(tz, t);
        cx = _mm256_add_epi32(cx, _mm256_and_si256(sx, _mm256_castps_si256(mx)));
        cy = _mm256_add_epi32(cy, _mm256_and_si256(sy, _mm256_castps_si256(my)));
        cz = _mm256_add_epi32(cz, _mm256_and_si256(sz, _mm256_castps_si256(mz)));
        let next = |c, q, o, i| {
            _mm256_mul_ps(
                _mm256_sub_ps(_mm256_cvtepi32_ps(_mm256_add_epi32(c, q)), o),
                i,
            )
        };
        tx = _mm256_blendv_ps(tx, next(cx, qx, ox, ix), mx);
        ty = _mm256_blendv_ps(ty, next(cy, qy, oy, iy), my);
        tz = _mm256_blendv_ps(tz, next(cz, qz, oz, iz), mz);
        iterations += 1;
    }
}

/// The packet walk of 16 lanes written with AVX-512 intrinsics: compares
/// give lane masks, and masked adds and moves replace the blends.
#[cfg(target_arch = "x86_64")]
#[target_feature(enable = "avx512f,avx512vl,avx2,fma")]
fn walk_packet_avx512_by_hand(grid: &Grid, lanes: &Lanes<16>, ends: &mut [End; 16]) -> u32 {
    use std::arch::x86_64::*;
    // SAFETY (both): unaligned loads of 16 lanes from arrays of 16.
    let ld = |v: &[f32; 16]| unsafe { _mm512_loadu_ps(v.as_ptr()) };
    let ldi = |v: &[i32; 16]| unsafe { _mm512_loadu_si512(v.as_ptr().cast()) };
    let o = [
        ld(&lanes.o_cross[0]),
        ld(&lanes.o_cross[1]),
        ld(&lanes.o_cross[2]),
    ];
    let inv = [ld(&lanes.inv[0]), ld(&lanes.inv[1]), ld(&lanes.inv[2])];
    let s = [
        ldi(&lanes.step[0]),
        ldi(&lanes.step[1]),
        ldi(&lanes.step[2]),
    ];
    let q: [__m512i; 3] = std::array::from_fn(|a| _mm512_add_epi32(s[a], ldi(&lanes.plane[a])));
    let mut c = [
        ldi(&lanes.cell[0]),
        ldi(&lanes.cell[1]),
        ldi(&lanes.cell[2]),
    ];
    let mut tm = [ld(&lanes.tmax[0]), ld(&lanes.tmax[1]), ld(&lanes.tmax[2])];
    let mask = _mm512_set1_epi32(MASK);
    let not_mask = _mm512_set1_epi32(!MASK);
    let mut t = _mm512_setzero_ps();
    let mut m: [__mmask16; 3] = [0; 3];
    let mut live: u32 = 0xffff;
    let mut iterations = 0;
    loop {
        let or = _mm512_or_si512(_mm512_or_si512(c[0], c[1]), c[2]);
        let outside_lanes = _mm512_test_epi32_mask(or, not_mask);
        let idx = _mm512_or_si512(
            _mm512_and_si512(c[0], mask),
            _mm512_or_si512(
                _mm512_slli_epi32::<7>(_mm512_and_si512(c[1], mask)),
                _mm512_slli_epi32::<14>(_mm512_and_si512(c[2], mask)),
            ),
        );
        // SAFETY: every index is below WORDS (coordinates masked to 0..N).
        let words = unsafe {
            _mm512_i32gather_epi32::<4>(_mm512_srli_epi32::<5>(idx), grid.bits.as_ptr().cast())
        };
        let bit = _mm512_srlv_epi32(words, _mm512_and_si512(idx, _mm512_set1_epi32(31)));
        let hit = _mm512_test_epi32_mask(bit, _mm512_set1_epi32(1));
        let done = (hit | outside_lanes) as u32;
        let mut ending = live & done;
        if ending != 0 {
            let mut cc = [[0i32; 16]; 3];
            let mut tt = [0f32; 16];
            // SAFETY: unaligned stores of 16 lanes into arrays of 16.
            unsafe {
                for a in 0..3 {
                    _mm512_storeu_si512(cc[a].as_mut_ptr().cast(), c[a]);
                }
                _mm512_storeu_ps(tt.as_mut_ptr(), t);
            }
            while ending != 0 {
                let l = ending.trailing_zeros() as usize;
                ending &= ending - 1;
                let cell = [cc[0][l], cc[1][l], cc[2][l]];
                let axes = (0..3).fold(0u8, |b, a| b | ((m[a] >> l & 1) as u8) << a);
                ends[l] = End {
                    cell,
                    axes,
                    t: tt[l],
                    hit: !outside(cell[0] | cell[1] | cell[2]),
                    steps: iterations,
                };
            }
        }
        live &= !done;
        if live == 0 {
            return iterations;
        }
        t = _mm512_min_ps(_mm512_min_ps(tm[0], tm[1]), tm[2]);
        for a in 0..3 {
            m[a] = _mm512_cmp_ps_mask::<_CMP_EQ_OQ>(tm[a], t);
            c[a] = _mm512_mask_add_epi32(c[a], m[a], c[a], s[a]);
            let next = _mm512_mul_ps(
                _mm512_sub_ps(_mm512_cvtepi32_ps(_mm512_add_epi32(c[a], q[a])), o[a]),
                inv[a],
            );
            tm[a] = _mm512_mask_mov_ps(tm[a], m[a], next);
        }
        iterations += 1;
    }
}

#[cfg(target_arch = "x86_64")]
#[target_feature(enable = "avx512f,avx512vl,avx2,fma")]
fn walk_packet_avx512(grid: &Grid, lanes: &mut Lanes<16>, ends: &mut [End; 16]) -> u32 {
    walk_packet(grid, lanes, ends)
}

/// The primary rays of a `w × h` image from an eye above the terrain, in
/// tiles of `tw × th` pixels (the order packets take them).
fn rays(w: usize, h: usize, tw: usize, th: usize) -> Vec<Ray> {
    let eye = [6.5f32, 92.3, 5.25];
    let target = [80.0f32, 28.0, 90.0];
    let f: [f32; 3] = std::array::from_fn(|a| target[a] - eye[a]);
    let norm = |v: [f32; 3]| {
        let n = (v[0] * v[0] + v[1] * v[1] + v[2] * v[2]).sqrt();
        [v[0] / n, v[1] / n, v[2] / n]
    };
    let cross = |a: [f32; 3], b: [f32; 3]| {
        [
            a[1] * b[2] - a[2] * b[1],
            a[2] * b[0] - a[0] * b[2],
            a[0] * b[1] - a[1] * b[0],
        ]
    };
    let f = norm(f);
    let right = norm(cross(f, [0.0, 1.0, 0.0]));
    let up = cross(right, f);
    let scale = (60f32.to_radians() / 2.0).tan();
    let aspect = w as f32 / h as f32;
    let mut out = Vec::with_capacity(w * h);
    for ty in (0..h).step_by(th) {
        for tx in (0..w).step_by(tw) {
            for y in ty..ty + th {
                for x in tx..tx + tw {
                    let u = ((x as f32 + 0.5) / w as f32 * 2.0 - 1.0) * scale * aspect;
                    let v = (1.0 - (y as f32 + 0.5) / h as f32 * 2.0) * scale;
                    let d: [f32; 3] = std::array::from_fn(|a| f[a] + u * right[a] + v * up[a]);
                    out.push(Ray::new(eye, norm(d)));
                }
            }
        }
    }
    out
}

/// Best of `passes` timings of `run`, seconds.
fn best(passes: usize, mut run: impl FnMut() -> u64) -> (f64, u64) {
    let mut best = f64::INFINITY;
    let mut sum = 0;
    for _ in 0..passes {
        let t = Instant::now();
        sum = run();
        best = best.min(t.elapsed().as_secs_f64());
    }
    (best, sum)
}

fn main() {
    #[cfg(not(target_arch = "x86_64"))]
    {
        eprintln!("error: packet_step measures x86-64 SIMD only");
        std::process::exit(1);
    }
    #[cfg(target_arch = "x86_64")]
    {
        let args: Vec<usize> = std::env::args()
            .skip(1)
            .map(|a| a.parse().expect("WIDTH and PASSES are whole numbers"))
            .collect();
        let w = args.first().copied().unwrap_or(512).max(16) / 4 * 4;
        let h = w * 3 / 4 / 4 * 4;
        let passes = args.get(1).copied().unwrap_or(5).max(1);
        if !is_x86_feature_detected!("avx2") || !is_x86_feature_detected!("fma") {
            eprintln!("error: this CPU has no AVX2: nothing to measure");
            std::process::exit(1);
        }
        let avx512 = is_x86_feature_detected!("avx512f") && is_x86_feature_detected!("avx512vl");
        let grid = Grid::terrain();
        println!("terrain {N}³, {w} × {h} primary rays, best of {passes} passes\n");
        for (tw, th) in [(4usize, 2usize), (4, 4)] {
            let lanes = tw * th;
            if lanes == 16 && !avx512 {
                println!("packets of 16: no AVX-512 on this CPU, not measured");
                continue;
            }
            let rays = rays(w, h, tw, th);
            let reference: Vec<End> = rays.iter().map(|r| walk(&grid, r)).collect();
            let scalar_steps: u64 = reference.iter().map(|e| e.steps as u64).sum();
            let (scalar_s, _) = best(passes, || {
                rays.iter()
                    .map(|r| {
                        std::hint::black_box(walk(&grid, std::hint::black_box(r))).steps as u64
                    })
                    .sum()
            });
            let n = rays.len() as f64;
            let hits = reference.iter().filter(|e| e.hit).count() as f64 / n;
            let step_ns = scalar_s * 1e9 / scalar_steps as f64;
            println!(
                "{tw} × {th} pixel packets ({lanes} lanes); {:.0} % of rays hit",
                hits * 100.0
            );
            println!(
                "  scalar walk:        {:6.1} ns a ray, {:.1} steps a ray, {:.2} ns a step",
                scalar_s * 1e9 / n,
                scalar_steps as f64 / n,
                step_ns
            );
            // One line per packet walk: ns a ray, what one iteration
            // costs in scalar steps, the most it may cost to pay (lanes ×
            // utilisation), and the speed-up.
            let report = |what: &str, seconds: f64, iterations: u64| {
                let utilisation = scalar_steps as f64 / (iterations as f64 * lanes as f64);
                println!(
                    "  {what:<19} {:6.1} ns a ray, lanes stepping {:.0} %, one iteration costs {:.2} scalar steps (pays below {:.2}): {:.2}×",
                    seconds * 1e9 / n,
                    utilisation * 100.0,
                    seconds * 1e9 / iterations as f64 / step_ns,
                    lanes as f64 * utilisation,
                    scalar_s / seconds
                );
            };
            {
                let mut hand_s = f64::INFINITY;
                let mut hand_iterations = 0u64;
                let packed8: Vec<Lanes<8>> = rays
                    .chunks_exact(8)
                    .map(|c| Lanes::<8>::new(c.try_into().unwrap()))
                    .collect();
                let packed16: Vec<Lanes<16>> = rays
                    .chunks_exact(16)
                    .map(|c| Lanes::<16>::new(c.try_into().unwrap()))
                    .collect();
                let mut ends = vec![End::default(); rays.len()];
                for _ in 0..passes {
                    let t0 = Instant::now();
                    hand_iterations = 0;
                    if lanes == 8 {
                        for (l, out) in packed8.iter().zip(ends.chunks_exact_mut(8)) {
                            // SAFETY: AVX2 and FMA were detected above.
                            hand_iterations += unsafe {
                                walk_packet_avx2_by_hand(&grid, l, out.try_into().unwrap())
                            } as u64;
                        }
                    } else {
                        for (l, out) in packed16.iter().zip(ends.chunks_exact_mut(16)) {
                            // SAFETY: AVX-512F/VL, AVX2 and FMA were detected above.
                            hand_iterations += unsafe {
                                walk_packet_avx512_by_hand(&grid, l, out.try_into().unwrap())
                            } as u64;
                        }
                    }
                    hand_s = hand_s.min(t0.elapsed().as_secs_f64());
                    for (i, (e, want)) in ends.iter().zip(&reference).enumerate() {
                        assert!(
                            e.cell == want.cell
                                && e.axes == want.axes
                                && e.t.to_bits() == want.t.to_bits()
                                && e.hit == want.hit,
                            "ray {i}: packet by hand {e:?}, scalar {want:?}"
                        );
                    }
                }
                report(
                    if lanes == 8 {
                        "AVX2 intrinsics:"
                    } else {
                        "AVX-512 intrinsics:"
                    },
                    hand_s,
                    hand_iterations,
                );
            }
            let mut packet_s = f64::INFINITY;
            let mut iterations = 0u64;
            for _ in 0..passes {
                let t0 = Instant::now();
                iterations = 0;
                for (k, chunk) in rays.chunks_exact(lanes).enumerate() {
                    let got: Vec<End> = if lanes == 8 {
                        let mut l = Lanes::<8>::new(chunk.try_into().unwrap());
                        let mut ends = [End::default(); 8];
                        // SAFETY: AVX2 and FMA were detected above.
                        iterations += unsafe { walk_packet_avx2(&grid, &mut l, &mut ends) } as u64;
                        ends.to_vec()
                    } else {
                        let mut l = Lanes::<16>::new(chunk.try_into().unwrap());
                        let mut ends = [End::default(); 16];
                        // SAFETY: AVX-512F/VL, AVX2 and FMA were detected above.
                        iterations +=
                            unsafe { walk_packet_avx512(&grid, &mut l, &mut ends) } as u64;
                        ends.to_vec()
                    };
                    for (i, e) in got.iter().enumerate() {
                        let want = reference[k * lanes + i];
                        assert!(
                            e.cell == want.cell
                                && e.axes == want.axes
                                && e.t.to_bits() == want.t.to_bits()
                                && e.hit == want.hit,
                            "ray {}: packet {e:?}, scalar {want:?}",
                            k * lanes + i
                        );
                    }
                }
                packet_s = packet_s.min(t0.elapsed().as_secs_f64());
            }
            report("auto-vectorised:", packet_s, iterations);
            println!("  every packet lane's hit (voxel, axes, t) equals the scalar walk's\n");
        }
    }
}
