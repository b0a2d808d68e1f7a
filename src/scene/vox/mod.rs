//! The `vox:FILE.vox` scene: MagicaVoxel files through `dot_vox`, with every
//! model of the scene graph placed.
//!
//! **Placement.** A shape's model of size `s` has its voxel `v` centred at
//! `c = v + 0.5 − floor(s / 2)`; transforms apply `R·c + t` from the shape up
//! to the root (MagicaVoxel's convention). MagicaVoxel is Z-up; the world is
//! Y-up, so a transformed centre `(x, y, z)` lands in voxel
//! `floor((x, z, −y))` — a rotation, so models are not mirrored.
//! Files without a scene graph place each model at the origin.
//!
//! **Colours.** Voxel colour index `i` (0-based, as `dot_vox` reports it)
//! becomes material `i + 1`, coloured by the file's palette entry `i`,
//! except materials 252 to 254, which the simulations keep for water, snow
//! and sediment: a model's voxels of those take the lowest ids it does not
//! use, with their colours (a model of more than 251 colours cannot run
//! simulations).

mod layout;

use std::path::Path;

use glam::{DVec3, IVec3};

use super::SceneError;
use crate::world::{
    BRICK_EDGE, BRICK_VOXELS, BrickContent, BrickStore, Palette, brick_of, voxel_index,
};

/// Largest accepted `.vox` file, bytes.
pub const MAX_FILE_BYTES: u64 = 256 << 20;
/// Deepest scene graph followed.
const MAX_DEPTH: u32 = 64;
/// Most voxels a file may place (instances × model voxels), counted before
/// anything is expanded: 64 M voxels is about 1 GiB while building.
pub const MAX_PLACED_VOXELS: u64 = 64 << 20;

/// A signed permutation matrix plus translation.
#[derive(Clone, Copy, Debug)]
struct Xform {
    r: [[i32; 3]; 3],
    t: [i32; 3],
}

impl Xform {
    const IDENTITY: Xform = Xform {
        r: [[1, 0, 0], [0, 1, 0], [0, 0, 1]],
        t: [0; 3],
    };

    fn then(&self, child: &Xform) -> Xform {
        let mut r = [[0; 3]; 3];
        let mut t = self.t;
        for i in 0..3 {
            for j in 0..3 {
                r[i][j] = (0..3).map(|k| self.r[i][k] * child.r[k][j]).sum();
            }
            // Saturating: a deep chain of translations lands past ±2^30
            // and is refused there, never wrapped back into range.
            let moved = (0..3).fold(0i32, |acc, k| {
                acc.saturating_add(self.r[i][k].saturating_mul(child.t[k]))
            });
            t[i] = t[i].saturating_add(moved);
        }
        Xform { r, t }
    }

    fn apply(&self, p: DVec3) -> DVec3 {
        let p = [p.x, p.y, p.z];
        let v: [f64; 3] = std::array::from_fn(|i| {
            (0..3).map(|k| self.r[i][k] as f64 * p[k]).sum::<f64>() + self.t[i] as f64
        });
        DVec3::from(v)
    }
}

/// Parse MagicaVoxel's `_r` rotation byte without panicking on bad input.
fn parse_rotation(s: &str) -> Result<[[i32; 3]; 3], String> {
    let b: u8 = s
        .trim()
        .parse()
        .map_err(|_| format!("rotation '{s}' is not a byte"))?;
    let i1 = (b & 3) as usize;
    let i2 = ((b >> 2) & 3) as usize;
    if i1 == 3 || i2 == 3 || i1 == i2 {
        return Err(format!("rotation byte {b} is not a signed permutation"));
    }
    let i3 = 3 - i1 - i2;
    let sign = |bit: u8| if b & (1 << bit) != 0 { -1 } else { 1 };
    let mut r = [[0; 3]; 3];
    r[0][i1] = sign(4);
    r[1][i2] = sign(5);
    r[2][i3] = sign(6);
    Ok(r)
}

