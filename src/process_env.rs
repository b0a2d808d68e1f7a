//! The environment the process runs in, set up before any thread starts.
//!
//! Changing the environment of a running process is `unsafe` in Rust 2024,
//! and `exec` is not: when something below is missing, [`ensure`]
//! re-executes the program once with all of it set (a marker variable
//! keeps it from looping). If anything fails, the program goes on as it
//! is; both settings are improvements, not requirements.
//! - **A private `XDG_RUNTIME_DIR`.** Mesa's Vulkan drivers (lavapipe
//!   included) print `error: XDG_RUNTIME_DIR is invalid or not set in the
//!   environment` on every device they open when the variable is missing,
//!   which reads like a failure to a new user. When it is unset, empty or
//!   not a directory, `TMPDIR/brickworld-runtime-UID` is created (mode
//!   0700, owned by the user; an existing one is used only if it is
//!   exactly that).
//! - **A fixed mmap threshold for the engine** (`run` and `soak`, on
//!   glibc): `MALLOC_MMAP_THRESHOLD_=131072`, unless the user set it or a
//!   `GLIBC_TUNABLES` mmap threshold. glibc raises its threshold each time
//!   a large block is freed (up to 32 MiB), after which large blocks (a
//!   packed column, a window's brick arrays, a frame) come from the heap
//!   and fragment it, and the memory a budget counts stays resident after
//!   the cache evicted what used it. A fixed threshold maps them on their
//!   own and returns them on free. Measured with the camera teleported
//!   every 0.2 s for 150 s under a 250 MiB budget (`worlds/endless.toml`):
//!   RSS peaked at 347 MiB with glibc's default, 329 with two arenas
//!   (`MALLOC_ARENA_MAX=2`), and **268** with the fixed threshold, where
//!   the cache also kept 35 MB instead of 22 at the same tick rate (a
//!   7.5-minute run with the binary setting it itself: peak 271 MiB).
//!   mimalloc as the global allocator was worse (peak 404 MiB, the cache
//!   squeezed to 3 MB), so glibc stays.
//!
//! The re-exec is skipped where it cannot run the program as itself (see
//! [`re_executable`]); the settings are then simply absent.

use std::path::{Path, PathBuf};

/// Marks the re-executed process, so that it never loops.
const MARK: &str = "BRICKWORLD_ENV_SET";

/// Whether `v` names a usable runtime directory: an absolute path to a
/// folder (Mesa refuses a relative one with its noise; review).
pub fn usable(v: Option<&std::ffi::OsStr>) -> bool {
    v.is_some_and(|v| Path::new(v).is_absolute() && Path::new(v).is_dir())
}

/// The engine's commands, which hold a memory budget.
const ENGINE_COMMANDS: [&str; 2] = ["run", "soak"];

/// glibc's mmap threshold for the engine, bytes (its own default's start).
const MMAP_THRESHOLD: &str = "131072";

/// Whether a process whose first argument is `command`, in an environment
/// where `var` reads variables, should run with [`MMAP_THRESHOLD`]: an
/// engine command on glibc, unless the user chose a threshold.
pub fn wants_mmap_threshold(
    command: Option<&std::ffi::OsStr>,
    var: impl Fn(&str) -> Option<std::ffi::OsString>,
) -> bool {
    let engine = command.is_some_and(|c| ENGINE_COMMANDS.iter().any(|e| c == *e));
    let chosen = var("MALLOC_MMAP_THRESHOLD_").is_some()
        || var("GLIBC_TUNABLES").is_some_and(|t| t.to_string_lossy().contains("mmap_threshold"));
    cfg!(all(target_os = "linux", target_env = "gnu")) && engine && !chosen
}

/// See the module docs. Call first thing in `main`, before any thread.
pub fn ensure() {
    if std::env::var_os(MARK).is_some() {
        return;
    }
    let mut set: Vec<(&str, std::ffi::OsString)> = Vec::new();
    #[cfg(unix)]
    if !usable(std::env::var_os("XDG_RUNTIME_DIR").as_deref())
        && let Some(dir) = private_dir()
    {
        set.push(("XDG_RUNTIME_DIR", dir.into_os_string()));
    }
    let command = std::env::args_os().nth(1);
    if wants_mmap_threshold(command.as_deref(), |k| std::env::var_os(k)) {
        set.push(("MALLOC_MMAP_THRESHOLD_", MMAP_THRESHOLD.into()));
    }
    if set.is_empty() {
        return;
    }
    #[cfg(unix)]
    {
        use std::os::unix::process::CommandExt;
        let Ok(exe) = std::env::current_exe() else {
            return;
        };
        if !re_executable(&exe) {
            return;
        }
        let mut args = std::env::args_os();
        let mut cmd = std::process::Command::new(exe);
        if let Some(arg0) = args.next() {
            // The name the user ran, for usage lines (review: a link's
            // name became "brickworld").
            cmd.arg0(arg0);
        }
        // Returns only if the exec failed: then go on as we are.
        let _ = cmd.args(args).envs(set).env(MARK, "1").exec();
    }
}

