//! Hot reload: watch a scripts *directory* (editors save by renaming a temp
//! file over the original, so watching single files misses saves), debounce
//! the events, and report each `.lua` file once its changes have settled.
//!
//! The caller then reloads the script with
//! [`Simulation::replace_script`](crate::sim::Simulation::replace_script), which
//! compiles it in a fresh VM and smoke-tests it before swapping it in at a
//! step boundary; a broken save leaves the last good version running.

use std::path::{Path, PathBuf};
use std::sync::Arc;
use std::sync::atomic::{AtomicBool, Ordering};
use std::time::{Duration, Instant};

use crossbeam_channel::{Receiver, unbounded};
use notify::event::ModifyKind;
use notify::{EventKind, RecursiveMode, Watcher};
use rustc_hash::FxHashMap;

use crate::sim::SimError;

/// A debounced watcher of one directory's `.lua` files. A directory that
/// is replaced (removed and made again, or another moved into its place)
/// is watched anew within [`RECHECK`], and its scripts are reported as
/// changed (regression: hot reload stopped silently, and a moved-away
/// directory's edits were read from the new one).
pub struct ScriptWatcher {
    watcher: Option<Watch>,
    events: Receiver<PathBuf>,
    tx: crossbeam_channel::Sender<PathBuf>,
    pending: FxHashMap<PathBuf, Instant>,
    debounce: Duration,
    dir: PathBuf,
    /// The watched directory's identity (device, inode), if known.
    identity: Option<(u64, u64)>,
    checked: Instant,
    notes: Vec<String>,
    /// The last failure to watch the directory anew, said once.
    last_failure: Option<String>,
}

/// How often the watched directory's identity is checked.
pub const RECHECK: Duration = Duration::from_secs(1);

fn identity(dir: &Path) -> Option<(u64, u64)> {
    let m = std::fs::metadata(dir).ok().filter(|m| m.is_dir())?;
    #[cfg(unix)]
    {
        use std::os::unix::fs::MetadataExt;
        Some((m.dev(), m.ino()))
    }
    #[cfg(not(unix))]
    {
        let _ = m;
        Some((0, 0))
    }
}

/// A watch on one directory, and whether it was lost: the directory itself
/// was removed or moved (its watch then ends), or events were dropped.
struct Watch {
    _watcher: notify::RecommendedWatcher,
    lost: Arc<AtomicBool>,
}

fn watch(dir: &Path, tx: crossbeam_channel::Sender<PathBuf>) -> Result<Watch, SimError> {
    let lost = Arc::new(AtomicBool::new(false));
    let flag = lost.clone();
    // notify reports the directory's own events under the absolute path
    // it watches (a relative `dir` is joined to the working directory):
    // compare with that (regression: a relative scripts dir, the usual
    // case, never matched).
    let own = std::path::absolute(dir).unwrap_or_else(|_| dir.to_path_buf());
    let mut watcher = notify::recommended_watcher(move |res: notify::Result<notify::Event>| {
        let Ok(ev) = res else { return };
        // The directory itself removed or renamed: its inode may come back
        // at once for a new directory made in its place (`rm -rf scripts &&
        // cp -r backup scripts` on ext4), so identity alone cannot tell
        // (regression).
        if ev.need_rescan()
            || (matches!(
                ev.kind,
                EventKind::Remove(_) | EventKind::Modify(ModifyKind::Name(_))
            ) && ev.paths.iter().any(|p| p == &own))
        {
            flag.store(true, Ordering::Relaxed);
        }
        // Removals too: a deleted script is then reported (its reload
        // fails, the loaded version runs on, and /status says why);
        // regression: it was said nowhere.
        if matches!(
            ev.kind,
            EventKind::Create(_) | EventKind::Modify(_) | EventKind::Remove(_)
        ) {
            for p in ev.paths {
                if p.extension().is_some_and(|e| e == "lua") {
                    let _ = tx.send(p);
                }
            }
        }
    })
    .map_err(|e| SimError::Internal(format!("cannot watch {}: {e}", dir.display())))?;
    watcher
        .watch(dir, RecursiveMode::NonRecursive)
        .map_err(|e| SimError::Internal(format!("cannot watch {}: {e}", dir.display())))?;
    Ok(Watch {
        _watcher: watcher,
        lost,
    })
}

impl ScriptWatcher {
    /// Watch `dir`; a file is reported `debounce` after its last event.
    pub fn new(dir: &Path, debounce: Duration) -> Result<Self, SimError> {
        let (tx, events) = unbounded();
        let watcher = watch(dir, tx.clone())?;
        Ok(ScriptWatcher {
            watcher: Some(watcher),
            events,
            tx,
            pending: FxHashMap::default(),
            debounce,
            dir: dir.to_path_buf(),
            identity: identity(dir),
            checked: Instant::now(),
            notes: Vec::new(),
            last_failure: None,
        })
    }

    /// What happened to the watched directory since the last call (a
    /// replacement, a removal), as lines for the log.
    pub fn take_notes(&mut self) -> Vec<String> {
        std::mem::take(&mut self.notes)
    }

    /// Watch the directory anew if it was replaced or removed.
    fn recheck(&mut self, now: Instant) {
        if now.duration_since(self.checked) < RECHECK {
            return;
        }
        self.checked = now;
        let id = identity(&self.dir);
        let lost = self
            .watcher
            .as_ref()
            .is_some_and(|w| w.lost.load(Ordering::Relaxed));
        if id == self.identity && !lost {
            return;
        }
        let shown = self.dir.display();
        self.identity = id;
        // The old watcher's events name paths in a directory that is not
        // this one any more: drop it and them.
        self.watcher = None;
        while self.events.try_recv().is_ok() {}
        self.pending.clear();
        if id.is_none() {
            self.notes.push(format!(
                "warning: the scripts directory {shown} is gone: hot reload resumes when it is back"
            ));
            return;
        }
        match watch(&self.dir, self.tx.clone()) {
            Ok(w) => {
                self.watcher = Some(w);
                self.last_failure = None;
                self.notes.push(format!(
                    "the scripts directory {shown} was replaced: watching the new one and reloading its scripts"
                ));
                if let Ok(rd) = std::fs::read_dir(&self.dir) {
                    for e in rd.flatten() {
                        let p = e.path();
                        if p.extension().is_some_and(|e| e == "lua") {
                            self.pending.insert(p, now);
                        }
                    }
                }
            }
            Err(e) => {
                // Checked again at the next recheck; said once per distinct
                // failure (regression: at the inotify limit it was said
                // every second for ever).
                self.identity = None;
                let note = format!("warning: {e}: hot reload is paused");
                if self.last_failure.as_deref() != Some(note.as_str()) {
                    self.notes.push(note.clone());
                    self.last_failure = Some(note);
                }
            }
        }
    }

    /// Files whose changes have settled since the last call, sorted.
    pub fn poll(&mut self) -> Vec<PathBuf> {
        let now = Instant::now();
        self.recheck(now);
        for p in self.events.try_iter() {
            self.pending.insert(p, now);
        }
        let mut ready: Vec<PathBuf> = self
            .pending
            .iter()
            .filter(|(_, t)| now.duration_since(**t) >= self.debounce)
            .map(|(p, _)| p.clone())
            .collect();
        for p in &ready {
            self.pending.remove(p);
        }
        ready.sort();
        ready
    }
}
