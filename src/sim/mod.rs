//! Cellular simulations over the world, written as Lua (Luau) scripts and
//! run in parallel: two grids on one runtime.
//!
//! - [`runtime`]: sandboxed Luau VMs, declarations, uncatchable budgets,
//!   deterministic randomness, hot reload, the built-in scripts.
//! - [`columns`]: the 2.5D grid of 8×8 column tiles: [`channels`] (sparse
//!   per-tile `f64` fields), [`step`] (the race-free parallel step: each
//!   pass reads the previous generation with a one-cell halo and writes only
//!   its own tile; a step is committed only if every pass of a script
//!   succeeded), [`native`] (the Rust reference water kernel), [`run`] (a
//!   simulation coupled to a scene) and [`writeback`] (ground, snow and
//!   water surfaces written into bricks, recording dirty bricks).
//! - [`voxels`]: scripts over the bricks' voxels themselves.
//! - [`health`]: each script's failed steps in a row and its suspension,
//!   the same rule for both grids.

pub mod columns;
pub mod health;
pub mod runtime;
mod slot;
pub mod voxels;

pub use columns::{channels, native, run, step, tile, writeback};
pub(crate) use runtime::interrupt;
pub use runtime::{embedded, reload, script};

use thiserror::Error;

pub use channels::{ChannelId, ChannelStore};
pub use health::{Health, SUSPEND_AFTER};
pub use reload::ScriptWatcher;
pub use run::WorldSim;
pub use runtime::source_file::{MAX_SCRIPT_BYTES, read_optional_script, read_script};
pub use script::{Limits, ParamSpec, PassSpec, ScriptSource, ScriptSpec, ScriptVm, StepKey};
pub use step::{Kernel, Simulation, StepReport};

/// A running script as a rebuilt simulation needs it (a streamed world's
/// region that moved is rebuilt with the scripts it ran): its current
/// source (hot reloads included), limits, rate and health.
#[derive(Clone, Debug)]
pub struct ScriptState {
    /// The source it runs now.
    pub src: ScriptSource,
    /// Its budgets.
    pub limits: Limits,
    /// Runs on ticks that are multiples of this.
    pub every: u64,
    /// Failed steps in a row.
    pub failures: u32,
    /// Why it is suspended, if it is.
    pub suspended: Option<SimError>,
}

impl SimError {
    /// Whether this is a kernel stopped by its time limit: a matter of the
    /// machine at the time, not of the world.
    pub fn is_time_budget(&self) -> bool {
        matches!(self, SimError::Runtime { msg, .. }
            if msg.contains(&format!("{} exceeded", runtime::interrupt::TIME_BUDGET)))
    }

    /// The script a step's error names ("" for errors of no one script).
    pub fn step_script(&self) -> &str {
        match self {
            SimError::Runtime { script, .. }
            | SimError::Unstable { script, .. }
            | SimError::OutOfBounds { script, .. } => script.as_str(),
            _ => "",
        }
    }
}

/// The most channel names a world's registry holds, built-ins included
/// (column and voxel registries each). It is also the most a stored chunk
/// or column blob may carry, so the engine never writes a blob that its own
/// reader refuses.
pub const MAX_CHANNELS: usize = 256;

/// Refuse script `script` if its channel `names`, those not yet `known`,
/// would take a registry of `registered` names past [`MAX_CHANNELS`].
pub(crate) fn channel_room(
    script: &str,
    names: &[String],
    known: impl Fn(&str) -> bool,
    registered: usize,
) -> Result<(), SimError> {
    let new = names.iter().filter(|n| !known(n)).count();
    if new > 0 && registered + new > MAX_CHANNELS {
        return Err(SimError::Declaration {
            script: script.to_string(),
            line: None,
            msg: format!(
                "its {new} new channels would give the world {} channels, more than {MAX_CHANNELS} (channels of earlier versions of the scripts stay registered while the engine runs; a restart registers only the scripts' channels and those the stored world holds)",
                registered + new
            ),
        });
    }
    Ok(())
}

/// The error of the lowest item of a parallel pass, whichever thread met
/// its error first: what a failed step reports is the same on every run
/// and thread count (regression, fuzzing: a script failing on many tiles
/// named a different tile from run to run). Items above the lowest error
/// seen so far are skipped; those below still run, since one of them may
/// fail too.
#[derive(Debug)]
pub(crate) struct LowestError {
    at: std::sync::atomic::AtomicUsize,
    err: std::sync::Mutex<Option<(usize, SimError)>>,
}

impl LowestError {
    pub(crate) fn new() -> Self {
        LowestError {
            at: std::sync::atomic::AtomicUsize::new(usize::MAX),
            err: std::sync::Mutex::new(None),
        }
    }

    /// Run item `i` (`f`), unless an earlier item already failed, and note
    /// its error.
    pub(crate) fn run(&self, i: usize, f: impl FnOnce() -> Result<(), SimError>) {
        if i > self.at.load(std::sync::atomic::Ordering::Relaxed) {
            return;
        }
        if let Err(e) = f() {
            let mut g = self.err.lock().unwrap_or_else(|p| p.into_inner());
            if g.as_ref().is_none_or(|(j, _)| i < *j) {
                *g = Some((i, e));
                self.at.fetch_min(i, std::sync::atomic::Ordering::Relaxed);
            }
        }
    }

    /// The lowest item's error, if any failed.
    pub(crate) fn result(self) -> Result<(), SimError> {
        match self.err.into_inner().unwrap_or_else(|p| p.into_inner()) {
            Some((_, e)) => Err(e),
            None => Ok(()),
        }
    }
}

