//! The state directory's guards: an exclusive lock held for the engine's
//! lifetime (two daemons on one directory would overwrite each other's token
//! and delete each other's checkpoints), and the control token, drawn from
//! the OS's random source and written to a file that is private (0600) from
//! the moment it exists.

use std::fs::{File, OpenOptions};
use std::io::Write;
use std::path::{Path, PathBuf};

use thiserror::Error;

/// Errors of the state directory.
#[derive(Debug, Error)]
pub enum StateDirError {
    /// Another engine holds the directory.
    #[error(
        "the state directory {} is in use by another brickworld engine (it holds {}); stop it or choose another --state",
        dir.display(), lock.display()
    )]
    InUse {
        /// The directory.
        dir: PathBuf,
        /// Its lock file.
        lock: PathBuf,
    },
    /// The OS random source failed: no token can be made safely.
    #[error("cannot draw a control token from the OS random source: {0}")]
    Random(String),
    /// Creating, locking or writing a file failed.
    #[error("{}: {error}", path.display())]
    Io {
        /// The file.
        path: PathBuf,
        /// The error.
        error: std::io::Error,
    },
}

/// An exclusive lock on a state directory, released when dropped (and by
/// the OS if the process dies, `kill -9` included).
#[derive(Debug)]
pub struct StateLock {
    _file: File,
    /// The lock file, for errors.
    path: PathBuf,
}

impl StateLock {
    /// A second handle on the same lock: the lock lasts until both are
    /// dropped.
    pub fn try_clone(&self) -> Result<StateLock, StateDirError> {
        Ok(StateLock {
            _file: self._file.try_clone().map_err(|error| StateDirError::Io {
                // The whole path (regression, hostile environment probe:
                // "engine.lock: Too many open files" named no folder).
                path: self.path.clone(),
                error,
            })?,
            path: self.path.clone(),
        })
    }
}

/// Create the state directory `dir` (and its parents); the folders this
/// call made, outermost first (see [`crate::files::missing_folders`]),
/// empty if `dir` was there. Whether it made `dir` is decided by
/// `create_dir` itself, so two processes cannot both think they did.
pub fn make(dir: &Path) -> Result<Vec<PathBuf>, StateDirError> {
    let ioe = |path: &Path| {
        let path = path.to_path_buf();
        move |error| StateDirError::Io { path, error }
    };
    match crate::files::make_dir(dir).map_err(ioe(dir))? {
        Some(made) => Ok(made),
        // Something that is not a folder: say so, not "File exists"
        // (regression, hostile probe: `--state /dev/null`).
        None if !dir.is_dir() => Err(ioe(dir)(std::io::Error::other(
            "is not a folder (the state directory must be one)",
        ))),
        // There already, or made meanwhile by another process: not ours.
        None => Ok(Vec::new()),
    }
}

/// Make (if needed) and lock the state directory `dir`; also the folders
/// this call made (`dir` and the parents it needed), empty if `dir` was
/// there. If the lock is refused, what this call made is removed again
/// while empty (another process's lock file keeps it). A caller that fails
/// later and made the directory removes it, and the parents made for it,
/// with [`crate::files::remove_made`] while it holds the lock.
pub fn claim(dir: &Path) -> Result<(StateLock, Vec<PathBuf>), StateDirError> {
    let made = make(dir)?;
    match lock(dir) {
        Ok(l) => Ok((l, made)),
        Err(e) => {
            // Only while empty: another engine may have taken it meanwhile.
            crate::files::remove_made_if_empty(&made);
            Err(e)
        }
    }
}

/// Create `dir` if needed and lock it (`flock`, non-blocking).
pub fn lock(dir: &Path) -> Result<StateLock, StateDirError> {
    let ioe = |path: &Path| {
        let path = path.to_path_buf();
        move |error| StateDirError::Io { path, error }
    };
    std::fs::create_dir_all(dir).map_err(ioe(dir))?;
    let path = dir.join("engine.lock");
    let not_a_file = || ioe(&path)(std::io::Error::other("not a regular file: move it away"));
    // A link is not followed: the PID written below truncated whatever a
    // link named engine.lock pointed at (regression, hostile probe).
    if crate::files::is_there_but_not_a_file(&path)
        || std::fs::symlink_metadata(&path).is_ok_and(|m| m.file_type().is_symlink())
    {
        return Err(not_a_file());
    }
    // Without waiting: a FIFO named engine.lock hung the start (regression).
    let mut options = OpenOptions::new();
    options.create(true).truncate(false).write(true);
    #[cfg(unix)]
    {
        use std::os::unix::fs::OpenOptionsExt;
        // Non-blocking (a FIFO) and not through a link made meanwhile.
        options.custom_flags(libc::O_NONBLOCK | libc::O_NOFOLLOW);
    }
    let file = options.open(&path).map_err(|e| {
        #[cfg(unix)]
        if e.raw_os_error() == Some(libc::ELOOP) {
            return not_a_file();
        }
        ioe(&path)(e)
    })?;
    if !file.metadata().map_err(ioe(&path))?.is_file() {
        return Err(not_a_file());
    }
    match file.try_lock() {
        Ok(()) => {}
        Err(std::fs::TryLockError::WouldBlock) => {
            return Err(StateDirError::InUse {
                dir: dir.to_path_buf(),
                lock: path,
            });
        }
        Err(std::fs::TryLockError::Error(e)) => return Err(ioe(&path)(e)),
    }
    // The holder's PID, for people (the lock itself is what counts).
    let _ = file.set_len(0);
    let _ = writeln!(&file, "{}", std::process::id());
    Ok(StateLock { _file: file, path })
}

