//! Tests of the timeline file: paths that are not regular files, a full
//! disk, a file removed or replaced while running, per-script headers,
//! and rotation.

use super::*;

fn row(tick: u64) -> Row {
    Row {
        tick,
        script_ms: vec![1.5],
        conserved: vec![42.0],
        ..Row::default()
    }
}

/// Regression (review): a FIFO at `STATE/timeline.csv` hung the engine
/// at start (deaf to SIGTERM); a link to /dev/zero filled memory.
#[cfg(unix)]
#[test]
fn a_timeline_that_is_not_a_regular_file_is_refused() {
    let dir = std::env::temp_dir().join(format!("bw-timeline-fifo-{}", std::process::id()));
    let _ = std::fs::remove_dir_all(&dir);
    std::fs::create_dir_all(&dir).unwrap();
    let fifo = dir.join("timeline.csv");
    crate::files::mkfifo(&fifo);
    let e = Timeline::open(&fifo, &[]).err().unwrap().to_string();
    assert!(e.contains("is not a regular file"), "{e}");
    let zero = dir.join("zero.csv");
    std::os::unix::fs::symlink("/dev/zero", &zero).unwrap();
    let e = Timeline::open(&zero, &[]).err().unwrap().to_string();
    assert!(e.contains("is not a regular file"), "{e}");
    let _ = std::fs::remove_dir_all(&dir);
}

/// Regression (operator probe): rows that could not be written (a full
/// disk) were lost without a word. The first lost row starts a count
/// (and is said), the next row written ends it (and says which ticks
/// are missing); the file holds exactly the rows written.
#[cfg(unix)]
#[test]
fn rows_lost_to_a_full_disk_are_counted_and_said() {
    let dir = std::env::temp_dir().join(format!("bw-timeline-full-{}", std::process::id()));
    let _ = std::fs::remove_dir_all(&dir);
    std::fs::create_dir_all(&dir).unwrap();
    let path = dir.join("timeline.csv");
    let mut t = Timeline::open(&path, &[]).unwrap();
    t.record(&row(1));
    // The file becomes /dev/full, and its path too (a path that no
    // longer names the file held is opened again).
    let good = std::mem::replace(&mut t.file, File::create("/dev/full").unwrap());
    let at = std::mem::replace(&mut t.at, "/dev/full".into());
    t.record(&row(2));
    t.record(&row(3));
    assert_eq!(t.failing, Some((2, 2)));
    (t.file, t.at) = (good, at);
    t.record(&row(4));
    assert_eq!(t.failing, None);
    let text = std::fs::read_to_string(&path).unwrap();
    let ticks: Vec<&str> = text
        .lines()
        .skip(1)
        .map(|l| l.split(',').next().unwrap())
        .collect();
    assert_eq!(ticks, ["1", "4"]);
    let _ = std::fs::remove_dir_all(&dir);
}

fn ticks_in(path: &Path) -> Vec<String> {
    let text = std::fs::read_to_string(path).unwrap();
    assert!(text.starts_with("tick,"), "a header first: {text}");
    text.lines()
        .skip(1)
        .map(|l| l.split(',').next().unwrap().to_string())
        .collect()
}

/// Regression (operator probe): a `timeline.csv` removed, or replaced
/// by a folder, while the engine ran took its rows into the file held
/// open, which nothing named, without a word. A removed file starts
/// again (with its header); a folder there is said, its rows go on
/// into the held file, and once the folder is gone a new file starts.
#[cfg(unix)]
#[test]
fn a_timeline_removed_or_replaced_while_running_starts_again() {
    let dir = std::env::temp_dir().join(format!("bw-timeline-gone-{}", std::process::id()));
    let _ = std::fs::remove_dir_all(&dir);
    std::fs::create_dir_all(&dir).unwrap();
    let path = dir.join("timeline.csv");
    let mut t = Timeline::open(&path, &["ms:x".to_string()]).unwrap();
    t.record(&row(1));
    std::fs::remove_file(&path).unwrap();
    t.record(&row(2));
    assert_eq!(ticks_in(&path), ["2"]);
    // Moved away: the moved file keeps its rows, a new one starts.
    std::fs::rename(&path, dir.join("old.csv")).unwrap();
    t.record(&row(3));
    assert_eq!(ticks_in(&dir.join("old.csv")), ["2"]);
    assert_eq!(ticks_in(&path), ["3"]);
    // A folder in its place: said once, and nothing is written into it.
    std::fs::remove_file(&path).unwrap();
    std::fs::create_dir(&path).unwrap();
    t.record(&row(4));
    t.record(&row(5));
    assert!(t.astray);
    assert_eq!(std::fs::read_dir(&path).unwrap().count(), 0);
    std::fs::remove_dir(&path).unwrap();
    t.record(&row(6));
    assert!(!t.astray);
    assert_eq!(ticks_in(&path), ["6"]);
    let _ = std::fs::remove_dir_all(&dir);
}