/// Where a channel value lies: a column of a column channel, or a voxel
/// of a voxel channel (regression, modder probe: a voxel channel's range
/// error said "at column (8, 0)").
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Place {
    /// Column (x, z).
    Column(i32, i32),
    /// Voxel `index` (x + 8·y + 64·z) of brick `brick`.
    Voxel {
        /// Index in the brick.
        index: u16,
        /// Brick coordinate.
        brick: [i32; 3],
    },
}

impl std::fmt::Display for Place {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        match self {
            Place::Column(x, z) => write!(f, "column ({x}, {z})"),
            Place::Voxel {
                index,
                brick: [x, y, z],
            } => write!(f, "voxel {index} of brick ({x}, {y}, {z})"),
        }
    }
}

/// Where a kernel call ran, as an error names it.
#[derive(Clone, Debug, PartialEq, Eq)]
pub enum CallSite {
    /// A column script's tile of 8×8 columns (x, z).
    Tile(i32, i32),
    /// A voxel script's brick (x, y, z).
    Brick([i32; 3]),
    /// The brick of a material a voxel script is tried on at load.
    TestBrick(String),
}

impl std::fmt::Display for CallSite {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        match self {
            CallSite::Tile(x, z) => write!(f, "tile ({x}, {z})"),
            CallSite::Brick([x, y, z]) => write!(f, "brick ({x}, {y}, {z})"),
            CallSite::TestBrick(m) => write!(f, "a test brick of {m}, at load"),
        }
    }
}

/// A number for a message: plain when moderate, in scientific notation
/// when huge or tiny (a 1e300 is not printed as 301 digits).
pub fn fmt_num(v: f64) -> String {
    if v != 0.0 && v.is_finite() && !(1e-6..1e9).contains(&v.abs()) {
        format!("{v:e}")
    } else {
        format!("{v}")
    }
}

/// `:LINE` after a script's file name, or nothing when the line is not
/// known (it printed `water.lua:?:`).
fn at_line(line: Option<usize>) -> String {
    line.map_or(String::new(), |l| format!(":{l}"))
}

/// Which check refused a step ([`SimError::Unstable`]).
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Rejection {
    /// A channel value became NaN or infinite.
    NotFinite,
    /// A `nonnegative` channel went below 0.
    Negative,
    /// A `conserved` channel's total changed in one step.
    Drift,
    /// The step's working set would not fit in memory.
    Memory,
}

/// Errors of the simulation subsystem. Every variant names the script.
#[derive(Debug, Error, Clone, PartialEq)]
pub enum SimError {
    /// The script does not compile.
    #[error("{script}.lua{}: syntax error: {msg}", at_line(*line))]
    Syntax {
        /// Script name.
        script: String,
        /// Line, if known.
        line: Option<usize>,
        /// Compiler message.
        msg: String,
    },
    /// The script's declarations are invalid.
    #[error("{script}.lua{}: {msg}", at_line(*line))]
    Declaration {
        /// Script name.
        script: String,
        /// Line, if known.
        line: Option<usize>,
        /// What is wrong.
        msg: String,
    },
    /// A kernel failed (error, budget, memory) during a step.
    #[error("{script}.lua{}: pass '{pass}' on {at}: {msg}", at_line(*line))]
    Runtime {
        /// Script name.
        script: String,
        /// Pass name.
        pass: String,
        /// Where the call ran: a column script's tile, a voxel script's
        /// brick (regression, modder probe: voxel errors named a "tile"
        /// that was a brick's x and z), or the test brick of a load.
        at: CallSite,
        /// Line, if known.
        line: Option<usize>,
        /// Message.
        msg: String,
    },
    /// A step produced NaN, infinity or a negative value in a non-negative
    /// channel, or changed the total of a conserved one (the message says
    /// which: not every one is an instability).
    #[error("{script}.lua: step rejected: {msg}")]
    Unstable {
        /// Script name.
        script: String,
        /// Which check refused the step, for callers that act on it
        /// (the message is for people).
        kind: Rejection,
        /// What was found.
        msg: String,
    },
    /// A step wrote a channel value outside its bound (the script's declared
    /// range, or by default ± [`step::DEFAULT_BOUND_HEIGHTS`] world heights).
    #[error("{script}.lua: step rejected: channel '{channel}' = {} at {} is outside its bound [{}, {}] ({why})", fmt_num(*value), place, fmt_num(bound.0), fmt_num(bound.1))]
    OutOfBounds {
        /// Script name.
        script: String,
        /// Channel.
        channel: String,
        /// Where the value lies.
        place: Place,
        /// The value written.
        value: f64,
        /// The bound.
        bound: (f64, f64),
        /// Where the bound comes from.
        why: String,
    },
    /// A parameter change was refused.
    #[error("{script}.lua: {msg}")]
    Param {
        /// Script name.
        script: String,
        /// What is wrong.
        msg: String,
    },
    /// A script's file could not be read (missing, not a regular file, too
    /// large). The message names the file's path, so not its name again
    /// (regression, hostile probe 3: "materials.lua: …/materials.lua is
    /// not a regular file").
    #[error("{msg}")]
    File {
        /// Script name.
        script: String,
        /// What is wrong, with the path.
        msg: String,
    },
    /// Unexpected failure inside the runtime.
    #[error("simulation runtime: {0}")]
    Internal(String),
    /// A failure recorded before the engine stopped, restored with the
    /// script's health on a resume: the original error, as text.
    #[error("{msg}")]
    Recorded {
        /// Script name.
        script: String,
        /// The original error's message.
        msg: String,
    },
}
