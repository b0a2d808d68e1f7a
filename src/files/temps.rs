//! Temporary files beside their destinations: made fresh, listed so that an
//! interrupt removes them (see `interrupt`), swept when a gone process left them, and
//! [`Staged`], the write that replaces its destination only on commit
//! (see the parent module).

use std::path::{Path, PathBuf};
use std::sync::atomic::{AtomicU64, Ordering};

/// A new, empty file `.NAME.PID-N.tmp` beside `dest`, opened for writing;
/// created with `create_new`, so it is never a file that was already there.
pub fn fresh_temp_beside(dest: &Path) -> std::io::Result<(PathBuf, std::fs::File)> {
    static NEXT: AtomicU64 = AtomicU64::new(0);
    let dir = match dest.parent() {
        Some(d) if !d.as_os_str().is_empty() => d,
        _ => Path::new("."),
    };
    let name = dest
        .file_name()
        .map(|n| n.to_string_lossy().to_string())
        .unwrap_or_else(|| "out".into());
    // The temporary's name must fit where the destination's does: a name
    // of up to 255 bytes is cut to 200, so `.NAME.PID-N.tmp` stays within
    // the limit (regression, odd-paths probe: a 251-byte name failed with
    // "File name too long", for the temporary's sake).
    let name = match name
        .char_indices()
        .find(|&(i, c)| i + c.len_utf8() > TEMP_NAME_BYTES)
    {
        Some((i, _)) => name[..i].to_string(),
        None => name,
    };
    sweep_stale_temps(dir, &name);
    // Made and listed as one where an interrupt removes temporaries: an
    // interrupt between the two, or one whose handler had already emptied
    // the list, left the file behind (second review: an interrupted
    // `init` left one and its folders, saying all was removed). No caller
    // holds `landing()` here.
    let _listing = super::interrupt::hold_for_listing();
    loop {
        let n = NEXT.fetch_add(1, Ordering::Relaxed);
        let tmp = dir.join(format!(".{name}.{}-{n}.tmp", std::process::id()));
        match std::fs::OpenOptions::new()
            .write(true)
            .create_new(true)
            .open(&tmp)
        {
            Ok(f) => {
                super::interrupt::note_temp(&tmp, dest);
                return Ok((tmp, f));
            }
            Err(e) if e.kind() == std::io::ErrorKind::AlreadyExists => continue,
            Err(e) => return Err(e),
        }
    }
}

/// The most bytes of a destination's name its temporary's name keeps.
const TEMP_NAME_BYTES: usize = 200;

/// Temporary files older than this, of a process that is gone, are removed.
const STALE_TEMP: std::time::Duration = std::time::Duration::from_secs(60);

/// Remove `.NAME.PID-N.tmp` files in `dir` left by a process that no longer
/// runs (killed, or stopped with Ctrl-C, mid-write), once a minute old:
/// without this, every interrupted command left a hidden file for good.
/// Only names of exactly that form are touched, and only where `/proc`
/// says the process is gone.
fn sweep_stale_temps(dir: &Path, name: &str) {
    let Ok(entries) = std::fs::read_dir(dir) else {
        return;
    };
    for e in entries.flatten() {
        let file = e.file_name();
        if file.to_str().and_then(temp_of_gone_process) != Some(name) {
            continue;
        }
        let old = e
            .metadata()
            .ok()
            .filter(|m| m.is_file())
            .and_then(|m| m.modified().ok())
            .and_then(|t| t.elapsed().ok())
            .is_some_and(|age| age > STALE_TEMP);
        if old {
            let _ = std::fs::remove_file(e.path());
        }
    }
}

/// The destination's name, if `file` is a temporary `.NAME.PID-N.tmp` made
/// by [`fresh_temp_beside`] in a process that no longer runs (where
/// `/proc` can say; elsewhere none is).
pub fn temp_of_gone_process(file: &str) -> Option<&str> {
    let rest = file.strip_prefix('.')?.strip_suffix(".tmp")?;
    let (name, tag) = rest.rsplit_once('.')?;
    let (pid, n) = tag.split_once('-')?;
    let digits = |t: &str| !t.is_empty() && t.bytes().all(|b| b.is_ascii_digit());
    let gone = digits(pid)
        && digits(n)
        && pid != std::process::id().to_string()
        && Path::new("/proc/self").exists()
        && !Path::new("/proc").join(pid).exists();
    gone.then_some(name)
}

/// A file being written beside its destination, which it replaces only on
/// [`commit`](Self::commit); dropped uncommitted, it is removed.
#[derive(Debug)]
pub struct Staged {
    tmp: PathBuf,
    dest: PathBuf,
    /// Committed, or written in place (a device or FIFO): nothing to undo.
    done: bool,
}

