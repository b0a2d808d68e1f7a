//! One VM per script per worker thread, created lazily and kept in a
//! thread-local cache; a VM whose kernel failed is dropped and rebuilt on
//! its next use, so no half-finished state survives an error. A script's
//! VMs are keyed by its [`VmId`]; when the script is replaced (a hot
//! reload) or removed, its id is dropped and every worker frees those VMs
//! at its next use of the cache.

use std::cell::{Cell, RefCell};
use std::sync::Mutex;
use std::sync::atomic::{AtomicU64, Ordering};

use rustc_hash::FxHashMap;

use crate::sim::{Limits, ScriptSource, ScriptSpec, ScriptVm, SimError, StepKey};

/// Most scripts' VMs kept per thread (a reload makes a new one).
const MAX_CACHED: usize = 32;

thread_local! {
    static VMS: RefCell<FxHashMap<u64, (ScriptVm, u64)>> = RefCell::new(FxHashMap::default());
    /// The [`RETIRED`] length this thread's cache was last swept at.
    static SWEPT: Cell<usize> = const { Cell::new(0) };
}

/// Ids of scripts that are gone, in the order they went.
static RETIRED: Mutex<Vec<u64>> = Mutex::new(Vec::new());
/// `RETIRED`'s length, read without the lock.
static RETIRED_LEN: AtomicU64 = AtomicU64::new(0);
static NEXT_ID: AtomicU64 = AtomicU64::new(1);

/// A loaded script's key in the workers' VM caches, unique for the
/// process's life. Dropping it frees the script's VMs on every worker
/// (regression, hostile probe: each hot reload kept the old version's VMs,
/// up to 32 per thread, about 75 MB a reload of a script holding a large
/// table, until the daemon aborted out of memory).
#[derive(Debug)]
pub struct VmId(u64);

impl VmId {
    /// A fresh id.
    pub fn new() -> Self {
        VmId(NEXT_ID.fetch_add(1, Ordering::Relaxed))
    }

    /// The id's value.
    pub fn get(&self) -> u64 {
        self.0
    }
}

impl Default for VmId {
    fn default() -> Self {
        Self::new()
    }
}

impl Drop for VmId {
    fn drop(&mut self) {
        let mut r = RETIRED.lock().unwrap_or_else(|p| p.into_inner());
        r.push(self.0);
        RETIRED_LEN.store(r.len() as u64, Ordering::Release);
    }
}

/// Drop this thread's VMs of scripts retired since its last sweep.
fn sweep(map: &mut FxHashMap<u64, (ScriptVm, u64)>) {
    let len = RETIRED_LEN.load(Ordering::Acquire) as usize;
    let seen = SWEPT.get();
    if len == seen {
        return;
    }
    let r = RETIRED.lock().unwrap_or_else(|p| p.into_inner());
    for uid in &r[seen.min(r.len())..] {
        map.remove(uid);
    }
    SWEPT.set(r.len());
}

/// VMs in this thread's cache (for tests).
pub fn cached_here() -> usize {
    VMS.with(|cell| {
        let mut map = cell.borrow_mut();
        sweep(&mut map);
        map.len()
    })
}

/// One step of one script as its VMs see it: the step's `dt`, its serial
/// (a VM is prepared once per serial) and its random key.
#[derive(Clone, Copy, Debug)]
pub struct StepStamp {
    /// Simulated time the step covers.
    pub dt: f64,
    /// The step's serial: a VM prepared for it is not prepared again.
    pub serial: u64,
    /// The step's random key.
    pub key: StepKey,
}

impl StepStamp {
    /// Prepare `vm` for this step unless it already is: `prepared` holds
    /// the serial it was last prepared for.
    pub fn prepare(
        &self,
        vm: &mut ScriptVm,
        prepared: &mut u64,
        (spec, params, materials): (&ScriptSpec, &[f64], &[u8]),
    ) -> Result<(), SimError> {
        if *prepared != self.serial {
            vm.begin_step(self.dt, spec, params, self.key, materials)?;
            *prepared = self.serial;
        }
        Ok(())
    }
}

/// One pass of a script and the channels it reads and writes, as indices
/// into the script's channels.
#[derive(Clone, Copy, Debug)]
pub struct PassChannels<'a> {
    /// The pass's index in its script.
    pub pass: usize,
    /// Channels it reads.
    pub reads: &'a [usize],
    /// Channels it writes.
    pub writes: &'a [usize],
}

/// Run `f` with this thread's VM for the script loaded as `uid` (loading
/// `src` if needed) and the serial of the step it was last prepared for.
pub fn with_vm<R>(
    uid: u64,
    src: &ScriptSource,
    limits: Limits,
    f: impl FnOnce(&mut ScriptVm, &mut u64) -> Result<R, SimError>,
) -> Result<R, SimError> {
    VMS.with(|cell| {
        let mut map = cell.borrow_mut();
        sweep(&mut map);
        if !map.contains_key(&uid) {
            if map.len() > MAX_CACHED {
                map.clear();
            }
            let (vm, _) = ScriptVm::load(src, limits)?;
            map.insert(uid, (vm, 0));
        }
        let (vm, prepared) = map.get_mut(&uid).expect("inserted above");
        let r = f(vm, prepared);
        if r.is_err() {
            map.remove(&uid);
        }
        r
    })
}