/// A fresh control token: 32 hex digits from the OS's random source.
pub fn new_token() -> Result<String, StateDirError> {
    token_from(getrandom::fill)
}

/// A token drawn with `fill`: the OS's random source, or a failing one in
/// tests (no other seed is ever used: a failure is an error, not a
/// fallback to something guessable).
fn token_from(
    fill: impl FnOnce(&mut [u8]) -> Result<(), getrandom::Error>,
) -> Result<String, StateDirError> {
    let mut bytes = [0u8; 16];
    fill(&mut bytes).map_err(|e| StateDirError::Random(e.to_string()))?;
    Ok(bytes.iter().map(|b| format!("{b:02x}")).collect())
}

/// Write `token` to `dir/control.token`, created 0600 (owner-only) before
/// a byte is written; an existing file is replaced, never reused.
pub fn write_token(dir: &Path, token: &str) -> Result<PathBuf, StateDirError> {
    let path = dir.join("control.token");
    let ioe = |error| StateDirError::Io {
        path: path.clone(),
        error,
    };
    // A fresh file: an old one (perhaps with looser permissions) goes first.
    match std::fs::remove_file(&path) {
        Ok(()) => {}
        Err(e) if e.kind() == std::io::ErrorKind::NotFound => {}
        Err(e) => return Err(ioe(e)),
    }
    let mut opts = OpenOptions::new();
    opts.write(true).create_new(true);
    #[cfg(unix)]
    {
        use std::os::unix::fs::OpenOptionsExt;
        opts.mode(0o600);
    }
    let mut f = opts.open(&path).map_err(ioe)?;
    f.write_all(token.as_bytes()).map_err(ioe)?;
    f.sync_all().map_err(ioe)?;
    Ok(path)
}

/// The file in a state directory that names the address its engine's
/// control server is bound to.
pub const ADDR_FILE: &str = "control.addr";

/// Write the bound control address `addr` to `dir/control.addr`, for
/// `ctl --state` (an engine on port 0 picks its port).
pub fn write_addr(dir: &Path, addr: std::net::SocketAddr) -> Result<PathBuf, StateDirError> {
    let path = dir.join(ADDR_FILE);
    std::fs::write(&path, format!("{addr}\n")).map_err(|error| StateDirError::Io {
        path: path.clone(),
        error,
    })?;
    Ok(path)
}

/// The address `dir/control.addr` names: `Ok(None)` if there is no such
/// file, an error naming it if it is there but holds no address (a FIFO,
/// a link to a device, garbage), rather than a fall back to the default
/// address, where another engine may listen (hostile probe).
pub fn read_addr(dir: &Path) -> Result<Option<String>, String> {
    let path = dir.join(ADDR_FILE);
    // Only a missing file means "no address": any other failure (a state
    // path that is a file, no permission) is said (review).
    match std::fs::symlink_metadata(&path) {
        Err(e) if e.kind() == std::io::ErrorKind::NotFound => return Ok(None),
        _ => {}
    }
    let why = |what: String| {
        format!(
            "{} {what}: pass --addr, or start the engine again to rewrite it",
            path.display()
        )
    };
    let text =
        crate::files::read_text(&path, 256).map_err(|e| why(format!("cannot be read ({e})")))?;
    let addr: std::net::SocketAddr = text
        .trim()
        .parse()
        .map_err(|_| why("does not hold an address".into()))?;
    Ok(Some(addr.to_string()))
}

#[cfg(test)]
mod tests {
    use super::*;

    /// Claim (README, control API): an engine that cannot read the OS's
    /// random source refuses to start, in one line, rather than make a
    /// guessable token. (`Engine::start` passes this error on with `?`,
    /// before it listens or writes a token file.)
    /// Regression (hostile probe): a state path that is a file or a
    /// device said "File exists".
    #[test]
    fn a_state_path_that_is_not_a_folder_says_so() {
        let file = std::env::temp_dir().join(format!("bw-state-file-{}", std::process::id()));
        std::fs::write(&file, "mine").unwrap();
        for p in [file.as_path(), Path::new("/dev/null")] {
            let e = make(p).unwrap_err().to_string();
            assert!(
                e.contains("is not a folder") && !e.contains("File exists"),
                "{e}"
            );
        }
        assert_eq!(std::fs::read_to_string(&file).unwrap(), "mine");
        let _ = std::fs::remove_file(&file);
    }

    #[test]
    fn a_failing_random_source_is_a_clear_error_not_a_weak_token() {
        let e = token_from(|_| Err(getrandom::Error::UNSUPPORTED)).unwrap_err();
        assert!(matches!(e, StateDirError::Random(_)), "{e:?}");
        let line = e.to_string();
        assert!(
            line.starts_with("cannot draw a control token from the OS random source: ")
                && !line.contains('\n'),
            "{line}"
        );
        // The real source: 32 hex digits, fresh each time.
        let (a, b) = (new_token().unwrap(), new_token().unwrap());
        assert!(
            a.len() == 32 && a.bytes().all(|c| c.is_ascii_hexdigit()),
            "{a}"
        );
        assert_ne!(a, b);
    }
}
