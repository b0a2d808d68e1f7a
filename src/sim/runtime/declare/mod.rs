//! Reading a script's returned table into a [`ScriptSpec`]: every field
//! checked, each error naming the script, the field and its line.

use mlua::{Table, Value};

use super::spec::{Grid, MAT, ScriptSource, ScriptSpec};
use crate::sim::SimError;

mod keys;
pub(super) mod read;
mod tables;
pub(super) use keys::only_known_keys;
use keys::{COLUMN_ONLY, SCRIPT_KEYS, VOXEL_ONLY, plain};
pub use keys::{MAX_NAME_LEN, is_plain_name};
pub use read::MAX_LIST;
use read::{field, strings};
use tables::{
    known, parse_boundary, parse_cfl, parse_fills, parse_params, parse_passes, parse_ranges,
};

/// The line (1-based) where `needle`, a name from a script's returned
/// table, is most likely declared, for declaration errors. Luau keeps no
/// line for a table constructor's keys, so this reads the text, outside
/// `--` comments, preferring in turn:
/// 1. the name as a whole word used as a key (`name =`, not `name ==`);
/// 2. the name as a bracketed string key (`["name"]`);
/// 3. the name as a whole word;
/// 4. the name anywhere (the one rule before: a one-letter material `x`
///    was reported at the first line holding an `x`, regression, hostile
///    probe of the twenty-third session).
///
/// ```
/// use brickworld::sim::runtime::declare::line_in;
/// let text = "-- an example\nreturn {\n  max = 2,\n  x = 1,\n}\n";
/// assert_eq!(line_in(text, "x"), Some(4));
/// assert_eq!(line_in(text, "nowhere"), None);
/// ```
pub fn line_in(text: &str, needle: &str) -> Option<usize> {
    if needle.is_empty() {
        return None;
    }
    let lines = code_lines(text);
    let first = |hit: &dyn Fn(&str) -> bool| lines.code.iter().position(|l| hit(l)).map(|i| i + 1);
    let first_in_strings =
        |hit: &dyn Fn(&str) -> bool| lines.strings.iter().position(|l| hit(l)).map(|i| i + 1);
    let as_key = |l: &str| {
        whole_words(l, needle).any(|end| {
            let rest = l[end..].trim_start();
            rest.starts_with('=') && !rest.starts_with("==")
        })
    };
    let bracketed =
        |l: &str| l.contains(&format!("[\"{needle}\"]")) || l.contains(&format!("['{needle}']"));
    first(&as_key)
        .or_else(|| first_in_strings(&bracketed))
        .or_else(|| first(&|l| whole_words(l, needle).next().is_some()))
        .or_else(|| text.lines().position(|l| l.contains(needle)).map(|i| i + 1))
}

/// The lines of `text` as code, twice: with every string's contents
/// blanked (`code`), and with short strings kept whole (`strings`, for
/// names written as strings: `["name"]`, `{ "sand" }`). Both blank `--`
/// comments, `--[[ … ]]` block comments and `[[ … ]]` long strings, to
/// spaces, so lines stay where they were. Short strings are `"…"`, `'…'`
/// and Luau's `` `…` ``, with `\` escapes, a `\` before a line break and
/// `\z` continuing them (review: a name in a block comment, a long
/// string or a short one was taken for its declaration, and `--` in a
/// string cut its line).
struct CodeLines {
    code: Vec<String>,
    strings: Vec<String>,
}

