//! The simulation-state blob: everything besides the chunks that defines a
//! world's future — tick, palette, bounds, script parameters, the drained
//! total, which tiles and bricks sleep, the material registry. Committed
//! with the dirty chunks in one transaction, so a resume sees a state and
//! chunks of the same tick.
//!
//! The payload is the checkpoint payload (format 3, see
//! `engine::checkpoint`) with no bricks, tiles or voxel arrays: one encoder
//! for both, so the two cannot drift apart.
//!
//! Blob: magic `BWST`, `u32` payload version, `u64` tick, `u32` CRC-32 of the
//! rest, LZ4 (size-prepended) payload.

use glam::IVec3;

use crate::engine::checkpoint::{self, SimExtras, WorldRef, WorldState};
use crate::sim::ChannelStore;
use crate::world::{BrickStore, Palette};

const MAGIC: &[u8; 4] = b"BWST";
/// 4: a trailing section with the scripts' health may follow; 5: one with
/// every script's source hash too (3 and 4 are read). A build that reads
/// only up to 4 then says the version, not "section 3 … is unknown".
const PAYLOAD_VERSION: u32 = 5;
/// The largest state a blob may decompress to (a 64k×64k-tile world's sleep
/// lists fit many times over).
const MAX_STATE: usize = 1 << 30;

/// Encode the state of a world at `tick`.
pub fn encode(
    tick: u64,
    palette: &Palette,
    bounds: (IVec3, IVec3),
    params: &[(String, Vec<(String, f64)>)],
    extras: &SimExtras,
) -> Vec<u8> {
    let store = BrickStore::new(palette.clone());
    let channels = ChannelStore::default();
    let extras = SimExtras {
        voxel_channels: Default::default(),
        ..extras.clone()
    };
    let payload = checkpoint::encode(WorldRef {
        tick,
        store: &store,
        bounds,
        channels: &channels,
        params,
        identity: None,
        extras: &extras,
    });
    let packed = lz4_flex::compress_prepend_size(&payload);
    let mut out = Vec::with_capacity(20 + packed.len());
    out.extend_from_slice(MAGIC);
    out.extend_from_slice(&PAYLOAD_VERSION.to_le_bytes());
    out.extend_from_slice(&tick.to_le_bytes());
    out.extend_from_slice(&crc32fast::hash(&packed).to_le_bytes());
    out.extend_from_slice(&packed);
    out
}

