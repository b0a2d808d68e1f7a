//! Rays, hits and the local tracing frame.
//!
//! Tracers work in a *local frame*: voxel coordinates minus an integer anchor
//! shared by every structure built for a scene. Cameras and world positions
//! are `f64`; subtracting the anchor in `f64` before rounding to `f32` keeps
//! full precision ±10⁶ voxels (and more) from the origin.

use glam::{DVec3, IVec3, Vec3};

/// A ray in a structure's local frame.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Ray {
    /// Origin, local voxel coordinates.
    pub origin: Vec3,
    /// Direction; normalise it so that `t` is a distance.
    pub dir: Vec3,
}

impl Ray {
    /// A ray from `origin` along `dir`.
    pub fn new(origin: Vec3, dir: Vec3) -> Self {
        Ray { origin, dir }
    }
}

/// What every tracer reports for a hit.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Hit {
    /// Distance along the ray (in units of `dir`) at which the voxel is entered;
    /// 0 when the ray starts inside it.
    pub t: f32,
    /// The voxel hit, world coordinates.
    pub voxel: IVec3,
    /// Outward normal of the face entered, or zero when the ray starts inside.
    pub normal: IVec3,
    /// Material of the voxel (never 0).
    pub material: u8,
    /// Level of detail of the cell hit: 0 a voxel, `s` a cube of `2^s`
    /// voxels entered through `voxel` (see `world/mip.rs`).
    pub level: u8,
}

/// The integer anchor of a local frame.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Default)]
pub struct Frame {
    /// World voxel coordinate of local (0, 0, 0).
    pub anchor: IVec3,
}

impl Frame {
    /// World point to local `f32` coordinates.
    pub fn to_local(&self, p: DVec3) -> Vec3 {
        (p - self.anchor.as_dvec3()).as_vec3()
    }

    /// Local cell to world voxel.
    #[inline(always)]
    pub fn to_world(&self, cell: [i32; 3]) -> IVec3 {
        IVec3::from(cell) + self.anchor
    }

    /// A world-space ray in this frame (direction normalised in `f64`).
    pub fn ray(&self, origin: DVec3, dir: DVec3) -> Ray {
        Ray::new(self.to_local(origin), dir.normalize_or_zero().as_vec3())
    }
}
