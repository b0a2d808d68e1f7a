//! What Ctrl-C or SIGTERM does to a one-shot command that writes files
//! (`render`, `sim`, `export`, `init`, `chart`, `verify`, the benches):
//! the temporary files it is writing are removed, what it was told to undo
//! is undone, one line says what is left, and it exits with status 130.
//! The engine (`run`), `import` and `soak` handle their signals themselves.
//!
//! The ledger behind it lists, once [`remove_temps_on_interrupt`] is on,
//! every temporary made beside a destination ([`super::fresh_temp_beside`]),
//! the outputs that landed under their names, and what a command asked to
//! undo ([`undo_on_interrupt`]).

use std::path::{Path, PathBuf};
use std::sync::atomic::{AtomicBool, Ordering};

/// Whether an interrupt removes the temporary files being written (see
/// [`remove_temps_on_interrupt`]); only then are they listed.
static INTERRUPTIBLE: AtomicBool = AtomicBool::new(false);

/// What an interrupt acts on.
#[derive(Default)]
struct Ledger {
    /// Temporaries being written, with their destinations.
    writing: Vec<(PathBuf, PathBuf)>,
    /// Temporaries that landed under their destinations' names.
    landed: Vec<(PathBuf, PathBuf)>,
    /// Files, then folders (removed only if empty), to remove: what a
    /// command that is all or nothing has put in place so far.
    undo: Vec<(PathBuf, bool)>,
}

fn ledger() -> std::sync::MutexGuard<'static, Ledger> {
    static LEDGER: std::sync::Mutex<Ledger> = std::sync::Mutex::new(Ledger {
        writing: Vec::new(),
        landed: Vec::new(),
        undo: Vec::new(),
    });
    LEDGER.lock().unwrap_or_else(|e| e.into_inner())
}

/// From now on the temporaries made are listed, for an interrupt handler
/// of another module to remove (`bench store`'s, which also clears its
/// scratch space).
pub(super) fn list_temps() {
    INTERRUPTIBLE.store(true, Ordering::Relaxed);
}

/// Where interrupts remove temporaries, [`landing`], held while a
/// temporary is made and listed: the handler holds it until the process
/// exits, so no temporary appears after it emptied the list.
pub(super) fn hold_for_listing() -> Option<std::sync::MutexGuard<'static, ()>> {
    INTERRUPTIBLE.load(Ordering::Relaxed).then(landing)
}

/// `tmp` was made beside `dest`: listed, where interrupts remove
/// temporaries.
pub(super) fn note_temp(tmp: &Path, dest: &Path) {
    if INTERRUPTIBLE.load(Ordering::Relaxed) {
        ledger()
            .writing
            .push((tmp.to_path_buf(), dest.to_path_buf()));
    }
}

/// Remove the temporary files this process made since
/// [`remove_temps_on_interrupt`]; returns the destinations of those that
/// were still there (those already renamed are gone, and stay so: their
/// names are this process's own).
pub fn remove_writing_temps() -> Vec<PathBuf> {
    std::mem::take(&mut ledger().writing)
        .into_iter()
        .filter(|(tmp, _)| std::fs::remove_file(tmp).is_ok())
        .map(|(_, dest)| dest)
        .collect()
}

/// `tmp` has landed under its final name: an interrupt no longer removes
/// anything of it, and names it as written.
pub fn temp_landed(tmp: &Path) {
    let mut l = ledger();
    if let Some(i) = l.writing.iter().position(|(t, _)| t == tmp) {
        let entry = l.writing.remove(i);
        l.landed.push(entry);
    }
}

/// `tmp` is this process's temporary again (after [`temp_landed`]): an
/// interrupt removes it, where interrupts remove temporaries.
pub fn temp_writing(tmp: &Path) {
    if !INTERRUPTIBLE.load(Ordering::Relaxed) {
        return;
    }
    let mut l = ledger();
    if l.writing.iter().any(|(t, _)| t == tmp) {
        return;
    }
    let entry = match l.landed.iter().position(|(t, _)| t == tmp) {
        Some(i) => l.landed.remove(i),
        None => (tmp.to_path_buf(), tmp.to_path_buf()),
    };
    l.writing.push(entry);
}

/// Held while a file lands by swapping names with another (an export over
/// an earlier backup), or while an all-or-nothing command puts a file in
/// place and lists it for [`undo_on_interrupt`]: an interrupt waits for it,
/// so it never acts on the moment a temporary's name holds another's file
/// (review: a Ctrl-C during the swap back removed a file put at the path
/// meanwhile), nor on a file placed but not yet listed.
pub fn landing() -> std::sync::MutexGuard<'static, ()> {
    static LANDING: std::sync::Mutex<()> = std::sync::Mutex::new(());
    LANDING.lock().unwrap_or_else(|e| e.into_inner())
}

