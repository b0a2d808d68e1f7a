//! Lua (Luau) scripts: loading, validating their declarations, and the
//! sandboxed VMs that run their kernels.
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
//!
//! A kernel gets `c.dt`, `c.tick`, `c.random`, `c.p` (parameters), `c.r.NAME` (10×10 halo buffers
//! of f64, read-only by convention) and `c.w.NAME` (8×8 output buffers,
//! pre-filled with the current values), and the tile coordinate. It must be
//! a pure function of those: the runtime runs tiles on many VMs in any order.
//!
//! **Sandbox.** Only `math`, `string`, `table`, `buffer`, `bit32` and `utf8`
//! are loaded: no files, OS, processes, `debug` or native modules, and the
//! globals `require`, `getfenv`, `setfenv`, `loadstring`, `collectgarbage`,
//! `gcinfo`, `newproxy` and `print` are removed.
//! Globals are read-only (Luau `sandbox`, with the per-thread proxy frozen
//! too), and `math.random` is gone: `c.random(x, y, z, k)` gives numbers
//! that are a pure function of (world seed, tick, script, x, y, z, k). Each VM has a memory limit, and
//! every kernel call an instruction budget and a wall-clock deadline checked
//! from Luau's interrupt; a script that exceeds them is stopped with an error
//! naming the script and line.

use std::sync::Arc;
use std::time::{Duration, Instant};

use mlua::{Buffer, Function, Lua, LuaOptions, StdLib, Table, Value};

use crate::sim::SimError;
use crate::sim::tile::{HALO_CELLS, TILE_CELLS};

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
                    "{}.lua: parameter '{}' = {v} is outside its new range [{}, {}]; clamped to {kept}",
                    new.name, p.name, p.min, p.max
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

/// Source of a script.
#[derive(Clone, Debug)]
pub struct ScriptSource {
    /// Script name (file stem), used in every error.
    pub name: String,
    /// Source text.
    pub text: Arc<str>,
}

/// What keys a step's random numbers: `c.random(x, y, z, k)` is a pure
/// function of (world seed, tick, script, x, y, z, k), so a world is
/// reproducible whatever the thread count, and across a stop and resume.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq)]
pub struct StepKey {
    /// The world's seed.
    pub seed: u64,
    /// The tick being computed.
    pub tick: u64,
    /// A hash of the script's name.
    pub script: u64,
}

fn mix64(mut z: u64) -> u64 {
    // SplitMix64's finaliser: a bijection with full avalanche.
    z = (z ^ (z >> 30)).wrapping_mul(0xbf58_476d_1ce4_e5b9);
    z = (z ^ (z >> 27)).wrapping_mul(0x94d0_49bb_1331_11eb);
    z ^ (z >> 31)
}

impl StepKey {
    /// The key of `script` at `tick` in a world of `seed`.
    pub fn new(seed: u64, tick: u64, script: &str) -> Self {
        let script = crate::persist::bytes::fnv1a(script.as_bytes());
        StepKey { seed, tick, script }
    }

    /// A uniform number in [0, 1) for the position (x, y, z) and counter k
    /// (each truncated to a whole number).
    pub fn random(&self, x: f64, y: f64, z: f64, k: f64) -> f64 {
        let mut h = mix64(self.seed ^ 0x9e37_79b9_7f4a_7c15);
        for v in [
            self.tick,
            self.script,
            x as i64 as u64,
            y as i64 as u64,
            z as i64 as u64,
            k as i64 as u64,
        ] {
            h = mix64(h ^ v);
        }
        (h >> 11) as f64 * (1.0 / (1u64 << 53) as f64)
    }
}

/// Resource limits of a VM.
#[derive(Clone, Copy, Debug)]
pub struct Limits {
    /// Bytes of Lua heap per VM.
    pub memory: usize,
    /// Interrupt ticks (loop iterations and calls) per kernel call.
    pub instructions: u64,
    /// Wall-clock time per kernel call.
    pub time: Duration,
}

impl Default for Limits {
    fn default() -> Self {
        Limits {
            memory: 64 << 20,
            instructions: 20_000_000,
            time: Duration::from_secs(5),
        }
    }
}

