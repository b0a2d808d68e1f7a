//! Guarded access to the files a user names.
//!
//! - **Reading** ([`read_bounded`], [`read_text`]) takes only a regular file
//!   (after following links) of at most a stated size: a FIFO would block
//!   for ever, `/dev/zero` would fill memory, and a file that grows while
//!   read is cut at the bound. Each refusal is one line naming the file.
//! - **Writing** ([`Staged`]) goes to a fresh temporary file beside the
//!   destination, created with `create_new` so it never reuses a file that
//!   is already there, and replaces the destination only on
//!   [`Staged::commit`]. A command that fails half-way leaves every file it
//!   was going to replace as it was. A link is followed (the file it names
//!   is replaced, or made if it is not there yet), and a destination that is not a regular file (`/dev/null`,
//!   a FIFO) is written directly, never replaced. Temporary files that a
//!   killed or interrupted process left beside a destination are removed
//!   by the next write to it, once a minute old.
//!
//! ```
//! use brickworld::files::{Staged, read_text};
//! let dir = std::env::temp_dir().join(format!("bw-files-doc-{}", std::process::id()));
//! std::fs::create_dir_all(&dir).unwrap();
//! let dest = dir.join("note.txt");
//! let staged = Staged::new(&dest).unwrap();
//! std::fs::write(staged.path(), "hello").unwrap();
//! assert!(!dest.exists()); // nothing replaced before the commit
//! staged.commit().unwrap();
//! assert_eq!(read_text(&dest, 1 << 10).unwrap(), "hello");
//! # std::fs::remove_dir_all(&dir).unwrap();
//! ```

use std::io::Read;
use std::path::{Path, PathBuf};

use thiserror::Error;

mod folders;
mod interrupt;
mod temps;
pub use folders::{
    SCRATCH_MARKER, ScratchDir, fresh_scratch_dir, make_dir, missing_folders, remove_made,
    remove_made_if_empty, remove_scratch_on_interrupt,
};
pub use interrupt::{
    keep_undo_list, landing, output_landed, remove_temps_on_interrupt, remove_writing_temps,
    temp_landed, temp_writing, undo_on_interrupt,
};
pub(crate) use temps::write_target;
pub use temps::{Staged, fresh_temp_beside, temp_of_gone_process};

/// Why a file could not be read.
#[derive(Debug, Error)]
pub enum FileError {
    /// The OS refused.
    // Not a `source`: the text already says it, and an error chain
    // (`anyhow`'s context) printed it twice (regression).
    #[error("cannot read {}: {error}", path.display())]
    Io {
        /// The file.
        path: PathBuf,
        /// What the OS said.
        error: std::io::Error,
    },
    /// A directory, FIFO, socket or device.
    #[error("{} is not a regular file", path.display())]
    NotAFile {
        /// The file.
        path: PathBuf,
    },
    /// Larger than the caller's bound.
    #[error("{} is larger than the {max}-byte limit ({size} bytes)", path.display())]
    TooLarge {
        /// The file.
        path: PathBuf,
        /// Its size (or the bytes read before the bound was passed).
        size: u64,
        /// The bound.
        max: u64,
    },
    /// Not UTF-8 text.
    #[error("{} is not UTF-8 text", path.display())]
    NotText {
        /// The file.
        path: PathBuf,
    },
}

impl FileError {
    /// The same error, naming the file as `path` (the name the user knows
    /// for a file read through another, such as a held folder's
    /// `/proc/self/fd/N/…`; regression, hostile environment probe: a
    /// warning named `/proc/self/fd/15/timeline.csv`).
    pub fn named(mut self, name: &Path) -> Self {
        match &mut self {
            FileError::Io { path, .. }
            | FileError::NotAFile { path }
            | FileError::TooLarge { path, .. }
            | FileError::NotText { path } => *path = name.to_path_buf(),
        }
        self
    }
}

/// `options` with `O_NONBLOCK` on Unix: opening a FIFO then returns at
/// once instead of waiting for the other end (a regular file reads and
/// writes as always).
pub fn without_waiting(options: &mut std::fs::OpenOptions) -> &mut std::fs::OpenOptions {
    #[cfg(unix)]
    {
        use std::os::unix::fs::OpenOptionsExt;
        options.custom_flags(libc::O_NONBLOCK);
    }
    options
}

