//! The `heightmap:FILE.png` scene: an 8- or 16-bit grayscale PNG where pixel
//! (u, v) with value h makes column x = u, z = v solid for 0 ≤ y < h,
//! coloured by height (a green–brown–white ramp) and slope (greys).

use std::io::Cursor;
use std::path::Path;

use glam::IVec3;

use super::SceneError;
use super::heightfield::Heightfield;
use crate::world::Palette;

/// Largest accepted file, bytes.
pub const MAX_FILE_BYTES: u64 = 256 << 20;
/// Largest accepted image side, pixels.
pub const MAX_SIDE: u32 = 16384;
/// Tallest accepted column, voxels.
pub const MAX_HEIGHT: i32 = 4096;

const RAMP: u8 = 200; // materials 1..=200: height ramp
const ROCK: u8 = 201; // 201..=240: steep slopes by height
const DEEP: u8 = 255;

/// A PNG decoder error as one readable line: the decoder prints a chunk's
/// type as its debug struct (`ChunkType { type: AGEG, critical: true, … }`),
/// which becomes `'AGEG'` (regression).
fn png_message(e: png::DecodingError) -> String {
    let mut msg = e.to_string();
    while let Some(i) = msg.find("ChunkType { type: ") {
        // The name is printed with Rust's escapes (`\u{7f}`), whose braces
        // are not the struct's: it ends at the first field after it
        // (regression, fuzzing: a name with odd bytes was cut to a letter
        // or two, and the struct's fields were left in the message).
        let start = i + "ChunkType { type: ".len();
        let Some(fields) = msg[start..].find(", critical:").map(|j| start + j) else {
            break;
        };
        // Bytes past ASCII came out as Latin-1 letters: shown as bytes.
        let name: String = msg[start..fields]
            .chars()
            .map(|c| match c as u32 {
                0x80..=0xff => format!("\\x{:02x}", c as u32),
                _ => c.to_string(),
            })
            .collect();
        let end = msg[fields..]
            .find(" }")
            .map_or(msg.len(), |k| fields + k + 2);
        msg.replace_range(i..end, &format!("'{name}'"));
    }
    msg.trim_end_matches('.').to_string()
}

/// A decoded heightmap.
#[derive(Clone, Debug)]
pub struct Heightmap {
    width: i32,
    depth: i32,
    heights: Vec<u16>,
    max: i32,
}

impl Heightmap {
    /// Load and validate a PNG.
    pub fn load(path: &Path) -> Result<Self, SceneError> {
        let bytes = super::budget::read_file(path, MAX_FILE_BYTES)?;
        // Check the world the image asks for from its header, before the
        // pixels are decoded.
        if let Some((w, h)) = Self::dims(&bytes) {
            super::budget::check_world(
                &path.display().to_string(),
                glam::IVec3::new(w as i32, 1, h as i32),
            )?;
        }
        Self::decode(&bytes).map_err(|msg| SceneError::Format {
            path: path.to_path_buf(),
            kind: "PNG heightmap",
            msg,
        })
    }

    /// The image's width and height from its header, if it has one.
    pub fn dims(bytes: &[u8]) -> Option<(u32, u32)> {
        let decoder = png::Decoder::new(Cursor::new(bytes));
        let reader = decoder.read_info().ok()?;
        Some((reader.info().width, reader.info().height))
    }

