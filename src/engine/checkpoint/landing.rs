//! Where `brickworld export` may land its backup, and how: nothing at the
//! path, or an earlier backup of the same world that verifies
//! ([`backup_target`]); landed on a free path without replacing a file made
//! meanwhile, and over an earlier backup by swapping names with exactly
//! the file that was checked ([`write_backup`]).

use std::fs;
use std::path::Path;

use super::file::{read_checked, write_landing};
use super::{CheckpointError, MAGIC, WorldIdentity, WorldRef};

/// What an export may write over: the path is free, or holds an earlier
/// backup of the same world (or an empty file).
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum BackupTarget {
    /// Nothing is at the path.
    Free,
    /// An earlier backup of the same world, or an empty file.
    Replaceable,
}

/// Whether a backup of `identity` may be written at `path`: nothing there,
/// an empty file, or a backup of the same world that verifies. Anything
/// else is kept, and the error says why and what to do (regression,
/// newcomer walk and its review: `export notes.txt` replaced the notes,
/// and an export replaced another world's only backup, exit 0).
pub fn backup_target(path: &Path, identity: &WorldIdentity) -> Result<BackupTarget, String> {
    let keep = |what: String| {
        format!("{what}: export would replace it, so name another path or remove it first")
    };
    let meta = match fs::symlink_metadata(path) {
        Err(e) if e.kind() == std::io::ErrorKind::NotFound => return Ok(BackupTarget::Free),
        Err(e) => return Err(format!("cannot be written ({e})")),
        Ok(m) => m,
    };
    if meta.file_type().is_symlink() {
        return Err(
            "is a symbolic link, which the backup would replace: name the file itself".into(),
        );
    }
    if !meta.is_file() {
        return Err("is not a regular file: name another path".into());
    }
    if meta.len() == 0 {
        return Ok(BackupTarget::Replaceable);
    }
    if meta.len() < MAGIC.len() as u64 {
        return Err(keep("is not a brickworld backup".into()));
    }
    match read_checked(path, false) {
        Ok((_, Some(id))) if id.same_world(identity) => Ok(BackupTarget::Replaceable),
        Ok((_, Some(id))) => Err(keep(format!("is a backup of another world ({id})"))),
        Ok((_, None)) => Err(keep(
            "is a checkpoint that does not say which world it is".into(),
        )),
        Err(CheckpointError::NotACheckpoint { .. }) => {
            Err(keep("is not a brickworld backup".into()))
        }
        Err(CheckpointError::Io { error, .. }) => Err(keep(format!("cannot be read ({error})"))),
        Err(CheckpointError::Corrupt { msg, .. }) => {
            Err(keep(format!("is a damaged backup ({msg})")))
        }
    }
}

/// `brickworld export`'s write: [`write_at`](super::write_at), with the target looked at
/// again just before the backup lands (see [`backup_target`]). Where the
/// path was free, it lands without replacing anything, so a file made
/// there meanwhile is kept. Over an earlier backup, it replaces exactly
/// the file that was checked: [`land_over`] swaps it out atomically and
/// swaps back anything else found there.
pub fn write_backup(
    path: &Path,
    state: WorldRef<'_>,
    identity: &WorldIdentity,
) -> Result<u64, CheckpointError> {
    write_landing(path, state, |tmp| {
        let before = Seen::of(path);
        match backup_target(path, identity) {
            Ok(BackupTarget::Replaceable) => match before {
                // Unchanged while it was checked: that is the file replaced.
                Ok(before) if Seen::of(path).is_ok_and(|after| after == before) => {
                    land_over(tmp, path, &before)
                }
                _ => Err(replaced_meanwhile()),
            },
            Ok(BackupTarget::Free) => {
                // Under the landing's lock, the flag set before it is
                // released: an interrupt between the rename and the flag
                // exited 130 with the backup in place (review).
                let _landing = crate::files::landing();
                land_on_free(tmp, path).inspect(|()| crate::files::output_landed(path))
            }
            Err(msg) => Err(std::io::Error::new(std::io::ErrorKind::AlreadyExists, msg)),
        }
        .inspect(|()| {
            crate::files::output_landed(path);
            // `BRICKWORLD_TEST_LANDED_STALL_MS`: a pause once the backup
            // has landed, so a test can interrupt the export there. Unset
            // in normal use.
            if let Some(ms) = std::env::var("BRICKWORLD_TEST_LANDED_STALL_MS")
                .ok()
                .and_then(|v| v.parse().ok())
            {
                std::thread::sleep(std::time::Duration::from_millis(ms));
            }
        })
    })
    .map_err(|e| match e {
        CheckpointError::Io { error, .. } if error.kind() == std::io::ErrorKind::AlreadyExists => {
            CheckpointError::Io {
                path: path.to_path_buf(),
                error: std::io::Error::new(
                    std::io::ErrorKind::AlreadyExists,
                    format!("{error}; nothing was written"),
                ),
            }
        }
        other => other,
    })
}