impl Staged {
    /// Create a fresh, empty temporary file beside `dest` (never one that
    /// exists already).
    pub fn new(dest: &Path) -> std::io::Result<Self> {
        // `out.npy/` names no file: its temporary would be made beside
        // `out.npy` and only the last rename would fail, after other
        // outputs were committed (regression: a failed render replaced
        // its PNG).
        if dest.file_name().is_none() || dest.as_os_str().as_encoded_bytes().ends_with(b"/") {
            return Err(std::io::Error::new(
                std::io::ErrorKind::InvalidInput,
                "not a file name (it ends in '/' or names a folder)",
            ));
        }
        let mut dest = dest.to_path_buf();
        if let Ok(meta) = std::fs::metadata(&dest) {
            if !meta.is_file() {
                // `/dev/null` or a FIFO: written in place, never replaced
                // (renaming over a device node would remove it). A FIFO
                // whose reader left since the command's check would block
                // the write for good: checked again here (review).
                super::hold_fifo_reader(&dest).map_err(std::io::Error::other)?;
                return Ok(Staged {
                    tmp: dest.clone(),
                    dest,
                    done: true,
                });
            }
            // Through a link to the file it names.
            dest = std::fs::canonicalize(&dest)?;
        } else {
            // A dangling link: the file it names is made, as a shell's `>`
            // makes it, and the link stays (regression: it was replaced).
            dest = write_target(&dest)?;
        }
        let (tmp, _) = fresh_temp_beside(&dest)?;
        Ok(Staged {
            tmp,
            dest,
            done: false,
        })
    }

    /// A fresh temporary file beside `dest` that replaces whatever is at
    /// `dest` itself on commit: a link or FIFO there is replaced, never
    /// followed or written into. For the files the engine names inside its
    /// own folders (`chart`'s SVGs), where nothing there is the user's.
    pub fn replacing(dest: &Path) -> std::io::Result<Self> {
        let (tmp, _) = fresh_temp_beside(dest)?;
        Ok(Staged {
            tmp,
            dest: dest.to_path_buf(),
            done: false,
        })
    }

    /// Where to write the content.
    pub fn path(&self) -> &Path {
        &self.tmp
    }

    /// Flush the content to disk and move it over the destination.
    pub fn commit(mut self) -> std::io::Result<()> {
        if self.done {
            return Ok(());
        }
        std::fs::File::open(&self.tmp)?.sync_all()?;
        // Landed and listed as one, for an interrupt (review: one between
        // the two said nothing was written).
        let _landing = super::interrupt::landing();
        std::fs::rename(&self.tmp, &self.dest)?;
        super::interrupt::temp_landed(&self.tmp);
        self.done = true;
        Ok(())
    }
}

fn is_link(p: &Path) -> bool {
    std::fs::symlink_metadata(p).is_ok_and(|m| m.file_type().is_symlink())
}

/// The path a write to `p` makes or replaces: `p`, or where its chain of
/// links ends (the first path in it that is not a link, there or not: a
/// dangling link's file is made). Refused past 40 links, as the OS
/// refuses, and for a loop.
pub(crate) fn write_target(p: &Path) -> std::io::Result<PathBuf> {
    let mut p = p.to_path_buf();
    for _ in 0..40 {
        if !is_link(&p) {
            return Ok(p);
        }
        let target = std::fs::read_link(&p)?;
        p = match p.parent() {
            Some(dir) if target.is_relative() => dir.join(target),
            _ => target,
        };
    }
    Err(std::io::Error::other("too many levels of symbolic links"))
}

impl Drop for Staged {
    fn drop(&mut self) {
        if !self.done {
            let _ = std::fs::remove_file(&self.tmp);
        }
    }
}

#[cfg(test)]
mod tests {
    use super::super::tests::dir;
    use super::*;

    /// `Staged::replacing` replaces a link at its destination instead of
    /// writing through it, and leaves no temporary file.
    #[cfg(unix)]
    #[test]
    fn a_replacing_stage_replaces_a_link_and_never_follows_it() {
        let dir = std::env::temp_dir().join(format!("bw-replacing-{}", std::process::id()));
        let _ = std::fs::remove_dir_all(&dir);
        std::fs::create_dir_all(&dir).unwrap();
        let target = dir.join("target");
        std::fs::write(&target, "mine").unwrap();
        let dest = dir.join("chart.svg");
        std::os::unix::fs::symlink(&target, &dest).unwrap();
        let f = Staged::replacing(&dest).unwrap();
        std::fs::write(f.path(), "new").unwrap();
        f.commit().unwrap();
        assert!(
            std::fs::symlink_metadata(&dest)
                .unwrap()
                .file_type()
                .is_file()
        );
        assert_eq!(std::fs::read_to_string(&dest).unwrap(), "new");
        assert_eq!(std::fs::read_to_string(&target).unwrap(), "mine");
        assert_eq!(std::fs::read_dir(&dir).unwrap().count(), 2);
        std::fs::remove_dir_all(&dir).unwrap();
    }

