//! The raw Luau C API, in one place: the per-call budget of kernels
//! (instructions, wall-clock time, memory), enforced from Luau's interrupt
//! hook, and [`upvalue_fingerprint`], which lets the runtime see a kernel
//! keep state between calls in its upvalues.
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
    /// Interrupts counted up to the last slow check.
    ticks: u64,
    /// Interrupts in the batch that ends at the next slow check.
    batch: u64,
    limit: u64,
    deadline: Instant,
    memory_soft_kb: c_int,
}

/// Most interrupts between two slow checks (time and memory are read there).
const BATCH: u64 = 256;

thread_local! {
    /// Interrupts left before the next slow check. The hot path of every
    /// loop back-edge and call is one decrement of this const-initialised
    /// thread-local; the budget below is only read every [`BATCH`].
    static COUNTDOWN: Cell<u64> = const { Cell::new(0) };
    static BUDGET: Cell<Budget> = Cell::new(Budget {
        tripped: None,
        ticks: 0,
        batch: 1,
        limit: u64::MAX,
        deadline: Instant::now() + std::time::Duration::from_secs(3600),
        memory_soft_kb: c_int::MAX,
    });
}

/// Reset the budget before a kernel call on this thread.
pub fn arm(instructions: u64, deadline: Instant, memory_soft_bytes: usize) {
    COUNTDOWN.with(|c| c.set(0));
    BUDGET.with(|b| {
        b.set(Budget {
            tripped: None,
            ticks: 0,
            batch: 1,
            limit: instructions,
            deadline,
            memory_soft_kb: (memory_soft_bytes / 1024).min(c_int::MAX as usize) as c_int,
        })
    });
}

/// The wall-clock limit's name in a budget error ("time budget exceeded").
pub const TIME_BUDGET: &str = "time budget";

/// The memory limit's name in a budget error.
pub const MEMORY_LIMIT: &str = "memory limit";

/// The name of a stop request in place of a limit.
pub const STOPPING: &str = "engine stop";

/// Set once the process is stopping and a step in flight has to give way.
static STOP: std::sync::atomic::AtomicBool = std::sync::atomic::AtomicBool::new(false);

/// Make every running and later kernel call fail at its next check (within
/// [`BATCH`] interrupts): for a stop that cannot wait for a long step
/// (regression: kernels just under their budget made a step of minutes,
/// and SIGTERM waited for it).
pub fn stop_all() {
    STOP.store(true, std::sync::atomic::Ordering::Relaxed);
}

/// Whether [`stop_all`] was called.
pub fn stopping() -> bool {
    STOP.load(std::sync::atomic::Ordering::Relaxed)
}

/// Which limit, if any, the running kernel has exceeded (counts one tick).
#[inline(always)]
fn exceeded(l: *mut ffi::lua_State) -> Option<&'static str> {
    let fast = COUNTDOWN.with(|c| {
        let v = c.get();
        c.set(v.wrapping_sub(1));
        v > 0
    });
    if fast { None } else { slow_check(l) }
}

