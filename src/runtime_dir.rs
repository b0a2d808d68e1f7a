//! A private `XDG_RUNTIME_DIR` when the environment lacks a usable one.
//!
//! Mesa's Vulkan drivers (lavapipe included) print `error: XDG_RUNTIME_DIR
//! is invalid or not set in the environment` on every device they open when
//! the variable is missing, which reads like a failure to a new user. When
//! it is unset, empty or not a directory, [`ensure`] creates
//! `TMPDIR/brickworld-runtime-UID` (mode 0700, owned by the user; an
//! existing one is used only if it is exactly that) and re-executes the
//! program with the variable set: changing the environment of a running
//! process is `unsafe` in Rust 2024, and `exec` is not. The re-executed
//! process finds the variable valid and goes on; if anything fails, the
//! program simply goes on without it (the noise is harmless).

use std::path::{Path, PathBuf};

/// Marks the re-executed process, so that it never loops.
const MARK: &str = "BRICKWORLD_RUNTIME_DIR_SET";

/// Whether `v` names a usable runtime directory.
pub fn usable(v: Option<&std::ffi::OsStr>) -> bool {
    v.is_some_and(|v| !v.is_empty() && Path::new(v).is_dir())
}

/// See the module docs. Call first thing in `main`, before any thread.
pub fn ensure() {
    if usable(std::env::var_os("XDG_RUNTIME_DIR").as_deref()) || std::env::var_os(MARK).is_some() {
        return;
    }
    #[cfg(unix)]
    if let Some(dir) = private_dir() {
        use std::os::unix::process::CommandExt;
        let Ok(exe) = std::env::current_exe() else {
            return;
        };
        // Returns only if the exec failed: then go on without the variable.
        let _ = std::process::Command::new(exe)
            .args(std::env::args_os().skip(1))
            .env("XDG_RUNTIME_DIR", dir)
            .env(MARK, "1")
            .exec();
    }
}

/// `TMPDIR/brickworld-runtime-UID`, created 0700, or `None` if it exists
/// and is not a directory of ours that only we can read.
#[cfg(unix)]
pub fn private_dir() -> Option<PathBuf> {
    use std::os::unix::fs::{DirBuilderExt, MetadataExt, PermissionsExt};
    let uid = std::fs::metadata("/proc/self").ok()?.uid();
    let dir = std::env::temp_dir().join(format!("brickworld-runtime-{uid}"));
    let _ = std::fs::DirBuilder::new().mode(0o700).create(&dir);
    let m = std::fs::symlink_metadata(&dir).ok()?;
    (m.is_dir() && m.uid() == uid && m.permissions().mode() & 0o077 == 0).then_some(dir)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn a_missing_empty_or_file_runtime_dir_is_unusable() {
        assert!(!usable(None));
        assert!(!usable(Some("".as_ref())));
        assert!(!usable(Some("/nonexistent/brickworld".as_ref())));
        assert!(!usable(Some("/proc/self/status".as_ref())));
        assert!(usable(Some(std::env::temp_dir().as_os_str())));
    }

    #[cfg(unix)]
    #[test]
    fn the_private_dir_is_ours_and_closed_to_others() {
        use std::os::unix::fs::PermissionsExt;
        let d = private_dir().expect("a private runtime directory");
        let mode = std::fs::metadata(&d).unwrap().permissions().mode();
        assert_eq!(mode & 0o077, 0, "{} is open to others", d.display());
    }
}
