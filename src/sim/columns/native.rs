//! Native reference kernels, with exactly the declarations and arithmetic of
//! their Lua counterparts (same operations, same order), so a Lua run and a
//! native run of the same world are bit-identical: the reference for both
//! accuracy and speed.

use crate::sim::step::NativeKernel;
use crate::sim::tile::{HALO_CELLS, TILE_CELLS, cell, halo};

/// `math.max(a, b)` as Luau computes it (the first argument wins ties and
/// −0.0/0.0 comparisons), so results match the Lua script bit for bit.
#[inline(always)]
fn lmax(a: f64, b: f64) -> f64 {
    if b > a { b } else { a }
}

/// The staggered shallow-water model of `scripts/water.lua`: channels
/// `ground, water, u, v, qx, qz`; parameters (sorted) `dx, friction,
/// gravity, rain`.
pub struct ShallowWater;

const GROUND: usize = 0;
const WATER: usize = 1;
const U: usize = 2;
const V: usize = 3;
const QX: usize = 4;
const QZ: usize = 5;

impl NativeKernel for ShallowWater {
    fn run(
        &self,
        pass: usize,
        dt: f64,
        params: &[f64],
        r: &[[f64; HALO_CELLS]],
        w: &mut [[f64; TILE_CELLS]],
    ) {
        let (dx, friction, g, rain) = (params[0], params[1], params[2], params[3]);
        match pass {
            0 => {
                let (b, h, u, v, qx, qz) = (&r[GROUND], &r[WATER], &r[U], &r[V], &r[QX], &r[QZ]);
                let k = g * dt / dx;
                let cf = friction * dt;
                let adv = |f_arr: &[f64; HALO_CELLS],
                           q: &[f64; HALO_CELLS],
                           i: usize,
                           s: usize,
                           f: f64,
                           hbar: f64| {
                    let ql = (q[i - s] + q[i]) * 0.5;
                    let qr = (q[i] + q[i + s]) * 0.5;
                    let ul = if ql >= 0.0 { f_arr[i - s] } else { f };
                    let ur = if qr >= 0.0 { f } else { f_arr[i + s] };
                    ((qr * ur - ql * ul) - f * (qr - ql)) / (dx * hbar)
                };
                for z in 0..8 {
                    for x in 0..8 {
                        let i = halo(x, z);
                        let o = cell(x, z);
                        let bi = b[i];
                        let hi = h[i];
                        let e = bi + hi;
                        let (br, hr) = (b[i + 1], h[i + 1]);
                        let er = br + hr;
                        let mut nu = 0.0;
                        if lmax(e, er) - lmax(bi, br) > 1e-9 {
                            let ui = u[i];
                            let hbar = (hi + hr) * 0.5;
                            let a = if hbar > 1e-9 {
                                adv(u, qx, i, 1, ui, hbar)
                            } else {
                                0.0
                            };
                            nu = ui - dt * a - k * (er - e);
                            nu /= 1.0 + cf * nu.abs() / lmax(hbar, 0.01);
                        }
                        w[U][o] = nu;
                        let (bt, ht) = (b[i + 10], h[i + 10]);
                        let et = bt + ht;
                        let mut nv = 0.0;
                        if lmax(e, et) - lmax(bi, bt) > 1e-9 {
                            let vi = v[i];
                            let hbar = (hi + ht) * 0.5;
                            let a = if hbar > 1e-9 {
                                adv(v, qz, i, 10, vi, hbar)
                            } else {
                                0.0
                            };
                            nv = vi - dt * a - k * (et - e);
                            nv /= 1.0 + cf * nv.abs() / lmax(hbar, 0.01);
                        }
                        w[V][o] = nv;
                    }
                }
            }
            1 => {
                let (h, u, v) = (&r[WATER], &r[U], &r[V]);
                let lim = |j: usize| {
                    let s = lmax(0.0, u[j])
                        + lmax(0.0, -u[j - 1])
                        + lmax(0.0, v[j])
                        + lmax(0.0, -v[j - 10]);
                    let t = s * dt;
                    if t > dx { dx / t } else { 1.0 }
                };
                for z in 0..8 {
                    for x in 0..8 {
                        let i = halo(x, z);
                        let o = cell(x, z);
                        let ui = u[i];
                        w[QX][o] = if ui > 0.0 {
                            ui * h[i] * lim(i)
                        } else if ui < 0.0 {
                            ui * h[i + 1] * lim(i + 1)
                        } else {
                            0.0
                        };
                        let vi = v[i];
                        w[QZ][o] = if vi > 0.0 {
                            vi * h[i] * lim(i)
                        } else if vi < 0.0 {
                            vi * h[i + 10] * lim(i + 10)
                        } else {
                            0.0
                        };
                    }
                }
            }
            _ => {
                let a = dt / dx;
                let rain = rain * dt;
                let (h, qx, qz) = (&r[WATER], &r[QX], &r[QZ]);
                for z in 0..8 {
                    for x in 0..8 {
                        let i = halo(x, z);
                        let net = (qx[i - 1] - qx[i]) + (qz[i - 10] - qz[i]);
                        w[WATER][cell(x, z)] = h[i] + a * net + rain;
                    }
                }
            }
        }
    }
}
