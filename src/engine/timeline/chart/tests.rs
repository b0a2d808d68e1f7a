//! Tests of `brickworld chart`: a timeline's tail, charts kept where a
//! file is in their place, thinned long series, hand-made timelines.

use super::*;

/// The tail holds the last rows whole, with the header's columns, from
/// a file much longer than what is read; a cut-off last line and a
/// malformed one are left out.
#[test]
fn the_tail_of_a_timeline_is_its_last_whole_rows() {
    let dir = std::env::temp_dir().join(format!("bw-tail-{}", std::process::id()));
    let _ = std::fs::remove_dir_all(&dir);
    std::fs::create_dir_all(&dir).unwrap();
    let csv = dir.join("timeline.csv");
    let mut text = String::from("tick,water\n");
    for i in 0..20_000 {
        text += &format!("{i},{}.5\n", i * 2);
    }
    text += "oops\n20000,4";
    std::fs::write(&csv, &text).unwrap();
    let t = read_tail(&csv, 100).unwrap();
    assert_eq!(t.columns, ["tick", "water"]);
    assert_eq!(t.rows.len(), 100);
    assert_eq!(t.rows[0], [19_900.0, 39_800.5]);
    assert_eq!(t.rows[99], [19_999.0, 39_998.5]);
    std::fs::write(&csv, "tick,water\n1,2\n").unwrap();
    assert_eq!(read_tail(&csv, 100).unwrap().rows, [[1.0, 2.0]]);
    std::fs::write(&csv, "").unwrap();
    assert!(read_tail(&csv, 100).unwrap().rows.is_empty());
    std::fs::remove_dir_all(&dir).unwrap();
}

/// Regression (hostile probe 2): a file at `STATE/charts` gave "cannot
/// create …: File exists"; it is named as not a folder, and kept.
/// Regression (hostile probe 3): a FIFO at a chart's name hung `chart`,
/// and a link there made it overwrite the file linked to.
#[test]
fn a_file_where_the_charts_go_is_named_and_kept() {
    let dir = std::env::temp_dir().join(format!("bw-chart-file-{}", std::process::id()));
    let _ = std::fs::remove_dir_all(&dir);
    std::fs::create_dir_all(&dir).unwrap();
    std::fs::write(dir.join("timeline.csv"), "tick,water\n1,1\n2,2\n").unwrap();
    std::fs::write(dir.join("charts"), "mine").unwrap();
    let e = chart(&dir).unwrap_err().to_string();
    assert!(
        e.ends_with("charts is not a folder: chart writes its SVGs there, so move it away"),
        "{e}"
    );
    assert_eq!(std::fs::read_to_string(dir.join("charts")).unwrap(), "mine");
    // Nor is anything but a file written into inside it.
    std::fs::remove_file(dir.join("charts")).unwrap();
    std::fs::create_dir(dir.join("charts")).unwrap();
    let victim = dir.join("victim");
    std::fs::write(&victim, "mine").unwrap();
    #[cfg(unix)]
    {
        std::os::unix::fs::symlink(&victim, dir.join("charts/total-water.svg")).unwrap();
        let e = chart(&dir).unwrap_err().to_string();
        assert!(e.contains("total-water.svg is not a regular file"), "{e}");
        assert_eq!(std::fs::read_to_string(&victim).unwrap(), "mine");
        std::fs::remove_file(dir.join("charts/total-water.svg")).unwrap();
        crate::files::mkfifo(&dir.join("charts/total-water.svg"));
        let e = chart(&dir).unwrap_err().to_string();
        assert!(e.contains("total-water.svg is not a regular file"), "{e}");
        // A link to a folder elsewhere is no charts folder (review).
        std::fs::remove_dir_all(dir.join("charts")).unwrap();
        let elsewhere = dir.join("elsewhere");
        std::fs::create_dir(&elsewhere).unwrap();
        std::os::unix::fs::symlink(&elsewhere, dir.join("charts")).unwrap();
        let e = chart(&dir).unwrap_err().to_string();
        assert!(e.contains("charts is not a folder"), "{e}");
        assert_eq!(std::fs::read_dir(&elsewhere).unwrap().count(), 0);
    }
    std::fs::remove_dir_all(&dir).unwrap();
}

/// Regression (long-run probe): a long timeline is drawn with at most
/// MAX_CHART_POINTS points a line, keeping each run's extremes: a
/// lone spike survives, the order stays, and short lines are whole.
#[test]
fn long_timelines_are_thinned_keeping_their_extremes() {
    let short: Vec<(f64, f64)> = (0..10).map(|i| (i as f64, 1.0)).collect();
    assert_eq!(thin(short.clone()), short);
    let mut long: Vec<(f64, f64)> = (0..300_000).map(|i| (i as f64, (i % 7) as f64)).collect();
    long[123_457].1 = 1e6;
    long[200_001].1 = -5.0;
    let t = thin(long);
    assert!(t.len() <= MAX_CHART_POINTS, "{}", t.len());
    assert!(t.contains(&(123_457.0, 1e6)) && t.contains(&(200_001.0, -5.0)));
    assert!(t.windows(2).all(|w| w[0].0 < w[1].0), "out of order");
    // And the SVG of a long run stays small.
    let dir = std::env::temp_dir().join(format!("bw-chart-long-{}", std::process::id()));
    let _ = std::fs::remove_dir_all(&dir);
    std::fs::create_dir_all(&dir).unwrap();
    let mut text = String::from("tick,water,rss_kb\n");
    for i in 1..=100_000 {
        text += &format!("{i},{},{}\n", 1000 + i % 13, 30_000 + i % 5);
    }
    std::fs::write(dir.join("timeline.csv"), text).unwrap();
    for svg in chart(&dir).unwrap() {
        let bytes = std::fs::metadata(&svg).unwrap().len();
        assert!(bytes < 1 << 20, "{}: {bytes} bytes", svg.display());
    }
    std::fs::remove_dir_all(&dir).unwrap();
}

