//! Hot reload: a script saved the way editors save it (write a temp file,
//! rename it over the original) is picked up within the debounce, swapped in
//! at a step boundary with its parameters kept; a broken save keeps the old
//! version running and reports the file and line.

#[path = "common/scratch.rs"]
mod scratch;
use scratch::Scratch;

use std::path::Path;
use std::time::{Duration, Instant};

use brickworld::sim::tile::TILE_CELLS;
use brickworld::sim::{Kernel, Limits, ScriptWatcher, SimError, Simulation, read_script};
use glam::IVec2;

const V1: &str = r#"
return {
  channels = { "heat" },
  params = { rate = { default = 1, min = 0, max = 10 } },
  passes = { { name = "warm", reads = {}, writes = { "heat" }, kernel = function(c)
    buffer.writef64(c.w.heat, 0, buffer.readf64(c.w.heat, 0) + c.p.rate)
  end } },
}
"#;

fn save_like_an_editor(path: &Path, text: &str) {
    let tmp = path.with_extension("lua.swp");
    std::fs::write(&tmp, text).unwrap();
    std::fs::rename(&tmp, path).unwrap();
}

fn heat(sim: &Simulation) -> f64 {
    let ch = sim.channels().find("heat").unwrap();
    sim.channels().get(IVec2::ZERO, ch).map_or(0.0, |d| d[0])
}

fn wait_for_change(w: &mut ScriptWatcher) -> Vec<std::path::PathBuf> {
    let t = Instant::now();
    loop {
        let r = w.poll();
        if !r.is_empty() || t.elapsed() > Duration::from_secs(10) {
            return r;
        }
        std::thread::sleep(Duration::from_millis(20));
    }
}

#[test]
fn edited_scripts_reload_and_broken_saves_keep_the_last_good_version() {
    let scratch = Scratch::dir("reload");
    let dir = scratch.to_path_buf();
    let path = dir.join("heater.lua");
    std::fs::write(&path, V1).unwrap();
    let mut sim = Simulation::new(IVec2::ZERO, IVec2::ONE);
    sim.add_script(read_script(&path).unwrap(), Kernel::Lua, Limits::default())
        .unwrap();
    sim.set_param(0, "rate", 2.0).unwrap();
    let mut watcher = ScriptWatcher::new(&dir, Duration::from_millis(150)).unwrap();
    sim.step(1.0);
    assert_eq!(heat(&sim), 2.0);

    // A real edit: the kernel now adds 10 × rate. The parameter value (2) survives.
    let t0 = Instant::now();
    save_like_an_editor(&path, &V1.replace("+ c.p.rate", "+ 10 * c.p.rate"));
    let changed = wait_for_change(&mut watcher);
    assert_eq!(changed, vec![path.clone()]);
    assert!(
        t0.elapsed() < Duration::from_secs(1),
        "reloaded within a second: {:?}",
        t0.elapsed()
    );
    sim.replace_script(0, read_script(&path).unwrap()).unwrap();
    sim.step(1.0);
    assert_eq!(heat(&sim), 22.0);

    // A broken save: rejected with file and line; the last good version runs on.
    save_like_an_editor(&path, &V1.replace("end } },", "end } ,,"));
    assert_eq!(wait_for_change(&mut watcher), vec![path.clone()]);
    let e = sim
        .replace_script(0, read_script(&path).unwrap())
        .unwrap_err();
    assert!(matches!(e, SimError::Syntax { line: Some(_), .. }), "{e:?}");
    assert!(e.to_string().starts_with("heater.lua:"), "{e}");
    sim.step(1.0);
    assert_eq!(heat(&sim), 42.0, "the last good version keeps running");
    let _ = std::fs::remove_dir_all(&dir);
    let _ = TILE_CELLS;
}

/// Regression (hostile probe): after the scripts directory was replaced,
/// hot reload stopped without a word; after it was moved away, edits to the
/// old one were read from the new one.
#[test]
fn a_replaced_scripts_directory_is_watched_anew() {
    let scratch = Scratch::dir("rewatch");
    let root = scratch.to_path_buf();
    let dir = root.join("scripts");
    std::fs::create_dir_all(&dir).unwrap();
    std::fs::write(dir.join("heat.lua"), V1).unwrap();
    let mut w = ScriptWatcher::new(&dir, Duration::from_millis(50)).unwrap();
    // Moved away, and a new directory put in its place.
    std::fs::rename(&dir, root.join("scripts.gone")).unwrap();
    std::fs::create_dir_all(&dir).unwrap();
    std::fs::write(dir.join("other.lua"), V1).unwrap();
    let t = Instant::now();
    let (mut seen, mut notes) = (Vec::new(), Vec::new());
    while t.elapsed() < Duration::from_secs(10)
        && !seen
            .iter()
            .any(|p: &std::path::PathBuf| p.ends_with("other.lua"))
    {
        seen.extend(w.poll());
        notes.extend(w.take_notes());
        std::thread::sleep(Duration::from_millis(50));
    }
    assert!(
        seen.iter().any(|p| p.ends_with("other.lua")),
        "{seen:?} {notes:?}"
    );
    assert!(
        notes.iter().any(|n| n.contains("was replaced")),
        "{notes:?}"
    );
    // The old directory's edits are no longer reported.
    seen.clear();
    save_like_an_editor(&root.join("scripts.gone").join("heat.lua"), V1);
    std::thread::sleep(Duration::from_millis(300));
    seen.extend(w.poll());
    assert!(seen.is_empty(), "{seen:?}");
    // And the new one's are.
    save_like_an_editor(&dir.join("other.lua"), V1);
    assert!(
        wait_for_change(&mut w)
            .iter()
            .any(|p| p.ends_with("other.lua"))
    );
}