/// The first `:LINE:` in a Lua error message.
pub fn line_of(msg: &str) -> Option<usize> {
    let mut rest = msg;
    while let Some(i) = rest.find(':') {
        let tail = &rest[i + 1..];
        let digits: String = tail.chars().take_while(|c| c.is_ascii_digit()).collect();
        if !digits.is_empty() && tail[digits.len()..].starts_with(':') {
            return digits.parse().ok();
        }
        rest = tail;
    }
    None
}

/// `"name.lua:12: message"` → `"message"` (the error's own prefix names the place).
fn strip_location(msg: &str) -> String {
    if let Some(line) = line_of(msg) {
        let tag = format!(":{line}: ");
        if let Some(i) = msg.find(&tag) {
            return msg[i + tag.len()..].to_string();
        }
    }
    msg.to_string()
}

/// Line of the first occurrence of `needle` in `text` (for declaration errors).
fn line_in(text: &str, needle: &str) -> Option<usize> {
    text.lines().position(|l| l.contains(needle)).map(|i| i + 1)
}

/// Longest error text kept from a script, in characters.
pub const MAX_ERROR_CHARS: usize = 500;

/// A sandboxed VM with a script loaded and its buffers ready.
pub struct ScriptVm {
    lua: Lua,
    /// Lua heap size at which kernels are stopped with a line number (90 %
    /// of the hard limit, which the allocator enforces).
    memory_soft: usize,
    kernels: Vec<Function>,
    /// Voxel scripts: the material halo (10³ bytes) and output (8³ bytes).
    mat: Option<(Buffer, Buffer)>,
    /// Each kernel's [`crate::sim::interrupt::upvalue_fingerprint`] after loading:
    /// a call that changes it kept state between calls.
    prints: Vec<u64>,
    reads: Vec<Buffer>,
    writes: Vec<Buffer>,
    /// Per pass: indices into `reads` / `writes` (channel order of `spec.channels`).
    read_tables: Vec<Table>,
    write_tables: Vec<Table>,
    /// One context table per pass (`dt`, `p`, `r`, `w`), rebuilt each step.
    ctx: Vec<Table>,
    name: String,
    limits: Limits,
}

fn declaration(src: &ScriptSource, needle: Option<&str>, msg: impl Into<String>) -> SimError {
    SimError::Declaration {
        script: src.name.clone(),
        line: needle.and_then(|n| line_in(&src.text, n)),
        msg: msg.into(),
    }
}

/// The most channels one script may declare (the stored blobs' bound: a
/// chunk or column blob carries at most as many).
pub const MAX_SCRIPT_CHANNELS: usize = 256;
/// The most parameters one script may declare.
pub const MAX_SCRIPT_PARAMS: usize = 256;

fn strings(src: &ScriptSource, t: &Table, field: &str) -> Result<Vec<String>, SimError> {
    let v: Value = t
        .get(field)
        .map_err(|e| declaration(src, Some(field), e.to_string()))?;
    match v {
        Value::Nil => Ok(Vec::new()),
        Value::Table(list) => {
            let mut out = Vec::new();
            for item in list.sequence_values::<Value>() {
                match item {
                    Ok(Value::String(s)) => {
                        out.push(s.to_str().map(|s| s.to_string()).unwrap_or_default())
                    }
                    Ok(other) => {
                        return Err(declaration(
                            src,
                            Some(field),
                            format!("'{field}' must list strings, found a {}", other.type_name()),
                        ));
                    }
                    Err(e) => return Err(declaration(src, Some(field), e.to_string())),
                }
            }
            Ok(out)
        }
        other => Err(declaration(
            src,
            Some(field),
            format!(
                "'{field}' must be a list of strings, found a {}",
                other.type_name()
            ),
        )),
    }
}

fn number(src: &ScriptSource, t: &Table, field: &str, param: &str) -> Result<f64, SimError> {
    match t.get::<Value>(field) {
        Ok(Value::Number(n)) => Ok(n),
        Ok(Value::Integer(n)) => Ok(n as f64),
        Ok(other) => Err(declaration(
            src,
            Some(param),
            format!(
                "parameter '{param}': '{field}' must be a number, found a {}",
                other.type_name()
            ),
        )),
        Err(e) => Err(declaration(src, Some(param), e.to_string())),
    }
}

