//! The sandbox every script VM runs in: which libraries and globals exist,
//! the preludes run before the globals freeze, the compiler, the memory
//! limit and the budget hook.

use mlua::{Lua, LuaOptions, StdLib, Table, Value};

use super::script::Limits;
use crate::sim::SimError;

/// `log()` lines of the kernel call in flight, held back until its verdict:
/// a call run again after running out of memory logs once, not twice. At
/// most [`PER_SECOND`](crate::sim::runtime::log::PER_SECOND) lines are held
/// (no more could be accepted in one second); the rest are only counted.
#[derive(Default)]
pub(super) struct HeldLog {
    pub(super) on: bool,
    pub(super) lines: Vec<String>,
    /// Lines past the most held, counted as dropped when released.
    pub(super) extra: u64,
}

/// A fresh Luau VM with the sandbox every script runs in: only `math`,
/// `string`, `table`, `buffer`, `bit32` and `utf8`; no module loading,
/// environments, code from strings, GC control or stdout; no unseeded
/// randomness; read-only globals and libraries; the memory limit and the
/// uncatchable budget hook installed.
pub fn sandboxed(limits: Limits, name: &str) -> Result<Lua, SimError> {
    let libs =
        StdLib::MATH | StdLib::STRING | StdLib::TABLE | StdLib::BUFFER | StdLib::BIT | StdLib::UTF8;
    let lua = Lua::new_with(libs, LuaOptions::default())
        .map_err(|e| SimError::Internal(e.to_string()))?;
    // Globals that reach outside the script (module loading, environments,
    // code from strings, the GC, stdout) go before the environment is frozen.
    {
        let g = lua.globals();
        // Unseeded, per-VM randomness would make worlds irreproducible;
        // kernels get `c.random(...)` (deterministic) instead.
        if let Ok(math) = g.raw_get::<Table>("math") {
            for name in ["random", "randomseed"] {
                math.raw_remove(name)
                    .map_err(|e| SimError::Internal(e.to_string()))?;
            }
        }
        for name in [
            "require",
            "getfenv",
            "setfenv",
            "loadstring",
            "load",
            "dofile",
            "loadfile",
            "collectgarbage",
            "gcinfo",
            "newproxy",
            "print",
        ] {
            g.raw_remove(name)
                .map_err(|e| SimError::Internal(e.to_string()))?;
        }
    }
    // log(...): rate-limited lines to the daemon log and /status.
    let who = name.to_string();
    lua.set_app_data(HeldLog::default());
    let log = lua
        .create_function(move |lua, args: mlua::Variadic<Value>| {
            use crate::sim::runtime::log::{LogPart, PER_SECOND, line_of};
            if let Some(mut held) = lua.app_data_mut::<HeldLog>()
                && held.on
                && held.lines.len() >= PER_SECOND as usize
            {
                held.extra += 1;
                return Ok(());
            }
            let strings: Vec<Option<mlua::BorrowedBytes>> = args
                .iter()
                .map(|v| match v {
                    Value::String(s) => Some(s.as_bytes()),
                    _ => None,
                })
                .collect();
            let line = line_of(args.iter().zip(&strings).map(|(v, b)| match (v, b) {
                (_, Some(b)) => LogPart::Bytes(b),
                (Value::Nil, _) => LogPart::Text("nil".into()),
                (Value::Boolean(b), _) => LogPart::Text(b.to_string()),
                (Value::Integer(i), _) => LogPart::Text(i.to_string()),
                (Value::Number(n), _) => LogPart::Text(number_text(*n)),
                (other, _) => LogPart::Text(other.type_name().to_string()),
            }));
            if let Some(mut held) = lua.app_data_mut::<HeldLog>()
                && held.on
            {
                held.lines.push(line);
                return Ok(());
            }
            crate::sim::runtime::log::push(&who, line);
            Ok(())
        })
        .map_err(|e| SimError::Internal(e.to_string()))?;
    lua.globals()
        .raw_set("log", log)
        .map_err(|e| SimError::Internal(e.to_string()))?;
    for prelude in [
        super::prelude::UNCATCHABLE_MEMORY_ERRORS,
        super::prelude::NO_ADDRESSES,
        super::prelude::NO_WEAK_TABLES,
    ] {
        lua.load(prelude)
            .set_name("=sandbox")
            .exec()
            .map_err(|e| SimError::Internal(e.to_string()))?;
    }
    lua.sandbox(true)
        .map_err(|e| SimError::Internal(e.to_string()))?;
    // Luau's sandbox gives each thread a writable proxy of the frozen
    // globals; freeze the proxy too, so `counter = counter + 1` is an
    // error instead of state that depends on which VM ran which tile.
    lua.globals().set_readonly(true);
    lua.set_memory_limit(limits.memory)
        .map_err(|e| SimError::Internal(e.to_string()))?;
    crate::sim::interrupt::install(&lua).map_err(|e| SimError::Internal(e.to_string()))?;
    // Optimisation level 2 inlines small local functions and unrolls loops;
    // type information lets native code use annotations (`W: buffer`).
    // The functions the preludes replace are never compiled as builtins:
    // in a sandboxed environment a builtin call goes straight to Luau's
    // own function (regression, hostile probe: weak tables passed the
    // replaced `setmetatable`).
    lua.set_compiler(super::compile::compiler());
    Ok(lua)
}

/// A number as `log` writes it: the shortest text that reads back as the
/// same number, with an exponent past 10¹⁵ and below 10⁻⁴, as `tostring`
/// does (regression, modder probe: `log(1e-300)` wrote 300 zeros, and the
/// rest of the line was cut at the length limit).
fn number_text(n: f64) -> String {
    if n.is_nan() {
        return "nan".into();
    }
    let a = n.abs();
    if a.is_finite() && a != 0.0 && !(1e-4..1e15).contains(&a) {
        format!("{n:e}")
    } else {
        n.to_string()
    }
}

#[cfg(test)]
mod tests {
    use super::number_text;

    #[test]
    fn log_writes_large_and_small_numbers_with_an_exponent() {
        assert_eq!(number_text(1e20), "1e20");
        assert_eq!(number_text(-1e-300), "-1e-300");
        assert_eq!(number_text(3.4028234663852886e38), "3.4028234663852886e38");
        assert_eq!(number_text(0.1), "0.1");
        assert_eq!(number_text(12345.5), "12345.5");
        assert_eq!(number_text(0.0), "0");
        assert_eq!(number_text(f64::INFINITY), "inf");
        assert_eq!(number_text(f64::NAN), "nan");
        for n in [1e20, 1e-300, 0.1, 2.5e-7, 123456789.125] {
            assert_eq!(number_text(n).parse::<f64>().unwrap(), n);
        }
    }
}
