//! What a start begins from: the world store (another world's refused, a
//! legacy directory migrated), the world built or regenerated, and then a
//! first start's placed boxes or a resume's stored state, with the config
//! parameters that stored state overrides named.

use std::path::Path;

use anyhow::{Context, Result, bail};

use crate::engine::checkpoint::CameraOverride;
use crate::engine::control::CheckpointRef;
use crate::engine::persistence::{self, DirtyChunks};
use crate::engine::streaming::{self, RegionRule, StreamPlan};
use crate::engine::world_config::{CameraMode, CameraSettings, WorldConfig};
use crate::persist::WorldDb;
use crate::progress::bar;
use crate::scene::{SceneWorld, build_scene};
use crate::sim::WorldSim;

/// Where a start left off: the camera (a resumed world's stored one, if
/// set) and the checkpoint it resumed from.
pub(super) struct Loaded {
    pub(super) camera: CameraSettings,
    pub(super) camera_override: Option<CameraOverride>,
    pub(super) loaded_from: Option<CheckpointRef>,
}

/// Apply a resumed world's stored state over the loaded scripts, saying
/// what it could not keep and which config parameters it overrides.
pub(super) fn resume(
    cfg: &WorldConfig,
    ctl: &str,
    db: &WorldDb,
    world: &SceneWorld,
    ws: &mut WorldSim,
    r: &persistence::Restored,
) -> Loaded {
    let mut camera = cfg.camera;
    let mut camera_override = None;
    if let Some(c) = r.state.extras.camera {
        camera = CameraSettings {
            mode: CameraMode::Fixed,
            eye: Some(glam::DVec3::from(c.eye)),
            target: Some(glam::DVec3::from(c.target)),
            fov: c.fov,
        };
        camera_override = Some(c);
    }
    for c in &r.corrupt {
        crate::say!("warning: {c}");
    }
    for w in persistence::apply_state(&r.state, ws) {
        crate::say!("warning: {w}");
    }
    for w in config_params_not_in_effect(cfg, ws, ctl) {
        crate::say!("warning: {w}");
    }
    let hash = persistence::engine_hash(world, ws);
    crate::say!(
        "resumed {} at tick {} ({} stored chunks and chunk columns, world hash {hash:#018x})",
        db.path().display(),
        r.state.tick,
        r.chunks
    );
    Loaded {
        camera,
        camera_override,
        loaded_from: Some(CheckpointRef {
            tick: r.state.tick,
            hash: format!("{hash:#018x}"),
        }),
    }
}

/// The parameters the world config sets that a resumed state overrides:
/// parameters are committed state (`ctl param` changes them while the
/// engine runs), so the stored value is kept, and this says so, with the
/// command that applies the config's (regression, hot-edit probe: a
/// `params` value edited in the config was overridden at the next start,
/// which said only that new settings apply from now on).
fn config_params_not_in_effect(cfg: &WorldConfig, ws: &WorldSim, ctl: &str) -> Vec<String> {
    let mut out = Vec::new();
    for set in &cfg.scripts {
        let name = set.file.strip_suffix(".lua").unwrap_or(&set.file);
        let Some(i) = ws.script_index(name) else {
            continue;
        };
        let spec = ws.spec(i);
        let values = ws.params(i);
        for (k, &want) in &set.params {
            let Some(j) = spec.params.iter().position(|p| &p.name == k) else {
                continue;
            };
            let have = values[j];
            if have != want {
                out.push(format!(
                    "{}: the world config sets {name}.{k} = {}, but the stored state holds {} (set while the engine ran, or by an earlier config): the stored value is kept; `{ctl} param {name} {k} {}` applies the config's",
                    cfg.file,
                    crate::sim::fmt_num(want),
                    crate::sim::fmt_num(have),
                    crate::sim::fmt_num(want),
                ));
            }
        }
    }
    out
}

/// Open (or create) the world store in `state`, refusing another world's,
/// and migrate a legacy checkpoint directory into it.
pub(super) fn open_store(state: &Path, cfg: &WorldConfig) -> Result<WorldDb> {
    crate::engine::backup::refuse_interrupted_import(state, &cfg.file)?;
    let identity = cfg.identity();
    let (mut db, warnings) = WorldDb::open(state, &identity)?;
    for w in &warnings {
        crate::say!("warning: {w}");
    }
    if let Some((path, tick)) = crate::engine::backup::migrate_legacy(&mut db, state, &identity)? {
        crate::say!(
            "migrated the checkpoint {} (tick {tick}) into the world store {}; the old checkpoint files are no longer read and can be deleted",
            path.display(),
            db.path().display()
        );
    }
    Ok(db)
}