/// A fresh Luau VM with the sandbox every script runs in: only `math`,
/// `string`, `table`, `buffer`, `bit32` and `utf8`; no module loading,
/// environments, code from strings, GC control or stdout; no unseeded
/// randomness; read-only globals and libraries; the memory limit and the
/// uncatchable budget hook installed.
pub fn sandboxed(limits: Limits, name: &str) -> Result<Lua, SimError> {
    let libs =
        StdLib::MATH | StdLib::STRING | StdLib::TABLE | StdLib::BUFFER | StdLib::BIT | StdLib::UTF8;
    let lua = Lua::new_with(libs, LuaOptions::default())
        .map_err(|e| SimError::Internal(e.to_string()))?;
    // Globals that reach outside the script (module loading, environments,
    // code from strings, the GC, stdout) go before the environment is frozen.
    {
        let g = lua.globals();
        // Unseeded, per-VM randomness would make worlds irreproducible;
        // kernels get `c.random(...)` (deterministic) instead.
        if let Ok(math) = g.raw_get::<Table>("math") {
            for name in ["random", "randomseed"] {
                math.raw_remove(name)
                    .map_err(|e| SimError::Internal(e.to_string()))?;
            }
        }
        for name in [
            "require",
            "getfenv",
            "setfenv",
            "loadstring",
            "load",
            "dofile",
            "loadfile",
            "collectgarbage",
            "gcinfo",
            "newproxy",
            "print",
        ] {
            g.raw_remove(name)
                .map_err(|e| SimError::Internal(e.to_string()))?;
        }
    }
    // log(...): rate-limited lines to the daemon log and /status.
    let who = name.to_string();
    let log = lua
        .create_function(move |_, args: mlua::Variadic<Value>| {
            let parts: Vec<String> = args
                .iter()
                .map(|v| match v {
                    Value::Nil => "nil".into(),
                    Value::Boolean(b) => b.to_string(),
                    Value::Integer(i) => i.to_string(),
                    Value::Number(n) => n.to_string(),
                    Value::String(s) => s.to_string_lossy(),
                    other => other.type_name().to_string(),
                })
                .collect();
            crate::sim::runtime::log::push(&who, parts.join("\t"));
            Ok(())
        })
        .map_err(|e| SimError::Internal(e.to_string()))?;
    lua.globals()
        .raw_set("log", log)
        .map_err(|e| SimError::Internal(e.to_string()))?;
    lua.sandbox(true)
        .map_err(|e| SimError::Internal(e.to_string()))?;
    // Luau's sandbox gives each thread a writable proxy of the frozen
    // globals; freeze the proxy too, so `counter = counter + 1` is an
    // error instead of state that depends on which VM ran which tile.
    lua.globals().set_readonly(true);
    lua.set_memory_limit(limits.memory)
        .map_err(|e| SimError::Internal(e.to_string()))?;
    crate::sim::interrupt::install(&lua);
    // Optimisation level 2 inlines small local functions and unrolls loops;
    // type information lets native code use annotations (`W: buffer`).
    lua.set_compiler(
        mlua::chunk::Compiler::new()
            .set_optimization_level(2)
            .set_type_info_level(1),
    );
    Ok(lua)
}