/// Make writes fail instead of killing the process, by blocking the two
/// signals a write can raise (a blocked signal stays pending, and the
/// write returns its error, which every writer reports):
/// - `SIGXFSZ`, past the process's file size limit (`ulimit -f`,
///   `RLIMIT_FSIZE`): the write returns `EFBIG` (a daemon's commit keeps
///   the last good checkpoint) instead of the process ending without a
///   word;
/// - `SIGPIPE`, on a pipe nothing reads: the write returns `EPIPE`. `std`
///   ignores it at start, but resets it to its default before an `exec`,
///   so after a failed re-exec ([`crate::process_env::ensure`]) a closed
///   standard output killed the process (regression, twenty-third
///   session's note). `exec` also empties the signal mask, so call this
///   after `ensure`, before any thread starts: threads inherit the mask.
///   Children that `std` spawns start with an empty mask.
///
/// A no-op off Unix.
pub fn no_signal_from_writes() {
    #[cfg(unix)]
    {
        use nix::sys::signal::{SigSet, Signal};
        let mut set = SigSet::empty();
        set.add(Signal::SIGXFSZ);
        set.add(Signal::SIGPIPE);
        // Blocking signals cannot fail with a valid set; if it did, the
        // defaults (a silent kill) are what remains.
        let _ = set.thread_block();
    }
}

/// The signals the engine takes as a stop request with a final commit on
/// a thread of its own, beside SIGINT, SIGTERM and SIGHUP (which `ctrlc`
/// handles): SIGXCPU (sent past a soft CPU-time limit), SIGQUIT (a
/// graceful stop, as in nginx), and SIGUSR1, SIGUSR2, SIGALRM, SIGVTALRM,
/// SIGPROF, SIGIO, SIGPWR and SIGSTKFLT, whose default action killed the
/// engine without a commit. (The real-time signals, which `nix`'s sets
/// cannot name, are taken through `signal-hook` in `engine::daemon::start`.)
#[cfg(unix)]
pub fn stop_signals() -> nix::sys::signal::SigSet {
    use nix::sys::signal::{SigSet, Signal};
    let mut set = SigSet::empty();
    for s in [
        Signal::SIGXCPU,
        Signal::SIGQUIT,
        Signal::SIGUSR1,
        Signal::SIGUSR2,
        Signal::SIGALRM,
        // Others whose default is to end the process (review).
        Signal::SIGVTALRM,
        Signal::SIGPROF,
        Signal::SIGIO,
        #[cfg(any(target_os = "linux", target_os = "android"))]
        Signal::SIGPWR,
        #[cfg(any(target_os = "linux", target_os = "android"))]
        Signal::SIGSTKFLT,
    ] {
        set.add(s);
    }
    set
}

/// Block the [`stop_signals`] in this thread and the threads it starts
/// from now on, so that the engine takes them as a stop request on a
/// thread of its own instead of dying without a final commit. Call it
/// before the engine starts any thread. A no-op off Unix. (Child
/// processes get an empty mask: `std` clears it before `execve`.)
pub fn block_stop_signals() {
    #[cfg(unix)]
    {
        // Blocking signals cannot fail with a valid set; if it did, the
        // defaults (death by the signal) are what remains.
        let _ = stop_signals().thread_block();
    }
}

/// Where the caller started this process with SIGHUP ignored (`nohup`),
/// keep it ignored: block it in this thread and every thread it starts
/// from now on, so it never arrives. Every command's interrupt handler
/// (`ctrlc`, which takes SIGHUP with SIGINT and SIGTERM) would otherwise
/// replace the ignore (regression, stop-path probe and its review: `nohup
/// brickworld run`, and then `nohup brickworld sim`, stopped when their
/// terminal closed). Call it before any thread starts.
pub fn keep_sighup_ignored() {
    #[cfg(unix)]
    if ignored_at_start(nix::sys::signal::Signal::SIGHUP) {
        let _ = nix::sys::signal::SigSet::from(nix::sys::signal::Signal::SIGHUP).thread_block();
    }
}

