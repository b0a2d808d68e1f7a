//! Sandboxed Luau VMs that load a script and run its kernels under
//! budgets that cannot be caught. What a script declares is
//! [`super::spec`] (re-exported here); reading the declaration is
//! [`super::declare`].
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
//! every kernel call an instruction budget and a time budget (the thread's
//! own running time: see `cpu_clock`) checked from Luau's interrupt; a script that exceeds them is stopped with an error
//! naming the script and line. Out-of-memory errors pass through `pcall`,
//! and a call that ran out is run once more from collected garbage
//! ([`ScriptVm::failed_on_memory`]); `tostring` never shows an address.

use std::time::Duration;

use mlua::{Buffer, Function, Lua, Table, Value};

use super::declare::declaration;
pub use super::declare::{MAX_SCRIPT_CHANNELS, MAX_SCRIPT_PARAMS};
use super::errors::one_line;
pub use super::errors::{MAX_ERROR_CHARS, line_of, without_addresses};
pub use super::random::StepKey;
use super::sandbox::HeldLog;
pub use super::sandbox::sandboxed;
pub use super::spec::*;
use crate::sim::SimError;
use crate::sim::tile::{HALO_CELLS, TILE_CELLS};

/// Resource limits of a VM.
#[derive(Clone, Copy, Debug)]
pub struct Limits {
    /// Bytes of Lua heap per VM.
    pub memory: usize,
    /// Interrupt ticks (loop iterations and calls) per kernel call.
    pub instructions: u64,
    /// Running time per kernel call: the calling thread's CPU time, so that
    /// time the process was stopped or waited for a core is not counted.
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

/// A sandboxed VM with a script loaded and its buffers ready.
pub struct ScriptVm {
    lua: Lua,
    /// Lua heap size at which kernels are stopped with a line number (90 %
    /// of the hard limit, which the allocator enforces).
    memory_soft: usize,
    kernels: Vec<Function>,
    /// Voxel scripts: the material halo (10³ bytes) and output (8³ bytes).
    mat: Option<(Buffer, Buffer)>,
    /// Each kernel's [`crate::sim::interrupt::fingerprint`] after loading:
    /// a call that changes it kept state between calls.
    prints: Vec<crate::sim::interrupt::Fingerprint>,
    /// Per kernel: every function it reaches, itself first
    /// ([`crate::sim::interrupt::seal`]).
    held: Vec<Table>,
    reads: Vec<Buffer>,
    writes: Vec<Buffer>,
    /// Per pass: indices into `reads` / `writes` (channel order of `spec.channels`).
    read_tables: Vec<Table>,
    write_tables: Vec<Table>,
    /// One context table per pass (`dt`, `p`, `r`, `w`), rebuilt each step.
    ctx: Vec<Table>,
    /// The metatables of `c.p`, `c.m` and `c` ([`super::strict`]).
    strict: Option<[Table; 3]>,
    name: String,
    limits: Limits,
    /// Whether the last call failed for want of memory (the soft limit or
    /// the allocator's).
    memory_failure: bool,
}

/// Luau's text for an allocation the memory limit refused.
pub const OUT_OF_MEMORY: &str = "not enough memory";

/// The one-line error of a script's chunk that failed to run at load: its
/// syntax error or its runtime error, at its line, without Luau's repeated
/// location, the `runtime error:` tag or a stack traceback.
pub(super) fn load_error(src: &ScriptSource, e: mlua::Error) -> SimError {
    // Only a location of the script's own, at the start, is a line: text
    // the script raised (`error("x.lua:42: hi", 0)`) is not (review).
    let (line, msg) = super::declare::read::lua_text(src, &e);
    match e {
        mlua::Error::SyntaxError { .. } => SimError::Syntax {
            script: src.name.clone(),
            line,
            msg: one_line(&msg),
        },
        _ => SimError::Declaration {
            script: src.name.clone(),
            line,
            msg: one_line(&msg),
        },
    }
}

impl ScriptVm {
    /// A fresh sandboxed VM with `src` loaded. Returns the VM and the
    /// validated declarations.
    pub fn load(src: &ScriptSource, limits: Limits) -> Result<(ScriptVm, ScriptSpec), SimError> {
        let bytecode = super::compile::shared_bytecode(src)?;
        let lua = sandboxed(limits, &src.name)?;
        super::compile::native_code_for(&lua, &src.text);
        let chunk = match &bytecode {
            Some(b) => lua.load(&b[..]).set_mode(mlua::chunk::ChunkMode::Binary),
            None => lua.load(&*src.text),
        }
        .set_name(format!("@{}.lua", src.name));
        // The chunk itself runs under the budget too (a script can loop at load).
        crate::sim::interrupt::arm(limits.instructions, limits.time, limits.memory / 10 * 9);
        let def: Value = chunk.eval().map_err(|e| load_error(src, e))?;
        let Value::Table(def) = def else {
            return Err(declaration(
                src,
                None,
                format!(
                    "the script must return a table, it returned {}",
                    super::declare::a(def.type_name())
                ),
            ));
        };
        let spec = super::declare::parse(src, &def)?;
        let mut vm = ScriptVm {
            lua,
            memory_soft: limits.memory / 10 * 9,
            kernels: Vec::new(),
            mat: None,
            prints: Vec::new(),
            held: Vec::new(),
            reads: Vec::new(),
            writes: Vec::new(),
            read_tables: Vec::new(),
            strict: None,
            write_tables: Vec::new(),
            ctx: Vec::new(),
            name: src.name.clone(),
            limits,
            memory_failure: false,
        };
        let passes: Table = def
            .get("passes")
            .map_err(|e| super::declare::read::from_lua(src, Some("passes"), &e))?;
        for (i, _) in spec.passes.iter().enumerate() {
            let p: Table = passes
                .get(i + 1)
                .map_err(|e| super::declare::read::from_lua(src, Some("passes"), &e))?;
            let k: Value = p
                .get("kernel")
                .map_err(|e| super::declare::read::from_lua(src, Some("kernel"), &e))?;
            match k {
                Value::Function(f) => {
                    let held = crate::sim::interrupt::seal(&vm.lua, &f).map_err(|m| {
                        declaration(
                            src,
                            Some("kernel"),
                            format!("pass '{}': {m}", spec.passes[i].name),
                        )
                    })?;
                    let print = crate::sim::interrupt::fingerprint(&vm.lua, &held)
                        .ok_or_else(|| {
                            declaration(
                                src,
                                Some("kernel"),
                                format!(
                                    "pass '{}': the kernel's state could not be read (out of memory?)",
                                    spec.passes[i].name
                                ),
                            )
                        })?;
                    vm.prints.push(print);
                    vm.held.push(held);
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
        let make = super::strict::maker(&self.lua)?;
        for pass in &spec.passes {
            let r = self.lua.create_table()?;
            if let Some((mr, _)) = &self.mat {
                // Materials are always readable, with the halo.
                r.set(MAT, mr.clone())?;
            }
            for &i in &pass.read_idx {
                r.set(spec.channels[i].as_str(), self.reads[i].clone())?;
            }
            let w = self.lua.create_table()?;
            if let Some((_, mw)) = &self.mat
                && pass.writes.iter().any(|w| w == MAT)
            {
                w.set(MAT, mw.clone())?;
            }
            for &i in &pass.write_idx {
                w.set(spec.channels[i].as_str(), self.writes[i].clone())?;
            }
            // A name the pass does not list is an error that says so
            // (claims audit: `c.w.mat` in a pass that does not write "mat"
            // was nil, and the kernel failed on "buffer expected, got nil").
            r.set_metatable(Some(super::strict::unlisted(
                &make, &pass.name, "r", "reads",
            )?))?;
            w.set_metatable(Some(super::strict::unlisted(
                &make, &pass.name, "w", "writes",
            )?))?;
            // Read-only, as `c` is: a table that kept what a kernel stored
            // in it would carry state from tile to tile on one VM, and the
            // result would depend on the thread count (regression).
            r.set_readonly(true);
            w.set_readonly(true);
            self.read_tables.push(r);
            self.write_tables.push(w);
        }
        // Misspelt parameters, materials and fields of `c` too (modder
        // probe: they read as nil, and failed lines later).
        let names = spec.params.iter().map(|p| p.name.as_str());
        let materials = spec.materials.iter().map(String::as_str);
        self.strict = Some([
            super::strict::unknown_param(&make, &spec.name, names)?,
            super::strict::unknown_material(&make, &spec.name, materials)?,
            super::strict::unknown_field(&make)?,
        ]);
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
            if let Some([_, mm, _]) = &self.strict {
                m.set_metatable(Some(mm.clone()))?;
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
            if let Some([pm, _, _]) = &self.strict {
                p.set_metatable(Some(pm.clone()))?;
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
                if let Some([_, _, cm]) = &self.strict {
                    c.set_metatable(Some(cm.clone()))?;
                }
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

    /// Run pass `pass` of a voxel script on brick `b`, after `fill` has
    /// filled its buffers (again, if the call runs twice: see
    /// [`failed_on_memory`](Self::failed_on_memory)).
    pub fn run_voxel(
        &mut self,
        pass: usize,
        pass_name: &str,
        b: [i32; 3],
        fill: impl FnMut(&ScriptVm),
    ) -> Result<(), SimError> {
        self.call(pass, pass_name, (b[0], b[1], Some(b[2])), fill)
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
                    at: crate::sim::CallSite::Brick(b),
                    line,
                    msg,
                },
                other => other,
            })
    }

    /// Run pass `pass` on tile (tx, tz), after `fill` has filled its
    /// buffers (again, if the call runs twice).
    pub fn run(
        &mut self,
        pass: usize,
        pass_name: &str,
        tx: i32,
        tz: i32,
        fill: impl FnMut(&ScriptVm),
    ) -> Result<(), SimError> {
        self.call(pass, pass_name, (tx, tz, None), fill)
    }

    /// One kernel call, run once more from collected garbage if it ran out
    /// of memory (its log lines then count once).
    fn call(
        &mut self,
        pass: usize,
        pass_name: &str,
        at: (i32, i32, Option<i32>),
        mut fill: impl FnMut(&ScriptVm),
    ) -> Result<(), SimError> {
        self.hold_log(true);
        let mut result = Ok(());
        for attempt in 0..2 {
            fill(self);
            result = self.call_once(pass, pass_name, at);
            if result.is_ok() || attempt == 1 || !self.memory_failure {
                break;
            }
            let _discarded = self.hold_log(true);
            self.collect_garbage();
        }
        let (lines, extra) = self.hold_log(false);
        for line in lines {
            crate::sim::runtime::log::push(&self.name, line);
        }
        crate::sim::runtime::log::drop_lines(&self.name, extra);
        result
    }

    /// Hold back `log()` lines (`on`) or stop; returns and forgets the
    /// lines held so far, and how many more were logged past the most held.
    fn hold_log(&self, on: bool) -> (Vec<String>, u64) {
        match self.lua.app_data_mut::<HeldLog>() {
            Some(mut held) => {
                held.on = on;
                (
                    std::mem::take(&mut held.lines),
                    std::mem::take(&mut held.extra),
                )
            }
            None => (Vec::new(), 0),
        }
    }

    /// Whether the last kernel call failed for want of memory. How much
    /// garbage was still uncollected decides that as much as the kernel
    /// does, so [`run`](Self::run) and [`run_voxel`](Self::run_voxel) run
    /// such a call once more after [`collect_garbage`](Self::collect_garbage),
    /// with its buffers filled again, and take that verdict: it starts from
    /// the VM's live data only, the same whichever tiles the VM ran before.
    pub fn failed_on_memory(&self) -> bool {
        self.memory_failure
    }

    /// A full garbage collection of the VM (between kernel calls).
    pub fn collect_garbage(&self) {
        let _ = self.lua.gc_collect();
    }

    fn call_once(
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
                self.limits.time,
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
            match crate::sim::interrupt::unchanged(&self.lua, &self.held[pass], &self.prints[pass])
            {
                Some(true) => {}
                Some(false) => {
                    return Err(mlua::Error::runtime(
                        "the kernel changed a variable outside itself (a local of the script, or one a helper function captures); kernels must keep no state between calls: use a channel",
                    ));
                }
                None => {
                    return Err(mlua::Error::runtime(
                        "the engine could not check that the kernel kept no state (out of memory?)",
                    ));
                }
            }
            Ok(())
        };
        let result = run();
        self.memory_failure = match &result {
            Ok(()) => false,
            Err(e) => {
                crate::sim::interrupt::tripped() == Some(crate::sim::interrupt::MEMORY_LIMIT)
                    || matches!(e, mlua::Error::MemoryError(_))
                    || e.to_string().contains(OUT_OF_MEMORY)
            }
        };
        result.map_err(|e| {
            let msg = match &e {
                mlua::Error::CallbackError { cause, .. } => cause.to_string(),
                other => other.to_string(),
            };
            // The line from the script's own location or Luau's traceback,
            // never from text the script raised (regression, fuzzing:
            // `error("see line 99", 0)` was reported at line 99, and
            // `error("other.lua:42: x", 0)` at 42 with its text cut).
            let (line, first) = super::declare::read::lua_text_of(&self.name, &msg);
            let line = line.or_else(|| {
                // No traceback: the budget's own "… at line N", else a
                // location in the text.
                let first = msg.lines().next().unwrap_or("");
                first
                    .rsplit("at line ")
                    .next()
                    .filter(|_| first.contains("at line "))
                    .and_then(|s| s.parse().ok())
                    .or_else(|| line_of(first))
            });
            SimError::Runtime {
                script: self.name.clone(),
                pass: pass_name.to_string(),
                at: crate::sim::CallSite::Tile(tx, tz),
                line,
                msg: one_line(&first),
            }
        })
    }
}
