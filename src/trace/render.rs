//! The tiled CPU renderer: 16×16 tiles traced in parallel on a rayon pool,
//! Lambert shading with one directional light, optional hard shadows,
//! optional per-voxel ambient occlusion and optional distance fog towards
//! the sky gradient.
//!
//! Shadow rays start from the exact hit point clamped into the empty
//! neighbour cell the primary ray came from (bit-exact cell bounds, no
//! epsilon), so a surface can never shadow itself.

use glam::{DVec3, IVec3, Vec3};
use rayon::prelude::*;

use super::Tracer;
use super::camera::Camera;
use super::ray::{Hit, Ray};
use crate::world::Palette;

/// Tile edge in pixels.
pub const TILE: usize = 16;

/// Lighting settings.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Shading {
    /// Direction *towards* the light (normalised).
    pub light: Vec3,
    /// Ambient term in [0, 1].
    pub ambient: f32,
}

impl Default for Shading {
    fn default() -> Self {
        Shading {
            light: Vec3::new(0.45, 0.8, 0.35).normalize(),
            ambient: 0.3,
        }
    }
}

/// What to render.
#[derive(Clone, Copy, Debug, Default, PartialEq)]
pub struct RenderOptions {
    /// Trace a shadow ray towards the light from every hit.
    pub shadows: bool,
    /// Lighting.
    pub shading: Shading,
    /// Distance fog: a hit at distance `t` (voxels) is blended towards the
    /// sky colour of its ray by `1 − exp(−t / fog)`. 0 is no fog.
    pub fog: f32,
    /// Level of detail: primary rays stop at cells under `lod` pixels wide
    /// (Áfra's `C`). 0 is exact.
    pub lod: f32,
    /// Where in each pixel the primary ray passes, in `[0, 1)²`; `None` is
    /// the centre. Jittered offsets averaged make a supersampled image.
    pub jitter: Option<[f64; 2]>,
    /// Per-voxel ambient occlusion on every hit ([`super::face_ao`]).
    pub ao: bool,
    /// Beam starts: a coarse pass per 8×8 block finds where its rays may
    /// start ([`super::beam`]); the image is the same, sooner.
    pub beam: bool,
}

/// Blend `c`, seen at distance `t`, into the sky colour `sky` by the fog
/// of extent `fog` (0: none).
fn fogged(c: [f32; 3], sky: [f32; 3], t: f32, fog: f32) -> [f32; 3] {
    if fog <= 0.0 {
        return c;
    }
    let k = 1.0 - (-t / fog).exp();
    [0, 1, 2].map(|i| c[i] + (sky[i] - c[i]) * k)
}

/// A rendered frame: 8-bit RGB, depth (t, +inf on a miss) and the hit per pixel.
#[derive(Clone, Debug)]
pub struct RenderOutput {
    /// Width in pixels.
    pub width: u32,
    /// Height in pixels.
    pub height: u32,
    /// Row-major RGB8.
    pub rgb: Vec<u8>,
    /// Row-major depth: t along the normalised ray, +inf for a miss.
    pub depth: Vec<f32>,
    /// Row-major primary hits.
    pub hits: Vec<Option<Hit>>,
}

impl RenderOutput {
    /// Fraction of pixels whose primary ray hit.
    pub fn hit_fraction(&self) -> f64 {
        self.hits.iter().filter(|h| h.is_some()).count() as f64 / self.hits.len().max(1) as f64
    }
}

fn sky(dir: DVec3) -> [f32; 3] {
    let k = dir.y.clamp(0.0, 1.0) as f32;
    let horizon = [0.78, 0.86, 0.95];
    let zenith = [0.33, 0.52, 0.84];
    [0, 1, 2].map(|c| horizon[c] + (zenith[c] - horizon[c]) * k)
}

fn shade(
    tracer: &dyn Tracer,
    ray: &Ray,
    hit: &Hit,
    palette: &Palette,
    opts: &RenderOptions,
) -> [f32; 3] {
    // A coarse cell: the average of its exposed faces as the view sees
    // them (each weighted by its projected area), not one face; no shadow.
    let mut lit = match coarse_average(tracer, hit, ray.dir, palette, opts.shading) {
        Some(avg) => avg,
        None => {
            let base = palette.rgb(hit.material).map(|c| c as f32 / 255.0);
            let k = voxel_light(tracer, ray, hit, opts);
            base.map(|c| c * k)
        }
    };
    if opts.ao {
        let cell = (hit.voxel - tracer.frame().anchor).to_array();
        let p = ray.origin + ray.dir * hit.t;
        let ao = super::face_ao(|c| tracer.solid_local(c), cell, hit.normal.to_array(), p);
        let k = 1.0 - super::AO_STRENGTH * (1.0 - ao);
        lit = lit.map(|c| c * k);
    }
    lit
}