/// Whether the program at `exe` (`current_exe`) can be run again as
/// itself: not when it was started through the dynamic loader
/// (`ld-linux-x86-64.so.2 brickworld …`, where `exe` is the loader, and
/// re-running it with the arguments would run the loader on `run`;
/// review), nor when the file is gone or replaced (`… (deleted)`).
/// Skipping the re-exec only forgoes its settings; an exec that fails
/// anyway (an environment past the kernel's limit, a policy that denies
/// `execve`) returns, and the program goes on, with SIGPIPE back at its
/// default and the signal mask emptied, as `std` leaves them before
/// `execve`; `main` then blocks the signals writes raise
/// ([`crate::files::no_signal_from_writes`]).
pub fn re_executable(exe: &Path) -> bool {
    let name = exe
        .file_name()
        .map(|n| n.to_string_lossy().into_owned())
        .unwrap_or_default();
    let loader = name.starts_with("ld-") || name.starts_with("ld.so");
    !loader && exe.is_file()
}

/// `TMPDIR/brickworld-runtime-UID`, created 0700, or under `/tmp` when
/// `TMPDIR` is not an absolute path to a folder where it can be made;
/// `None` if neither holds a directory of ours that only we can read.
/// An empty or relative `TMPDIR` made every command create the folder in
/// the working directory, and passed Mesa a relative path, which it
/// refused with its noise; a `TMPDIR` that is a file or missing gave the
/// noise too (regression, hostile environment probe).
#[cfg(unix)]
pub fn private_dir() -> Option<PathBuf> {
    let tmp = std::env::temp_dir();
    tmp.is_absolute()
        .then(|| private_dir_in(&tmp))
        .flatten()
        .or_else(|| private_dir_in(Path::new("/tmp")))
}

/// [`private_dir`] under `base`.
#[cfg(unix)]
fn private_dir_in(base: &Path) -> Option<PathBuf> {
    use std::os::unix::fs::{DirBuilderExt, MetadataExt, PermissionsExt};
    let uid = std::fs::metadata("/proc/self").ok()?.uid();
    let dir = base.join(format!("brickworld-runtime-{uid}"));
    let _ = std::fs::DirBuilder::new().mode(0o700).create(&dir);
    let m = std::fs::symlink_metadata(&dir).ok()?;
    (m.is_dir() && m.uid() == uid && m.permissions().mode() & 0o077 == 0).then_some(dir)
}

#[cfg(test)]
mod tests {
    use super::*;

    /// The engine's commands get the threshold on glibc, others do not,
    /// and a threshold the user chose is left alone.
    #[test]
    fn only_the_engine_gets_a_fixed_mmap_threshold_unless_one_was_chosen() {
        let none = |_: &str| None;
        let glibc = cfg!(all(target_os = "linux", target_env = "gnu"));
        assert_eq!(wants_mmap_threshold(Some("run".as_ref()), none), glibc);
        assert_eq!(wants_mmap_threshold(Some("soak".as_ref()), none), glibc);
        for other in ["render", "bench", "runner", "--help"] {
            assert!(!wants_mmap_threshold(Some(other.as_ref()), none), "{other}");
        }
        assert!(!wants_mmap_threshold(None, none));
        let set = |k: &str| (k == "MALLOC_MMAP_THRESHOLD_").then(|| "65536".into());
        assert!(!wants_mmap_threshold(Some("run".as_ref()), set));
        let tunables =
            |k: &str| (k == "GLIBC_TUNABLES").then(|| "glibc.malloc.mmap_threshold=1".into());
        assert!(!wants_mmap_threshold(Some("run".as_ref()), tunables));
        let other = |k: &str| (k == "GLIBC_TUNABLES").then(|| "glibc.malloc.arena_max=2".into());
        assert_eq!(wants_mmap_threshold(Some("run".as_ref()), other), glibc);
    }

    /// The loader and a deleted binary are not run again.
    #[test]
    fn the_loader_and_a_deleted_binary_are_not_re_executed() {
        assert!(re_executable(&std::env::current_exe().unwrap()));
        assert!(!re_executable(Path::new("/lib64/ld-linux-x86-64.so.2")));
        assert!(!re_executable(Path::new("/usr/lib/ld.so")));
        assert!(!re_executable(Path::new("/tmp/brickworld (deleted)")));
    }

    #[test]
    fn a_missing_empty_or_file_runtime_dir_is_unusable() {
        assert!(!usable(None));
        assert!(!usable(Some("".as_ref())));
        assert!(!usable(Some("/nonexistent/brickworld".as_ref())));
        assert!(!usable(Some("/proc/self/status".as_ref())));
        // Relative, though a folder here.
        assert!(!usable(Some(".".as_ref())));
        assert!(usable(Some("/".as_ref())));
        assert!(usable(Some(std::env::temp_dir().as_os_str())));
    }

    #[cfg(unix)]
    #[test]
    fn the_private_dir_is_ours_and_closed_to_others() {
        use std::os::unix::fs::PermissionsExt;
        // Under a folder of the test's own: the real one is kept for
        // later runs, and a test must leave nothing in the temp dir.
        let base = std::env::temp_dir().join(format!("bw-private-{}", std::process::id()));
        std::fs::create_dir_all(&base).unwrap();
        let d = private_dir_in(&base).expect("a private runtime directory");
        let mode = std::fs::metadata(&d).unwrap().permissions().mode();
        assert_eq!(mode & 0o077, 0, "{} is open to others", d.display());
        // One open to others is refused.
        std::fs::set_permissions(&d, std::fs::Permissions::from_mode(0o755)).unwrap();
        assert_eq!(private_dir_in(&base), None);
        std::fs::remove_dir_all(&base).unwrap();
    }
}
