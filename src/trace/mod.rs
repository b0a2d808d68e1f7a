//! Ray tracing: the exact DDA, three interchangeable CPU tracers behind the
//! [`Tracer`] trait, the pinhole camera and the tiled renderer.
//!
//! | tracer | structure | traversal |
//! |---|---|---|
//! | [`DenseGrid`] | one bit per voxel + material bytes | Amanatides–Woo DDA |
//! | [`Svo`] | flat ESVO child descriptors | parent stack per scale |
//! | [`BrickmapTracer`] | occupancy layer → brick grid → bricks | stackless 3-level DDA |
//!
//! All three share [`dda::DdaRay`], so they agree on every ray: same voxel,
//! same face, same `t`.

mod ao;
mod beam;
mod brickmap;
mod camera;
pub mod dda;
mod dense;
#[cfg(test)]
mod level_walk;
mod lod;
mod output;
mod ray;
mod render;
mod svo;

use std::fmt;
use std::str::FromStr;

use glam::IVec3;
use thiserror::Error;

use crate::world::Palette;

pub use ao::{AO_STRENGTH, face_ao};
pub use beam::{BEAM, beam_of, ray_start};
pub use brickmap::BrickmapTracer;
pub use camera::{Camera, CameraError, MAX_FOV, MIN_FOV, view_direction};
pub use dense::DenseGrid;
pub use lod::lod_level;
pub use output::{write_npy, write_png};
pub use ray::{Frame, Hit, Ray};
pub use render::{
    RenderOptions, RenderOutput, Shading, jitter_sample, render, supersample, trace_hits,
};
pub use svo::Svo;

/// Errors building a tracing structure.
#[derive(Debug, Error)]
pub enum TraceError {
    /// The dense grid would exceed its memory limit.
    #[error("dense grid of {}x{}x{} voxels needs {}, over the limit of {} (raise --dense-limit-mib or use svo/brickmap)", dims.x, dims.y, dims.z, crate::scene::budget::human(*bytes), crate::scene::budget::human(*limit))]
    DenseTooLarge {
        /// Grid size in voxels.
        dims: IVec3,
        /// Bytes needed.
        bytes: u64,
        /// Limit in bytes.
        limit: u64,
    },
    /// The dense grid is under its limit but over the memory there is.
    #[error("dense grid of {}x{}x{} voxels needs {}; {} is available (use svo/brickmap)", dims.x, dims.y, dims.z, crate::scene::budget::human(*bytes), crate::scene::budget::human(*available))]
    DenseOutOfMemory {
        /// Grid size in voxels.
        dims: IVec3,
        /// Bytes needed.
        bytes: u64,
        /// Bytes available.
        available: u64,
    },
    /// The brick grid could not be built.
    #[error(transparent)]
    World(#[from] crate::world::WorldError),
}

/// A CPU ray tracer over one structure.
pub trait Tracer: Sync {
    /// Short name: `dense`, `svo` or `brickmap`.
    fn name(&self) -> &'static str;
    /// The local frame rays must be expressed in.
    fn frame(&self) -> Frame;
    /// First solid voxel along `ray` with `t ≤ t_max`.
    fn trace(&self, ray: &Ray, t_max: f32) -> Option<Hit>;
    /// First cell solid at the level of detail its footprint allows, with
    /// `k = C ·` pixel angle; `k = 0` is [`trace`](Self::trace). Tracers
    /// without levels (dense, svo) trace exactly.
    fn trace_lod(&self, ray: &Ray, t_max: f32, k: f32) -> Option<Hit> {
        let _ = k;
        self.trace(ray, t_max)
    }
    /// [`trace_lod`](Self::trace_lod) for a ray that meets nothing before
    /// `t_start` (a beam start): the same answer, sooner. The default
    /// ignores the start.
    fn trace_from(&self, ray: &Ray, t_start: f32, t_max: f32, k: f32) -> Option<Hit> {
        let _ = t_start;
        self.trace_lod(ray, t_max, k)
    }
    /// [`trace_lod`](Self::trace_lod) for a ray whose start lies `skipped`
    /// voxels along from the eye (a far eye's ray, started where it enters
    /// the exact range): the footprint is measured from the eye. Tracers
    /// without levels ignore `skipped`.
    fn trace_skipped(&self, ray: &Ray, t_max: f32, k: f32, skipped: f32) -> Option<Hit> {
        let _ = skipped;
        self.trace_lod(ray, t_max, k)
    }
    /// A distance before which every ray within `spread` (tangent of the
    /// half-angle) of `centre` meets nothing, at level of detail `k`; 0
    /// (the default) when the tracer cannot say.
    fn beam_start(&self, centre: &Ray, spread: f32, k: f32) -> f32 {
        let _ = (centre, spread, k);
        0.0
    }
    /// For a level-of-detail hit on a cell of 2 or 4 voxels, the colours
    /// of its exposed voxel faces summed per direction (an index of
    /// [`crate::world::FACE_DIRS`]), for the directions in `facing` (bit
    /// `d`: the faces that can look at the viewer), so that it can be shaded
    /// as the average of what it holds; `None` for voxel hits, coarser
    /// cells and tracers without levels.
    fn coarse_faces(&self, hit: &Hit, facing: u8, palette: &Palette) -> Option<FaceSums> {
        let _ = (hit, facing, palette);
        None
    }
    /// Whether local voxel `c` is solid (for ambient occlusion). The
    /// default asks [`trace`](Self::trace) for a hit at `t = 0` from the
    /// voxel's centre; tracers with a direct lookup override it.
    fn solid_local(&self, c: [i32; 3]) -> bool {
        let o = glam::Vec3::new(c[0] as f32 + 0.5, c[1] as f32 + 0.5, c[2] as f32 + 0.5);
        self.trace(&Ray::new(o, glam::Vec3::X), 0.0).is_some()
    }
    /// Bytes of the structure as traced.
    fn bytes(&self) -> usize;
    /// Voxels (dense), descriptors (svo) or non-empty bricks (brickmap).
    fn nodes_or_bricks(&self) -> u64;
}

/// A coarse cell's exposed voxel faces, per direction of
/// [`crate::world::FACE_DIRS`]: how many there are and their colours
/// summed (RGB, 0–255 each). Integer sums: the order in which faces are
/// visited cannot change the average.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq)]
pub struct FaceSums {
    /// Exposed faces per direction.
    pub faces: [u32; 6],
    /// Their colours summed per direction.
    pub rgb: [[u32; 3]; 6],
}

/// Which tracer to use.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Hash, serde::Serialize)]
#[serde(rename_all = "lowercase")]
pub enum Structure {
    /// Dense bit grid.
    Dense,
    /// Sparse voxel octree.
    Svo,
    /// Brickmap.
    Brickmap,
}

impl Structure {
    /// All structures, in bench order.
    pub const ALL: [Structure; 3] = [Structure::Dense, Structure::Svo, Structure::Brickmap];

    /// The CLI name.
    pub fn name(self) -> &'static str {
        match self {
            Structure::Dense => "dense",
            Structure::Svo => "svo",
            Structure::Brickmap => "brickmap",
        }
    }
}

impl fmt::Display for Structure {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        f.write_str(self.name())
    }
}

impl FromStr for Structure {
    type Err = String;
    fn from_str(s: &str) -> Result<Self, String> {
        match s {
            "dense" => Ok(Structure::Dense),
            "svo" => Ok(Structure::Svo),
            "brickmap" => Ok(Structure::Brickmap),
            _ => Err(format!(
                "unknown structure '{s}' (expected dense, svo or brickmap)"
            )),
        }
    }
}
