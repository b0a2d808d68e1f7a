//! What both grids keep alike for each loaded script: its source and
//! declarations, parameter values, budgets, rate and health, and the id its
//! worker VMs are cached by. Each grid's loaded script adds its own
//! channel and material ids and its kernel around one [`ScriptSlot`].

use super::runtime::vms::VmId;
use super::script::carry_params;
use super::{Health, Limits, ScriptSource, ScriptSpec, ScriptState, SimError};

/// One loaded script's state, the same on the column and the voxel grid.
#[derive(Debug)]
pub(crate) struct ScriptSlot {
    /// The id its worker VMs are cached by (a new one per version).
    pub(crate) uid: VmId,
    /// The source it runs.
    pub(crate) src: ScriptSource,
    /// Its declarations.
    pub(crate) spec: ScriptSpec,
    /// Parameter values, in declaration order.
    pub(crate) params: Vec<f64>,
    /// Its budgets.
    pub(crate) limits: Limits,
    /// Run on ticks that are multiples of this.
    pub(crate) every: u64,
    /// Failed steps in a row, and why the script is suspended.
    pub(crate) health: Health,
}

impl ScriptSlot {
    /// A script just loaded: its parameters at their defaults, run every
    /// tick, healthy.
    pub(crate) fn new(src: ScriptSource, spec: ScriptSpec, limits: Limits) -> Self {
        let params = spec.params.iter().map(|p| p.default).collect();
        ScriptSlot {
            uid: VmId::new(),
            src,
            spec,
            params,
            limits,
            every: 1,
            health: Health::default(),
        }
    }

    /// A new version of `old`'s script takes over its rate and the values of
    /// its parameters that still exist, clamped into narrowed ranges; the
    /// warnings say which were clamped. Its health is fresh: a suspended
    /// script runs again.
    pub(crate) fn carry_over(&mut self, old: &ScriptSlot) -> Vec<String> {
        self.every = old.every;
        let (values, warnings) = carry_params(&old.spec, &old.params, &self.spec);
        self.params = values;
        warnings
    }

    /// Its source, budgets, rate and health, for a rebuild.
    pub(crate) fn state(&self) -> ScriptState {
        ScriptState {
            src: self.src.clone(),
            limits: self.limits,
            every: self.every,
            failures: self.health.failures(),
            suspended: self.health.suspended().cloned(),
        }
    }

    /// Give it the health a rebuilt or resumed simulation carries over.
    pub(crate) fn restore_health(&mut self, failures: u32, suspended: Option<SimError>) {
        self.health = Health::restored(failures, suspended);
    }

    /// Run it on ticks that are multiples of `every` (at least 1).
    pub(crate) fn set_every(&mut self, every: u64) {
        self.every = every.max(1);
    }

    /// Set parameter `name`; refused outside its declared range.
    pub(crate) fn set_param(&mut self, name: &str, value: f64) -> Result<(), SimError> {
        let k = self.spec.param_index(name, value)?;
        self.params[k] = value;
        Ok(())
    }
}

/// `Deref` and `DerefMut` to its `slot` field for a grid's loaded script,
/// which extends the slot both grids share: the slot's fields read as the
/// script's own (`s.spec`, `s.params`).
macro_rules! extends_slot {
    ($t:ty) => {
        impl std::ops::Deref for $t {
            type Target = $crate::sim::slot::ScriptSlot;
            fn deref(&self) -> &Self::Target {
                &self.slot
            }
        }

        impl std::ops::DerefMut for $t {
            fn deref_mut(&mut self) -> &mut Self::Target {
                &mut self.slot
            }
        }
    };
}
pub(crate) use extends_slot;
