//! Folders the commands make: the missing parents of a path listed and
//! made ([`make_dir`]), removed again when the command fails
//! ([`remove_made`]), and scratch directories ([`fresh_scratch_dir`]),
//! removed or emptied when the command ends, or is interrupted where the
//! command asked for that ([`remove_scratch_on_interrupt`]).

use std::path::{Path, PathBuf};

/// The file that marks a directory as scratch space this program made.
pub const SCRATCH_MARKER: &str = ".brickworld-scratch";

/// A scratch directory [`fresh_scratch_dir`] prepared. When dropped (the
/// command is done, or failed part-way), it is removed with the parents
/// made for it, or, where it was there already, emptied;
/// [`keep`](Self::keep) leaves it for the user to look at.
#[derive(Debug)]
pub struct ScratchDir {
    dir: PathBuf,
    /// The folders made for it, outermost first (see [`missing_folders`]);
    /// empty if it was there already.
    made: Vec<PathBuf>,
    keep: bool,
}

impl ScratchDir {
    /// Leave the scratch directory as it is (`soak` keeps its state).
    pub fn keep(mut self) {
        self.keep = true;
        forget_live(&self.dir);
    }
}

impl Drop for ScratchDir {
    fn drop(&mut self) {
        if self.keep {
            return;
        }
        forget_live(&self.dir);
        // A removal that failed was silent: under `ulimit -n 4`, `bench
        // store` left its world in `--dir` and said nothing (regression,
        // hostile environment probe).
        if let Err(e) = clear(&self.dir, &self.made) {
            crate::say!(
                "warning: cannot remove the scratch directory {}: {e} (remove it by hand)",
                self.dir.display()
            );
        }
    }
}

/// Remove a scratch directory and the folders made for it (`made`,
/// outermost first), or, where it was there already (`made` empty), empty
/// it but for its marker, so a next run takes it again.
fn clear(dir: &Path, made: &[PathBuf]) -> std::io::Result<()> {
    let Some((last, parents)) = made.split_last() else {
        return empty_dir(dir, Some(SCRATCH_MARKER));
    };
    match std::fs::remove_dir_all(last) {
        Err(e) if e.kind() != std::io::ErrorKind::NotFound => Err(e),
        _ => {
            remove_made_if_empty(parents);
            Ok(())
        }
    }
}

/// The scratch directories alive in this process, with the folders made
/// for each, for an interrupt to clear (see [`remove_scratch_on_interrupt`]).
fn live() -> std::sync::MutexGuard<'static, Vec<(PathBuf, Vec<PathBuf>)>> {
    static LIVE: std::sync::Mutex<Vec<(PathBuf, Vec<PathBuf>)>> = std::sync::Mutex::new(Vec::new());
    LIVE.lock().unwrap_or_else(|e| e.into_inner())
}

fn forget_live(dir: &Path) {
    live().retain(|(d, _)| d != dir);
}

/// From now on, Ctrl-C or SIGTERM clears the scratch directories alive in
/// this process (as their drop would) and exits with status 130: for a
/// command whose scratch space is large and that has no other use for
/// signals (regression, hostile environment probe: an interrupted `bench
/// store` left 16 MB in its `--dir`).
pub fn remove_scratch_on_interrupt() -> std::io::Result<()> {
    super::interrupt::list_temps();
    ctrlc::set_handler(|| {
        // The report being written, too (stop-path probe).
        let removed = super::interrupt::remove_writing_temps();
        if !removed.is_empty() {
            crate::say!("interrupted: the file being written was removed");
        }
        for (dir, made) in std::mem::take(&mut *live()) {
            // The command writes on meanwhile (a file made between the
            // listing and the folder's removal fails it), so a few tries.
            let mut cleared = clear(&dir, &made);
            for _ in 0..4 {
                if cleared.is_ok() {
                    break;
                }
                std::thread::sleep(std::time::Duration::from_millis(50));
                cleared = clear(&dir, &made);
            }
            match cleared {
                Ok(()) => crate::say!(
                    "interrupted: the scratch directory {} was cleared",
                    dir.display()
                ),
                // Said, as the drop says it (review: this path was silent).
                Err(e) => crate::say!(
                    "interrupted; warning: cannot remove the scratch directory {}: {e} (remove it by hand)",
                    dir.display()
                ),
            }
        }
        std::process::exit(130);
    })
    .map_err(std::io::Error::other)
}

/// Remove everything inside `dir` but the entry named `but`.
fn empty_dir(dir: &Path, but: Option<&str>) -> std::io::Result<()> {
    for e in std::fs::read_dir(dir)? {
        let e = e?;
        if but.is_some_and(|b| e.file_name() == b) {
            continue;
        }
        let p = e.path();
        if std::fs::symlink_metadata(&p)?.is_dir() {
            std::fs::remove_dir_all(&p)?;
        } else {
            std::fs::remove_file(&p)?;
        }
    }
    Ok(())
}

