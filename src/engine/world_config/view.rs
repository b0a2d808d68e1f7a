//! The second stage of a world config's view sections: `[camera]` (where
//! the engine looks, fixed, orbiting or flying), `[render]` (frame size,
//! tracer, level of detail and shading) and `[frames]` (where frames go and
//! how many are kept). Every error names the file, the field and the
//! reason, as in [`super::validate`].

use std::path::PathBuf;

use glam::DVec3;

use super::raw::{RawCamera, RawFrames, RawRender};
use super::validate::{Fields, every};
use super::{
    CameraMode, CameraSettings, DEFAULT_FRAMES_MB, DEFAULT_LOD, MAX_COORD, StreamSettings,
    WorldConfigError,
};

/// A camera coordinate: finite and within the command line's `--eye` bound.
fn coord(at: Fields, v: Option<[f64; 3]>, f: &str) -> Result<Option<DVec3>, WorldConfigError> {
    match v {
        Some(a) if a.iter().all(|x| x.is_finite() && x.abs() <= MAX_COORD) => {
            Ok(Some(DVec3::from(a)))
        }
        Some(a) => Err(at.err(
            f,
            format!("{a:?} must be finite and within ±1e9 voxels (as --eye)"),
        )),
        None => Ok(None),
    }
}

/// A camera period: at least 10 ms (a subnormal period made the camera's
/// phase infinite and no frame was drawn; regression).
fn period(at: Fields, p: f64, f: &str) -> Result<f64, WorldConfigError> {
    if !(0.01..=1e9).contains(&p) {
        return Err(at.err(
            f,
            format!(
                "{} must be from 0.01 to 1e9 seconds",
                crate::sim::fmt_num(p)
            ),
        ));
    }
    Ok(p)
}

/// `[camera]`: its movement, eye and target. `follows_region`: a streamed
/// world's region follows the camera, so the camera must be placed.
pub(super) fn camera(
    at: Fields,
    raw: Option<RawCamera>,
    follows_region: bool,
) -> Result<CameraSettings, WorldConfigError> {
    let err = |f: &str, r: String| at.err(f, r);
    let cam = raw.unwrap_or(RawCamera {
        mode: None,
        eye: None,
        target: None,
        fov: None,
        orbit_period_s: None,
        fly_to: None,
        fly_period_s: None,
        velocity: None,
    });
    let fov = cam.fov.unwrap_or(50.0);
    if !(crate::trace::MIN_FOV..=crate::trace::MAX_FOV).contains(&fov) {
        return Err(err(
            "camera.fov",
            format!("{} is outside 0.01..=179 degrees", crate::sim::fmt_num(fov)),
        ));
    }
    let mode = match cam.mode.as_deref().unwrap_or("fixed") {
        "fixed" => CameraMode::Fixed,
        "orbit" => CameraMode::Orbit {
            period_s: period(
                at,
                cam.orbit_period_s.unwrap_or(60.0),
                "camera.orbit_period_s",
            )?,
        },
        "fly" => {
            let p = period(at, cam.fly_period_s.unwrap_or(60.0), "camera.fly_period_s")?;
            let Some(to) = coord(at, cam.fly_to, "camera.fly_to")? else {
                return Err(err("camera.fly_to", "is needed with mode = \"fly\"".into()));
            };
            if cam.eye.is_none() {
                return Err(err("camera.eye", "is needed with mode = \"fly\"".into()));
            }
            CameraMode::Fly { to, period_s: p }
        }
        "line" => {
            let velocity = match cam.velocity {
                Some(a) if a.iter().all(|x| x.is_finite() && x.abs() <= 1e5) => DVec3::from(a),
                Some(a) => {
                    return Err(err(
                        "camera.velocity",
                        format!("{a:?} must be finite, at most 100000 voxels/s per axis"),
                    ));
                }
                None => {
                    return Err(err(
                        "camera.velocity",
                        "is needed with mode = \"line\"".into(),
                    ));
                }
            };
            if cam.eye.is_none() {
                return Err(err("camera.eye", "is needed with mode = \"line\"".into()));
            }
            CameraMode::Line { velocity }
        }
        other => {
            return Err(err(
                "camera.mode",
                format!("'{other}' is not fixed, orbit, fly or line"),
            ));
        }
    };
    let (eye, target) = (
        coord(at, cam.eye, "camera.eye")?,
        coord(at, cam.target, "camera.target")?,
    );
    if let (Some(e), Some(t)) = (eye, target)
        && let Err(why) = crate::trace::view_direction(e, t)
    {
        let why = match why {
            crate::trace::CameraError::Vertical => "is straight above or below camera.eye",
            _ => "equals camera.eye (or lies within 1e-6 of it)",
        };
        return Err(err("camera.target", why.into()));
    }
    match (eye, target) {
        (Some(_), None) => {
            return Err(err("camera.target", "is needed with camera.eye".into()));
        }
        (None, Some(_)) => {
            return Err(err("camera.eye", "is needed with camera.target".into()));
        }
        (None, None) if follows_region => {
            // The default view is the region's own: it would move with it.
            return Err(err(
                "camera.eye",
                "is needed when a streamed world's region follows the camera ([sim] radius)".into(),
            ));
        }
        _ => {}
    }
    Ok(CameraSettings {
        mode,
        eye,
        target,
        fov,
    })
}