/// Ambient plus Lambert (with an optional shadow ray) on a voxel's face.
fn voxel_light(tracer: &dyn Tracer, ray: &Ray, hit: &Hit, opts: &RenderOptions) -> f32 {
    let n = hit.normal.as_vec3();
    let light = opts.shading.light;
    let mut lambert = n.dot(light).max(0.0);
    if opts.shadows && lambert > 0.0 {
        // Start inside the empty cell the ray came from, at the hit point.
        let frame = tracer.frame();
        let cell = hit.voxel + hit.normal - frame.anchor;
        let p = ray.origin + ray.dir * hit.t;
        let lo = cell.as_vec3();
        let hi = (cell + IVec3::ONE).as_vec3();
        let clamped = Vec3::new(
            p.x.clamp(lo.x, hi.x.next_down()),
            p.y.clamp(lo.y, hi.y.next_down()),
            p.z.clamp(lo.z, hi.z.next_down()),
        );
        if tracer
            .trace(&Ray::new(clamped, light), f32::INFINITY)
            .is_some()
        {
            lambert = 0.0;
        }
    }
    if hit.normal == IVec3::ZERO {
        opts.shading.ambient
    } else {
        opts.shading.ambient + (1.0 - opts.shading.ambient) * lambert
    }
}

/// Sample `k` of the R2 low-discrepancy sequence in `[0, 1)²` (Roberts
/// 2018): where the `k`-th jittered sample of a pixel passes.
pub fn jitter_sample(k: u32) -> [f64; 2] {
    const G: f64 = 1.324_717_957_244_746;
    [
        (0.5 + k as f64 / G).fract(),
        (0.5 + k as f64 / (G * G)).fract(),
    ]
}

/// Average `samples` jittered images: `draw` renders one with the options
/// it is given (the caller's, with [`RenderOptions::jitter`] set). One
/// sample is the caller's options unchanged.
///
/// ```
/// use brickworld::trace::{RenderOptions, supersample};
/// // Two "images" of one pixel, 0 and 255, average to 128.
/// let mut k = 0;
/// let rgb = supersample(2, &RenderOptions::default(), |_| {
///     k += 1;
///     vec![if k == 1 { 0 } else { 255 }; 3]
/// });
/// assert_eq!(rgb, vec![128; 3]);
/// ```
pub fn supersample(
    samples: u32,
    opts: &RenderOptions,
    mut draw: impl FnMut(&RenderOptions) -> Vec<u8>,
) -> Vec<u8> {
    if samples <= 1 {
        return draw(opts);
    }
    let mut acc: Vec<u32> = Vec::new();
    for k in 0..samples {
        let o = RenderOptions {
            jitter: Some(jitter_sample(k)),
            ..*opts
        };
        let img = draw(&o);
        if acc.is_empty() {
            acc = vec![0; img.len()];
        }
        for (a, &c) in acc.iter_mut().zip(&img) {
            *a += c as u32;
        }
    }
    acc.iter()
        .map(|&a| ((a + samples / 2) / samples) as u8)
        .collect()
}

/// The colour of a coarse level-of-detail hit: its exposed voxel faces'
/// colours lit by Lambert, averaged by the area each shows along `dir`.
/// `None` for voxel hits (or if no face looks at the viewer).
fn coarse_average(
    tracer: &dyn Tracer,
    hit: &Hit,
    dir: Vec3,
    palette: &Palette,
    shading: Shading,
) -> Option<[f32; 3]> {
    let normal = |d: usize| {
        let f = crate::world::FACE_DIRS[d];
        Vec3::new(f[0] as f32, f[1] as f32, f[2] as f32)
    };
    // The area a face of direction `d` shows: faces turned away from the
    // viewer weigh 0 and are not even looked up.
    let area: [f32; 6] = std::array::from_fn(|d| (-normal(d).dot(dir)).max(0.0));
    let facing = (0..6).fold(0u8, |b, d| b | ((area[d] > 0.0) as u8) << d);
    let sums = tracer.coarse_faces(hit, facing, palette)?;
    let (mut sum, mut weight) = ([0.0f32; 3], 0.0f32);
    for d in (0..6).filter(|&d| sums.faces[d] > 0 && area[d] > 0.0) {
        let light =
            shading.ambient + (1.0 - shading.ambient) * normal(d).dot(shading.light).max(0.0);
        let k = light * area[d] / 255.0;
        for (s, &c) in sum.iter_mut().zip(&sums.rgb[d]) {
            *s += c as f32 * k;
        }
        weight += sums.faces[d] as f32 * area[d];
    }
    (weight > 0.0).then(|| sum.map(|s| s / weight))
}

