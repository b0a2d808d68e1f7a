//! The pinhole camera, exactly as `DESIGN.md` §3 defines it, in `f64`.
//!
//! Pixel (i, j), i right and j down, looks along
//! `normalize(f + a·r + b·u)` with `a = ((i+0.5)/W·2−1)·tan(fov/2)·W/H`,
//! `b = (1−(j+0.5)/H·2)·tan(fov/2)`, `f = normalize(target − eye)`,
//! `r = normalize(f × Y)` and `u = r × f`.

use glam::DVec3;
use thiserror::Error;

/// Why a camera was rejected.
#[derive(Debug, Error, PartialEq)]
pub enum CameraError {
    /// A coordinate is NaN or infinite.
    #[error("camera {0} has a NaN or infinite coordinate")]
    NotFinite(&'static str),
    /// Eye and target coincide.
    #[error("camera eye equals its target: the view direction is undefined")]
    EyeIsTarget,
    /// The view is vertical, so "right" is undefined.
    #[error(
        "camera looks straight up or down: the right vector f × (0,1,0) is zero; tilt the target slightly"
    )]
    Vertical,
    /// Field of view out of range.
    #[error("fov must be in (0, 180) degrees, got {0}")]
    BadFov(f64),
    /// Image size out of range.
    #[error("image size must be 1..=16384 on each side, got {0}x{1}")]
    BadSize(u32, u32),
}

/// A validated pinhole camera.
///
/// ```
/// use brickworld::trace::Camera;
/// use glam::DVec3;
/// let cam = Camera::new(DVec3::ZERO, DVec3::new(0.0, 0.0, -1.0), 90.0, 3, 3).unwrap();
/// let centre = cam.direction(1, 1);
/// assert!((centre - DVec3::new(0.0, 0.0, -1.0)).length() < 1e-12);
/// ```
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Camera {
    /// Eye position (world voxels).
    pub eye: DVec3,
    /// Look-at point.
    pub target: DVec3,
    /// Vertical field of view, degrees.
    pub fov_deg: f64,
    /// Image width.
    pub width: u32,
    /// Image height.
    pub height: u32,
    f: DVec3,
    r: DVec3,
    u: DVec3,
    tan_half: f64,
}

impl Camera {
    /// Validate and build a camera.
    pub fn new(
        eye: DVec3,
        target: DVec3,
        fov_deg: f64,
        width: u32,
        height: u32,
    ) -> Result<Self, CameraError> {
        if !eye.is_finite() {
            return Err(CameraError::NotFinite("eye"));
        }
        if !target.is_finite() {
            return Err(CameraError::NotFinite("target"));
        }
        if eye == target {
            return Err(CameraError::EyeIsTarget);
        }
        if !(fov_deg > 0.0 && fov_deg < 180.0) {
            return Err(CameraError::BadFov(fov_deg));
        }
        if width == 0 || height == 0 || width > 16384 || height > 16384 {
            return Err(CameraError::BadSize(width, height));
        }
        let f = (target - eye).normalize();
        let r = f.cross(DVec3::Y);
        if r.length() < 1e-9 {
            return Err(CameraError::Vertical);
        }
        let r = r.normalize();
        let u = r.cross(f);
        Ok(Camera {
            eye,
            target,
            fov_deg,
            width,
            height,
            f,
            r,
            u,
            tan_half: (fov_deg.to_radians() * 0.5).tan(),
        })
    }

    /// The angle one pixel subtends at the image centre (radians, small
    /// angle): a cone of this angle per unit distance is a pixel's
    /// footprint, what level-of-detail selection compares cells with.
    pub fn pixel_angle(&self) -> f64 {
        2.0 * self.tan_half / self.height as f64
    }

    /// Normalised world direction of pixel (i, j) (through its centre).
    #[inline]
    pub fn direction(&self, i: u32, j: u32) -> DVec3 {
        self.direction_at(i as f64 + 0.5, j as f64 + 0.5)
    }

    /// Normalised world direction through image point `(x, y)` in pixels
    /// (pixel `(i, j)` covers `[i, i+1) × [j, j+1)`): for jittered samples.
    #[inline]
    pub fn direction_at(&self, x: f64, y: f64) -> DVec3 {
        let w = self.width as f64;
        let h = self.height as f64;
        let a = (x / w * 2.0 - 1.0) * self.tan_half * w / h;
        let b = (1.0 - y / h * 2.0) * self.tan_half;
        (self.f + a * self.r + b * self.u).normalize()
    }
}