fn code_lines(text: &str) -> CodeLines {
    // The closing bracket of the long bracket open at `s` (`[[`, `[==[`).
    fn long_open(s: &[u8]) -> Option<(usize, Vec<u8>)> {
        let eq = s.iter().skip(1).take_while(|&&c| c == b'=').count();
        (s.first() == Some(&b'[') && s.get(1 + eq) == Some(&b'['))
            .then(|| (2 + eq, [b"]".as_slice(), &vec![b'='; eq], b"]"].concat()))
    }
    let b = text.as_bytes();
    let (mut code, mut strings) = (Vec::with_capacity(b.len()), Vec::with_capacity(b.len()));
    // Blank `n` bytes in both (a line break stays one).
    let blank = |code: &mut Vec<u8>, strings: &mut Vec<u8>, bytes: &[u8]| {
        for &c in bytes {
            let k = if c == b'\n' { b'\n' } else { b' ' };
            code.push(k);
            strings.push(k);
        }
    };
    // Inside a long comment or string: its closing bracket.
    let mut long: Option<Vec<u8>> = None;
    let mut i = 0;
    while i < b.len() {
        if let Some(close) = &long {
            if b[i..].starts_with(close) {
                let n = close.len();
                blank(&mut code, &mut strings, &b[i..i + n]);
                i += n;
                long = None;
            } else {
                blank(&mut code, &mut strings, &b[i..i + 1]);
                i += 1;
            }
            continue;
        }
        match b[i] {
            q @ (b'"' | b'\'' | b'`') => {
                code.push(q);
                strings.push(q);
                i += 1;
                while i < b.len() && b[i] != q && b[i] != b'\n' {
                    if b[i] == b'\\' && i + 1 < b.len() {
                        let mut n = 2;
                        if b[i + 1] == b'z' {
                            // `\z` skips the white space after it, line
                            // breaks included.
                            while b.get(i + n).is_some_and(|c| c.is_ascii_whitespace()) {
                                n += 1;
                            }
                        }
                        for &c in &b[i..i + n] {
                            code.push(if c == b'\n' { b'\n' } else { b' ' });
                            strings.push(c);
                        }
                        i += n;
                        continue;
                    }
                    code.push(b' ');
                    strings.push(b[i]);
                    i += 1;
                }
                if i < b.len() && b[i] == q {
                    code.push(q);
                    strings.push(q);
                    i += 1;
                }
            }
            b'-' if b[i..].starts_with(b"--") => {
                if let Some((n, close)) = long_open(&b[i + 2..]) {
                    blank(&mut code, &mut strings, &b[i..i + 2 + n]);
                    i += 2 + n;
                    long = Some(close);
                } else {
                    let end = b[i..]
                        .iter()
                        .position(|&c| c == b'\n')
                        .map_or(b.len(), |e| i + e);
                    blank(&mut code, &mut strings, &b[i..end]);
                    i = end;
                }
            }
            b'[' if long_open(&b[i..]).is_some() => {
                let (n, close) = long_open(&b[i..]).expect("checked");
                blank(&mut code, &mut strings, &b[i..i + n]);
                i += n;
                long = Some(close);
            }
            c => {
                code.push(c);
                strings.push(c);
                i += 1;
            }
        }
    }
    let lines = |v: Vec<u8>| -> Vec<String> {
        String::from_utf8_lossy(&v)
            .lines()
            .map(str::to_string)
            .collect()
    };
    CodeLines {
        code: lines(code),
        strings: lines(strings),
    }
}

/// The line (1-based) where `needle` first stands as a string (`"name"` or
/// `'name'`) in code, else [`line_in`]'s: for names listed as strings,
/// such as a voxel script's `materials = { "sand", "glass" }`, which a
/// `local glass = 1` earlier must not claim (review).
pub fn string_line_in(text: &str, needle: &str) -> Option<usize> {
    let quoted = [format!("\"{needle}\""), format!("'{needle}'")];
    code_lines(text)
        .strings
        .iter()
        .position(|l| quoted.iter().any(|q| l.contains(q.as_str())))
        .map(|i| i + 1)
        .or_else(|| line_in(text, needle))
}

/// The end of each occurrence of `needle` in `line` that is not part of a
/// longer identifier.
fn whole_words<'a>(line: &'a str, needle: &'a str) -> impl Iterator<Item = usize> + 'a {
    let ident = |c: char| c.is_alphanumeric() || c == '_';
    line.match_indices(needle).filter_map(move |(at, _)| {
        let end = at + needle.len();
        let before = line[..at].chars().next_back().is_some_and(ident);
        let after = line[end..].chars().next().is_some_and(ident);
        (!before && !after).then_some(end)
    })
}

/// The most channels one script may declare (the stored blobs' bound: a
/// chunk or column blob carries at most as many).
pub const MAX_SCRIPT_CHANNELS: usize = 256;
/// The most parameters one script may declare.
pub const MAX_SCRIPT_PARAMS: usize = 256;
/// The most passes one script may declare.
pub const MAX_SCRIPT_PASSES: usize = 256;

/// A declaration error in `src`, at the line of `needle` if given. The
/// message is cut to one readable line: names in it come from the script,
/// so control characters (a newline too) are escaped, not cut at
/// (regression, hostile probe 3: a key holding a newline ended the message
/// there, and a key holding `x.lua:42:` was taken for Luau's location).
/// Errors of Luau's go through [`read::from_lua`].
pub(super) fn declaration(
    src: &ScriptSource,
    needle: Option<&str>,
    msg: impl Into<String>,
) -> SimError {
    SimError::Declaration {
        script: src.name.clone(),
        line: needle.and_then(|n| line_in(&src.text, n)),
        msg: super::errors::one_line(&msg.into()),
    }
}

/// A Lua type name with its article ("a table", "an integer").
pub(super) fn a(type_name: &str) -> String {
    match type_name.chars().next() {
        // Not 'u': "a userdata".
        Some('a' | 'e' | 'i' | 'o') => format!("an {type_name}"),
        _ => format!("a {type_name}"),
    }
}

