//! World configs: the shipped worlds load; bad configs give errors that name
//! the file, the field and the reason.

use std::path::Path;

use brickworld::engine::world_config::{CameraMode, WorldConfig};
use brickworld::scene::{SceneSpec, build_scene};
use indicatif::ProgressBar;

const ROOT: &str = env!("CARGO_MANIFEST_DIR");

#[test]
fn the_shipped_worlds_load_and_build() {
    for name in [
        "default",
        "snowy_mountain",
        "valley",
        "caves",
        "sandbox",
        "continent",
        "endless",
    ] {
        let path = Path::new(ROOT).join("worlds").join(format!("{name}.toml"));
        let cfg = WorldConfig::load(&path).unwrap_or_else(|e| panic!("{e}"));
        for s in &cfg.scripts {
            assert!(
                cfg.scripts_dir.join(&s.file).exists(),
                "{name}: {} missing",
                s.file
            );
        }
        if let SceneSpec::Heightmap(_) = cfg.source {
            build_scene(&cfg.source, cfg.size, cfg.seed, &ProgressBar::hidden()).unwrap();
        }
    }
    let d = WorldConfig::default_world();
    assert_eq!(d.scripts.len(), 3);
    // The default world runs from any directory: its scripts are built in.
    assert!(d.scripts_embedded);
    for s in &d.scripts {
        assert!(
            brickworld::sim::embedded::script(&s.file).is_some(),
            "{} not embedded",
            s.file
        );
    }
    assert!(matches!(d.camera.mode, CameraMode::Orbit { .. }));
    let snowy = WorldConfig::load(&Path::new(ROOT).join("worlds/snowy_mountain.toml")).unwrap();
    assert!(matches!(snowy.camera.mode, CameraMode::Fly { period_s, .. } if period_s == 120.0));
}

fn error(text: &str) -> String {
    WorldConfig::parse("bad.toml", text, Path::new("."))
        .unwrap_err()
        .to_string()
}