impl ScriptVm {
    /// A fresh sandboxed VM with `src` loaded. Returns the VM and the
    /// validated declarations.
    pub fn load(src: &ScriptSource, limits: Limits) -> Result<(ScriptVm, ScriptSpec), SimError> {
        let lua = sandboxed(limits, &src.name)?;
        let chunk = lua.load(&*src.text).set_name(format!("@{}.lua", src.name));
        // The chunk itself runs under the budget too (a script can loop at load).
        crate::sim::interrupt::arm(
            limits.instructions,
            Instant::now() + limits.time,
            limits.memory / 10 * 9,
        );
        let def: Value = chunk.eval().map_err(|e| {
            let msg = e.to_string();
            match e {
                mlua::Error::SyntaxError { .. } => SimError::Syntax {
                    script: src.name.clone(),
                    line: line_of(&msg),
                    msg: strip_location(msg.lines().next().unwrap_or("")),
                },
                _ => SimError::Declaration {
                    script: src.name.clone(),
                    line: line_of(&msg),
                    msg: strip_location(
                        msg.lines()
                            .next()
                            .unwrap_or("")
                            .trim_start_matches("runtime error: "),
                    ),
                },
            }
        })?;
        let Value::Table(def) = def else {
            return Err(declaration(
                src,
                None,
                format!(
                    "the script must return a table, it returned a {}",
                    def.type_name()
                ),
            ));
        };
        let spec = Self::parse_spec(src, &def)?;
        let mut vm = ScriptVm {
            lua,
            memory_soft: limits.memory / 10 * 9,
            kernels: Vec::new(),
            mat: None,
            prints: Vec::new(),
            reads: Vec::new(),
            writes: Vec::new(),
            read_tables: Vec::new(),
            write_tables: Vec::new(),
            ctx: Vec::new(),
            name: src.name.clone(),
            limits,
        };
        let passes: Table = def
            .get("passes")
            .map_err(|e| declaration(src, Some("passes"), e.to_string()))?;
        for (i, _) in spec.passes.iter().enumerate() {
            let p: Table = passes
                .get(i + 1)
                .map_err(|e| declaration(src, Some("passes"), e.to_string()))?;
            let k: Value = p
                .get("kernel")
                .map_err(|e| declaration(src, Some("kernel"), e.to_string()))?;
            match k {
                Value::Function(f) => {
                    crate::sim::interrupt::freeze_upvalues(&vm.lua, &f).map_err(|m| {
                        declaration(
                            src,
                            Some("kernel"),
                            format!("pass '{}': {m}", spec.passes[i].name),
                        )
                    })?;
                    vm.prints
                        .push(crate::sim::interrupt::upvalue_fingerprint(&vm.lua, &f));
                    vm.kernels.push(f);
                }
                _ => {
                    return Err(declaration(
                        src,
                        Some(&spec.passes[i].name),
                        format!("pass '{}' has no kernel function", spec.passes[i].name),
                    ));
                }
            }
        }
        vm.make_buffers(&spec)
            .map_err(|e| SimError::Internal(e.to_string()))?;
        Ok((vm, spec))
    }

