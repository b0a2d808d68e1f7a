//! `brickworld sim`: run Lua simulations on a scene headless, with a
//! progress bar, then render the result with the CPU tracer.
//!
//! [`SimRun`] holds a run; its loop calls named stages: apply what changed
//! on disk (`--watch`), step, say what the step did; then the totals and
//! the image.

use std::path::{Path, PathBuf};
use std::time::Instant;

use anyhow::{Context, Result, bail};
use indicatif::ProgressBar;

use crate::app::{build_world, thread_pool};
use crate::config::SimSettings;
use crate::progress::bar;
use crate::scene::SceneWorld;
use crate::sim::{Limits, ScriptWatcher, SimError, WorldSim, read_script};
use crate::trace::{RenderOptions, render, write_png};

/// Run the `sim` command.
pub fn run(s: &SimSettings) -> Result<()> {
    let pool = thread_pool(s.view.threads)?;
    pool.install(|| {
        let mut run = SimRun::start(s)?;
        let pb = bar("simulating", s.steps);
        let t0 = Instant::now();
        for _ in 0..s.steps {
            run.apply_changes(&pb);
            run.step(&pb);
            pb.inc(1);
        }
        pb.finish_and_clear();
        run.report(t0.elapsed().as_secs_f64());
        run.write_image()
    })
}

/// What a run has done so far, for its closing lines.
#[derive(Default)]
struct Totals {
    /// Per script, its time in the steps, ms.
    script_ms: Vec<f64>,
    /// Column cells updated (active tiles × 64 × sub-steps).
    cells: u64,
    /// Dirty bricks published.
    bricks: usize,
    /// Tiles active after the last step.
    last_active: usize,
    /// The most CFL sub-steps a step took.
    max_sub: u32,
}

/// A headless simulation run of `sim`.
struct SimRun<'a> {
    s: &'a SimSettings,
    world: SceneWorld,
    ws: WorldSim,
    /// One per folder of the scripts, with `--watch`.
    watchers: Vec<ScriptWatcher>,
    /// Per script, the first error since it last loaded: a run ends
    /// failed while any is left (a reload under `--watch` clears its own).
    failed: Vec<Option<SimError>>,
    /// Scripts whose reload was refused, retried when `materials.lua`
    /// changes.
    refused: Vec<PathBuf>,
    totals: Totals,
}

impl<'a> SimRun<'a> {
    /// Build the scene, load `materials.lua` (beside the first script) and
    /// the scripts, and set the parameters.
    fn start(s: &'a SimSettings) -> Result<Self> {
        let mut world = build_world(&s.scene)?;
        if let Some(msg) = crate::sim::run::reserved_conflicts(&world.materials) {
            bail!("{msg}");
        }
        let mut ws = WorldSim::with_edges(&mut world, s.drain);
        ws.set_seed(s.scene.seed);
        // A materials.lua beside the first script names the voxel scripts' materials.
        let beside = s
            .scripts
            .first()
            .and_then(|p| p.parent())
            .map(|d| d.join("materials.lua"));
        if let Some(m) = beside
            .map(|m| crate::sim::read_optional_script(&m))
            .transpose()?
            .flatten()
        {
            ws.load_materials(&mut world, &m)?;
        }
        for path in &s.scripts {
            // Regression (newcomer walk): it was read as a script, and
            // refused for its material names ("unknown key 'basalt'").
            if path.file_name().is_some_and(|n| n == "materials.lua") {
                bail!(
                    "{}: materials.lua lists the world's materials and is not a simulation script; sim reads it from beside the first --script",
                    crate::text::shown(&path.display().to_string(), 200)
                );
            }
            let src = read_script(path)?;
            ws.add_script(&world, src, Limits::default())
                .context("cannot load the script")?;
        }
        ws.check_memory()?;
        ws.vox.apply_fills(world.store(), &world.materials);
        if let Some(w) = crate::sim::run::below_zero_warning(&ws, &world) {
            crate::say!("{w}");
        }
        for p in &s.params {
            let index = ws.script_index(&p.script).with_context(|| {
                format!("--param names script '{}', which is not loaded", p.script)
            })?;
            ws.set_param(index, &p.name, p.value)?;
        }
        let mut watchers = Vec::new();
        if s.watch {
            let mut dirs: Vec<PathBuf> = s.scripts.iter().map(|p| folder_of(p)).collect();
            dirs.sort();
            dirs.dedup();
            for d in dirs {
                watchers.push(ScriptWatcher::new(
                    &d,
                    std::time::Duration::from_millis(200),
                )?);
            }
        }
        let scripts = ws.script_count();
        Ok(SimRun {
            s,
            world,
            ws,
            watchers,
            failed: vec![None; scripts],
            refused: Vec::new(),
            totals: Totals {
                script_ms: vec![0.0; scripts],
                max_sub: 1,
                ..Totals::default()
            },
        })
    }

