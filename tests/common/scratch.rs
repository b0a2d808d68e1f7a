//! Scratch folders for tests, removed when the test that made them passes.
//!
//! Each is a folder of its own under the temp dir, named after its test
//! and this process. When its guard is dropped the folder is removed,
//! unless the thread is panicking (a failing test): then it is kept, and
//! its path printed, to look at. Regression: tests wrote their worlds,
//! states and images under the temp dir and never removed them, about
//! 150 MB a run (4.5 GB in `/tmp` after 30 runs); `.ci/run` now fails if
//! a run leaves anything behind.

#![allow(dead_code)]

use std::ffi::OsStr;
use std::ops::Deref;
use std::path::{Path, PathBuf};
use std::sync::atomic::{AtomicUsize, Ordering};

/// A scratch folder (or a path inside one), removed on drop unless the
/// test is failing. Derefs to its path.
#[derive(Debug)]
pub struct Scratch {
    root: PathBuf,
    path: PathBuf,
}

static NEXT: AtomicUsize = AtomicUsize::new(0);

impl Scratch {
    /// The empty folder `brickworld-NAME-PID` (emptied first, in case a
    /// failed test of an earlier run with the same process id left it).
    pub fn dir(name: &str) -> Scratch {
        let root = std::env::temp_dir().join(format!("brickworld-{name}-{}", std::process::id()));
        Scratch::empty(root, None)
    }

    /// The path `name` inside an empty folder of its own,
    /// `brickworld-TAG-PID-N` (N counts this process's calls); the path
    /// itself is not created: the test writes it, or asks a command to.
    pub fn file(tag: &str, name: &str) -> Scratch {
        let n = NEXT.fetch_add(1, Ordering::Relaxed);
        let root =
            std::env::temp_dir().join(format!("brickworld-{tag}-{}-{n}", std::process::id()));
        Scratch::empty(root, Some(name))
    }

    fn empty(root: PathBuf, name: Option<&str>) -> Scratch {
        let _ = std::fs::remove_dir_all(&root);
        std::fs::create_dir_all(&root).unwrap();
        Scratch {
            path: name.map_or_else(|| root.clone(), |n| root.join(n)),
            root,
        }
    }

    /// The path (the folder for [`Scratch::dir`]).
    pub fn path(&self) -> &Path {
        &self.path
    }

    /// The path, owned.
    pub fn to_path_buf(&self) -> PathBuf {
        self.path.clone()
    }
}

impl Deref for Scratch {
    type Target = Path;
    fn deref(&self) -> &Path {
        &self.path
    }
}

// Only a reference is a path: a guard given by value to a command's
// `arg` or to `fs::write` would be dropped there, removing its folder
// before it is used (it happened), so that does not compile.
impl AsRef<Path> for &Scratch {
    fn as_ref(&self) -> &Path {
        &self.path
    }
}

impl AsRef<OsStr> for &Scratch {
    fn as_ref(&self) -> &OsStr {
        self.path.as_os_str()
    }
}

impl Drop for Scratch {
    fn drop(&mut self) {
        if std::thread::panicking() {
            eprintln!("kept {} for the failing test", self.root.display());
        } else {
            let _ = std::fs::remove_dir_all(&self.root);
        }
    }
}