/// An interrupt from now on removes `path` (a file this command put in
/// place; `folder`: a folder it made, removed only if empty), in the
/// reverse order of these calls: for a command that is all or nothing
/// (`init`: an interrupt left 3 of its 10 files, and the next `init`
/// refused the folder; stop-path probe). List a file under [`landing`].
pub fn undo_on_interrupt(path: &Path, folder: bool) {
    if INTERRUPTIBLE.load(Ordering::Relaxed) {
        ledger().undo.push((path.to_path_buf(), folder));
    }
}

/// The command is done: an interrupt no longer undoes what it listed.
pub fn keep_undo_list() {
    ledger().undo.clear();
}

/// Whether the command's output has landed (see [`output_landed`]).
static OUTPUT_LANDED: AtomicBool = AtomicBool::new(false);

/// The output of a command that [`remove_temps_on_interrupt`] is now
/// complete under its final name: from now on an interrupt lets the
/// command finish instead of ending it with status 130. Call it under
/// [`landing`] where the landing holds it, so that an interrupt waiting
/// for the landing sees it.
pub fn output_landed(dest: &Path) {
    *landed_at() = Some(dest.to_path_buf());
    OUTPUT_LANDED.store(true, Ordering::Release);
}

/// Where the output landed (see [`output_landed`]).
fn landed_at() -> std::sync::MutexGuard<'static, Option<PathBuf>> {
    static AT: std::sync::Mutex<Option<PathBuf>> = std::sync::Mutex::new(None);
    AT.lock().unwrap_or_else(|e| e.into_inner())
}

/// From now on, Ctrl-C or SIGTERM removes the temporary files this process
/// is writing, undoes what it listed ([`undo_on_interrupt`]), says in one
/// line what is left, and exits with status 130 (regressions: an `export`
/// stopped with Ctrl-C left a temporary as large as the backup; `render`,
/// `sim`, `chart` and the benches were killed by the signal, leaving
/// theirs, and an interrupted `export` that had not begun writing said
/// nothing). For commands that have no other use for signals.
pub fn remove_temps_on_interrupt() -> std::io::Result<()> {
    INTERRUPTIBLE.store(true, Ordering::Relaxed);
    ctrlc::set_handler(|| {
        let _landing = landing();
        // The output is complete: the command ends as it would have, in a
        // moment, with its own message and status (regression, hostile
        // environment probe: an export interrupted just after its backup
        // replaced the earlier one exited 130 without a word, as if
        // nothing had been written).
        // A second interrupt then ends it at once, still with status 0:
        // the output is complete (review: a stalled export could not be
        // stopped but by SIGKILL).
        if OUTPUT_LANDED.load(Ordering::Acquire) {
            static ASKED: AtomicBool = AtomicBool::new(false);
            if ASKED.swap(true, Ordering::Relaxed) {
                // Its folder synced first, as the command would have
                // (review: a second Ctrl-C during that sync said "written
                // in full" before the rename was on disk).
                let folder = landed_at()
                    .as_ref()
                    .and_then(|p| p.parent().map(Path::to_path_buf))
                    .filter(|d| !d.as_os_str().is_empty())
                    .unwrap_or_else(|| PathBuf::from("."));
                if std::fs::File::open(&folder)
                    .and_then(|d| d.sync_all())
                    .is_err()
                {
                    crate::say!(
                        "interrupted after the output was written, before its folder was synced"
                    );
                    std::process::exit(130);
                }
                crate::say!("interrupted after the output was written in full");
                std::process::exit(0);
            }
            return;
        }
        let removed = remove_writing_temps();
        let undone = undo();
        let landed: Vec<PathBuf> = ledger().landed.iter().map(|(_, d)| d.clone()).collect();
        crate::say!("{}", interrupted_line(&removed, &landed, undone));
        std::process::exit(130);
    })
    .map_err(std::io::Error::other)
}

/// Undo what [`undo_on_interrupt`] listed, last first; whether anything
/// was listed.
fn undo() -> bool {
    let undo = std::mem::take(&mut ledger().undo);
    for (p, folder) in undo.iter().rev() {
        let _ = if *folder {
            std::fs::remove_dir(p)
        } else {
            std::fs::remove_file(p)
        };
    }
    !undo.is_empty()
}

