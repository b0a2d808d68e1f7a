//! One VM per script per worker thread, created lazily and kept in a
//! thread-local cache; a VM whose kernel failed is dropped and rebuilt on
//! its next use, so no half-finished state survives an error.

use std::cell::RefCell;

use rustc_hash::FxHashMap;

use crate::sim::{Limits, ScriptSource, ScriptVm, SimError};

/// Most scripts' VMs kept per thread (a reload makes a new one).
const MAX_CACHED: usize = 32;

thread_local! {
    static VMS: RefCell<FxHashMap<u64, (ScriptVm, u64)>> = RefCell::new(FxHashMap::default());
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