    fn parse_spec(src: &ScriptSource, def: &Table) -> Result<ScriptSpec, SimError> {
        let channels = strings(src, def, "channels")?;
        if channels.len() > MAX_SCRIPT_CHANNELS {
            return Err(declaration(
                src,
                Some("channels"),
                format!(
                    "the script declares {} channels, more than {MAX_SCRIPT_CHANNELS}",
                    channels.len()
                ),
            ));
        }
        let voxel_grid = matches!(def.get::<Value>("grid"), Ok(Value::String(ref g)) if g.to_str().is_ok_and(|g| g == "voxels"));
        if channels.is_empty() && !voxel_grid {
            return Err(declaration(
                src,
                Some("channels"),
                "the script declares no channels",
            ));
        }
        let grid = match def.get::<Value>("grid") {
            Ok(Value::Nil) => Grid::Columns,
            Ok(Value::String(g)) if g.to_str().is_ok_and(|g| g == "columns") => Grid::Columns,
            Ok(Value::String(g)) if g.to_str().is_ok_and(|g| g == "voxels") => Grid::Voxels,
            _ => {
                return Err(declaration(
                    src,
                    Some("grid"),
                    "'grid' must be \"columns\" or \"voxels\"",
                ));
            }
        };
        let materials = strings(src, def, "materials")?;
        let only = strings(src, def, "only")?;
        let keep_awake = strings(src, def, "keep_awake")?;
        let conserved = strings(src, def, "conserved")?;
        let sky = match def.get::<Value>("sky") {
            Ok(Value::Nil) => false,
            Ok(Value::Boolean(b)) if grid == Grid::Voxels || !b => b,
            _ => {
                return Err(declaration(
                    src,
                    Some("sky"),
                    "'sky' is true or false, for voxel scripts",
                ));
            }
        };
        let known = |name: &str, what: &str| -> Result<(), SimError> {
            if channels.iter().any(|c| c == name) {
                Ok(())
            } else {
                Err(declaration(
                    src,
                    Some(&format!("\"{name}\"")),
                    format!(
                        "{what} names unknown channel '{name}' (declared: {})",
                        channels.join(", ")
                    ),
                ))
            }
        };
        let mut boundary = Vec::new();
        match def.get::<Value>("boundary") {
            Ok(Value::Nil) => {}
            Ok(Value::Table(t)) => {
                for pair in t.pairs::<String, f64>() {
                    let (ch, v) = pair.map_err(|e| {
                        declaration(
                            src,
                            Some("boundary"),
                            format!("'boundary' maps channel names to numbers: {e}"),
                        )
                    })?;
                    known(&ch, "'boundary'")?;
                    if !v.is_finite() {
                        return Err(declaration(
                            src,
                            Some("boundary"),
                            format!("boundary.{ch} must be finite"),
                        ));
                    }
                    boundary.push((ch, v));
                }
                boundary.sort_by(|a, b| a.0.cmp(&b.0));
            }
            _ => {
                return Err(declaration(
                    src,
                    Some("boundary"),
                    "'boundary' must be a table",
                ));
            }
        }
        let drains = strings(src, def, "drains")?;
        for d in &drains {
            known(d, "'drains'")?;
        }
        let cfl = match def.get::<Value>("cfl") {
            Ok(Value::Nil) => None,
            Ok(Value::Table(t)) => {
                let bad = || {
                    declaration(
                        src,
                        Some("cfl"),
                        "'cfl' is { depth = CHANNEL, velocities = { CHANNEL… }, gravity = PARAM, dx = PARAM }",
                    )
                };
                let depth: String = t.get("depth").map_err(|_| bad())?;
                let gravity: String = t.get("gravity").map_err(|_| bad())?;
                let dx: String = t.get("dx").map_err(|_| bad())?;
                let velocities = strings(src, &t, "velocities")?;
                known(&depth, "'cfl.depth'")?;
                for v in &velocities {
                    known(v, "'cfl.velocities'")?;
                }
                Some(CflSpec {
                    depth,
                    velocities,
                    gravity,
                    dx,
                })
            }
            _ => return Err(declaration(src, Some("cfl"), "'cfl' must be a table")),
        };
        let mut fills = Vec::new();
        match def.get::<Value>("fills") {
            Ok(Value::Nil) => {}
            Ok(Value::Table(t)) => {
                for pair in t.pairs::<String, String>() {
                    let (ch, m) = pair.map_err(|e| {
                        declaration(
                            src,
                            Some("fills"),
                            format!("'fills' maps channel names to material names: {e}"),
                        )
                    })?;
                    if !channels.contains(&ch) || !materials.contains(&m) {
                        return Err(declaration(
                            src,
                            Some("fills"),
                            format!(
                                "fills.{ch} = \"{m}\": the channel must be in 'channels' and the material in 'materials'"
                            ),
                        ));
                    }
                    fills.push((ch, m));
                }
                fills.sort();
            }
            _ => return Err(declaration(src, Some("fills"), "'fills' must be a table")),
        }
        if grid == Grid::Columns {
            for (field, list) in [
                ("materials", &materials),
                ("only", &only),
                ("keep_awake", &keep_awake),
            ] {
                if !list.is_empty() {
                    return Err(declaration(
                        src,
                        Some(field),
                        format!("'{field}' is for voxel scripts (grid = \"voxels\")"),
                    ));
                }
            }
        }
        for m in only.iter().chain(&keep_awake) {
            if !materials.contains(m) {
                return Err(declaration(
                    src,
                    Some(m),
                    format!("material '{m}' must also be listed in 'materials'"),
                ));
            }
        }
        for c in &channels {
            if c == MAT && grid == Grid::Voxels {
                return Err(declaration(
                    src,
                    Some(c),
                    "'mat' is the material buffer; name the channel otherwise",
                ));
            }
            if c.is_empty() || !c.chars().all(|ch| ch.is_ascii_alphanumeric() || ch == '_') {
                return Err(declaration(
                    src,
                    Some(c),
                    format!("channel name '{c}' must be letters, digits and '_'"),
                ));
            }
        }
        let nonnegative = strings(src, def, "nonnegative")?;
        for c in &nonnegative {
            known(c, "'nonnegative'")?;
        }
        for c in &conserved {
            known(c, "'conserved'")?;
        }
        let mut params = Vec::new();
        match def.get::<Value>("params") {
            Ok(Value::Nil) => {}
            Ok(Value::Table(t)) => {
                for pair in t.pairs::<String, Value>() {
                    // Every parameter is in each `/status` and each step's
                    // context: 50 000 of them slowed the engine fourfold.
                    if params.len() == MAX_SCRIPT_PARAMS {
                        return Err(declaration(
                            src,
                            Some("params"),
                            format!("more than {MAX_SCRIPT_PARAMS} parameters"),
                        ));
                    }
                    let (name, v) =
                        pair.map_err(|e| declaration(src, Some("params"), format!("params: {e}")))?;
                    let Value::Table(p) = v else {
                        return Err(declaration(
                            src,
                            Some(&name),
                            format!("parameter '{name}' must be a table {{default, min, max}}"),
                        ));
                    };
                    let (default, min, max) = (
                        number(src, &p, "default", &name)?,
                        number(src, &p, "min", &name)?,
                        number(src, &p, "max", &name)?,
                    );
                    if min.is_nan()
                        || max.is_nan()
                        || min > max
                        || !(min..=max).contains(&default)
                        || !default.is_finite()
                    {
                        return Err(declaration(
                            src,
                            Some(&name),
                            format!(
                                "parameter '{name}': default {default} is outside [{min}, {max}]"
                            ),
                        ));
                    }
                    params.push(ParamSpec {
                        name,
                        default,
                        min,
                        max,
                    });
                }
                params.sort_by(|a, b| a.name.cmp(&b.name));
            }
            Ok(other) => {
                return Err(declaration(
                    src,
                    Some("params"),
                    format!("'params' must be a table, found a {}", other.type_name()),
                ));
            }
            Err(e) => return Err(declaration(src, Some("params"), e.to_string())),
        }
        let mut ranges = Vec::new();
        match def.get::<Value>("ranges") {
            Ok(Value::Nil) => {}
            Ok(Value::Table(t)) => {
                for pair in t.pairs::<String, Value>() {
                    let (name, v) =
                        pair.map_err(|e| declaration(src, Some("ranges"), format!("ranges: {e}")))?;
                    known(&name, "'ranges'")?;
                    let bad = || {
                        declaration(
                            src,
                            Some("ranges"),
                            format!("ranges.{name} must be {{min, max}} with min <= max, finite"),
                        )
                    };
                    let Value::Table(r) = v else {
                        return Err(bad());
                    };
                    let (lo, hi): (f64, f64) =
                        (r.get(1).map_err(|_| bad())?, r.get(2).map_err(|_| bad())?);
                    if !(lo.is_finite() && hi.is_finite() && lo <= hi) {
                        return Err(bad());
                    }
                    ranges.push((name, lo, hi));
                }
                ranges.sort_by(|a, b| a.0.cmp(&b.0));
            }
            Ok(other) => {
                return Err(declaration(
                    src,
                    Some("ranges"),
                    format!("'ranges' must be a table, found a {}", other.type_name()),
                ));
            }
            Err(e) => return Err(declaration(src, Some("ranges"), e.to_string())),
        }
        let passes_v: Value = def
            .get("passes")
            .map_err(|e| declaration(src, Some("passes"), e.to_string()))?;
        let Value::Table(passes_t) = passes_v else {
            return Err(declaration(
                src,
                Some("passes"),
                "the script has no 'passes' list (each pass needs a kernel)",
            ));
        };
        let mut passes = Vec::new();
        for (i, p) in passes_t.sequence_values::<Value>().enumerate() {
            let p = p.map_err(|e| declaration(src, Some("passes"), e.to_string()))?;
            let Value::Table(p) = p else {
                return Err(declaration(
                    src,
                    Some("passes"),
                    format!("passes[{}] must be a table", i + 1),
                ));
            };
            let name: String = match p.get::<Value>("name") {
                Ok(Value::String(s)) => s.to_str().map(|s| s.to_string()).unwrap_or_default(),
                _ => format!("pass{}", i + 1),
            };
            let reads = strings(src, &p, "reads")?;
            let writes = strings(src, &p, "writes")?;
            let is_mat = |c: &str| grid == Grid::Voxels && c == MAT;
            for r in reads.iter().filter(|r| !is_mat(r)) {
                known(r, &format!("pass '{name}' reads"))?;
            }
            for w in writes.iter().filter(|w| !is_mat(w)) {
                known(w, &format!("pass '{name}' writes"))?;
            }
            if writes.is_empty() {
                return Err(declaration(
                    src,
                    Some(&name),
                    format!("pass '{name}' writes no channel"),
                ));
            }
            passes.push(PassSpec {
                name,
                reads,
                writes,
            });
        }
        if passes.is_empty() {
            return Err(declaration(
                src,
                Some("passes"),
                "the script declares no passes",
            ));
        }
        if let Some(c) = &cfl {
            for p in [&c.gravity, &c.dx] {
                if !params.iter().any(|q| &q.name == p) {
                    return Err(declaration(
                        src,
                        Some("cfl"),
                        format!("cfl names parameter '{p}', which the script does not declare"),
                    ));
                }
            }
        }
        Ok(ScriptSpec {
            name: src.name.clone(),
            grid,
            materials,
            only,
            keep_awake,
            conserved,
            sky,
            boundary,
            cfl,
            drains,
            fills,
            channels,
            nonnegative,
            params,
            ranges,
            passes,
        })
    }

