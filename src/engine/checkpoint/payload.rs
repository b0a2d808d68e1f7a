//! The checkpoint payload: the world's state (palette, bounds, bricks,
//! channels, parameters, sleep state and the optional trailing sections)
//! as bytes, and back. Decoding never panics and never allocates more than
//! the bytes justify.

use glam::{IVec2, IVec3};

use super::{CameraOverride, ScriptHealth, SimExtras, WorldRef, WorldState};
use crate::persist::bytes::{Reader, Writer};
use crate::sim::ChannelStore;
use crate::sim::tile::TILE_CELLS;
use crate::world::{BRICK_VOXELS, BrickContent, BrickStore, Palette};

pub(crate) fn encode(state: WorldRef<'_>) -> Vec<u8> {
    let mut w = Writer::default();
    for m in 0..=255u8 {
        w.0.extend_from_slice(&state.store.palette().rgb(m));
    }
    for v in [state.bounds.0, state.bounds.1] {
        w.i32(v.x);
        w.i32(v.y);
        w.i32(v.z);
    }
    let mut keys: Vec<IVec3> = state.store.iter().map(|(b, _)| b).collect();
    keys.sort_by_key(|k| (k.z, k.y, k.x));
    w.u32(keys.len() as u32);
    let mut dense = [0u8; BRICK_VOXELS];
    for k in keys {
        w.i32(k.x);
        w.i32(k.y);
        w.i32(k.z);
        state.store.read_dense(k, &mut dense);
        w.0.extend_from_slice(&dense);
    }
    let names: Vec<(crate::sim::ChannelId, String)> = state
        .channels
        .channels()
        .map(|(id, n)| (id, n.to_string()))
        .collect();
    w.u32(names.len() as u32);
    for (_, n) in &names {
        w.str(n);
    }
    let tiles = state.channels.tiles();
    w.u32(tiles.len() as u32);
    for t in tiles {
        w.i32(t.x);
        w.i32(t.y);
        let present: Vec<&(crate::sim::ChannelId, String)> = names
            .iter()
            .filter(|(id, _)| state.channels.get(t, *id).is_some())
            .collect();
        w.u32(present.len() as u32);
        for (id, _) in present {
            w.u32(id.index() as u32);
            for v in state.channels.get(t, *id).expect("present").iter() {
                w.f64(*v);
            }
        }
    }
    w.u32(state.params.len() as u32);
    for (script, ps) in state.params {
        w.str(script);
        w.u32(ps.len() as u32);
        for (n, v) in ps {
            w.str(n);
            w.f64(*v);
        }
    }
    // Version 2: the rest of the simulation state.
    w.f64(state.extras.drained);
    match &state.extras.sleep {
        None => w.u32(0),
        Some(sl) => {
            w.u32(1);
            w.u32(sl.active.len() as u32);
            for t in &sl.active {
                w.i32(t.x);
                w.i32(t.y);
            }
            w.u32(sl.quiet.len() as u32);
            for (t, q) in &sl.quiet {
                w.i32(t.x);
                w.i32(t.y);
                w.0.push(*q);
            }
        }
    }
    // Version 3: the voxel scripts' channels.
    let vc = &state.extras.voxel_channels;
    w.u32(vc.names().len() as u32);
    for (id, name) in vc.names().iter().enumerate() {
        w.str(name);
        let bricks = vc.sorted_bricks(id);
        w.u32(bricks.len() as u32);
        for b in bricks {
            w.i32(b.x);
            w.i32(b.y);
            w.i32(b.z);
            for v in vc.get(id, b).expect("listed").iter() {
                w.0.extend_from_slice(&v.to_le_bytes());
            }
        }
    }
    w.u32(state.extras.materials.len() as u32);
    for (id, name, kind, density) in &state.extras.materials {
        w.0.push(*id);
        w.str(name);
        w.0.push(*kind as u8);
        w.0.extend_from_slice(&density.to_le_bytes());
    }
    match &state.extras.voxel_sleep {
        None => w.u32(0),
        Some((active, quiet)) => {
            w.u32(1);
            w.u32(active.len() as u32);
            for b in active {
                w.i32(b.x);
                w.i32(b.y);
                w.i32(b.z);
            }
            w.u32(quiet.len() as u32);
            for (b, q) in quiet {
                w.i32(b.x);
                w.i32(b.y);
                w.i32(b.z);
                w.0.push(*q);
            }
        }
    }
    // Optional trailing sections, each behind its tag.
    if let Some(c) = &state.extras.camera {
        w.u32(SECTION_CAMERA);
        for v in c.eye.iter().chain(&c.target).chain([&c.fov]) {
            w.f64(*v);
        }
    }
    if !state.extras.health.is_empty() {
        w.u32(SECTION_HEALTH);
        w.u32(state.extras.health.len() as u32);
        for h in &state.extras.health {
            w.str(&h.script);
            w.u64(h.source);
            w.u32(h.failures);
            match &h.suspended {
                None => w.u8(0),
                Some(why) => {
                    w.u8(1);
                    w.str(why);
                }
            }
        }
    }
    if !state.extras.sources.is_empty() {
        w.u32(SECTION_SOURCES);
        w.u32(state.extras.sources.len() as u32);
        for (script, source) in &state.extras.sources {
            w.str(script);
            w.u64(*source);
        }
    }
    w.0
}