#[test]
fn bad_configs_name_the_file_field_and_reason() {
    let ok = "[world]\nsource = \"terrain\"\n";
    assert!(WorldConfig::parse("ok.toml", ok, Path::new(".")).is_ok());
    let cases = [
        (
            "[world]\nsource = \"terrain\"\ncolour = 3\n",
            "unknown field `colour`",
        ),
        ("[world]\nsource = \"lava\"\n", "world.source"),
        (
            "[world]\nsource = \"terrain\"\nsize = [4, 8, 8]\n",
            "world.size",
        ),
        // Arrays of another length (regression, hostile probe: the extra
        // numbers were ignored).
        (
            "[world]\nsource = \"terrain\"\nsize = [64, 32, 64, 5]\n",
            "world.size (line 3, column 8): expected an array of 3 numbers, found 4",
        ),
        (
            "[world]\nsource = \"terrain\"\n[camera]\neye = [1, 2]\n",
            "expected an array of 3 numbers, found 2",
        ),
        (
            "[world]\nsource = \"terrain\"\n[sim]\nregion = { min = [0, 0, 0], max = [8, 8] }\n",
            "expected an array of 2 numbers, found 3",
        ),
        ("[world]\nsource = \"terrain\"\nsize = \"big\"\n", "line 3"),
        // Regression (hostile probe): a wrong type named only the line and
        // column, in Rust's words.
        (
            "[world]\nsource = \"terrain\"\n[render]\nwidth = \"64\"\n",
            "render.width (line 4, column 9): invalid type: string \"64\", expected a whole number",
        ),
        (
            "[world]\nsource = \"terrain\"\n[[scripts]]\nfile = \"a.lua\"\n[[scripts]]\nfile = \"b.lua\"\nevery = 1.5\n",
            "scripts[1].every (line 7",
        ),
        // Regression (hostile probe 2): past 64 bits, "expected a whole
        // number" of a whole number.
        (
            "[world]\nsource = \"terrain\"\n[checkpoint]\nevery = 18446744073709551615\n",
            "checkpoint.every (line 4, column 9): 18446744073709551615 is too large",
        ),
        // (Review: a negative one was "too large" too.)
        (
            "[world]\nsource = \"terrain\"\nseed = -1\n",
            "world.seed (line 3, column 8): -1 is below 0",
        ),
        (
            "[world]\nsource = \"terrain\"\n[sim]\ndt = \"fast\"\n",
            "sim.dt (line 4, column 6): invalid type: string \"fast\", expected a number",
        ),
        (
            "[world]\nsource = \"terrain\"\n[sim]\ndt = -1.0\n",
            "sim.dt",
        ),
        (
            "[world]\nsource = \"terrain\"\n[sim]\nradius = 64.0\nregion = { min = [0, 0], max = [8, 8] }\n",
            "not both",
        ),
        (
            "[world]\nsource = \"terrain\"\n[sim]\nregion = { min = [8, 0], max = [8, 8] }\n",
            "sim.region",
        ),
        (
            "[world]\nsource = \"terrain\"\n[sim]\nradius = 2.0\n",
            "sim.radius",
        ),
        (
            "[world]\nsource = \"terrain\"\n[sim]\nregion = { min = [0, 0] }\n",
            "missing field `max`",
        ),
        (
            "[world]\nsource = \"terrain\"\n[[scripts]]\nfile = \"../evil.lua\"\n",
            "scripts[0].file",
        ),
        (
            "[world]\nsource = \"terrain\"\n[[scripts]]\nfile = \"w.lua\"\nevery = 0\n",
            "scripts[0].every",
        ),
        // Regression (review): one file twice was two scripts of one name.
        (
            "[world]\nsource = \"terrain\"\n[[scripts]]\nfile = \"w.lua\"\n[[scripts]]\nfile = \"w.lua\"\n",
            "scripts[1].file: 'w.lua' is already listed as scripts[0]",
        ),
        (
            "[world]\nsource = \"terrain\"\n[camera]\nfov = 200.0\n",
            "camera.fov",
        ),
        // Regression (hostile probe): 1e300 was printed with all its 301
        // digits, and 1e-40 as a 42-digit decimal.
        (
            "[world]\nsource = \"terrain\"\n[frames]\nmax_mb = 1e300\n",
            "frames.max_mb: 1e300 is outside",
        ),
        (
            "[world]\nsource = \"terrain\"\n[render]\nlod = 1e-40\n",
            "render.lod: 1e-40 is not a cell footprint",
        ),
        // Regression (hostile probe): the config took any fov in (0, 180),
        // where --fov and POST /camera take 0.01..=179.
        (
            "[world]\nsource = \"terrain\"\n[camera]\nfov = 1e-300\n",
            "camera.fov: 1e-300 is outside 0.01..=179 degrees",
        ),
        (
            "[world]\nsource = \"terrain\"\n[camera]\nfov = 179.99999999\n",
            "camera.fov",
        ),
        // Regression (hostile probe): a subnormal period drew no frames.
        (
            "[world]\nsource = \"terrain\"\n[camera]\nmode = \"orbit\"\norbit_period_s = 5e-324\n",
            "camera.orbit_period_s: 5e-324 must be from 0.01 to 1e9 seconds",
        ),
        // Regression (hostile probe): the command line caps --eye at 1e9.
        (
            "[world]\nsource = \"terrain\"\n[camera]\neye = [1e30, 0.0, 0.0]\ntarget = [0.0, 0.0, 1.0]\n",
            "camera.eye: [1e30, 0.0, 0.0] must be finite and within ±1e9 voxels",
        ),
        (
            "[world]\nsource = \"terrain\"\n[camera]\nmode = \"spin\"\n",
            "camera.mode",
        ),
        (
            "[world]\nsource = \"terrain\"\n[camera]\neye = [1.0, 2.0, 3.0]\ntarget = [1.0, 2.0, 3.0]\n",
            "camera.target",
        ),
        (
            "[world]\nsource = \"terrain\"\n[camera]\neye = [1.0, 2.0, 3.0]\n",
            "camera.target",
        ),
        (
            "[world]\nsource = \"terrain\"\n[camera]\nmode = \"fly\"\neye = [1.0, 2.0, 3.0]\ntarget = [4.0, 2.0, 3.0]\n",
            "camera.fly_to",
        ),
        (
            "[world]\nsource = \"terrain\"\n[camera]\nmode = \"fly\"\nfly_to = [1.0, 2.0, 3.0]\nfly_period_s = -1.0\n",
            "camera.fly_period_s",
        ),
        (
            "[world]\nsource = \"terrain\"\n[render]\nwidth = 0\n",
            "render.width",
        ),
        // Streamed and unbounded worlds.
        (
            "[world]\nsource = \"terrain\"\nsize = [64, 64, 64]\nheight = 64\n",
            "world.height: give size",
        ),
        (
            "[world]\nsource = \"balls\"\nheight = 64\n",
            "world.height: only terrain",
        ),
        (
            "[world]\nsource = \"terrain\"\nheight = 64\n",
            "stream: an unbounded world must stream",
        ),
        (
            "[world]\nsource = \"terrain\"\nheight = 64\n[stream]\n",
            "sim.region: a streamed world",
        ),
        (
            "[world]\nsource = \"terrain\"\n[stream]\n[sim]\nradius = 64.0\n",
            "camera.eye: is needed when a streamed world's region follows the camera",
        ),
        (
            "[world]\nsource = \"balls\"\n[stream]\n",
            "stream: only terrain",
        ),
        (
            "[world]\nsource = \"terrain\"\n[stream]\nmemory_budget = \"lots\"\n[sim]\nregion = { min = [0, 0], max = [8, 8] }\n",
            "stream.memory_budget: 'lots' is not a size",
        ),
        (
            "[world]\nsource = \"terrain\"\n[stream]\nmemory_budget = \"2 parsecs\"\n[sim]\nregion = { min = [0, 0], max = [8, 8] }\n",
            "unknown unit",
        ),
        (
            "[world]\nsource = \"terrain\"\n[stream]\nmemory_budget = -5\n[sim]\nregion = { min = [0, 0], max = [8, 8] }\n",
            "stream.memory_budget",
        ),
        (
            "[world]\nsource = \"terrain\"\n[stream]\nview_distance = 1.0\n[sim]\nregion = { min = [0, 0], max = [8, 8] }\n",
            "stream.view_distance",
        ),
        (
            "[world]\nsource = \"terrain\"\n[stream]\nfetchers = 0\n[sim]\nregion = { min = [0, 0], max = [8, 8] }\n",
            "stream.fetchers",
        ),
        (
            "[world]\nsource = \"terrain\"\nsize = [64, 64, 64]\n[stream]\n[sim]\nregion = { min = [100, 0], max = [200, 8] }\n",
            "lies outside the world",
        ),
        (
            "[world]\nsource = \"terrain\"\n[camera]\nmode = \"line\"\neye = [1.0, 2.0, 3.0]\ntarget = [4.0, 2.0, 3.0]\n",
            "camera.velocity: is needed",
        ),
        (
            "[world]\nsource = \"terrain\"\n[camera]\nmode = \"line\"\nvelocity = [1e9, 0.0, 0.0]\neye = [1.0, 2.0, 3.0]\ntarget = [4.0, 2.0, 3.0]\n",
            "camera.velocity",
        ),
        (
            "[world]\nsource = \"terrain\"\n[render]\ntracer = \"tpu\"\n",
            "render.tracer",
        ),
        (
            "[world]\nsource = \"terrain\"\n[render]\nfog = -5.0\n",
            "render.fog: -5 is outside",
        ),
        (
            "[world]\nsource = \"terrain\"\n[render]\naa = 0\n",
            "render.aa: 0 is outside 1..=16",
        ),
        (
            "[world]\nsource = \"terrain\"\n[render]\nlod = -2.0\n",
            "render.lod: -2 is not a cell footprint",
        ),
        (
            "[world]\nsource = \"terrain\"\n[render]\nlod = 1e-50\n",
            "render.lod: 1e-50 is not a cell footprint",
        ),
        (
            "[world]\nsource = \"terrain\"\n[render]\nlod = nan\n",
            "render.lod: NaN is not a cell footprint",
        ),
        (
            "[world]\nsource = \"terrain\"\n[frames]\nmax_mb = 0.5\n",
            "frames.max_mb: 0.5 is outside 1..=1048576 MiB",
        ),
        (
            "[world]\nsource = \"terrain\"\n[frames]\nmax_mb = inf\n",
            "frames.max_mb: inf is outside",
        ),
        (
            "[world]\nsource = \"terrain\"\n[checkpoint]\nevery = 0\n",
            "checkpoint.every",
        ),
        (
            "[world]\nsource = \"terrain\"\n[frames]\nevery = 0\n",
            "frames.every: 0 is outside 1..=100000000 ticks",
        ),
        (
            "[world]\nsource = \"terrain\"\n[frames]\nkeep = 0\n",
            "frames.keep: 0 is outside 1..=1000000",
        ),
        (
            "[world]\nsource = \"terrain\"\n[[place]]\nmaterial = \"lava\"\nat = [0, 0, 0]\nsize = [0, 1, 1]\n",
            "place[0]: at [0, 0, 0] size [0, 1, 1]: sizes must be 1..=65536",
        ),
        // Regression (code review): `abs()` of i64::MIN wraps to itself,
        // so this position passed the ±2^24 check and became x = 0.
        (
            "[world]\nsource = \"terrain\"\n[[place]]\nmaterial = \"lava\"\nat = [-9223372036854775808, 0, 0]\n",
            "place[0]: at [-9223372036854775808, 0, 0] size [1, 1, 1]: sizes must be 1..=65536 and positions within ±2^24",
        ),
        (
            "[world]\nsource = \"terrain\"\n[control]\naddr = \"localhost\"\n",
            "control.addr",
        ),
        (
            "[world]\nsource = \"terrain\"\n[control]\nhosts = [\"box.lan:80\"]\n",
            "control.hosts: \"box.lan:80\" is not a host name",
        ),
        (
            "[world]\nsource = \"terrain\"\n[control]\nhosts = [\"\"]\n",
            "control.hosts: \"\" is not a host name",
        ),
        (
            "[world]\nsource = \"vox:m.vox\"\nsize = [8, 8, 8]\n",
            "world.size",
        ),
        ("this is = not [ toml", "line 1"),
        ("", "missing field `world`"),
    ];
    for (text, needle) in cases {
        let e = error(text);
        assert!(e.starts_with("bad.toml: "), "{e}");
        assert!(e.contains(needle), "'{e}' should mention '{needle}'");
    }
    let missing = WorldConfig::load(Path::new("/nonexistent/world.toml"))
        .unwrap_err()
        .to_string();
    assert!(
        missing.contains("/nonexistent/world.toml") && missing.contains("cannot read"),
        "{missing}"
    );
}

