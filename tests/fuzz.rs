//! Fuzzing the decoders of untrusted input (issue 8): the checkpoint file
//! and payload decoders, the .vox and PNG heightmap loaders, the world
//! config, and (issue 10) the world store's chunk, column and state blobs, each fed random bytes and mutations of a valid input. No input
//! may panic. Cases per target: `BRICKWORLD_FUZZ_CASES` (default 2 000 so
//! CI stays quick; the README's figure is from 100 000).

#[path = "common/scratch.rs"]
mod scratch;
use scratch::Scratch;

use brickworld::engine::checkpoint;
use brickworld::engine::world_config::WorldConfig;
use brickworld::scene::{heightmap_from_bytes, vox_voxels_from_bytes};
use proptest::prelude::*;
use proptest::test_runner::{Config, TestRunner};

fn cases() -> u32 {
    std::env::var("BRICKWORLD_FUZZ_CASES")
        .ok()
        .and_then(|v| v.parse().ok())
        .unwrap_or(2000)
}

/// Random bytes, or `seed` with up to 16 random byte changes and a random
/// truncation: mutations of a valid file reach deep into a decoder.
fn inputs(seed: Vec<u8>) -> impl Strategy<Value = Vec<u8>> {
    let n = seed.len().max(1);
    prop_oneof![
        proptest::collection::vec(any::<u8>(), 0..2048),
        (proptest::collection::vec((0..n, any::<u8>()), 0..16), 0..=n,).prop_map(
            move |(edits, keep)| {
                let mut b = seed.clone();
                for (i, v) in edits {
                    if i < b.len() {
                        b[i] = v;
                    }
                }
                b.truncate(keep.max(1));
                b
            }
        ),
    ]
}

/// Run `f` on `cases()` inputs; a panic fails the test with the input.
fn fuzz(name: &str, seed: Vec<u8>, f: impl Fn(&[u8])) {
    let mut runner = TestRunner::new(Config {
        cases: cases(),
        failure_persistence: None,
        ..Config::default()
    });
    let result = runner.run(&inputs(seed), |bytes| {
        let r = std::panic::catch_unwind(std::panic::AssertUnwindSafe(|| f(&bytes)));
        prop_assert!(r.is_ok(), "{name} panicked");
        Ok(())
    });
    if let Err(e) = result {
        panic!("{name}: {e}");
    }
    eprintln!("{name}: {} cases, no panic", cases());
}

fn valid_checkpoint() -> Vec<u8> {
    let w = brickworld::scene::build_scene(
        &brickworld::scene::SceneSpec::Terrain { caves: false },
        glam::IVec3::new(16, 16, 16),
        1,
        &indicatif::ProgressBar::hidden(),
    )
    .unwrap();
    let scratch = Scratch::dir("fuzz");
    let dir = scratch.join("state");
    let state = checkpoint::WorldState {
        tick: 7,
        store: w.store().clone(),
        bounds: w.bounds(),
        channels: Default::default(),
        params: vec![("water".into(), vec![("rain".into(), 0.5)])],
        identity: None,
        extras: Default::default(),
    };
    let (path, _) = checkpoint::write(&dir, &state).unwrap();
    std::fs::read(path).unwrap()
}

#[test]
fn the_checkpoint_decoder_never_panics() {
    let file = valid_checkpoint();
    fuzz("checkpoint file", file.clone(), |b| {
        let _ = checkpoint::parse(b, true);
    });
    // The payload decoder behind the checksums, fed directly.
    let id_len = u32::from_le_bytes(file[40..44].try_into().unwrap()) as usize;
    let raw = lz4_flex::decompress_size_prepended(&file[48 + id_len..]).unwrap();
    fuzz("checkpoint payload", raw, |b| {
        let _ = checkpoint::decode(1, 2, b);
    });
}

