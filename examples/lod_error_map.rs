//! Where does one-sample error come from, and how much of it does level of
//! detail remove? Terrain 2048², the overview at 960×540: FLIP of the exact
//! one-sample image and of LOD images against a 16-sample reference, split
//! into the pixels that LOD (C = 1) draws from a coarse level and the rest.
//!
//! `cargo run --release --example lod_error_map` (about a minute).
use brickworld::scene::{SceneSpec, build_scene};
use brickworld::trace::{Camera, RenderOptions, render, supersample};
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
}
