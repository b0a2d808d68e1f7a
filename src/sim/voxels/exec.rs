//! One voxel script's step over its candidate bricks: the working set (the
//! previous generation of every brick the candidates can see, held densely
//! and addressed by small indices), the parallel passes that gather each
//! candidate's halo and run its kernel (Lua or native) into per-candidate
//! outputs, and the commit of each pass with validation. Every pass reads
//! only the previous generation and commits in candidate order, so the
//! result does not depend on the thread count.

use std::sync::Arc;

use glam::IVec3;
use rayon::prelude::*;
use rustc_hash::FxHashMap;

use super::channels::{VoxelChannelId, VoxelChannels};
use super::halo::{SELF, gather, keep_outside, neighbour_offset, wall_off};
use super::memory::step_fits;
use super::native::{NativeBrick, VoxelNativeKernel};
use super::step::BOUNDARY;
use crate::sim::runtime::vms::{PassChannels, StepStamp};
use crate::sim::script::{MAT, VOXEL_CELLS, VOXEL_HALO};
use crate::sim::{Limits, Rejection, ScriptSource, ScriptSpec, SimError};
use crate::world::{BRICK_EDGE, BrickStore};

/// How a voxel script's kernels run.
#[derive(Clone)]
pub enum VoxelKernel {
    /// The script's Lua kernels, in a sandboxed VM per worker.
    Lua,
    /// A native reference with the same declarations.
    Native(Arc<dyn VoxelNativeKernel>),
}

/// What a step needs to know of one loaded script.
pub(super) struct Job<'a> {
    pub uid: u64,
    pub src: &'a ScriptSource,
    pub spec: &'a ScriptSpec,
    pub params: &'a [f64],
    pub channel_ids: &'a [VoxelChannelId],
    pub material_ids: &'a [u8],
    pub limits: Limits,
    pub kernel: &'a VoxelKernel,
}

/// Sentinel neighbour index: outside the simulated bounds.
const OUTSIDE: u32 = u32::MAX;

/// The previous generation of every brick the candidates can see, dense.
pub(super) struct Working {
    /// Candidate bricks, sorted; they are the first entries of `bricks`.
    pub cands: Vec<IVec3>,
    /// Materials of every brick in reach (candidates first, then their
    /// other neighbours).
    pub mats: Vec<[u8; VOXEL_CELLS]>,
    /// Each script channel's values over the same bricks (zero where absent).
    pub chans: Vec<Vec<[f32; VOXEL_CELLS]>>,
    /// The candidates' materials before the step.
    orig: Vec<[u8; VOXEL_CELLS]>,
    /// Each candidate's 27 neighbours, as indices into `bricks`.
    nbr: Vec<[u32; 27]>,
}

impl Working {
    fn build(
        store: &BrickStore,
        channels: &VoxelChannels,
        (spec, channel_ids): (&ScriptSpec, &[VoxelChannelId]),
        cands: &[IVec3],
        (lo, hi): (IVec3, IVec3),
    ) -> Result<Self, SimError> {
        let inside = |b: IVec3| b.cmpge(lo).all() && b.cmplt(hi).all();
        let mut index: FxHashMap<IVec3, u32> = FxHashMap::default();
        index.reserve(cands.len() * 2);
        let mut bricks: Vec<IVec3> = cands.to_vec();
        for (i, &b) in cands.iter().enumerate() {
            index.insert(b, i as u32);
        }
        let nbr: Vec<[u32; 27]> = cands
            .iter()
            .map(|&b| {
                std::array::from_fn(|n| {
                    let nb = b + neighbour_offset(n);
                    if !inside(nb) {
                        return OUTSIDE;
                    }
                    *index.entry(nb).or_insert_with(|| {
                        bricks.push(nb);
                        (bricks.len() - 1) as u32
                    })
                })
            })
            .collect();
        step_fits(spec, channel_ids.len(), cands.len(), bricks.len())?;
        let mats: Vec<[u8; VOXEL_CELLS]> = bricks
            .par_iter()
            .map(|&b| {
                let mut d = [0u8; VOXEL_CELLS];
                store.read_dense(b, &mut d);
                d
            })
            .collect();
        let chans = channel_ids
            .iter()
            .map(|&id| {
                bricks
                    .par_iter()
                    .map(|&b| channels.get(id, b).copied().unwrap_or([0.0; VOXEL_CELLS]))
                    .collect()
            })
            .collect();
        Ok(Working {
            cands: cands.to_vec(),
            orig: mats[..cands.len()].to_vec(),
            mats,
            chans,
            nbr,
        })
    }

