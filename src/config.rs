//! Second stage of argument handling: raw CLI strings become validated,
//! typed settings. Every error names the flag at fault.

use std::path::{Path, PathBuf};

use glam::{DVec3, IVec3};
use thiserror::Error;

use crate::cli::{BenchTracersArgs, RenderArgs, SceneArgs, SimArgs, ViewArgs};
use crate::scene::{SceneSpec, View};
use crate::trace::Structure;

/// A flag with a bad value.
#[derive(Debug, Error, PartialEq, Eq)]
#[error("invalid {flag} '{value}': {reason}")]
pub struct ConfigError {
    /// The flag, e.g. `--size`.
    pub flag: &'static str,
    /// The value given.
    pub value: String,
    /// What is wrong with it.
    pub reason: String,
}

fn bad(flag: &'static str, value: &str, reason: impl Into<String>) -> ConfigError {
    ConfigError {
        flag,
        value: value.to_string(),
        reason: reason.into(),
    }
}

/// Largest procedural extent along x and z.
pub const MAX_XZ: i32 = 65536;
/// Largest procedural extent along y.
pub const MAX_Y: i32 = 4096;

/// A whole number in decimal, saturated to `i32` (so that one too large
/// for it is refused as out of range, not as "not a whole number").
fn whole_number(t: &str) -> Option<i32> {
    let digits = t.strip_prefix(['-', '+']).unwrap_or(t);
    if digits.is_empty() || !digits.bytes().all(|b| b.is_ascii_digit()) {
        return None;
    }
    Some(match t.parse::<i32>() {
        Ok(n) => n,
        Err(_) if t.starts_with('-') => i32::MIN,
        Err(_) => i32::MAX,
    })
}

/// Parse `XxYxZ`.
pub fn parse_size(s: &str) -> Result<IVec3, ConfigError> {
    let parts: Vec<&str> = s.split(['x', 'X']).collect();
    if parts.len() != 3 {
        return Err(bad("--size", s, "expected XxYxZ, e.g. 512x128x512"));
    }
    let mut v = [0i32; 3];
    for (i, p) in parts.iter().enumerate() {
        v[i] = whole_number(p.trim())
            .ok_or_else(|| bad("--size", s, format!("'{p}' is not a whole number")))?;
    }
    let v = IVec3::from(v);
    if v.min_element() < 8 {
        return Err(bad("--size", s, "every side must be at least 8 voxels"));
    }
    if v.x > MAX_XZ || v.z > MAX_XZ || v.y > MAX_Y {
        return Err(bad(
            "--size",
            s,
            format!("the limit is {MAX_XZ}x{MAX_Y}x{MAX_XZ}"),
        ));
    }
    Ok(v)
}

/// Parse `x,y,z` into a finite vector.
pub fn parse_vec3(flag: &'static str, s: &str) -> Result<DVec3, ConfigError> {
    let parts: Vec<&str> = s.split(',').collect();
    if parts.len() != 3 {
        return Err(bad(flag, s, "expected x,y,z"));
    }
    let mut v = [0f64; 3];
    for (i, p) in parts.iter().enumerate() {
        let x: f64 = p
            .trim()
            .parse()
            .map_err(|_| bad(flag, s, format!("'{p}' is not a number")))?;
        if !x.is_finite() {
            return Err(bad(flag, s, "coordinates must be finite (no NaN or inf)"));
        }
        if x.abs() > 1e9 {
            return Err(bad(flag, s, "coordinates must be within ±1e9 voxels"));
        }
        v[i] = x;
    }
    Ok(DVec3::from(v))
}

