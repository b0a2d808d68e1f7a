//! `brickworld init`: a world and its scripts written out for a modder.

use std::path::{Path, PathBuf};

use anyhow::{Context, Result, bail};

/// Write the default world and its scripts into `dir` for a modder to edit:
/// `dir/world.toml` and `dir/scripts/*.lua`. Existing files are never
/// overwritten.
pub fn init(dir: &Path) -> Result<Vec<PathBuf>> {
    let scripts = dir.join("scripts");
    let mut files: Vec<(PathBuf, String)> = crate::sim::embedded::SCRIPTS
        .iter()
        .map(|(f, text)| (scripts.join(f), text.to_string()))
        .collect();
    let world = crate::engine::world_config::DEFAULT_WORLD
        .replace("scripts_dir = \"../scripts\"", "scripts_dir = \"scripts\"");
    files.push((dir.join("world.toml"), world));
    // `symlink_metadata`: a dangling link counts as there (regression: init
    // wrote through it, outside DIR).
    let there = |p: &Path| std::fs::symlink_metadata(p).is_ok();
    if let Some((p, _)) = files.iter().find(|(p, _)| there(p)) {
        bail!(
            "{} already exists; brickworld init never overwrites files (choose an empty directory)",
            p.display()
        );
    }
    if there(&scripts) && !scripts.is_dir() {
        bail!(
            "{} exists and is not a directory (choose an empty directory)",
            scripts.display()
        );
    }
    std::fs::create_dir_all(&scripts)
        .with_context(|| format!("cannot create {}", scripts.display()))?;
    for (p, text) in &files {
        // `create_new` never follows a link or replaces a file that
        // appeared meanwhile.
        std::fs::OpenOptions::new()
            .write(true)
            .create_new(true)
            .open(p)
            .and_then(|mut f| std::io::Write::write_all(&mut f, text.as_bytes()))
            .with_context(|| format!("cannot write {}", p.display()))?;
    }
    Ok(files.into_iter().map(|(p, _)| p).collect())
}
