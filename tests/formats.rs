//! File formats: MagicaVoxel through `dot_vox` (its documented
//! `placeholder.vox`), heightmap PNGs (exact columns, 8 and 16 bit), and
//! clear errors for corrupt, truncated, wrong-kind and oversized files.

use std::path::{Path, PathBuf};

mod common;

use brickworld::scene::{SceneError, SceneSpec, build_scene};
use glam::IVec3;
use indicatif::ProgressBar;

fn tmp(name: &str) -> common::scratch::Scratch {
    common::cli::tmp("formats", name)
}

/// The `dot_vox` crate's source folder, found through `cargo metadata`.
fn dot_vox_dir() -> PathBuf {
    let cargo = std::env::var("CARGO").unwrap_or_else(|_| "cargo".into());
    let out = std::process::Command::new(cargo)
        .args(["metadata", "--format-version", "1"])
        .current_dir(env!("CARGO_MANIFEST_DIR"))
        .output()
        .expect("cargo metadata runs");
    let meta: serde_json::Value = serde_json::from_slice(&out.stdout).expect("cargo metadata JSON");
    let pkg = meta["packages"]
        .as_array()
        .unwrap()
        .iter()
        .find(|p| p["name"] == "dot_vox")
        .expect("dot_vox is a dependency");
    Path::new(pkg["manifest_path"].as_str().unwrap())
        .parent()
        .unwrap()
        .to_path_buf()
}

fn build(spec: SceneSpec) -> Result<brickworld::scene::SceneWorld, SceneError> {
    build_scene(&spec, IVec3::splat(8), 0, &ProgressBar::hidden())
}

#[test]
fn placeholder_vox_matches_the_crates_documented_voxels() {
    let path = dot_vox_dir().join("src/resources/placeholder.vox");
    let w = build(SceneSpec::Vox(path.to_path_buf())).unwrap();
    // dot_vox documents model 0 (2×2×2) as voxels (x, y, z, i):
    // (0,0,0,225) (0,1,1,215) (1,0,1,235) (1,1,0,5), under a transform
    // `_t = "0 0 1"`. Centre c = v + 0.5 − 1, plus t, then Z-up → Y-up
    // (x, z, −y) and floor gives these world voxels; material = i + 1.
    let expected = [
        (IVec3::new(-1, 0, 0), 226u8),
        (IVec3::new(-1, 1, -1), 216),
        (IVec3::new(0, 1, 0), 236),
        (IVec3::new(0, 0, -1), 6),
    ];
    assert_eq!(w.store().solid_voxels(), 4);
    for (p, m) in expected {
        assert_eq!(w.store().voxel(p), m, "voxel {p}");
        let c = dot_vox::DEFAULT_PALETTE[m as usize - 1];
        assert_eq!(w.store().palette().rgb(m), [c.r, c.g, c.b]);
    }
    assert_eq!(w.bounds(), (IVec3::new(-1, 0, -1), IVec3::new(1, 2, 1)));
}

#[test]
fn every_vox_resource_of_dot_vox_loads_or_fails_cleanly() {
    let dir = dot_vox_dir().join("src/resources");
    for entry in std::fs::read_dir(dir).unwrap() {
        let p = entry.unwrap().path();
        if p.extension().is_some_and(|e| e == "vox") {
            match build(SceneSpec::Vox(p.to_path_buf())) {
                Ok(w) => assert!(w.store().solid_voxels() > 0, "{}", p.display()),
                Err(e) => assert!(e.to_string().contains(&*p.to_string_lossy()), "{e}"),
            }
        }
    }
}

fn write_gray_png(path: &Path, w: u32, h: u32, depth: png::BitDepth, data: &[u8]) {
    let f = std::io::BufWriter::new(std::fs::File::create(path).unwrap());
    let mut enc = png::Encoder::new(f, w, h);
    enc.set_color(png::ColorType::Grayscale);
    enc.set_depth(depth);
    enc.write_header().unwrap().write_image_data(data).unwrap();
}

