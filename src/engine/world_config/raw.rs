//! The first stage of a world config: plain serde structs that mirror the
//! TOML and reject unknown fields. [`super::validate`] turns them into the
//! typed settings of [`super::WorldConfig`].

use std::collections::BTreeMap;

use serde::Deserialize;

#[derive(Debug, Deserialize)]
#[serde(deny_unknown_fields)]
pub(super) struct RawConfig {
    pub(super) world: RawWorld,
    #[serde(default)]
    pub(super) sim: RawSim,
    #[serde(default)]
    pub(super) scripts: Vec<RawScript>,
    pub(super) camera: Option<RawCamera>,
    #[serde(default)]
    pub(super) render: RawRender,
    #[serde(default)]
    pub(super) frames: RawFrames,
    #[serde(default)]
    pub(super) checkpoint: RawCheckpoint,
    #[serde(default)]
    pub(super) control: RawControl,
    #[serde(default)]
    pub(super) place: Vec<RawPlace>,
    pub(super) stream: Option<RawStream>,
}

#[derive(Debug, Deserialize)]
#[serde(deny_unknown_fields)]
pub(super) struct RawStream {
    pub(super) view_distance: Option<f64>,
    pub(super) memory_budget: Option<toml::Value>,
    pub(super) fetchers: Option<i64>,
}

#[derive(Debug, Deserialize)]
#[serde(deny_unknown_fields)]
pub(super) struct RawPlace {
    pub(super) material: String,
    pub(super) at: [i64; 3],
    pub(super) size: Option<[i64; 3]>,
}

#[derive(Debug, Deserialize)]
#[serde(deny_unknown_fields)]
pub(super) struct RawWorld {
    pub(super) source: String,
    pub(super) size: Option<[i64; 3]>,
    pub(super) height: Option<i64>,
    #[serde(default)]
    pub(super) seed: u64,
}

#[derive(Debug, Default, Deserialize)]
#[serde(deny_unknown_fields)]
pub(super) struct RawSim {
    pub(super) dt: Option<f64>,
    pub(super) scripts_dir: Option<String>,
    pub(super) region: Option<RawRegion>,
    pub(super) radius: Option<f64>,
}

#[derive(Debug, Deserialize)]
#[serde(deny_unknown_fields)]
pub(super) struct RawRegion {
    pub(super) min: [i64; 2],
    pub(super) max: [i64; 2],
}

#[derive(Debug, Deserialize)]
#[serde(deny_unknown_fields)]
pub(super) struct RawScript {
    pub(super) file: String,
    pub(super) every: Option<i64>,
    #[serde(default)]
    pub(super) params: BTreeMap<String, f64>,
}

#[derive(Debug, Deserialize)]
#[serde(deny_unknown_fields)]
pub(super) struct RawCamera {
    pub(super) mode: Option<String>,
    pub(super) eye: Option<[f64; 3]>,
    pub(super) target: Option<[f64; 3]>,
    pub(super) fov: Option<f64>,
    pub(super) orbit_period_s: Option<f64>,
    pub(super) fly_to: Option<[f64; 3]>,
    pub(super) fly_period_s: Option<f64>,
    pub(super) velocity: Option<[f64; 3]>,
}

#[derive(Debug, Default, Deserialize)]
#[serde(deny_unknown_fields)]
pub(super) struct RawRender {
    pub(super) width: Option<i64>,
    pub(super) height: Option<i64>,
    pub(super) tracer: Option<String>,
    pub(super) shadows: Option<bool>,
    pub(super) fog: Option<f64>,
    pub(super) lod: Option<f64>,
    pub(super) ao: Option<bool>,
    pub(super) aa: Option<i64>,
    pub(super) beam: Option<bool>,
}

#[derive(Debug, Default, Deserialize)]
#[serde(deny_unknown_fields)]
pub(super) struct RawFrames {
    pub(super) dir: Option<String>,
    pub(super) every: Option<i64>,
    pub(super) keep: Option<i64>,
    pub(super) max_mb: Option<f64>,
}

#[derive(Debug, Default, Deserialize)]
#[serde(deny_unknown_fields)]
pub(super) struct RawCheckpoint {
    pub(super) every: Option<i64>,
}

#[derive(Debug, Default, Deserialize)]
#[serde(deny_unknown_fields)]
pub(super) struct RawControl {
    pub(super) addr: Option<String>,
    pub(super) hosts: Option<Vec<String>>,
}