/// Whether this process started with `sig` ignored (inherited from its
/// parent, as `nohup` sets SIGHUP), as Linux's `/proc/self/status` says;
/// false where it cannot say.
#[cfg(unix)]
pub fn ignored_at_start(sig: nix::sys::signal::Signal) -> bool {
    std::fs::read_to_string("/proc/self/status")
        .ok()
        .and_then(|s| {
            let hex = s.lines().find_map(|l| l.strip_prefix("SigIgn:"))?.trim();
            u64::from_str_radix(hex, 16).ok()
        })
        .is_some_and(|mask| mask >> (sig as i32 - 1) & 1 == 1)
}

/// Whether something other than a regular file (a FIFO, a device, a
/// directory) is at `path`: a file the engine reads or appends to there
/// would block or never end.
pub fn is_there_but_not_a_file(path: &Path) -> bool {
    std::fs::metadata(path).is_ok_and(|m| !m.is_file())
}

/// Why an output FIFO cannot be written.
#[derive(Debug, thiserror::Error)]
pub enum FifoError {
    /// Nothing has it open for reading: a write would wait for good.
    #[error(
        "is a FIFO that nothing reads (a write would wait for ever): start its reader first, or name a file"
    )]
    NoReader,
    /// It could not be opened.
    #[error("is a FIFO that cannot be opened: {0}")]
    Open(std::io::Error),
}

/// If `path` is a FIFO (a named pipe, or a pipe such as `/dev/stdout`),
/// check that something reads it, and keep it open for writing until the
/// process ends: the later write then finds its reader still there, which
/// sees the output as one stream (closing the check's descriptor would
/// end a named pipe's stream for its reader). Anything else: `Ok`.
pub fn hold_fifo_reader(path: &Path) -> Result<(), FifoError> {
    #[cfg(unix)]
    {
        use std::os::unix::fs::{FileTypeExt, OpenOptionsExt};
        static HELD: std::sync::Mutex<Vec<std::fs::File>> = std::sync::Mutex::new(Vec::new());
        if !std::fs::metadata(path).is_ok_and(|m| m.file_type().is_fifo()) {
            return Ok(());
        }
        // Opening a FIFO to write without blocking fails with ENXIO when
        // no reader has it open.
        match std::fs::OpenOptions::new()
            .write(true)
            .custom_flags(libc::O_NONBLOCK)
            .open(path)
        {
            Ok(f) => HELD.lock().unwrap_or_else(|e| e.into_inner()).push(f),
            Err(e) if e.raw_os_error() == Some(libc::ENXIO) => return Err(FifoError::NoReader),
            Err(e) => return Err(FifoError::Open(e)),
        }
    }
    #[cfg(not(unix))]
    let _ = path;
    Ok(())
}

/// The path of a folder held open as `dir`, through its descriptor
/// (`/proc/self/fd/N`): it names the folder opened even after the path it
/// was opened by names another one (a state directory deleted and made
/// again, another engine's). `None` without `/proc`.
pub fn held_folder(dir: &std::fs::File) -> Option<PathBuf> {
    #[cfg(unix)]
    {
        use std::os::fd::AsRawFd;
        let p = PathBuf::from(format!("/proc/self/fd/{}", dir.as_raw_fd()));
        p.is_dir().then_some(p)
    }
    #[cfg(not(unix))]
    {
        let _ = dir;
        None
    }
}

/// Whether `path` names the file open as `file` (the same device and
/// inode). The file is held open, so its inode cannot be reused while
/// this is asked. Without Unix metadata, true.
pub fn names_open_file(path: &Path, file: &std::fs::File) -> bool {
    #[cfg(unix)]
    {
        use std::os::unix::fs::MetadataExt;
        match (std::fs::metadata(path), file.metadata()) {
            (Ok(a), Ok(b)) => a.dev() == b.dev() && a.ino() == b.ino(),
            _ => false,
        }
    }
    #[cfg(not(unix))]
    {
        let _ = (path, file);
        true
    }
}

/// Open `path` to read it, [`without_waiting`].
pub fn open_for_reading(path: &Path) -> std::io::Result<std::fs::File> {
    without_waiting(std::fs::OpenOptions::new().read(true)).open(path)
}