fn parse_num<T>(flag: &'static str, s: &str, lo: T, hi: T) -> Result<T, ConfigError>
where
    T: std::str::FromStr + PartialOrd + std::fmt::Display + Copy,
{
    let v: T = s.trim().parse().map_err(|_| {
        // A number the type cannot hold (4294967296 for a u32, 1.5 for a
        // count) is out of range, not "not a number" (regression).
        match s.trim().parse::<f64>() {
            Ok(x) if x.is_finite() => bad(flag, s, format!("must be in {lo}..={hi}")),
            _ => bad(flag, s, "not a number"),
        }
    })?;
    if !(v >= lo && v <= hi) {
        return Err(bad(flag, s, format!("must be in {lo}..={hi}")));
    }
    Ok(v)
}

/// Refuse an output name whose extension promises another format than the
/// one written (`--out view.jpg` used to get PNG bytes). A name without an
/// extension is accepted.
pub fn check_extension(flag: &'static str, path: &Path, ext: &str) -> Result<(), ConfigError> {
    match path.extension().and_then(|e| e.to_str()) {
        Some(e) if !e.eq_ignore_ascii_case(ext) => Err(bad(
            flag,
            &path.display().to_string(),
            format!("only .{ext} is written here: name the file with .{ext}"),
        )),
        _ => Ok(()),
    }
}

/// A benchmark's `--json` and `--chart` outputs, checked before any work:
/// two distinct files (regression: one path for both left only the chart,
/// with exit 0), a chart named `.svg`, and each in a folder that exists and
/// not itself a folder (regression: found only after the whole run).
pub fn check_bench_outputs(json: &Path, chart: Option<&Path>) -> Result<(), ConfigError> {
    let placed = |flag: &'static str, p: &Path| -> Result<(), ConfigError> {
        let shown = p.display().to_string();
        if p.is_dir() {
            return Err(bad(flag, &shown, "is a folder: name a file"));
        }
        match p.parent() {
            Some(dir) if !dir.as_os_str().is_empty() && !dir.is_dir() => Err(bad(
                flag,
                &shown,
                format!("its folder {} does not exist", dir.display()),
            )),
            _ => Ok(()),
        }
    };
    placed("--json", json)?;
    // The same file however it is spelled (`./r.svg`, `a/../r.svg`, a link).
    let same = |a: &Path, b: &Path| {
        let resolved = |p: &Path| {
            let dir = match p.parent() {
                Some(d) if !d.as_os_str().is_empty() => d,
                _ => Path::new("."),
            };
            Some(dir.canonicalize().ok()?.join(p.file_name()?))
        };
        #[cfg(unix)]
        if let (Ok(x), Ok(y)) = (std::fs::metadata(a), std::fs::metadata(b)) {
            use std::os::unix::fs::MetadataExt;
            return (x.dev(), x.ino()) == (y.dev(), y.ino());
        }
        a == b || matches!((resolved(a), resolved(b)), (Some(x), Some(y)) if x == y)
    };
    if let Some(chart) = chart {
        if same(chart, json) {
            return Err(bad(
                "--chart",
                &chart.display().to_string(),
                "is also --json: the chart would overwrite the results; name two files",
            ));
        }
        check_extension("--chart", chart, "svg")?;
        placed("--chart", chart)?;
    }
    Ok(())
}

/// Validated scene choice.
#[derive(Clone, Debug, PartialEq)]
pub struct SceneSettings {
    /// Which scene.
    pub spec: SceneSpec,
    /// Size for procedural scenes.
    pub size: IVec3,
    /// Seed.
    pub seed: u64,
}

impl SceneSettings {
    /// Validate scene flags; `default_size` applies when `--size` is absent.
    pub fn from_args(a: &SceneArgs, default_size: IVec3) -> Result<Self, ConfigError> {
        let spec: SceneSpec = a
            .scene
            .parse()
            .map_err(|e: crate::scene::SceneError| bad("--scene", &a.scene, e.to_string()))?;
        let size = match &a.size {
            Some(s) if !spec.is_procedural() => {
                return Err(bad(
                    "--size",
                    s,
                    "heightmap and vox scenes take their size from the file",
                ));
            }
            Some(s) => parse_size(s)?,
            None => default_size,
        };
        Ok(SceneSettings {
            spec,
            size,
            seed: a.seed,
        })
    }
}

/// Validated camera and image flags (the view itself may default later).
#[derive(Clone, Debug, PartialEq)]
pub struct ViewSettings {
    /// Explicit view, if --eye/--target were given.
    pub view: Option<View>,
    /// Field of view when no explicit view is given, or with one.
    pub fov: Option<f64>,
    /// Image width.
    pub width: u32,
    /// Image height.
    pub height: u32,
    /// Thread count (None: all cores).
    pub threads: Option<usize>,
}