/// Regression (hostile probe): a hand-made timeline lacking a column
/// panicked, a huge value hung the axis, and a link to /dev/zero filled
/// memory.
#[test]
fn chart_survives_hand_made_timelines() {
    let dir = std::env::temp_dir().join(format!("bw-chart-{}", std::process::id()));
    let _ = std::fs::remove_dir_all(&dir);
    std::fs::create_dir_all(&dir).unwrap();
    let csv = dir.join("timeline.csv");
    std::fs::write(&csv, "tick,water,rss_kb\n1,1,100\n2,1.7e308,200\n3,2,300\n").unwrap();
    let drawn = chart(&dir).unwrap();
    let names: Vec<String> = drawn
        .iter()
        .map(|p| p.file_name().unwrap().to_string_lossy().to_string())
        .collect();
    assert_eq!(names, ["memory.svg", "total-water.svg"]);
    // Each script's time per step goes to scripts.svg (audit: the
    // README names it; no test drew it).
    std::fs::write(
        &csv,
        "tick,water,ms:water,ms:snow\n1,1,0.5,0.2\n2,1,0.7,0.3\n",
    )
    .unwrap();
    let drawn = chart(&dir).unwrap();
    let svg = drawn
        .iter()
        .find(|p| p.ends_with("scripts.svg"))
        .expect("scripts.svg");
    let text = std::fs::read_to_string(svg).unwrap();
    assert!(text.contains("water") && text.contains("snow"), "{text}");
    // A total with no finite value is skipped, not the end of every
    // chart, and the chart of a total the timeline no longer has is
    // removed (review).
    std::fs::write(&csv, "tick,water,snow\n1,nan,1\n2,nan,2\n").unwrap();
    let drawn = chart(&dir).unwrap();
    let names: Vec<String> = std::fs::read_dir(dir.join("charts"))
        .unwrap()
        .map(|e| e.unwrap().file_name().to_string_lossy().to_string())
        .filter(|n| n.starts_with("total"))
        .collect();
    assert_eq!(names, ["total-snow.svg"], "{drawn:?}");
    // No value is no point (review: the NaN frame time of a start's
    // first row was drawn at 1e-9, stretching the axis nine decades).
    std::fs::write(
        &csv,
        "tick,steps_per_s,frame_ms\n1,10,NaN\n2,11,5.5\n3,12,6\n",
    )
    .unwrap();
    chart(&dir).unwrap();
    // The numbers a chart's axes are labelled with.
    let labels = |file: &str| -> Vec<f64> {
        let svg = std::fs::read_to_string(dir.join("charts").join(file)).unwrap();
        svg.split("</text>")
            .filter_map(|t| t.rsplit('>').next()?.trim().parse().ok())
            .collect()
    };
    let labels_rate = labels("rate.svg");
    assert!(
        labels_rate.len() >= 3 && labels_rate.iter().all(|&v| v >= 1.0),
        "{labels_rate:?}"
    );
    // A zero sits a decade below the least value, not at 1e-9 (review).
    std::fs::write(
        &csv,
        "tick,active_bricks,dirty_bricks\n1,100,0\n2,120,5\n3,90,0\n",
    )
    .unwrap();
    chart(&dir).unwrap();
    let labels_work = labels("work.svg");
    assert!(labels_work.iter().all(|&v| v >= 0.1), "{labels_work:?}");
    std::fs::write(&csv, "a,b\n1,2\n3,4\n").unwrap();
    assert!(
        chart(&dir)
            .unwrap_err()
            .to_string()
            .contains("not a brickworld timeline")
    );
    // Regression (hostile probe): a file of nothing but malformed rows
    // was said to need a longer run.
    std::fs::write(&csv, "tick,water\n\"1\",\"2\",x\n3\n").unwrap();
    let e = chart(&dir).unwrap_err().to_string();
    assert!(e.contains("not a timeline the engine wrote"), "{e}");
    // One row and a last line cut off by a kill: the engine's, short.
    std::fs::write(&csv, "tick,water\n1,2\n2,").unwrap();
    let e = chart(&dir).unwrap_err().to_string();
    assert!(e.contains("fewer than two rows"), "{e}");
    std::fs::remove_file(&csv).unwrap();
    #[cfg(unix)]
    {
        std::os::unix::fs::symlink("/dev/zero", &csv).unwrap();
        let e = chart(&dir).unwrap_err().to_string();
        assert!(e.contains("not a regular file"), "{e}");
    }
    std::fs::remove_dir_all(&dir).unwrap();
}
