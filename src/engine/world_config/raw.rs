//! The first stage of a world config: plain serde structs that mirror the
//! TOML and reject unknown fields. [`super::validate`] turns them into the
//! typed settings of [`super::WorldConfig`].

use std::collections::BTreeMap;

use serde::{Deserialize, Deserializer};

/// An array of exactly `N` values: the TOML reader fills a fixed array from
/// the first `N` and ignored the rest, so `size = [64, 32, 64, 5]` (or one
/// of 200 000 numbers) was read as a size (regression, hostile probe).
fn exact<'de, D, T, const N: usize>(d: D) -> Result<[T; N], D::Error>
where
    D: Deserializer<'de>,
    T: Deserialize<'de>,
{
    let v: Vec<T> = Vec::deserialize(d)?;
    let n = v.len();
    v.try_into().map_err(|_| {
        serde::de::Error::custom(format!("expected an array of {N} numbers, found {n}"))
    })
}

/// [`exact`] for an optional array.
fn exact_opt<'de, D, T, const N: usize>(d: D) -> Result<Option<[T; N]>, D::Error>
where
    D: Deserializer<'de>,
    T: Deserialize<'de>,
{
    exact(d).map(Some)
}

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
    #[serde(deserialize_with = "exact")]
    pub(super) at: [i64; 3],
    #[serde(default, deserialize_with = "exact_opt")]
    pub(super) size: Option<[i64; 3]>,
}

#[derive(Debug, Deserialize)]
#[serde(deny_unknown_fields)]
pub(super) struct RawWorld {
    pub(super) source: String,
    #[serde(default, deserialize_with = "exact_opt")]
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
    #[serde(deserialize_with = "exact")]
    pub(super) min: [i64; 2],
    #[serde(deserialize_with = "exact")]
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
    #[serde(default, deserialize_with = "exact_opt")]
    pub(super) eye: Option<[f64; 3]>,
    #[serde(default, deserialize_with = "exact_opt")]
    pub(super) target: Option<[f64; 3]>,
    pub(super) fov: Option<f64>,
    pub(super) orbit_period_s: Option<f64>,
    #[serde(default, deserialize_with = "exact_opt")]
    pub(super) fly_to: Option<[f64; 3]>,
    pub(super) fly_period_s: Option<f64>,
    #[serde(default, deserialize_with = "exact_opt")]
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
