//! What a script declares, as validated data: its grid, channels,
//! parameters, passes and the rest of the table it returns. Reading that
//! table is [`super::declare`]; the VMs that run it are [`super::script`].
//!
//! A script returns a table:
//!
//! ```lua
//! return {
//!   channels = { "water", "ground" },               -- every channel it touches
//!   nonnegative = { "water" },                      -- checked after each step
//!   params = { gravity = { default = 9.81, min = 0, max = 100 } },
//!   passes = {
//!     { name = "flux", reads = { "water", "ground" }, writes = { "water" },
//!       kernel = function(c, tx, tz) ... end },
//!   },
//! }
//! ```

use std::sync::Arc;

/// A parameter a script declares.
#[derive(Clone, Debug, PartialEq)]
pub struct ParamSpec {
    /// Name.
    pub name: String,
    /// Default value.
    pub default: f64,
    /// Smallest allowed value.
    pub min: f64,
    /// Largest allowed value.
    pub max: f64,
}

/// One pass: channels read (with halo) and written (own tile).
#[derive(Clone, Debug, PartialEq)]
pub struct PassSpec {
    /// Name.
    pub name: String,
    /// Channels read with a one-cell halo.
    pub reads: Vec<String>,
    /// Channels written.
    pub writes: Vec<String>,
    /// `reads` as indices into the script's `channels`, in order, without a
    /// voxel script's `mat` (not a channel): resolved once, where the names
    /// are checked, so a step never looks a name up.
    pub read_idx: Vec<usize>,
    /// `writes` as indices, likewise.
    pub write_idx: Vec<usize>,
}

/// Which grid a script runs over.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Default)]
pub enum Grid {
    /// 8×8 column tiles of `f64` channels (`grid = "columns"`, the default).
    #[default]
    Columns,
    /// 8³ bricks of materials and `f32` per-voxel channels (`grid = "voxels"`).
    Voxels,
}

impl Grid {
    /// The error for a script declared for this grid and loaded onto the
    /// other one. On a reload the engine is running, and the message says
    /// that a restart allows the switch (it said only "cannot run",
    /// regression, hostile probe of the twenty-third session).
    pub fn mismatch(self, script: &str, reload: bool) -> crate::sim::SimError {
        let mut msg = match self {
            Grid::Voxels => "a voxel script (grid = \"voxels\") cannot run on the column grid",
            Grid::Columns => "a column script cannot run on the voxel grid",
        }
        .to_string();
        if reload {
            msg.push_str(
                "; the engine puts each script on its grid when it starts: stop it and start \
                 it again to switch this script's grid (the running version keeps running)",
            );
        }
        crate::sim::SimError::Declaration {
            script: script.into(),
            line: None,
            msg,
        }
    }
}

/// The material buffer's name in a voxel kernel's `c.r` / `c.w`.
pub const MAT: &str = "mat";

/// Voxels in a brick with its one-voxel halo (10³).
pub const VOXEL_HALO: usize = 1000;
/// Voxels in a brick.
pub const VOXEL_CELLS: usize = 512;

/// A column script's CFL declaration: which channel is the depth, which
/// are velocities, which parameters are gravity and the cell size.
#[derive(Clone, Debug, PartialEq)]
pub struct CflSpec {
    /// Depth channel.
    pub depth: String,
    /// Velocity channels.
    pub velocities: Vec<String>,
    /// Gravity parameter.
    pub gravity: String,
    /// Cell-size parameter.
    pub dx: String,
}

/// Parameter values for a reloaded script: each parameter that still
/// exists keeps its value, clamped into a narrowed range (with a warning);
/// new ones start at their defaults.
pub fn carry_params(
    old: &ScriptSpec,
    old_values: &[f64],
    new: &ScriptSpec,
) -> (Vec<f64>, Vec<String>) {
    let mut values: Vec<f64> = new.params.iter().map(|p| p.default).collect();
    let mut warnings = Vec::new();
    for (i, p) in new.params.iter().enumerate() {
        if let Some(j) = old.params.iter().position(|q| q.name == p.name) {
            let v = old_values[j];
            let kept = v.clamp(p.min, p.max);
            if kept != v {
                warnings.push(format!(
                    "{}.lua: parameter '{}' = {} is outside its new range [{}, {}]; clamped to {}",
                    new.name,
                    p.name,
                    crate::sim::fmt_num(v),
                    crate::sim::fmt_num(p.min),
                    crate::sim::fmt_num(p.max),
                    crate::sim::fmt_num(kept)
                ));
            }
            values[i] = kept;
        }
    }
    (values, warnings)
}