/// The folders `create_dir_all(dir)` would make, outermost first, as paths
/// under the canonical form of the deepest folder that exists (so a link
/// or `..` on the way cannot make them name something else). An error if a
/// `..` comes after a folder that does not exist: what it names is not
/// known until that folder is made (regression, review: `--dir
/// missing/../victim` emptied `victim` and then removed it).
pub fn missing_folders(dir: &Path) -> Result<Vec<PathBuf>, String> {
    use std::path::Component;
    let mut there = PathBuf::new();
    let mut comps = dir.components().peekable();
    while let Some(c) = comps.peek() {
        let next = there.join(c);
        if std::fs::symlink_metadata(&next).is_err() {
            break;
        }
        there = next;
        comps.next();
    }
    let base = if there.as_os_str().is_empty() {
        Path::new(".").canonicalize()
    } else {
        there.canonicalize()
    }
    .map_err(|e| format!("cannot resolve {}: {e}", there.display()))?;
    let mut made = Vec::new();
    let mut at = base;
    for c in comps {
        match c {
            Component::Normal(name) => {
                at = at.join(name);
                made.push(at.clone());
            }
            Component::CurDir => {}
            _ => {
                return Err(format!(
                    "{} has '..' after a folder that does not exist: name the folder without it",
                    dir.display()
                ));
            }
        }
    }
    Ok(made)
}

/// Create `dir` and the parents it needs: `Some` of the folders made
/// (outermost first, see [`missing_folders`]), or `None` if `dir` was
/// there, or was made meanwhile by another process (`create_dir` decides,
/// so two processes cannot both think they made it). A failure removes
/// what this call made while it is empty.
pub fn make_dir(dir: &Path) -> std::io::Result<Option<Vec<PathBuf>>> {
    let made = missing_folders(dir).map_err(std::io::Error::other)?;
    let parents = &made[..made.len().saturating_sub(1)];
    if let Some(parent) = parents.last()
        && let Err(e) = std::fs::create_dir_all(parent)
    {
        remove_made_if_empty(parents);
        return Err(e);
    }
    match made.last().map(std::fs::create_dir) {
        Some(Ok(())) => Ok(Some(made)),
        Some(Err(e)) if e.kind() == std::io::ErrorKind::AlreadyExists => Ok(None),
        Some(Err(e)) => {
            remove_made_if_empty(&made);
            Err(e)
        }
        None => Ok(None),
    }
}

/// Remove the folders `made` (outermost first, from [`missing_folders`]):
/// the innermost with all it holds, then its parents, each only while
/// empty. What a command that made them and then failed leaves
/// (regression, hostile probe: a refused `import --state a/b/c` left
/// `a/b`).
pub fn remove_made(made: &[PathBuf]) {
    if let Some(last) = made.last() {
        let _ = std::fs::remove_dir_all(last);
        remove_made_if_empty(&made[..made.len() - 1]);
    }
}

/// Remove the folders `made` (outermost first), innermost first, each
/// only while empty; stop at the first that is not.
pub fn remove_made_if_empty(made: &[PathBuf]) {
    for d in made.iter().rev() {
        if std::fs::remove_dir(d).is_err() {
            break;
        }
    }
}

/// Make `dir` a fresh, empty scratch directory (holding only
/// [`SCRATCH_MARKER`]): create it, or empty it if it is empty already or
/// carries the marker. Any other directory, or a file, is refused and left
/// untouched (regression: `bench store --dir` and `soak --state` deleted
/// whatever directory they were given). A link to a directory is that
/// directory, and `.` is emptied in place (regression, hostile probe:
/// "cannot empty .: Invalid argument").
pub fn fresh_scratch_dir(dir: &Path) -> Result<ScratchDir, String> {
    let shown = dir.display();
    let made = match std::fs::metadata(dir) {
        Err(e) if e.kind() == std::io::ErrorKind::NotFound => {
            make_dir(dir).map_err(|e| format!("cannot create {shown}: {e}"))?
        }
        Err(e) => return Err(format!("cannot use {shown}: {e}")),
        Ok(_) => None,
    };
    let made = match made {
        Some(made) => made,
        None => {
            let m = std::fs::metadata(dir).map_err(|e| format!("cannot use {shown}: {e}"))?;
            if !m.is_dir() {
                return Err(format!("{shown} exists and is not a directory"));
            }
            let empty = std::fs::read_dir(dir)
                .map_err(|e| format!("cannot read {shown}: {e}"))?
                .next()
                .is_none();
            if !empty && !dir.join(SCRATCH_MARKER).is_file() {
                return Err(format!(
                    "{shown} holds files and is not scratch space of this command (no {SCRATCH_MARKER} in it; \
                     it empties the directory it is given, so it takes a new or empty one, or one it made): \
                     name another, or empty it yourself"
                ));
            }
            empty_dir(dir, None).map_err(|e| format!("cannot empty {shown}: {e}"))?;
            Vec::new()
        }
    };
    let scratch = ScratchDir {
        dir: dir.to_path_buf(),
        made,
        keep: false,
    };
    std::fs::write(
        dir.join(SCRATCH_MARKER),
        "scratch space of brickworld: emptied without asking by the next run\n",
    )
    .map_err(|e| format!("cannot write in {shown}: {e}"))?;
    live().push((scratch.dir.clone(), scratch.made.clone()));
    Ok(scratch)
}
