//! The per-call budget of Luau kernels (instructions, wall-clock time,
//! memory), enforced from Luau's interrupt hook through the raw C API.
//!
//! This is the crate's only `unsafe` code. It exists because a benchmark
//! demanded it: mlua's safe `set_interrupt` wraps every Luau safepoint (each
//! loop back-edge and call) in its error-handling machinery, which cost
//! 15–35 % of kernel time in `brickworld bench sim`. The raw hook below
//! counts in a thread-local and only calls into the C API when a limit is
//! exceeded. It follows Luau's own documented pattern for timeouts: raise an
//! error from the interrupt callback.
//!
//! A VM is only ever used on the thread that created it (VMs live in a
//! thread-local cache), so a thread-local budget is the budget of the VM that
//! is running.
//!
//! **A budget cannot be caught.** Once a limit trips, every later interrupt
//! of the same call raises the error again, so a script that wraps its loop
//! in `pcall` (or loops in an `xpcall` handler) is stopped at its next loop
//! back-edge or call; and [`tripped`] tells the caller, after the kernel
//! returns, that its budget ran out even if the script swallowed every error.

use std::cell::Cell;
use std::ffi::c_int;
use std::time::Instant;

use mlua::{Lua, ffi};

#[derive(Clone, Copy)]
struct Budget {
    /// The limit that tripped, if one did; it stays set (and is raised again
    /// at every interrupt) until [`arm`] starts the next call.
    tripped: Option<&'static str>,
    ticks: u64,
    limit: u64,
    deadline: Instant,
    memory_soft_kb: c_int,
}

thread_local! {
    static BUDGET: Cell<Budget> = Cell::new(Budget {
        tripped: None,
        ticks: 0,
        limit: u64::MAX,
        deadline: Instant::now() + std::time::Duration::from_secs(3600),
        memory_soft_kb: c_int::MAX,
    });
}

/// Reset the budget before a kernel call on this thread.
pub fn arm(instructions: u64, deadline: Instant, memory_soft_bytes: usize) {
    BUDGET.with(|b| {
        b.set(Budget {
            tripped: None,
            ticks: 0,
            limit: instructions,
            deadline,
            memory_soft_kb: (memory_soft_bytes / 1024).min(c_int::MAX as usize) as c_int,
        })
    });
}

/// Which limit, if any, the running kernel has exceeded (counts one tick).
fn exceeded(l: *mut ffi::lua_State) -> Option<&'static str> {
    BUDGET.with(|cell| {
        let mut b = cell.get();
        if b.tripped.is_some() {
            // Sticky: a caught budget error is raised again.
            return b.tripped;
        }
        b.ticks += 1;
        let mut what = None;
        if b.ticks > b.limit {
            what = Some("instruction budget");
        } else if b.ticks & 1023 == 0 && Instant::now() > b.deadline {
            what = Some("time budget");
        } else if b.ticks & 255 == 0 {
            // SAFETY: `l` is the live state Luau passed to the interrupt
            // hook; LUA_GCCOUNT only reads the allocator's counter.
            let kb = unsafe { ffi::lua_gc(l, ffi::LUA_GCCOUNT, 0) };
            if kb > b.memory_soft_kb {
                what = Some("memory limit");
            }
        }
        b.tripped = what;
        cell.set(b);
        what
    })
}

/// The limit that tripped during the current (or last) call on this thread,
/// if any: a kernel that returned normally after catching its budget error
/// has still failed.
pub fn tripped() -> Option<&'static str> {
    BUDGET.with(|cell| cell.get().tripped)
}

unsafe extern "C-unwind" fn interrupt(l: *mut ffi::lua_State, gc: c_int) {
    // gc >= 0 marks a GC-step interrupt, from which errors may not be raised.
    if gc >= 0 {
        return;
    }
    let Some(what) = exceeded(l) else { return };
    // Find the line being executed (level 0 is the interrupted function).
    let mut line = -1;
    for level in 0..3 {
        // SAFETY: lua_Debug is a plain C struct of integers, pointers and a
        // char array, for which all-zero bytes are a valid value.
        let mut ar: ffi::lua_Debug = unsafe { std::mem::zeroed() };
        // SAFETY: `l` is live; "l" asks only for `currentline`; `ar` is a
        // valid, exclusively borrowed lua_Debug.
        let found = unsafe { ffi::lua_getinfo(l, level, c"l".as_ptr(), &mut ar) };
        if found != 0 && ar.currentline > 0 {
            line = ar.currentline;
            break;
        }
    }
    let msg = if line > 0 {
        format!("{what} exceeded at line {line}")
    } else {
        format!("{what} exceeded")
    };
    // SAFETY: `l` is live and the interrupt may push a value; Luau copies
    // the bytes, so `msg` can be dropped right after.
    unsafe { ffi::lua_pushlstring_(l, msg.as_ptr().cast(), msg.len()) };
    drop(msg);
    // SAFETY: raising an error from the interrupt hook (gc < 0) is what Luau
    // documents for timeouts; no Rust value with a destructor is alive in
    // this frame, and the hook is declared "C-unwind" so the error may
    // propagate through it to the pcall that mlua set up around the kernel.
    unsafe { ffi::lua_error(l) }
}

/// Install the budget hook on `lua` (replacing any interrupt callback).
pub fn install(lua: &Lua) {
    // SAFETY: exec_raw hands us the VM's main state while it holds the VM's
    // lock; lua_callbacks returns the state's callback table, valid for the
    // VM's lifetime, and setting `interrupt` is how the C API installs a hook.
    unsafe {
        let _: mlua::Result<()> = lua.exec_raw((), |state| {
            (*ffi::lua_callbacks(state)).interrupt = Some(interrupt);
        });
    }
}