    fn make_buffers(&mut self, spec: &ScriptSpec) -> mlua::Result<()> {
        let (halo, own) = match spec.grid {
            Grid::Columns => (HALO_CELLS * 8, TILE_CELLS * 8),
            Grid::Voxels => (VOXEL_HALO * 4, VOXEL_CELLS * 4),
        };
        for _ in &spec.channels {
            self.reads.push(self.lua.create_buffer_with_capacity(halo)?);
            self.writes.push(self.lua.create_buffer_with_capacity(own)?);
        }
        if spec.grid == Grid::Voxels {
            self.mat = Some((
                self.lua.create_buffer_with_capacity(VOXEL_HALO)?,
                self.lua.create_buffer_with_capacity(VOXEL_CELLS)?,
            ));
        }
        for pass in &spec.passes {
            let r = self.lua.create_table()?;
            if let Some((mr, _)) = &self.mat {
                // Materials are always readable, with the halo.
                r.set(MAT, mr.clone())?;
            }
            for name in pass
                .reads
                .iter()
                .filter(|n| spec.grid == Grid::Columns || *n != MAT)
            {
                let i = spec.channels.iter().position(|c| c == name).unwrap_or(0);
                r.set(name.as_str(), self.reads[i].clone())?;
            }
            let w = self.lua.create_table()?;
            if let Some((_, mw)) = &self.mat
                && pass.writes.iter().any(|w| w == MAT)
            {
                w.set(MAT, mw.clone())?;
            }
            for name in pass
                .writes
                .iter()
                .filter(|n| spec.grid == Grid::Columns || *n != MAT)
            {
                let i = spec.channels.iter().position(|c| c == name).unwrap_or(0);
                w.set(name.as_str(), self.writes[i].clone())?;
            }
            // Read-only, as `c` is: a table that kept what a kernel stored
            // in it would carry state from tile to tile on one VM, and the
            // result would depend on the thread count (regression).
            r.set_readonly(true);
            w.set_readonly(true);
            self.read_tables.push(r);
            self.write_tables.push(w);
        }
        Ok(())
    }