impl ViewSettings {
    /// Validate view flags with default image size `w`×`h`.
    pub fn from_args(a: &ViewArgs, w: u32, h: u32) -> Result<Self, ConfigError> {
        let fov = a
            .fov
            .as_deref()
            .map(|s| parse_num("--fov", s, 0.01f64, 179.0))
            .transpose()?;
        let view = match (&a.eye, &a.target) {
            (Some(e), Some(t)) => {
                let eye = parse_vec3("--eye", e)?;
                let target = parse_vec3("--target", t)?;
                if eye == target {
                    return Err(bad(
                        "--target",
                        t,
                        "equals --eye, so the view direction is undefined",
                    ));
                }
                let f = (target - eye).normalize();
                if f.cross(DVec3::Y).length() < 1e-9 {
                    return Err(bad(
                        "--target",
                        t,
                        "is straight above or below --eye; tilt it slightly",
                    ));
                }
                Some(View {
                    eye: eye.to_array(),
                    target: target.to_array(),
                    fov: fov.unwrap_or(50.0),
                })
            }
            (Some(e), None) => return Err(bad("--eye", e, "needs --target too")),
            (None, Some(t)) => return Err(bad("--target", t, "needs --eye too")),
            (None, None) => None,
        };
        Ok(ViewSettings {
            view,
            fov,
            width: a
                .width
                .as_deref()
                .map(|s| parse_num("--width", s, 1u32, 16384))
                .transpose()?
                .unwrap_or(w),
            height: a
                .height
                .as_deref()
                .map(|s| parse_num("--height", s, 1u32, 16384))
                .transpose()?
                .unwrap_or(h),
            threads: a
                .threads
                .as_deref()
                .map(|s| parse_num("--threads", s, 1usize, 1024))
                .transpose()?,
        })
    }
}

/// Settings of `brickworld render`.
#[derive(Clone, Debug, PartialEq)]
pub struct RenderSettings {
    /// Scene.
    pub scene: SceneSettings,
    /// View.
    pub view: ViewSettings,
    /// Tracer.
    pub structure: Structure,
    /// Hard shadows.
    pub shadows: bool,
    /// PNG path.
    pub out: PathBuf,
    /// Depth path.
    pub depth_out: Option<PathBuf>,
    /// Dense grid limit, bytes.
    pub dense_limit: u64,
    /// Where to trace.
    pub tracer: crate::gpu::TracerChoice,
    /// Distance fog extent in voxels (0: none).
    pub fog: f32,
    /// Level of detail `C` in pixels (0: exact).
    pub lod: f32,
    /// Ambient occlusion.
    pub ao: bool,
    /// Beam starts.
    pub beam: bool,
}

/// Largest level-of-detail `C`, in pixels.
pub const MAX_LOD: f64 = 256.0;
/// Smallest level-of-detail `C`, in pixels (smaller ones would round to an
/// exact trace unannounced).
pub const MIN_LOD: f64 = 0.01;

/// Whether `c` is a level-of-detail `C` in [`MIN_LOD`]..=[`MAX_LOD`].
pub fn lod_in_range(c: f64) -> bool {
    c.is_finite() && (MIN_LOD..=MAX_LOD).contains(&c)
}

/// Validate a level-of-detail `C` given as `flag`.
pub fn lod_c(flag: &'static str, c: f64) -> Result<f32, ConfigError> {
    if lod_in_range(c) {
        Ok(c as f32)
    } else {
        Err(bad(
            flag,
            &crate::sim::fmt_num(c),
            format!(
                "expected a cell footprint in pixels from {MIN_LOD} to {MAX_LOD} (leave it out for exact tracing)"
            ),
        ))
    }
}

/// Default size of procedural scenes for `render`.
pub const RENDER_DEFAULT_SIZE: IVec3 = IVec3::new(512, 128, 512);
/// Default size of procedural scenes for `bench tracers`.
pub const BENCH_DEFAULT_SIZE: IVec3 = IVec3::new(512, 128, 512);

impl RenderSettings {
    /// Validate `render` arguments.
    pub fn from_args(a: &RenderArgs) -> Result<Self, ConfigError> {
        // One path for both would leave only the depth (regression).
        if let Some(d) = &a.depth_out
            && d == &a.out
        {
            return Err(bad(
                "--depth-out",
                &d.display().to_string(),
                "is also --out: the depth would overwrite the image; name two files",
            ));
        }
        check_extension("--out", &a.out, "png")?;
        if let Some(d) = &a.depth_out {
            check_extension("--depth-out", d, "npy")?;
        }
        Ok(RenderSettings {
            scene: SceneSettings::from_args(&a.scene, RENDER_DEFAULT_SIZE)?,
            view: ViewSettings::from_args(&a.view, 960, 540)?,
            structure: a
                .structure
                .parse()
                .map_err(|e: String| bad("--structure", &a.structure, e))?,
            shadows: a.shadows,
            out: a.out.clone(),
            depth_out: a.depth_out.clone(),
            dense_limit: a.dense_limit_mib.saturating_mul(1 << 20),
            tracer: a
                .tracer
                .parse()
                .map_err(|e: String| bad("--tracer", &a.tracer, e))?,
            fog: if a.fog.is_finite() && (0.0..=1e6).contains(&a.fog) {
                a.fog as f32
            } else {
                return Err(bad(
                    "--fog",
                    &crate::sim::fmt_num(a.fog),
                    "expected a distance in 0..=1000000 voxels (0: no fog)",
                ));
            },
            lod: match a.lod {
                None => 0.0,
                Some(_) if a.structure != "brickmap" => {
                    return Err(bad(
                        "--structure",
                        &a.structure,
                        "--lod needs the brickmap (the dense grid and the octree have no levels)",
                    ));
                }
                Some(c) => lod_c("--lod", c)?,
            },
            ao: a.ao,
            beam: a.beam,
        })
    }
}