/// The whole of a regular file of at most `max` bytes.
pub fn read_bounded(path: &Path, max: u64) -> Result<Vec<u8>, FileError> {
    let io = |error| FileError::Io {
        path: path.to_path_buf(),
        error,
    };
    let meta = std::fs::metadata(path).map_err(io)?;
    if !meta.is_file() {
        return Err(FileError::NotAFile {
            path: path.to_path_buf(),
        });
    }
    let too_large = |size| FileError::TooLarge {
        path: path.to_path_buf(),
        size,
        max,
    };
    if meta.len() > max {
        return Err(too_large(meta.len()));
    }
    let f = open_for_reading(path).map_err(io)?;
    // Opened after the check, without blocking (a file swapped for a FIFO in
    // between would block in `open` itself), and the type checked again on
    // the open handle before anything is read.
    if !f.metadata().map_err(io)?.is_file() {
        return Err(FileError::NotAFile {
            path: path.to_path_buf(),
        });
    }
    let mut bytes = Vec::with_capacity(meta.len() as usize);
    f.take(max + 1).read_to_end(&mut bytes).map_err(io)?;
    if bytes.len() as u64 > max {
        return Err(too_large(bytes.len() as u64));
    }
    Ok(bytes)
}

/// [`read_bounded`] as UTF-8 text.
pub fn read_text(path: &Path, max: u64) -> Result<String, FileError> {
    String::from_utf8(read_bounded(path, max)?).map_err(|_| FileError::NotText {
        path: path.to_path_buf(),
    })
}

/// Make a FIFO at `path`, for the unit tests of inputs that must not block.
#[cfg(all(test, unix))]
pub(crate) fn mkfifo(path: &Path) {
    let made = std::process::Command::new("mkfifo")
        .arg(path)
        .status()
        .unwrap();
    assert!(made.success(), "mkfifo {}", path.display());
}

#[cfg(test)]
mod tests {
    use super::*;

    /// A read error names the file as the user knows it, not the path it
    /// was reached by (regression, hostile environment probe: a warning
    /// named `/proc/self/fd/15/timeline.csv`).
    #[test]
    fn a_read_error_is_named_by_the_path_the_user_knows() {
        let e = FileError::Io {
            path: PathBuf::from("/proc/self/fd/15/timeline.csv"),
            error: std::io::Error::from_raw_os_error(24),
        }
        .named(Path::new("state/timeline.csv"));
        let said = e.to_string();
        assert!(
            said.starts_with("cannot read state/timeline.csv: "),
            "{said}"
        );
        assert!(!said.contains("/proc/"), "{said}");
    }

    /// A test's own empty folder, removed when the test passes (kept to
    /// look at when it fails). Regression: these folders were never
    /// removed, four a run.
    pub(super) struct TestDir(PathBuf);

    impl std::ops::Deref for TestDir {
        type Target = Path;
        fn deref(&self) -> &Path {
            &self.0
        }
    }

    impl AsRef<Path> for TestDir {
        fn as_ref(&self) -> &Path {
            &self.0
        }
    }

    impl Drop for TestDir {
        fn drop(&mut self) {
            if !std::thread::panicking() {
                let _ = std::fs::remove_dir_all(&self.0);
            }
        }
    }

    pub(super) fn dir(name: &str) -> TestDir {
        let d = std::env::temp_dir().join(format!("bw-files-{name}-{}", std::process::id()));
        let _ = std::fs::remove_dir_all(&d);
        std::fs::create_dir_all(&d).unwrap();
        TestDir(d)
    }