/// The engine's world: generated (a procedural source), the stored frame
/// of an imported one, or a streamed world's simulated region (with the
/// plan the render thread streams the rest by).
pub(super) fn build_world(
    cfg: &WorldConfig,
    db: &WorldDb,
) -> Result<(SceneWorld, Option<(StreamPlan, RegionRule)>)> {
    let mut stream_plan = None;
    let world = match &cfg.stream {
        Some(st) => {
            // A streamed world: only the simulated region is the
            // engine's; the render thread streams the rest.
            let (gen_, rule) = streaming::generator(cfg)?;
            let columns = match (rule, persistence::stored_frame(db)?) {
                // Where a region that follows the camera was is part of the
                // committed state.
                (RegionRule::Follow { .. }, Some((_, (lo, hi)))) => {
                    streaming::columns_of_bounds(lo, hi)
                }
                _ => rule.around(initial_eye(cfg)),
            };
            let (world, mut plan) = streaming::build_region(gen_, columns, st, rule.follows())?;
            plan.overlay = Some(streaming::store_overlay(db.reader(), &plan.gen_));
            streaming::check_budget(&world, &mut plan, st.memory_budget, rule.follows())?;
            crate::say!(
                "streaming: simulated region of {} chunk columns ({}), render window {} columns across, memory budget {}",
                (plan.live.1 - plan.live.0).element_product(),
                crate::scene::budget::human(streaming::world_bytes(&world)),
                2 * plan.window.radius + 1,
                crate::scene::budget::human(plan.window.budget_bytes),
            );
            stream_plan = Some((plan, rule));
            world
        }
        None => fixed_world(cfg, db)?,
    };
    Ok((world, stream_plan))
}

/// The world an unstreamed world's stored chunks go over, for `run` and
/// `export` alike. A procedural world is regenerated (only its edits are
/// stored); a heightmap or .vox world was imported whole into the store on
/// its first start, so its file is not read again: an empty world of the
/// stored frame (regression, hostile probe: `export` rebuilt it from the
/// file, so a backup taken after the file changed held another world,
/// exit 0, while `run` resumed the stored one).
pub(crate) fn fixed_world(cfg: &WorldConfig, db: &WorldDb) -> Result<SceneWorld> {
    let imported = if cfg.source.is_procedural() {
        None
    } else {
        persistence::stored_frame(db)?
    };
    Ok(match imported {
        Some((palette, (lo, hi))) => {
            SceneWorld::new(crate::world::BrickStore::new(palette), lo, hi)?
        }
        None => {
            let pb = bar("scene", 0);
            let w = build_scene(&cfg.source, cfg.size, cfg.seed, &pb)
                .context("cannot build the world")?;
            pb.finish_and_clear();
            w
        }
    })
}

/// Where the camera starts (every camera mode is at its configured eye at
/// tick 0): the middle of the world when the config names no eye.
fn initial_eye(cfg: &WorldConfig) -> glam::DVec3 {
    cfg.camera.eye.unwrap_or_else(|| {
        if cfg.unbounded {
            glam::DVec3::ZERO
        } else {
            cfg.size.as_dvec3() * 0.5
        }
    })
}

/// A world's first start (nothing stored yet): place the config's boxes,
/// and import a heightmap or .vox world whole into the store.
pub(super) fn first_start(
    cfg: &WorldConfig,
    db: &mut WorldDb,
    world: &mut SceneWorld,
    ws: &mut WorldSim,
    dirty_chunks: &mut DirtyChunks,
) -> Result<()> {
    let mut placed = Vec::new();
    for (i, p) in cfg.place.iter().enumerate() {
        let id = world.materials.id(&p.material).with_context(|| {
            format!(
                "{}: place[{i}].material: unknown material '{}' (declare it in materials.lua)",
                cfg.file, p.material
            )
        })?;
        let (lo, hi) = world.bounds();
        if p.at.cmplt(lo).any() || (p.at + p.size).cmpgt(hi).any() {
            // Named as what it is: a box that overlaps the world only in
            // part was said to be "outside" it (scale probe), and on a
            // streamed world the box is placed in its simulated region.
            bail!(
                "{}: place[{i}]: the box at {} of size {} does not lie wholly inside the {} [{lo}, {hi})",
                cfg.file,
                p.at,
                p.size,
                if cfg.stream.is_some() {
                    "simulated region"
                } else {
                    "world"
                }
            );
        }
        let ((), changed) = world.edit(|s, _| s.fill_box(p.at, p.at + p.size, id));
        placed.extend(changed);
    }
    // The columns' ground follows the boxes (it was read before they were
    // placed), and their snow and water are redrawn on it.
    let redrawn = ws.follow_voxels(world, &placed);
    placed.extend(redrawn);
    dirty_chunks.bricks(&placed);
    ws.vox.notify_edited(&placed);
    ws.vox.apply_fills(world.store(), &world.materials);
    if !cfg.source.is_procedural() {
        // Import the file's world whole, now: from here on the
        // store is the world, and the file is not needed.
        dirty_chunks.everything(world, ws);
        let st = persistence::commit(db, dirty_chunks, world, ws, None).with_context(|| {
            format!(
                "cannot store {} in {} on the world's first start",
                cfg.source_text,
                db.path().display()
            )
        })?;
        crate::say!(
            "imported {} into {} ({} chunks, {} bytes)",
            cfg.source_text,
            db.path().display(),
            st.chunks,
            st.bytes
        );
    }
    Ok(())
}