/// The line an interrupt prints: what was removed, and what was written
/// in full before it.
fn interrupted_line(removed: &[PathBuf], landed: &[PathBuf], undone: bool) -> String {
    let names = |ps: &[PathBuf]| {
        let mut s: Vec<String> = ps.iter().take(3).map(|p| p.display().to_string()).collect();
        if ps.len() > 3 {
            s.push(format!("{} more", ps.len() - 3));
        }
        s.join(", ")
    };
    let mut line = if undone {
        "interrupted: what was written so far was removed".to_string()
    } else if removed.is_empty() {
        "interrupted before anything was written".to_string()
    } else {
        format!(
            "interrupted: the file being written was removed ({})",
            names(removed)
        )
    };
    if !undone && !landed.is_empty() {
        if removed.is_empty() {
            line = "interrupted".to_string();
        }
        line.push_str(&format!("; written in full before it: {}", names(landed)));
    }
    line
}

#[cfg(test)]
mod tests {
    use super::*;

    /// The ledger is the process's: its tests take turns.
    static ONE_AT_A_TIME: std::sync::Mutex<()> = std::sync::Mutex::new(());

    /// What an interrupt removes: the temporaries being written, and not
    /// one that has landed (the review's Ctrl-C during `export`; the
    /// signal itself was tried by hand: exit 130, nothing left).
    #[test]
    fn an_interrupt_removes_the_temporaries_being_written_only() {
        let dir = std::env::temp_dir().join(format!("bw-interrupt-temps-{}", std::process::id()));
        let _ = std::fs::remove_dir_all(&dir);
        std::fs::create_dir_all(&dir).unwrap();
        let _one = ONE_AT_A_TIME.lock().unwrap_or_else(|e| e.into_inner());
        let (a, b) = (dir.join(".a.tmp"), dir.join(".b.tmp"));
        for p in [&a, &b] {
            std::fs::write(p, "x").unwrap();
            ledger().writing.push((p.to_path_buf(), p.to_path_buf()));
        }
        temp_landed(&b);
        assert_eq!(remove_writing_temps(), vec![a.clone()]);
        assert!(!a.exists());
        assert!(b.exists(), "a landed file is not removed");
        assert!(remove_writing_temps().is_empty());
        let _ = std::fs::remove_dir_all(&dir);
    }

    /// The ledger an interrupt reads: a staged output not yet landed is
    /// removed and named, one that landed is named as written, and what
    /// an all-or-nothing command listed is undone, files before folders.
    #[test]
    fn an_interrupt_removes_what_is_being_written_and_undoes_what_was_listed() {
        let dir = std::env::temp_dir().join(format!("bw-interrupt-ledger-{}", std::process::id()));
        std::fs::create_dir_all(&dir).unwrap();
        let _one = ONE_AT_A_TIME.lock().unwrap_or_else(|e| e.into_inner());
        // Listed by hand: turning listing on for the whole test process
        // would let this test remove other tests' temporaries.
        let (done, cut) = (dir.join("a.json"), dir.join("a.svg"));
        let a = super::super::Staged::new(&done).unwrap();
        ledger()
            .writing
            .push((a.path().to_path_buf(), done.clone()));
        std::fs::write(a.path(), "{}").unwrap();
        a.commit().unwrap();
        let b = super::super::Staged::new(&cut).unwrap();
        ledger().writing.push((b.path().to_path_buf(), cut.clone()));
        std::fs::write(b.path(), "<svg").unwrap();
        let removed = remove_writing_temps();
        assert!(
            removed.contains(&cut) && !removed.contains(&done),
            "{removed:?}"
        );
        assert!(!b.path().exists(), "the temporary is still there");
        assert!(ledger().landed.iter().any(|(_, d)| d == &done));
        assert!(done.exists());
        // All or nothing: a folder made, then a file put in it.
        let made = dir.join("made");
        std::fs::create_dir(&made).unwrap();
        ledger().undo.push((made.clone(), true));
        std::fs::write(made.join("f"), "x").unwrap();
        ledger().undo.push((made.join("f"), false));
        assert!(undo());
        assert!(!made.exists(), "the folder made was not removed");
        assert!(!undo(), "undone twice");
        drop(b);
        std::fs::remove_dir_all(&dir).unwrap();
    }

    #[test]
    fn the_interrupt_line_says_what_was_removed_and_what_was_written() {
        let p = |s: &str| PathBuf::from(s);
        assert_eq!(
            interrupted_line(&[], &[], false),
            "interrupted before anything was written"
        );
        assert_eq!(
            interrupted_line(&[p("a.svg")], &[p("a.json")], false),
            "interrupted: the file being written was removed (a.svg); written in full before it: a.json"
        );
        assert_eq!(
            interrupted_line(&[], &[p("1"), p("2"), p("3"), p("4"), p("5")], false),
            "interrupted; written in full before it: 1, 2, 3, 2 more"
        );
        assert_eq!(
            interrupted_line(&[p("x")], &[], true),
            "interrupted: what was written so far was removed"
        );
    }
}
