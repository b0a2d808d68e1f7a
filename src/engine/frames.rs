//! Frames on disk: each written atomically (a temporary file, then a
//! rename), found again at start, and pruned oldest first to `[frames]
//! keep` and `max_mb`; only files named as the engine names its frames are
//! ever pruned.

use std::path::PathBuf;

/// The frames on disk, oldest first (by tick), with their sizes,
/// pruned to a count and a byte total (`[frames] keep` and `max_mb`).
#[derive(Debug, Default)]
pub struct FrameFiles {
    files: std::collections::VecDeque<(PathBuf, u64)>,
    bytes: u64,
}

/// The tick of a frame file's name, if it is one the engine writes:
/// `frame-`, the tick as `{:08}` writes it, `.png`. Anything else in the
/// frames directory is the user's and is never pruned (regression: every
/// `frame-*.png` was, a user's `frame-holiday.png` included).
pub fn frame_tick(name: &str) -> Option<u64> {
    let digits = name.strip_prefix("frame-")?.strip_suffix(".png")?;
    if digits.len() < 8 || !digits.bytes().all(|b| b.is_ascii_digit()) {
        return None;
    }
    let tick: u64 = digits.parse().ok()?;
    (format!("{tick:08}") == digits).then_some(tick)
}

/// A frame the engine was writing when it was killed: the old fixed name
/// `.frame-NNNNNNNN.png.tmp`, or `.frame-NNNNNNNN.png.PID-N.tmp` of a
/// process that is gone (a running engine's is left alone).
fn engine_temp(name: &str) -> bool {
    let fixed = name
        .strip_prefix('.')
        .and_then(|n| n.strip_suffix(".tmp"))
        .and_then(frame_tick);
    fixed.is_some()
        || crate::files::temp_of_gone_process(name)
            .and_then(frame_tick)
            .is_some()
}

impl FrameFiles {
    /// The frames already in `dir` (a missing directory has none), oldest
    /// first by tick (a tick past 8 digits sorts after, not before).
    pub fn scan(dir: &std::path::Path) -> Self {
        let mut v: Vec<(u64, PathBuf, u64)> = std::fs::read_dir(dir)
            .map(|rd| {
                rd.flatten()
                    .filter(|e| e.file_type().is_ok_and(|t| t.is_file()))
                    .filter(|e| {
                        // A frame half-written when the engine was killed
                        // (`.frame-NNNNNNNN.png.tmp`, the engine's own name):
                        // removed, not kept for ever.
                        let temp = e.file_name().to_str().is_some_and(engine_temp);
                        if temp {
                            let _ = std::fs::remove_file(e.path());
                        }
                        !temp
                    })
                    .filter_map(|e| {
                        let tick = frame_tick(e.file_name().to_str()?)?;
                        Some((tick, e.path(), e.metadata().map_or(0, |m| m.len())))
                    })
                    .collect()
            })
            .unwrap_or_default();
        v.sort();
        let v: Vec<(PathBuf, u64)> = v.into_iter().map(|(_, p, b)| (p, b)).collect();
        let bytes = v.iter().map(|f| f.1).sum();
        FrameFiles {
            files: v.into(),
            bytes,
        }
    }

    /// Record a frame just written (replacing one of the same name).
    pub fn push(&mut self, path: PathBuf, bytes: u64) {
        if let Some(i) = self.files.iter().position(|f| f.0 == path) {
            let (_, b) = self.files.remove(i).expect("present");
            self.bytes -= b;
        }
        self.bytes += bytes;
        self.files.push_back((path, bytes));
    }

    /// Delete the oldest frames until at most `keep` remain and they hold at
    /// most `max_bytes` (the newest frame is always kept).
    pub fn prune(&mut self, keep: usize, max_bytes: u64) {
        while self.files.len() > keep || (self.bytes > max_bytes && self.files.len() > 1) {
            let Some((old, b)) = self.files.pop_front() else {
                break;
            };
            self.bytes -= b;
            let _ = std::fs::remove_file(old);
        }
    }

    /// Frames kept, and their bytes.
    pub fn totals(&self) -> (usize, u64) {
        (self.files.len(), self.bytes)
    }
}

