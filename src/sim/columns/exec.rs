//! One column script's step: the work set (active tiles and their
//! neighbours, held densely), the parallel passes that gather each tile's
//! halo and run its kernel (Lua or native) into per-tile outputs, the
//! commit of each pass (double-buffered) and the validation of what was
//! written. Every pass reads only the previous generation.

use rayon::prelude::*;
use rustc_hash::FxHashMap;

use super::step::{DEFAULT_BOUND_HEIGHTS, Kernel, Loaded, MIN_BOUND_HEIGHT};
use crate::sim::channels::ChannelStore;
use crate::sim::runtime::vms::{PassChannels, StepStamp};
use crate::sim::script::StepKey;
use crate::sim::tile::{HALO_CELLS, TILE, TILE_CELLS, TileCoord, neighbourhood};
use crate::sim::{Rejection, SimError};

/// A step's dense working buffers, kept between steps.
#[derive(Default)]
pub(super) struct StepScratch {
    /// The running script's channels over the work set, tile-major (all of
    /// a tile's channels side by side, so a tile's halo reads nine short
    /// runs of memory instead of 9 × channels scattered ones): channel `i`
    /// of work-set tile `w` is `data[w * channels + i]`.
    pub(super) data: Vec<[f64; TILE_CELLS]>,
    /// One pass's outputs, per active tile and written channel.
    outs: Vec<[f64; TILE_CELLS]>,
}

/// The tiles a step touches: the active ones and their neighbours, densely
/// indexed, with each active tile's 3×3 neighbourhood as indices.
pub(super) struct WorkSet {
    pub(super) tiles: Vec<TileCoord>,
    pub(super) active: Vec<u32>,
    nbr: Vec<[u32; 9]>,
}

const OUTSIDE: u32 = u32::MAX;

impl WorkSet {
    pub(super) fn new(active: &[TileCoord], min: TileCoord, max: TileCoord) -> Self {
        let inside = |t: TileCoord| t.cmpge(min).all() && t.cmplt(max).all();
        let mut tiles: Vec<TileCoord> = active
            .iter()
            .flat_map(|&t| neighbourhood(t))
            .filter(|&t| inside(t))
            .collect();
        tiles.sort_by_key(|t| (t.y, t.x));
        tiles.dedup();
        let index: FxHashMap<TileCoord, u32> = tiles
            .iter()
            .enumerate()
            .map(|(i, t)| (*t, i as u32))
            .collect();
        let active_idx = active.iter().map(|t| index[t]).collect();
        let nbr = active
            .iter()
            .map(|&t| {
                let mut n = [OUTSIDE; 9];
                for (k, nt) in neighbourhood(t).enumerate() {
                    if let Some(&i) = index.get(&nt) {
                        n[k] = i;
                    }
                }
                n
            })
            .collect();
        WorkSet {
            tiles,
            active: active_idx,
            nbr,
        }
    }

    /// Gather the halo of active tile `k` from dense `data`: rows and
    /// columns copied as slices, outside-world neighbours filled with
    /// `boundary`.
    /// `data` is tile-major: channel `ch` of work-set tile `w` is
    /// `data[w * stride + ch]`.
    fn gather(
        &self,
        k: usize,
        (data, stride, ch): (&[[f64; TILE_CELLS]], usize, usize),
        boundary: f64,
        out: &mut [f64; HALO_CELLS],
    ) {
        let n = &self.nbr[k];
        let get = |i: usize| {
            if n[i] == OUTSIDE {
                None
            } else {
                Some(&data[n[i] as usize * stride + ch])
            }
        };
        let t = TILE as usize;
        // The −z row, the tile's own rows, the +z row.
        fn row(
            out: &mut [f64; HALO_CELLS],
            hz: usize,
            src: Option<&[f64; TILE_CELLS]>,
            sz: usize,
            boundary: f64,
        ) {
            let t = TILE as usize;
            let dst = &mut out[hz * 10 + 1..hz * 10 + 1 + t];
            match src {
                Some(d) => dst.copy_from_slice(&d[sz * t..sz * t + t]),
                None => dst.fill(boundary),
            }
        }
        row(out, 0, get(1), t - 1, boundary);
        for z in 0..t {
            row(out, z + 1, get(4), z, boundary);
        }
        row(out, t + 1, get(7), 0, boundary);
        // −x and +x columns, and the corners.
        for (hz, sz, left, right) in [(0usize, t - 1, 0usize, 2usize), (t + 1, 0, 6, 8)] {
            out[hz * 10] = get(left).map_or(boundary, |d| d[sz * t + t - 1]);
            out[hz * 10 + 9] = get(right).map_or(boundary, |d| d[sz * t]);
        }
        let (l, r) = (get(3), get(5));
        for z in 0..t {
            out[(z + 1) * 10] = l.map_or(boundary, |d| d[z * t + t - 1]);
            out[(z + 1) * 10 + 9] = r.map_or(boundary, |d| d[z * t]);
        }
    }
}