    /// Stage 1 (`--watch`): apply what changed on disk, `materials.lua`
    /// first (regression, modder probe: `--watch` ignored it, and a script
    /// refused for an undeclared material was never retried), then the
    /// scripts, with those refused before.
    fn apply_changes(&mut self, pb: &ProgressBar) {
        for w in 0..self.watchers.len() {
            let mut changed = self.watchers[w].poll();
            let materials = changed
                .iter()
                .position(|p| p.file_name().is_some_and(|n| n == "materials.lua"));
            if let Some(m) = materials {
                let path = changed.remove(m);
                if self.apply_materials(&path, pb) {
                    let retry: Vec<PathBuf> = self
                        .refused
                        .drain(..)
                        .filter(|p| !changed.contains(p))
                        .collect();
                    changed.extend(retry);
                }
            }
            for path in changed {
                self.reload(&path, pb);
            }
        }
    }

    /// Apply `materials.lua` at `path`; whether it was.
    fn apply_materials(&mut self, path: &Path, pb: &ProgressBar) -> bool {
        let loaded = read_script(path)
            .map_err(anyhow::Error::from)
            .and_then(|src| Ok(self.ws.load_materials(&mut self.world, &src)?));
        match loaded {
            Ok((names, _)) => {
                pb.suspend(|| {
                    crate::say!("applied {} ({} materials)", path.display(), names.len())
                });
                true
            }
            Err(e) => {
                pb.suspend(|| crate::say!("warning: kept the materials: {e:#}"));
                false
            }
        }
    }

    /// Reload the script at `path`; a refusal keeps the last good version
    /// and is retried when `materials.lua` changes.
    fn reload(&mut self, path: &Path, pb: &ProgressBar) {
        match self.ws.reload(&self.world, path) {
            Ok(Some((i, warnings))) => {
                pb.suspend(|| {
                    crate::say!("reloaded {}", path.display());
                    // A value clamped into a narrowed range, as the engine
                    // says it (regression, modder probe: `sim --watch`
                    // clamped in silence).
                    for w in &warnings {
                        crate::say!("warning: {w}");
                    }
                });
                self.failed[i] = None;
                self.refused.retain(|p| p != path);
            }
            Ok(None) => {}
            Err(e) => {
                pb.suspend(|| crate::say!("warning: kept the last good version: {e}"));
                if !self.refused.iter().any(|p| p == path) {
                    self.refused.push(path.to_path_buf());
                }
            }
        }
    }

    /// Stage 2: one step (split into CFL sub-steps with `--cfl`), then what
    /// it did: the scripts' log lines, each script's first failure and its
    /// suspension (a headless run has no `/status`; regression, modder
    /// probe: only the run's first failure was said).
    fn step(&mut self, pb: &ProgressBar) {
        let (s, ws) = (self.s, &mut self.ws);
        // The tick the kernels see (the label was one more; modder probe).
        let tick = ws.sim.tick();
        let before: Vec<bool> = (0..ws.script_count())
            .map(|i| ws.suspended(i).is_some())
            .collect();
        let (r, n) = if s.cfl > 0.0 {
            ws.step_within_cfl(&mut self.world, s.dt, s.cfl)
        } else {
            (ws.step(&mut self.world, s.dt), 1)
        };
        let t = &mut self.totals;
        t.max_sub = t.max_sub.max(n);
        for (i, ms) in t.script_ms.iter_mut().enumerate() {
            *ms += ws.script_ms(&r, i);
        }
        t.cells += r.active_tiles as u64 * 64 * n as u64;
        t.last_active = r.active_tiles;
        t.bricks += r.bricks.len();
        for (script, line) in crate::sim::runtime::log::take_unprinted() {
            pb.suspend(|| crate::say!("[{script}] {line}"));
        }
        for e in r.errors {
            if let Some(i) = ws.script_index(e.step_script())
                && self.failed[i].is_none()
            {
                pb.suspend(|| crate::say!("warning: the step at tick {tick} was rejected: {e}"));
                self.failed[i] = Some(e);
            }
        }
        for (i, was) in before.into_iter().enumerate() {
            if let Some(e) = ws.suspended(i).filter(|_| !was) {
                pb.suspend(|| {
                    crate::say!(
                        "warning: {}.lua is suspended after {} failed steps in a row: {e}",
                        ws.spec(i).name,
                        ws.failures(i)
                    )
                });
            }
        }
    }

