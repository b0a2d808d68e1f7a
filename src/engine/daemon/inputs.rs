//! What reaches the engine from outside between steps: scripts changed on
//! disk ([`Engine::hot_reload`]) and the commands clients queued through
//! the control API ([`Engine::apply_commands`]).

use std::time::Instant;

use glam::DVec3;

use super::{Engine, ScriptNotes};
use crate::engine::checkpoint::CameraOverride;
use crate::engine::control::Command;
use crate::engine::world_config::CameraMode;

impl Engine {
    /// Swap in scripts changed on disk (a broken one keeps the old version).
    pub(super) fn hot_reload(&mut self) {
        let Some(w) = self.watcher.as_mut() else {
            return;
        };
        let changed = w.poll();
        for note in w.take_notes() {
            crate::say!("{note}");
        }
        // Any reload, applied or refused, counts: the stop commits.
        if !changed.is_empty() {
            self.changed_since_load = true;
        }
        for path in changed {
            if path.file_name().is_some_and(|n| n == "materials.lua") {
                self.materials_changed(&path);
                continue;
            }
            self.reload_script(&path);
        }
    }

    /// Swap in the script at `path` if it is a loaded one (a broken version
    /// keeps the running one, and `/status` says why).
    fn reload_script(&mut self, path: &std::path::Path) {
        {
            let name = path
                .file_stem()
                .map(|s| s.to_string_lossy().to_string())
                .unwrap_or_default();
            let index = self.ws.script_index(&name);
            match self.ws.reload(&self.world, path) {
                Ok(Some((i, mut warnings))) => {
                    // With its tick: the log is where a researcher finds
                    // when conditions changed (researcher probe).
                    crate::say!("tick {}: reloaded {}", self.ws.sim.tick(), path.display());
                    // A parameter the config sets and the new version does
                    // not declare: running on is fine, but the next start
                    // refuses the config (regression: said nowhere).
                    let file = format!("{}.lua", self.ws.spec(i).name);
                    if let Some(set) = self.cfg.scripts.iter().find(|s| s.file == file) {
                        let spec = self.ws.spec(i);
                        for (k, &v) in &set.params {
                            match spec.params.iter().find(|p| &p.name == k) {
                                None => warnings.push(format!(
                                    "the world config sets parameter '{k}' of {file}, which it no longer declares: the next start will refuse the config until one of them changes"
                                )),
                                // Regression (hostile probe 2): a narrowed
                                // range ran clamped, and only the next start
                                // said the config no longer fits.
                                Some(p) if !(p.min..=p.max).contains(&v) => {
                                    warnings.push(format!(
                                        "the world config sets parameter '{k}' of {file} to {}, outside its new range [{}, {}]: the next start will refuse the config until one of them changes",
                                        crate::sim::fmt_num(v),
                                        crate::sim::fmt_num(p.min),
                                        crate::sim::fmt_num(p.max)
                                    ))
                                }
                                Some(_) => {}
                            }
                        }
                    }
                    for w in &warnings {
                        crate::say!("warning: {w}");
                    }
                    let reloads = self.notes[i].reloads + 1;
                    self.notes[i] = ScriptNotes {
                        warning: warnings.last().cloned(),
                        reloads,
                        reloaded_at: self.ws.sim.tick(),
                        // Counted over the run, reloads included.
                        failed_steps: self.notes[i].failed_steps,
                        ..Default::default()
                    };
                }
                Ok(None) => {}
                Err(e) => {
                    crate::say!("warning: kept the last good version: {e}");
                    if let Some(i) = index {
                        self.notes[i].reload_error = Some(e.to_string());
                    }
                }
            }
        }
    }

