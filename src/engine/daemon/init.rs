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
    // The folders this run makes: DIR, any missing parents, and scripts.
    let made: Vec<PathBuf> = dir
        .ancestors()
        .take_while(|a| !a.as_os_str().is_empty() && !there(a))
        .map(Path::to_path_buf)
        .collect();
    let made_scripts = !there(&scripts);
    {
        // An interrupt undoes all of it, as a failure does (regression,
        // stop-path probe: a Ctrl-C left some of the files, and the next
        // `init` refused the folder); the folders are made and listed as
        // one (review).
        let _making = crate::files::landing();
        std::fs::create_dir_all(&scripts)
            .with_context(|| format!("cannot create {}", scripts.display()))?;
        for d in made.iter().rev() {
            crate::files::undo_on_interrupt(d, true);
        }
        if made_scripts {
            crate::files::undo_on_interrupt(&scripts, true);
        }
    }
    // Every file is written in full beside its place first, then linked in
    // (regression: a write past `ulimit -f` left a truncated script, and
    // the next `init` refused to overwrite it). On any failure, what this
    // run put in place is taken out again.
    let mut temps: Vec<PathBuf> = Vec::new();
    let mut placed: Vec<&Path> = Vec::new();
    let outcome = (|| -> Result<()> {
        for (p, text) in &files {
            let (tmp, mut f) = crate::files::fresh_temp_beside(p)
                .with_context(|| format!("cannot write {}", p.display()))?;
            temps.push(tmp);
            std::io::Write::write_all(&mut f, text.as_bytes())
                .and_then(|_| f.sync_all())
                .with_context(|| format!("cannot write {}", p.display()))?;
        }
        for ((p, _), tmp) in files.iter().zip(&temps) {
            let _placing = crate::files::landing();
            place_new(tmp, p).with_context(|| format!("cannot write {}", p.display()))?;
            crate::files::undo_on_interrupt(p, false);
            placed.push(p);
        }
        Ok(())
    })();
    for tmp in &temps {
        let _ = std::fs::remove_file(tmp);
    }
    if let Err(e) = outcome {
        for p in placed {
            let _ = std::fs::remove_file(p);
        }
        // Only folders this run made, and only if empty: never anything of
        // the user's.
        if made_scripts {
            let _ = std::fs::remove_dir(&scripts);
        }
        for d in &made {
            let _ = std::fs::remove_dir(d);
        }
        return Err(e);
    }
    {
        // Done: an interrupt now lets the command finish (review: it said
        // nothing was written).
        let _done = crate::files::landing();
        crate::files::keep_undo_list();
        crate::files::output_landed(&dir.join("world.toml"));
    }
    Ok(files.into_iter().map(|(p, _)| p).collect())
}

/// Put the finished file `tmp` at `dest`, which must not exist: a hard link
/// never replaces a file or follows a link that appeared meanwhile. Where
/// the file system has no hard links, a rename after a last check.
fn place_new(tmp: &Path, dest: &Path) -> std::io::Result<()> {
    match std::fs::hard_link(tmp, dest) {
        Ok(()) => Ok(()),
        Err(e) if e.kind() == std::io::ErrorKind::AlreadyExists => Err(e),
        Err(_) if std::fs::symlink_metadata(dest).is_err() => std::fs::rename(tmp, dest),
        Err(e) => Err(e),
    }
}
