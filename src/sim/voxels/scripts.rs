//! Voxel scripts in a [`VoxelSim`]: loading one (declarations checked
//! against the material registry, then a smoke test on an empty brick),
//! replacing it on hot reload (parameters kept), native reference kernels,
//! and each script's rate, parameters and health.

use rustc_hash::{FxHashMap, FxHashSet};

use super::channels::VoxelChannelId;
use super::exec::VoxelKernel;
use super::native::VoxelNativeKernel;
use super::schedule::{MatSet, set_of};
use super::step::{BOUNDARY, VoxelSim};
use crate::sim::script::{Grid, VOXEL_CELLS, VOXEL_HALO};
use crate::sim::slot::ScriptSlot;
use crate::sim::{Limits, ScriptSource, ScriptSpec, ScriptVm, SimError, StepKey};
use crate::world::MaterialRegistry;

/// A loaded voxel script: what both grids keep ([`ScriptSlot`], which it
/// dereferences to), its channel and material ids, where it runs and its
/// kernel.
pub(super) struct Loaded {
    pub(super) slot: ScriptSlot,
    pub(super) channel_ids: Vec<VoxelChannelId>,
    pub(super) material_ids: Vec<u8>,
    pub(super) only: Option<MatSet>,
    pub(super) keep_awake: MatSet,
    pub(super) kernel: VoxelKernel,
}

crate::sim::slot::extends_slot!(Loaded);

impl VoxelSim {
    /// Number of scripts.
    pub fn script_count(&self) -> usize {
        self.scripts.len()
    }

    /// Declarations of script `i`.
    pub fn spec(&self, i: usize) -> &ScriptSpec {
        &self.scripts[i].spec
    }

    /// Why script `i` is suspended, if it is.
    pub fn suspended(&self, i: usize) -> Option<&SimError> {
        self.scripts[i].health.suspended()
    }

    /// Current parameter values of script `i` (spec order).
    pub fn params(&self, i: usize) -> &[f64] {
        &self.scripts[i].params
    }

    /// Failed steps in a row of script `i`.
    pub fn failures(&self, i: usize) -> u32 {
        self.scripts[i].health.failures()
    }

    /// Replace script `i` with a new version (its materials must be
    /// registered), keeping parameter values, clamped into narrowed ranges
    /// with a warning. A suspended script runs again.
    pub fn replace_script(
        &mut self,
        i: usize,
        src: ScriptSource,
        registry: &MaterialRegistry,
    ) -> Result<Vec<String>, SimError> {
        let mut trial = VoxelSim {
            channels: self.channels.clone(),
            scripts: Vec::new(),
            lo: self.lo,
            hi: self.hi,
            voxels: self.voxels,
            arena_limit: self.arena_limit,
            active: FxHashSet::default(),
            quiet: FxHashMap::default(),
            presence: FxHashMap::default(),
            wake_pending: false,
            tick: self.tick,
            seed: self.seed,
        };
        trial.load_script(src, self.scripts[i].limits, registry, true)?;
        let mut new = trial.scripts.pop().expect("added");
        for name in trial
            .channels
            .names()
            .iter()
            .skip(self.channels.names().len())
        {
            self.channels.channel(name);
        }
        new.channel_ids = new
            .spec
            .channels
            .iter()
            .map(|c| self.channels.channel(c))
            .collect();
        let warnings = new.slot.carry_over(&self.scripts[i].slot);
        self.scripts[i] = new;
        self.wake_all_known();
        Ok(warnings)
    }

    /// Script `i`'s source, limits, rate and health, for a rebuild.
    pub fn script_state(&self, i: usize) -> crate::sim::ScriptState {
        self.scripts[i].state()
    }

    /// Give script `i` the health a rebuilt simulation carries over.
    pub fn set_health(&mut self, i: usize, failures: u32, suspended: Option<SimError>) {
        self.scripts[i].restore_health(failures, suspended);
    }

    /// Run script `i` on ticks that are multiples of `every`.
    pub fn set_every(&mut self, i: usize, every: u64) {
        self.scripts[i].set_every(every);
    }

    /// The tick interval of script `i`.
    pub fn every(&self, i: usize) -> u64 {
        self.scripts[i].every
    }

    /// Set a parameter (refused outside its declared range).
    pub fn set_param(&mut self, i: usize, name: &str, value: f64) -> Result<(), SimError> {
        self.scripts[i].set_param(name, value)?;
        self.wake_all_known();
        Ok(())
    }

    /// Load a voxel script. Its materials must be registered.
    pub fn add_script(
        &mut self,
        src: ScriptSource,
        limits: Limits,
        registry: &MaterialRegistry,
    ) -> Result<usize, SimError> {
        self.load_script(src, limits, registry, false)
    }