/// Local coordinates within this of the anchor start their rays at the eye.
const NEAR: f64 = (super::dda::MAX_LOCAL / 2.0) as f64;

/// `Some(local eye)` when the eye, in local `f64` coordinates, is farther
/// than [`NEAR`] from the anchor on some axis.
fn far_eye(local: glam::DVec3) -> Option<glam::DVec3> {
    (local.abs().max_element() > NEAR).then_some(local)
}

/// The ray from the far `local` eye along `dir`, started where it enters
/// the box of half-edge [`NEAR`] around the anchor (every world lies well
/// inside it), and the distance it skipped; `None` for the distance when
/// the ray never enters it (and so hits nothing).
fn near_start(local: glam::DVec3, dir: glam::DVec3) -> (Ray, Option<f64>) {
    let (mut t_in, mut t_out) = (0.0f64, f64::INFINITY);
    for a in 0..3 {
        let (o, d) = (local[a], dir[a]);
        if d == 0.0 {
            if o.abs() > NEAR {
                t_in = f64::INFINITY;
            }
            continue;
        }
        let (t0, t1) = ((-NEAR - o) / d, (NEAR - o) / d);
        t_in = t_in.max(t0.min(t1));
        t_out = t_out.min(t0.max(t1));
    }
    let start = local + dir * t_in;
    let ray = Ray::new(start.as_vec3(), dir.as_vec3());
    (ray, (t_in <= t_out && t_in.is_finite()).then_some(t_in))
}

/// What a frame's primary rays share, computed once per frame for
/// [`render`] and [`trace_hits`] alike.
struct PrimaryRays {
    /// The eye in the tracer's local coordinates.
    origin: Vec3,
    /// An eye so far away that its local f32 coordinates are no longer
    /// exact integers (the DDA refuses such origins): each ray starts where
    /// it enters the exact range instead, found in f64 (regression: such an
    /// eye saw nothing). Never the case within 2^23 voxels of the anchor,
    /// which keeps every other image bit for bit as it was.
    far: Option<DVec3>,
    /// The level-of-detail factor: the same f32 product the GPU shader is
    /// given.
    lod_k: f32,
    /// Each column's and row's part of the direction.
    cols: Vec<f64>,
    rows: Vec<f64>,
}

impl PrimaryRays {
    fn new(tracer: &dyn Tracer, camera: &Camera, opts: &RenderOptions) -> Self {
        let frame = tracer.frame();
        let [jx, jy] = opts.jitter.unwrap_or([0.5, 0.5]);
        PrimaryRays {
            origin: frame.to_local(camera.eye),
            far: far_eye(camera.eye - frame.anchor.as_dvec3()),
            lod_k: opts.lod * camera.pixel_angle() as f32,
            cols: (0..camera.width)
                .map(|i| camera.column_factor(i as f64 + jx))
                .collect(),
            rows: (0..camera.height)
                .map(|j| camera.row_factor(j as f64 + jy))
                .collect(),
        }
    }
}