#[test]
fn heightmap_png_gives_exactly_the_columns_it_encodes() {
    // 8-bit, 13×9, heights 0..=37.
    let (w, h) = (13u32, 9u32);
    let heights: Vec<u8> = (0..w * h).map(|i| ((i * 7919) % 38) as u8).collect();
    let path = tmp("h8.png");
    write_gray_png(&path, w, h, png::BitDepth::Eight, &heights);
    let world = build(SceneSpec::Heightmap(path.to_path_buf())).unwrap();
    for v in 0..h as i32 {
        for u in 0..w as i32 {
            let hv = heights[(v as u32 * w + u as u32) as usize] as i32;
            for y in -2..45 {
                let solid = world.store().voxel(IVec3::new(u, y, v)) != 0;
                assert_eq!(
                    solid,
                    (0..hv).contains(&y),
                    "column ({u}, {v}) height {hv} at y = {y}"
                );
            }
        }
    }
    // 16-bit, big-endian samples above 255.
    let vals: [u16; 4] = [300, 0, 1, 513];
    let bytes: Vec<u8> = vals.iter().flat_map(|v| v.to_be_bytes()).collect();
    let path = tmp("h16.png");
    write_gray_png(&path, 2, 2, png::BitDepth::Sixteen, &bytes);
    let world = build(SceneSpec::Heightmap(path.to_path_buf())).unwrap();
    for (i, &hv) in vals.iter().enumerate() {
        let (u, v) = ((i % 2) as i32, (i / 2) as i32);
        let top = (0..600)
            .filter(|&y| world.store().voxel(IVec3::new(u, y, v)) != 0)
            .count();
        assert_eq!(top, hv as usize);
    }
}

/// Regression (hostile probe): a heightmap whose compressed data was
/// damaged, with its chunk CRCs made to match, was read as other terrain:
/// the zlib stream's Adler-32 was not checked. Here only that checksum is
/// wrong, so nothing else could catch it.
#[test]
fn a_heightmap_with_a_wrong_zlib_checksum_is_refused() {
    let path = tmp("adler.png");
    write_gray_png(&path, 4, 4, png::BitDepth::Eight, &[9u8; 16]);
    let mut bytes = std::fs::read(&path).unwrap();
    // Chunks from byte 8: length, type, data, CRC over type and data.
    let mut at = 8;
    loop {
        let len = u32::from_be_bytes(bytes[at..at + 4].try_into().unwrap()) as usize;
        if &bytes[at + 4..at + 8] == b"IDAT" {
            let end = at + 8 + len; // the zlib stream ends with its Adler-32
            bytes[end - 1] ^= 0x5a;
            let crc = crc32fast::hash(&bytes[at + 4..end]);
            bytes[end..end + 4].copy_from_slice(&crc.to_be_bytes());
            break;
        }
        at += 12 + len;
    }
    std::fs::write(&path, &bytes).unwrap();
    expect_error(SceneSpec::Heightmap(path.to_path_buf()), "PNG");
}

fn expect_error(spec: SceneSpec, needle: &str) {
    let e = build(spec).expect_err("must fail").to_string();
    assert!(e.contains(needle), "error '{e}' should mention '{needle}'");
    assert!(!e.contains('\n'), "one-line error: {e}");
}

#[test]
fn bad_files_give_clear_errors() {
    let missing = tmp("does-not-exist.png");
    expect_error(SceneSpec::Heightmap(missing.to_path_buf()), "cannot read");
    expect_error(SceneSpec::Vox(missing.to_path_buf()), "cannot read");

    let garbage = tmp("garbage.bin");
    std::fs::write(&garbage, b"this is not an image at all, just text\n").unwrap();
    expect_error(
        SceneSpec::Heightmap(garbage.to_path_buf()),
        "not a valid PNG heightmap",
    );
    expect_error(
        SceneSpec::Vox(garbage.to_path_buf()),
        "not a valid MagicaVoxel .vox",
    );

    // Truncated: a valid PNG cut in half.
    let good = tmp("good.png");
    write_gray_png(&good, 64, 64, png::BitDepth::Eight, &vec![9u8; 64 * 64]);
    let bytes = std::fs::read(&good).unwrap();
    let cut = tmp("cut.png");
    std::fs::write(&cut, &bytes[..bytes.len() / 2]).unwrap();
    expect_error(
        SceneSpec::Heightmap(cut.to_path_buf()),
        "not a valid PNG heightmap",
    );

    // A chunk before IHDR: the decoder's debug text of the chunk type is
    // turned into its name (regression: `ChunkType { type: AGEG, critical:
    // true, private: false, … }`).
    let early = tmp("early-chunk.png");
    std::fs::write(&early, b"\x89PNG\r\n\x1a\nGARBAGEGARBAGE").unwrap();
    let e = build(SceneSpec::Heightmap(early.to_path_buf()))
        .expect_err("must fail")
        .to_string();
    assert!(
        e.contains("'AGEG' chunk appeared") && !e.contains("ChunkType"),
        "{e}"
    );

    // Truncated .vox: the documented placeholder cut short.
    let vox = std::fs::read(dot_vox_dir().join("src/resources/placeholder.vox")).unwrap();
    let cut = tmp("cut.vox");
    std::fs::write(&cut, &vox[..vox.len() / 3]).unwrap();
    expect_error(
        SceneSpec::Vox(cut.to_path_buf()),
        "not a valid MagicaVoxel .vox",
    );

    // Wrong kind of PNG: RGB.
    let rgb = tmp("rgb.png");
    brickworld::trace::write_png(&rgb, 2, 2, &[0u8; 12]).unwrap();
    expect_error(SceneSpec::Heightmap(rgb.to_path_buf()), "grayscale");

    // Oversized: too wide, and too big a file (sparse, never read).
    let wide = tmp("wide.png");
    write_gray_png(&wide, 16385, 1, png::BitDepth::Eight, &vec![1u8; 16385]);
    expect_error(
        SceneSpec::Heightmap(wide.to_path_buf()),
        "over the 16384x16384 limit",
    );
    let huge = tmp("huge.vox");
    std::fs::File::create(&huge)
        .unwrap()
        .set_len(300 << 20)
        .unwrap();
    expect_error(SceneSpec::Vox(huge.to_path_buf()), "too large");
    std::fs::remove_file(&huge).unwrap();

    // Too tall for the world: a 16-bit value over the height limit.
    let tall = tmp("tall.png");
    write_gray_png(&tall, 1, 1, png::BitDepth::Sixteen, &60000u16.to_be_bytes());
    expect_error(SceneSpec::Heightmap(tall.to_path_buf()), "taller than");
}

