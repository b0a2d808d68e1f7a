//! Checkpoints: a world (bricks, channels, tick, parameters) survives a round
//! trip with the same hash; only the last two are kept; a corrupt or
//! truncated newest checkpoint is reported and the previous one is used;
//! a write that fails leaves the previous checkpoints untouched.

#[path = "common/scratch.rs"]
mod scratch;
use scratch::Scratch;

use brickworld::engine::checkpoint::{self, CheckpointError, WorldState};
use brickworld::scene::{SceneSpec, build_scene};
use brickworld::sim::ChannelStore;
use glam::{IVec2, IVec3};
use indicatif::ProgressBar;

fn state(tick: u64, seed: u64) -> WorldState {
    let w = build_scene(
        &SceneSpec::Terrain { caves: false },
        IVec3::new(32, 24, 32),
        seed,
        &ProgressBar::hidden(),
    )
    .unwrap();
    let mut channels = ChannelStore::default();
    let water = channels.channel("water");
    let mut d = [0.0; 64];
    d[7] = 1.25 + seed as f64;
    channels.set(IVec2::new(1, 2), water, &d);
    WorldState {
        tick,
        store: w.store().clone(),
        bounds: w.bounds(),
        channels,
        params: vec![("water".into(), vec![("rain".into(), 0.5)])],
        identity: None,
        extras: Default::default(),
    }
}

/// A path `ckpt` (not yet made) in a scratch folder of its own.
fn dir(name: &str) -> Scratch {
    Scratch::file(&format!("ckpt-{name}"), "ckpt")
}

#[test]
fn a_world_round_trips_with_the_same_hash() {
    let d = dir("roundtrip");
    let s = state(42, 1);
    let hash = checkpoint::world_hash(&s.store, &s.channels);
    let (path, written) = checkpoint::write(&d, &s).unwrap();
    assert_eq!(written, hash);
    let back = checkpoint::read(&path).unwrap();
    assert_eq!(back.tick, 42);
    assert_eq!(checkpoint::world_hash(&back.store, &back.channels), hash);
    assert_eq!(back.bounds, s.bounds);
    assert_eq!(back.params, s.params);
    assert_eq!(back.store.palette(), s.store.palette());
}

#[test]
fn only_the_last_two_are_kept_and_a_corrupt_newest_falls_back() {
    let d = dir("keep");
    for t in 1..=4 {
        checkpoint::write(&d, &state(t * 10, t)).unwrap();
    }
    let files = checkpoint::list(&d).unwrap();
    assert_eq!(files.len(), 2);
    // Damage the newest one's payload.
    let mut bytes = std::fs::read(&files[0]).unwrap();
    let n = bytes.len();
    bytes[n - 5] ^= 0x5a;
    std::fs::write(&files[0], &bytes).unwrap();
    let checkpoint::Latest { found, skipped } = checkpoint::latest(&d).unwrap();
    let (_, s) = found.expect("the previous checkpoint loads");
    assert_eq!(s.tick, 30);
    assert_eq!(skipped.len(), 1);
    assert!(
        matches!(skipped[0], CheckpointError::Corrupt { .. }),
        "{}",
        skipped[0]
    );
}

#[test]
fn truncated_or_foreign_files_are_reported_not_loaded() {
    let d = dir("trunc");
    let (path, _) = checkpoint::write(&d, &state(5, 2)).unwrap();
    let bytes = std::fs::read(&path).unwrap();
    for cut in [0, 10, 39, 40, bytes.len() / 2, bytes.len() - 1] {
        std::fs::write(&path, &bytes[..cut]).unwrap();
        let e = checkpoint::read(&path).unwrap_err();
        assert!(
            matches!(e, CheckpointError::Corrupt { .. }),
            "cut at {cut}: {e}"
        );
    }
    std::fs::write(
        &path,
        b"PK\x03\x04 definitely a zip file, not a checkpoint, padded to forty bytes",
    )
    .unwrap();
    assert!(
        checkpoint::read(&path)
            .unwrap_err()
            .to_string()
            .contains("is not a brickworld checkpoint or backup")
    );
    let checkpoint::Latest { found, skipped } = checkpoint::latest(&d).unwrap();
    assert!(found.is_none() && skipped.len() == 1);
}