/// Render `camera`'s view of `tracer` on the current rayon pool.
pub fn render(
    tracer: &dyn Tracer,
    camera: &Camera,
    palette: &Palette,
    opts: &RenderOptions,
) -> RenderOutput {
    let (w, h) = (camera.width as usize, camera.height as usize);
    let mut rgb = vec![0u8; w * h * 3];
    let mut depth = vec![f32::INFINITY; w * h];
    let mut hits = vec![None; w * h];
    let rays = PrimaryRays::new(tracer, camera, opts);
    let (origin, far, lod_k) = (rays.origin, rays.far, rays.lod_k);
    let bw = camera.width.div_ceil(super::BEAM);
    let starts: Option<Vec<f32>> = (opts.beam && far.is_none()).then(|| {
        let bh = camera.height.div_ceil(super::BEAM);
        (0..bw * bh)
            .into_par_iter()
            .map(|b| {
                let (c, spread) = super::beam_of(camera, b % bw, b / bw);
                let centre = Ray::new(origin, c.as_vec3());
                super::ray_start(tracer.beam_start(&centre, spread, lod_k))
            })
            .collect()
    });
    rgb.par_chunks_mut(w * 3 * TILE)
        .zip(depth.par_chunks_mut(w * TILE))
        .zip(hits.par_chunks_mut(w * TILE))
        .enumerate()
        .for_each(|(band, ((rgb, depth), hits))| {
            let rows = depth.len() / w;
            for tx in (0..w).step_by(TILE) {
                for r in 0..rows {
                    let j = band * TILE + r;
                    for i in tx..(tx + TILE).min(w) {
                        let dir = camera.direction_from(rays.cols[i], rays.rows[j]);
                        let (ray, shift) = match far {
                            None => (Ray::new(origin, dir.as_vec3()), Some(0.0)),
                            Some(local) => near_start(local, dir),
                        };
                        let px = r * w + i;
                        let t0 = starts.as_ref().map_or(0.0, |s| {
                            s[(j as u32 / super::BEAM * bw + i as u32 / super::BEAM) as usize]
                        });
                        let found = shift.and_then(|shift| {
                            let hit = if shift > 0.0 {
                                tracer.trace_skipped(&ray, f32::INFINITY, lod_k, shift as f32)
                            } else {
                                tracer.trace_from(&ray, t0, f32::INFINITY, lod_k)
                            }?;
                            Some((hit, shift))
                        });
                        let c = match found {
                            Some((hit, shift)) => {
                                // From the eye, not from the shifted start.
                                let t = (hit.t as f64 + shift) as f32;
                                depth[px] = t;
                                hits[px] = Some(Hit { t, ..hit });
                                let c = shade(tracer, &ray, &hit, palette, opts);
                                if opts.fog > 0.0 {
                                    fogged(c, sky(dir), t, opts.fog)
                                } else {
                                    c
                                }
                            }
                            None => sky(dir),
                        };
                        for k in 0..3 {
                            rgb[px * 3 + k] = (c[k].clamp(0.0, 1.0) * 255.0 + 0.5) as u8;
                        }
                    }
                }
            }
        });
    RenderOutput {
        width: camera.width,
        height: camera.height,
        rgb,
        depth,
        hits,
    }
}

/// The primary hits of `camera`'s view alone: the rays [`render`] traces
/// (with `opts.lod`, from the eye, no beam starts), with no shading, sky,
/// depth or image. The hits are [`render`]'s, bit for bit (tested); this
/// is what a peer that only intersects rays (Embree's `rtcIntersect1`,
/// which returns a distance, a primitive and a normal) is compared with.
pub fn trace_hits(tracer: &dyn Tracer, camera: &Camera, opts: &RenderOptions) -> Vec<Option<Hit>> {
    let (w, h) = (camera.width as usize, camera.height as usize);
    let mut hits = vec![None; w * h];
    let rays = PrimaryRays::new(tracer, camera, opts);
    let (origin, far, lod_k) = (rays.origin, rays.far, rays.lod_k);
    hits.par_chunks_mut(w * TILE)
        .enumerate()
        .for_each(|(band, hits)| {
            let rows = hits.len() / w;
            for tx in (0..w).step_by(TILE) {
                for r in 0..rows {
                    let j = band * TILE + r;
                    for i in tx..(tx + TILE).min(w) {
                        let dir = camera.direction_from(rays.cols[i], rays.rows[j]);
                        hits[r * w + i] = match far {
                            None => tracer.trace_from(
                                &Ray::new(origin, dir.as_vec3()),
                                0.0,
                                f32::INFINITY,
                                lod_k,
                            ),
                            Some(local) => {
                                let (ray, shift) = near_start(local, dir);
                                shift.and_then(|shift| {
                                    let hit = if shift > 0.0 {
                                        tracer.trace_skipped(
                                            &ray,
                                            f32::INFINITY,
                                            lod_k,
                                            shift as f32,
                                        )
                                    } else {
                                        tracer.trace_from(&ray, 0.0, f32::INFINITY, lod_k)
                                    }?;
                                    Some(Hit {
                                        t: (hit.t as f64 + shift) as f32,
                                        ..hit
                                    })
                                })
                            }
                        };
                    }
                }
            }
        });
    hits
}

#[cfg(test)]
mod tests {
    use super::*;

    /// No fog leaves the colour; fog blends towards the sky with distance,
    /// by 1 − 1/e at its extent.
    #[test]
    fn fog_blends_towards_the_sky_with_distance() {
        let (c, s) = ([0.2, 0.4, 0.6], [1.0, 1.0, 1.0]);
        assert_eq!(fogged(c, s, 500.0, 0.0), c);
        let near = fogged(c, s, 1.0, 100.0);
        let at = fogged(c, s, 100.0, 100.0);
        let far = fogged(c, s, 1e5, 100.0);
        assert!((at[0] - (0.2 + 0.8 * (1.0 - (-1.0f32).exp()))).abs() < 1e-6);
        assert!(near[0] < at[0] && at[0] < far[0]);
        assert!((far[0] - 1.0).abs() < 1e-6);
    }
}