/// The timeline is written in the folder it was opened in, never in
/// another made at the same path since (the frames' rule: a stale
/// engine must not write into a new engine's state directory).
#[cfg(target_os = "linux")]
#[test]
fn a_timeline_never_writes_into_a_folder_made_at_its_path_since() {
    let base = std::env::temp_dir().join(format!("bw-timeline-swap-{}", std::process::id()));
    let _ = std::fs::remove_dir_all(&base);
    let dir = base.join("state");
    std::fs::create_dir_all(&dir).unwrap();
    let path = dir.join("timeline.csv");
    let mut t = Timeline::open(&path, &[]).unwrap();
    t.record(&row(1));
    std::fs::rename(&dir, base.join("moved")).unwrap();
    std::fs::create_dir(&dir).unwrap();
    t.record(&row(2));
    // A reload that changes the columns opens it again: in the old folder.
    let mut t = t.reopen(&["ms:y".to_string()]).unwrap();
    t.record(&row(3));
    assert_eq!(std::fs::read_dir(&dir).unwrap().count(), 0);
    let moved = base.join("moved").join("timeline.csv");
    assert_eq!(ticks_in(&moved), ["3"]);
    let _ = std::fs::remove_dir_all(&base);
}

#[test]
fn per_script_columns_round_trip_and_another_header_is_moved_aside() {
    let dir = std::env::temp_dir().join(format!("bw-timeline-{}", std::process::id()));
    let _ = std::fs::remove_dir_all(&dir);
    std::fs::create_dir_all(&dir).unwrap();
    let path = dir.join("timeline.csv");
    let extra = vec!["ms:water3d".to_string(), "total:water3d.water".to_string()];
    {
        let mut t = Timeline::open(&path, &extra).unwrap();
        t.record(&row(1));
        t.record(&row(2));
    }
    let table = read(&path).unwrap();
    assert_eq!(table.rows.len(), 2);
    let c = table.col("total:water3d.water").unwrap();
    assert_eq!(table.rows[1][c], 42.0);
    assert_eq!(table.rows[0][table.col("ms:water3d").unwrap()], 1.5);
    // Same header: appended to. Another header: the old file is kept aside.
    Timeline::open(&path, &extra).unwrap().record(&row(3));
    assert_eq!(read(&path).unwrap().rows.len(), 3);
    Timeline::open(&path, &["ms:sand".to_string()]).unwrap();
    let aside: Vec<_> = std::fs::read_dir(&dir)
        .unwrap()
        .filter_map(|e| e.ok())
        .filter(|e| e.file_name() != "timeline.csv")
        .collect();
    assert_eq!(aside.len(), 1, "the old timeline is kept");
    assert_eq!(read(&aside[0].path()).unwrap().rows.len(), 3);
    assert_eq!(read(&path).unwrap().rows.len(), 0);
    // Moved aside again within the same second: a second name.
    Timeline::open(&path, &extra).unwrap();
    let n = std::fs::read_dir(&dir).unwrap().count();
    assert_eq!(n, 3, "two files aside and the current one");
    let _ = std::fs::remove_dir_all(&dir);
}

/// Regression (code review): a rotation whose new file could not be
/// made (a full disk) left rows going into the file moved aside, with
/// the rotation count at 0, and the next row the disk refused cut that
/// file to the count: the history emptied. It is taken back to its own
/// length.
#[test]
fn a_failed_rotation_then_a_full_disk_keeps_the_history() {
    let dir = std::env::temp_dir().join(format!("bw-timeline-rotfail-{}", std::process::id()));
    let _ = std::fs::remove_dir_all(&dir);
    std::fs::create_dir_all(&dir).unwrap();
    let path = dir.join("timeline.csv");
    let mut t = Timeline::open(&path, &[]).unwrap();
    for tick in 1..=5 {
        t.record(&row(tick));
    }
    t.written = ROTATE_BYTES - 10;
    FULL_DISK.set(true);
    t.record(&row(6));
    t.record(&row(7));
    assert_eq!(t.failing, Some((6, 2)));
    let moved = dir.join("timeline.1.csv");
    assert_eq!(ticks_in(&moved), ["1", "2", "3", "4", "5"]);
    // Space again: the new file gets its header, and the rows go on.
    FULL_DISK.set(false);
    t.record(&row(8));
    assert_eq!(ticks_in(&path), ["8"]);
    assert_eq!(ticks_in(&moved), ["1", "2", "3", "4", "5"]);
    // An empty timeline left by a full disk, or one with a blank or
    // cut header and no row, is opened as a new one, not moved aside as
    // another world's (review).
    for left in ["", "\n", "tick,steps_p"] {
        std::fs::write(&path, left).unwrap();
        let mut t = Timeline::open(&path, &[]).unwrap();
        t.record(&row(9));
        assert_eq!(ticks_in(&path), ["9"], "{left:?}");
    }
    let names: Vec<_> = std::fs::read_dir(&dir)
        .unwrap()
        .flatten()
        .map(|e| e.file_name())
        .collect();
    assert_eq!(names.len(), 2, "nothing moved aside: {names:?}");
    let _ = std::fs::remove_dir_all(&dir);
}

#[test]
fn a_full_timeline_rotates_instead_of_growing() {
    let dir = std::env::temp_dir().join(format!("bw-timeline-rot-{}", std::process::id()));
    let _ = std::fs::remove_dir_all(&dir);
    std::fs::create_dir_all(&dir).unwrap();
    let path = dir.join("timeline.csv");
    let mut t = Timeline::open(&path, &[]).unwrap();
    t.written = ROTATE_BYTES - 10;
    t.record(&Row::default());
    assert!(dir.join("timeline.1.csv").exists());
    let now = std::fs::metadata(&path).unwrap().len();
    assert!(now < 1024, "a fresh file: {now} bytes");
    assert_eq!(read(&path).unwrap().rows.len(), 1);
    let _ = std::fs::remove_dir_all(&dir);
}