    /// Regressions (hostile probe, review): a scratch directory's parents
    /// made for it were left; `missing/../victim` made `missing`, took the
    /// user's `victim` as new, and removed it afterwards; `.` could not be
    /// emptied. Made folders go with their parents; one that was there is
    /// emptied, marker kept; a `..` after a missing folder is refused.
    #[test]
    fn scratch_dirs_remove_what_they_made_and_never_what_was_there() {
        let d = dir("scratchmade");
        let victim = d.join("victim");
        std::fs::create_dir(&victim).unwrap();
        std::fs::write(victim.join("data.txt"), "mine").unwrap();
        let e = fresh_scratch_dir(&d.join("missing/../victim")).unwrap_err();
        assert!(e.contains("'..' after a folder that does not exist"), "{e}");
        assert!(!d.join("missing").exists());
        assert_eq!(
            std::fs::read_to_string(victim.join("data.txt")).unwrap(),
            "mine"
        );
        // Made with its parents: removed with them.
        let s = fresh_scratch_dir(&d.join("a/b/c")).unwrap();
        std::fs::write(d.join("a/b/c/store"), "x").unwrap();
        drop(s);
        assert!(!d.join("a").exists());
        // There already (through a link, and as `./`): emptied, marker kept.
        let there = d.join("there");
        std::fs::create_dir(&there).unwrap();
        let link = d.join("link");
        std::os::unix::fs::symlink(&there, &link).unwrap();
        let s = fresh_scratch_dir(&link.join(".")).unwrap();
        std::fs::write(there.join("store"), "x").unwrap();
        drop(s);
        let left: Vec<_> = std::fs::read_dir(&there)
            .unwrap()
            .flatten()
            .map(|e| e.file_name())
            .collect();
        assert_eq!(left, [SCRATCH_MARKER]);
        // Kept when asked.
        let s = fresh_scratch_dir(&d.join("kept")).unwrap();
        s.keep();
        assert!(d.join("kept").join(SCRATCH_MARKER).is_file());
        // A folder holding another's files is refused, untouched.
        assert!(fresh_scratch_dir(&victim).is_err());
        assert!(victim.join("data.txt").is_file());
    }

    #[test]
    fn special_and_oversized_files_are_refused_before_reading() {
        let d = dir("read");
        let e = read_bounded(Path::new("/dev/zero"), 1 << 20).unwrap_err();
        assert!(matches!(e, FileError::NotAFile { .. }), "{e}");
        let e = read_bounded(&d, 1 << 20).unwrap_err();
        assert!(e.to_string().ends_with("is not a regular file"), "{e}");
        let f = d.join("big");
        std::fs::write(&f, [0u8; 100]).unwrap();
        let e = read_bounded(&f, 99).unwrap_err();
        assert!(
            e.to_string().contains("larger than the 99-byte limit"),
            "{e}"
        );
        assert_eq!(read_bounded(&f, 100).unwrap().len(), 100);
        std::fs::write(&f, [0xffu8; 4]).unwrap();
        assert!(matches!(
            read_text(&f, 10).unwrap_err(),
            FileError::NotText { .. }
        ));
    }

    /// Regression (review): opening a FIFO blocked in `open` itself, before
    /// the handle's type could be checked.
    #[cfg(unix)]
    #[test]
    fn opening_a_fifo_does_not_wait_for_a_writer() {
        let d = dir("fifo");
        let fifo = d.join("pipe");
        mkfifo(&fifo);
        // Returns at once (a blocking open would hang this test).
        let f = open_for_reading(&fifo).unwrap();
        assert!(!f.metadata().unwrap().is_file());
        let e = read_bounded(&fifo, 1 << 20).unwrap_err();
        assert!(matches!(e, FileError::NotAFile { .. }), "{e}");
    }

    #[test]
    fn only_scratch_directories_are_emptied() {
        let d = dir("scratch");
        let mine = d.join("mine");
        // Kept, as `soak` keeps its state for the next run to empty.
        fresh_scratch_dir(&mine).unwrap().keep();
        std::fs::write(mine.join("world.redb"), "x").unwrap();
        fresh_scratch_dir(&mine).unwrap().keep();
        assert!(!mine.join("world.redb").exists(), "emptied");
        let theirs = d.join("theirs");
        std::fs::create_dir_all(&theirs).unwrap();
        std::fs::write(theirs.join("precious.txt"), "keep").unwrap();
        let e = fresh_scratch_dir(&theirs).unwrap_err();
        assert!(e.contains("is not scratch space of this command"), "{e}");
        assert_eq!(
            std::fs::read_to_string(theirs.join("precious.txt")).unwrap(),
            "keep"
        );
        let file = d.join("file");
        std::fs::write(&file, "keep").unwrap();
        assert!(
            fresh_scratch_dir(&file)
                .unwrap_err()
                .contains("not a directory")
        );
        let empty = d.join("empty");
        std::fs::create_dir_all(&empty).unwrap();
        fresh_scratch_dir(&empty).unwrap();
    }
}