/// What tells one file from another that took its place: the same inode,
/// with the same size and modification time.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
struct Seen {
    dev: u64,
    ino: u64,
    len: u64,
    mtime: (i64, i64),
}

impl Seen {
    fn of(path: &Path) -> std::io::Result<Seen> {
        use std::os::unix::fs::MetadataExt;
        let m = fs::symlink_metadata(path)?;
        Ok(Seen {
            dev: m.dev(),
            ino: m.ino(),
            len: m.len(),
            mtime: (m.mtime(), m.mtime_nsec()),
        })
    }
}

fn replaced_meanwhile() -> std::io::Error {
    std::io::Error::new(
        std::io::ErrorKind::AlreadyExists,
        "the earlier backup there was replaced or changed while this one was made",
    )
}

/// `NAME.kept-PID` beside `path`: where another's file goes when the
/// backup has taken its place and it cannot go back.
fn kept_name(path: &Path) -> std::path::PathBuf {
    let mut name = path.file_name().unwrap_or_default().to_os_string();
    name.push(format!(".kept-{}", std::process::id()));
    path.with_file_name(name)
}

/// A failed swap back left another's file at the temporary path, or moved
/// it beside: [`write_landing`] must not remove
/// the temporary.
#[derive(Debug)]
pub(super) struct AnothersFile(String);

impl std::fmt::Display for AnothersFile {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.write_str(&self.0)
    }
}

impl std::error::Error for AnothersFile {}

/// Move `tmp` over `path`, replacing only the file `checked` saw there.
/// Where the system can swap two names atomically (`renameat2` with
/// `RENAME_EXCHANGE`), the backup swaps places with what is at `path`,
/// which is then looked at: the checked file is removed; anything else (a
/// file put there since the check) is swapped back and kept, and nothing
/// is written. Elsewhere a plain rename follows the last look.
fn land_over(tmp: &Path, path: &Path, checked: &Seen) -> std::io::Result<()> {
    // An interrupt waits for the whole landing, and finds the output
    // landed once it has (review: the plain-rename and free-path landings
    // set the flag after the lock was released).
    let _landing = crate::files::landing();
    let landed = |r: std::io::Result<()>| r.inspect(|()| crate::files::output_landed(path));
    #[cfg(all(target_os = "linux", target_env = "gnu"))]
    {
        use nix::fcntl::{AT_FDCWD, RenameFlags, renameat2};
        let swap = || renameat2(AT_FDCWD, tmp, AT_FDCWD, path, RenameFlags::RENAME_EXCHANGE);
        // From the swap on, `tmp` may name another's file: an interrupt
        // waits until it is settled (`_landing`, held to the end), and then
        // must not remove it (review: a Ctrl-C just after the swap did).
        crate::files::temp_landed(tmp);
        match swap() {
            Ok(()) => {
                // `tmp` now names what was at `path`.
                if Seen::of(tmp).is_ok_and(|s| s == *checked) {
                    // Landed: said under the landing's lock, before the
                    // earlier backup (perhaps large) is removed.
                    crate::files::output_landed(path);
                    let _ = fs::remove_file(tmp);
                    return Ok(());
                }
                // Another file: give it its name back; `tmp` is the
                // backup again, which the caller removes.
                if swap().is_ok() {
                    crate::files::temp_writing(tmp);
                    return Err(replaced_meanwhile());
                }
                // The backup has gone from `path` since: theirs goes back.
                if land_on_free(tmp, path).is_ok() {
                    return Err(replaced_meanwhile());
                }
                // The backup is at `path`, and theirs cannot go back: it
                // is kept under a name no sweep of temporaries takes
                // (review: it stayed at the temporary's name, which the
                // next export to this path removed).
                let kept = kept_name(path);
                let at = match land_on_free(tmp, &kept) {
                    Ok(()) => format!("it is kept as {}", kept.display()),
                    Err(_) => format!(
                        "it is kept at {} (a temporary's name, which a later export to this path removes: move it)",
                        tmp.display()
                    ),
                };
                return Err(std::io::Error::other(AnothersFile(format!(
                    "a file was put at {0} while the backup was made, and could not be put back: {at}; the backup is at {0}",
                    path.display()
                ))));
            }
            // The checked file has gone: the path is free.
            Err(nix::errno::Errno::ENOENT) => {
                crate::files::temp_writing(tmp);
                return landed(land_on_free(tmp, path));
            }
            // No atomic swap here: the last look stands.
            Err(_) => crate::files::temp_writing(tmp),
        }
    }
    match Seen::of(path) {
        Ok(s) if s == *checked => landed(fs::rename(tmp, path)),
        Err(e) if e.kind() == std::io::ErrorKind::NotFound => landed(land_on_free(tmp, path)),
        _ => Err(replaced_meanwhile()),
    }
}