/// Tags of the optional sections that may follow a state.
const SECTION_CAMERA: u32 = 1;
const SECTION_HEALTH: u32 = 2;
const SECTION_SOURCES: u32 = 3;

/// Highest tick a stored state may claim: 2^53, where a tick stops being
/// exact as the `f64` of simulated time (285 000 years at 1 000 ticks a
/// second). A larger one is forged or corrupt. The engine steps no further
/// than this, so it never commits a tick it would then refuse (regression,
/// fuzzing: a backup at 2^53 imported, stepped to 2^53 + 2, committed, and
/// could not be resumed).
pub const MAX_TICK: u64 = 1 << 53;

/// Decode a decompressed payload of format `version` (1 to 6; 5 and 6
/// changed only the header's hash). Never
/// panics, whatever the bytes: every count is checked against what is left,
/// and a tick past [`MAX_TICK`] is refused.
pub fn decode(tick: u64, version: u32, payload: &[u8]) -> Result<WorldState, String> {
    if tick > MAX_TICK {
        // A forged tick near u64::MAX wrapped on the next step (regression).
        return Err(format!(
            "tick {tick} is past 2^53, which no world reaches: the file is forged or corrupt"
        ));
    }
    let mut r = Reader::new(payload);
    let mut colors = [[0u8; 3]; 256];
    for c in colors.iter_mut() {
        c.copy_from_slice(r.take(3)?);
    }
    let mut store = BrickStore::new(Palette::new(colors));
    let lo = IVec3::new(r.i32()?, r.i32()?, r.i32()?);
    let hi = IVec3::new(r.i32()?, r.i32()?, r.i32()?);
    let bricks = r.count(1 << 28, "brick")?;
    for _ in 0..bricks {
        let b = IVec3::new(r.i32()?, r.i32()?, r.i32()?);
        let dense: [u8; BRICK_VOXELS] = r.take(BRICK_VOXELS)?.try_into().expect("512 bytes");
        let content = BrickContent::from_dense(&dense, store.palette());
        store.set_brick(b, content);
    }
    store.take_modified();
    let mut channels = ChannelStore::default();
    let n = r.count(crate::sim::MAX_CHANNELS, "channel")?;
    let ids: Vec<crate::sim::ChannelId> = (0..n)
        .map(|_| r.str().map(|s| channels.channel(&s)))
        .collect::<Result<_, _>>()?;
    let tiles = r.count(1 << 28, "tile")?;
    for _ in 0..tiles {
        let t = IVec2::new(r.i32()?, r.i32()?);
        let k = r.count(n, "channel in a tile")?;
        for _ in 0..k {
            let c = r.u32()? as usize;
            let id = *ids
                .get(c)
                .ok_or_else(|| format!("channel index {c} out of range"))?;
            let mut d = [0.0; TILE_CELLS];
            for v in d.iter_mut() {
                *v = r.f64()?;
            }
            channels.set(t, id, &d);
        }
    }
    let scripts = r.count(1024, "script")?;
    let mut params = Vec::new();
    for _ in 0..scripts {
        let name = r.str()?;
        let k = r.count(1024, "parameter")?;
        let mut ps = Vec::new();
        for _ in 0..k {
            ps.push((r.str()?, r.f64()?));
        }
        params.push((name, ps));
    }
    let mut extras = SimExtras::default();
    if version >= 2 {
        extras.drained = r.f64()?;
        // Regression (fuzzing): NaN and ±inf were taken, and every total
        // after them was nonsense.
        if !extras.drained.is_finite() {
            return Err(format!(
                "the drained water total {} is not a finite number",
                extras.drained
            ));
        }
        if r.u32()? == 1 {
            let left = |r: &Reader, per: usize| (r.data.len() - r.at) / per;
            let n = r.count(left(&r, 8), "awake tile")?;
            let mut active = Vec::with_capacity(n);
            for _ in 0..n {
                active.push(IVec2::new(r.i32()?, r.i32()?));
            }
            let n = r.count(left(&r, 9), "quiet tile")?;
            let mut quiet = Vec::with_capacity(n);
            for _ in 0..n {
                quiet.push((IVec2::new(r.i32()?, r.i32()?), r.take(1)?[0]));
            }
            extras.sleep = Some(crate::sim::step::SleepState { active, quiet });
        }
    }
    if version >= 3 {
        let n = r.count(crate::sim::MAX_CHANNELS, "voxel channel")?;
        for _ in 0..n {
            let name = r.str()?;
            let id = extras.voxel_channels.channel(&name);
            let left = (r.data.len() - r.at) / (12 + 2048);
            let k = r.count(left, "voxel channel brick")?;
            for _ in 0..k {
                let b = IVec3::new(r.i32()?, r.i32()?, r.i32()?);
                let raw = r.take(2048)?;
                let v: [f32; 512] = std::array::from_fn(|i| {
                    f32::from_le_bytes(raw[i * 4..i * 4 + 4].try_into().expect("4"))
                });
                extras.voxel_channels.set(id, b, &v);
            }
        }
        let n = r.count(256, "material")?;
        for _ in 0..n {
            let id = r.take(1)?[0];
            let name = r.str()?;
            let kind = match r.take(1)?[0] {
                0 => crate::world::MaterialKind::Solid,
                1 => crate::world::MaterialKind::Liquid,
                2 => crate::world::MaterialKind::Granular,
                3 => crate::world::MaterialKind::Gas,
                k => return Err(format!("material kind {k} is unknown")),
            };
            let density = f32::from_le_bytes(r.take(4)?.try_into().expect("4"));
            // Regression (fuzzing): names holding a newline or a path were
            // taken, then dropped without a word by the registry.
            if id == 0 || !crate::world::MaterialRegistry::valid_name(&name) {
                return Err(format!(
                    "material {id} is named '{}', which no material may be",
                    crate::text::escape_controls(&name, false)
                ));
            }
            if !(density.is_finite() && density >= 0.0) {
                return Err(format!("material '{name}' has density {density}"));
            }
            extras.materials.push((id, name, kind, density));
        }
        if r.u32()? == 1 {
            let left = |r: &Reader, per: usize| (r.data.len() - r.at) / per;
            let n = r.count(left(&r, 12), "awake brick")?;
            let mut active = Vec::with_capacity(n);
            for _ in 0..n {
                active.push(IVec3::new(r.i32()?, r.i32()?, r.i32()?));
            }
            let n = r.count(left(&r, 13), "quiet brick")?;
            let mut quiet = Vec::with_capacity(n);
            for _ in 0..n {
                quiet.push((IVec3::new(r.i32()?, r.i32()?, r.i32()?), r.take(1)?[0]));
            }
            extras.voxel_sleep = Some((active, quiet));
        }
        let (mut camera, mut health, mut sources) = (false, false, false);
        while r.at < payload.len() {
            match r.u32()? {
                SECTION_CAMERA if !camera => {
                    camera = true;
                    extras.camera = Some(read_camera(&mut r)?)
                }
                SECTION_HEALTH if !health && version >= 4 => {
                    health = true;
                    extras.health = read_health(&mut r)?
                }
                SECTION_SOURCES if !sources && version >= 4 => {
                    sources = true;
                    extras.sources = read_sources(&mut r)?
                }
                tag => {
                    return Err(format!(
                        "section {tag} after the state is unknown or repeated"
                    ));
                }
            }
        }
    }
    if r.at != payload.len() {
        return Err(format!(
            "{} unexpected bytes after the state",
            payload.len() - r.at
        ));
    }
    Ok(WorldState {
        tick,
        store,
        bounds: (lo, hi),
        channels,
        params,
        identity: None,
        extras,
    })
}

