//! Streamed worlds through the real daemon: a bounded world larger than
//! what is resident and an unbounded one. Only the simulated region is
//! stored, resume is bit-identical, the render window follows the camera,
//! and a budget too small for one view is refused naming the minimum.

mod common;

use std::path::{Path, PathBuf};

use common::cli::assert_clear_failure;
use common::daemon::{hash_at, run_cmd, run_ok};

/// A streamed world: 2048² terrain (or unbounded with `height`), a 128²
/// simulated region with rain, a small view, frames every 5 ticks.
fn streamed(name: &str, world: &str, camera: &str) -> (PathBuf, PathBuf) {
    let dir = std::env::temp_dir().join(format!("brickworld-stream-{name}-{}", std::process::id()));
    let _ = std::fs::remove_dir_all(&dir);
    std::fs::create_dir_all(&dir).unwrap();
    let cfg = dir.join("world.toml");
    std::fs::write(
        &cfg,
        format!(
            "[world]\nsource = \"terrain\"\n{world}\nseed = 5\n\
             [stream]\nview_distance = 128.0\nmemory_budget = \"256MiB\"\nfetchers = 1\n\
             [sim]\ndt = 0.05\nscripts_dir = \"{}/scripts\"\nregion = {{ min = [512, 512], max = [640, 640] }}\n\
             [[scripts]]\nfile = \"water.lua\"\nparams = {{ rain = 0.5 }}\n\
             {camera}\n\
             [render]\nwidth = 48\nheight = 32\ntracer = \"cpu\"\n\
             [frames]\nevery = 5\n[checkpoint]\nevery = 20\n[control]\naddr = \"127.0.0.1:0\"\n",
            env!("CARGO_MANIFEST_DIR")
        ),
    )
    .unwrap();
    (cfg, dir.join("state"))
}

const FLY: &str = "[camera]\nmode = \"line\"\neye = [560.0, 120.0, 560.0]\ntarget = [700.0, 60.0, 580.0]\nvelocity = [400.0, 0.0, 100.0]\n";

/// The chunks the store holds, as chunk coordinates.
fn stored_chunks(cfg: &Path, state: &Path) -> Vec<[i32; 3]> {
    let identity = brickworld::engine::world_config::WorldConfig::load(cfg)
        .unwrap()
        .identity();
    let (db, _) = brickworld::persist::WorldDb::open(state, &identity).unwrap();
    db.chunk_keys()
        .unwrap()
        .into_iter()
        .map(|k| k.0.to_array())
        .collect()
}

#[test]
fn a_streamed_world_stores_only_its_region_and_resumes_bit_identically() {
    let (cfg, state) = streamed("resume", "size = [2048, 96, 2048]", FLY);
    let (_, err) = run_ok(&cfg, &state, "--until-tick", 30);
    assert!(
        err.contains("streaming: simulated region of 4 chunk columns"),
        "{err}"
    );
    let legs = hash_at(&cfg, &state, 60);
    let fresh = state.with_file_name("fresh");
    let straight = hash_at(&cfg, &fresh, 60);
    assert_eq!(legs, straight, "30 + 30 ticks differ from 60 in one go");
    // The camera flew 600 voxels east over the unsimulated terrain; only
    // the simulated region's chunks (x and z in 8..10) were ever stored.
    let chunks = stored_chunks(&cfg, &state);
    assert!(!chunks.is_empty());
    for c in &chunks {
        assert!(
            (8..10).contains(&c[0]) && (8..10).contains(&c[2]),
            "chunk {c:?} stored"
        );
    }
    // Frames were drawn along the flight.
    let frames = std::fs::read_dir(state.join("frames")).unwrap().count();
    assert!(frames >= 10, "{frames} frames");
    // The backup of a streamed world is its region (regression: export
    // tried to build the whole world).
    let backup = state.with_file_name("backup.bwc");
    let out = std::process::Command::new(env!("CARGO_BIN_EXE_brickworld"))
        .args(["export", backup.to_str().unwrap(), "--world"])
        .arg(&cfg)
        .arg("--state")
        .arg(&state)
        .output()
        .unwrap();
    let said = String::from_utf8_lossy(&out.stdout);
    assert!(
        out.status.success() && said.contains("exported tick 60"),
        "{said}{}",
        String::from_utf8_lossy(&out.stderr)
    );
}

