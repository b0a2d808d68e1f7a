//! Material ids over a world's life: names that no file declares any more
//! keep their ids while the engine runs, and a restart frees those that no
//! stored voxel holds, so renaming materials cannot fill the registry for
//! good.

use std::path::Path;

mod common;
use common::daemon::*;

/// `materials.lua`: the shipped materials and `extra` more, named
/// `{prefix}0`, `{prefix}1`…
fn materials_with(scripts: &Path, prefix: &str, extra: usize) {
    let mut text = shipped_script("materials.lua");
    let more: String = (0..extra)
        .map(|i| {
            format!("  {prefix}{i} = {{ color = {{ 1, 2, 3 }}, kind = \"solid\", density = 1 }},\n")
        })
        .collect();
    text = text.replacen("return {\n", &format!("return {{\n{more}"), 1);
    std::fs::write(scripts.join("materials.lua"), text).unwrap();
}

/// A lava world (see `lava_world`) whose `materials.lua` also declares
/// `old0` to `old{n-1}`, run for two ticks; its config, state, scripts
/// folder and stored registry.
fn world_with_old_names(
    name: &str,
    n: usize,
) -> (
    common::scratch::Scratch,
    std::path::PathBuf,
    std::path::PathBuf,
    std::path::PathBuf,
    Vec<(u8, String)>,
) {
    let (scratch, cfg, state, _, scripts) = lava_world(name);
    materials_with(&scripts, "old", n);
    run_ok(&cfg, &state, "--ticks", 2);
    let (stored, _) = stored_materials(&cfg, &state);
    (scratch, cfg, state, scripts, stored)
}

/// The id of `name` in a registry listing.
fn id(m: &[(u8, String)], name: &str) -> Option<u8> {
    m.iter().find(|e| e.1 == name).map(|e| e.0)
}

/// Regression: a name no longer declared kept its id for the world's life,
/// so a world whose materials were renamed often enough could take no new
/// name, ever, and a start with one new name failed for good.
#[test]
fn a_restart_frees_the_ids_of_names_nothing_declares_and_no_voxel_holds() {
    let (_scratch, cfg, state, _, scripts) = lava_world("reclaim");
    // 230 names beside the shipped ones; a box of one of them is stored.
    materials_with(&scripts, "old", 230);
    let mut text = std::fs::read_to_string(&cfg).unwrap();
    text.push_str("[[place]]\nmaterial = \"old7\"\nat = [4, 26, 4]\nsize = [3, 3, 3]\n");
    std::fs::write(&cfg, text).unwrap();
    run_ok(&cfg, &state, "--ticks", 2);
    let (before, _) = stored_materials(&cfg, &state);
    let old7 = id(&before, "old7").unwrap();
    let lava = id(&before, "lava").unwrap();
    assert!(before.len() > 230, "{before:?}");

    // The modder renames them all: 40 new names do not fit beside the 230
    // stored ones, but a restart frees all of them except the one voxels
    // hold.
    materials_with(&scripts, "new", 40);
    let (said, log) = run_ok(&cfg, &state, "--ticks", 2);
    assert!(
        log.contains(
            "materials: freed 229 ids of names that nothing declares and no stored voxel holds (old"
        ) && log.contains("1 such name still held by voxels keeps theirs"),
        "{said}\n{log}"
    );
    let (after, _) = stored_materials(&cfg, &state);
    assert_eq!(
        id(&after, "old7"),
        Some(old7),
        "held by voxels: kept, same id"
    );
    assert_eq!(id(&after, "lava"), Some(lava), "declared: kept, same id");
    assert_eq!(id(&after, "old8"), None);
    assert!((0..40).all(|i| id(&after, &format!("new{i}")).is_some()));

    // A further restart frees nothing more (it is not nearly full now, and
    // the file asks for no new id).
    let (said, log) = run_ok(&cfg, &state, "--ticks", 1);
    assert!(!log.contains("materials: freed"), "{log}");
    assert!(
        said.contains("resumed") || log.contains("resumed"),
        "{said}\n{log}"
    );
}

/// The other side: a name a script still lists is kept although no voxel
/// holds it and `materials.lua` no longer declares it, so the script that
/// uses it still loads.
#[test]
fn a_name_a_script_still_uses_is_not_freed() {
    let (_scratch, cfg, state, scripts, before) = world_with_old_names("reclaim-used", 230);
    // lava.lua lists basalt; materials.lua stops declaring it.
    let basalt = id(&before, "basalt").unwrap();
    let text = std::fs::read_to_string(scripts.join("materials.lua")).unwrap();
    let without: String = text
        .lines()
        .filter(|l| !l.trim_start().starts_with("basalt =") && !l.contains("old"))
        .map(|l| format!("{l}\n"))
        .collect();
    std::fs::write(scripts.join("materials.lua"), without).unwrap();
    let (_, log) = run_ok(&cfg, &state, "--ticks", 2);
    assert!(log.contains("materials: freed 230 ids"), "{log}");
    let (after, _) = stored_materials(&cfg, &state);
    assert_eq!(id(&after, "basalt"), Some(basalt), "lava.lua uses it");
}

/// Regression (review): the ids were freed only while fewer than 32 were
/// free, so with 34 free a rename to 40 new names failed at every start,
/// for good. A start also frees them when `materials.lua` asks for more
/// new ids than are free.
#[test]
fn a_rename_that_needs_more_ids_than_are_free_starts() {
    let (_scratch, cfg, state, scripts, before) = world_with_old_names("reclaim-needed", 200);
    let free = 251
        - before
            .iter()
            .filter(|(id, _)| (1..=251).contains(id))
            .count();
    assert!(
        (32..40).contains(&free),
        "{free} ids free: the case needs 32..40"
    );
    materials_with(&scripts, "new", 40);
    let (_, log) = run_ok(&cfg, &state, "--ticks", 2);
    assert!(log.contains("materials: freed 200 ids"), "{log}");
    let (after, _) = stored_materials(&cfg, &state);
    assert!(after.iter().any(|(_, n)| n == "new39"), "{after:?}");
}
