//! Script files on disk: a script is read only from a regular `.lua` file
//! of bounded size, named after its stem, and refused with a message that
//! names it when it is anything else.

use std::path::Path;

use super::script::ScriptSource;
use crate::sim::SimError;

/// Largest script file (a script is code, not data).
pub const MAX_SCRIPT_BYTES: u64 = 4 << 20;

/// [`read_script`] for a file that may be absent (`materials.lua`): `None`
/// only when nothing is at `path`. Anything else there, a folder, a FIFO, a
/// device or a dangling link, is read as a script and refused as one
/// (regression: such a `materials.lua` was taken as missing, and the error
/// then blamed the script that named a material).
pub fn read_optional_script(path: &Path) -> Result<Option<ScriptSource>, SimError> {
    match std::fs::symlink_metadata(path) {
        Err(e) if e.kind() == std::io::ErrorKind::NotFound => Ok(None),
        _ => read_script(path).map(Some),
    }
}

/// Read a script file (a regular file of at most [`MAX_SCRIPT_BYTES`]) into
/// a source named after its stem.
pub fn read_script(path: &Path) -> Result<ScriptSource, SimError> {
    let stem = path
        .file_stem()
        .map(|s| s.to_string_lossy().to_string())
        .unwrap_or_else(|| "script".into());
    // A script is named by its stem wherever a parameter is set: a name
    // that is not UTF-8 loaded, but no command line could name it
    // (regression, odd-paths probe).
    if path.file_stem().is_some_and(|s| s.to_str().is_none()) {
        return Err(SimError::Declaration {
            script: crate::text::escape_controls(&stem, false).into_owned(),
            line: None,
            msg: "script file names must be UTF-8 (a script's parameters are set by its name)"
                .into(),
        });
    }
    // The name is in every message about the script: one that would print
    // a newline, a terminal escape or a bidirectional override is refused
    // (regression, hostile probe), named with those characters escaped.
    let name = crate::text::escape_controls(&stem, false).into_owned();
    if name != stem {
        return Err(SimError::Declaration {
            script: name,
            line: None,
            msg: "script file names must not contain control characters or bidirectional overrides"
                .into(),
        });
    }
    // Only a regular file of bounded size: a FIFO hung the engine and a
    // link to /dev/zero filled memory (regression).
    let text = crate::files::read_text(path, MAX_SCRIPT_BYTES).map_err(|e| SimError::File {
        script: name.clone(),
        msg: e.to_string(),
    })?;
    // Messages call a script `NAME.lua`: another file would be named
    // after one that does not exist (regression, docs walk: `sim --script
    // README.md` reported "README.lua:1: syntax error").
    if path.extension().is_none_or(|e| e != "lua") {
        return Err(SimError::File {
            script: name,
            msg: format!(
                "{}: a script is a .lua file (messages name it after its stem)",
                crate::text::shown(&path.display().to_string(), 200)
            ),
        });
    }
    // A byte-order mark, which some editors write, is not Luau: it is
    // dropped, as TOML drops it in a world config (regression, fuzzing:
    // a materials.lua saved with one was a syntax error).
    let text = match text.strip_prefix('\u{feff}') {
        Some(rest) => rest.to_string(),
        None => text,
    };
    Ok(ScriptSource {
        name,
        text: text.into(),
    })
}
