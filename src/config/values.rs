//! Values of the command line, one at a time: sizes, vectors, numbers in
//! ranges, level-of-detail `C`, and output paths. Each error is a
//! [`ConfigError`] naming the flag at fault.

use std::path::Path;

use glam::{DVec3, IVec3};
use thiserror::Error;

/// A flag with a bad value.
#[derive(Debug, Error, PartialEq, Eq)]
#[error("invalid {flag} '{value}': {reason}")]
pub struct ConfigError {
    /// The flag, e.g. `--size`.
    pub flag: &'static str,
    /// The value given.
    pub value: String,
    /// What is wrong with it.
    pub reason: String,
}

pub(super) fn bad(flag: &'static str, value: &str, reason: impl Into<String>) -> ConfigError {
    ConfigError {
        flag,
        value: value.to_string(),
        reason: reason.into(),
    }
}

/// Largest procedural extent along x and z.
pub const MAX_XZ: i32 = 65536;
/// Largest procedural extent along y.
pub const MAX_Y: i32 = 4096;

/// A whole number in decimal, saturated to `i32` (so that one too large
/// for it is refused as out of range, not as "not a whole number").
fn whole_number(t: &str) -> Option<i32> {
    let digits = t.strip_prefix(['-', '+']).unwrap_or(t);
    if digits.is_empty() || !digits.bytes().all(|b| b.is_ascii_digit()) {
        return None;
    }
    Some(match t.parse::<i32>() {
        Ok(n) => n,
        Err(_) if t.starts_with('-') => i32::MIN,
        Err(_) => i32::MAX,
    })
}

/// Parse `XxYxZ`.
pub fn parse_size(s: &str) -> Result<IVec3, ConfigError> {
    let parts: Vec<&str> = s.split(['x', 'X']).collect();
    if parts.len() != 3 {
        return Err(bad("--size", s, "expected XxYxZ, e.g. 512x128x512"));
    }
    let mut v = [0i32; 3];
    for (i, p) in parts.iter().enumerate() {
        v[i] = whole_number(p.trim())
            .ok_or_else(|| bad("--size", s, format!("'{p}' is not a whole number")))?;
    }
    let v = IVec3::from(v);
    if v.min_element() < 8 {
        return Err(bad("--size", s, "every side must be at least 8 voxels"));
    }
    if v.x > MAX_XZ || v.z > MAX_XZ || v.y > MAX_Y {
        return Err(bad(
            "--size",
            s,
            format!("the limit is {MAX_XZ}x{MAX_Y}x{MAX_XZ}"),
        ));
    }
    Ok(v)
}

/// Parse `x,y,z` into a finite vector.
pub fn parse_vec3(flag: &'static str, s: &str) -> Result<DVec3, ConfigError> {
    let parts: Vec<&str> = s.split(',').collect();
    if parts.len() != 3 {
        return Err(bad(flag, s, "expected x,y,z"));
    }
    let mut v = [0f64; 3];
    for (i, p) in parts.iter().enumerate() {
        let x: f64 = p
            .trim()
            .parse()
            .map_err(|_| bad(flag, s, format!("'{p}' is not a number")))?;
        if !x.is_finite() {
            return Err(bad(flag, s, "coordinates must be finite (no NaN or inf)"));
        }
        if x.abs() > 1e9 {
            return Err(bad(flag, s, "coordinates must be within ±1e9 voxels"));
        }
        v[i] = x;
    }
    Ok(DVec3::from(v))
}

/// `bench sim --sizes`: world sides, each a multiple of 8 in 8..=8192
/// (regression, hostile probe: clap's own parse said "4294967296 is not
/// in -2147483648..=2147483647").
pub fn parse_sim_sizes(sizes: &[String]) -> Result<Vec<i32>, ConfigError> {
    if sizes.is_empty() {
        return Err(bad("--sizes", "", "name at least one size"));
    }
    sizes
        .iter()
        .map(|s| {
            let v = parse_num("--sizes", s, 8i32, 8192)?;
            if v % 8 != 0 {
                return Err(bad("--sizes", s, "must be a multiple of 8"));
            }
            Ok(v)
        })
        .collect()
}