fn parse_translation(s: &str) -> Result<[i32; 3], String> {
    let v: Vec<i32> = s
        .split_whitespace()
        .map(|p| {
            p.parse::<i32>()
                .map_err(|_| format!("translation '{s}' is not three integers"))
        })
        .collect::<Result<_, _>>()?;
    // `unsigned_abs`: `i32::MIN.abs()` wraps to itself in a release build
    // (regression, code review: a translation of -2^31 passed).
    if v.len() != 3 || v.iter().any(|c| c.unsigned_abs() > 1 << 20) {
        return Err(format!(
            "translation '{s}' is not three integers within ±2^20"
        ));
    }
    Ok([v[0], v[1], v[2]])
}

/// The voxels of a file, each as (world voxel, material), plus the palette.
pub fn voxels(data: &dot_vox::DotVoxData) -> Result<(Vec<(IVec3, u8)>, Palette), String> {
    let mut out = Vec::new();
    let mut placed: Vec<(u32, Xform)> = Vec::new();
    if data.scenes.is_empty() {
        placed.extend((0..data.models.len() as u32).map(|m| (m, Xform::IDENTITY)));
    } else {
        // Count first (memoised per node, so a graph that shares nodes is
        // counted in time linear in its size), then expand.
        let mut memo = vec![None; data.scenes.len()];
        let (n, visits) = count(data, 0, 0, &mut memo)?;
        if n > MAX_PLACED_VOXELS {
            return Err(format!(
                "the scene graph places {n} voxels (about {} while building); the limit is {MAX_PLACED_VOXELS}",
                super::budget::human(n.saturating_mul(16))
            ));
        }
        // The expansion's own work: a graph can place nothing (an empty or
        // missing model) along 2^60 paths (regression: a hang or an
        // out-of-memory abort from a 2 KB file).
        if visits > MAX_NODE_VISITS {
            return Err(format!(
                "the scene graph expands to {visits} node visits; the limit is {MAX_NODE_VISITS}"
            ));
        }
        walk(data, 0, Xform::IDENTITY, 0, &mut placed)?;
    }
    for (model_id, xf) in placed {
        let model = data.models.get(model_id as usize).ok_or_else(|| {
            format!(
                "scene graph names model {model_id}, but the file has {}",
                data.models.len()
            )
        })?;
        let half = DVec3::new(
            (model.size.x / 2) as f64,
            (model.size.y / 2) as f64,
            (model.size.z / 2) as f64,
        );
        for v in &model.voxels {
            // Regression (hostile probe): a SIZE of zero or "negative" (a
            // huge u32) was accepted whatever the voxels said.
            if v.x as u32 >= model.size.x
                || v.y as u32 >= model.size.y
                || v.z as u32 >= model.size.z
            {
                return Err(format!(
                    "model {model_id} has a voxel at ({}, {}, {}) outside its size {}x{}x{}",
                    v.x, v.y, v.z, model.size.x, model.size.y, model.size.z
                ));
            }
            let c = DVec3::new(v.x as f64, v.y as f64, v.z as f64) + 0.5 - half;
            let w = xf.apply(c);
            let w = DVec3::new(w.x, w.z, -w.y).floor();
            // Within ±2^30, so that bounds, bricks and `hi + 1` never
            // overflow (regression: a translation of -2^20 on a huge size
            // saturated at i32::MAX and three voxels became one).
            if !w.is_finite() || w.abs().max_element() > MAX_COORD {
                return Err(format!(
                    "model {model_id} places a voxel at ({}, {}, {}), beyond ±2^30",
                    w.x, w.y, w.z
                ));
            }
            out.push((w.as_ivec3(), v.i.saturating_add(1)));
        }
    }
    let mut palette = Palette::grey_ramp();
    for (i, c) in data.palette.iter().enumerate().take(255) {
        palette.set(i as u8 + 1, [c.r, c.g, c.b]);
    }
    keep_simulation_ids_free(&mut out, &mut palette);
    Ok((out, palette))
}