/// The check at the end of a batch: count the batch, then compare with the
/// instruction limit (exactly: a batch never runs past it), the deadline and
/// the memory limit, and size the next batch.
#[cold]
fn slow_check(l: *mut ffi::lua_State) -> Option<&'static str> {
    BUDGET.with(|cell| {
        let mut b = cell.get();
        if b.tripped.is_some() {
            // Sticky: a caught budget error is raised again at every
            // interrupt (the countdown stays at zero).
            COUNTDOWN.with(|c| c.set(0));
            return b.tripped;
        }
        b.ticks = b.ticks.saturating_add(b.batch);
        let mut what = None;
        if stopping() {
            what = Some(STOPPING);
        } else if b.ticks > b.limit {
            what = Some("instruction budget");
        } else if Instant::now() > b.deadline {
            what = Some(TIME_BUDGET);
        } else {
            // SAFETY: `l` is the live state Luau passed to the interrupt
            // hook; LUA_GCCOUNT only reads the allocator's counter.
            let kb = unsafe { ffi::lua_gc(l, ffi::LUA_GCCOUNT, 0) };
            if kb > b.memory_soft_kb {
                what = Some(MEMORY_LIMIT);
            }
        }
        b.tripped = what;
        // The next slow check comes at interrupt limit + 1 at the latest.
        b.batch = if what.is_some() {
            1
        } else {
            BATCH.min(b.limit.saturating_add(1) - b.ticks).max(1)
        };
        COUNTDOWN.with(|c| c.set(b.batch - 1));
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
    let msg = if what == STOPPING {
        "interrupted: the engine is stopping".to_string()
    } else if line > 0 {
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

/// Most function levels followed through upvalues.
const MAX_UPVALUE_DEPTH: u32 = 8;

/// A fingerprint of the state `f` can reach through its upvalues, following
/// function upvalues (helpers) recursively: numbers, booleans, strings and
/// vectors by value, every other object by identity. A kernel that assigns
/// to a local of its chunk (`counter = counter + 1`) changes it; one that
/// only reads constants and calls helpers does not. Table *contents* are not
/// covered (a scratch table may be reused; its contents must not carry state).
pub fn upvalue_fingerprint(lua: &Lua, f: &mlua::Function) -> u64 {
    let mut h = 0xcbf2_9ce4_8422_2325u64;
    let mut seen: Vec<*const std::ffi::c_void> = Vec::new();
    // SAFETY: exec_raw pushes `f` on the VM's stack and runs the closure in
    // a protected call while holding the VM's lock; the walk only reads
    // values, checks the stack before each push and pops what it pushed.
    let _: mlua::Result<()> = unsafe {
        lua.exec_raw(f.clone(), |state| {
            let top = ffi::lua_gettop(state);
            walk_upvalues(state, top, 0, &mut h, &mut seen);
        })
    };
    h
}

/// Mix the upvalues of the function at absolute stack index `idx` into `h`.
///
/// # Safety
/// `state` must be a live Luau state with a function at `idx`.
unsafe fn walk_upvalues(
    state: *mut ffi::lua_State,
    idx: c_int,
    depth: u32,
    h: &mut u64,
    seen: &mut Vec<*const std::ffi::c_void>,
) {
    fn mix(h: &mut u64, v: u64) {
        *h ^= v;
        *h = h.wrapping_mul(0x0100_0000_01b3);
    }
    // SAFETY (whole body): `idx` holds a function (caller's contract); every
    // push is preceded by lua_checkstack and matched by a pop.
    unsafe {
        let p = ffi::lua_topointer(state, idx);
        if depth > MAX_UPVALUE_DEPTH || seen.contains(&p) {
            return;
        }
        seen.push(p);
        let mut n = 1;
        loop {
            if ffi::lua_checkstack(state, 2) == 0 {
                return;
            }
            if ffi::lua_getupvalue(state, idx, n).is_null() {
                break;
            }
            let t = ffi::lua_type(state, -1);
            mix(h, t as u64);
            match t {
                ffi::LUA_TNUMBER => mix(h, ffi::lua_tonumber(state, -1).to_bits()),
                ffi::LUA_TBOOLEAN => mix(h, ffi::lua_toboolean(state, -1) as u64),
                ffi::LUA_TSTRING => {
                    let mut len = 0usize;
                    let s = ffi::lua_tolstring(state, -1, &mut len);
                    if !s.is_null() {
                        for b in std::slice::from_raw_parts(s.cast::<u8>(), len) {
                            mix(h, *b as u64);
                        }
                    }
                }
                ffi::LUA_TVECTOR => {
                    let v = ffi::lua_tovector(state, -1);
                    if !v.is_null() {
                        for k in 0..3 {
                            mix(h, (*v.add(k)).to_bits() as u64);
                        }
                    }
                }
                ffi::LUA_TFUNCTION => {
                    mix(h, ffi::lua_topointer(state, -1) as u64);
                    // C functions (math.max, buffer.readf64…) hold no
                    // script state: only Lua helpers are followed.
                    if ffi::lua_iscfunction(state, -1) == 0 {
                        let at = ffi::lua_gettop(state);
                        walk_upvalues(state, at, depth + 1, h, seen);
                    }
                }
                _ => mix(h, ffi::lua_topointer(state, -1) as u64),
            }
            ffi::lua_pop(state, 1);
            n += 1;
        }
    }
}

/// The Lua functions held in the tables `f` reaches through its upvalues
/// (and through those tables, their metatables and the functions found),
/// collected once at load. The tables are frozen, so no other function can
/// appear in them; each of these can still change its own upvalues, so
/// [`upvalue_fingerprint_of`] covers them on every call (regression, hostile
/// probe: a counter closure used as a table key kept state between calls).
pub fn closures_in_tables(lua: &Lua, f: &mlua::Function) -> Vec<mlua::Function> {
    let Ok(holder) = lua.create_table() else {
        return Vec::new();
    };
    let mut seen: Vec<*const std::ffi::c_void> = Vec::new();
    // SAFETY: exec_raw pushes `f` then `holder` and runs the walk in a
    // protected call holding the VM's lock; the walk checks the stack
    // before each push and pops what it pushes, and only appends functions
    // to `holder` with lua_rawseti.
    let _: mlua::Result<()> = unsafe {
        lua.exec_raw((f.clone(), holder.clone()), |state| {
            let top = ffi::lua_gettop(state);
            let mut n = 0;
            collect_at(state, top - 1, top, false, 0, &mut seen, &mut n);
        })
    };
    holder
        .sequence_values::<mlua::Function>()
        .filter_map(Result::ok)
        .collect()
}

/// Walk the function or table at absolute index `idx`, appending to the
/// table at `holder` every Lua function found in a table (`in_table`).
///
/// # Safety
/// `state` must be a live Luau state with a function or table at `idx` and
/// a table at `holder`.
unsafe fn collect_at(
    state: *mut ffi::lua_State,
    idx: c_int,
    holder: c_int,
    in_table: bool,
    depth: u32,
    seen: &mut Vec<*const std::ffi::c_void>,
    n: &mut c_int,
) {
    // SAFETY (whole body): the caller's contract; every push is preceded
    // by lua_checkstack and matched by a pop.
    unsafe {
        let p = ffi::lua_topointer(state, idx);
        if depth > MAX_UPVALUE_DEPTH || seen.contains(&p) {
            return;
        }
        seen.push(p);
        if ffi::lua_checkstack(state, 3) == 0 {
            return;
        }
        match ffi::lua_type(state, idx) {
            ffi::LUA_TFUNCTION => {
                if ffi::lua_iscfunction(state, idx) != 0 {
                    return;
                }
                if in_table {
                    ffi::lua_pushvalue(state, idx);
                    *n += 1;
                    ffi::lua_rawseti(state, holder, *n as i64);
                }
                let mut u = 1;
                while !ffi::lua_getupvalue(state, idx, u).is_null() {
                    let t = ffi::lua_type(state, -1);
                    if t == ffi::LUA_TFUNCTION || t == ffi::LUA_TTABLE {
                        let at = ffi::lua_gettop(state);
                        collect_at(state, at, holder, false, depth + 1, seen, n);
                    }
                    ffi::lua_pop(state, 1);
                    u += 1;
                }
            }
            ffi::LUA_TTABLE => {
                if ffi::lua_getmetatable(state, idx) != 0 {
                    let at = ffi::lua_gettop(state);
                    collect_at(state, at, holder, true, depth + 1, seen, n);
                    ffi::lua_pop(state, 1);
                }
                ffi::lua_pushnil(state);
                while ffi::lua_next(state, idx) != 0 {
                    let top = ffi::lua_gettop(state);
                    for at in [top, top - 1] {
                        let t = ffi::lua_type(state, at);
                        if t == ffi::LUA_TFUNCTION || t == ffi::LUA_TTABLE {
                            collect_at(state, at, holder, true, depth + 1, seen, n);
                        }
                    }
                    ffi::lua_pop(state, 1);
                }
            }
            _ => {}
        }
    }
}

/// [`upvalue_fingerprint`] of a kernel combined with those of the closures
/// held in its tables ([`closures_in_tables`]).
pub fn upvalue_fingerprint_of(lua: &Lua, f: &mlua::Function, held: &[mlua::Function]) -> u64 {
    held.iter().fold(upvalue_fingerprint(lua, f), |h, g| {
        (h ^ upvalue_fingerprint(lua, g)).wrapping_mul(0x0100_0000_01b3)
    })
}

/// Freeze every table a kernel can reach through its upvalues (and through
/// those tables and its Lua helpers' upvalues), so that a kernel cannot keep
/// state in a table's contents either. A captured buffer is refused: it is
/// mutable state by nature (create scratch buffers inside the kernel).
pub fn freeze_upvalues(lua: &Lua, f: &mlua::Function) -> Result<(), String> {
    let mut refused = None;
    let mut seen: Vec<*const std::ffi::c_void> = Vec::new();
    // SAFETY: as in `upvalue_fingerprint`: exec_raw pushes `f` and runs the
    // walk in a protected call holding the VM's lock; the walk checks the
    // stack before each push and pops what it pushes.
    let _: mlua::Result<()> = unsafe {
        lua.exec_raw(f.clone(), |state| {
            let top = ffi::lua_gettop(state);
            freeze_at(state, top, 0, &mut seen, &mut refused);
        })
    };
    match refused {
        Some(_) => Err(
            "the kernel captures a buffer from outside itself; buffers are mutable state: create scratch buffers inside the kernel"
                .to_string(),
        ),
        None => Ok(()),
    }
}

/// Freeze what the value at absolute index `idx` (a function or a table)
/// reaches.
///
/// # Safety
/// `state` must be a live Luau state with a function or table at `idx`.
unsafe fn freeze_at(
    state: *mut ffi::lua_State,
    idx: c_int,
    depth: u32,
    seen: &mut Vec<*const std::ffi::c_void>,
    refused: &mut Option<String>,
) {
    // SAFETY (whole body): the caller's contract; every push is preceded
    // by lua_checkstack and matched by a pop.
    unsafe {
        let p = ffi::lua_topointer(state, idx);
        if depth > MAX_UPVALUE_DEPTH || seen.contains(&p) || refused.is_some() {
            return;
        }
        seen.push(p);
        match ffi::lua_type(state, idx) {
            ffi::LUA_TFUNCTION => {
                if ffi::lua_iscfunction(state, idx) != 0 {
                    return;
                }
                let mut n = 1;
                loop {
                    if ffi::lua_checkstack(state, 2) == 0 {
                        return;
                    }
                    let name = ffi::lua_getupvalue(state, idx, n);
                    if name.is_null() {
                        break;
                    }
                    let t = ffi::lua_type(state, -1);
                    if t == ffi::LUA_TBUFFER {
                        *refused = Some(
                            std::ffi::CStr::from_ptr(name)
                                .to_string_lossy()
                                .into_owned(),
                        );
                    } else if t == ffi::LUA_TFUNCTION || t == ffi::LUA_TTABLE {
                        let at = ffi::lua_gettop(state);
                        freeze_at(state, at, depth + 1, seen, refused);
                    }
                    ffi::lua_pop(state, 1);
                    n += 1;
                }
            }
            ffi::LUA_TTABLE => {
                ffi::lua_setreadonly(state, idx, 1);
                if ffi::lua_checkstack(state, 3) == 0 {
                    return;
                }
                // Its metatable too (regression, hostile probe: a kernel
                // counted in `getmetatable(proxy).n`).
                if ffi::lua_getmetatable(state, idx) != 0 {
                    let at = ffi::lua_gettop(state);
                    freeze_at(state, at, depth + 1, seen, refused);
                    ffi::lua_pop(state, 1);
                }
                ffi::lua_pushnil(state);
                while ffi::lua_next(state, idx) != 0 {
                    // Values and keys alike (regression: a table used as
                    // a key, or a buffer held in a table, kept state).
                    let top = ffi::lua_gettop(state);
                    for at in [top, top - 1] {
                        match ffi::lua_type(state, at) {
                            ffi::LUA_TFUNCTION | ffi::LUA_TTABLE => {
                                freeze_at(state, at, depth + 1, seen, refused)
                            }
                            ffi::LUA_TBUFFER => *refused = Some("a buffer in a table".into()),
                            _ => {}
                        }
                    }
                    ffi::lua_pop(state, 1);
                }
            }
            _ => {}
        }
    }
}
