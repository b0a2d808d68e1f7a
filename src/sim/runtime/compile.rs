//! How a script's source becomes code in each worker VM: the compiler's
//! options, native code for small scripts only, and large scripts compiled
//! once and shared as bytecode.
//!
//! Luau's compiler and code generator allocate outside a VM's memory
//! limit, and a failed allocation there is a C++ exception that aborts the
//! process. For small scripts that is nothing; a 4 MB script took about
//! 270 MB to compile (65 bytes a source byte) and 1.3 GB of native code,
//! in every worker VM at once (regression, hostile probe: SIGILL in the
//! code generator, or "Rust cannot catch foreign exceptions"). So:
//! - scripts over [`NATIVE_MAX_BYTES`] are interpreted;
//! - they are compiled once, one at a time, after a check that the memory
//!   is there, and every VM loads the bytecode (inside its own limit).

use std::sync::{Arc, Mutex};

use mlua::Lua;
use mlua::chunk::Compiler;

use crate::sim::{ScriptSource, SimError};

/// Largest script compiled to native code, and compiled in each VM;
/// larger ones are interpreted, from bytecode compiled once. At this size a
/// VM's native code stays near 20 MiB; the shipped scripts are under
/// 16 KiB.
pub const NATIVE_MAX_BYTES: usize = 64 << 10;

/// Measured peak bytes of Luau's compiler per source byte (65), with a
/// margin.
const COMPILE_BYTES_PER_BYTE: u64 = 80;

/// A large script's text and its bytecode.
type Compiled = (Arc<str>, Arc<[u8]>);

/// The compiler every script VM uses.
pub fn compiler() -> Compiler {
    // The functions the preludes replace are never compiled as builtins:
    // in a sandboxed environment a builtin call goes straight to Luau's
    // own function (regression, hostile probe: weak tables passed the
    // replaced `setmetatable`).
    Compiler::new()
        .set_optimization_level(2)
        .set_type_info_level(1)
        .set_disabled_builtins(["setmetatable", "tostring", "string.format"])
}

/// Compile the chunks `lua` loads next to native code only if `text` is
/// small enough (see [`NATIVE_MAX_BYTES`]).
pub fn native_code_for(lua: &Lua, text: &str) {
    lua.enable_jit(text.len() <= NATIVE_MAX_BYTES);
}

/// For a script over [`NATIVE_MAX_BYTES`], its bytecode, compiled once for
/// every VM that loads it (and kept while the script is loaded); `None` for a small script, or one that does not
/// compile (loading its text then reports the error as usual).
pub fn shared_bytecode(src: &ScriptSource) -> Result<Option<Arc<[u8]>>, SimError> {
    static CACHE: Mutex<Vec<Compiled>> = Mutex::new(Vec::new());
    if src.text.len() <= NATIVE_MAX_BYTES {
        return Ok(None);
    }
    // Held while compiling: large scripts compile one at a time.
    let mut cache = CACHE.lock().unwrap_or_else(|p| p.into_inner());
    if let Some((_, b)) = cache
        .iter()
        .find(|(t, _)| Arc::ptr_eq(t, &src.text) || **t == *src.text)
    {
        return Ok(Some(b.clone()));
    }
    let need = (src.text.len() as u64).saturating_mul(COMPILE_BYTES_PER_BYTE);
    let have = crate::scene::budget::headroom_bytes();
    if need > have {
        return Err(SimError::Declaration {
            script: src.name.clone(),
            line: None,
            msg: format!(
                "a script of {} needs about {} to compile; {} is available",
                crate::scene::budget::human(src.text.len() as u64),
                crate::scene::budget::human(need),
                crate::scene::budget::human(have)
            ),
        });
    }
    let Ok(bytes) = compiler().compile(&*src.text) else {
        return Ok(None);
    };
    let bytes: Arc<[u8]> = bytes.into();
    // Kept while a loaded script holds its text, so that a worker's VM made
    // later (or rebuilt after an error) never compiles or checks memory
    // again mid-run (regression, review: with a fixed number of entries, a
    // ninth large script evicted one in use, and whether a tile failed the
    // memory check then depended on threads and timing).
    cache.retain(|(t, _)| Arc::strong_count(t) > 1);
    cache.push((src.text.clone(), bytes.clone()));
    Ok(Some(bytes))
}
