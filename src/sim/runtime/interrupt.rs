//! The raw Luau C API, in one place: the per-call budget of kernels
//! (instructions, running time, memory), enforced from Luau's interrupt
//! hook, and the walks that keep kernels stateless: [`seal`] (at load:
//! freeze what a kernel reaches, collect its functions) and
//! [`fingerprint`] (after each call: did any of those functions' upvalues
//! change).
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
use std::time::{Duration, Instant};

use super::cpu_clock;

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
    /// When the call's time budget has passed on the wall clock; past it,
    /// the thread's CPU time decides ([`cpu_clock::spent`]).
    deadline: Instant,
    /// The call's time budget.
    time: Duration,
    /// This thread's CPU time when the call was armed (give or take
    /// [`cpu_clock::REFRESH`]), if the system has a per-thread CPU clock.
    cpu_start: Option<Duration>,
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
        deadline: Instant::now() + Duration::from_secs(3600),
        time: Duration::from_secs(3600),
        cpu_start: None,
        memory_soft_kb: c_int::MAX,
    });
}

/// Reset the budget before a kernel call on this thread: `instructions`
/// interrupts, `time` of the thread's own running time (see [`cpu_clock`]),
/// and a soft memory limit.
pub fn arm(instructions: u64, time: Duration, memory_soft_bytes: usize) {
    let now = Instant::now();
    let cpu_start = cpu_clock::reference(now);
    COUNTDOWN.with(|c| c.set(0));
    BUDGET.with(|b| {
        b.set(Budget {
            tripped: None,
            ticks: 0,
            batch: 1,
            limit: instructions,
            deadline: now + time,
            time,
            cpu_start,
            memory_soft_kb: (memory_soft_bytes / 1024).min(c_int::MAX as usize) as c_int,
        })
    });
}