    /// Prepare a step: time step, parameter values (in `spec.params`
    /// order), and the key of the step's random numbers.
    pub fn begin_step(
        &mut self,
        dt: f64,
        spec: &ScriptSpec,
        params: &[f64],
        key: StepKey,
        material_ids: &[u8],
    ) -> Result<(), SimError> {
        let make = || -> mlua::Result<Vec<Table>> {
            let m = self.lua.create_table()?;
            m.set("air", 0)?;
            for (name, id) in spec.materials.iter().zip(material_ids) {
                m.set(name.as_str(), *id)?;
            }
            m.set_readonly(true);
            let random = self.lua.create_function(
                move |_, (x, y, z, k): (f64, Option<f64>, Option<f64>, Option<f64>)| {
                    Ok(key.random(x, y.unwrap_or(0.0), z.unwrap_or(0.0), k.unwrap_or(0.0)))
                },
            )?;
            let p = self.lua.create_table()?;
            for (s, v) in spec.params.iter().zip(params) {
                p.set(s.name.as_str(), *v)?;
            }
            p.set_readonly(true);
            let mut out = Vec::with_capacity(self.read_tables.len());
            for (r, w) in self.read_tables.iter().zip(&self.write_tables) {
                let c = self.lua.create_table()?;
                c.set("dt", dt)?;
                c.set("tick", key.tick)?;
                c.set("random", random.clone())?;
                c.set("p", p.clone())?;
                c.set("m", m.clone())?;
                c.set("r", r.clone())?;
                c.set("w", w.clone())?;
                c.set_readonly(true);
                out.push(c);
            }
            Ok(out)
        };
        self.ctx = make().map_err(|e| SimError::Internal(e.to_string()))?;
        Ok(())
    }