/// A one-model `.vox` file of `size` holding `voxels`, written to `name`.
fn model_file(name: &str, size: [u32; 3], voxels: Vec<dot_vox::Voxel>) -> common::scratch::Scratch {
    use dot_vox::{DotVoxData, Model, Size};
    let data = DotVoxData {
        version: 150,
        index_map: Vec::new(),
        models: vec![Model {
            size: Size {
                x: size[0],
                y: size[1],
                z: size[2],
            },
            voxels,
        }],
        palette: dot_vox::DEFAULT_PALETTE.to_vec(),
        materials: Vec::new(),
        scenes: Vec::new(),
        layers: Vec::new(),
    };
    let path = tmp(name);
    let mut bytes = Vec::new();
    data.write_vox(&mut bytes).unwrap();
    std::fs::write(&path, bytes).unwrap();
    path
}

/// A one-row model whose voxel `k` has colour index `colours[k]` (0-based,
/// as `dot_vox` reports it), written to `name`.
fn row_model(name: &str, colours: &[u8]) -> common::scratch::Scratch {
    let voxels = colours
        .iter()
        .enumerate()
        .map(|(k, &i)| dot_vox::Voxel {
            x: k as u8,
            y: 0,
            z: 0,
            i,
        })
        .collect();
    model_file(name, [colours.len() as u32, 1, 1], voxels)
}

/// `sim` for one step of the shipped `script` on the `.vox` model at
/// `path`.
fn sim_on(path: &Path, script: &str) -> std::process::Output {
    std::process::Command::new(env!("CARGO_BIN_EXE_brickworld"))
        .args(["sim", "--steps", "1", "--script"])
        .arg(format!("{}/scripts/{script}", env!("CARGO_MANIFEST_DIR")))
        .arg("--out")
        .arg(&tmp("sim_on.png"))
        .arg("--scene")
        .arg(format!("vox:{}", path.display()))
        .output()
        .unwrap()
}

/// `run --ticks 1` of the engine on the `.vox` model at `path`, with the
/// shipped `script`, in a fresh state directory `state` under this test's
/// folder; returns the output and the state directory.
fn run_on(
    path: &Path,
    script: &str,
    name: &str,
) -> (std::process::Output, common::scratch::Scratch) {
    let cfg = tmp(&format!("{name}.toml"));
    std::fs::write(
        &cfg,
        format!(
            "[world]\nsource = \"vox:{}\"\n[sim]\nscripts_dir = \"{}/scripts\"\n[[scripts]]\nfile = \"{script}\"\n\
             [render]\nwidth = 16\nheight = 12\ntracer = \"cpu\"\n[control]\naddr = \"127.0.0.1:0\"\n",
            path.display(),
            env!("CARGO_MANIFEST_DIR")
        ),
    )
    .unwrap();
    let state = tmp(&format!("{name}-state"));
    let _ = std::fs::remove_dir_all(&state);
    let out = std::process::Command::new(env!("CARGO_BIN_EXE_brickworld"))
        .arg("run")
        .arg(&cfg)
        .arg("--state")
        .arg(&state)
        .args(["--ticks", "1"])
        .env_remove("RUST_BACKTRACE")
        .output()
        .unwrap();
    (out, state)
}