/// What a script declares, validated.
#[derive(Clone, Debug, PartialEq)]
pub struct ScriptSpec {
    /// Script name (file stem).
    pub name: String,
    /// The grid it runs over.
    pub grid: Grid,
    /// Materials it names (`c.m.NAME` holds each id), voxel scripts only.
    pub materials: Vec<String>,
    /// Run only on bricks that hold one of these materials (empty: all
    /// active bricks), voxel scripts only.
    pub only: Vec<String>,
    /// Bricks holding one of these materials never sleep (a lava source).
    pub keep_awake: Vec<String>,
    /// Channels whose total the runtime reports and checks stays constant
    /// (to round-off) across the script's step.
    pub conserved: Vec<String>,
    /// Also run on the world's top layer of bricks, awake or not (rain).
    pub sky: bool,
    /// Halo values outside the world, per channel (default 0): a wall of
    /// `ground` is `boundary = { ground = 1e9 }`.
    pub boundary: Vec<(String, f64)>,
    /// Column scripts: the gravity-wave CFL limit the runtime sub-steps
    /// for, `cfl = { depth = "water", velocities = { "u", "v" }, gravity =
    /// "gravity", dx = "dx" }` (channel and parameter names).
    pub cfl: Option<CflSpec>,
    /// Column scripts: channels drained into the moat at the world's edges
    /// (counted, so world + drained is conserved).
    pub drains: Vec<String>,
    /// Initial conditions of a freshly built world: (channel, material):
    /// the channel is set to 1 in every voxel of the material.
    pub fills: Vec<(String, String)>,
    /// Channels used.
    pub channels: Vec<String>,
    /// Channels that must stay ≥ 0.
    pub nonnegative: Vec<String>,
    /// Parameters.
    pub params: Vec<ParamSpec>,
    /// Declared value ranges: (channel, min, max). A step that writes a
    /// value outside is rejected; undeclared channels get a default bound.
    pub ranges: Vec<(String, f64, f64)>,
    /// Passes, run in order each step.
    pub passes: Vec<PassSpec>,
}

impl ScriptSpec {
    /// The most channels one of its passes writes (a voxel pass's `mat` is
    /// not a channel): how many output buffers a step needs per tile or
    /// brick.
    pub fn widest_writes(&self) -> usize {
        self.passes
            .iter()
            .map(|p| p.write_idx.len())
            .max()
            .unwrap_or(0)
    }

    /// The index of parameter `name` if `value` may be set: the one check
    /// both grids' `set_param` make (the voxel grid's had drifted: no list
    /// of known names, numbers unformatted).
    pub fn param_index(&self, name: &str, value: f64) -> Result<usize, crate::sim::SimError> {
        let err = |msg: String| crate::sim::SimError::Param {
            script: self.name.clone(),
            msg,
        };
        let Some(i) = self.params.iter().position(|p| p.name == name) else {
            let known: Vec<&str> = self.params.iter().map(|p| p.name.as_str()).collect();
            return Err(err(format!(
                "no parameter '{name}' ({})",
                known_params(&known)
            )));
        };
        let p = &self.params[i];
        if !(p.min..=p.max).contains(&value) {
            return Err(err(format!(
                "parameter '{name}' = {} is outside [{}, {}]",
                crate::sim::fmt_num(value),
                crate::sim::fmt_num(p.min),
                crate::sim::fmt_num(p.max)
            )));
        }
        Ok(i)
    }
}

/// Source of a script.
#[derive(Clone, Debug)]
pub struct ScriptSource {
    /// Script name (file stem), used in every error.
    pub name: String,
    /// Source text.
    pub text: Arc<str>,
}

/// The parameters a "no parameter" error lists: `known: a, b`, or that
/// the script declares none (an empty "known: " read as a cut message).
pub fn known_params(names: &[&str]) -> String {
    if names.is_empty() {
        "the script declares no parameters".into()
    } else {
        format!("known: {}", names.join(", "))
    }
}