/// Move the voxels of materials 252 to 254 (colour indices 251 to 253),
/// which the simulations keep for water, snow and sediment, to ids the
/// model does not use, with their colours (regression, panic audit: a
/// model's red voxels of colour 252 became liquid water once a simulation
/// ran). A model using more than 251 colours keeps them where they are;
/// a simulation then refuses the world (see
/// [`reserved_conflicts`](crate::sim::run::reserved_conflicts)).
fn keep_simulation_ids_free(voxels: &mut [(IVec3, u8)], palette: &mut Palette) {
    use crate::sim::writeback::{SEDIMENT, WATER};
    let mut used = [false; 256];
    for &(_, m) in voxels.iter() {
        used[m as usize] = true;
    }
    let taken: Vec<u8> = (WATER..=SEDIMENT).filter(|&m| used[m as usize]).collect();
    let free: Vec<u8> = (1..WATER).filter(|&m| !used[m as usize]).collect();
    if taken.is_empty() || free.len() < taken.len() {
        return;
    }
    let mut to = [0u8; 256];
    for (k, &m) in taken.iter().enumerate() {
        to[m as usize] = free[k];
        palette.set(free[k], palette.rgb(m));
    }
    for (_, m) in voxels.iter_mut() {
        if to[*m as usize] != 0 {
            *m = to[*m as usize];
        }
    }
}

/// The largest voxel coordinate a file may place, in absolute value.
pub const MAX_COORD: f64 = (1u32 << 30) as f64;

/// Nodes the expansion of a scene graph may visit (each instance of a
/// shared node counts).
pub const MAX_NODE_VISITS: u64 = 1 << 24;

/// Voxels placed under `node`, and nodes the expansion visits there (both
/// saturating), memoised per node.
fn count(
    data: &dot_vox::DotVoxData,
    node: u32,
    depth: u32,
    memo: &mut Vec<Option<(u64, u64)>>,
) -> Result<(u64, u64), String> {
    if depth > MAX_DEPTH {
        return Err(format!(
            "scene graph deeper than {MAX_DEPTH} levels (a cycle?)"
        ));
    }
    if let Some(Some(n)) = memo.get(node as usize) {
        return Ok(*n);
    }
    let n = data.scenes.get(node as usize).ok_or_else(|| {
        format!(
            "scene graph names node {node}, but the file has {}",
            data.scenes.len()
        )
    })?;
    let total = match n {
        dot_vox::SceneNode::Transform { child, .. } => {
            let (v, w) = count(data, *child, depth + 1, memo)?;
            (v, w.saturating_add(1))
        }
        dot_vox::SceneNode::Group { children, .. } => {
            let mut t = (0u64, 1u64);
            for c in children {
                let (v, w) = count(data, *c, depth + 1, memo)?;
                t = (t.0.saturating_add(v), t.1.saturating_add(w));
            }
            t
        }
        dot_vox::SceneNode::Shape { models, .. } => (
            models
                .iter()
                .map(|m| {
                    data.models
                        .get(m.model_id as usize)
                        .map_or(0, |m| m.voxels.len() as u64)
                })
                .fold(0u64, u64::saturating_add),
            // Each model a shape lists is a placement the expansion makes
            // (regression, fuzzing: 2 000 empty models under 2^20 paths
            // passed as 2^20 visits and aborted out of memory).
            (models.len() as u64).max(1),
        ),
    };
    memo[node as usize] = Some(total);
    Ok(total)
}

fn walk(
    data: &dot_vox::DotVoxData,
    node: u32,
    xf: Xform,
    depth: u32,
    out: &mut Vec<(u32, Xform)>,
) -> Result<(), String> {
    if depth > MAX_DEPTH {
        return Err(format!(
            "scene graph deeper than {MAX_DEPTH} levels (a cycle?)"
        ));
    }
    let n = data.scenes.get(node as usize).ok_or_else(|| {
        format!(
            "scene graph names node {node}, but the file has {}",
            data.scenes.len()
        )
    })?;
    match n {
        dot_vox::SceneNode::Transform { frames, child, .. } => {
            let mut local = Xform::IDENTITY;
            if let Some(f) = frames.first() {
                if let Some(r) = f.attributes.get("_r") {
                    local.r = parse_rotation(r)?;
                }
                if let Some(t) = f.attributes.get("_t") {
                    local.t = parse_translation(t)?;
                }
            }
            walk(data, *child, xf.then(&local), depth + 1, out)
        }
        dot_vox::SceneNode::Group { children, .. } => {
            for c in children {
                walk(data, *c, xf, depth + 1, out)?;
            }
            Ok(())
        }
        dot_vox::SceneNode::Shape { models, .. } => {
            out.extend(models.iter().map(|m| (m.model_id, xf)));
            Ok(())
        }
    }
}