#[test]
fn the_vox_loader_never_panics() {
    use dot_vox::{DotVoxData, Frame, Model, SceneNode, ShapeModel, Size, Voxel};
    let mut frame = dot_vox::Dict::new();
    frame.insert("_t".into(), "1 2 3".into());
    frame.insert("_r".into(), "4".into());
    let data = DotVoxData {
        version: 150,
        index_map: Vec::new(),
        models: vec![Model {
            size: Size { x: 2, y: 2, z: 2 },
            voxels: (0..4)
                .map(|i| Voxel {
                    x: i % 2,
                    y: i / 2,
                    z: 1,
                    i: i + 1,
                })
                .collect(),
        }],
        palette: dot_vox::DEFAULT_PALETTE.to_vec(),
        materials: Vec::new(),
        scenes: vec![
            SceneNode::Transform {
                attributes: Default::default(),
                frames: vec![Frame::new(Default::default())],
                child: 1,
                layer_id: 0,
            },
            SceneNode::Group {
                attributes: Default::default(),
                children: vec![2, 2],
            },
            SceneNode::Transform {
                attributes: Default::default(),
                frames: vec![Frame::new(frame)],
                child: 3,
                layer_id: 0,
            },
            SceneNode::Shape {
                attributes: Default::default(),
                models: vec![ShapeModel {
                    model_id: 0,
                    attributes: Default::default(),
                }],
            },
        ],
        layers: Vec::new(),
    };
    let mut seed = Vec::new();
    data.write_vox(&mut seed).unwrap();
    assert_eq!(
        vox_voxels_from_bytes(&seed),
        Ok(8),
        "the seed file is valid"
    );
    fuzz("vox", seed, |b| {
        let _ = vox_voxels_from_bytes(b);
    });
}

#[test]
fn the_png_heightmap_loader_never_panics() {
    let mut png = Vec::new();
    {
        let mut enc = png::Encoder::new(&mut png, 5, 4);
        enc.set_color(png::ColorType::Grayscale);
        enc.set_depth(png::BitDepth::Eight);
        enc.write_header()
            .unwrap()
            .write_image_data(&[3; 20])
            .unwrap();
    }
    fuzz("png heightmap", png, |b| {
        let _ = heightmap_from_bytes(b);
    });
}

#[test]
fn the_world_config_parser_never_panics() {
    let seed = brickworld::engine::world_config::DEFAULT_WORLD
        .as_bytes()
        .to_vec();
    fuzz("world config", seed, |b| {
        let text = String::from_utf8_lossy(b);
        let _ = WorldConfig::parse("fuzz.toml", &text, std::path::Path::new("."));
    });
}

/// The world store's chunk and chunk-column decoders, on random and mutated
/// payloads (past the checksum, so the mutations reach the decoder) and on
/// random and mutated sealed blobs.
#[test]
fn the_world_store_decoders_never_panic() {
    use brickworld::persist::chunk::{self, ChunkKey, ColumnKey};
    use glam::{IVec2, IVec3};
    let w = brickworld::scene::build_scene(
        &"terrain".parse().unwrap(),
        IVec3::new(64, 64, 64),
        2,
        &indicatif::ProgressBar::hidden(),
    )
    .unwrap();
    let key = ChunkKey(IVec3::ZERO);
    let mut vox = brickworld::sim::voxels::VoxelChannels::default();
    let water = vox.channel("water");
    vox.set(water, IVec3::new(1, 2, 3), &[0.5; 512]);
    let palette = w.store().palette().clone();
    let payload = chunk::chunk_payload(key, w.store(), &vox);
    fuzz("chunk payload", payload, |b| {
        let _ = chunk::decode_chunk_payload(key, b, &palette);
    });
    let blob = chunk::encode_chunk(key, w.store(), &vox);
    fuzz("chunk blob", blob, |b| {
        let _ = chunk::decode_chunk(key, b, &palette);
    });
    let mut ch = brickworld::sim::ChannelStore::default();
    let g = ch.channel("ground");
    ch.set(IVec2::new(1, 1), g, &[3.0; 64]);
    let col = ColumnKey(IVec2::ZERO);
    fuzz("column payload", chunk::column_payload(col, &ch), |b| {
        let _ = chunk::decode_column_payload(col, b);
    });
    let state = brickworld::persist::state::encode(
        7,
        &palette,
        (IVec3::ZERO, IVec3::splat(64)),
        &[("water".into(), vec![("rain".into(), 0.5)])],
        &Default::default(),
    );
    fuzz("state blob", state, |b| {
        let _ = brickworld::persist::state::decode(b);
    });
}
