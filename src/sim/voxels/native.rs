//! Native (Rust) reference kernels for voxel scripts: the same rule as a
//! shipped Lua script, with its declarations and its arithmetic (same
//! operations in the same order, `f64` in flight and `f32` in storage), so a
//! Lua run and a native run of one world are bit-identical. They are the
//! reference for both accuracy and speed (`bench voxels`).

use glam::IVec3;

use crate::sim::script::{VOXEL_CELLS, VOXEL_HALO};

/// What a native kernel sees of one brick in one pass: the Lua kernel's `c`.
pub struct NativeBrick<'a> {
    /// Brick coordinates.
    pub brick: IVec3,
    /// Time step.
    pub dt: f64,
    /// Parameter values, in the script's (sorted) parameter order.
    pub params: &'a [f64],
    /// Ids of the script's declared materials, in declaration order.
    pub materials: &'a [u8],
    /// Material halo (10³, x fastest, then y, then z).
    pub mat: &'a [u8; VOXEL_HALO],
    /// Channel halos, by the script's channel index (only the pass's reads
    /// are filled; the others hold stale values).
    pub reads: &'a [[f32; VOXEL_HALO]],
    /// The brick's materials, to be written.
    pub mat_out: &'a mut [u8; VOXEL_CELLS],
    /// The pass's written channels in the order the pass declares them
    /// (`mat` left out), holding the brick's current values.
    pub writes: &'a mut [[f32; VOXEL_CELLS]],
}

/// A voxel rule written in Rust, run in place of a Lua script's kernels.
pub trait VoxelNativeKernel: Send + Sync {
    /// The parameter names it expects, in the script's (sorted) order; a
    /// script whose declarations differ is refused.
    fn params(&self) -> &[&str];
    /// The channels it expects, in declaration order (refused likewise).
    fn channels(&self) -> &[&str];
    /// The materials it expects, in declaration order (refused likewise).
    fn materials(&self) -> &[&str];
    /// Run pass `pass` on one brick.
    fn run(&self, pass: usize, b: NativeBrick<'_>);
}

/// `math.max(a, b)` as Luau computes it (the first argument wins ties and
/// −0.0/0.0 comparisons).
#[inline(always)]
fn lmax(a: f64, b: f64) -> f64 {
    if b > a { b } else { a }
}

const DY: usize = 10;
const DZ: usize = 100;

/// The rule of `scripts/water3d.lua`: channels `water, k`; materials
/// `water`; parameters `compress, fall, film, spread, still`; passes `limit` and
/// `flow`.
pub struct Water3d {
    /// The script's `STABLE`: the most that 2·spread + fall/2 may be.
    pub stable: f64,
}

impl Default for Water3d {
    fn default() -> Self {
        Water3d {
            stable: WATER3D_STABLE,
        }
    }
}

/// water3d.lua's `STABLE`.
pub const WATER3D_STABLE: f64 = 0.45;

#[inline(always)]
fn lower(t: f64, comp: f64) -> f64 {
    if t <= 1.0 {
        t
    } else if t < 2.0 + comp {
        (1.0 + t * comp) / (1.0 + comp)
    } else {
        (t + comp) / 2.0
    }
}

impl VoxelNativeKernel for Water3d {
    fn params(&self) -> &[&str] {
        &["compress", "fall", "film", "spread", "still"]
    }

    fn channels(&self) -> &[&str] {
        &["water", "k"]
    }

    fn materials(&self) -> &[&str] {
        &["water"]
    }

