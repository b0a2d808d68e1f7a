//! `materials.lua`: the modder's material declarations, read in the same
//! sandbox as scripts and registered by name (ids stay stable across hot
//! reloads: see [`MaterialRegistry`]).
//!
//! ```lua
//! return {
//!   lava = { color = { 255, 96, 24 }, kind = "liquid", density = 3.1 },
//!   sand = { color = { 218, 196, 140 }, kind = "granular", density = 1.6 },
//! }
//! ```

use mlua::{Table, Value};

use crate::sim::script::sandboxed;
use crate::sim::{Limits, ScriptSource, SimError};
use crate::world::{MaterialDef, MaterialKind, MaterialRegistry};

fn err(src: &ScriptSource, name: Option<&str>, msg: String) -> SimError {
    SimError::Declaration {
        script: src.name.clone(),
        line: name.and_then(|n| super::declare::line_in(&src.text, n)),
        // Names in it come from the script: no raw control characters.
        msg: crate::text::escape_controls(&msg, false).into_owned(),
    }
}

/// Register every material `src` declares. On error nothing is registered.
pub fn load_materials(
    src: &ScriptSource,
    registry: &mut MaterialRegistry,
) -> Result<Vec<String>, SimError> {
    let limits = Limits::default();
    let lua = sandboxed(limits, &src.name)?;
    // Run once, at load: never worth native code.
    lua.enable_jit(false);
    crate::sim::interrupt::arm(limits.instructions, limits.time, limits.memory / 10 * 9);
    let v: Value = lua
        .load(&*src.text)
        .set_name(format!("@{}.lua", src.name))
        .eval()
        .map_err(|e| super::script::load_error(src, e))?;
    let Value::Table(t) = v else {
        return Err(err(
            src,
            None,
            format!(
                "must return a table of materials, it returned {}",
                super::declare::a(v.type_name())
            ),
        ));
    };
    let mut defs: Vec<(String, MaterialDef)> = Vec::new();
    for pair in t.pairs::<Value, Value>() {
        let (key, v) = pair.map_err(|e| err(src, None, format!("cannot read the table: {e}")))?;
        // A list (`{ {color = …}, … }`) or a number key made materials
        // named "1", "2"… (regression, hostile probe).
        let Value::String(key) = key else {
            return Err(err(
                src,
                None,
                format!(
                    "material names must be strings (name = {{ color, kind, density }}); a key is {}",
                    super::declare::a(key.type_name())
                ),
            ));
        };
        let name = key.to_string_lossy();
        if !MaterialRegistry::valid_name(&name) {
            // Cut: a 4 MB name was echoed whole into every `/status`
            // (regression, hostile probe).
            return Err(err(
                src,
                None,
                format!(
                    "material name '{}' must be 1 to 64 letters, digits and '_' (and not 'air')",
                    crate::text::shown(&name, 80)
                ),
            ));
        }
        let Value::Table(d) = v else {
            return Err(err(
                src,
                Some(&name),
                format!("material '{name}' must be a table {{color, kind, density}}"),
            ));
        };
        defs.push((name.clone(), parse_def(src, &name, &d)?));
    }
    defs.sort_by(|a, b| a.0.cmp(&b.0));
    let mut trial = registry.clone();
    for (name, def) in &defs {
        trial
            .register(name, *def)
            .map_err(|e| err(src, Some(name), e.to_string()))?;
    }
    *registry = trial;
    Ok(defs.into_iter().map(|(n, _)| n).collect())
}

fn parse_def(src: &ScriptSource, name: &str, d: &Table) -> Result<MaterialDef, SimError> {
    let bad = |m: String| err(src, Some(name), format!("material '{name}': {m}"));
    super::declare::only_known_keys(
        src,
        d,
        &format!("material '{name}'"),
        &["color", "kind", "density"],
    )?;
    let color: Table = d
        .get("color")
        .map_err(|_| bad("color must be {r, g, b}".into()))?;
    let n = color.raw_len();
    if n > 3 {
        return Err(bad(format!(
            "color must be 3 numbers {{r, g, b}}; it has {n}"
        )));
    }
    super::declare::only_known_keys(
        src,
        &color,
        &format!("material '{name}': color"),
        &["[1]", "[2]", "[3]"],
    )?;
    let mut rgb = [0u8; 3];
    for (k, c) in rgb.iter_mut().enumerate() {
        // Numbers only: "12" was taken as 12, where a density of "2" is
        // refused (regression, hostile probe).
        let v: f64 = match color.get::<Value>(k + 1) {
            Ok(Value::Number(n)) => n,
            Ok(Value::Integer(n)) => n as f64,
            _ => return Err(bad("color must be 3 numbers {r, g, b}".into())),
        };
        if !(0.0..=255.0).contains(&v) {
            return Err(bad(format!("colour component {v} is outside 0..=255")));
        }
        *c = v as u8;
    }
    let kind = match d.get::<Value>("kind") {
        Ok(Value::Nil) => MaterialKind::Solid,
        Ok(Value::String(s)) => s
            .to_str()
            .map_err(|_| bad("kind must be text".into()))?
            .parse()
            .map_err(bad)?,
        _ => return Err(bad("kind must be solid, liquid, granular or gas".into())),
    };
    let density = match d.get::<Value>("density") {
        Ok(Value::Nil) => 1.0,
        Ok(Value::Number(n)) => n,
        Ok(Value::Integer(n)) => n as f64,
        _ => return Err(bad("density must be a number".into())),
    };
    Ok(MaterialDef {
        color: rgb,
        kind,
        density: density as f32,
    })
}

