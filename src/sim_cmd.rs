//! `brickworld sim`: run Lua simulations on a scene headless, with a
//! progress bar, then render the result with the CPU tracer.

use std::time::Instant;

use anyhow::{Context, Result, bail};
use glam::DVec3;

use crate::app::{build_world, thread_pool};
use crate::config::SimSettings;
use crate::progress::bar;
use crate::sim::{Limits, ScriptWatcher, WorldSim, read_script};
use crate::trace::{Camera, RenderOptions, render, write_png};

/// Run the `sim` command.
pub fn run(s: &SimSettings) -> Result<()> {
    let pool = thread_pool(s.view.threads)?;
    pool.install(|| {
        let mut world = build_world(&s.scene)?;
        if let Some(msg) = crate::sim::run::reserved_conflicts(&world.materials) {
            anyhow::bail!("{msg}");
        }
        let mut ws = WorldSim::with_edges(&mut world, s.drain);
        ws.set_seed(s.scene.seed);
        // A materials.lua beside the first script names the voxel scripts' materials.
        let beside = s.scripts.first().and_then(|p| p.parent()).map(|d| d.join("materials.lua"));
        if let Some(m) = beside.map(|m| crate::sim::read_optional_script(&m)).transpose()?.flatten() {
            ws.load_materials(&mut world, &m)?;
        }
        for path in &s.scripts {
            let src = read_script(path)?;
            ws.add_script(&world, src, Limits::default()).context("cannot load the script")?;
        }
        ws.vox.apply_fills(world.store(), &world.materials);
        if let Some(w) = crate::sim::run::below_zero_warning(&ws, &world) {
            crate::say!("{w}");
        }
        for p in &s.params {
            let index = ws.script_index(&p.script)
                .with_context(|| format!("--param names script '{}', which is not loaded", p.script))?;
            ws.set_param(index, &p.name, p.value)?;
        }
        let mut script_ms = vec![0.0; ws.script_count()];
        let mut watchers = Vec::new();
        if s.watch {
            let mut dirs: Vec<std::path::PathBuf> = s.scripts.iter().map(|p| p.parent().map_or(".".into(), |d| if d.as_os_str().is_empty() { ".".into() } else { d.to_path_buf() })).collect();
            dirs.sort();
            dirs.dedup();
            for d in dirs {
                watchers.push(ScriptWatcher::new(&d, std::time::Duration::from_millis(200))?);
            }
        }
        let pb = bar("simulating", s.steps);
        let t0 = Instant::now();
        let (mut cells, mut bricks) = (0u64, 0usize);
        // Per script, the first error since it last loaded: a run ends
        // failed while any is left (a reload under --watch clears its own).
        let mut failed: Vec<Option<crate::sim::SimError>> = vec![None; ws.script_count()];
        // Scripts whose reload was refused, retried when materials.lua changes.
        let mut refused: Vec<std::path::PathBuf> = Vec::new();
        let mut last_active = 0;
        let mut max_sub = 1;
        for _ in 0..s.steps {
            for w in &mut watchers {
                let mut changed = w.poll();
                // materials.lua is applied too (regression, modder probe:
                // --watch ignored it, and a script refused for an undeclared
                // material was never retried); then the refused scripts.
                if let Some(m) = changed.iter().position(|p| p.file_name().is_some_and(|n| n == "materials.lua")) {
                    let path = changed.remove(m);
                    match read_script(&path).map_err(anyhow::Error::from).and_then(|src| Ok(ws.load_materials(&mut world, &src)?)) {
                        Ok((names, _)) => {
                            pb.suspend(|| crate::say!("applied {} ({} materials)", path.display(), names.len()));
                            changed.extend(refused.drain(..).filter(|p| !changed.contains(p)).collect::<Vec<_>>());
                        }
                        Err(e) => pb.suspend(|| crate::say!("warning: kept the materials: {e:#}")),
                    }
                }
                for path in changed {
                    match ws.reload(&world, &path) {
                        Ok(Some((i, _))) => {
                            pb.suspend(|| crate::say!("reloaded {}", path.display()));
                            failed[i] = None;
                            refused.retain(|p| *p != path);
                        }
                        Ok(None) => {}
                        Err(e) => {
                            pb.suspend(|| crate::say!("warning: kept the last good version: {e}"));
                            if !refused.contains(&path) {
                                refused.push(path);
                            }
                        }
                    }
                }
            }
            // The tick the kernels see (the label was one more; modder probe).
            let tick = ws.sim.tick();
            let before: Vec<bool> = (0..ws.script_count()).map(|i| ws.suspended(i).is_some()).collect();
            let (r, n) = if s.cfl > 0.0 { ws.step_within_cfl(&mut world, s.dt, s.cfl) } else { (ws.step(&mut world, s.dt), 1) };
            max_sub = max_sub.max(n);
            for (i, t) in script_ms.iter_mut().enumerate() {
                *t += ws.script_ms(&r, i);
            }
            for (script, line) in crate::sim::runtime::log::take_unprinted() {
                pb.suspend(|| crate::say!("[{script}] {line}"));
            }
            cells += r.active_tiles as u64 * 64 * n as u64;
            last_active = r.active_tiles;
            bricks += r.bricks.len();
            // Each script's first failure, and its suspension, are said (a
            // headless run has no /status; regression, modder probe: only
            // the run's first failure was).
            for e in r.errors {
                if let Some(i) = ws.script_index(e.step_script())
                    && failed[i].is_none()
                {
                    pb.suspend(|| crate::say!("warning: the step at tick {tick} was rejected: {e}"));
                    failed[i] = Some(e);
                }
            }
            for (i, was) in before.into_iter().enumerate() {
                if let Some(e) = ws.suspended(i).filter(|_| !was) {
                    pb.suspend(|| crate::say!("warning: {}.lua is suspended after {} failed steps in a row: {e}", ws.spec(i).name, ws.failures(i)));
                }
            }
            pb.inc(1);
        }
        pb.finish_and_clear();
        let secs = t0.elapsed().as_secs_f64();
        crate::say!(
            "{} steps in {:.2} s ({:.1} steps/s, {:.1} M column updates/s, up to {max_sub} sub-steps); {} tiles active at the end; {} dirty bricks published",
            s.steps,
            secs,
            s.steps as f64 / secs,
            cells as f64 / secs / 1e6,
            last_active,
            bricks
        );
        if max_sub >= crate::sim::columns::run::MAX_SUBSTEPS {
            crate::say!(
                "warning: some steps needed the most sub-steps there are ({max_sub}); the CFL limit may not have been met there: use a smaller --dt or a larger --cfl"
            );
        }
        for (i, t) in script_ms.iter().enumerate() {
            crate::say!("  {}: {:.3} ms per step", ws.spec(i).name, t / s.steps.max(1) as f64);
            for (name, total) in ws.conserved_totals(i) {
                crate::say!("    conserved {name}: {total:.6}");
            }
        }
        // Conserved quantities (sources such as rain and snowfall add to them).
        for name in ["water", "ground", "sediment", "snow"] {
            if let Some(id) = ws.sim.channels().find(name) {
                crate::say!("  total {name}: {:.6}", ws.sim.channels().total(id));
            }
        }
        if s.drain {
            crate::say!("  water drained over the edges: {:.6}", ws.drained);
        }
        // A failed run writes no image: an existing --out stays as it was
        // (regression: it was replaced, then the run exited 1).
        if let Some(e) = failed.iter().flatten().next() {
            bail!("a script failed during the run, so no image was written (first error: {e})");
        }
        let view = s.view.view.unwrap_or_else(|| world.default_views()[1]);
        let cam = Camera::new(DVec3::from(view.eye), DVec3::from(view.target), view.fov, s.view.width, s.view.height)?;
        let opts = RenderOptions {
            shadows: s.shadows,
            ..Default::default()
        };
        let out = render(&world.brickmap(), &cam, world.store().palette(), &opts);
        let staged = crate::files::Staged::new(&s.out).with_context(|| format!("cannot write {}", s.out.display()))?;
        write_png(staged.path(), out.width, out.height, &out.rgb).with_context(|| format!("cannot write {}", s.out.display()))?;
        staged.commit().with_context(|| format!("cannot write {}", s.out.display()))?;
        crate::say!("-> {}", s.out.display());
        Ok(())
    })
}