    /// `materials.lua` changed on disk: applied between steps, as a hot
    /// reload of a script is (regression, hostile probe: an edit was
    /// silently ignored, and a script using a newly declared material
    /// failed with "declare it in materials.lua"; a later session applied
    /// it only at the next start).
    ///
    /// - A declared name keeps its id and takes its new colour, kind and
    ///   density; a new name takes a free id, the one the next start would
    ///   give it (the store's registry goes under `materials.lua` there),
    ///   unless that start first frees ids no voxel holds
    ///   (`persistence::reclaim_materials`).
    /// - A name it no longer declares stays registered: voxels and scripts
    ///   may hold its id.
    /// - Bricks holding a recoloured material get new LOD colours, and go
    ///   to the renderer.
    /// - Scripts whose last reload failed are tried again: the usual
    ///   reason is a material they use that was not declared yet.
    fn materials_changed(&mut self, path: &std::path::Path) {
        let shown = path.display();
        let not_loaded = |e: &dyn std::fmt::Display| {
            format!(
                "{shown} changed and does not load ({e}); the engine keeps the materials it has"
            )
        };
        let src = match crate::sim::read_optional_script(path) {
            Ok(Some(src)) => src,
            Ok(None) => {
                return self.materials_refused(format!(
                    "{shown} was removed: the engine keeps the materials it has (voxels and scripts may hold their ids)"
                ));
            }
            Err(e) => return self.materials_refused(not_loaded(&e)),
        };
        let before = self.world.materials.clone();
        let palette = self.world.store().palette().clone();
        let (names, bricks) = match self.ws.load_materials(&mut self.world, &src) {
            Ok(loaded) => loaded,
            Err(e) => return self.materials_refused(not_loaded(&e)),
        };
        let added: Vec<&str> = names
            .iter()
            .filter(|n| before.id(n).is_none())
            .map(String::as_str)
            .collect();
        // New names take ids whose palette entry changes too; only the
        // materials the world had count as recoloured.
        let now = self.world.store().palette();
        let recoloured = (1..=255u8)
            .filter(|&id| now.rgb(id) != palette.rgb(id) && before.get(id).is_some())
            .count();
        // Their voxels are the same: nothing to commit. The renderer's copy
        // recolours its own with the palette the next frame brings.
        let redrawn = bricks.len();
        let retyped = names
            .iter()
            .filter_map(|n| before.id(n))
            .filter(|&id| {
                let kd = |r: &crate::world::MaterialRegistry| {
                    r.get(id).map(|(_, d)| (d.kind, d.density))
                };
                kd(&before) != kd(&self.world.materials)
            })
            .count();
        // At most ten names: a file may declare 251.
        let listed = match added.len() {
            0 => String::new(),
            n if n <= 10 => format!(" ({})", added.join(", ")),
            n => format!(" ({} and {} more)", added[..10].join(", "), n - 10),
        };
        let msg = format!(
            "{shown} applied: {} new material{}{listed}, {recoloured} recoloured, {retyped} with a new kind or density ({redrawn} bricks redrawn)",
            added.len(),
            if added.len() == 1 { "" } else { "s" },
        );
        crate::say!("{msg}");
        self.materials_note = Some(msg);
        // Scripts a missing material kept from reloading.
        let failed: Vec<std::path::PathBuf> = (0..self.notes.len())
            .filter(|&i| self.notes[i].reload_error.is_some())
            .map(|i| {
                self.cfg
                    .scripts_dir
                    .join(format!("{}.lua", self.ws.spec(i).name))
            })
            .collect();
        for p in failed {
            self.reload_script(&p);
        }
    }

    /// Say why `materials.lua` was not applied, in the log and `/status`.
    fn materials_refused(&mut self, msg: String) {
        crate::say!("warning: {msg}");
        self.materials_note = Some(msg);
    }