/// Regression (review): a scripts directory removed and made again at once
/// (`rm -rf scripts && cp -r backup scripts`) often gets its inode back on
/// ext4, so the (device, inode) check saw no change, the dead watch was kept,
/// and later edits were never reloaded. The watch now notices that its
/// directory itself went away.
#[test]
fn a_scripts_directory_removed_and_made_again_is_watched_anew() {
    // A relative path, as a world config's scripts dir usually is (notify
    // reports the directory's own events under its absolute path; the
    // first version of this fix compared them with the relative one).
    let root = std::path::PathBuf::from(format!("target/bw-remade-{}", std::process::id()));
    let _ = std::fs::remove_dir_all(&root);
    let dir = root.join("scripts");
    std::fs::create_dir_all(&dir).unwrap();
    std::fs::write(dir.join("heat.lua"), V1).unwrap();
    let mut w = ScriptWatcher::new(&dir, Duration::from_millis(50)).unwrap();
    std::fs::remove_dir_all(&dir).unwrap();
    std::fs::create_dir(&dir).unwrap();
    std::fs::write(dir.join("heat.lua"), V1).unwrap();
    // Past the identity recheck: the watcher has had its chance to re-watch.
    let t = Instant::now();
    let mut notes = Vec::new();
    while t.elapsed() < brickworld::sim::reload::RECHECK * 3 {
        w.poll();
        notes.extend(w.take_notes());
        std::thread::sleep(Duration::from_millis(50));
    }
    assert!(
        notes.iter().any(|n| n.contains("was replaced")),
        "{notes:?}"
    );
    // An edit in the new directory is reported.
    save_like_an_editor(
        &dir.join("heat.lua"),
        &V1.replace("+ c.p.rate", "+ 3 * c.p.rate"),
    );
    assert!(
        wait_for_change(&mut w)
            .iter()
            .any(|p| p.ends_with("heat.lua")),
        "{notes:?}"
    );
    let _ = std::fs::remove_dir_all(&root);
}

/// Regression (modder probe): `sim --watch` ignored `materials.lua`, so a
/// script whose reload was refused for an undeclared material stayed
/// refused after the material was declared. Now the file is applied and
/// the refused script is reloaded, as the daemon does.
#[test]
fn sim_watch_applies_materials_lua_and_retries_a_refused_script() {
    let scratch = Scratch::dir("simwatch");
    let dir = scratch.to_path_buf();
    let mat = |names: &[&str]| {
        let body: String = names
            .iter()
            .map(|n| {
                format!("  {n} = {{ color = {{ 1, 2, 3 }}, kind = \"solid\", density = 1 }},\n")
            })
            .collect();
        format!("return {{\n{body}}}\n")
    };
    let grow = |names: &str| {
        format!(
            "return {{ grid = \"voxels\", materials = {{ {names} }}, passes = {{ {{ name = \"p\", reads = {{}}, writes = {{ \"mat\" }},\n\
             kernel = function(c, bx, by, bz) end }} }} }}\n"
        )
    };
    std::fs::write(dir.join("materials.lua"), mat(&["moss"])).unwrap();
    std::fs::write(dir.join("grow.lua"), grow("\"moss\"")).unwrap();
    let (mut child, rx) = sim_watch(&dir, "grow.lua", &[]);
    let mut seen = Vec::new();
    let mut wait_for = |needle: &str| {
        let t = Instant::now();
        while t.elapsed() < Duration::from_secs(30) {
            match rx.recv_timeout(Duration::from_millis(100)) {
                Ok(l) => {
                    seen.push(l);
                    if seen.last().unwrap().contains(needle) {
                        return true;
                    }
                }
                Err(std::sync::mpsc::RecvTimeoutError::Disconnected) => return false,
                Err(_) => {}
            }
        }
        false
    };
    // Let it start and its watcher settle.
    std::thread::sleep(Duration::from_millis(1500));
    save_like_an_editor(&dir.join("grow.lua"), &grow("\"moss\", \"lichen\""));
    let refused = wait_for("unknown material 'lichen'");
    save_like_an_editor(&dir.join("materials.lua"), &mat(&["moss", "lichen"]));
    let applied = wait_for("materials.lua (2 materials)");
    let reloaded = wait_for("reloaded");
    let _ = child.kill();
    let _ = child.wait();
    assert!(refused && applied && reloaded, "{seen:#?}");
    assert!(seen.last().unwrap().contains("grow.lua"), "{seen:#?}");
}