    /// Regression (hostile probe): a command killed or stopped with Ctrl-C
    /// mid-write left its hidden temporary file for good. The next write to
    /// the same destination removes those of gone processes, once a minute
    /// old, and nothing else.
    #[cfg(target_os = "linux")]
    #[test]
    fn temporaries_of_gone_processes_are_swept_by_the_next_write() {
        let d = dir("sweep");
        let dest = d.join("out.png");
        // A pid no process has: past every live one in /proc.
        let gone = (4_000_000u32..)
            .find(|p| !Path::new("/proc").join(p.to_string()).exists())
            .unwrap();
        let alive = std::process::id(); // this process: never swept
        let old = std::time::SystemTime::now() - std::time::Duration::from_secs(3600);
        let make = |name: String, backdate: bool| {
            let p = d.join(name);
            let f = std::fs::File::create(&p).unwrap();
            if backdate {
                f.set_modified(old).unwrap();
            }
            p
        };
        let stale = make(format!(".out.png.{gone}-0.tmp"), true);
        let recent = make(format!(".out.png.{gone}-1.tmp"), false);
        let mine = make(format!(".out.png.{alive}-999.tmp"), true);
        let other_dest = make(format!(".other.png.{gone}-0.tmp"), true);
        let not_ours = make(format!(".out.png.{gone}-x.tmp"), true);
        let st = Staged::new(&dest).unwrap();
        std::fs::write(st.path(), "new").unwrap();
        st.commit().unwrap();
        assert!(!stale.exists(), "a stale temporary was kept");
        for kept in [&recent, &mine, &other_dest, &not_ours] {
            assert!(kept.exists(), "{} was removed", kept.display());
        }
        assert_eq!(std::fs::read_to_string(&dest).unwrap(), "new");
        let _ = std::fs::remove_dir_all(&d);
    }

    #[test]
    fn a_staged_write_replaces_only_on_commit_and_never_reuses_a_file() {
        let d = dir("stage");
        let dest = d.join("a.png");
        std::fs::write(&dest, "old").unwrap();
        // A file that looks like a temp name is left alone.
        let decoy = d.join(format!(".a.png.{}-0.tmp", std::process::id()));
        std::fs::write(&decoy, "keep").unwrap();
        {
            let s = Staged::new(&dest).unwrap();
            assert_ne!(s.path(), decoy.as_path());
            std::fs::write(s.path(), "new").unwrap();
            // Dropped without a commit: the destination keeps "old".
        }
        assert_eq!(std::fs::read_to_string(&dest).unwrap(), "old");
        assert_eq!(std::fs::read_to_string(&decoy).unwrap(), "keep");
        let s = Staged::new(&dest).unwrap();
        std::fs::write(s.path(), "new").unwrap();
        s.commit().unwrap();
        assert_eq!(std::fs::read_to_string(&dest).unwrap(), "new");
        let left: Vec<_> = std::fs::read_dir(&d).unwrap().flatten().collect();
        assert_eq!(left.len(), 2, "only a.png and the decoy: {left:?}");
        // A device is written in place, not replaced.
        let s = Staged::new(Path::new("/dev/null")).unwrap();
        assert_eq!(s.path(), Path::new("/dev/null"));
        s.commit().unwrap();
        assert!(!std::fs::metadata("/dev/null").unwrap().is_file());
        // A link: the file it names is replaced, the link stays a link.
        #[cfg(unix)]
        {
            let link = d.join("link.png");
            std::os::unix::fs::symlink(&dest, &link).unwrap();
            let s = Staged::new(&link).unwrap();
            std::fs::write(s.path(), "via link").unwrap();
            s.commit().unwrap();
            assert!(
                std::fs::symlink_metadata(&link)
                    .unwrap()
                    .file_type()
                    .is_symlink()
            );
            assert_eq!(std::fs::read_to_string(&dest).unwrap(), "via link");
        }
    }

    /// Regression (nineteenth session's review): `--json` naming a dangling
    /// link replaced the link with a file. The file the link names is made
    /// (through a chain of two links, one relative), and the links stay;
    /// a loop of links is refused and leaves nothing behind.
    #[cfg(unix)]
    #[test]
    fn a_dangling_link_is_written_through_not_replaced() {
        use std::os::unix::fs::symlink;
        let d = dir("dangling");
        std::fs::create_dir_all(d.join("sub")).unwrap();
        let first = d.join("out.json");
        symlink("sub/middle", &first).unwrap();
        symlink("target.json", d.join("sub/middle")).unwrap();
        let s = Staged::new(&first).unwrap();
        std::fs::write(s.path(), "through").unwrap();
        s.commit().unwrap();
        for link in [&first, &d.join("sub/middle")] {
            assert!(is_link(link), "{} is no longer a link", link.display());
        }
        assert_eq!(
            std::fs::read_to_string(d.join("sub/target.json")).unwrap(),
            "through"
        );
        let (a, b) = (d.join("a"), d.join("b"));
        symlink("b", &a).unwrap();
        symlink("a", &b).unwrap();
        assert!(Staged::new(&a).is_err());
        assert!(is_link(&a) && is_link(&b));
        let names: Vec<_> = std::fs::read_dir(&d)
            .unwrap()
            .flatten()
            .map(|e| e.file_name())
            .collect();
        assert_eq!(names.len(), 4, "no temporary left: {names:?}");
        let _ = std::fs::remove_dir_all(&d);
    }
}