/// Parse `.vox` bytes, turning any parser failure (even a panic) into an error.
pub fn parse(bytes: &[u8]) -> Result<dot_vox::DotVoxData, String> {
    let counts = layout::check(bytes)?;
    match crate::catch_quietly(|| dot_vox::load_bytes(bytes)) {
        // A node or model chunk that could not be read is skipped by the
        // parser, and every index after it shifts.
        Ok(Ok(d)) if d.scenes.len() != counts.nodes => Err(format!(
            "{} of the file's {} scene-graph chunks could not be read",
            counts.nodes - d.scenes.len().min(counts.nodes),
            counts.nodes
        )),
        Ok(Ok(d)) if d.models.len() != counts.models => Err(format!(
            "{} of the file's {} models could not be read",
            counts.models - d.models.len().min(counts.models),
            counts.models
        )),
        Ok(Ok(d)) => Ok(d),
        Ok(Err(e)) => Err(e.to_string()),
        Err(_) => Err("the .vox parser rejected the file (malformed chunk)".into()),
    }
}

/// Load a `.vox` file into a store; returns it with its voxel bounds `[min, max)`.
pub fn load(path: &Path) -> Result<(BrickStore, IVec3, IVec3), SceneError> {
    let bytes = super::budget::read_file(path, MAX_FILE_BYTES)?;
    let fmt_err = |msg: String| SceneError::Format {
        path: path.to_path_buf(),
        kind: "MagicaVoxel .vox",
        msg,
    };
    let data = parse(&bytes).map_err(fmt_err)?;
    let (vox, palette) = voxels(&data).map_err(fmt_err)?;
    if vox.is_empty() {
        return Err(fmt_err("the file holds no voxels".into()));
    }
    // The world spans the voxels' bounding box: check it fits in memory
    // before the bricks and the grid over it are allocated.
    let (lo, hi) = vox
        .iter()
        .fold((IVec3::MAX, IVec3::MIN), |(lo, hi), (p, _)| {
            (lo.min(*p), hi.max(*p))
        });
    let extent = (hi.as_i64vec3() - lo.as_i64vec3() + 1).min(glam::I64Vec3::splat(i32::MAX as i64));
    let what = path.display().to_string();
    super::budget::check_world(&what, extent.as_ivec3())?;
    let (order, bricks) = brick_order(&vox);
    super::budget::check_stored_bricks(
        &what,
        bricks,
        super::budget::grid_bytes(extent.as_ivec3()),
    )?;
    Ok(build_in_order(&vox, &order, palette))
}

/// Build a store from a voxel list; returns it with the bounds `[min, max)`.
/// Where two voxels share a position, the later one wins.
pub fn store_from_voxels(vox: &[(IVec3, u8)], palette: Palette) -> (BrickStore, IVec3, IVec3) {
    let (order, _) = brick_order(vox);
    build_in_order(vox, &order, palette)
}

/// The voxels' indices grouped by brick, bricks in (z, y, x) order and each
/// brick's voxels in list order, and the number of distinct bricks: 4 bytes
/// a voxel, where a map of dense bricks would hold 512 bytes a brick at once
/// (a scattered model of a few million voxels needed gigabytes).
fn brick_order(vox: &[(IVec3, u8)]) -> (Vec<u32>, u64) {
    let key = |i: &u32| {
        let b = brick_of(vox[*i as usize].0);
        (b.z, b.y, b.x)
    };
    let mut order: Vec<u32> = (0..vox.len() as u32).collect();
    order.sort_by_key(key); // stable: a brick's voxels keep their order
    let bricks = 1 + order
        .windows(2)
        .filter(|w| key(&w[0]) != key(&w[1]))
        .count() as u64;
    (order, if vox.is_empty() { 0 } else { bricks })
}