    /// [`Self::add_script`], for a first load or a `reload` of a running
    /// script (which changes what a wrong grid's error says).
    fn load_script(
        &mut self,
        src: ScriptSource,
        limits: Limits,
        registry: &MaterialRegistry,
        reload: bool,
    ) -> Result<usize, SimError> {
        let (mut vm, spec) = ScriptVm::load(&src, limits)?;
        if spec.grid != Grid::Voxels {
            return Err(spec.grid.mismatch(&spec.name, reload));
        }
        let material_ids = spec
            .materials
            .iter()
            .map(|m| {
                registry.id(m).ok_or_else(|| SimError::Declaration {
                    script: spec.name.clone(),
                    line: crate::sim::runtime::declare::string_line_in(&src.text, m),
                    msg: format!("unknown material '{m}' (declare it in materials.lua)"),
                })
            })
            .collect::<Result<Vec<u8>, SimError>>()?;
        let id_of = |names: &[String]| {
            set_of(names.iter().filter_map(|n| {
                spec.materials
                    .iter()
                    .position(|m| m == n)
                    .map(|i| material_ids[i])
            }))
        };
        // Smoke test, as for column scripts: every pass once on a test
        // brick at tick 0, in this fresh VM, so a broken save is refused at
        // load and a hot reload keeps the version that works (regression:
        // it replaced it and failed every step). The brick is air, or the
        // first `only` material for a script that runs only where it is
        // (regression: such kernels met air they never see in a step).
        // Channels are 0.
        let (sample, sample_name) = spec
            .only
            .first()
            .and_then(|n| spec.materials.iter().position(|m| m == n))
            .map_or((0, "air".to_string()), |i| {
                (material_ids[i], format!("'{}'", spec.materials[i]))
            });
        let defaults: Vec<f64> = spec.params.iter().map(|p| p.default).collect();
        vm.begin_step(
            0.01,
            &spec,
            &defaults,
            StepKey::new(self.seed, 0, &spec.name),
            &material_ids,
        )?;
        for (pi, pass) in spec.passes.iter().enumerate() {
            crate::sim::runtime::log::at_load(|| {
                vm.run_voxel(pi, &pass.name, [0, 0, 0], |vm| {
                    let (halo, own) = vm
                        .material_buffers()
                        .expect("a voxel VM has material buffers");
                    halo.write_bytes(0, &[sample; VOXEL_HALO]);
                    own.write_bytes(0, &[sample; VOXEL_CELLS]);
                    // Channels are 0 for every pass, as a step fills them
                    // afresh (regression, modder probe: a pass that wrote
                    // into its read buffers showed the next pass its
                    // scribbles, here only).
                    for ch in 0..spec.channels.len() {
                        for b in [vm.read_buffer(ch), vm.write_buffer(ch)] {
                            b.write_bytes(0, &vec![0u8; b.len()]);
                        }
                    }
                })
            })
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
                    at: crate::sim::CallSite::TestBrick(sample_name.to_string()),
                    line,
                    msg,
                },
                other => other,
            })?;
            let (_, written) = vm
                .material_buffers()
                .expect("a voxel VM has material buffers");
            let written: [u8; VOXEL_CELLS] = written.read_bytes(0);
            if let Some(&bad) = written
                .iter()
                .find(|&&m| m != 0 && (m == BOUNDARY || registry.get(m).is_none()))
            {
                return Err(SimError::Runtime {
                    script: spec.name.clone(),
                    pass: pass.name.clone(),
                    at: crate::sim::CallSite::TestBrick(sample_name.to_string()),
                    line: None,
                    msg: format!("wrote material id {bad}, which is not registered"),
                });
            }
        }
        let only = (!spec.only.is_empty()).then(|| id_of(&spec.only));
        let keep_awake = id_of(&spec.keep_awake);
        let (ch, n) = (&self.channels, self.channels.names().len());
        crate::sim::channel_room(&spec.name, &spec.channels, |c| ch.find(c).is_some(), n)?;
        let channel_ids = spec
            .channels
            .iter()
            .map(|c| self.channels.channel(c))
            .collect();
        self.scripts.push(Loaded {
            slot: ScriptSlot::new(src, spec, limits),
            channel_ids,
            material_ids,
            only,
            keep_awake,
            kernel: VoxelKernel::Lua,
        });
        Ok(self.scripts.len() - 1)
    }

    /// Load a voxel script for its declarations but run `kernel`, a native
    /// reference of the same rule, in place of its Lua kernels.
    pub fn add_native(
        &mut self,
        src: ScriptSource,
        limits: Limits,
        registry: &MaterialRegistry,
        kernel: std::sync::Arc<dyn VoxelNativeKernel>,
    ) -> Result<usize, SimError> {
        let i = self.add_script(src, limits, registry)?;
        let spec = &self.scripts[i].spec;
        let same = |declared: &[String], expected: &[&str]| {
            declared
                .iter()
                .map(String::as_str)
                .eq(expected.iter().copied())
        };
        let params: Vec<String> = spec.params.iter().map(|p| p.name.clone()).collect();
        let mismatch = [
            ("parameters", params.clone(), kernel.params()),
            ("channels", spec.channels.clone(), kernel.channels()),
            ("materials", spec.materials.clone(), kernel.materials()),
        ]
        .into_iter()
        .find(|(_, declared, expected)| !same(declared, expected));
        if let Some((what, declared, expected)) = mismatch {
            let s = self.scripts.pop().expect("added");
            return Err(SimError::Declaration {
                script: s.slot.spec.name,
                line: None,
                msg: format!(
                    "the native kernel expects {what} {expected:?}, the script declares {declared:?}"
                ),
            });
        }
        self.scripts[i].kernel = VoxelKernel::Native(kernel);
        Ok(i)
    }
}
