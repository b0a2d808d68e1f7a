//! A state directory's checkpoints: listing them, retention of the newest
//! [`KEEP`] that verify as this world's, corrupt files set aside as
//! `*.corrupt`, and finding the newest good one.

use std::fs;
use std::path::{Path, PathBuf};

use super::file::{read, read_checked, write_at};
use super::{CheckpointError, KEEP, WorldIdentity, WorldRef, WorldState, io};

fn file_name(tick: u64) -> String {
    format!("ckpt-{tick:016}.bwc")
}

/// The checkpoint files in `dir`, newest first.
pub fn list(dir: &Path) -> Result<Vec<PathBuf>, CheckpointError> {
    let mut out: Vec<PathBuf> = match fs::read_dir(dir) {
        Ok(rd) => rd
            .filter_map(|e| e.ok().map(|e| e.path()))
            .filter(|p| {
                p.file_name()
                    .and_then(|n| n.to_str())
                    .is_some_and(|n| n.starts_with("ckpt-") && n.ends_with(".bwc"))
            })
            .collect(),
        Err(e) if e.kind() == std::io::ErrorKind::NotFound => Vec::new(),
        Err(e) => return Err(io(dir, e)),
    };
    out.sort();
    out.reverse();
    Ok(out)
}

/// Write a checkpoint of `state` into `dir` atomically, keeping the newest
/// [`KEEP`] that verify (see [`Checkpoints`]). Returns its path and world
/// hash. On any error (a full disk, say) the previous checkpoints are
/// untouched.
pub fn write(dir: &Path, state: &WorldState) -> Result<(PathBuf, u64), CheckpointError> {
    let mut set = Checkpoints::scan(dir, state.identity.clone())?;
    set.write(WorldRef {
        tick: state.tick,
        store: &state.store,
        bounds: state.bounds,
        channels: &state.channels,
        params: &state.params,
        identity: state.identity.as_ref(),
        extras: &state.extras,
    })
}

/// What [`Checkpoints::open`] returns: the set, the newest of this world's
/// checkpoints that verified (with its path), and warnings to show.
pub type Opened = (Checkpoints, Option<(PathBuf, WorldState)>, Vec<String>);

/// A state directory's checkpoints, as one engine sees them: which files
/// verified as this world's, so retention never counts a corrupt, foreign
/// or stray file, and never deletes the file it just wrote.
#[derive(Debug)]
pub struct Checkpoints {
    dir: PathBuf,
    identity: Option<WorldIdentity>,
    /// This world's verified checkpoints, oldest first.
    good: Vec<PathBuf>,
}

impl Checkpoints {
    /// Scan `dir`: files whose header, identity and payload checksum verify
    /// (and belong to `identity`, when given) count for retention; corrupt
    /// files are renamed `*.corrupt`; foreign ones are left alone.
    pub fn scan(dir: &Path, identity: Option<WorldIdentity>) -> Result<Self, CheckpointError> {
        let mut good = Vec::new();
        for path in list(dir)?.into_iter().rev() {
            match read_checked(&path, false) {
                Ok((_, id)) if matches_world(identity.as_ref(), id.as_ref()) => good.push(path),
                Ok(_) => {}
                // A checkpoint's name on another kind of file is a damaged
                // checkpoint too.
                Err(CheckpointError::Corrupt { .. } | CheckpointError::NotACheckpoint { .. }) => {
                    quarantine(&path)
                }
                Err(_) => {}
            }
        }
        Ok(Checkpoints {
            dir: dir.to_path_buf(),
            identity,
            good,
        })
    }