#[test]
fn a_failed_write_leaves_the_previous_checkpoints_untouched() {
    let d = dir("fail");
    checkpoint::write(&d, &state(1, 3)).unwrap();
    // A directory squatting on the final name makes the rename fail, like
    // a full disk would, after the temp file was written. (Its twin
    // `*.corrupt` keeps retention from setting the squatter aside.)
    for name in [
        "ckpt-0000000000000002.bwc",
        "ckpt-0000000000000002.bwc.corrupt",
    ] {
        std::fs::create_dir_all(d.join(name).join("x")).unwrap();
    }
    let e = checkpoint::write(&d, &state(2, 4)).unwrap_err();
    assert!(matches!(e, CheckpointError::Io { .. }), "{e}");
    let found = checkpoint::latest(&d).unwrap().found;
    assert_eq!(found.unwrap().1.tick, 1);
    // The temp file went with the failure.
    let temps = std::fs::read_dir(&d)
        .unwrap()
        .flatten()
        .filter(|e| e.file_name().to_string_lossy().ends_with(".tmp"))
        .count();
    assert_eq!(temps, 0);
}

/// Checkpoints of format versions 1 and 2 (no identity, fewer sections)
/// still decode to the same world: their payloads are this version's less
/// the sections added since (12 bytes each when those are empty).
#[test]
fn version_1_and_2_payloads_still_load() {
    let d = dir("versions");
    let s = state(9, 1);
    let (path, hash) = checkpoint::write(&d, &s).unwrap();
    let bytes = std::fs::read(&path).unwrap();
    let id_len = u32::from_le_bytes(bytes[40..44].try_into().unwrap()) as usize;
    let raw = lz4_flex::decompress_size_prepended(&bytes[48 + id_len..]).unwrap();
    for (version, cut) in [(1u32, 24usize), (2, 12)] {
        let old = checkpoint::decode(9, version, &raw[..raw.len() - cut])
            .unwrap_or_else(|e| panic!("version {version}: {e}"));
        assert_eq!(checkpoint::world_hash(&old.store, &old.channels), hash);
        assert_eq!(old.params, s.params);
        assert!(old.extras.voxel_sleep.is_none());
    }
    // The current version refuses a payload cut short.
    assert!(checkpoint::decode(9, 3, &raw[..raw.len() - 12]).is_err());
}

/// Regression (hostile probe): a backup written into a user's folder reused
/// `.NAME.tmp` and deleted every `.ckpt-*.tmp` there.
#[test]
fn a_backup_leaves_the_files_beside_it_alone() {
    let d = dir("beside");
    std::fs::create_dir_all(&d).unwrap();
    for decoy in [".keep.bwc.tmp", ".ckpt-9.tmp"] {
        std::fs::write(d.join(decoy), "precious").unwrap();
    }
    let s = state(5, 1);
    checkpoint::write_at(
        &d.join("keep.bwc"),
        checkpoint::WorldRef {
            tick: s.tick,
            store: &s.store,
            bounds: s.bounds,
            channels: &s.channels,
            params: &s.params,
            identity: None,
            extras: &s.extras,
        },
    )
    .unwrap();
    assert_eq!(checkpoint::read(&d.join("keep.bwc")).unwrap().tick, 5);
    for decoy in [".keep.bwc.tmp", ".ckpt-9.tmp"] {
        assert_eq!(
            std::fs::read_to_string(d.join(decoy)).unwrap(),
            "precious",
            "{decoy}"
        );
    }
    let n = std::fs::read_dir(&d).unwrap().count();
    assert_eq!(n, 3, "the backup and the two decoys, no temp left");
}

