//! Lua run in every script VM before the sandbox freezes its globals:
//! `pcall`/`xpcall` that let out-of-memory through, `tostring` /
//! `string.format` that never show an address, and a `setmetatable` that
//! refuses weak tables and freezes metatables. All keep a script's outcome
//! independent of which VM ran it and what ran there before.

/// `pcall` and `xpcall` that let an out-of-memory error through. Whether
/// an allocation fits the limit depends on how much garbage the VM has not
/// collected yet, which depends on which tiles it ran before: a script that
/// caught the error and went on gave different worlds on different runs
/// and thread counts (regression). Uncaught, the failure reaches the
/// runtime, which collects all garbage and runs the call once more
/// ([`super::script::ScriptVm::failed_on_memory`]), so the verdict is the same whatever
/// ran before. `error(MEM, 0)` re-raises without allocating.
pub(super) const UNCATCHABLE_MEMORY_ERRORS: &str = r#"
local MEM = "not enough memory"
local rawpcall, rawxpcall, error, type = pcall, xpcall, error, type
local function pass(ok, ...)
    if not ok and (...) == MEM then
        error(MEM, 0)
    end
    return ok, ...
end
pcall = function(f, ...)
    return pass(rawpcall(f, ...))
end
xpcall = function(f, handler, ...)
    if type(handler) ~= "function" then
        -- Luau's own message, at the script's line (regression, fuzzing:
        -- raised in here, it named a line of this wrapper).
        error("invalid argument #2 to 'xpcall' (function expected)", 2)
    end
    return pass(rawxpcall(f, function(e)
        if e == MEM then
            return MEM
        end
        -- The handler running out of memory too (Luau would report
        -- "error in error handling", which the script could catch).
        local ok, r = rawpcall(handler, e)
        if ok then
            return r
        elseif r == MEM then
            return MEM
        end
        error(r, 0)
    end, ...))
end
"#;

/// `tostring` and `string.format` that show a table, function, buffer or
/// userdata by its type name (or its `__tostring`), never its address:
/// addresses differ between VMs and runs, so a kernel that branched on one
/// (or on a string holding one) made worlds that differed from run to run
/// (regression).
pub(super) const NO_ADDRESSES: &str = r##"
local rawtostring, rawformat, type, find, select, unpack =
    tostring, string.format, type, string.find, select, table.unpack
local objects = { table = true, userdata = true, ["function"] = true, buffer = true, thread = true }
local function shown(v)
    local kind = type(v)
    local text = rawtostring(v)
    -- Luau's own text for an object is "TYPE: 0xADDRESS"; what a
    -- __tostring returns is kept (getmetatable cannot decide which it is:
    -- __metatable can lie).
    if objects[kind] and type(text) == "string" and find(text, ": 0x%x+$") then
        return kind
    end
    return text
end
tostring = shown
-- A format error is raised at the script's line, not this wrapper's
-- (regression, hostile probe: errors named "sandbox:27"). Levels: 1 is
-- `fail`, 2 the wrapper, 3 the script's caller.
local pcall, error = pcall, error
local function fail(msg)
    error(msg, 3)
end
string.format = function(fmt, ...)
    local n = select("#", ...)
    for i = 1, n do
        if objects[type((select(i, ...)))] then
            local args = { ... }
            for j = 1, n do
                if objects[type(args[j])] then
                    args[j] = shown(args[j])
                end
            end
            local ok, r = pcall(rawformat, fmt, unpack(args, 1, n))
            if not ok then
                fail(r)
            end
            return r
        end
    end
    local ok, r = pcall(rawformat, fmt, ...)
    if not ok then
        fail(r)
    end
    return r
end
"##;

/// `setmetatable` that refuses weak tables and freezes the metatable it
/// sets (regression, hostile probe):
/// - what a weak table (`__mode`) still holds depends on when the garbage
///   collector last ran, so a kernel that counted one gave different
///   worlds from run to run, even on one thread;
/// - a metatable is shared by every table it is set on, and a kernel that
///   counted in one (`getmetatable(proxy).n += 1`) kept state between
///   calls that depended on which tiles its VM ran. Frozen, `__mode` cannot
///   be added later either.
pub(super) const NO_WEAK_TABLES: &str = r#"
local rawsetmetatable, rawget, type, error = setmetatable, rawget, type, error
local rawpcall = pcall
local freeze, isfrozen = table.freeze, table.isfrozen
setmetatable = function(t, mt)
    -- Bad arguments are Luau's own errors, at the script's line (regression,
    -- fuzzing: raised in here, they named a line of this wrapper).
    if type(t) ~= "table" then
        error("invalid argument #1 to 'setmetatable' (table expected, got " .. type(t) .. ")", 2)
    end
    if mt ~= nil and type(mt) ~= "table" then
        error("invalid argument #2 to 'setmetatable' (nil or table expected)", 2)
    end
    if type(mt) == "table" then
        if rawget(mt, "__mode") ~= nil then
            error("weak tables (__mode) are not allowed: what they hold depends on when the garbage collector runs", 2)
        end
        if not isfrozen(mt) then
            freeze(mt)
        end
    end
    local ok, r = rawpcall(rawsetmetatable, t, mt)
    if not ok then
        if r == "not enough memory" then
            error(r, 0)
        end
        -- A protected metatable (`__metatable`) or a frozen table.
        error(r, 2)
    end
    return r
end
"#;
