//! Hot reload: watch a scripts *directory* (editors save by renaming a temp
//! file over the original, so watching single files misses saves), debounce
//! the events, and report each `.lua` file once its changes have settled.
//!
//! The caller then reloads the script with
//! [`Simulation::replace_script`](crate::sim::Simulation::replace_script), which
//! compiles it in a fresh VM and smoke-tests it before swapping it in at a
//! step boundary; a broken save leaves the last good version running.

use std::path::{Path, PathBuf};
use std::time::{Duration, Instant};

use crossbeam_channel::{Receiver, unbounded};
use notify::{EventKind, RecursiveMode, Watcher};
use rustc_hash::FxHashMap;

use crate::sim::SimError;

/// A debounced watcher of one directory's `.lua` files.
pub struct ScriptWatcher {
    _watcher: notify::RecommendedWatcher,
    events: Receiver<PathBuf>,
    pending: FxHashMap<PathBuf, Instant>,
    debounce: Duration,
}

impl ScriptWatcher {
    /// Watch `dir`; a file is reported `debounce` after its last event.
    pub fn new(dir: &Path, debounce: Duration) -> Result<Self, SimError> {
        let (tx, events) = unbounded();
        let mut watcher = notify::recommended_watcher(move |res: notify::Result<notify::Event>| {
            if let Ok(ev) = res
                && matches!(ev.kind, EventKind::Create(_) | EventKind::Modify(_))
            {
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
        Ok(ScriptWatcher {
            _watcher: watcher,
            events,
            pending: FxHashMap::default(),
            debounce,
        })
    }

    /// Files whose changes have settled since the last call, sorted.
    pub fn poll(&mut self) -> Vec<PathBuf> {
        let now = Instant::now();
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