/// Build the store from voxels grouped by [`brick_order`], one dense brick
/// at a time.
fn build_in_order(
    vox: &[(IVec3, u8)],
    order: &[u32],
    palette: Palette,
) -> (BrickStore, IVec3, IVec3) {
    let (mut lo, mut hi) = (IVec3::MAX, IVec3::MIN);
    let mut store = BrickStore::new(palette);
    let mut dense = [0u8; BRICK_VOXELS];
    let mut i = 0;
    while i < order.len() {
        let b = brick_of(vox[order[i] as usize].0);
        dense.fill(0);
        while let Some(&j) = order.get(i)
            && brick_of(vox[j as usize].0) == b
        {
            let (p, m) = vox[j as usize];
            lo = lo.min(p);
            hi = hi.max(p);
            let l = p - b * BRICK_EDGE;
            dense[voxel_index(l.x, l.y, l.z)] = m;
            i += 1;
        }
        let c = BrickContent::from_dense(&dense, store.palette());
        store.set_brick(b, c);
    }
    (store, lo, hi + IVec3::ONE)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn rotation_bytes_are_validated_not_panicked_on() {
        assert_eq!(
            parse_rotation("4").unwrap(),
            [[1, 0, 0], [0, 1, 0], [0, 0, 1]]
        );
        assert!(parse_rotation("3").is_err());
        assert!(parse_rotation("15").is_err());
        assert!(parse_rotation("x").is_err());
        assert!(parse_translation("1 2").is_err());
        assert_eq!(parse_translation("-1 2 3").unwrap(), [-1, 2, 3]);
    }

    /// Regression (code review): `abs()` of -2^31 wraps to itself in a
    /// release build, so that translation passed the ±2^20 check, and
    /// chained translations wrapped back into range.
    #[test]
    fn the_most_negative_translation_is_refused_and_chains_saturate() {
        assert!(parse_translation("-2147483648 0 0").is_err());
        assert!(parse_translation("0 0 -1048577").is_err());
        assert_eq!(parse_translation("0 0 -1048576").unwrap(), [0, 0, -1 << 20]);
        let far = Xform {
            r: Xform::IDENTITY.r,
            t: [i32::MIN, 0, i32::MAX],
        };
        let twice = far.then(&far);
        assert_eq!(twice.t, [i32::MIN, 0, i32::MAX]);
    }

    fn one_model(size: [u32; 3], at: &[[u8; 3]]) -> dot_vox::DotVoxData {
        dot_vox::DotVoxData {
            version: 150,
            index_map: Vec::new(),
            models: vec![dot_vox::Model {
                size: dot_vox::Size {
                    x: size[0],
                    y: size[1],
                    z: size[2],
                },
                voxels: at
                    .iter()
                    .map(|p| dot_vox::Voxel {
                        x: p[0],
                        y: p[1],
                        z: p[2],
                        i: 1,
                    })
                    .collect(),
            }],
            palette: Vec::new(),
            materials: Vec::new(),
            scenes: Vec::new(),
            layers: Vec::new(),
        }
    }

    /// Regression (hostile probe): voxels past the i32 range were clamped
    /// (three became one, and the bounds wrapped), and a model's size was
    /// never checked against its voxels.
    #[test]
    fn voxels_beyond_range_or_outside_their_model_are_refused() {
        let far = one_model([1, u32::MAX - 1, 1], &[[0, 0, 0], [0, 1, 0], [0, 2, 0]]);
        let e = voxels(&far).unwrap_err();
        assert!(e.contains("beyond ±2^30"), "{e}");
        let zero = one_model([0, 0, 0], &[[0, 0, 0]]);
        let e = voxels(&zero).unwrap_err();
        assert!(e.contains("outside its size 0x0x0"), "{e}");
        let ok = one_model([2, 2, 2], &[[0, 0, 0], [1, 1, 1]]);
        assert_eq!(voxels(&ok).unwrap().0.len(), 2);
    }
}
