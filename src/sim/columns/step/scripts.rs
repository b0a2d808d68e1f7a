//! A simulation's scripts: loading one (checked against the column grid,
//! the channel registry's room and a smoke test on a sample tile before it
//! is registered), replacing it on a hot reload with its parameters carried
//! over, and each script's parameters, rate and health.

use super::{Kernel, Loaded, Simulation};
use crate::sim::SimError;
use crate::sim::channels::ChannelId;
use crate::sim::script::{Limits, ScriptSource, ScriptSpec, ScriptVm, StepKey};
use crate::sim::slot::ScriptSlot;
use crate::sim::tile::TileCoord;

impl Simulation {
    /// Load a script (validated and smoke-tested on a sample tile). Returns
    /// its index.
    pub fn add_script(
        &mut self,
        src: ScriptSource,
        kernel: Kernel,
        limits: Limits,
    ) -> Result<usize, SimError> {
        let loaded = self.prepare(src, kernel, limits, false)?;
        self.scripts.push(loaded);
        Ok(self.scripts.len() - 1)
    }

    /// Replace script `index` with a new version, keeping parameter values
    /// that still exist (clamped into a narrowed range, with a warning in the
    /// returned list). On error the old version stays. A suspended script
    /// runs again.
    pub fn replace_script(
        &mut self,
        index: usize,
        src: ScriptSource,
    ) -> Result<Vec<String>, SimError> {
        let (kernel, limits) = (
            self.scripts[index].kernel.clone(),
            self.scripts[index].limits,
        );
        let mut loaded = self.prepare(src, kernel, limits, true)?;
        let warnings = loaded.slot.carry_over(&self.scripts[index].slot);
        self.scripts[index] = loaded;
        self.wake_all();
        Ok(warnings)
    }

    fn prepare(
        &mut self,
        src: ScriptSource,
        kernel: Kernel,
        limits: Limits,
        reload: bool,
    ) -> Result<Loaded, SimError> {
        let (mut vm, spec) = ScriptVm::load(&src, limits)?;
        if spec.grid != crate::sim::script::Grid::Columns {
            return Err(spec.grid.mismatch(&spec.name, reload));
        }
        let (ch, n) = (&self.channels, self.channels.channels().count());
        crate::sim::channel_room(&spec.name, &spec.channels, |c| ch.find(c).is_some(), n)?;
        let boundary: Vec<f64> = spec
            .channels
            .iter()
            .map(|c| {
                spec.boundary
                    .iter()
                    .find(|(n, _)| n == c)
                    .map_or(0.0, |(_, v)| *v)
            })
            .collect();
        let nonneg = spec
            .nonnegative
            .iter()
            .filter_map(|n| spec.channels.iter().position(|c| c == n))
            .collect();
        let params: Vec<f64> = spec.params.iter().map(|p| p.default).collect();
        // Smoke test: every pass once on a dry sample tile, in this fresh VM.
        if matches!(kernel, Kernel::Lua) {
            crate::sim::runtime::log::at_load(|| -> Result<(), SimError> {
                vm.begin_step(
                    0.01,
                    &spec,
                    &params,
                    StepKey::new(self.seed, 0, &spec.name),
                    &[],
                )?;
                for (pi, pass) in spec.passes.iter().enumerate() {
                    vm.run(pi, &pass.name, 0, 0, |_| {})?;
                }
                Ok(())
            })?;
        }
        if reload {
            self.reload_fits(&spec)?;
        }
        // Registered only once the script has passed every check: a
        // rejected reload must leave the world's registry as it was
        // (regression: its channels stayed and filled the bound).
        let ids: Vec<ChannelId> = spec
            .channels
            .iter()
            .map(|c| self.channels.channel(c))
            .collect();
        Ok(Loaded {
            slot: ScriptSlot::new(src, spec, limits),
            ids,
            boundary,
            nonneg,
            kernel,
        })
    }

    /// The most channels one pass of any script writes (a step's gathered
    /// outputs are as many per tile).
    pub fn most_writes(&self) -> usize {
        self.scripts
            .iter()
            .map(|s| s.spec.widest_writes())
            .max()
            .unwrap_or(0)
    }