/// The validated declarations of the table `def` that `src` returned.
pub(super) fn parse(src: &ScriptSource, def: &Table) -> Result<ScriptSpec, SimError> {
    // A plain table: what is declared is what is there.
    if def.metatable().is_some() {
        return Err(declaration(
            src,
            Some("setmetatable"),
            "the returned table has a metatable; a declaration is a plain table",
        ));
    }
    only_known_keys(src, def, "the script's table", &SCRIPT_KEYS)?;
    // The grid first: a typo there explains the rest (regression: `grid =
    // "voxel"` was reported as declaring no channels).
    let grid = match field(src, def, "grid")? {
        Value::Nil => Grid::Columns,
        Value::String(g) if g.to_str().is_ok_and(|g| g == "columns") => Grid::Columns,
        Value::String(g) if g.to_str().is_ok_and(|g| g == "voxels") => Grid::Voxels,
        _ => {
            return Err(declaration(
                src,
                Some("grid"),
                "'grid' must be \"columns\" or \"voxels\"",
            ));
        }
    };
    let channels = strings(src, def, "channels")?;
    if channels.len() > MAX_SCRIPT_CHANNELS {
        return Err(declaration(
            src,
            Some("channels"),
            format!(
                "the script declares {} channels, more than {MAX_SCRIPT_CHANNELS}",
                channels.len()
            ),
        ));
    }
    // Names are bounded (64 plain characters) before any is compared with
    // another (regression, review: 40 KB names made the checks below cost
    // a second of Rust time per load).
    for c in &channels {
        if c == MAT && grid == Grid::Voxels {
            return Err(declaration(
                src,
                Some(c),
                "'mat' is the material buffer; name the channel otherwise",
            ));
        }
        plain(src, "channel", c)?;
    }
    if channels.is_empty() && grid == Grid::Columns {
        return Err(declaration(
            src,
            Some("channels"),
            "the script declares no channels",
        ));
    }
    // A declaration the runtime would not act on for this grid is refused,
    // not ignored (regression: `nonnegative`, `boundary` and `cfl` loaded on
    // voxel scripts and did nothing).
    let (foreign, kind): (&[&str], &str) = match grid {
        Grid::Columns => (&VOXEL_ONLY, "voxel scripts (grid = \"voxels\")"),
        Grid::Voxels => (&COLUMN_ONLY, "column scripts (grid = \"columns\")"),
    };
    for key in foreign {
        let v = field(src, def, key)?;
        // `sky = false` says nothing, on either grid.
        let says_nothing = match v {
            Value::Nil => true,
            Value::Boolean(false) => *key == "sky",
            _ => false,
        };
        if !says_nothing {
            let field = key;
            return Err(declaration(
                src,
                Some(field),
                format!("'{field}' is for {kind}"),
            ));
        }
    }
    let materials = strings(src, def, "materials")?;
    for m in &materials {
        plain(src, "material", m)?;
    }
    let only = strings(src, def, "only")?;
    let keep_awake = strings(src, def, "keep_awake")?;
    let conserved = strings(src, def, "conserved")?;
    let sky = match field(src, def, "sky")? {
        Value::Nil => false,
        Value::Boolean(b) if grid == Grid::Voxels || !b => b,
        _ => {
            return Err(declaration(
                src,
                Some("sky"),
                "'sky' is true or false, for voxel scripts",
            ));
        }
    };
    let boundary = parse_boundary(src, def, &channels)?;
    let drains = strings(src, def, "drains")?;
    for d in &drains {
        known(src, &channels, d, "'drains'")?;
    }
    let cfl = parse_cfl(src, def, &channels)?;
    let fills = parse_fills(src, def, &channels, &materials)?;
    for m in only.iter().chain(&keep_awake) {
        if !materials.contains(m) {
            return Err(declaration(
                src,
                Some(m),
                format!("material '{m}' must also be listed in 'materials'"),
            ));
        }
    }
    let nonnegative = strings(src, def, "nonnegative")?;
    for c in &nonnegative {
        known(src, &channels, c, "'nonnegative'")?;
    }
    for c in &conserved {
        known(src, &channels, c, "'conserved'")?;
    }
    let params = parse_params(src, def)?;
    let ranges = parse_ranges(src, def, &channels)?;
    let passes = parse_passes(src, def, grid, &channels)?;
    if let Some(c) = &cfl {
        for p in [&c.gravity, &c.dx] {
            if !params.iter().any(|q| &q.name == p) {
                return Err(declaration(
                    src,
                    Some("cfl"),
                    format!("cfl names parameter '{p}', which the script does not declare"),
                ));
            }
        }
    }
    Ok(ScriptSpec {
        name: src.name.clone(),
        grid,
        materials,
        only,
        keep_awake,
        conserved,
        sky,
        boundary,
        cfl,
        drains,
        fills,
        channels,
        nonnegative,
        params,
        ranges,
        passes,
    })
}
