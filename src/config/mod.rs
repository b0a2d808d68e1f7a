//! Second stage of argument handling: raw CLI strings become validated,
//! typed settings, one struct per command. Every error names the flag at
//! fault; the single values are parsed in [`values`].

mod run;
mod values;

use std::path::{Path, PathBuf};

use glam::{DVec3, IVec3};

use crate::cli::{BenchTracersArgs, RenderArgs, SceneArgs, SimArgs, ViewArgs};
use crate::scene::{SceneSpec, View};
use crate::trace::Structure;
pub use run::{ParamOverride, RunSettings, SimSettings};
pub use values::{
    ConfigError, MAX_LOD, MAX_XZ, MAX_Y, MIN_LOD, check_bench_outputs, check_extension,
    check_output, lod_c, lod_in_range, not_an_input, parse_sim_sizes, parse_size, parse_vec3,
    same_file,
};
use values::{bad, parse_num};

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
    /// Refuse a bench's outputs (`--json`, `--chart`) that name the scene's
    /// own file (a heightmap or `.vox`), which they would overwrite
    /// (regression, hostile probe: `bench gpu --scene heightmap:h.png
    /// --json h.png` replaced the heightmap).
    pub fn check_outputs(&self, json: &Path, chart: Option<&Path>) -> Result<(), ConfigError> {
        if let Some(file) = self.spec.file() {
            values::not_an_input("--json", json, &[("scene file", file)])?;
            if let Some(c) = chart {
                values::not_an_input("--chart", c, &[("scene file", file)])?;
            }
        }
        Ok(())
    }

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
            Some(s) => {
                let size = parse_size(s)?;
                // Named by the flag, not the config key the library
                // checks under (hostile probe: "world.size: not enough
                // memory" for `render --size`).
                if let Err(crate::scene::SceneError::OutOfMemory { msg, .. }) =
                    crate::scene::budget::check_world("--size", size)
                {
                    return Err(bad("--size", s, format!("not enough memory: {msg}")));
                }
                size
            }
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
    /// The camera of these settings: the explicit view, or `default` with
    /// `--fov` applied, at the image size.
    pub fn camera(&self, default: View) -> Result<crate::trace::Camera, crate::trace::CameraError> {
        let view = self.view.unwrap_or(View {
            fov: self.fov.unwrap_or(default.fov),
            ..default
        });
        crate::trace::Camera::new(
            DVec3::from(view.eye),
            DVec3::from(view.target),
            view.fov,
            self.width,
            self.height,
        )
    }

    /// Validate view flags with default image size `w`×`h`.
    pub fn from_args(a: &ViewArgs, w: u32, h: u32) -> Result<Self, ConfigError> {
        let fov = a
            .fov
            .as_deref()
            .map(|s| parse_num("--fov", s, crate::trace::MIN_FOV, crate::trace::MAX_FOV))
            .transpose()?;
        let view = match (&a.eye, &a.target) {
            (Some(e), Some(t)) => {
                let eye = parse_vec3("--eye", e)?;
                let target = parse_vec3("--target", t)?;
                match crate::trace::view_direction(eye, target) {
                    Ok(_) => {}
                    Err(crate::trace::CameraError::Vertical) => {
                        return Err(bad(
                            "--target",
                            t,
                            "is straight above or below --eye; tilt it slightly",
                        ));
                    }
                    Err(_) => {
                        return Err(bad(
                            "--target",
                            t,
                            "equals --eye (or lies within 1e-6 of it), so the view direction is undefined",
                        ));
                    }
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

/// Default size of procedural scenes for `render`.
pub const RENDER_DEFAULT_SIZE: IVec3 = IVec3::new(512, 128, 512);
/// Default size of procedural scenes for `bench tracers`.
pub const BENCH_DEFAULT_SIZE: IVec3 = IVec3::new(512, 128, 512);

impl RenderSettings {
    /// Validate `render` arguments.
    pub fn from_args(a: &RenderArgs) -> Result<Self, ConfigError> {
        // One file for both would leave only the depth (regression), also
        // when spelled differently or through a link (regression: a link
        // to the PNG named as --depth-out turned it into a .npy, exit 0).
        if let Some(d) = &a.depth_out
            && values::same_file(d, &a.out)
        {
            return Err(bad(
                "--depth-out",
                &d.display().to_string(),
                "is also --out: the depth would overwrite the image; name two files",
            ));
        }
        check_extension("--out", &a.out, "png")?;
        check_output("--out", &a.out)?;
        if let Some(d) = &a.depth_out {
            check_extension("--depth-out", d, "npy")?;
            check_output("--depth-out", d)?;
        }
        let scene = SceneSettings::from_args(&a.scene, RENDER_DEFAULT_SIZE)?;
        if let Some(file) = scene.spec.file() {
            values::not_an_input("--out", &a.out, &[("scene file", file)])?;
            if let Some(d) = &a.depth_out {
                values::not_an_input("--depth-out", d, &[("scene file", file)])?;
            }
        }
        Ok(RenderSettings {
            scene,
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
        let scene = SceneSettings::from_args(&a.scene, BENCH_LOD_DEFAULT_SIZE)?;
        scene.check_outputs(&a.json, a.chart.as_deref())?;
        Ok(BenchLodSettings {
            scene,
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
        let scene = SceneSettings::from_args(&a.scene, BENCH_DEFAULT_SIZE)?;
        scene.check_outputs(&a.json, a.chart.as_deref())?;
        Ok(BenchTracersSettings {
            scene,
            view: ViewSettings::from_args(&a.view, 1024, 768)?,
            json: a.json.clone(),
            chart: a.chart.clone(),
            repeat: a.repeat,
            dense_limit: a.dense_limit_mib.saturating_mul(1 << 20),
        })
    }
}

#[cfg(test)]
mod tests;