/// `v` as little-endian bytes: the values themselves on a little-endian
/// machine, else converted into `scratch`.
fn le_bytes<'a>(v: &'a [f64], scratch: &'a mut [u8]) -> &'a [u8] {
    if cfg!(target_endian = "little") {
        bytemuck::cast_slice(v)
    } else {
        for (i, x) in v.iter().enumerate() {
            scratch[i * 8..i * 8 + 8].copy_from_slice(&x.to_le_bytes());
        }
        &scratch[..v.len() * 8]
    }
}

/// What every tile of a step shares.
pub(super) struct StepContext {
    pub(super) dt: f64,
    /// Identifies the step to the per-thread VMs (prepared once per step).
    pub(super) serial: u64,
    pub(super) seed: u64,
    pub(super) tick: u64,
    pub(super) default_bound: f64,
    pub(super) world_columns: Option<(glam::IVec2, glam::IVec2)>,
}

/// Run one script's passes over the work set. Returns, for each channel it
/// wrote (index in its spec), the dense data after the step.
pub(super) fn run_script(
    s: &Loaded,
    base: &ChannelStore,
    ws: &WorkSet,
    ctx: &StepContext,
    scratch: &mut StepScratch,
) -> Result<Vec<usize>, SimError> {
    let dt = ctx.dt;
    let stamp = StepStamp {
        dt,
        serial: ctx.serial,
        key: StepKey::new(ctx.seed, ctx.tick, &s.spec.name),
    };
    let n = s.spec.channels.len();
    // Dense previous generation of every channel this script uses, gathered
    // in parallel into the reused buffers.
    let StepScratch { data, outs } = scratch;
    data.resize(ws.tiles.len() * n, [0.0; TILE_CELLS]);
    data.par_chunks_mut(n)
        .zip(ws.tiles.par_iter())
        .for_each(|(d, &t)| {
            for (d, &id) in d.iter_mut().zip(&s.ids) {
                *d = base.get(t, id).copied().unwrap_or([0.0; TILE_CELLS]);
            }
        });
    let mut written = vec![false; n];
    for (pi, pass) in s.spec.passes.iter().enumerate() {
        let (read_idx, write_idx) = (pass.read_idx.as_slice(), pass.write_idx.as_slice());
        let data_ref = &*data;
        let nw = write_idx.len();
        outs.resize(ws.active.len() * nw, [0.0; TILE_CELLS]);
        let failed = crate::sim::LowestError::new();
        outs.par_chunks_mut(nw).enumerate().for_each_init(
            || (vec![[0.0f64; HALO_CELLS]; n], vec![[0.0f64; TILE_CELLS]; n]),
            |(reads, writes), (k, out)| {
                failed.run(k, || -> Result<(), SimError> {
                    for &i in read_idx {
                        ws.gather(k, (data_ref, n, i), s.boundary[i], &mut reads[i]);
                    }
                    let w = ws.active[k] as usize;
                    for &i in write_idx {
                        writes[i] = data_ref[w * n + i];
                    }
                    let t = ws.tiles[w];
                    match &s.kernel {
                        Kernel::Native(kern) => kern.run(pi, dt, &s.params, reads, writes),
                        Kernel::Lua => {
                            let io = PassChannels {
                                pass: pi,
                                reads: read_idx,
                                writes: write_idx,
                            };
                            run_lua(s, io, t, stamp, reads, writes)?
                        }
                    }
                    for (j, &i) in write_idx.iter().enumerate() {
                        out[j] = writes[i];
                    }
                    Ok(())
                });
            },
        );
        failed.result()?;
        // Commit the pass into the dense generation (double buffering: every
        // tile of this pass read the previous values).
        for (k, out) in outs.chunks(nw).enumerate() {
            let w = ws.active[k] as usize;
            for (j, &i) in write_idx.iter().enumerate() {
                data[w * n + i] = out[j];
            }
        }
        for &i in write_idx {
            written[i] = true;
        }
    }
    // Reject blow-ups and out-of-bound values before they reach the world.
    for i in (0..n).filter(|&i| written[i]) {
        let nonneg = s.nonneg.contains(&i);
        let name = &s.spec.channels[i];
        let (lo, hi, why) = match s.spec.ranges.iter().find(|r| &r.0 == name) {
            Some(r) => (r.1, r.2, "its declared range".to_string()),
            None => (
                -ctx.default_bound,
                ctx.default_bound,
                format!(
                    "{DEFAULT_BOUND_HEIGHTS} world heights of at least {MIN_BOUND_HEIGHT}; declare `ranges` to change it"
                ),
            ),
        };
        let d = |w: u32| &data[w as usize * n + i];
        let out_of_bounds = ws.active.par_iter().find_map_first(|&w| {
            match d(w).iter().enumerate().find(|(_, x)| **x < lo || **x > hi) {
                Some((c, x)) if x.is_finite() => Some((w, c, *x)),
                _ => None,
            }
        });
        if let Some((w, c, x)) = out_of_bounds {
            let t = ws.tiles[w as usize];
            let column = glam::IVec2::new(
                t.x * TILE + (c as i32 % TILE),
                t.y * TILE + (c as i32 / TILE),
            );
            // A column of the ring around the world is nowhere a user can
            // look: say what it is (long-run probe: snow suspended at
            // "column (-8, 48)" of a world from 0 to 96).
            let ring = ctx
                .world_columns
                .is_some_and(|(lo, hi)| column.cmplt(lo).any() || column.cmpge(hi).any());
            let why = if ring {
                format!(
                    "{why}; the column lies in the ring of tiles around the world, where what leaves the world collects"
                )
            } else {
                why
            };
            return Err(SimError::OutOfBounds {
                script: s.spec.name.clone(),
                channel: name.clone(),
                place: crate::sim::Place::Column(column.x, column.y),
                value: x,
                bound: (lo, hi),
                why,
            });
        }
        let unstable = ws.active.par_iter().find_map_first(|&w| {
            d(w).iter()
                .enumerate()
                .find(|(_, x)| !x.is_finite() || (nonneg && **x < -1e-9))
                .map(|(c, x)| (w, c, *x))
        });
        if let Some((w, c, x)) = unstable {
            let t = ws.tiles[w as usize];
            return Err(SimError::Unstable {
                script: s.spec.name.clone(),
                kind: if x.is_finite() {
                    Rejection::Negative
                } else {
                    Rejection::NotFinite
                },
                // A negative value in a `nonnegative` channel is named as
                // such: it may be a plain write, not an unstable step
                // (regression, fuzzing: "reduce dt" for `c.w[i] = -1`).
                msg: format!(
                    "channel '{}' = {x} at column ({}, {}){}",
                    s.spec.channels[i],
                    t.x * TILE + (c as i32 % TILE),
                    t.y * TILE + (c as i32 / TILE),
                    if x.is_finite() {
                        ", below 0 in a channel declared nonnegative (a write of a negative value, or a step too large: reduce dt or enable sub-stepping)"
                    } else {
                        // A kernel may have written it: not only an
                        // unstable step (docs walk).
                        ", not a finite number: a kernel wrote it, or the step went unstable (then reduce dt or enable sub-stepping)"
                    }
                ),
            });
        }
    }
    Ok((0..n).filter(|&i| written[i]).collect())
}