    fn run(&self, pass: usize, b: NativeBrick<'_>) {
        let (comp, mut fall, film, mut spread, still) = (
            b.params[0],
            b.params[1],
            b.params[2],
            b.params[3],
            b.params[4],
        );
        let sum = 2.0 * spread + 0.5 * fall;
        if sum > self.stable {
            let r = self.stable / sum;
            spread *= r;
            fall *= r;
        }
        let water = b.materials[0];
        let w = &b.reads[0];
        let shape = Shape {
            w,
            mats: b.mat,
            water,
            comp,
            fall,
            film,
            spread,
        };
        let mut acc = [0.0f64; VOXEL_HALO];
        if pass == 0 {
            shape.faces(&mut acc, |f, _, _| {
                if f > still {
                    (f, 0.0)
                } else if f < -still {
                    (0.0, -f)
                } else {
                    (0.0, 0.0)
                }
            });
            for i in 0..VOXEL_CELLS {
                let h = own(i);
                let (out, m) = (acc[h], w[h] as f64);
                b.writes[0][i] = if out == 0.0 {
                    0.0
                } else if out > m {
                    (m / out) as f32
                } else {
                    1.0
                };
            }
        } else {
            let kk = &b.reads[1];
            shape.faces(&mut acc, |f, ha, hb| {
                let g = if f > still {
                    f * kk[ha] as f64
                } else if f < -still {
                    f * kk[hb] as f64
                } else {
                    0.0
                };
                // a's share is −g, carried to b as +g.
                (-g, g)
            });
            for i in 0..VOXEL_CELLS {
                let h = own(i);
                if shape.open(h) {
                    let new = lmax(w[h] as f64 + acc[h], 0.0);
                    b.writes[0][i] = new as f32;
                    b.mat_out[i] = if new >= 0.5 { water } else { 0 };
                }
            }
        }
    }
}

/// What water3d's faces are computed from.
struct Shape<'a> {
    w: &'a [f32; VOXEL_HALO],
    mats: &'a [u8; VOXEL_HALO],
    water: u8,
    comp: f64,
    fall: f64,
    film: f64,
    spread: f64,
}

impl Shape<'_> {
    #[inline(always)]
    fn open(&self, h: usize) -> bool {
        let m = self.mats[h];
        m == 0 || m == self.water
    }

    /// What is below cell `h` (fill `w`) is solid or cannot take all of it.
    #[inline(always)]
    fn supported(&self, h: usize, w: f64) -> bool {
        !self.open(h - DY) || self.w[h - DY] as f64 + w > 1.0
    }

    /// Walk every face in water3d.lua's order (x, z, then vertical faces,
    /// each along its axis), with `share(f, a, b)` giving a face's flux
    /// (f > 0: a sends) as (a's part, the part carried to b). A cell's sum is
    /// `carry + a's part`, written for the x faces and added for the others,
    /// exactly as the script does.
    #[inline(always)]
    fn faces(
        &self,
        acc: &mut [f64; VOXEL_HALO],
        mut share: impl FnMut(f64, usize, usize) -> (f64, f64),
    ) {
        for (axis, step) in [(0, 1), (1, DZ), (2, DY)] {
            for q in 0..8 {
                for p in 0..8 {
                    let mut a = match axis {
                        0 => (p + 1) * DY + (q + 1) * DZ,
                        1 => (p + 1) + (q + 1) * DY,
                        _ => (p + 1) + (q + 1) * DZ,
                    };
                    let mut wa = self.w[a] as f64;
                    let mut oa = self.open(a);
                    let mut sa = axis == 2 || self.supported(a, wa);
                    let mut carry = 0.0;
                    for s in 1..10 {
                        let b = a + step;
                        let wb = self.w[b] as f64;
                        let ob = self.open(b);
                        let sb = axis == 2 || self.supported(b, wb);
                        let (mine, next) = if axis == 2 {
                            let t = wa + wb;
                            if t > 0.0 && oa && ob {
                                // Free fall where both fit in the lower cell.
                                let f = if t <= 1.0 {
                                    -wb
                                } else {
                                    self.fall * (wa - lower(t, self.comp))
                                };
                                share(f, a, b)
                            } else {
                                share(0.0, a, b)
                            }
                        } else if wa != wb && oa && ob {
                            // Only a supported sender spreads sideways, and
                            // only what it holds above the film.
                            let ex = |w: f64| if w > self.film { w - self.film } else { 0.0 };
                            let f = self.spread * (ex(wa) - ex(wb));
                            if (f > 0.0 && sa) || (f < 0.0 && sb) {
                                share(f, a, b)
                            } else {
                                share(0.0, a, b)
                            }
                        } else {
                            share(0.0, a, b)
                        };
                        if s > 1 {
                            acc[a] = if axis == 0 {
                                carry + mine
                            } else {
                                acc[a] + (carry + mine)
                            };
                        }
                        carry = next;
                        a = b;
                        wa = wb;
                        oa = ob;
                        sa = sb;
                    }
                }
            }
        }
    }
}

/// Halo index of own cell `i` (x fastest, then y, then z).
#[inline(always)]
fn own(i: usize) -> usize {
    (i % 8 + 1) + (i / 8 % 8 + 1) * DY + (i / 64 + 1) * DZ
}