    /// About the bytes `channels` channels take over this simulation's
    /// tiles when one pass writes `writes` of them: each stored channel
    /// (512 bytes a tile), a step's outputs and rollback copy for the
    /// widest pass (2.5 × its channels, measured: one script writing 250
    /// channels on 512² columns held 1.72 GB, this says 1.79), and the
    /// tiles' own records (4 channels' worth; water, erosion and snow, 16
    /// channels, measured 8.6 to 11 KiB a tile, this says 15).
    pub fn channel_bytes(&self, channels: usize, writes: usize) -> u64 {
        let d = (self.tiles_max - self.tiles_min).max(TileCoord::ZERO);
        let tiles = d.x as u64 * d.y as u64;
        let cell_bytes = crate::sim::tile::TILE_CELLS as u64 * 8;
        let units = channels as u64 + (5 * writes as u64).div_ceil(2) + 4;
        tiles.saturating_mul(cell_bytes * units)
    }

    /// Refuse a reload whose new channels (or wider pass) would need more
    /// memory than the process may still allocate: the running version is
    /// kept (regression, memory probe: a reload from 1 to 250 channels on a
    /// 512² world passed no check, and under `ulimit -v` the running
    /// engine aborted at its next step).
    fn reload_fits(&self, spec: &ScriptSpec) -> Result<(), SimError> {
        use crate::scene::budget::{headroom_bytes, human};
        let now = self.channels.channels().count();
        let new = spec
            .channels
            .iter()
            .filter(|c| self.channels.find(c).is_none())
            .count();
        let writes = spec.widest_writes();
        let most = self.most_writes();
        let (before, after) = (
            self.channel_bytes(now, most),
            self.channel_bytes(now + new, most.max(writes)),
        );
        let (more, room) = (after.saturating_sub(before), headroom_bytes());
        if more > room {
            let d = self.tiles_max - self.tiles_min;
            return Err(SimError::Declaration {
                script: spec.name.clone(),
                line: None,
                msg: format!(
                    "this version's channels ({} in all, {} written by one pass) need about {} more over {} by {} tiles; {} is available, so the running version is kept",
                    now + new,
                    most.max(writes),
                    human(more),
                    d.x,
                    d.y,
                    human(room)
                ),
            });
        }
        Ok(())
    }

    /// Script `i`'s source, limits, rate and health, for a rebuild.
    pub fn script_state(&self, i: usize) -> crate::sim::ScriptState {
        self.scripts[i].state()
    }

    /// Give script `i` the health a rebuilt simulation carries over.
    pub fn set_health(&mut self, i: usize, failures: u32, suspended: Option<SimError>) {
        self.scripts[i].restore_health(failures, suspended);
    }

    /// Run script `index` only on ticks that are multiples of `every` (≥ 1).
    pub fn set_every(&mut self, index: usize, every: u64) {
        self.scripts[index].set_every(every);
    }

    /// The tick interval of script `index`.
    pub fn every(&self, index: usize) -> u64 {
        self.scripts[index].every
    }

    /// Declarations of script `index`.
    pub fn spec(&self, index: usize) -> &ScriptSpec {
        &self.scripts[index].spec
    }

    /// Number of scripts.
    pub fn script_count(&self) -> usize {
        self.scripts.len()
    }

    /// The index of the script called `name`, if one is loaded.
    pub fn script_index(&self, name: &str) -> Option<usize> {
        (0..self.scripts.len()).find(|&i| self.spec(i).name == name)
    }

    /// Current parameter values of script `index` (spec order).
    pub fn params(&self, index: usize) -> &[f64] {
        &self.scripts[index].params
    }

    /// Change a parameter; refused outside its declared range. Takes effect
    /// at the next step, with no restart.
    pub fn set_param(&mut self, index: usize, name: &str, value: f64) -> Result<(), SimError> {
        self.scripts[index].set_param(name, value)?;
        self.wake_all();
        Ok(())
    }
}
