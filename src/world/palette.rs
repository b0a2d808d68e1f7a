//! The world palette: 256 RGB colours indexed by a voxel's material byte.
//!
//! Material 0 is "empty" and its colour is never drawn. Scenes build their own
//! palette (terrain bands, heightmap ramps, a `.vox` file's colours).

/// 256 RGB colours; entry `m` is the colour of material `m`.
#[derive(Clone, Debug, PartialEq, Eq)]
pub struct Palette {
    colors: Box<[[u8; 3]; 256]>,
}

impl Palette {
    /// A palette from explicit colours.
    pub fn new(colors: [[u8; 3]; 256]) -> Self {
        Palette {
            colors: Box::new(colors),
        }
    }

    /// Material `m` is grey level `m`: handy for tests.
    pub fn grey_ramp() -> Self {
        let mut c = [[0u8; 3]; 256];
        for (i, e) in c.iter_mut().enumerate() {
            *e = [i as u8; 3];
        }
        Palette::new(c)
    }

    /// Colour of material `m`.
    #[inline(always)]
    pub fn rgb(&self, m: u8) -> [u8; 3] {
        self.colors[m as usize]
    }

    /// Set the colour of material `m`.
    pub fn set(&mut self, m: u8, rgb: [u8; 3]) {
        self.colors[m as usize] = rgb;
    }
}

impl Default for Palette {
    fn default() -> Self {
        Palette::grey_ramp()
    }
}