/// Claim (README, `sim`): a run in which a script failed exits 1 without
/// an image, *unless `--watch` reloaded every failed script since*
/// (claims audit: only the failing side was tested). A script that fails
/// from tick 2 is fixed by an editor's save while a slow script keeps the
/// run going: the run ends with status 0 and writes its image.
#[test]
fn sim_watch_that_reloaded_a_failed_script_exits_0_with_its_image() {
    use std::io::BufRead;
    let dir = scratch("simwatchfix");
    let busy = "return { channels = { \"b\" }, passes = { { name = \"p\", reads = {}, writes = { \"b\" },\n\
         kernel = function(c) for i = 1, 300000 do end buffer.writef64(c.w.b, 0, c.tick) end } } }\n";
    let flaky = |fails: bool| {
        format!(
            "return {{ channels = {{ \"s\" }}, passes = {{ {{ name = \"p\", reads = {{}}, writes = {{ \"s\" }},\n\
             kernel = function(c) if {fails} and c.tick >= 2 then error(\"boom\") end buffer.writef64(c.w.s, 0, c.tick) end }} }} }}\n"
        )
    };
    std::fs::write(dir.join("busy.lua"), busy).unwrap();
    std::fs::write(dir.join("flaky.lua"), flaky(true)).unwrap();
    let png = dir.join("out.png");
    let mut child = std::process::Command::new(env!("CARGO_BIN_EXE_brickworld"))
        .args([
            "sim", "--size", "64x16x64", "--steps", "150", "--watch", "--out",
        ])
        .arg(&png)
        .arg("--script")
        .arg(dir.join("busy.lua"))
        .arg("--script")
        .arg(dir.join("flaky.lua"))
        .stderr(std::process::Stdio::piped())
        .stdout(std::process::Stdio::null())
        .spawn()
        .unwrap();
    let mut lines = std::io::BufReader::new(child.stderr.take().unwrap()).lines();
    let mut seen = Vec::new();
    for l in lines.by_ref().map_while(Result::ok) {
        let failed = l.contains("boom");
        seen.push(l);
        if failed {
            break;
        }
    }
    save_like_an_editor(&dir.join("flaky.lua"), &flaky(false));
    seen.extend(lines.map_while(Result::ok));
    let status = child.wait().unwrap();
    assert!(
        seen.iter().any(|l| l.contains("boom")),
        "it never failed: {seen:#?}"
    );
    assert!(
        seen.iter()
            .any(|l| l.contains("reloaded") && l.contains("flaky.lua")),
        "the run ended before the reload (a faster machine needs more steps): {seen:#?}"
    );
    assert!(status.success(), "{status:?}: {seen:#?}");
    assert!(png.is_file(), "{seen:#?}");
}

/// Regression (modder probe): `sim --watch` clamped a parameter into a
/// range a save narrowed without a word, where the engine warns.
#[test]
fn sim_watch_says_when_a_narrowed_range_clamps_a_parameter() {
    let dir = scratch("simwatchclamp");
    let script = |max: u32| {
        format!(
            "return {{ channels = {{ \"s\" }}, params = {{ v = {{ default = 1, min = 0, max = {max} }} }}, passes = {{ {{ name = \"p\", reads = {{}}, writes = {{ \"s\" }},\n\
             kernel = function(c) for i = 1, 20000 do end buffer.writef64(c.w.s, 0, c.p.v + c.tick) end }} }} }}\n"
        )
    };
    std::fs::write(dir.join("vv.lua"), script(10)).unwrap();
    let (mut child, rx) = sim_watch(&dir, "vv.lua", &["--param", "vv.v=8"]);
    std::thread::sleep(Duration::from_millis(1500));
    save_like_an_editor(&dir.join("vv.lua"), &script(5));
    let mut seen = Vec::new();
    let t = Instant::now();
    while t.elapsed() < Duration::from_secs(30)
        && !seen.iter().any(|l: &String| l.contains("clamped"))
    {
        if let Ok(l) = rx.recv_timeout(Duration::from_millis(100)) {
            seen.push(l);
        }
    }
    let _ = child.kill();
    let _ = child.wait();
    let line = seen
        .iter()
        .find(|l| l.contains("clamped"))
        .unwrap_or_else(|| panic!("{seen:#?}"));
    assert!(
        line.starts_with("warning:") && line.contains("'v'") && line.contains("5"),
        "{line}"
    );
}