/// Claim (README, known gaps): the engine, like `sim`, refuses a `.vox`
/// model whose colours hold the simulations' ids 252 to 254, in one line,
/// and writes no store (claims audit: only `sim` and `import` were tested;
/// without the check the engine would run water over those voxels and
/// commit them).
#[test]
fn the_engine_refuses_a_vox_model_on_the_simulations_ids() {
    let all: Vec<u8> = (0..=254).collect();
    let full = row_model("full_run.vox", &all);
    let (out, state) = run_on(&full, "water.lua", "full");
    common::cli::assert_clear_failure(
        &out,
        "run on a 255-colour model",
        "hold ids 252 to 254, which simulations keep for water, snow and sediment",
    );
    assert!(!state.exists(), "a refused start left {}", state.display());
}

/// Regression (panic audit): a model's voxels of colours 252 to 254 held
/// the material ids simulations keep for water, snow and sediment, so once
/// a simulation ran they became water (a red voxel counted as liquid), with
/// no error. They now take ids the model does not use, with their colours;
/// a model of more than 251 colours, which cannot, is refused by `sim`.
#[test]
fn vox_colours_on_the_simulations_ids_move_out_of_their_way() {
    let colours = [0u8, 5, 251, 252, 253];
    let path = row_model("sim_ids.vox", &colours);
    let world = build_scene(
        &SceneSpec::Vox(path.to_path_buf()),
        IVec3::ONE,
        1,
        &ProgressBar::hidden(),
    )
    .unwrap();
    let (lo, _) = world.bounds();
    let held: Vec<u8> = (0..5)
        .map(|k| world.store().voxel(lo + IVec3::new(k, 0, 0)))
        .collect();
    assert!(held.iter().all(|&m| (1..252).contains(&m)), "{held:?}");
    assert_eq!(held[..2], [1, 6], "other colours keep their ids");
    let mut distinct = held.clone();
    distinct.sort();
    distinct.dedup();
    assert_eq!(distinct.len(), 5, "{held:?}");
    for (k, &m) in held.iter().enumerate() {
        let c = dot_vox::DEFAULT_PALETTE[colours[k] as usize];
        assert_eq!(world.store().palette().rgb(m), [c.r, c.g, c.b], "voxel {k}");
    }
    for id in 252..=254u8 {
        assert!(world.materials.get(id).is_none(), "id {id} is taken");
    }
    // 255 colours: the simulations' ids cannot be freed, and `sim` says so.
    let all: Vec<u8> = (0..=254).collect();
    let full = row_model("full.vox", &all);
    common::cli::assert_clear_failure(
        &sim_on(&full, "water.lua"),
        "sim on a 255-colour model",
        "hold ids 252 to 254, which simulations keep for water, snow and sediment",
    );
}

/// Regression (panic audit): column scripts see the world from y = 0 up,
/// and a `.vox` model is centred on the origin, so they saw nothing of its
/// lower half without a word. `sim` (and the engine) now say so when a
/// column script runs on a world reaching below y = 0, and not for voxel
/// scripts, which see all of it.
#[test]
fn column_scripts_on_a_world_below_zero_are_warned() {
    let voxels = (0..8)
        .map(|z| dot_vox::Voxel {
            x: 0,
            y: 0,
            z,
            i: 3,
        })
        .collect();
    let path = model_file("tower.vox", [2, 2, 8], voxels);
    let sim = |script: &str| {
        let out = sim_on(&path, script);
        assert!(out.status.success(), "{out:?}");
        String::from_utf8_lossy(&out.stderr).to_string()
    };
    let warned =
        "column scripts see the world from y = 0 up, and this world reaches down to y = -4";
    assert!(sim("water.lua").contains(warned));
    assert!(!sim("water3d.lua").contains("column scripts see"));
    // The engine says it too (claims audit: only `sim` was tested).
    let (out, _) = run_on(&path, "water.lua", "tower");
    let err = String::from_utf8_lossy(&out.stderr);
    assert!(out.status.success(), "{err}");
    assert_eq!(err.matches(warned).count(), 1, "{err}");
    let (out, _) = run_on(&path, "water3d.lua", "tower3d");
    let err = String::from_utf8_lossy(&out.stderr);
    assert!(out.status.success(), "{err}");
    assert!(!err.contains("column scripts see"), "{err}");
}