/// Write frame `tick` into `dir` atomically: a temporary file, then a
/// rename, so a full disk or a kill never leaves a truncated frame under a
/// final name (a failed write removes its temporary file). Returns the
/// frame's path.
pub fn write_frame(dir: &std::path::Path, tick: u64, png: &[u8]) -> std::io::Result<PathBuf> {
    use std::io::Write as _;
    let path = dir.join(format!("frame-{tick:08}.png"));
    // A fresh temporary (`create_new`), never one at a fixed name: a link
    // planted at `.frame-N.png.tmp` was written through (regression,
    // odd-paths probe).
    let (tmp, mut f) = crate::files::fresh_temp_beside(&path)?;
    match f.write_all(png).and_then(|_| std::fs::rename(&tmp, &path)) {
        Ok(()) => Ok(path),
        Err(e) => {
            let _ = std::fs::remove_file(&tmp);
            Err(e)
        }
    }
}

/// Encode an RGB8 image as PNG bytes. An error (an image whose bytes do
/// not fill `w`×`h`) is returned, never a PNG of the header alone (found by
/// review: the encoder's errors were dropped, and such a file would have
/// been served and kept as a frame).
pub fn png_bytes(w: u32, h: u32, rgb: &[u8]) -> Result<Vec<u8>, png::EncodingError> {
    let mut out = Vec::new();
    {
        let mut enc = png::Encoder::new(&mut out, w, h);
        enc.set_color(png::ColorType::Rgb);
        enc.set_depth(png::BitDepth::Eight);
        // Fast deflate: on a 640×360 terrain frame 0.98 ms against the
        // default level's 22.8, for a file 26 % larger (257 against 204
        // KB; `cargo bench --bench frame_png`). On the CPU tracer the
        // default world's frames went from about 83 to 68 ms; on a GPU,
        // whose frames trace in a few ms, the default level would be
        // nearly all of one.
        enc.set_compression(png::Compression::Fast);
        let mut wr = enc.write_header()?;
        wr.write_image_data(rgb)?;
        wr.finish()?;
    }
    Ok(out)
}

#[cfg(test)]
mod tests {
    use super::FrameFiles;

    /// Found by review: an image whose bytes do not fill its size made a
    /// PNG of the header alone, served and kept as a frame. It is an error;
    /// a whole image still encodes and decodes back.
    #[test]
    fn a_short_image_is_an_error_not_a_header_alone() {
        assert!(super::png_bytes(4, 4, &[0u8; 47]).is_err());
        let rgb: Vec<u8> = (0..48).collect();
        let png = super::png_bytes(4, 4, &rgb).unwrap();
        let mut r = png::Decoder::new(std::io::Cursor::new(png))
            .read_info()
            .unwrap();
        let mut back = vec![0; r.output_buffer_size().unwrap()];
        r.next_frame(&mut back).unwrap();
        assert_eq!(back, rgb);
    }

    /// Frames replace by rename, never in place: a frame that already
    /// exists (hard-linked here to a witness) is swapped for a new file, so
    /// a reader never sees a partial one; a failed write leaves neither a
    /// frame nor its temporary file.
    #[test]
    fn frames_are_written_by_rename_never_in_place() {
        let dir = std::env::temp_dir().join(format!("bw-frame-write-{}", std::process::id()));
        let _ = std::fs::remove_dir_all(&dir);
        std::fs::create_dir_all(&dir).unwrap();
        let witness = dir.join("witness");
        std::fs::write(&witness, b"old").unwrap();
        std::fs::hard_link(&witness, dir.join("frame-00000007.png")).unwrap();
        let path = super::write_frame(&dir, 7, b"new frame").unwrap();
        assert_eq!(path, dir.join("frame-00000007.png"));
        assert_eq!(std::fs::read(&path).unwrap(), b"new frame");
        assert_eq!(std::fs::read(&witness).unwrap(), b"old", "written in place");
        // Something at the old fixed temporary name, a link to a user's
        // file, is never written through (regression, odd-paths probe).
        let precious = dir.join("precious");
        std::fs::write(&precious, b"mine").unwrap();
        std::os::unix::fs::symlink(&precious, dir.join(".frame-00000008.png.tmp")).unwrap();
        super::write_frame(&dir, 8, b"frame 8").unwrap();
        assert_eq!(std::fs::read(&precious).unwrap(), b"mine");
        assert_eq!(
            std::fs::read(dir.join("frame-00000008.png")).unwrap(),
            b"frame 8"
        );
        // A write that fails (a folder where the frame goes) fails cleanly,
        // leaving no temporary.
        std::fs::create_dir(dir.join("frame-00000009.png")).unwrap();
        assert!(super::write_frame(&dir, 9, b"x").is_err());
        let left: Vec<String> = std::fs::read_dir(&dir)
            .unwrap()
            .flatten()
            .map(|e| e.file_name().to_string_lossy().to_string())
            .filter(|n| n.contains("00000009") && n.ends_with(".tmp"))
            .collect();
        assert!(left.is_empty(), "{left:?}");
        std::fs::remove_dir_all(&dir).unwrap();
    }