    /// Candidates (by index) whose materials the step changed.
    pub fn changed_mats(&self) -> impl Iterator<Item = usize> + '_ {
        (0..self.cands.len()).filter(|&i| self.mats[i] != self.orig[i])
    }

    /// Sum and absolute sum of channel `ch` over the candidates.
    fn sums(&self, ch: usize) -> (f64, f64) {
        self.chans[ch][..self.cands.len()]
            .iter()
            .flatten()
            .fold((0.0, 0.0), |(t, a), &v| {
                (t + v as f64, a + (v as f64).abs())
            })
    }

    fn neighbours<'w, T>(
        &self,
        ci: usize,
        data: &'w [[T; VOXEL_CELLS]],
    ) -> [Option<&'w [T; VOXEL_CELLS]>; 27] {
        let n = &self.nbr[ci];
        std::array::from_fn(|k| (n[k] != OUTSIDE).then(|| &data[n[k] as usize]))
    }
}

/// Every pass's outputs for `cands` candidates, in two buffers made once
/// per step: a material brick each, and as many channel bricks each as the
/// widest pass writes. A script that writes no channel gets no channel
/// buffer (growth probe: it got one a brick, 2 KiB each, which its step's
/// memory estimate did not count).
fn output_buffers(
    spec: &ScriptSpec,
    cands: usize,
) -> (Vec<[u8; VOXEL_CELLS]>, Vec<[f32; VOXEL_CELLS]>) {
    (
        vec![[0u8; VOXEL_CELLS]; cands],
        vec![[0.0f32; VOXEL_CELLS]; cands * spec.widest_writes()],
    )
}

/// A pass's output for one candidate: materials and written channels.
/// One brick's outputs of a pass: views into buffers made once per step
/// for every candidate (code-habits audit: a `Vec` was made for every
/// brick in every pass).
struct BrickOut<'a> {
    mat: &'a mut [u8; VOXEL_CELLS],
    chans: &'a mut [[f32; VOXEL_CELLS]],
}

/// Per-worker scratch: the halos and the byte image of one channel.
struct Scratch {
    mat: [u8; VOXEL_HALO],
    chans: Vec<[f32; VOXEL_HALO]>,
    bytes: Vec<u8>,
}

/// `f32`s as the little-endian bytes a Luau buffer holds.
fn to_le_bytes(src: &[f32], dst: &mut [u8]) {
    if cfg!(target_endian = "little") {
        dst.copy_from_slice(bytemuck::cast_slice(src));
    } else {
        for (d, v) in dst.chunks_exact_mut(4).zip(src) {
            d.copy_from_slice(&v.to_le_bytes());
        }
    }
}

fn from_le_bytes(src: &[u8], dst: &mut [f32]) {
    for (d, s) in dst.iter_mut().zip(src.chunks_exact(4)) {
        *d = f32::from_le_bytes([s[0], s[1], s[2], s[3]]);
    }
}

/// Where a voxel simulation runs: its bricks `[lo, hi)`, and the world's
/// voxels `[lo, hi)` within them (the last bricks of a world whose size is
/// not a multiple of 8 end past it).
#[derive(Clone, Copy, Debug)]
pub(super) struct Bounds {
    pub bricks: (IVec3, IVec3),
    pub voxels: (IVec3, IVec3),
}

impl Bounds {
    /// Whether the world ends on brick edges (its voxel box is its bricks'):
    /// then no brick holds voxels past it.
    fn aligned(&self) -> bool {
        self.voxels.0 == self.bricks.0 * BRICK_EDGE && self.voxels.1 == self.bricks.1 * BRICK_EDGE
    }
}

