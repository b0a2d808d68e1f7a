//! The procedural `terrain` scene: an fBm landscape coloured by height and
//! slope, with optional overhangs and caves (`terrain:caves`).

use glam::IVec3;

use super::heightfield::Heightfield;
use super::noise::{Noise, hash64};
use crate::world::Palette;

/// Materials of the terrain palette.
mod mat {
    pub const GRASS: u8 = 1; // 1..=3
    pub const DIRT: u8 = 4; // 4..=5
    pub const ROCK: u8 = 6; // 6..=8
    pub const SNOW: u8 = 9; // 9..=10
    pub const SAND: u8 = 11;
    pub const DEEP: u8 = 12;
}

/// The terrain's material names (the variants of a material are shades).
pub const NAMES: &[(u8, &str)] = &[
    (1, "grass"),
    (2, "grass_2"),
    (3, "grass_3"),
    (4, "dirt"),
    (5, "dirt_2"),
    (6, "rock"),
    (7, "rock_2"),
    (8, "rock_3"),
    (9, "snowcap"),
    (10, "snowcap_2"),
    (11, "sand"),
    (12, "bedrock"),
];

/// The terrain palette.
pub fn palette() -> Palette {
    let mut p = Palette::grey_ramp();
    let colors: [(u8, [u8; 3]); 12] = [
        (1, [88, 140, 62]),
        (2, [101, 152, 70]),
        (3, [79, 128, 56]),
        (4, [120, 92, 64]),
        (5, [108, 82, 58]),
        (6, [128, 124, 118]),
        (7, [116, 112, 108]),
        (8, [140, 136, 128]),
        (9, [240, 242, 246]),
        (10, [226, 230, 238]),
        (11, [214, 196, 140]),
        (12, [96, 92, 90]),
    ];
    for (m, c) in colors {
        p.set(m, c);
    }
    p
}

/// fBm terrain.
#[derive(Clone, Debug)]
pub struct Terrain {
    extent: IVec3,
    noise: Noise,
    caves: bool,
    scale: f64,
    /// Unbounded in x and z: heights are not clamped to an extent.
    unbounded: bool,
}

/// The horizontal feature scale of every terrain at least 1536 voxels wide,
/// and of unbounded ones: an 8192² continent and an endless world share it,
/// so the same coordinates look alike in both.
pub const LARGE_SCALE: f64 = 512.0;

impl Terrain {
    /// A terrain of `extent` voxels (x, max height, z).
    pub fn new(extent: IVec3, seed: u64, caves: bool) -> Self {
        let scale = (extent.x.max(extent.z) as f64 / 3.0).clamp(64.0, LARGE_SCALE);
        Terrain {
            extent,
            noise: Noise::new(seed),
            caves,
            scale,
            unbounded: false,
        }
    }

    /// A terrain without bounds in x and z, `height` voxels tall, with the
    /// feature scale of the largest bounded terrains ([`LARGE_SCALE`]).
    pub fn unbounded(height: i32, seed: u64, caves: bool) -> Self {
        Terrain {
            extent: IVec3::new(i32::MAX, height, i32::MAX),
            noise: Noise::new(seed),
            caves,
            scale: LARGE_SCALE,
            unbounded: true,
        }
    }

    fn jitter(&self, x: i32, z: i32, n: u64) -> u8 {
        (hash64(((x as u64) << 32) ^ (z as u32 as u64) ^ 0xa5a5) % n) as u8
    }
}

impl Heightfield for Terrain {
    fn extent(&self) -> IVec3 {
        self.extent
    }

    fn height(&self, x: i32, z: i32) -> i32 {
        let (x, z) = if self.unbounded {
            (x as f64, z as f64)
        } else {
            (
                x.clamp(0, self.extent.x - 1) as f64,
                z.clamp(0, self.extent.z - 1) as f64,
            )
        };
        let n = self.noise.fbm2(x / self.scale, z / self.scale, 5);
        // Ridged low-frequency noise raises mountain ranges with snow caps.
        let ridge = 1.0
            - (self
                .noise
                .noise2(x / (self.scale * 2.2) + 31.7, z / (self.scale * 2.2) - 7.3)
                * 2.2)
                .abs();
        let ridge = ridge.clamp(0.0, 1.0);
        let y = self.extent.y as f64;
        ((0.26 + 0.22 * n + 0.5 * ridge * ridge * ridge) * y).clamp(1.0, y - 1.0) as i32
    }

    fn material(&self, x: i32, y: i32, z: i32, h: i32, slope: f32) -> u8 {
        let depth = h - 1 - y;
        let ey = self.extent.y;
        if depth >= 4 {
            mat::DEEP
        } else if slope > 1.25 {
            mat::ROCK + self.jitter(x, z, 3)
        } else if h * 100 > ey * 72 {
            mat::SNOW + self.jitter(x, z, 2)
        } else if h * 100 < ey * 20 {
            mat::SAND
        } else if depth <= 0 {
            mat::GRASS + self.jitter(x, z, 3)
        } else {
            mat::DIRT + self.jitter(x, z, 2)
        }
    }

    fn solid(&self, x: i32, y: i32, z: i32, h: i32) -> bool {
        if !self.caves {
            return y < h;
        }
        let (fx, fy, fz) = (x as f64, y as f64, z as f64);
        let overhang = 5.0 * self.noise.noise3(fx / 11.0, fy / 9.0, fz / 11.0);
        if (h - y) as f64 + overhang <= 0.0 {
            return false;
        }
        let cave = self.noise.noise3(fx / 29.0 + 100.0, fy / 17.0, fz / 29.0);
        !(y > 2 && cave > 0.42)
    }

    fn margin_above(&self) -> i32 {
        if self.caves { 6 } else { 0 }
    }

    fn deep(&self) -> Option<(i32, u8)> {
        if self.caves {
            None
        } else {
            Some((4, mat::DEEP))
        }
    }
}