/// Claim (README): `render.lod = 0` is not refused, as `--lod 0` is: it
/// turns level of detail off (claims audit: only refused values were
/// tested). -0 does the same.
#[test]
fn render_lod_zero_turns_level_of_detail_off() {
    for zero in ["0", "0.0", "-0.0"] {
        let c = WorldConfig::parse(
            "lod.toml",
            &format!("[world]\nsource = \"terrain\"\n[render]\nlod = {zero}\n"),
            Path::new("."),
        )
        .unwrap_or_else(|e| panic!("lod = {zero}: {e}"));
        assert_eq!(c.look.lod.to_bits(), 0, "lod = {zero}");
    }
}

/// The defaults the README states for a config that sets nothing: frames
/// every 10 ticks, 200 kept within 256 MiB, commits every 500 ticks, the
/// `auto` tracer, level of detail C = 1, occlusion and shadows on, beams
/// and anti-aliasing off, 640×360 frames on 127.0.0.1:7878; a streamed
/// world's fog at half its view distance, an unstreamed one without fog.
#[test]
fn a_config_that_sets_nothing_gets_the_documented_defaults() {
    let c = WorldConfig::parse(
        "min.toml",
        "[world]\nsource = \"terrain\"\n",
        Path::new("."),
    )
    .unwrap();
    assert_eq!(c.frames_every, 10);
    assert_eq!(c.frames_keep, 200);
    assert_eq!(c.frames_max_bytes, 256 << 20);
    assert_eq!(c.checkpoint_every, 500);
    assert_eq!(c.look.tracer, brickworld::gpu::TracerChoice::Auto);
    assert_eq!(c.look.lod, 1.0);
    assert!(c.look.ao && c.look.shadows && !c.look.beam);
    assert_eq!(c.look.aa, 1);
    assert_eq!(c.look.fog, 0.0);
    assert_eq!((c.width, c.height), (640, 360));
    assert_eq!(c.addr.to_string(), "127.0.0.1:7878");
    let continent = WorldConfig::load(&Path::new(ROOT).join("worlds/continent.toml")).unwrap();
    let text = std::fs::read_to_string(Path::new(ROOT).join("worlds/continent.toml")).unwrap();
    assert!(
        !text.contains("fog"),
        "continent.toml sets its fog: pick a world that does not"
    );
    let view = continent.stream.as_ref().unwrap().view_distance;
    assert_eq!(continent.look.fog, (view * 0.5) as f32);
}

/// Regression (fuzzing): a NUL in a key reached the error raw, and a
/// 100 000-character tracer name made a 100 KB error line.
#[test]
fn config_errors_escape_control_characters_and_cut_long_values() {
    let nul = error("[world]\nsource = \"terrain\"\n\"si\0ze\" = [48, 32, 48]\n");
    assert!(!nul.contains('\0'), "{nul:?}");
    assert!(
        nul.contains("world.si\\0ze") || nul.contains("world.si\\u{0}ze"),
        "{nul:?}"
    );
    let long = "a".repeat(100_000);
    let e = error(&format!(
        "[world]\nsource = \"terrain\"\n[render]\ntracer = \"{long}\"\n"
    ));
    assert!(e.contains("render.tracer"), "{e}");
    assert!(e.len() < 1000, "{} bytes", e.len());
    assert!(e.contains("more characters)"), "{e}");
    assert!(!e.contains('\n'), "{e}");
    // The file's name too (found by review).
    let named = WorldConfig::parse("x\ny.toml", "[world]\nsize = 1\n", Path::new("."))
        .unwrap_err()
        .to_string();
    assert!(named.starts_with("x\\ny.toml: "), "{named}");
}
