//! Where does one-sample error come from, and how much of it does level of
//! detail remove? Terrain 2048², the overview at 960×540: FLIP of the exact
//! one-sample image and of LOD images against a 16-sample reference, split
//! into the pixels that LOD (C = 1) draws from a coarse level and the rest.
//!
//! Then two baselines that bound what one ray a pixel can do:
//! - exact images of 2, 4 and 8 jittered samples (R2 samples 100 on, so
//!   none is one of the reference's), the error that *n* rays buy;
//! - LOD images of 4 samples: what is left when LOD's noise is averaged
//!   away is its bias against the reference, and a brightness gain on the
//!   coarse pixels shows how much of that bias is mere darkening.
//!
//! Last, a screen-space filter: a 3×3 tent over the pixels LOD draws
//! coarse, and over the whole exact image, to show whether the error left
//! is aliasing a reconstruction filter would remove.
//!
//! `cargo run --release --example lod_error_map` (about a minute).
use brickworld::scene::{SceneSpec, build_scene};
use brickworld::trace::{Camera, RenderOptions, jitter_sample, render, supersample};
use glam::{DVec3, IVec3};

fn main() {
    let spec: SceneSpec = "terrain".parse().unwrap();
    let hidden = indicatif::ProgressBar::hidden();
    let w = build_scene(&spec, IVec3::new(2048, 256, 2048), 1, &hidden).unwrap();
    let v = w.default_views()[0];
    let (width, height) = (960u32, 540u32);
    let cam = Camera::new(
        DVec3::from(v.eye),
        DVec3::from(v.target),
        v.fov,
        width,
        height,
    )
    .unwrap();
    let bm = w.brickmap();
    let pal = w.store().palette();
    let reference = supersample(16, &RenderOptions::default(), |o| {
        render(&bm, &cam, pal, o).rgb
    });
    let flip = |img: &[u8]| {
        let r = nv_flip::FlipImageRgb8::with_data(width, height, &reference);
        let t = nv_flip::FlipImageRgb8::with_data(width, height, img);
        nv_flip::flip(r, t, nv_flip::DEFAULT_PIXELS_PER_DEGREE).to_vec()
    };
    let exact = render(&bm, &cam, pal, &RenderOptions::default());
    let lod1 = render(
        &bm,
        &cam,
        pal,
        &RenderOptions {
            lod: 1.0,
            ..Default::default()
        },
    );
    let coarse: Vec<bool> = exact
        .hits
        .iter()
        .zip(&lod1.hits)
        .map(|(a, b)| a != b)
        .collect();
    let n = coarse.len() as f64;
    for c in [0.0f32, 0.75, 1.0, 1.5, 2.0, 4.0] {
        let img = render(
            &bm,
            &cam,
            pal,
            &RenderOptions {
                lod: c,
                ..Default::default()
            },
        );
        let e = flip(&img.rgb);
        let (far, near) = e
            .iter()
            .zip(&coarse)
            .fold((0.0f64, 0.0f64), |(f, r), (&x, &c)| {
                if c {
                    (f + x as f64, r)
                } else {
                    (f, r + x as f64)
                }
            });
        println!(
            "C = {c}: mean FLIP {:.4}; share from the {:.1} % of pixels coarse at C = 1: {:.1} %",
            (far + near) / n,
            coarse.iter().filter(|&&c| c).count() as f64 / n * 100.0,
            far / (far + near) * 100.0
        );
    }

    // Baselines: n exact rays a pixel, and LOD's bias.
    let mean = |e: Vec<f32>| e.iter().map(|&x| x as f64).sum::<f64>() / n;
    let exact1 = mean(flip(&exact.rgb));
    let jittered = |samples: u32, lod: f32| {
        let mut acc = vec![0u32; exact.rgb.len()];
        for k in 100..100 + samples {
            let o = RenderOptions {
                jitter: Some(jitter_sample(k)),
                lod,
                ..Default::default()
            };
            for (a, &c) in acc.iter_mut().zip(&render(&bm, &cam, pal, &o).rgb) {
                *a += c as u32;
            }
        }
        acc.iter()
            .map(|&a| ((a + samples / 2) / samples) as u8)
            .collect::<Vec<u8>>()
    };
    for samples in [2, 4, 8] {
        let e = mean(flip(&jittered(samples, 0.0)));
        println!(
            "exact, {samples} samples: mean FLIP {e:.4} ({:.2}x one sample)",
            e / exact1
        );
    }
    let e = mean(flip(&jittered(4, 1.0)));
    println!(
        "LOD C = 1, 4 samples: mean FLIP {e:.4} ({:.2}x exact one sample)",
        e / exact1
    );
    let (w, h) = (width as usize, height as usize);
    let everywhere = vec![true; exact.hits.len()];
    let e = mean(flip(&tent3(&exact.rgb, w, h, &everywhere)));
    println!(
        "exact, 1 sample, 3x3 tent: mean FLIP {e:.4} ({:.2}x exact one sample)",
        e / exact1
    );
    let lod_coarse: Vec<bool> = lod1
        .hits
        .iter()
        .map(|h| h.is_some_and(|h| h.level > 0))
        .collect();
    let e = mean(flip(&tent3(&lod1.rgb, w, h, &lod_coarse)));
    println!(
        "LOD C = 1, 3x3 tent on coarse pixels: mean FLIP {e:.4} ({:.2}x exact one sample)",
        e / exact1
    );
    for gain in [1.01f32, 1.02, 1.03, 1.04] {
        let mut img = lod1.rgb.clone();
        for (px, h) in lod1.hits.iter().enumerate() {
            if h.is_some_and(|h| h.level > 0) {
                for c in &mut img[px * 3..px * 3 + 3] {
                    *c = (*c as f32 * gain).min(255.0) as u8;
                }
            }
        }
        let e = mean(flip(&img));
        println!(
            "LOD C = 1, coarse pixels x{gain}: mean FLIP {e:.4} ({:.2}x exact one sample)",
            e / exact1
        );
    }
}

/// A 3×3 tent filter (weights 1 2 1 in each direction) over the pixels of
/// `rgb` (`w` × `h`) where `mask` is set; the others are copied.
fn tent3(rgb: &[u8], w: usize, h: usize, mask: &[bool]) -> Vec<u8> {
    const K: [f32; 3] = [1.0, 2.0, 1.0];
    let mut out = rgb.to_vec();
    for y in 0..h {
        for x in 0..w {
            let p = y * w + x;
            if !mask[p] {
                continue;
            }
            let (mut acc, mut sum) = ([0f32; 3], 0f32);
            for (dy, ky) in K.iter().enumerate() {
                for (dx, kx) in K.iter().enumerate() {
                    let (yy, xx) = ((y + dy).wrapping_sub(1), (x + dx).wrapping_sub(1));
                    if yy >= h || xx >= w {
                        continue;
                    }
                    let q = (yy * w + xx) * 3;
                    for (a, &c) in acc.iter_mut().zip(&rgb[q..q + 3]) {
                        *a += ky * kx * c as f32;
                    }
                    sum += ky * kx;
                }
            }
            for (o, a) in out[p * 3..p * 3 + 3].iter_mut().zip(acc) {
                *o = (a / sum).round() as u8;
            }
        }
    }
    out
}
