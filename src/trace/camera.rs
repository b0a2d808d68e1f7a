//! The pinhole camera, exactly as `DESIGN.md` §3 defines it, in `f64`.
//!
//! Pixel (i, j), i right and j down, looks along
//! `normalize(f + a·r + b·u)` with `a = ((i+0.5)/W·2−1)·tan(fov/2)·W/H`,
//! `b = (1−(j+0.5)/H·2)·tan(fov/2)`, `f = normalize(target − eye)`,
//! `r = normalize(f × Y)` and `u = r × f`.

use glam::DVec3;
use thiserror::Error;

/// Fields of view every input accepts (`--fov`, `[camera] fov`, `POST
/// /camera`), in degrees: one range for all (regression, hostile probe:
/// the world config took anything in (0, 180), 1e-300 included).
pub const MIN_FOV: f64 = 0.01;
/// See [`MIN_FOV`].
pub const MAX_FOV: f64 = 179.0;

/// Why a camera was rejected.
#[derive(Debug, Error, PartialEq)]
pub enum CameraError {
    /// A coordinate is NaN or infinite.
    #[error("camera {0} has a NaN or infinite coordinate")]
    NotFinite(&'static str),
    /// Eye and target coincide, or are too close for a direction.
    #[error(
        "camera eye equals its target (or lies within 1e-6 of it): the view direction is undefined"
    )]
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

/// The unit direction from `eye` to `target` (both finite), or why there is
/// none: they coincide or lie within 1e-6 of each other (regression,
/// hostile probe: a target 1e-200 from the eye passed the equality check,
/// and its direction, normalised from an underflowed length, was NaN: a
/// blank image with exit 0), or the view is vertical, so that "right" is
/// undefined. Every camera check (flags, configs, `POST /camera`) uses it.
pub fn view_direction(eye: DVec3, target: DVec3) -> Result<DVec3, CameraError> {
    let d = target - eye;
    // Coordinates near f64's limits can overflow the difference.
    if !d.is_finite() {
        return Err(CameraError::NotFinite("view direction"));
    }
    if d.length() < 1e-6 {
        return Err(CameraError::EyeIsTarget);
    }
    let f = d.normalize();
    if !(f.is_finite() && f.cross(DVec3::Y).length() >= 1e-9) {
        return Err(CameraError::Vertical);
    }
    Ok(f)
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
        let f = view_direction(eye, target)?;
        if !(fov_deg > 0.0 && fov_deg < 180.0) {
            return Err(CameraError::BadFov(fov_deg));
        }
        if width == 0 || height == 0 || width > 16384 || height > 16384 {
            return Err(CameraError::BadSize(width, height));
        }
        let r = f.cross(DVec3::Y).normalize();
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
        self.direction_from(self.column_factor(x), self.row_factor(y))
    }

    /// The horizontal part of [`direction_at`](Self::direction_at) for
    /// image column `x`: a frame computes it once per column (and
    /// [`row_factor`](Self::row_factor) once per row), where every pixel
    /// computed both, with their divisions, before.
    #[inline]
    pub fn column_factor(&self, x: f64) -> f64 {
        let w = self.width as f64;
        let h = self.height as f64;
        (x / w * 2.0 - 1.0) * self.tan_half * w / h
    }

    /// The vertical part of [`direction_at`](Self::direction_at) for image
    /// row `y`.
    #[inline]
    pub fn row_factor(&self, y: f64) -> f64 {
        let h = self.height as f64;
        (1.0 - y / h * 2.0) * self.tan_half
    }

    /// The normalised direction of column factor `a` and row factor `b`:
    /// `direction_from(column_factor(x), row_factor(y))` is
    /// `direction_at(x, y)`, bit for bit.
    #[inline(always)]
    pub fn direction_from(&self, a: f64, b: f64) -> DVec3 {
        (self.f + a * self.r + b * self.u).normalize()
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// Regression (hostile probe): a target a hair from the eye (1e-200,
    /// whose squared length underflows) gave a NaN direction, so every ray
    /// missed; it is refused as the same point, for `POST /camera` and
    /// configs too, which build a `Camera`.
    #[test]
    fn a_target_a_hair_from_the_eye_is_refused_not_a_nan_direction() {
        let eye = DVec3::new(0.0, 20.0, 10.0);
        for d in [1e-200, 1e-160, 1e-7] {
            let t = eye + DVec3::new(d, 0.0, 0.0);
            assert!(
                matches!(
                    Camera::new(eye, t, 50.0, 8, 8),
                    Err(CameraError::EyeIsTarget)
                ),
                "{d}"
            );
        }
        let f = view_direction(eye, eye + DVec3::new(1e-5, 0.0, 0.0)).unwrap();
        assert!((f - DVec3::X).length() < 1e-12, "{f}");
        assert!(matches!(
            view_direction(eye, eye + DVec3::new(1e-12, 5.0, 0.0)),
            Err(CameraError::Vertical)
        ));
    }

    /// A frame's directions, built from per-column and per-row factors,
    /// are the per-pixel formula of `DESIGN.md` §3 bit for bit (depth
    /// output and the Embree peer depend on it), for odd sizes, wide and
    /// narrow fields of view and jittered sample positions.
    #[test]
    fn split_factors_give_the_per_pixel_formula_bit_for_bit() {
        let views = [
            (
                DVec3::new(-286.6, 1185.0, -244.4),
                DVec3::new(1024.0, 128.0, 1024.0),
                50.0,
                960,
                540,
            ),
            (
                DVec3::new(3.0, 2.0, 1.0),
                DVec3::new(0.0, 0.5, -7.0),
                1.5,
                33,
                17,
            ),
            (
                DVec3::new(0.1, 0.2, 0.3),
                DVec3::new(40.0, -3.0, 2.0),
                170.0,
                7,
                1024,
            ),
        ];
        for (eye, target, fov, w, h) in views {
            let cam = Camera::new(eye, target, fov, w, h).unwrap();
            let (wf, hf) = (w as f64, h as f64);
            for j in (0..h).step_by(5) {
                for i in (0..w).step_by(3) {
                    for (jx, jy) in [
                        (0.5, 0.5),
                        (0.0, 0.999),
                        (0.7548776662466927, 0.5698402909980532),
                    ] {
                        let (x, y) = (i as f64 + jx, j as f64 + jy);
                        let a = (x / wf * 2.0 - 1.0) * cam.tan_half * wf / hf;
                        let b = (1.0 - y / hf * 2.0) * cam.tan_half;
                        let want = (cam.f + a * cam.r + b * cam.u).normalize();
                        let got = cam.direction_from(cam.column_factor(x), cam.row_factor(y));
                        assert_eq!(
                            got.to_array().map(f64::to_bits),
                            want.to_array().map(f64::to_bits)
                        );
                        assert_eq!(cam.direction_at(x, y), want);
                    }
                }
            }
        }
    }
}