/// Regression (hostile probe): when the world hash came to take channels by
/// name, the format number stayed, and every backup and checkpoint written
/// before was refused as corrupt ("world hash … differs from the
/// recorded …"); a legacy state directory then restarted from tick 0. Files
/// of versions 1 to 4 are checked against the hash they were written with,
/// and newer ones against the new hash only.
#[test]
fn a_version_4_file_with_the_hash_by_id_still_loads() {
    let d = dir("v4hash");
    let mut s = state(11, 2);
    // A second channel: the hash by id mixes ids, the hash by name names,
    // so the two differ.
    let mut d2 = [0.0; 64];
    d2[3] = -0.5;
    let a = s.channels.channel("a_second");
    s.channels.set(IVec2::new(0, 0), a, &d2);
    let by_id = checkpoint::world_hash_by_id(&s.store, &s.channels);
    assert_ne!(by_id, checkpoint::world_hash(&s.store, &s.channels));
    let (path, _) = checkpoint::write(&d, &s).unwrap();
    let bytes = std::fs::read(&path).unwrap();
    let with_header = |version: u32, hash: u64| {
        let mut b = bytes.clone();
        b[4..8].copy_from_slice(&version.to_le_bytes());
        b[16..24].copy_from_slice(&hash.to_le_bytes());
        let crc = crc32fast::hash(&b[..36]);
        b[36..40].copy_from_slice(&crc.to_le_bytes());
        b
    };
    let (back, _) = checkpoint::parse(&with_header(4, by_id), true).unwrap();
    let back = back.unwrap();
    assert_eq!(back.tick, 11);
    assert_eq!(
        checkpoint::world_hash(&back.store, &back.channels),
        checkpoint::world_hash(&s.store, &s.channels)
    );
    // Builds of one session wrote version 4 with the hash by name.
    let by_name = checkpoint::world_hash_v5(&s.store, &s.channels);
    assert!(checkpoint::parse(&with_header(4, by_name), true).is_ok());
    let err = checkpoint::parse(&with_header(5, by_id), true).unwrap_err();
    assert!(err.contains("differs from the recorded"), "{err}");
    // Version 5 recorded the hash by name mixed by FNV-1a; version 6 that
    // of XXH3 (regression, modder probe: FNV-1a over whole words let two
    // worlds collide). Each is checked against its own only.
    let xxh3 = checkpoint::world_hash(&s.store, &s.channels);
    assert_ne!(xxh3, by_name);
    assert!(checkpoint::parse(&with_header(5, by_name), true).is_ok());
    assert!(checkpoint::parse(&with_header(6, xxh3), true).is_ok());
    for (version, hash) in [(5, xxh3), (6, by_name)] {
        let err = checkpoint::parse(&with_header(version, hash), true).unwrap_err();
        assert!(err.contains("differs from the recorded"), "{err}");
    }
    assert_eq!(&bytes[4..8], &6u32.to_le_bytes(), "files are written as 6");
}

/// Regression (modder probe): the world hash mixed whole 64-bit words by
/// FNV-1a, whose multiply carries a bit only upwards, so a change in a
/// word's top byte (a voxel at x ≡ 7 (mod 8)) reached only the hash's top
/// byte and worlds collided one time in 256; a channel value's sign bit
/// reached only bit 63, so two sign flips cancelled. Under the old mixing
/// the probe's 144 worlds differ only in the hash's top byte (so some must
/// collide); under the world hash they all hash apart.
#[test]
fn worlds_that_fnv_over_whole_words_confused_hash_apart() {
    let world = |a: u8, b: u8| {
        let mut s = state(1, 0);
        s.store.set_voxel(IVec3::new(7, 20, 7), a);
        s.store.set_voxel(IVec3::new(15, 20, 7), b);
        s
    };
    let low = |h: u64| h & ((1 << 56) - 1);
    let (mut old_low, mut new_low, mut new) = (Vec::new(), Vec::new(), Vec::new());
    for a in 1..=12 {
        for b in 1..=12 {
            let w = world(a, b);
            old_low.push(low(checkpoint::world_hash_v5(&w.store, &w.channels)));
            let h = checkpoint::world_hash(&w.store, &w.channels);
            new_low.push(low(h));
            new.push(h);
        }
    }
    assert!(
        old_low.iter().all(|&h| h == old_low[0]),
        "the probe's weakness"
    );
    new.sort_unstable();
    new.dedup();
    assert_eq!(new.len(), 144, "every world hashes apart");
    new_low.sort_unstable();
    new_low.dedup();
    assert_eq!(new_low.len(), 144, "and not only in the top byte");
    let signs = |s: f64| {
        let mut c = ChannelStore::default();
        let foo = c.channel("foo");
        c.set(IVec2::new(0, 0), foo, &[s; 64]);
        c.set(IVec2::new(1, 0), foo, &[s; 64]);
        c
    };
    let (p, n) = (signs(1.0), signs(-1.0));
    assert_eq!(
        p.hash_with(brickworld::persist::bytes::Mixing::Words),
        n.hash_with(brickworld::persist::bytes::Mixing::Words)
    );
    assert_ne!(p.hash(), n.hash());
}