    /// Apply the commands clients queued, in order; whether there were any.
    pub(super) fn apply_commands(&mut self) -> bool {
        let commands: Vec<Command> =
            std::mem::take(&mut *self.shared.commands.lock().expect("command lock"));
        let any = !commands.is_empty();
        for c in commands {
            match c {
                Command::Pause => {
                    self.paused = true;
                    // Queued single steps are cancelled too: paused means still.
                    self.steps_left = 0;
                }
                Command::Resume => {
                    if !self.should_step() {
                        self.rate.restart(Instant::now());
                    }
                    self.paused = false;
                    self.steps_left = 0;
                }
                Command::Step(n) => {
                    if !self.should_step() {
                        self.rate.restart(Instant::now());
                    }
                    self.paused = true;
                    self.steps_left = (self.steps_left + n).min(100_000);
                }
                Command::Checkpoint { verdict } => {
                    self.commit();
                    // The caller learns whether it was written (regression:
                    // 200 was answered on queueing, before any commit).
                    verdict.send(match &self.commit_error {
                        None => Ok(()),
                        Some(e) => Err(e.clone()),
                    });
                }
                Command::Camera {
                    eye, target, fov, ..
                } => {
                    self.camera.mode = CameraMode::Fixed;
                    self.camera.eye = Some(DVec3::from(eye));
                    self.camera.target = Some(DVec3::from(target));
                    self.camera.fov = fov;
                    // Committed with the state: a region that follows the
                    // camera must follow it after a resume too.
                    self.camera_override = Some(CameraOverride { eye, target, fov });
                    self.view_due = true;
                }
                Command::Params {
                    script,
                    values,
                    verdict,
                } => {
                    // The server validated against /status; a reload in
                    // between may still refuse: the caller is told, and the
                    // refusal is shown per script.
                    let Some(i) = self.ws.script_index(&script) else {
                        verdict.send(Err(format!("no script named '{script}' any more")));
                        continue;
                    };
                    // All or nothing: every value is checked against the
                    // script as it is now before any is set, so a refusal
                    // leaves the parameters as they were (regression: the
                    // values before a refused one stayed applied).
                    let refused: Vec<String> = (values.iter())
                        .filter_map(|(k, v)| self.ws.spec(i).param_index(k, *v).err())
                        .map(|e| e.to_string())
                        .collect();
                    let before = self.ws.params(i).to_vec();
                    if refused.is_empty() {
                        let tick = self.ws.sim.tick();
                        for (k, v) in values {
                            let was = self.ws.spec(i).param_index(&k, v).ok().map(|j| before[j]);
                            // Checked just above, on this thread.
                            if let Err(e) = self.ws.set_param(i, &k, v) {
                                crate::say!("{e}");
                                continue;
                            }
                            // Each change, with its tick, on standard error:
                            // the timeline has no parameter columns, and a
                            // researcher must be able to find when
                            // conditions changed (researcher probe: recorded
                            // nowhere).
                            if let Some(was) = was.filter(|w| w.to_bits() != v.to_bits()) {
                                // A tiny or huge value in exponent form
                                // (hostile probe: 1e-320 took 330 digits).
                                crate::say!(
                                    "tick {tick}: {script}.{k} = {} (was {})",
                                    crate::sim::fmt_num(v),
                                    crate::sim::fmt_num(was)
                                );
                            }
                        }
                        // A suspended script runs again once its parameters
                        // change: it failed under other conditions (for a
                        // built-in script, which cannot be edited, this is
                        // the way back; regression, newcomer walk). A value
                        // set to what it was changes nothing (review).
                        // (Compared bit for bit: 0 to -0 is a change too.)
                        let changed = (self.ws.params(i).iter().zip(&before))
                            .any(|(now, was)| now.to_bits() != was.to_bits());
                        if self.ws.suspended(i).is_some() && changed {
                            self.ws.set_health(i, 0, None);
                            self.notes[i].step_error = None;
                            self.notes[i].announced = None;
                            crate::say!("{script}.lua runs again: its parameters changed");
                        }
                        verdict.send(Ok(()));
                    } else {
                        let msg = format!("refused, nothing changed: {}", refused.join("; "));
                        self.notes[i].warning = Some(msg.clone());
                        verdict.send(Err(msg));
                    }
                }
                Command::CameraPath { .. } => {
                    self.camera = self.cfg.camera;
                    self.camera_override = None;
                    self.view_due = true;
                }
            }
        }
        any
    }
}
