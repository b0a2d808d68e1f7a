//! The shipped scripts, built into the binary: the embedded default world
//! runs from any directory (after `cargo install`, say), and
//! `brickworld init DIR` writes them out for a modder to edit.

use crate::sim::ScriptSource;

/// `(file name, source)` of every shipped script.
pub const SCRIPTS: &[(&str, &str)] = &[
    ("water.lua", include_str!("../../../scripts/water.lua")),
    ("erosion.lua", include_str!("../../../scripts/erosion.lua")),
    ("snow.lua", include_str!("../../../scripts/snow.lua")),
    (
        "materials.lua",
        include_str!("../../../scripts/materials.lua"),
    ),
    ("water3d.lua", include_str!("../../../scripts/water3d.lua")),
    ("sand.lua", include_str!("../../../scripts/sand.lua")),
    ("lava.lua", include_str!("../../../scripts/lava.lua")),
    ("grass.lua", include_str!("../../../scripts/grass.lua")),
    ("rain3d.lua", include_str!("../../../scripts/rain3d.lua")),
];

/// The shipped script called `file` (e.g. `water.lua`), if there is one.
pub fn script(file: &str) -> Option<ScriptSource> {
    SCRIPTS
        .iter()
        .find(|(f, _)| *f == file)
        .map(|(f, text)| ScriptSource {
            name: f.trim_end_matches(".lua").to_string(),
            text: (*text).into(),
        })
}
