//! Native reference kernels, with exactly the declarations and arithmetic of
//! their Lua counterparts (same operations, same order), so a Lua run and a
//! native run of the same world are bit-identical: the reference for both
//! accuracy and speed.

use super::step::NativeKernel;
use super::tile::{HALO_CELLS, TILE_CELLS, cell, halo};

/// `math.max(a, b)` as Luau computes it (the first argument wins ties and
/// −0.0/0.0 comparisons), so results match the Lua script bit for bit.
#[inline(always)]
fn lmax(a: f64, b: f64) -> f64 {
    if b > a { b } else { a }
}

/// The virtual pipe water model (Mei, Decaudin & Hu 2007) of
/// `scripts/water.lua`: channels `ground, water, out_l, out_r, out_b, out_t`;
/// parameters (sorted) `dx, gravity, rain`.
pub struct PipeWater;

const GROUND: usize = 0;
const WATER: usize = 1;
const OUT_L: usize = 2;
const OUT_R: usize = 3;
const OUT_B: usize = 4;
const OUT_T: usize = 5;

impl NativeKernel for PipeWater {
    fn run(
        &self,
        pass: usize,
        dt: f64,
        params: &[f64],
        r: &[[f64; HALO_CELLS]],
        w: &mut [[f64; TILE_CELLS]],
    ) {
        let (dx, gravity, rain) = (params[0], params[1], params[2]);
        if pass == 0 {
            let k = dt * gravity;
            let (b, d) = (&r[GROUND], &r[WATER]);
            for z in 0..8 {
                for x in 0..8 {
                    let i = halo(x, z);
                    let di = d[i];
                    let bi = b[i];
                    let h = bi + di;
                    let (bl, br, bb, bt) = (b[i - 1], b[i + 1], b[i - 10], b[i + 10]);
                    let (hl, hr, hb, ht) = (bl + d[i - 1], br + d[i + 1], bb + d[i - 10], bt + d[i + 10]);
                    let mut fl = lmax(0.0, r[OUT_L][i] + k * (lmax(h, hl) - lmax(bi, bl)) * (h - hl));
                    let mut fr = lmax(0.0, r[OUT_R][i] + k * (lmax(h, hr) - lmax(bi, br)) * (h - hr));
                    let mut fb = lmax(0.0, r[OUT_B][i] + k * (lmax(h, hb) - lmax(bi, bb)) * (h - hb));
                    let mut ft = lmax(0.0, r[OUT_T][i] + k * (lmax(h, ht) - lmax(bi, bt)) * (h - ht));
                    let sum = fl + fr + fb + ft;
                    if sum > 0.0 {
                        let s = di * (dx * dx) / (sum * dt);
                        if s < 1.0 {
                            fl *= s;
                            fr *= s;
                            fb *= s;
                            ft *= s;
                        }
                    }
                    let o = cell(x, z);
                    w[OUT_L][o] = fl;
                    w[OUT_R][o] = fr;
                    w[OUT_B][o] = fb;
                    w[OUT_T][o] = ft;
                }
            }
        } else {
            let d = &r[WATER];
            let (l, rr, bo, t) = (&r[OUT_L], &r[OUT_R], &r[OUT_B], &r[OUT_T]);
            for z in 0..8 {
                for x in 0..8 {
                    let i = halo(x, z);
                    let out = l[i] + rr[i] + bo[i] + t[i];
                    let inflow = rr[i - 1] + l[i + 1] + t[i - 10] + bo[i + 10];
                    w[WATER][cell(x, z)] = d[i] + dt * (inflow - out) / (dx * dx) + rain * dt;
                }
            }
        }
    }
}