/// Run every pass of one script over `cands`; on success the working set
/// holds the new generation of the candidates.
pub(super) fn run_script(
    job: &Job<'_>,
    store: &BrickStore,
    channels: &VoxelChannels,
    cands: &[IVec3],
    bounds: Bounds,
    valid: &[bool; 256],
    stamp: StepStamp,
) -> Result<Working, SimError> {
    let dt = stamp.dt;
    let spec = job.spec;
    let mut work = Working::build(
        store,
        channels,
        (spec, job.channel_ids),
        cands,
        bounds.bricks,
    )?;
    let nch = job.channel_ids.len();
    let conserved: Vec<usize> = spec
        .conserved
        .iter()
        .filter_map(|c| spec.channels.iter().position(|x| x == c))
        .collect();
    let before: Vec<(f64, f64)> = conserved.iter().map(|&i| work.sums(i)).collect();
    let (mut mats_out, mut chans_out) = output_buffers(spec, cands.len());
    for (pi, pass) in spec.passes.iter().enumerate() {
        let writes_mat = pass.writes.iter().any(|w| w == MAT);
        let (ridx, widx) = (pass.read_idx.as_slice(), pass.write_idx.as_slice());
        // The pass's channel outputs, `width` to a candidate (none where
        // it writes only materials: no buffer is made for them).
        let width = widx.len();
        let w = &work;
        let aligned = bounds.aligned();
        let failed = crate::sim::LowestError::new();
        let mut no_chans: Vec<&mut [[f32; VOXEL_CELLS]]> = Vec::new();
        let chans_of: Vec<&mut [[f32; VOXEL_CELLS]]> = if width == 0 {
            no_chans.resize_with(cands.len(), Default::default);
            no_chans
        } else {
            chans_out[..cands.len() * width].chunks_mut(width).collect()
        };
        mats_out
            .par_iter_mut()
            .zip(chans_of)
            .map(|(mat, chans)| BrickOut { mat, chans })
            .enumerate()
            .for_each_init(
                || Scratch {
                    mat: [0; VOXEL_HALO],
                    chans: vec![[0.0; VOXEL_HALO]; nch],
                    bytes: vec![0; VOXEL_HALO * 4],
                },
                |sc, (ci, mut out)| {
                    failed.run(ci, || -> Result<(), SimError> {
                        let b = cands[ci];
                        gather(&w.neighbours(ci, &w.mats), BOUNDARY, &mut sc.mat);
                        if !aligned {
                            wall_off(b, bounds.voxels, BOUNDARY, &mut sc.mat);
                        }
                        for &i in ridx {
                            let nbr = w.neighbours(ci, &w.chans[i]);
                            // Outside the bounds a channel reads 0.
                            let nbr = nbr.map(|n| Some(n.unwrap_or(&ZERO_F32)));
                            gather(&nbr, 0.0, &mut sc.chans[i]);
                            if !aligned {
                                wall_off(b, bounds.voxels, 0.0, &mut sc.chans[i]);
                            }
                        }
                        let own = &w.mats[nbr_self(w, ci)];
                        *out.mat = *own;
                        for (j, &i) in widx.iter().enumerate() {
                            out.chans[j] = w.chans[i][nbr_self(w, ci)];
                        }
                        let ran = match job.kernel {
                            VoxelKernel::Native(k) => {
                                k.run(
                                    pi,
                                    NativeBrick {
                                        brick: b,
                                        dt,
                                        params: job.params,
                                        materials: job.material_ids,
                                        mat: &sc.mat,
                                        reads: &sc.chans,
                                        mat_out: out.mat,
                                        writes: out.chans,
                                    },
                                );
                                Ok(())
                            }
                            VoxelKernel::Lua => {
                                let io = PassChannels {
                                    pass: pi,
                                    reads: ridx,
                                    writes: widx,
                                };
                                run_lua(job, io, sc, &mut out, b, stamp)
                            }
                        };
                        // Past the world's edge (inside its last bricks):
                        // materials and channels keep what they held.
                        if !aligned {
                            keep_outside(b, bounds.voxels, own, out.mat);
                            for (j, &i) in widx.iter().enumerate() {
                                let before = &w.chans[i][nbr_self(w, ci)];
                                keep_outside(b, bounds.voxels, before, &mut out.chans[j]);
                            }
                        }
                        ran
                    });
                },
            );
        failed.result()?;
        // Commit the pass (every brick of it read the previous generation).
        for (ci, mat) in mats_out.iter().enumerate() {
            let chans = &chans_out[ci * width..(ci + 1) * width];
            let b = cands[ci];
            if writes_mat {
                if let Some(&bad) = mat.iter().find(|&&v| !valid[v as usize]) {
                    return Err(SimError::Runtime {
                        script: spec.name.clone(),
                        pass: pass.name.clone(),
                        at: crate::sim::CallSite::Brick(b.to_array()),
                        line: None,
                        msg: format!("wrote material id {bad}, which is not registered"),
                    });
                }
                work.mats[ci] = *mat;
            }
            for (j, &i) in widx.iter().enumerate() {
                let v = &chans[j];
                check_channel(spec, i, b, v)?;
                work.chans[i][ci] = *v;
            }
        }
    }
    for (k, &i) in conserved.iter().enumerate() {
        let (after, abs_after) = work.sums(i);
        let (was, abs_was) = before[k];
        let tol = 1e-5 * (abs_was.max(abs_after) + 1.0);
        if (after - was).abs() > tol {
            return Err(SimError::Unstable {
                script: spec.name.clone(),
                kind: Rejection::Drift,
                msg: format!(
                    "conserved channel '{}' drifted from {was} to {after} in one step (tolerance {tol:.3e}): the step's writes do not conserve it",
                    spec.channels[i]
                ),
            });
        }
    }
    Ok(work)
}

const ZERO_F32: [f32; VOXEL_CELLS] = [0.0; VOXEL_CELLS];

/// Index of candidate `ci` itself in the working set.
fn nbr_self(w: &Working, ci: usize) -> usize {
    w.nbr[ci][SELF] as usize
}