    /// Decode PNG bytes.
    pub fn decode(bytes: &[u8]) -> Result<Self, String> {
        // The zlib stream's Adler-32 is checked too (the crate skips it by
        // default): a heightmap damaged inside its compressed data, with
        // its chunk CRCs made to match, was read as other terrain.
        let mut options = png::DecodeOptions::default();
        options.set_ignore_adler32(false);
        let mut decoder = png::Decoder::new_with_options(Cursor::new(bytes), options);
        decoder.set_limits(png::Limits { bytes: 1 << 30 });
        let mut reader = decoder.read_info().map_err(png_message)?;
        let info = reader.info();
        let (w, h) = (info.width, info.height);
        if w > MAX_SIDE || h > MAX_SIDE {
            return Err(format!(
                "image is {w}x{h}, over the {MAX_SIDE}x{MAX_SIDE} limit"
            ));
        }
        let (color, depth) = (info.color_type, info.bit_depth);
        if color != png::ColorType::Grayscale {
            return Err(format!("expected 8- or 16-bit grayscale, found {color:?}"));
        }
        if depth != png::BitDepth::Eight && depth != png::BitDepth::Sixteen {
            return Err(format!(
                "expected 8- or 16-bit grayscale, found {depth:?}-bit"
            ));
        }
        let size = reader.output_buffer_size().ok_or("image too large")?;
        let mut buf = vec![0u8; size];
        let frame = reader.next_frame(&mut buf).map_err(png_message)?;
        let stride = frame.line_size;
        let mut heights = Vec::with_capacity((w * h) as usize);
        for v in 0..h as usize {
            let row = &buf[v * stride..];
            for u in 0..w as usize {
                let value = if depth == png::BitDepth::Sixteen {
                    u16::from_be_bytes([row[2 * u], row[2 * u + 1]])
                } else {
                    row[u] as u16
                };
                heights.push(value);
            }
        }
        let max = heights.iter().copied().max().unwrap_or(0) as i32;
        if max > MAX_HEIGHT {
            return Err(format!(
                "a pixel value of {max} asks for a column taller than the {MAX_HEIGHT}-voxel limit"
            ));
        }
        Ok(Heightmap {
            width: w as i32,
            depth: h as i32,
            heights,
            max,
        })
    }

    /// Height of column (x, z), exactly the pixel value (0 outside the image).
    pub fn value(&self, x: i32, z: i32) -> i32 {
        if x < 0 || z < 0 || x >= self.width || z >= self.depth {
            return 0;
        }
        self.heights[(z * self.width + x) as usize] as i32
    }

    /// The palette this scene's materials index.
    pub fn palette() -> Palette {
        let mut p = Palette::grey_ramp();
        for i in 0..RAMP {
            let t = i as f32 / (RAMP - 1) as f32;
            let stops = [
                [70.0, 130.0, 60.0],
                [150.0, 140.0, 80.0],
                [120.0, 90.0, 60.0],
                [245.0, 245.0, 250.0],
            ];
            let s = t * 3.0;
            let k = (s.floor() as usize).min(2);
            let f = s - k as f32;
            let c = [0, 1, 2].map(|c| (stops[k][c] + (stops[k + 1][c] - stops[k][c]) * f) as u8);
            p.set(1 + i, c);
        }
        for i in 0..40u8 {
            let g = 90 + i * 3;
            p.set(ROCK + i, [g, g.saturating_sub(4), g.saturating_sub(8)]);
        }
        p.set(DEEP, [80, 76, 74]);
        p
    }
}

impl Heightfield for Heightmap {
    fn extent(&self) -> IVec3 {
        IVec3::new(self.width, self.max.max(1), self.depth)
    }

    fn height(&self, x: i32, z: i32) -> i32 {
        self.value(x.clamp(0, self.width - 1), z.clamp(0, self.depth - 1))
    }

    fn material(&self, _x: i32, y: i32, _z: i32, h: i32, slope: f32) -> u8 {
        if h - 1 - y >= 3 {
            return DEEP;
        }
        let t = h as f32 / self.max.max(1) as f32;
        if slope > 1.5 {
            ROCK + (t * 39.0) as u8
        } else {
            1 + (t * (RAMP - 1) as f32) as u8
        }
    }

    fn deep(&self) -> Option<(i32, u8)> {
        Some((3, DEEP))
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// Regression (fuzzing): a chunk type holding bytes that are not
    /// letters was shown cut (`''DR`), followed by the debug fields of the
    /// decoder's struct. The whole name is shown, escaped, and nothing else.
    #[test]
    fn a_chunk_name_with_odd_bytes_is_shown_whole() {
        let mut png = b"\x89PNG\r\n\x1a\n".to_vec();
        let kind = [0xff, 0x7f, b'D', b'R'];
        png.extend(0u32.to_be_bytes());
        png.extend(kind);
        png.extend(crc32fast::hash(&kind).to_be_bytes());
        let e = Heightmap::decode(&png).unwrap_err();
        assert!(e.contains(r"'\xff\u{7f}DR'"), "{e}");
        assert!(!e.contains("critical"), "{e}");
    }
}