pub(super) fn parse_num<T>(flag: &'static str, s: &str, lo: T, hi: T) -> Result<T, ConfigError>
where
    T: std::str::FromStr + PartialOrd + std::fmt::Display + Copy,
{
    let v: T = s.trim().parse().map_err(|_| {
        // A number the type cannot hold (4294967296 for a u32, 1.5 for a
        // count) is out of range, not "not a number" (regression).
        match s.trim().parse::<f64>() {
            Ok(x) if x.is_finite() => bad(flag, s, format!("must be in {lo}..={hi}")),
            _ => bad(flag, s, "not a number"),
        }
    })?;
    if !(v >= lo && v <= hi) {
        return Err(bad(flag, s, format!("must be in {lo}..={hi}")));
    }
    Ok(v)
}

/// Refuse an output name whose extension promises another format than the
/// one written (`--out view.jpg` used to get PNG bytes). A name without an
/// extension is accepted.
pub fn check_extension(flag: &'static str, path: &Path, ext: &str) -> Result<(), ConfigError> {
    match path.extension().and_then(|e| e.to_str()) {
        Some(e) if !e.eq_ignore_ascii_case(ext) => Err(bad(
            flag,
            &path.display().to_string(),
            format!("only .{ext} is written here: name the file with .{ext}"),
        )),
        _ => Ok(()),
    }
}

/// A benchmark's `--json` and `--chart` outputs, checked before any work:
/// two distinct files (regression: one path for both left only the chart,
/// with exit 0), a chart named `.svg`, and each in a folder that exists and
/// not itself a folder (regression: found only after the whole run).
pub fn check_bench_outputs(json: &Path, chart: Option<&Path>) -> Result<(), ConfigError> {
    let placed = check_output;
    placed("--json", json)?;
    if let Some(chart) = chart {
        if same_file(chart, json) {
            return Err(bad(
                "--chart",
                &chart.display().to_string(),
                "is also --json: the chart would overwrite the results; name two files",
            ));
        }
        check_extension("--chart", chart, "svg")?;
        placed("--chart", chart)?;
    }
    Ok(())
}

/// An output file `p` (given with `flag`) can be made: it names a file,
/// not a folder (nor ends in '/'), in a folder that exists, and if it is a
/// FIFO, something reads it. Checked before the work, so that a run is not
/// lost to its output's path.
pub fn check_output(flag: &'static str, p: &Path) -> Result<(), ConfigError> {
    let shown = p.display().to_string();
    if p.is_dir() || p.as_os_str().as_encoded_bytes().ends_with(b"/") {
        return Err(bad(flag, &shown, "is a folder: name a file"));
    }
    // A FIFO is written in place, as a pipe to its reader; with none, the
    // write would wait for good (regression, hostile probe: `render`,
    // `sim`, `verify` and `soak` hung at their end, their results lost).
    if let Err(e) = crate::files::hold_fifo_reader(p) {
        return Err(bad(flag, &shown, e.to_string()));
    }
    // Through links: a dangling link's file is the one to be made.
    let target = crate::files::write_target(p).map_err(|e| {
        bad(
            flag,
            &shown,
            format!("is a link that cannot be followed: {e}"),
        )
    })?;
    match target.parent() {
        Some(dir) if !dir.as_os_str().is_empty() && !dir.is_dir() => Err(bad(
            flag,
            &shown,
            format!("its folder {} does not exist", dir.display()),
        )),
        _ => Ok(()),
    }
}

/// `out` (given with `flag`) is none of the command's `inputs` (each named
/// by what it is): an output over an input destroys what the command read
/// (regression, odd-paths probe: `render --scene heightmap:in.png --out
/// in.png` replaced the heightmap with its render, `export` wrote a backup
/// over the world config it was given).
pub fn not_an_input(
    flag: &'static str,
    out: &Path,
    inputs: &[(&str, &Path)],
) -> Result<(), ConfigError> {
    for (what, input) in inputs {
        if same_file(out, input) {
            return Err(bad(
                flag,
                &out.display().to_string(),
                format!("is the {what} this command reads: name another file"),
            ));
        }
    }
    Ok(())
}

/// Whether `a` and `b` name the same file (by identity where both exist,
/// else by their resolved paths).
pub fn same_file(a: &Path, b: &Path) -> bool {
    let resolved = |p: &Path| {
        // A dangling link names the file it will make (regression, review:
        // two outputs linking to one missing file were both written there).
        let target = crate::files::write_target(p).ok()?;
        let p = target.as_path();
        let dir = match p.parent() {
            Some(d) if !d.as_os_str().is_empty() => d,
            _ => Path::new("."),
        };
        Some(dir.canonicalize().ok()?.join(p.file_name()?))
    };
    #[cfg(unix)]
    if let (Ok(x), Ok(y)) = (std::fs::metadata(a), std::fs::metadata(b)) {
        use std::os::unix::fs::MetadataExt;
        return (x.dev(), x.ino()) == (y.dev(), y.ino());
    }
    a == b || matches!((resolved(a), resolved(b)), (Some(x), Some(y)) if x == y)
}

/// Largest level-of-detail `C`, in pixels.
pub const MAX_LOD: f64 = 256.0;
/// Smallest level-of-detail `C`, in pixels (smaller ones would round to an
/// exact trace unannounced).
pub const MIN_LOD: f64 = 0.01;

/// Whether `c` is a level-of-detail `C` in [`MIN_LOD`]..=[`MAX_LOD`].
pub fn lod_in_range(c: f64) -> bool {
    c.is_finite() && (MIN_LOD..=MAX_LOD).contains(&c)
}

/// Validate a level-of-detail `C` given as `flag`.
pub fn lod_c(flag: &'static str, c: f64) -> Result<f32, ConfigError> {
    if lod_in_range(c) {
        Ok(c as f32)
    } else {
        Err(bad(
            flag,
            &crate::sim::fmt_num(c),
            format!(
                "expected a cell footprint in pixels from {MIN_LOD} to {MAX_LOD} (leave it out for exact tracing)"
            ),
        ))
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// The documented bounds of `C`, at their edges (audit: only 1e9 and
    /// 1e-50 were tried).
    #[test]
    fn lod_c_accepts_its_bounds_and_refuses_just_past_them() {
        assert!(lod_c("--lod", 0.01).is_ok());
        assert!(lod_c("--lod", 256.0).is_ok());
        assert!(lod_c("--lod", 0.0099).is_err());
        assert!(lod_c("--lod", 256.001).is_err());
    }

    #[test]
    fn sizes_parse_and_bad_ones_name_the_flag() {
        assert_eq!(
            parse_size("512x128x256").unwrap(),
            IVec3::new(512, 128, 256)
        );
        for s in ["512x128", "axbxc", "4x8x8", "100000x8x8", "-8x8x8", ""] {
            let e = parse_size(s).unwrap_err();
            assert_eq!(e.flag, "--size", "{s}");
        }
    }

    /// Regression (hostile probe): a side too large for 32 bits was said
    /// not to be a whole number.
    #[test]
    fn a_size_past_32_bits_is_out_of_range_not_malformed() {
        for (s, says) in [
            ("64x64x99999999999", "the limit is"),
            ("64x64x99999999999999999999999", "the limit is"),
            ("64x-99999999999x64", "at least 8"),
            ("64x1e3x64", "'1e3' is not a whole number"),
            ("64x+x64", "'+' is not a whole number"),
        ] {
            let e = parse_size(s).unwrap_err().to_string();
            assert!(e.contains(says), "{s}: {e}");
        }
        assert_eq!(parse_size("+64x 64x64").unwrap(), IVec3::splat(64));
    }

    /// A dangling link is checked where it leads: its target's folder must
    /// exist, and a loop of links is refused before the work.
    #[cfg(unix)]
    #[test]
    fn an_output_at_a_dangling_link_is_checked_where_it_leads() {
        use std::os::unix::fs::symlink;
        let d = std::env::temp_dir().join(format!("bw-out-link-{}", std::process::id()));
        let _ = std::fs::remove_dir_all(&d);
        std::fs::create_dir_all(&d).unwrap();
        symlink("r.json", d.join("ok.json")).unwrap();
        assert!(check_output("--json", &d.join("ok.json")).is_ok());
        symlink("nowhere/r.json", d.join("lost.json")).unwrap();
        let e = check_output("--json", &d.join("lost.json")).unwrap_err();
        assert!(e.to_string().contains("does not exist"), "{e}");
        symlink("b", d.join("a")).unwrap();
        symlink("a", d.join("b")).unwrap();
        let e = check_output("--json", &d.join("a")).unwrap_err();
        assert!(e.to_string().contains("cannot be followed"), "{e}");
        // Two dangling links to one file are one output (review).
        symlink("t.out", d.join("l1.json")).unwrap();
        symlink("./t.out", d.join("l2.svg")).unwrap();
        let e = check_bench_outputs(&d.join("l1.json"), Some(&d.join("l2.svg"))).unwrap_err();
        assert!(e.to_string().contains("is also --json"), "{e}");
        assert!(same_file(&d.join("l1.json"), &d.join("t.out")));
        assert!(!same_file(&d.join("l1.json"), &d.join("ok.json")));
        let _ = std::fs::remove_dir_all(&d);
    }

    #[test]
    fn vectors_reject_nan_and_wrong_arity() {
        assert_eq!(
            parse_vec3("--eye", "1,-2.5,3").unwrap(),
            DVec3::new(1.0, -2.5, 3.0)
        );
        for s in ["NaN,0,0", "1,2", "inf,0,0", "a,b,c", "1,2,3,4"] {
            assert_eq!(parse_vec3("--eye", s).unwrap_err().flag, "--eye", "{s}");
        }
    }
}