/// `sim --watch` on `DIR/SCRIPT` (16³ voxels, steps enough to outlast a
/// test, `extra` flags), with its standard error as a channel of lines.
fn sim_watch(
    dir: &std::path::Path,
    script: &str,
    extra: &[&str],
) -> (std::process::Child, std::sync::mpsc::Receiver<String>) {
    use std::io::BufRead;
    let mut child = std::process::Command::new(env!("CARGO_BIN_EXE_brickworld"))
        .args([
            "sim", "--size", "16x16x16", "--steps", "10000000", "--watch",
        ])
        .args(extra)
        .arg("--out")
        .arg(dir.join("out.png"))
        .arg("--script")
        .arg(dir.join(script))
        .stderr(std::process::Stdio::piped())
        .stdout(std::process::Stdio::null())
        .spawn()
        .unwrap();
    let (tx, rx) = std::sync::mpsc::channel();
    let stderr = child.stderr.take().unwrap();
    std::thread::spawn(move || {
        for l in std::io::BufReader::new(stderr)
            .lines()
            .map_while(Result::ok)
        {
            let _ = tx.send(l);
        }
    });
    (child, rx)
}

/// A scratch folder of this test's own.
fn scratch(name: &str) -> Scratch {
    Scratch::dir(name)
}

/// Regression (hot-edit probe): a script that is a link was not reloaded
/// when the file it points to was edited (the folder's watch sees the
/// link, not its target); a restart loaded the edit. It is reported
/// within the watcher's recheck.
#[cfg(unix)]
#[test]
fn a_linked_script_is_reported_when_its_target_is_edited() {
    let dir = scratch("reload-link");
    let outside = scratch("reload-link-target");
    let target = outside.join("heater.lua");
    std::fs::write(&target, V1).unwrap();
    let link = dir.join("heater.lua");
    std::os::unix::fs::symlink(&target, &link).unwrap();
    let mut watcher = ScriptWatcher::new(&dir, Duration::from_millis(150)).unwrap();
    assert!(watcher.poll().is_empty());
    std::thread::sleep(Duration::from_millis(50));
    std::fs::write(&target, V1.replace("+ c.p.rate", "+ 10 * c.p.rate")).unwrap();
    assert_eq!(wait_for_change(&mut watcher), vec![link.clone()]);
    // Nothing more once it was reported.
    std::thread::sleep(Duration::from_millis(2500));
    assert!(watcher.poll().is_empty());
    // A link pointed elsewhere is reported once, not by its event and
    // again by the next look at its target (review).
    let other = outside.join("other.lua");
    std::fs::write(&other, V1).unwrap();
    let tmp = dir.join("heater.lua.new");
    std::os::unix::fs::symlink(&other, &tmp).unwrap();
    std::fs::rename(&tmp, &link).unwrap();
    assert_eq!(wait_for_change(&mut watcher), vec![link.clone()]);
    std::thread::sleep(Duration::from_millis(2500));
    assert!(watcher.poll().is_empty(), "reported twice");
}

/// Regression (hot-edit probe): a script edited while its folder could
/// not be read failed to reload ("Permission denied"), and was never
/// tried again once the folder could be read: a change to the folder's
/// own permissions names no script. It now reports every script.
#[cfg(unix)]
#[test]
fn scripts_are_reported_again_when_their_folders_permissions_change() {
    use std::os::unix::fs::PermissionsExt;
    let dir = scratch("reload-chmod");
    std::fs::write(dir.join("a.lua"), V1).unwrap();
    std::fs::write(dir.join("b.lua"), V1).unwrap();
    let mut watcher = ScriptWatcher::new(&dir, Duration::from_millis(150)).unwrap();
    std::fs::set_permissions(&dir, std::fs::Permissions::from_mode(0o700)).unwrap();
    let mut got = wait_for_change(&mut watcher);
    got.sort();
    assert_eq!(got, vec![dir.join("a.lua"), dir.join("b.lua")]);
    // A change of the folder's times alone (`touch`) asks for nothing
    // (review: it reloaded every script).
    let when = std::time::SystemTime::now() - Duration::from_secs(3600);
    std::fs::File::open(&dir)
        .unwrap()
        .set_times(
            std::fs::FileTimes::new()
                .set_modified(when)
                .set_accessed(when),
        )
        .unwrap();
    std::thread::sleep(Duration::from_millis(1500));
    assert!(watcher.poll().is_empty());
}