#[test]
fn an_unbounded_world_streams_as_the_camera_flies() {
    let (cfg, state) = streamed("endless", "height = 96", FLY);
    let (_, err) = run_ok(&cfg, &state, "--ticks", 200);
    assert!(
        !err.contains("panicked") && !err.contains("warning"),
        "{err}"
    );
    // 200 ticks × 0.05 s × 400 voxels/s: the camera is 4 000 voxels east,
    // far outside any bounded extent, and the frames kept coming.
    let newest = std::fs::read_dir(state.join("frames"))
        .unwrap()
        .filter_map(|e| e.ok())
        .map(|e| e.file_name().to_string_lossy().to_string())
        .max()
        .unwrap();
    assert_eq!(newest, "frame-00000200.png");
    for c in stored_chunks(&cfg, &state) {
        assert!(
            (8..10).contains(&c[0]) && (8..10).contains(&c[2]),
            "chunk {c:?} stored"
        );
    }
}

/// The same flight with the GPU tracer (lavapipe in CI): the toroidal
/// grid slides under the GPU's streamed copy without a fallback.
#[test]
fn an_unbounded_world_streams_on_the_gpu_too() {
    let (cfg, state) = streamed("endless-gpu", "height = 96", FLY);
    common::daemon::edit_config(&cfg, "tracer = \"cpu\"", "tracer = \"gpu\"");
    let (_, err) = run_ok(&cfg, &state, "--ticks", 100);
    assert!(!err.contains("panicked"), "{err}");
    if common::gpu_context().is_some() {
        assert!(!err.contains("rendering on the CPU"), "{err}");
    }
    let frames = std::fs::read_dir(state.join("frames")).unwrap().count();
    assert!(frames >= 10, "{frames} frames");
}

#[test]
fn a_budget_too_small_for_one_view_names_the_minimum() {
    let (cfg, state) = streamed("budget", "size = [2048, 96, 2048]", FLY);
    let out = run_cmd(&cfg, &state)
        .args(["--ticks", "5", "--memory-budget", "64KiB"])
        .output()
        .unwrap();
    assert!(!out.status.success());
    let err = String::from_utf8_lossy(&out.stderr);
    assert_eq!(err.trim().lines().count(), 1, "{err}");
    assert!(
        err.contains("memory budget 64 KiB is too small for one view") && err.contains("at least"),
        "{err}"
    );
    // The minimum it names is enough.
    let need = err
        .split("memory_budget to ")
        .nth(1)
        .and_then(|s| s.split(',').next())
        .unwrap_or_else(|| panic!("no minimum in {err}"))
        .replace(' ', "");
    let out = run_cmd(&cfg, &state)
        .args(["--ticks", "5", "--memory-budget", &need])
        .output()
        .unwrap();
    assert!(
        out.status.success(),
        "{need}: {}",
        String::from_utf8_lossy(&out.stderr)
    );
    for bad in ["lots", "0", "3 parsecs", "9e99GiB"] {
        let out = run_cmd(&cfg, &state)
            .args(["--ticks", "5", "--memory-budget", bad])
            .output()
            .unwrap();
        assert_clear_failure(&out, bad, "--memory-budget");
    }
}

#[test]
fn a_memory_budget_for_a_world_that_does_not_stream_is_refused() {
    let (cfg, state, _) = common::daemon::setup("budget-resident");
    let out = run_cmd(&cfg, &state)
        .args(["--ticks", "5", "--memory-budget", "1GiB"])
        .output()
        .unwrap();
    assert_clear_failure(
        &out,
        "a budget for a resident world",
        "--memory-budget applies to streamed worlds",
    );
}