/// `[render]`, validated.
pub(super) struct Render {
    pub(super) width: u32,
    pub(super) height: u32,
    pub(super) look: super::FrameLook,
}

/// `[render]`: frame size, tracer and shading. A streamed world's window
/// ends at the view distance: fog hides the edge by default.
pub(super) fn render(
    at: Fields,
    r: &RawRender,
    stream: Option<StreamSettings>,
) -> Result<Render, WorldConfigError> {
    let err = |f: &str, r: String| at.err(f, r);
    let dim = |v: Option<i64>, d: i64, f: &str| -> Result<u32, WorldConfigError> {
        let v = v.unwrap_or(d);
        if !(1..=8192).contains(&v) {
            return Err(err(f, format!("{v} is outside 1..=8192")));
        }
        Ok(v as u32)
    };
    let fog = match r.fog {
        Some(f) if f.is_finite() && (0.0..=1e6).contains(&f) => f as f32,
        Some(f) => {
            return Err(err(
                "render.fog",
                format!(
                    "{} is outside 0..=1000000 voxels (0 is no fog)",
                    crate::sim::fmt_num(f)
                ),
            ));
        }
        None => stream.map_or(0.0, |s| (s.view_distance * 0.5) as f32),
    };
    let tracer: crate::gpu::TracerChoice = r
        .tracer
        .as_deref()
        .unwrap_or("auto")
        .parse()
        .map_err(|e| err("render.tracer", e))?;
    let width = dim(r.width, 640, "render.width")?;
    let height = dim(r.height, 360, "render.height")?;
    let look = super::FrameLook {
        tracer,
        shadows: r.shadows.unwrap_or(true),
        ao: r.ao.unwrap_or(true),
        beam: r.beam.unwrap_or(false),
        aa: match r.aa.unwrap_or(1) {
            n @ 1..=16 => n as u32,
            n => {
                return Err(err(
                    "render.aa",
                    format!("{n} is outside 1..=16 samples per pixel (1 is no anti-aliasing)"),
                ));
            }
        },
        fog,
        lod: match r.lod {
            None => DEFAULT_LOD,
            Some(0.0) => 0.0,
            Some(c) if crate::config::lod_in_range(c) => c as f32,
            Some(c) => {
                return Err(err(
                    "render.lod",
                    format!(
                        "{} is not a cell footprint in pixels from {} to {} (0 turns level of detail off)",
                        crate::sim::fmt_num(c),
                        crate::config::MIN_LOD,
                        crate::config::MAX_LOD
                    ),
                ));
            }
        },
    };
    Ok(Render {
        width,
        height,
        look,
    })
}

/// `[frames]`, validated.
pub(super) struct Frames {
    pub(super) dir: PathBuf,
    pub(super) every: u64,
    pub(super) keep: usize,
    pub(super) max_bytes: u64,
}

/// `[frames]`: where frames go, how often, and how many are kept.
pub(super) fn frames(at: Fields, f: &RawFrames) -> Result<Frames, WorldConfigError> {
    let err = |field: &str, r: String| at.err(field, r);
    Ok(Frames {
        dir: PathBuf::from(f.dir.clone().unwrap_or_else(|| "frames".into())),
        every: every(at, f.every, 10, "frames.every")?,
        keep: match f.keep.unwrap_or(200) {
            k @ 1..=1_000_000 => k as usize,
            k => return Err(err("frames.keep", format!("{k} is outside 1..=1000000"))),
        },
        max_bytes: match f.max_mb.unwrap_or(DEFAULT_FRAMES_MB) {
            m if m.is_finite() && (1.0..=1_048_576.0).contains(&m) => (m * 1048576.0) as u64,
            m => {
                return Err(err(
                    "frames.max_mb",
                    format!("{} is outside 1..=1048576 MiB", crate::sim::fmt_num(m)),
                ));
            }
        },
    })
}