    /// Halo buffer of channel `ch` (index in the spec's channel list).
    pub fn read_buffer(&self, ch: usize) -> &Buffer {
        &self.reads[ch]
    }

    /// Output buffer of channel `ch`.
    pub fn write_buffer(&self, ch: usize) -> &Buffer {
        &self.writes[ch]
    }

    /// The material halo (10³ bytes, x fastest, then y, then z) and output
    /// (8³ bytes) buffers of a voxel script.
    pub fn material_buffers(&self) -> Option<&(Buffer, Buffer)> {
        self.mat.as_ref()
    }

    /// Run pass `pass` of a voxel script on brick `b`. Buffers must be
    /// filled beforehand.
    pub fn run_voxel(&mut self, pass: usize, pass_name: &str, b: [i32; 3]) -> Result<(), SimError> {
        self.call(pass, pass_name, (b[0], b[1], Some(b[2])))
            .map_err(|e| match e {
                SimError::Runtime {
                    script,
                    pass,
                    line,
                    msg,
                    ..
                } => SimError::Runtime {
                    script,
                    pass,
                    tile: (b[0], b[2]),
                    line,
                    msg: format!("brick ({}, {}, {}): {msg}", b[0], b[1], b[2]),
                },
                other => other,
            })
    }

    /// Run pass `pass` on tile (tx, tz). Buffers must be filled beforehand.
    pub fn run(&mut self, pass: usize, pass_name: &str, tx: i32, tz: i32) -> Result<(), SimError> {
        self.call(pass, pass_name, (tx, tz, None))
    }

    fn call(
        &mut self,
        pass: usize,
        pass_name: &str,
        (tx, tz, third): (i32, i32, Option<i32>),
    ) -> Result<(), SimError> {
        let ctx = self
            .ctx
            .get(pass)
            .ok_or_else(|| SimError::Internal("begin_step was not called".into()))?;
        let run = || -> mlua::Result<()> {
            crate::sim::interrupt::arm(
                self.limits.instructions,
                Instant::now() + self.limits.time,
                self.memory_soft,
            );
            match third {
                None => self.kernels[pass].call::<()>((ctx.clone(), tx, tz))?,
                Some(z) => self.kernels[pass].call::<()>((ctx.clone(), tx, tz, z))?,
            }
            // A script that caught its own budget error still failed.
            if let Some(what) = crate::sim::interrupt::tripped() {
                return Err(mlua::Error::runtime(format!(
                    "{what} exceeded (the script caught the error, but a budget cannot be caught)"
                )));
            }
            // State kept between calls would depend on which VM ran which tile.
            if crate::sim::interrupt::upvalue_fingerprint(&self.lua, &self.kernels[pass])
                != self.prints[pass]
            {
                return Err(mlua::Error::runtime(
                    "the kernel changed a variable outside itself (a local of the script, or one a helper function captures); kernels must keep no state between calls: use a channel",
                ));
            }
            Ok(())
        };
        run().map_err(|e| {
            let msg = match &e {
                mlua::Error::CallbackError { cause, .. } => cause.to_string(),
                other => other.to_string(),
            };
            let msg = msg
                .lines()
                .next()
                .unwrap_or("")
                .trim_start_matches("runtime error: ");
            // A script's own error text is cut to a readable length
            // (regression: `error(string.rep("E", 1e7))` was one 10 MB line).
            let msg = match msg.char_indices().nth(MAX_ERROR_CHARS) {
                Some((i, _)) => format!("{}… (cut at {MAX_ERROR_CHARS} characters)", &msg[..i]),
                None => msg.to_string(),
            };
            let line =
                line_of(&msg).or_else(|| msg.rsplit("line ").next().and_then(|s| s.parse().ok()));
            SimError::Runtime {
                script: self.name.clone(),
                pass: pass_name.to_string(),
                tile: (tx, tz),
                line,
                msg: strip_location(&msg),
            }
        })
    }
}
