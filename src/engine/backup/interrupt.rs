//! What Ctrl-C or SIGTERM does to `brickworld import`: the phase the
//! import is in ([`Phase`], set by the import as it goes) decides what an
//! interrupt leaves and what it says, in one line with status 130, where
//! the signal's default ended the process without a word (the last note's
//! gap).

use std::path::PathBuf;
use std::sync::Mutex;

/// Where this process's import stands.
#[derive(Clone, Debug)]
pub(super) enum Phase {
    /// Not importing yet (the state directory is not claimed).
    Idle,
    /// Reading and checking the backup: nothing is written but what
    /// claiming the state directory made (`made`: the folders it created,
    /// or the lock file it added to an existing one), removed again.
    Checking {
        made: Vec<PathBuf>,
        lock_file: Option<PathBuf>,
        /// The marker an earlier import cut short left there, which stays.
        marker: PathBuf,
    },
    /// Writing the world under the import's marker into `dir`: a cut
    /// leaves the marker, which `run` and `export` refuse and an import
    /// again redoes.
    Writing { dir: PathBuf },
    /// The marker is gone: the world is imported, and the command ends in
    /// a moment with its own message.
    Done,
}

static PHASE: Mutex<Phase> = Mutex::new(Phase::Idle);

/// The command that redoes this import, as the user typed it (with its
/// `--world`: without it another world's config was named; review).
static REDO: std::sync::OnceLock<String> = std::sync::OnceLock::new();

/// The last [`Phase::Checking`] entered: what an import that gives up
/// after it began writing returns to, so that an interrupt then still
/// removes what claiming the directory made.
static CHECKING: Mutex<Option<Phase>> = Mutex::new(None);

/// The import is now in `phase`. An interrupt waits for this to return, so
/// it never sees a phase whose work has begun before it was entered.
pub(super) fn enter(phase: Phase) {
    if matches!(phase, Phase::Checking { .. }) {
        *CHECKING.lock().unwrap_or_else(|e| e.into_inner()) = Some(phase.clone());
    }
    *PHASE.lock().unwrap_or_else(|e| e.into_inner()) = phase;
}

/// [`enter_after`] the last [`Phase::Checking`] (or [`Phase::Idle`]).
pub(super) fn back_to_checking_after<E>(step: impl FnOnce() -> Result<(), E>) -> Result<(), E> {
    enter_after(last_checking(), step)
}

/// Back to the last [`Phase::Checking`] (or [`Phase::Idle`]) now.
pub(super) fn back_to_checking() {
    enter(last_checking());
}

fn last_checking() -> Phase {
    let checking = CHECKING.lock().unwrap_or_else(|e| e.into_inner()).clone();
    checking.unwrap_or(Phase::Idle)
}

/// Do `step` and, if it succeeds, enter `phase`, with interrupts held off
/// in between: an interrupt sees the phase before `step` or the one after
/// it (review: the marker was written after the phase said it was there).
pub(super) fn enter_after<E>(phase: Phase, step: impl FnOnce() -> Result<(), E>) -> Result<(), E> {
    let mut now = PHASE.lock().unwrap_or_else(|e| e.into_inner());
    step()?;
    *now = phase;
    Ok(())
}

/// From now on, Ctrl-C or SIGTERM ends an import by its [`Phase`]: before
/// it writes, it removes what claiming the directory made and says nothing
/// was imported; while it writes, it says the import did not finish and
/// how to redo it; once it is done, the import ends as it would have. For
/// the `import` command only (the handler is the process's one); `redo`
/// is the command line that redoes the import.
pub fn say_interrupted_imports(redo: String) -> std::io::Result<()> {
    let _ = REDO.set(redo);
    ctrlc::set_handler(|| {
        // Held until exit: the import cannot move on to its next phase.
        let phase = PHASE.lock().unwrap_or_else(|e| e.into_inner());
        match &*phase {
            Phase::Done => return,
            Phase::Idle => crate::say!("interrupted: nothing was imported"),
            Phase::Checking {
                made,
                lock_file,
                marker,
            } => {
                if !made.is_empty() {
                    crate::files::remove_made(made);
                } else if let Some(l) = lock_file {
                    let _ = std::fs::remove_file(l);
                }
                // Redoing a cut import: the directory stays refused, and
                // says so (stop-path probe: "as it was" hid it).
                if std::fs::symlink_metadata(marker).is_ok() {
                    crate::say!(
                        "interrupted: nothing was imported; the directory still holds the earlier interrupted import, refused until `{}` is run again",
                        REDO.get().map_or("brickworld import", String::as_str)
                    );
                } else {
                    crate::say!(
                        "interrupted: nothing was imported (the state directory is as it was)"
                    );
                }
            }
            Phase::Writing { dir } => crate::say!(
                "interrupted: the import into {} did not finish, and the directory is refused until `{}` is run again",
                dir.display(),
                REDO.get().map_or("brickworld import", String::as_str)
            ),
        }
        std::process::exit(130);
    })
    .map_err(std::io::Error::other)
}