/// Move `tmp` to the free path `path` without replacing a file that
/// appeared there since: a rename that refuses to replace where the
/// system has one, else a hard link (made only where nothing is), else,
/// on a file system with neither, a plain rename.
fn land_on_free(tmp: &Path, path: &Path) -> std::io::Result<()> {
    let appeared = || {
        std::io::Error::new(
            std::io::ErrorKind::AlreadyExists,
            "a file appeared there while the backup was made",
        )
    };
    #[cfg(all(target_os = "linux", target_env = "gnu"))]
    {
        use nix::fcntl::{AT_FDCWD, RenameFlags, renameat2};
        match renameat2(AT_FDCWD, tmp, AT_FDCWD, path, RenameFlags::RENAME_NOREPLACE) {
            Ok(()) => return Ok(()),
            Err(nix::errno::Errno::EEXIST) => return Err(appeared()),
            // Not supported here: try a hard link.
            Err(_) => {}
        }
    }
    match fs::hard_link(tmp, path) {
        Ok(()) => {
            let _ = fs::remove_file(tmp);
            Ok(())
        }
        Err(e) if e.kind() == std::io::ErrorKind::AlreadyExists => Err(appeared()),
        Err(_) => fs::rename(tmp, path),
    }
}

#[cfg(test)]
mod tests {
    use super::{Seen, land_on_free, land_over};

    /// Over an earlier backup, only the file that was checked is replaced:
    /// one put in its place since, or changed in place, is kept and the
    /// backup stays in its temporary (gap: the look just before a plain
    /// rename was the last check); the checked file, unchanged, is
    /// replaced and leaves nothing behind; gone, the path is free.
    #[test]
    fn landing_over_a_backup_replaces_only_the_file_that_was_checked() {
        let dir = std::env::temp_dir().join(format!("bw-over-{}", std::process::id()));
        let _ = std::fs::remove_dir_all(&dir);
        std::fs::create_dir_all(&dir).unwrap();
        let (tmp, path) = (dir.join(".b.tmp"), dir.join("b.bwc"));
        let read = |p: &std::path::Path| std::fs::read_to_string(p).unwrap();
        std::fs::write(&tmp, "new backup").unwrap();
        std::fs::write(&path, "old backup").unwrap();
        // Another file renamed into its place.
        let checked = Seen::of(&path).unwrap();
        std::fs::write(dir.join("other"), "put there meanwhile").unwrap();
        std::fs::rename(dir.join("other"), &path).unwrap();
        let e = land_over(&tmp, &path, &checked).unwrap_err();
        assert_eq!(e.kind(), std::io::ErrorKind::AlreadyExists, "{e}");
        assert_eq!(read(&path), "put there meanwhile");
        assert_eq!(read(&tmp), "new backup");
        // The same file, changed in place.
        let checked = Seen::of(&path).unwrap();
        std::fs::write(&path, "put there meanwhile, then edited").unwrap();
        assert!(land_over(&tmp, &path, &checked).is_err());
        assert_eq!(read(&path), "put there meanwhile, then edited");
        assert_eq!(read(&tmp), "new backup");
        // Unchanged since the check: replaced, and nothing is left over.
        let checked = Seen::of(&path).unwrap();
        land_over(&tmp, &path, &checked).unwrap();
        assert_eq!(read(&path), "new backup");
        let names: Vec<_> = std::fs::read_dir(&dir)
            .unwrap()
            .map(|e| e.unwrap().file_name())
            .collect();
        assert_eq!(names, vec![std::ffi::OsString::from("b.bwc")]);
        // Gone since the check: the backup lands on the free path.
        std::fs::write(&tmp, "newer backup").unwrap();
        let checked = Seen::of(&path).unwrap();
        std::fs::remove_file(&path).unwrap();
        land_over(&tmp, &path, &checked).unwrap();
        assert_eq!(read(&path), "newer backup");
        assert!(!tmp.exists());
        let _ = std::fs::remove_dir_all(&dir);
    }

    /// A file made at the export's path while the backup was being made
    /// is kept, and the backup stays in its temporary (review: it was
    /// replaced, exit 0); where the path is still free, the backup lands.
    #[test]
    fn landing_on_a_free_path_never_replaces_a_file_made_meanwhile() {
        let dir = std::env::temp_dir().join(format!("bw-land-{}", std::process::id()));
        let _ = std::fs::remove_dir_all(&dir);
        std::fs::create_dir_all(&dir).unwrap();
        let (tmp, path) = (dir.join(".b.tmp"), dir.join("b.bwc"));
        std::fs::write(&tmp, "backup").unwrap();
        std::fs::write(&path, "notes made meanwhile").unwrap();
        let e = land_on_free(&tmp, &path).unwrap_err();
        assert_eq!(e.kind(), std::io::ErrorKind::AlreadyExists, "{e}");
        assert_eq!(
            std::fs::read_to_string(&path).unwrap(),
            "notes made meanwhile"
        );
        assert_eq!(std::fs::read_to_string(&tmp).unwrap(), "backup");
        std::fs::remove_file(&path).unwrap();
        land_on_free(&tmp, &path).unwrap();
        assert_eq!(std::fs::read_to_string(&path).unwrap(), "backup");
        assert!(!tmp.exists());
        let _ = std::fs::remove_dir_all(&dir);
    }
}