/// Decode a state blob: a [`WorldState`] whose store holds only the palette
/// and whose channels are empty (the chunks hold those).
pub fn decode(blob: &[u8]) -> Result<WorldState, String> {
    if blob.len() < 24 || &blob[..4] != MAGIC {
        return Err("the simulation state is not a brickworld state blob".into());
    }
    let version = u32::from_le_bytes(blob[4..8].try_into().expect("4"));
    if !(3..=PAYLOAD_VERSION).contains(&version) {
        return Err(format!(
            "the simulation state has version {version}; this build reads 3 to {PAYLOAD_VERSION}"
        ));
    }
    let tick = u64::from_le_bytes(blob[8..16].try_into().expect("8"));
    let crc = u32::from_le_bytes(blob[16..20].try_into().expect("4"));
    let packed = &blob[20..];
    if crc32fast::hash(packed) != crc {
        return Err("the simulation state's checksum does not match".into());
    }
    let claimed = u32::from_le_bytes(packed[..4].try_into().expect("4")) as usize;
    if claimed > MAX_STATE || claimed > super::chunk::lz4_bound(packed.len()) {
        return Err(format!(
            "the simulation state claims {claimed} bytes from {} packed bytes",
            packed.len()
        ));
    }
    let payload = lz4_flex::decompress_size_prepended(packed)
        .map_err(|e| format!("the simulation state: LZ4: {e}"))?;
    checkpoint::decode(tick, version, &payload).map_err(|e| format!("the simulation state: {e}"))
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::engine::checkpoint::{CameraOverride, ScriptHealth};
    use crate::persist::bytes::fnv1a;

    fn extras() -> SimExtras {
        SimExtras {
            camera: Some(CameraOverride {
                eye: [1.0, 2.0, 3.0],
                target: [0.0; 3],
                fov: 60.0,
            }),
            health: vec![
                ScriptHealth {
                    script: "flaky".into(),
                    source: fnv1a(b"return {}"),
                    failures: 3,
                    suspended: Some("flaky.lua:1: boom".into()),
                },
                ScriptHealth {
                    script: "wobbly".into(),
                    source: 7,
                    failures: 1,
                    suspended: None,
                },
            ],
            ..Default::default()
        }
    }

    fn blob(extras: &SimExtras) -> Vec<u8> {
        let bounds = (IVec3::ZERO, IVec3::splat(64));
        encode(9, &Palette::grey_ramp(), bounds, &[], extras)
    }

    /// A state of a version this build does not read (a newer build's, or a
    /// forged one) is refused naming its version and the range read, and
    /// the versions in that range are read (claims audit: nothing held the
    /// check to its range).
    #[test]
    fn a_state_of_an_unknown_version_is_refused_naming_it() {
        let good = blob(&extras());
        for v in [0u32, 2, PAYLOAD_VERSION + 1, u32::MAX] {
            let mut b = good.clone();
            b[4..8].copy_from_slice(&v.to_le_bytes());
            let err = decode(&b).expect_err("refused");
            assert_eq!(
                err,
                format!(
                    "the simulation state has version {v}; this build reads 3 to {PAYLOAD_VERSION}"
                )
            );
        }
        assert_eq!(decode(&good).map(|s| s.tick), Ok(9));
        // Earlier versions pass the version check (version 3 then refuses
        // this blob's later sections as such).
        for v in 3..PAYLOAD_VERSION {
            let mut b = good.clone();
            b[4..8].copy_from_slice(&v.to_le_bytes());
            let said = decode(&b).map(|s| s.tick);
            assert!(
                said.as_ref().is_ok_and(|t| *t == 9)
                    || said.as_ref().is_err_and(|e| e.contains("section")),
                "version {v}: {said:?}"
            );
        }
    }

    /// Regression (hostile probe): a forged tick near `u64::MAX` wrapped.
    #[test]
    fn a_forged_tick_past_2_pow_53_is_refused() {
        let bounds = (IVec3::ZERO, IVec3::splat(64));
        let e = SimExtras::default();
        for tick in [u64::MAX, crate::engine::checkpoint::MAX_TICK + 1] {
            let b = encode(tick, &Palette::grey_ramp(), bounds, &[], &e);
            let err = decode(&b).expect_err("refused");
            assert!(err.contains("forged or corrupt"), "{err}");
        }
        let max = crate::engine::checkpoint::MAX_TICK;
        let b = encode(max, &Palette::grey_ramp(), bounds, &[], &e);
        assert_eq!(decode(&b).unwrap().tick, max);
    }

    /// The optional sections (camera, scripts' health) round-trip, alone
    /// and together, and a state without them reads as before.
    #[test]
    fn the_camera_and_the_scripts_health_round_trip() {
        let full = extras();
        let only_health = SimExtras {
            camera: None,
            ..full.clone()
        };
        for e in [full, only_health, SimExtras::default()] {
            let st = decode(&blob(&e)).unwrap();
            assert_eq!(st.extras.camera, e.camera);
            assert_eq!(st.extras.health, e.health);
        }
    }

    /// Every script's source round-trips (a resume compares it to wake a
    /// script changed while stopped); one named twice is refused.
    #[test]
    fn the_scripts_sources_round_trip_and_a_name_twice_is_refused() {
        let e = SimExtras {
            sources: vec![("water".into(), 1), ("grass".into(), u64::MAX)],
            ..extras()
        };
        let st = decode(&blob(&e)).unwrap();
        assert_eq!(st.extras.sources, e.sources);
        assert_eq!(st.extras.health, e.health);
        let twice = SimExtras {
            sources: vec![("water".into(), 1), ("water".into(), 2)],
            ..Default::default()
        };
        let err = decode(&blob(&twice)).unwrap_err();
        assert!(err.contains("water's source is stored twice"), "{err}");
    }

    /// Regression (fuzzing): a stored state with a NaN or infinite drained
    /// total, an eye at 1e300, or a material named with a newline or a
    /// path loaded with exit 0. Each is refused, naming what is wrong.
    #[test]
    fn a_state_with_impossible_values_is_refused() {
        use crate::world::MaterialKind;
        let named = |name: &str| SimExtras {
            materials: vec![(5, name.to_string(), MaterialKind::Solid, 1.0)],
            ..Default::default()
        };
        let far = SimExtras {
            camera: Some(CameraOverride {
                eye: [1e300, 0.0, 0.0],
                target: [0.0; 3],
                fov: 60.0,
            }),
            ..Default::default()
        };
        let mut cases = vec![
            (named("sand\nrock"), "which no material may be"),
            (named("../etc"), "which no material may be"),
            (far, "within ±1e9 voxels"),
        ];
        for d in [f64::NAN, f64::INFINITY, f64::NEG_INFINITY] {
            let e = SimExtras {
                drained: d,
                ..Default::default()
            };
            cases.push((e, "not a finite number"));
        }
        for (e, needle) in cases {
            let err = decode(&blob(&e)).expect_err(needle);
            assert!(err.contains(needle), "{err}");
            assert!(!err.contains('\n'), "{err}");
        }
        // What a world writes still loads.
        assert!(decode(&blob(&named("sand_2"))).is_ok());
    }

    /// A section repeated or unknown, or a bad suspension flag, is refused
    /// with a message, never read as something else.
    #[test]
    fn a_repeated_or_unknown_section_is_refused() {
        let payload = |e: &SimExtras| {
            let b = blob(e);
            lz4_flex::decompress_size_prepended(&b[20..]).unwrap()
        };
        let base = payload(&SimExtras::default());
        let with = payload(&extras());
        let health = with.len() - (base.len() + 4 + 56);
        let tail = with[with.len() - health..].to_vec();
        for (bytes, needle) in [
            ([with.clone(), tail.clone()].concat(), "unknown or repeated"),
            (
                [base.clone(), 9u32.to_le_bytes().to_vec()].concat(),
                "section 9",
            ),
        ] {
            let e = checkpoint::decode(9, PAYLOAD_VERSION, &bytes).unwrap_err();
            assert!(e.contains(needle), "{e}");
        }
        // The first script's flag byte (after the tag, count, name, source
        // and failures) set to 2.
        let mut bad = with.clone();
        let flag = with.len() - health + 4 + 4 + (4 + 5) + 8 + 4;
        assert_eq!(bad[flag], 1);
        bad[flag] = 2;
        let e = checkpoint::decode(9, PAYLOAD_VERSION, &bad).unwrap_err();
        assert!(e.contains("flag is 2"), "{e}");
        // A version-3 state has no health section.
        let e = checkpoint::decode(9, 3, &with).unwrap_err();
        assert!(e.contains("section 2"), "{e}");
    }

    /// Health no run can leave (review: u32::MAX failures overflowed the
    /// next failure's count; "suspended after 0 failed steps"; a long
    /// streak not suspended; one script twice) is refused.
    #[test]
    fn impossible_health_is_refused() {
        let with = |h: Vec<ScriptHealth>| SimExtras {
            health: h,
            ..Default::default()
        };
        let one = |failures: u32, suspended: bool, name: &str| ScriptHealth {
            script: name.into(),
            source: 1,
            failures,
            suspended: suspended.then(|| "why".to_string()),
        };
        for h in [
            vec![one(0, true, "a")],
            vec![one(0, false, "a")],
            vec![one(u32::MAX, true, "a")],
            vec![one(3, false, "a")],
            vec![one(1, false, "a"), one(2, false, "a")],
        ] {
            let e = decode(&blob(&with(h.clone()))).unwrap_err();
            assert!(e.contains("is not one a run can leave"), "{h:?}: {e}");
        }
        for h in [
            vec![one(2, false, "a"), one(3, true, "b")],
            vec![one(1, true, "a")],
        ] {
            assert_eq!(decode(&blob(&with(h.clone()))).unwrap().extras.health, h);
        }
    }
}