/// The time limit's name in a budget error ("time budget exceeded").
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
        } else if Instant::now() > b.deadline
            && cpu_clock::spent(&mut b.deadline, b.time, b.cpu_start)
        {
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
    // Find the script's line being executed (level 0 is the interrupted
    // function). Frames of the sandbox's own Lua (the `pcall` wrapper) are
    // skipped: a budget error a script caught and retried was reported at
    // the wrapper's line, which the script does not have (regression,
    // hostile probe).
    let mut line = -1;
    for level in 0..8 {
        // SAFETY: lua_Debug is a plain C struct of integers, pointers and a
        // char array, for which all-zero bytes are a valid value.
        let mut ar: ffi::lua_Debug = unsafe { std::mem::zeroed() };
        // SAFETY: `l` is live; "sl" asks for the source and `currentline`;
        // `ar` is a valid, exclusively borrowed lua_Debug.
        let found = unsafe { ffi::lua_getinfo(l, level, c"sl".as_ptr(), &mut ar) };
        if found == 0 {
            break;
        }
        // SAFETY: when set, `source` is a NUL-terminated string owned by
        // the function's prototype, alive while the frame is.
        let ours = !ar.source.is_null()
            && unsafe { std::ffi::CStr::from_ptr(ar.source) }.to_bytes() == b"=sandbox";
        if !ours && ar.currentline > 0 {
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
/// An error means the hook is not there: the VM must not run scripts
/// (found by review: the result was dropped, so a VM without a budget
/// could have run).
pub fn install(lua: &Lua) -> mlua::Result<()> {
    // SAFETY: exec_raw hands us the VM's main state while it holds the VM's
    // lock; lua_callbacks returns the state's callback table, valid for the
    // VM's lifetime, and setting `interrupt` is how the C API installs a hook.
    unsafe {
        lua.exec_raw((), |state| {
            (*ffi::lua_callbacks(state)).interrupt = Some(interrupt);
        })
    }
}

/// Deepest nesting of functions and tables [`seal`] follows; a kernel that
/// reaches deeper is refused rather than left partly unsealed.
pub const MAX_SEAL_DEPTH: u32 = 64;

/// What [`seal`] refused.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
enum Refusal {
    Buffer,
    TooDeep,
    Stack,
}

/// Seal kernel `f` at load, so that it can keep no state between calls:
/// - every table it reaches (through the upvalues of Lua functions, and
///   tables' keys, values and metatables) is frozen;
/// - a buffer reached that way is refused (buffers are mutable by nature);
/// - a graph nested deeper than [`MAX_SEAL_DEPTH`] is refused, never
///   walked in part (regression, review: tables first reached at the old
///   depth cap of 8 were skipped for good, and stayed writable);
/// - every function reached, `f` first, Lua functions and C closures alike
///   (`string.gmatch`'s iterator keeps its position in an upvalue;
///   regression, review), is returned in a table for [`fingerprint`].
///
/// With the tables frozen, the only state left is in those functions'
/// upvalues, which [`fingerprint`] covers.
pub fn seal(lua: &Lua, f: &mlua::Function) -> Result<mlua::Table, String> {
    let holder = lua.create_table().map_err(|e| e.to_string())?;
    let mut walk = SealWalk {
        holder: 0,
        seen: rustc_hash::FxHashSet::default(),
        collected: 0,
        refused: None,
    };
    // SAFETY: exec_raw pushes `f` then `holder` and runs the walk in a
    // protected call holding the VM's lock; the walk checks the stack
    // before each push, pops what it pushes, and only appends functions to
    // `holder` with lua_rawseti.
    let ran: mlua::Result<()> = unsafe {
        lua.exec_raw((f.clone(), holder.clone()), |state| {
            let top = ffi::lua_gettop(state);
            walk.holder = top;
            walk.at(state, top - 1, 0);
        })
    };
    match walk.refused {
        // A walk cut short by an error (memory, while the holder grew) left
        // part of the kernel unsealed: refused, never half-sealed (found by
        // review: the error was dropped).
        None => match ran {
            Ok(()) => Ok(holder),
            Err(e) => Err(format!("the kernel could not be sealed: {e}")),
        },
        Some(Refusal::Buffer) => Err(
            "the kernel captures a buffer from outside itself; buffers are mutable state: create scratch buffers inside the kernel"
                .into(),
        ),
        Some(Refusal::TooDeep) | Some(Refusal::Stack) => Err(format!(
            "the kernel reaches tables or functions nested more than {MAX_SEAL_DEPTH} levels deep; flatten them"
        )),
    }
}

/// The state of one [`seal`] walk.
struct SealWalk {
    /// Absolute stack index of the table collecting functions.
    holder: c_int,
    /// Functions and tables already walked (by address).
    seen: rustc_hash::FxHashSet<usize>,
    /// Functions collected so far.
    collected: c_int,
    refused: Option<Refusal>,
}

impl SealWalk {
    /// Seal the function or table at absolute index `idx`, `depth` levels
    /// below the kernel.
    ///
    /// # Safety
    /// `state` must be a live Luau state with a function or table at `idx`
    /// and the holder table at `self.holder`.
    unsafe fn at(&mut self, state: *mut ffi::lua_State, idx: c_int, depth: u32) {
        // SAFETY (whole body): the caller's contract; every push is
        // preceded by lua_checkstack and matched by a pop.
        unsafe {
            if self.refused.is_some() {
                return;
            }
            let p = ffi::lua_topointer(state, idx) as usize;
            if self.seen.contains(&p) {
                return;
            }
            if depth > MAX_SEAL_DEPTH {
                self.refused = Some(Refusal::TooDeep);
                return;
            }
            self.seen.insert(p);
            if ffi::lua_checkstack(state, 3) == 0 {
                self.refused = Some(Refusal::Stack);
                return;
            }
            match ffi::lua_type(state, idx) {
                ffi::LUA_TFUNCTION => {
                    ffi::lua_pushvalue(state, idx);
                    self.collected += 1;
                    ffi::lua_rawseti(state, self.holder, self.collected as i64);
                    // A C closure's upvalues are its own (a gmatch position,
                    // a callback's handle): checked by value, not followed.
                    if ffi::lua_iscfunction(state, idx) != 0 {
                        return;
                    }
                    let mut u = 1;
                    while !ffi::lua_getupvalue(state, idx, u).is_null() {
                        let at = ffi::lua_gettop(state);
                        self.value(state, at, depth);
                        ffi::lua_pop(state, 1);
                        u += 1;
                    }
                }
                ffi::LUA_TTABLE => {
                    ffi::lua_setreadonly(state, idx, 1);
                    if ffi::lua_getmetatable(state, idx) != 0 {
                        let at = ffi::lua_gettop(state);
                        self.value(state, at, depth);
                        ffi::lua_pop(state, 1);
                    }
                    ffi::lua_pushnil(state);
                    while ffi::lua_next(state, idx) != 0 {
                        // Keys and values alike; the key is left as it was
                        // for lua_next.
                        let top = ffi::lua_gettop(state);
                        self.value(state, top, depth);
                        self.value(state, top - 1, depth);
                        ffi::lua_pop(state, 1);
                    }
                }
                _ => {}
            }
        }
    }

    /// Seal the value at absolute index `at` if it is a function or table
    /// (one level below `depth`); refuse a buffer.
    ///
    /// # Safety
    /// As [`SealWalk::at`], for the value at `at`.
    unsafe fn value(&mut self, state: *mut ffi::lua_State, at: c_int, depth: u32) {
        // SAFETY: the caller's contract.
        unsafe {
            match ffi::lua_type(state, at) {
                ffi::LUA_TFUNCTION | ffi::LUA_TTABLE => self.at(state, at, depth + 1),
                ffi::LUA_TBUFFER => self.refused = Some(Refusal::Buffer),
                _ => {}
            }
        }
    }
}

/// The upvalues of every function [`seal`] collected, word for word:
/// numbers, booleans and vectors by value, strings and every other object
/// by identity. A call after which they are not the same kept state
/// between calls. Kept exactly, not hashed (regression, determinism probe:
/// a running xor-multiply hash let an even number of sign flips cancel, so
/// two locals, or one captured by two functions, kept a counter in their
/// signs unseen).
///
/// Strings by identity: Luau interns every string (`luaS_newlstr` and
/// `luaS_buffinish` return the live string of the same bytes), so two
/// live strings are the same object exactly when their bytes are equal.
/// Every object the fingerprint saw by identity (strings, tables,
/// functions, buffers) is pinned in the holder (`pins`), so none of them
/// can be freed and its address taken by another
/// (regression, review: strings were copied byte by byte into the
/// fingerprint, once per function capturing them, and read byte by byte
/// after every call: one 8 MB string captured by 200 closures took 1.6 GB
/// outside the VM's memory limit and 0.6 s a call).
#[derive(Clone, Debug, Default, PartialEq, Eq)]
pub struct Fingerprint(Vec<u64>);

/// The [`Fingerprint`] of the functions in `held`, pinning the strings it
/// saw in `held`. Only each function's own upvalues are read (the tables
/// are frozen, and every function reachable is in `held`), so the cost is
/// the number of functions and upvalues, not the size of the tables or
/// strings. `None` when it could not be taken whole (no stack room, or an
/// error): the caller fails rather than trust a part (found by review: a
/// partial one was returned).
pub fn fingerprint(lua: &Lua, held: &mlua::Table) -> Option<Fingerprint> {
    let mut words = Vec::new();
    visit_upvalues(lua, held, true, &mut |w| words.push(w)).then_some(Fingerprint(words))
}

/// Whether the functions in `held` still have the upvalues of `print`,
/// compared word by word as they are read, allocating nothing (after every
/// kernel call). `None` when they could not be read whole.
pub fn unchanged(lua: &Lua, held: &mlua::Table, print: &Fingerprint) -> Option<bool> {
    let (mut at, mut same) = (0usize, true);
    let whole = visit_upvalues(lua, held, false, &mut |w| {
        same &= print.0.get(at) == Some(&w);
        at += 1;
    });
    whole.then_some(same && at == print.0.len())
}

/// Hand every word of the upvalues of the functions in `held` to `emit`
/// (and, with `pin`, keep every upvalue seen by identity alive in
/// `held.pins`);
/// whether they were read whole.
fn visit_upvalues(lua: &Lua, held: &mlua::Table, pin: bool, emit: &mut dyn FnMut(u64)) -> bool {
    let mut whole = false;
    // SAFETY: exec_raw pushes `held` and runs the closure in a protected
    // call holding the VM's lock; the pin table is created after a stack
    // check, each function is pushed with rawgeti after a stack check for
    // it, its upvalue and a copy to pin, read, and popped; the pin table is
    // stored in `held` (which pops it) before the closure returns.
    let ran: mlua::Result<()> = unsafe {
        lua.exec_raw(held.clone(), |state| {
            let t = ffi::lua_gettop(state);
            let len = ffi::lua_objlen(state, t) as c_int;
            let mut pins = None;
            if pin {
                if ffi::lua_checkstack(state, 1) == 0 {
                    return;
                }
                ffi::lua_createtable(state, 0, 0);
                pins = Some((ffi::lua_gettop(state), 0));
            }
            for i in 1..=len {
                if ffi::lua_checkstack(state, 3) == 0 {
                    return;
                }
                ffi::lua_rawgeti(state, t, i as _);
                let f = ffi::lua_gettop(state);
                emit_upvalues(state, f, pins.as_mut(), emit);
                ffi::lua_pop(state, 1);
            }
            if pins.is_some() {
                ffi::lua_rawsetfield(state, t, c"pins".as_ptr());
            }
            whole = true;
        })
    };
    ran.is_ok() && whole
}

/// Hand the direct upvalues of the function at absolute index `idx` to
/// `emit`: the function's identity, then per upvalue its type and value;
/// with `pins` (the pin table's index and its count), each value seen by
/// identity is also stored there.
///
/// # Safety
/// `state` must be a live Luau state with a function at `idx`, the pin
/// table at its index, and room for two more values on its stack.
unsafe fn emit_upvalues(
    state: *mut ffi::lua_State,
    idx: c_int,
    mut pins: Option<&mut (c_int, c_int)>,
    emit: &mut dyn FnMut(u64),
) {
    // SAFETY (whole body): the caller's contract; each upvalue pushed is
    // popped before the next, and its pinned copy is popped by rawseti.
    unsafe {
        emit(ffi::lua_topointer(state, idx) as u64);
        let mut n = 1;
        while !ffi::lua_getupvalue(state, idx, n).is_null() {
            let t = ffi::lua_type(state, -1);
            emit(t as u64);
            match t {
                ffi::LUA_TNUMBER => emit(ffi::lua_tonumber(state, -1).to_bits()),
                ffi::LUA_TBOOLEAN => emit(ffi::lua_toboolean(state, -1) as u64),
                ffi::LUA_TVECTOR => {
                    let v = ffi::lua_tovector(state, -1);
                    if !v.is_null() {
                        for k in 0..3 {
                            emit((*v.add(k)).to_bits() as u64);
                        }
                    }
                }
                // Strings (interned: identity is their bytes), tables,
                // functions, buffers and userdata by identity, pinned:
                // none can be freed and its address taken by another while
                // the fingerprint stands (regression, review: a table freed
                // by the collection before a retry after running out of
                // memory gave its address to a new, unfrozen table, which
                // then kept state unseen).
                _ => {
                    emit(ffi::lua_topointer(state, -1) as u64);
                    if let Some((table, count)) = pins.as_deref_mut() {
                        *count += 1;
                        ffi::lua_pushvalue(state, -1);
                        ffi::lua_rawseti(state, *table, *count as _);
                    }
                }
            }
            ffi::lua_pop(state, 1);
            n += 1;
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// A kernel whose chunk runs `prelude` and whose body is `body`, sealed,
    /// with its fingerprint taken.
    fn kernel(lua: &Lua, prelude: &str, body: &str) -> (mlua::Function, mlua::Table, Fingerprint) {
        let f: mlua::Function = lua
            .load(format!("{prelude}\nreturn function() {body} end"))
            .eval()
            .unwrap();
        let held = seal(lua, &f).unwrap();
        let print = fingerprint(lua, &held).unwrap();
        (f, held, print)
    }

    /// Found by review: a seal cut short by an error (here the memory
    /// limit, while the holder of 20 000 functions grows) returned the
    /// kernel as sealed, with the rest of it unfrozen. It is refused.
    #[test]
    fn a_seal_cut_short_by_memory_is_refused() {
        let lua = Lua::new();
        let f: mlua::Function = lua
            .load(
                "local fs = {} for i = 1, 20000 do fs[i] = function() return i end end \
                 return function() return fs end",
            )
            .eval()
            .unwrap();
        lua.set_memory_limit(lua.used_memory() + 4096).unwrap();
        let sealed = seal(&lua, &f);
        lua.set_memory_limit(0).unwrap();
        let e = sealed.expect_err("a half-sealed kernel was accepted");
        assert!(e.contains("could not be sealed"), "{e}");
        // With room, the same kernel seals, and its fingerprint is whole.
        let held = seal(&lua, &f).unwrap();
        let print = fingerprint(&lua, &held).unwrap();
        assert_eq!(unchanged(&lua, &held, &print), Some(true));
    }

    /// Strings are compared by identity, which interning makes equality:
    /// a kernel that builds an equal string again (by any route) kept no
    /// state, and one that changes a 1 MB string is seen at once.
    #[test]
    fn an_equal_string_made_again_is_unchanged() {
        let lua = Lua::new();
        for (prelude, body, same) in [
            ("local s = 'xx' .. 'xxx'", "s = string.rep('x', 5)", true),
            (
                "local s = string.rep('y', 1048576)",
                "s = ('y'):rep(1048576)",
                true,
            ),
            (
                "local s = string.rep('y', 1048576)",
                "s = ('y'):rep(1048575) .. 'z'",
                false,
            ),
            (
                "local s = 'a,b'",
                "s = table.concat({ 'a', 'b' }, ',')",
                true,
            ),
        ] {
            let (f, held, print) = kernel(&lua, prelude, body);
            // The string seen is pinned: it outlives its upvalue.
            let pins: mlua::Table = held.get("pins").unwrap();
            assert_eq!(pins.raw_len(), 1, "{prelude}");
            f.call::<()>(()).unwrap();
            lua.gc_collect().unwrap();
            assert_eq!(unchanged(&lua, &held, &print), Some(same), "{body}");
        }
    }

    /// Regression (review): a table freed by the collection before a retry
    /// gave its address to a new, unfrozen table, which kept state unseen.
    /// Every upvalue held by identity is pinned, so its address stays its
    /// own; numbers are values and are not.
    #[test]
    fn upvalues_held_by_identity_are_pinned() {
        let lua = Lua::new();
        let f: mlua::Function = lua
            .load(
                "local t, s, n = {}, string.rep('x', 2), tonumber('1')\nlocal function g() return t end\n\
                 return function() return g(), s, n end",
            )
            .eval()
            .unwrap();
        let held = seal(&lua, &f).unwrap();
        fingerprint(&lua, &held).unwrap();
        let pins: mlua::Table = held.get("pins").unwrap();
        // The kernel's g, s and n (n is a number), and g's t.
        let kinds: Vec<String> = pins
            .sequence_values::<mlua::Value>()
            .map(|v| v.unwrap().type_name().to_string())
            .collect();
        assert_eq!(kinds.len(), 3, "{kinds:?}");
        for k in ["function", "string", "table"] {
            assert!(kinds.iter().any(|x| x == k), "{k} not pinned: {kinds:?}");
        }
    }

    /// Regression (determinism probe): sign flips of two upvalues, or of
    /// one captured by two functions, cancelled in the old hash, so a
    /// kernel kept a counter between calls unseen. Each flip is seen; a
    /// string changed to another of the same length is seen too.
    #[test]
    fn every_change_of_an_upvalue_is_seen() {
        let lua = Lua::new();
        for (prelude, body) in [
            ("local a, b = 1.0, 1.0", "a = -a; b = -b"),
            (
                "local a = 1.0; local function g() return a end",
                "a = -a; local _ = g()",
            ),
            ("local s = 'ab'", "s = if s == 'ab' then 'ba' else 'ab'"),
            ("local v = 0", "v = v + 1; v = v - 1 + 2^-40"),
            // A string freed and made again in between is still seen: the
            // one the fingerprint saw is pinned, so its address is not
            // reused.
            (
                "local s = string.rep('a', 100)",
                "s = nil; collectgarbage(); s = string.rep('c', 100)",
            ),
        ] {
            let (f, held, print) = kernel(&lua, prelude, body);
            assert_eq!(unchanged(&lua, &held, &print), Some(true), "{prelude}");
            f.call::<()>(()).unwrap();
            assert_eq!(
                unchanged(&lua, &held, &print),
                Some(false),
                "{prelude}; {body}"
            );
        }
    }
}