/// Settings of `brickworld bench lod`.
#[derive(Clone, Debug, PartialEq)]
pub struct BenchLodSettings {
    /// Scene.
    pub scene: SceneSettings,
    /// View (the scene's three bench views unless one is given).
    pub view: ViewSettings,
    /// Footprints measured besides exact tracing, ascending.
    pub lods: Vec<f32>,
    /// Reference samples per pixel.
    pub spp: u32,
    /// Timed renders per point.
    pub repeat: u32,
    /// JSON path.
    pub json: PathBuf,
    /// Chart path.
    pub chart: Option<PathBuf>,
}

/// Default size of procedural scenes for `bench lod` (the terrain).
pub const BENCH_LOD_DEFAULT_SIZE: IVec3 = IVec3::new(2048, 256, 2048);

impl BenchLodSettings {
    /// Validate `bench lod` arguments.
    pub fn from_args(a: &crate::cli::BenchLodArgs) -> Result<Self, ConfigError> {
        let mut lods = Vec::new();
        for part in a.lod.split(',') {
            let c: f64 = part
                .trim()
                .parse()
                .map_err(|_| bad("--lod", &a.lod, format!("'{part}' is not a number")))?;
            lods.push(lod_c("--lod", c)?);
        }
        lods.sort_by(f32::total_cmp);
        lods.dedup();
        check_bench_outputs(&a.json, a.chart.as_deref())?;
        Ok(BenchLodSettings {
            scene: SceneSettings::from_args(&a.scene, BENCH_LOD_DEFAULT_SIZE)?,
            view: ViewSettings::from_args(&a.view, 960, 540)?,
            lods,
            spp: parse_num("--spp", &a.spp, 16u32, 1024)?,
            repeat: parse_num("--repeat", &a.repeat, 1u32, 100)?,
            json: a.json.clone(),
            chart: a.chart.clone(),
        })
    }
}

/// Settings of `brickworld bench tracers`.
#[derive(Clone, Debug, PartialEq)]
pub struct BenchTracersSettings {
    /// Scene.
    pub scene: SceneSettings,
    /// View.
    pub view: ViewSettings,
    /// JSON path.
    pub json: PathBuf,
    /// Chart path.
    pub chart: Option<PathBuf>,
    /// Repeats per view.
    pub repeat: u32,
    /// Dense grid limit, bytes.
    pub dense_limit: u64,
}

impl BenchTracersSettings {
    /// Validate `bench tracers` arguments.
    pub fn from_args(a: &BenchTracersArgs) -> Result<Self, ConfigError> {
        if a.repeat == 0 || a.repeat > 100 {
            return Err(bad("--repeat", &a.repeat.to_string(), "must be in 1..=100"));
        }
        check_bench_outputs(&a.json, a.chart.as_deref())?;
        Ok(BenchTracersSettings {
            scene: SceneSettings::from_args(&a.scene, BENCH_DEFAULT_SIZE)?,
            view: ViewSettings::from_args(&a.view, 1024, 768)?,
            json: a.json.clone(),
            chart: a.chart.clone(),
            repeat: a.repeat,
            dense_limit: a.dense_limit_mib.saturating_mul(1 << 20),
        })
    }
}

/// A parameter override `SCRIPT.NAME=VALUE`.
#[derive(Clone, Debug, PartialEq)]
pub struct ParamOverride {
    /// Script name (file stem).
    pub script: String,
    /// Parameter name.
    pub name: String,
    /// Value.
    pub value: f64,
}

