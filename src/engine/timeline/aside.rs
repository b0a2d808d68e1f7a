//! Timelines set aside: a file whose header differs is renamed
//! `timeline.<unix seconds>.csv` beside the current one, and those files
//! are pruned, oldest first, past [`ASIDE_BYTES`] together or
//! [`ASIDE_FILES`], so a world left running for days keeps a bounded
//! timeline.

use std::path::Path;

use super::ROTATE_BYTES;

/// A free name beside `path` for a timeline set aside:
/// `timeline.<unix seconds>.csv` (a second one in the same second must not
/// overwrite the first).
pub(super) fn aside_path(path: &Path) -> std::path::PathBuf {
    let secs = std::time::SystemTime::now()
        .duration_since(std::time::UNIX_EPOCH)
        .map_or(0, |d| d.as_secs());
    let mut aside = path.with_extension(format!("{secs}.csv"));
    let mut n = 1;
    while aside.exists() {
        aside = path.with_extension(format!("{secs}-{n}.csv"));
        n += 1;
    }
    aside
}

/// Files set aside (`timeline.<secs>.csv`) kept together at most: past
/// this, the oldest are deleted (the newest is always kept). With the
/// rotation this bounds a timeline's files at about three times
/// [`ROTATE_BYTES`] (regression, long-run probe: every reload that changed
/// a script's columns kept a file aside, up to 32 MiB each, for ever).
pub const ASIDE_BYTES: u64 = ROTATE_BYTES;
/// Files set aside kept at most, however small.
pub const ASIDE_FILES: usize = 64;

/// The (seconds, number) a file set aside beside `path` is named by
/// (`timeline.<secs>.csv`, `timeline.<secs>-<n>.csv`), or None for any
/// other file, `timeline.1.csv` (the rotation's) included.
fn aside_key(path: &Path, name: &str) -> Option<(u64, u64)> {
    let stem = path.file_stem()?.to_str()?;
    let rest = name.strip_prefix(stem)?.strip_prefix('.')?;
    let rest = rest.strip_suffix(".csv")?;
    let (secs, n) = rest.split_once('-').unwrap_or((rest, "0"));
    let all_digits = |t: &str| !t.is_empty() && t.bytes().all(|b| b.is_ascii_digit());
    if !all_digits(secs) || !all_digits(n) || rest == "1" {
        return None;
    }
    Some((secs.parse().ok()?, n.parse().ok()?))
}

/// Delete the oldest files set aside beside `path` until those left
/// weigh at most [`ASIDE_BYTES`] and number at most [`ASIDE_FILES`]; the
/// newest stays whatever its size. Errors are ignored (the timeline must
/// never stop the engine).
pub(super) fn prune_aside(path: &Path) {
    let Some(dir) = path.parent() else { return };
    let Ok(entries) = std::fs::read_dir(if dir.as_os_str().is_empty() {
        Path::new(".")
    } else {
        dir
    }) else {
        return;
    };
    let mut aside: Vec<((u64, u64), std::path::PathBuf, u64)> = entries
        .flatten()
        .filter_map(|e| {
            let key = aside_key(path, e.file_name().to_str()?)?;
            let meta = e.metadata().ok().filter(|m| m.is_file())?;
            Some((key, e.path(), meta.len()))
        })
        .collect();
    // Newest first.
    aside.sort_by_key(|b| std::cmp::Reverse(b.0));
    let mut kept = 0u64;
    for (i, (_, file, len)) in aside.iter().enumerate() {
        kept += len;
        if i > 0 && (kept > ASIDE_BYTES || i >= ASIDE_FILES) {
            let _ = std::fs::remove_file(file);
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// Regression (long-run probe): files set aside were never deleted, so
    /// a researcher's reloads that changed a script's columns kept up to
    /// 32 MiB each for ever. The oldest go past `ASIDE_BYTES` together
    /// or `ASIDE_FILES`; the newest, the current file, its rotation and
    /// other files stay.
    #[test]
    fn files_set_aside_are_pruned_oldest_first() {
        let dir = std::env::temp_dir().join(format!("bw-timeline-prune-{}", std::process::id()));
        let _ = std::fs::remove_dir_all(&dir);
        std::fs::create_dir_all(&dir).unwrap();
        let path = dir.join("timeline.csv");
        let third = (ASIDE_BYTES / 3 + 1) as usize;
        for (name, len) in [
            ("timeline.1700000000.csv", third),
            ("timeline.1700000001.csv", third),
            ("timeline.1700000001-1.csv", third),
            ("timeline.1700000002.csv", third),
            ("timeline.1.csv", 10),
            ("timeline.csv", 10),
            ("timeline.notes.csv", 10),
        ] {
            std::fs::write(dir.join(name), vec![b'x'; len]).unwrap();
        }
        prune_aside(&path);
        let mut left: Vec<String> = std::fs::read_dir(&dir)
            .unwrap()
            .map(|e| e.unwrap().file_name().into_string().unwrap())
            .collect();
        left.sort();
        assert_eq!(
            left,
            [
                "timeline.1.csv",
                "timeline.1700000001-1.csv",
                "timeline.1700000002.csv",
                "timeline.csv",
                "timeline.notes.csv"
            ]
        );
        // The newest stays even when it alone is over the bound.
        std::fs::write(
            dir.join("timeline.1700000003.csv"),
            vec![b'x'; ASIDE_BYTES as usize + 1],
        )
        .unwrap();
        prune_aside(&path);
        assert!(dir.join("timeline.1700000003.csv").exists());
        assert!(!dir.join("timeline.1700000002.csv").exists());
        // Many small ones: at most ASIDE_FILES.
        for i in 0..ASIDE_FILES + 5 {
            std::fs::write(dir.join(format!("timeline.{}.csv", 1800000000 + i)), b"x").unwrap();
        }
        prune_aside(&path);
        let n = std::fs::read_dir(&dir)
            .unwrap()
            .filter(|e| {
                aside_key(&path, e.as_ref().unwrap().file_name().to_str().unwrap()).is_some()
            })
            .count();
        assert_eq!(n, ASIDE_FILES);
        let _ = std::fs::remove_dir_all(&dir);
    }
}