    /// The newest checkpoint of this world that fully verifies, with the
    /// problems met on the way (newer corrupt files, renamed `*.corrupt`,
    /// and other worlds' checkpoints, skipped). Files found good count for
    /// retention.
    pub fn open(dir: &Path, identity: WorldIdentity) -> Result<Opened, CheckpointError> {
        let mut warnings = Vec::new();
        let mut found = None;
        let mut good = Vec::new();
        for path in list(dir)? {
            if found.is_some() {
                // Older files: a cheap check is enough to count them.
                if let Ok((_, id)) = read_checked(&path, false)
                    && matches_world(Some(&identity), id.as_ref())
                {
                    good.push(path);
                }
                continue;
            }
            match read(&path) {
                Ok(st) => match &st.identity {
                    Some(id) if !id.same_world(&identity) => warnings.push(format!(
                        "{} belongs to another world ({id}, this is {identity}); skipped and left alone",
                        path.display()
                    )),
                    id => {
                        match id {
                            None => warnings.push(format!(
                                "{} predates world identities (format 1); assuming it is this world",
                                path.display()
                            )),
                            Some(id) if id.config_hash != identity.config_hash => warnings.push(format!(
                                "the world config changed since {} was written; resuming with the new config",
                                path.display()
                            )),
                            Some(_) => {}
                        }
                        good.push(path.clone());
                        found = Some((path, st));
                    }
                },
                Err(e @ (CheckpointError::Corrupt { .. } | CheckpointError::NotACheckpoint { .. })) => {
                    warnings.push(format!("{e}; renamed to *.corrupt and skipped"));
                    quarantine(&path);
                }
                Err(e) => warnings.push(format!("{e}; skipped")),
            }
        }
        good.reverse();
        Ok((
            Checkpoints {
                dir: dir.to_path_buf(),
                identity: Some(identity),
                good,
            },
            found,
            warnings,
        ))
    }

    /// The verified checkpoints retention counts, oldest first.
    pub fn good(&self) -> &[PathBuf] {
        &self.good
    }

    /// Write a checkpoint atomically, then delete this world's verified
    /// checkpoints beyond the newest [`KEEP`] (never the one just written).
    pub fn write(&mut self, state: WorldRef<'_>) -> Result<(PathBuf, u64), CheckpointError> {
        let state = WorldRef {
            identity: state.identity.or(self.identity.as_ref()),
            ..state
        };
        let (path, hash) = write_file(&self.dir, state)?;
        self.good.retain(|p| p != &path);
        self.good.push(path.clone());
        while self.good.len() > KEEP {
            let old = self.good.remove(0);
            let _ = fs::remove_file(old);
        }
        Ok((path, hash))
    }
}

fn matches_world(want: Option<&WorldIdentity>, got: Option<&WorldIdentity>) -> bool {
    match (want, got) {
        (Some(w), Some(g)) => w.same_world(g),
        _ => true,
    }
}

/// Rename a corrupt checkpoint out of the way (kept for inspection).
fn quarantine(path: &Path) {
    let mut to = path.as_os_str().to_owned();
    to.push(".corrupt");
    let _ = fs::rename(path, PathBuf::from(to));
}

fn write_file(dir: &Path, state: WorldRef<'_>) -> Result<(PathBuf, u64), CheckpointError> {
    fs::create_dir_all(dir).map_err(|e| io(dir, e))?;
    let path = dir.join(file_name(state.tick));
    let hash = write_at(&path, state)?;
    // Temp files left in the state directory by a process killed mid-write
    // never load; drop them. Only here: an export's folder is the user's
    // (regression: export deleted a user's `.ckpt-9.tmp`).
    if let Ok(rd) = fs::read_dir(dir) {
        for e in rd.flatten() {
            let n = e.file_name();
            let n = n.to_string_lossy();
            if n.starts_with(".ckpt-") && n.ends_with(".tmp") && e.path() != path {
                let _ = fs::remove_file(e.path());
            }
        }
    }
    Ok((path, hash))
}

/// What [`latest`] found.
#[derive(Debug)]
pub struct Latest {
    /// The newest checkpoint that verified, and its state.
    pub found: Option<(PathBuf, WorldState)>,
    /// Newer checkpoints that failed to verify (to report).
    pub skipped: Vec<CheckpointError>,
}

/// The newest checkpoint in `dir` that verifies, whatever its world, with
/// the problems of any newer ones skipped on the way (files are not
/// renamed: this only reads).
pub fn latest(dir: &Path) -> Result<Latest, CheckpointError> {
    let mut skipped = Vec::new();
    for path in list(dir)? {
        match read(&path) {
            Ok(s) => {
                return Ok(Latest {
                    found: Some((path, s)),
                    skipped,
                });
            }
            Err(e) => skipped.push(e),
        }
    }
    Ok(Latest {
        found: None,
        skipped,
    })
}