/// Settings of `brickworld sim`.
#[derive(Clone, Debug, PartialEq)]
pub struct SimSettings {
    /// Scene.
    pub scene: SceneSettings,
    /// View of the final render.
    pub view: ViewSettings,
    /// Script files.
    pub scripts: Vec<PathBuf>,
    /// Steps.
    pub steps: u64,
    /// Time step.
    pub dt: f64,
    /// Parameter overrides.
    pub params: Vec<ParamOverride>,
    /// Output PNG.
    pub out: PathBuf,
    /// Shadows in the final render.
    pub shadows: bool,
    /// Hot reload.
    pub watch: bool,
    /// CFL target for sub-stepping (0: off).
    pub cfl: f64,
    /// Water drains over the world's edges.
    pub drain: bool,
}

/// Default size of procedural scenes for `sim`.
pub const SIM_DEFAULT_SIZE: IVec3 = IVec3::new(256, 96, 256);

impl SimSettings {
    /// Validate `sim` arguments.
    pub fn from_args(a: &SimArgs) -> Result<Self, ConfigError> {
        let mut params = Vec::new();
        for p in &a.params {
            let (lhs, value) = p
                .split_once('=')
                .ok_or_else(|| bad("--param", p, "expected SCRIPT.NAME=VALUE"))?;
            let (script, name) = lhs
                .split_once('.')
                .ok_or_else(|| bad("--param", p, "expected SCRIPT.NAME=VALUE"))?;
            let value: f64 = value
                .trim()
                .parse()
                .map_err(|_| bad("--param", p, format!("'{value}' is not a number")))?;
            if !value.is_finite() {
                return Err(bad("--param", p, "the value must be finite"));
            }
            // Two values for one parameter: the user meant one of them.
            if params
                .iter()
                .any(|q: &ParamOverride| q.script == script && q.name == name)
            {
                return Err(bad(
                    "--param",
                    p,
                    format!("{script}.{name} is given more than once"),
                ));
            }
            params.push(ParamOverride {
                script: script.to_string(),
                name: name.to_string(),
                value,
            });
        }
        check_extension("--out", &a.out, "png")?;
        Ok(SimSettings {
            scene: SceneSettings::from_args(&a.scene, SIM_DEFAULT_SIZE)?,
            view: ViewSettings::from_args(&a.view, 960, 540)?,
            scripts: a.scripts.clone(),
            steps: parse_num("--steps", &a.steps, 1u64, 10_000_000)?,
            dt: parse_num("--dt", &a.dt, 1e-9f64, 1e3)?,
            params,
            out: a.out.clone(),
            shadows: a.shadows,
            watch: a.watch,
            cfl: parse_num("--cfl", &a.cfl, 0.0f64, 1.0)?,
            drain: !a.closed_edges,
        })
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// The documented bounds of `C`, at their edges (audit: only 1e9 and
    /// 1e-50 were tried).
    #[test]
    fn lod_c_accepts_its_bounds_and_refuses_just_past_them() {
        assert!(lod_c("--lod", 0.01).is_ok());
        assert!(lod_c("--lod", 256.0).is_ok());
        assert!(lod_c("--lod", 0.0099).is_err());
        assert!(lod_c("--lod", 256.001).is_err());
    }

    #[test]
    fn sizes_parse_and_bad_ones_name_the_flag() {
        assert_eq!(
            parse_size("512x128x256").unwrap(),
            IVec3::new(512, 128, 256)
        );
        for s in ["512x128", "axbxc", "4x8x8", "100000x8x8", "-8x8x8", ""] {
            let e = parse_size(s).unwrap_err();
            assert_eq!(e.flag, "--size", "{s}");
        }
    }

    /// Regression (hostile probe): a side too large for 32 bits was said
    /// not to be a whole number.
    #[test]
    fn a_size_past_32_bits_is_out_of_range_not_malformed() {
        for (s, says) in [
            ("64x64x99999999999", "the limit is"),
            ("64x64x99999999999999999999999", "the limit is"),
            ("64x-99999999999x64", "at least 8"),
            ("64x1e3x64", "'1e3' is not a whole number"),
            ("64x+x64", "'+' is not a whole number"),
        ] {
            let e = parse_size(s).unwrap_err().to_string();
            assert!(e.contains(says), "{s}: {e}");
        }
        assert_eq!(parse_size("+64x 64x64").unwrap(), IVec3::splat(64));
    }

    #[test]
    fn vectors_reject_nan_and_wrong_arity() {
        assert_eq!(
            parse_vec3("--eye", "1,-2.5,3").unwrap(),
            DVec3::new(1.0, -2.5, 3.0)
        );
        for s in ["NaN,0,0", "1,2", "inf,0,0", "a,b,c", "1,2,3,4"] {
            assert_eq!(parse_vec3("--eye", s).unwrap_err().flag, "--eye", "{s}");
        }
    }
}
