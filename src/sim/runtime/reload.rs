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
use rustc_hash::{FxHashMap, FxHashSet};

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
    /// `dir` made absolute: the paths it reports are named as the watch's
    /// events name them, so one change is not reported twice.
    abs: PathBuf,
    /// The watched directory's identity (device, inode), if known.
    identity: Option<(u64, u64)>,
    checked: Instant,
    notes: Vec<String>,
    /// The last failure to watch the directory anew, said once.
    last_failure: Option<String>,
    /// What each `.lua` link in the directory pointed at when last looked
    /// at (the target's identity, size and times; `None` when dangling):
    /// the directory's watch sees a link replaced, not its target edited.
    links: FxHashMap<PathBuf, Option<Target>>,
    /// Links whose target changed at the last recheck: reported once it
    /// has not changed for a whole recheck (a target being written is not
    /// read half-way).
    settling: FxHashSet<PathBuf>,
    /// The folder's permissions and owner: a change of them asks for every
    /// script again, a change of its times does not.
    access: Option<(u32, u32, u32)>,
}

/// A folder's permission bits and owner.
fn access(dir: &Path) -> Option<(u32, u32, u32)> {
    let m = std::fs::metadata(dir).ok()?;
    #[cfg(unix)]
    {
        use std::os::unix::fs::{MetadataExt, PermissionsExt};
        Some((m.permissions().mode(), m.uid(), m.gid()))
    }
    #[cfg(not(unix))]
    {
        Some((m.permissions().readonly() as u32, 0, 0))
    }
}

/// A link target's identity, size and change times.
type Target = (u64, u64, u64, i64, i64, i64, i64);

fn target(path: &Path) -> Option<Target> {
    let m = std::fs::metadata(path).ok()?;
    #[cfg(unix)]
    {
        use std::os::unix::fs::MetadataExt;
        Some((
            m.dev(),
            m.ino(),
            m.len(),
            m.mtime(),
            m.mtime_nsec(),
            m.ctime(),
            m.ctime_nsec(),
        ))
    }
    #[cfg(not(unix))]
    {
        let t = m
            .modified()
            .ok()?
            .duration_since(std::time::UNIX_EPOCH)
            .ok()?;
        Some((
            0,
            0,
            m.len(),
            t.as_secs() as i64,
            t.subsec_nanos() as i64,
            0,
            0,
        ))
    }
}

/// The `.lua` links in `dir` and what they point at.
fn scan_links(dir: &Path) -> FxHashMap<PathBuf, Option<Target>> {
    let mut out = FxHashMap::default();
    let Ok(rd) = std::fs::read_dir(dir) else {
        return out;
    };
    for e in rd.flatten() {
        let p = e.path();
        if p.extension().is_some_and(|x| x == "lua") && e.file_type().is_ok_and(|t| t.is_symlink())
        {
            let t = target(&p);
            out.insert(p, t);
        }
    }
    out
}

/// The `.lua` files in `dir`.
fn lua_files(dir: &Path) -> Vec<PathBuf> {
    let Ok(rd) = std::fs::read_dir(dir) else {
        return Vec::new();
    };
    rd.flatten()
        .map(|e| e.path())
        .filter(|p| p.extension().is_some_and(|x| x == "lua"))
        .collect()
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

/// Watch `dir`, whose absolute path is `own`: notify reports the
/// directory's own events under the absolute path it watches (a relative
/// `dir` is joined to the working directory), so they are compared with
/// that (regression: a relative scripts dir, the usual case, never matched).
fn watch(
    dir: &Path,
    own: PathBuf,
    tx: crossbeam_channel::Sender<PathBuf>,
) -> Result<Watch, SimError> {
    let lost = Arc::new(AtomicBool::new(false));
    let flag = lost.clone();
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
        // The directory's own permissions or owner changed: a script that
        // could not be read may be readable now, and no event names it
        // (regression, hot-edit probe: an edit made while the folder was
        // unreadable failed, and was never tried again). The directory's
        // path, which is no `.lua`, asks for all of its scripts.
        if matches!(ev.kind, EventKind::Modify(ModifyKind::Metadata(_)))
            && ev.paths.iter().any(|p| p == &own)
        {
            let _ = tx.send(own.clone());
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
    // notify starts its event loop's thread without checking that it
    // started. With none (the process at its thread limit, `ulimit -u`),
    // `watch` panicked, and so did dropping the watcher, which aborted
    // the engine (regression, hostile environment probe). `configure`
    // asks the loop and fails cleanly when no thread runs it; such a
    // watcher is forgotten, never dropped.
    if watcher.configure(notify::Config::default()).is_err() {
        std::mem::forget(watcher);
        return Err(SimError::Internal(format!(
            "cannot watch {}: cannot start the watcher's thread (is the process at its thread limit? see ulimit -u)",
            dir.display()
        )));
    }
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
        let abs = std::path::absolute(dir).unwrap_or_else(|_| dir.to_path_buf());
        let watcher = watch(dir, abs.clone(), tx.clone())?;
        Ok(ScriptWatcher {
            watcher: Some(watcher),
            events,
            tx,
            pending: FxHashMap::default(),
            debounce,
            dir: dir.to_path_buf(),
            abs: abs.clone(),
            identity: identity(dir),
            checked: Instant::now(),
            notes: Vec::new(),
            last_failure: None,
            links: scan_links(&abs),
            settling: FxHashSet::default(),
            access: access(&abs),
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
        // A script that is a link: its target edited in place (regression,
        // hot-edit probe: such edits were never reloaded; a restart loaded
        // them). Looked at once per recheck.
        let links = scan_links(&self.abs);
        for (p, t) in &links {
            if self.links.get(p).is_some_and(|old| old != t) {
                self.settling.insert(p.clone());
            } else if self.settling.remove(p) {
                self.pending.insert(p.clone(), now);
            }
        }
        self.settling.retain(|p| links.contains_key(p));
        self.links = links;
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
        match watch(&self.dir, self.abs.clone(), self.tx.clone()) {
            Ok(w) => {
                self.watcher = Some(w);
                self.last_failure = None;
                self.notes.push(format!(
                    "the scripts directory {shown} was replaced: watching the new one and reloading its scripts"
                ));
                for p in lua_files(&self.abs) {
                    self.pending.insert(p, now);
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
        let events: Vec<PathBuf> = self.events.try_iter().collect();
        for p in events {
            if p.extension().is_some_and(|x| x == "lua") {
                // A link replaced is reported by its event: what it points
                // at now is the known target (review: a re-pointed link
                // was reloaded twice, by its event and by the recheck).
                if let Some(known) = self.links.get_mut(&p) {
                    *known = target(&p);
                    self.settling.remove(&p);
                }
                self.pending.insert(p, now);
            } else {
                // The folder's attributes: only a change of its
                // permissions or owner asks for every script (review: a
                // `touch` of the folder reloaded them all).
                let now_access = access(&self.abs);
                if now_access != self.access {
                    self.access = now_access;
                    for p in lua_files(&self.abs) {
                        self.pending.insert(p, now);
                    }
                }
            }
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
