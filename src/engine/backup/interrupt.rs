//! What Ctrl-C or SIGTERM does to `brickworld import`: the phase the
//! import is in ([`Phase`], set by the import as it goes) decides what an
//! interrupt leaves and what it says, in one line with status 130, where
//! the signal's default ended the process without a word (the last note's
//! gap).

use std::path::PathBuf;
use std::sync::Mutex;

/// Where this process's import stands.
#[derive(Debug)]
pub(super) enum Phase {
    /// Not importing yet (the state directory is not claimed).
    Idle,
    /// Reading and checking the backup: nothing is written but what
    /// claiming the state directory made (`made`: the folders it created,
    /// or the lock file it added to an existing one), removed again.
    Checking {
        made: Vec<PathBuf>,
        lock_file: Option<PathBuf>,
    },
    /// Writing the world under the import's marker: a cut leaves the
    /// marker, which `run` and `export` refuse and an import again redoes.
    Writing { file: PathBuf, dir: PathBuf },
    /// The marker is gone: the world is imported, and the command ends in
    /// a moment with its own message.
    Done,
}

static PHASE: Mutex<Phase> = Mutex::new(Phase::Idle);

/// The import is now in `phase`. An interrupt waits for this to return, so
/// it never sees a phase whose work has begun before it was entered.
pub(super) fn enter(phase: Phase) {
    *PHASE.lock().unwrap_or_else(|e| e.into_inner()) = phase;
}

/// From now on, Ctrl-C or SIGTERM ends an import by its [`Phase`]: before
/// it writes, it removes what claiming the directory made and says nothing
/// was imported; while it writes, it says the import did not finish and
/// how to redo it; once it is done, the import ends as it would have. For
/// the `import` command only (the handler is the process's one).
pub fn say_interrupted_imports() -> std::io::Result<()> {
    ctrlc::set_handler(|| {
        // Held until exit: the import cannot move on to its next phase.
        let phase = PHASE.lock().unwrap_or_else(|e| e.into_inner());
        match &*phase {
            Phase::Done => return,
            Phase::Idle => crate::say!("interrupted: nothing was imported"),
            Phase::Checking { made, lock_file } => {
                if !made.is_empty() {
                    crate::files::remove_made(made);
                } else if let Some(l) = lock_file {
                    let _ = std::fs::remove_file(l);
                }
                crate::say!("interrupted: nothing was imported (the state directory is as it was)");
            }
            Phase::Writing { file, dir } => crate::say!(
                "interrupted: the import into {} did not finish, and the directory is refused until `brickworld import {} --state {}` is run again",
                dir.display(),
                crate::shell_quoted(file),
                crate::shell_quoted(dir)
            ),
        }
        std::process::exit(130);
    })
    .map_err(std::io::Error::other)
}