#[cfg(test)]
mod tests {
    use super::*;

    fn declaration_line(text: &str) -> Option<usize> {
        let src = ScriptSource {
            name: "materials".into(),
            text: text.into(),
        };
        match load_materials(&src, &mut MaterialRegistry::new()) {
            Err(SimError::Declaration { line, .. }) => line,
            other => panic!("expected a declaration error, got {other:?}"),
        }
    }

    #[test]
    fn regression_an_entry_that_is_not_a_table_is_reported_at_its_own_line() {
        // The probe's case: `x = 1,` on line 7 was reported at line 1,
        // the first line holding an `x`.
        let text = "-- example materials, extended\nreturn {\n  -- sand: max grain\n  \
                    sand = { color = { 218, 196, 140 }, kind = \"granular\" },\n\n  \
                    lava = { color = { 255, 96, 24 } },\n  x = 1,\n}\n";
        assert_eq!(declaration_line(text), Some(7));
        // A bracketed key, and a name that is a prefix of another.
        let text = "return {\n  sandy = { color = { 1, 2, 3 } },\n  [\"sand\"] = 2,\n}\n";
        assert_eq!(declaration_line(text), Some(3));
        // An error inside an entry's table names that entry's line, not
        // a comment that mentions it earlier.
        let text = "-- lava glows\nreturn {\n  lava = { color = { 300, 0, 0 } },\n}\n";
        assert_eq!(declaration_line(text), Some(3));
        // Review: a block comment, a long string, and `--` inside a
        // string key.
        let text = "--[[ old:\n  x = { color = { 1, 2, 3 } },\n]]\nreturn {\n  sand = { color = { 1, 2, 3 } },\n  x = 1,\n}\n";
        assert_eq!(declaration_line(text), Some(6));
        let text = "local doc = [==[\nx = the material\n]==]\nreturn {\n  sand = { color = { 1, 2, 3 } },\n  x = 1,\n}\n";
        assert_eq!(declaration_line(text), Some(6));
        let line_in = crate::sim::runtime::declare::line_in;
        let text = "return {\n  a = \"x--y\", y = 1,\n  z = 2,\n  w = y,\n}\n";
        assert_eq!(line_in(text, "y"), Some(2));
        // Second review: a backtick string holding `--[[`, strings
        // continued by `\` and `\z` over a line break holding `--[[`, and
        // a short string holding `speed = 2`.
        let text = "local tag = `--[[`\nreturn {\n  a = 1,\n  speed = 2,\n}\n-- ]] speed = 3\n";
        assert_eq!(line_in(text, "speed"), Some(4));
        let text =
            "local s = \"a\\\n--[[ b\"\nreturn {\n  a = 1,\n  speed = 2,\n}\n-- ]] speed = 3\n";
        assert_eq!(line_in(text, "speed"), Some(5));
        let text =
            "local s = \"a\\z\n  --[[ b\"\nreturn {\n  a = 1,\n  speed = 2,\n}\n-- ]] speed = 3\n";
        assert_eq!(line_in(text, "speed"), Some(5));
        let text =
            "local USAGE = \"set speed = 2 in world.toml\"\nreturn {\n  a = 1,\n  speed = 2,\n}\n";
        assert_eq!(line_in(text, "speed"), Some(4));
        // A name listed as a string is found there, not at a local.
        let string_line_in = crate::sim::runtime::declare::string_line_in;
        let text = "local glass = 1\nreturn {\n  materials = { \"sand\", \"glass\" },\n}\n";
        assert_eq!(string_line_in(text, "glass"), Some(3));
        assert_eq!(line_in(text, "glass"), Some(1));
    }
}
