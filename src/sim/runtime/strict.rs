//! Unknown names in a kernel's context are errors that say what is known.
//!
//! `c`, `c.r`, `c.w`, `c.p` and `c.m` are read-only tables. Each also gets
//! a frozen metatable whose `__index`, called only for a name the table
//! lacks, raises an error at the kernel's line (level 2 of a Lua function):
//! - `c.w.mat: pass 'p' does not list "mat" in its writes` (and `reads`);
//! - `c.p.rte: script 'fire' declares no parameter "rte" (its parameters: rate)`;
//! - `c.m.grasss: script 'fire' does not list "grasss" in its materials (listed: air, grass)`;
//! - `c.dT: the context has no field "dT" (it has dt, tick, random, p, m, r, w)`.
//!
//! A misspelt name read as nil and failed later, far from the typo, on
//! "attempt to compare number < nil" or "number expected, got nil"
//! (modder probe; for `c.r`/`c.w`, the claims audit).

use mlua::{Function, Lua, Table};

/// Compile the maker of such metatables: `make(prefix, before, after)`
/// gives one whose `__index` raises `prefix .. name .. before .. name ..
/// after`. Compiled once per VM.
pub(super) fn maker(lua: &Lua) -> mlua::Result<Function> {
    lua.load(
        r#"local prefix, before, after = ...
        local mt = { __index = function(_, k)
          local name = type(k) == "string" and k or ("[" .. type(k) .. "]")
          error(prefix .. name .. before .. name .. after, 2)
        end }
        table.freeze(mt)
        return mt"#,
    )
    .set_name("=unknown")
    .into_function()
}

/// The metatable of a pass's `c.r` (`tbl` "r", `list` "reads") or `c.w`
/// ("w", "writes").
pub(super) fn unlisted(make: &Function, pass: &str, tbl: &str, list: &str) -> mlua::Result<Table> {
    make.call((
        format!("c.{tbl}."),
        format!(": pass '{pass}' does not list \""),
        format!("\" in its {list}"),
    ))
}

/// The metatable of `c.p` for script `script` with parameters `names`.
pub(super) fn unknown_param<'a>(
    make: &Function,
    script: &str,
    names: impl Iterator<Item = &'a str>,
) -> mlua::Result<Table> {
    let names: Vec<&str> = names.collect();
    let known = if names.is_empty() {
        "it declares none".to_string()
    } else {
        format!("its parameters: {}", names.join(", "))
    };
    make.call((
        "c.p.",
        format!(": script '{script}' declares no parameter \""),
        format!("\" ({known})"),
    ))
}

/// The metatable of `c.m` for script `script` listing `names` (after `air`).
pub(super) fn unknown_material<'a>(
    make: &Function,
    script: &str,
    names: impl Iterator<Item = &'a str>,
) -> mlua::Result<Table> {
    let listed: Vec<&str> = std::iter::once("air").chain(names).collect();
    make.call((
        "c.m.",
        format!(": script '{script}' does not list \""),
        format!("\" in its materials (listed: {})", listed.join(", ")),
    ))
}

/// The metatable of `c` itself.
pub(super) fn unknown_field(make: &Function) -> mlua::Result<Table> {
    make.call((
        "c.",
        ": the context has no field \"",
        "\" (it has dt, tick, random, p, m, r, w)",
    ))
}