    /// Stage 3: the run's speed, each script's time and conserved totals,
    /// and the world's totals.
    fn report(&self, secs: f64) {
        let (s, ws, t) = (self.s, &self.ws, &self.totals);
        // Column figures only where column scripts ran (regression,
        // newcomer walk: voxel scripts alone printed "0 tiles active").
        if ws.sim.script_count() > 0 {
            crate::say!(
                "{} steps in {:.2} s ({:.1} steps/s, {:.1} M column updates/s, up to {} sub-steps); {} tiles active at the end; {} dirty bricks published",
                s.steps,
                secs,
                s.steps as f64 / secs,
                t.cells as f64 / secs / 1e6,
                t.max_sub,
                t.last_active,
                t.bricks
            );
        } else {
            crate::say!(
                "{} steps in {:.2} s ({:.1} steps/s); {} dirty bricks published",
                s.steps,
                secs,
                s.steps as f64 / secs,
                t.bricks
            );
        }
        if t.max_sub >= crate::sim::columns::run::MAX_SUBSTEPS {
            crate::say!(
                "warning: some steps needed the most sub-steps there are ({}); the CFL limit may not have been met there: use a smaller --dt or a larger --cfl",
                t.max_sub
            );
        }
        for (i, ms) in t.script_ms.iter().enumerate() {
            crate::say!(
                "  {}: {:.3} ms per step",
                ws.spec(i).name,
                ms / s.steps.max(1) as f64
            );
            for (name, total) in ws.conserved_totals(i) {
                crate::say!("    conserved {name}: {}", six_places(total));
            }
        }
        // Conserved quantities (sources such as rain and snowfall add to them).
        for name in ["water", "ground", "sediment", "snow"] {
            if let Some(id) = ws.sim.channels().find(name) {
                crate::say!(
                    "  total {name}: {}",
                    six_places(ws.sim.channels().total(id))
                );
            }
        }
        if s.drain && ws.sim.channels().find("water").is_some() {
            crate::say!("  water drained over the edges: {}", six_places(ws.drained));
        }
        // The daemon's hash (bricks and every channel): the same for any
        // thread count, so two runs can be compared by one line.
        crate::say!(
            "  world hash {:#018x}",
            crate::engine::persistence::engine_hash(&self.world, ws)
        );
    }

    /// Stage 4: the final image, unless a script failed: a failed run
    /// writes none, and an existing `--out` stays as it was (regression: it
    /// was replaced, then the run exited 1).
    fn write_image(&self) -> Result<()> {
        let s = self.s;
        if let Some(e) = self.failed.iter().flatten().next() {
            bail!("a script failed during the run, so no image was written (first error: {e})");
        }
        let cam = s.view.camera(self.world.default_views()[1])?;
        let opts = RenderOptions {
            shadows: s.shadows,
            ..Default::default()
        };
        let out = render(
            &self.world.brickmap(),
            &cam,
            self.world.store().palette(),
            &opts,
        );
        let cannot = || format!("cannot write {}", s.out.display());
        let staged = crate::files::Staged::new(&s.out).with_context(cannot)?;
        write_png(staged.path(), out.width, out.height, &out.rgb).with_context(cannot)?;
        staged.commit().with_context(cannot)?;
        crate::say!("-> {}", s.out.display());
        Ok(())
    }
}

/// The folder `path` is in (`.` for a bare file name).
fn folder_of(path: &Path) -> PathBuf {
    match path.parent() {
        Some(d) if !d.as_os_str().is_empty() => d.to_path_buf(),
        _ => PathBuf::from("."),
    }
}

/// `x` to six decimal places, with no minus sign on a value that rounds to
/// zero (a sum of round-off printed "-0.000000").
fn six_places(x: f64) -> String {
    let s = format!("{x:.6}");
    if s == "-0.000000" {
        s[1..].to_string()
    } else {
        s
    }
}