    #[test]
    fn frames_are_pruned_to_a_count_and_to_a_byte_total_oldest_first() {
        let dir = std::env::temp_dir().join(format!("bw-frames-{}", std::process::id()));
        let _ = std::fs::remove_dir_all(&dir);
        std::fs::create_dir_all(&dir).unwrap();
        let name = |t: u32| dir.join(format!("frame-{t:08}.png"));
        for t in 0..5 {
            std::fs::write(name(t), vec![0u8; 100]).unwrap();
        }
        std::fs::write(dir.join("notes.txt"), "not a frame").unwrap();
        let mut f = FrameFiles::scan(&dir);
        assert_eq!(f.totals(), (5, 500));
        // By count.
        f.prune(4, u64::MAX);
        assert!(!name(0).exists() && name(1).exists());
        // By size: a new 250-byte frame under a 400-byte cap leaves 250 + 100.
        std::fs::write(name(5), vec![0u8; 250]).unwrap();
        f.push(name(5), 250);
        f.prune(100, 400);
        assert_eq!(f.totals(), (2, 350));
        assert!(name(4).exists() && name(5).exists() && !name(3).exists());
        // The newest frame stays even when it alone is over the cap.
        f.prune(100, 10);
        assert_eq!(f.totals(), (1, 250));
        assert!(name(5).exists() && dir.join("notes.txt").exists());
        std::fs::remove_dir_all(&dir).unwrap();
    }

    /// Regression (hostile probe): pruning took every `frame-*.png`, so a
    /// user's `frame-holiday.png` in the frames directory was deleted; and
    /// a tick past 8 digits sorted before the older ones.
    #[test]
    fn only_the_engines_own_frames_are_pruned_oldest_tick_first() {
        let dir = std::env::temp_dir().join(format!("bw-frames-own-{}", std::process::id()));
        let _ = std::fs::remove_dir_all(&dir);
        std::fs::create_dir_all(&dir).unwrap();
        let theirs = [
            "frame-holiday.png",
            "frame-.png",
            "frame-1.png",
            "frame-0000001x.png",
            "frame-00000001.png.bak",
            "frame-000000001.png",
        ];
        for n in theirs {
            std::fs::write(dir.join(n), "precious").unwrap();
        }
        std::fs::create_dir(dir.join("frame-00000009.png")).unwrap();
        std::fs::write(dir.join(".frame-00000007.png.tmp"), "half").unwrap();
        std::fs::write(dir.join(".frame-holiday.png.tmp"), "theirs").unwrap();
        for t in [99_999_999u64, 100_000_000, 100_000_001] {
            std::fs::write(dir.join(format!("frame-{t:08}.png")), [0u8; 10]).unwrap();
        }
        let mut f = FrameFiles::scan(&dir);
        assert_eq!(f.totals(), (3, 30));
        f.prune(1, u64::MAX);
        for n in theirs {
            assert!(dir.join(n).exists(), "{n} was deleted");
        }
        assert!(dir.join("frame-100000001.png").exists());
        assert!(
            !dir.join(".frame-00000007.png.tmp").exists(),
            "a half-written frame stayed"
        );
        assert!(dir.join(".frame-holiday.png.tmp").exists());
        assert!(!dir.join("frame-99999999.png").exists());
        assert!(!dir.join("frame-100000000.png").exists());
        std::fs::remove_dir_all(&dir).unwrap();
    }
}