/// Values written to channel `i` of brick `b` must be finite and within the
/// channel's declared range.
fn check_channel(
    spec: &ScriptSpec,
    i: usize,
    b: IVec3,
    v: &[f32; VOXEL_CELLS],
) -> Result<(), SimError> {
    if let Some((c, x)) = v.iter().enumerate().find(|(_, x)| !x.is_finite()) {
        return Err(SimError::Unstable {
            script: spec.name.clone(),
            kind: Rejection::NotFinite,
            msg: format!(
                "channel '{}' = {x} at voxel {} of brick ({}, {}, {}), not a finite number: a kernel wrote it, or the step went unstable",
                spec.channels[i], c, b.x, b.y, b.z
            ),
        });
    }
    if spec.nonnegative.contains(&spec.channels[i])
        && let Some((c, x)) = v.iter().enumerate().find(|(_, x)| **x < -1e-9)
    {
        return Err(SimError::Unstable {
            script: spec.name.clone(),
            kind: Rejection::Negative,
            msg: format!(
                "channel '{}' = {x} at voxel {} of brick ({}, {}, {}), below 0 in a `nonnegative` channel",
                spec.channels[i], c, b.x, b.y, b.z
            ),
        });
    }
    if let Some(r) = spec.ranges.iter().find(|r| r.0 == spec.channels[i])
        && let Some((c, x)) = v
            .iter()
            .enumerate()
            .find(|(_, x)| (**x as f64) < r.1 || (**x as f64) > r.2)
    {
        return Err(SimError::OutOfBounds {
            script: spec.name.clone(),
            channel: r.0.clone(),
            place: crate::sim::Place::Voxel {
                index: c as u16,
                brick: b.to_array(),
            },
            value: *x as f64,
            bound: (r.1, r.2),
            why: "its declared range".into(),
        });
    }
    Ok(())
}

/// Cross one brick into this worker's VM for the script, run pass `pi`'s
/// kernel and read its outputs back: one buffer copy per channel each way.
fn run_lua(
    job: &Job<'_>,
    io: PassChannels<'_>,
    sc: &mut Scratch,
    out: &mut BrickOut<'_>,
    b: IVec3,
    stamp: StepStamp,
) -> Result<(), SimError> {
    let PassChannels {
        pass: pi,
        reads: ridx,
        writes: widx,
    } = io;
    let pass = &job.spec.passes[pi];
    let writes_mat = pass.writes.iter().any(|w| w == MAT);
    crate::sim::runtime::vms::with_vm(job.uid, job.src, job.limits, |vm, prepared| {
        stamp.prepare(vm, prepared, (job.spec, job.params, job.material_ids))?;
        vm.run_voxel(pi, &pass.name, b.to_array(), |vm| {
            let (mr, mw) = vm
                .material_buffers()
                .expect("a voxel VM has material buffers");
            mr.write_bytes(0, &sc.mat);
            mw.write_bytes(0, &out.mat[..]);
            for &i in ridx {
                to_le_bytes(&sc.chans[i], &mut sc.bytes);
                vm.read_buffer(i).write_bytes(0, &sc.bytes);
            }
            for (j, &i) in widx.iter().enumerate() {
                let bytes = &mut sc.bytes[..VOXEL_CELLS * 4];
                to_le_bytes(&out.chans[j], bytes);
                vm.write_buffer(i).write_bytes(0, bytes);
            }
        })?;
        if writes_mat {
            let (_, mw) = vm.material_buffers().expect("voxel VM");
            *out.mat = mw.read_bytes::<VOXEL_CELLS>(0);
        }
        for (j, &i) in widx.iter().enumerate() {
            let raw: [u8; VOXEL_CELLS * 4] = vm.write_buffer(i).read_bytes(0);
            from_le_bytes(&raw, &mut out.chans[j]);
        }
        Ok(())
    })
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::sim::ScriptVm;

    fn spec(channels: &str, writes: &str) -> ScriptSpec {
        let text = format!(
            "return {{ grid = \"voxels\", channels = {{ {channels} }},\n  passes = {{ {{ name = \"p\", reads = {{}}, writes = {{ {writes} }}, kernel = function() end }} }} }}"
        );
        let src = ScriptSource {
            name: "out".into(),
            text: text.into(),
        };
        let limits = Limits {
            memory: 16 << 20,
            instructions: 200_000,
            time: std::time::Duration::from_secs(2),
        };
        ScriptVm::load(&src, limits).unwrap().1
    }

    /// Regression (growth probe): a voxel script that writes only `mat`
    /// got an output channel per brick anyway.
    #[test]
    fn a_script_that_writes_no_channel_gets_no_channel_buffer() {
        let (mats, chans) = output_buffers(&spec("\"a\"", "\"mat\""), 10);
        assert_eq!((mats.len(), chans.len()), (10, 0));
        let (mats, chans) = output_buffers(&spec("\"a\", \"b\"", "\"a\", \"mat\", \"b\""), 10);
        assert_eq!((mats.len(), chans.len()), (10, 20));
    }
}