fn read_camera(r: &mut Reader) -> Result<CameraOverride, String> {
    let mut v = [0f64; 7];
    for x in v.iter_mut() {
        *x = r.f64()?;
    }
    // Within ±1e9 voxels, as `--eye` and a config's camera (regression,
    // fuzzing: an eye at 1e300 was taken).
    if v[..6].iter().any(|x| x.is_nan() || x.abs() > 1e9) || !(v[6] > 0.0 && v[6] < 180.0) {
        return Err(
            "the stored camera is not within ±1e9 voxels or its field of view is outside (0, 180)"
                .into(),
        );
    }
    Ok(CameraOverride {
        eye: [v[0], v[1], v[2]],
        target: [v[3], v[4], v[5]],
        fov: v[6],
    })
}

/// The most failures in a row a stored health may claim (a script is
/// suspended after a few; far more is a damaged or forged state).
const MAX_STORED_FAILURES: u32 = 1 << 20;

/// The scripts' sources at the commit: each script once.
fn read_sources(r: &mut Reader) -> Result<Vec<(String, u64)>, String> {
    let n = r.count(1024, "script source")?;
    let mut sources: Vec<(String, u64)> = Vec::with_capacity(n);
    for _ in 0..n {
        let script = r.str()?;
        let source = r.u64()?;
        if sources.iter().any(|(s, _)| *s == script) {
            return Err(format!("script {script}'s source is stored twice"));
        }
        sources.push((script, source));
    }
    Ok(sources)
}

fn read_health(r: &mut Reader) -> Result<Vec<ScriptHealth>, String> {
    let n = r.count(1024, "script health")?;
    let mut health: Vec<ScriptHealth> = Vec::with_capacity(n);
    for _ in 0..n {
        let script = r.str()?;
        let source = r.u64()?;
        let failures = r.u32()?;
        let suspended = match r.u8()? {
            0 => None,
            1 => Some(r.str()?),
            f => {
                return Err(format!(
                    "script {script}'s suspension flag is {f}, not 0 or 1"
                ));
            }
        };
        // Only failing or suspended scripts are stored, once each; a
        // streak long enough to suspend is stored suspended.
        let limit = crate::sim::SUSPEND_AFTER;
        if failures == 0
            || failures > MAX_STORED_FAILURES
            || (suspended.is_none() && failures >= limit)
            || health.iter().any(|h| h.script == script)
        {
            return Err(format!(
                "script {script}'s stored health ({failures} failures in a row, {}) is not one a run can leave",
                if suspended.is_some() {
                    "suspended"
                } else {
                    "not suspended"
                }
            ));
        }
        health.push(ScriptHealth {
            script,
            source,
            failures,
            suspended,
        });
    }
    Ok(health)
}