/// One tile of one pass in this thread's VM of the script (loaded on first
/// use, prepared once per step).
fn run_lua(
    s: &Loaded,
    io: PassChannels<'_>,
    t: TileCoord,
    stamp: StepStamp,
    reads: &[[f64; HALO_CELLS]],
    writes: &mut [[f64; TILE_CELLS]],
) -> Result<(), SimError> {
    let PassChannels {
        pass,
        reads: read_idx,
        writes: write_idx,
    } = io;
    crate::sim::runtime::vms::with_vm(s.uid.get(), &s.src, s.limits, |vm, prepared| {
        stamp.prepare(vm, prepared, (&s.spec, &s.params, &[]))?;
        // Luau buffers hold little-endian f64s: on a little-endian machine
        // the values' own bytes are copied straight in and out.
        let mut rb = [0u8; HALO_CELLS * 8];
        let mut wb = [0u8; TILE_CELLS * 8];
        vm.run(pass, &s.spec.passes[pass].name, t.x, t.y, |vm| {
            for &i in read_idx {
                vm.read_buffer(i)
                    .write_bytes(0, le_bytes(&reads[i], &mut rb));
            }
            for &i in write_idx {
                vm.write_buffer(i)
                    .write_bytes(0, le_bytes(&writes[i], &mut wb));
            }
        })?;
        for &i in write_idx {
            let bytes: [u8; TILE_CELLS * 8] = vm.write_buffer(i).read_bytes(0);
            if cfg!(target_endian = "little") {
                bytemuck::cast_slice_mut::<f64, u8>(&mut writes[i]).copy_from_slice(&bytes);
            } else {
                for (k, w) in writes[i].iter_mut().enumerate() {
                    *w = f64::from_le_bytes(bytes[k * 8..k * 8 + 8].try_into().expect("8 bytes"));
                }
            }
        }
        Ok(())
    })
}
