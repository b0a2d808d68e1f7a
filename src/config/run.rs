//! The settings of the commands that run simulations: the flags `run`
//! lays over a world config ([`RunSettings`]) and `sim`'s
//! ([`SimSettings`]), each error naming its flag.

use std::path::PathBuf;

use super::values::{bad, parse_num};
use super::*;

/// The flags `run` lays over a world config, validated (the config itself
/// is loaded and validated by [`crate::engine::world_config`]).
#[derive(Clone, Debug, PartialEq)]
pub struct RunSettings {
    /// `--addr`: the control server's address.
    pub addr: Option<std::net::SocketAddr>,
    /// `--memory-budget` in bytes (a streamed world's).
    pub memory_budget: Option<u64>,
    /// `--scripts`: the scripts directory.
    pub scripts: Option<PathBuf>,
    /// `--ticks`: stop after this many (at least one).
    pub ticks: Option<u64>,
}

impl RunSettings {
    /// Validate `run`'s flags.
    pub fn from_args(a: &crate::cli::RunArgs) -> Result<Self, ConfigError> {
        let addr = match &a.addr {
            Some(text) => Some(text.parse().map_err(|_| {
                bad(
                    "--addr",
                    text,
                    "expected an IP address and a port, e.g. 127.0.0.1:7878 (not a host name)",
                )
            })?),
            None => None,
        };
        let memory_budget = match &a.memory_budget {
            Some(text) => Some(
                crate::engine::world_config::parse_bytes(text)
                    .map_err(|e| bad("--memory-budget", text, e))?,
            ),
            None => None,
        };
        if a.ticks == Some(0) {
            return Err(bad("--ticks", "0", "at least one tick"));
        }
        Ok(RunSettings {
            addr,
            memory_budget,
            scripts: a.scripts.clone(),
            ticks: a.ticks,
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
                .rsplit_once('.')
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
        // Before the simulation, not after it (regression, odd-paths probe:
        // a missing folder failed once every step had run), and not over a
        // file it reads.
        check_output("--out", &a.out)?;
        let scene = SceneSettings::from_args(&a.scene, SIM_DEFAULT_SIZE)?;
        let mut inputs: Vec<(&str, &std::path::Path)> =
            a.scripts.iter().map(|p| ("script", p.as_path())).collect();
        if let Some(f) = scene.spec.file() {
            inputs.push(("scene file", f));
        }
        not_an_input("--out", &a.out, &inputs)?;
        Ok(SimSettings {
            scene,
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
