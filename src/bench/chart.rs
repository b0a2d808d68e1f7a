//! SVG charts of bench results (plotters).

use std::path::Path;

use plotters::prelude::*;

use super::tracers::{BenchReport, StructureReport};

fn color(name: &str) -> RGBColor {
    match name {
        "dense" => RGBColor(200, 70, 60),
        "svo" => RGBColor(60, 110, 200),
        _ => RGBColor(40, 150, 80),
    }
}

/// Memory (MiB, log scale) against speed (Mrays/s), one point per structure
/// and scene, labelled `scene/structure`.
pub fn memory_vs_speed(path: &Path, reports: &[&BenchReport]) -> Result<(), ChartError> {
    staged(path, |tmp| draw(tmp, reports))
}

/// Draw the chart in memory, then write it to a temporary file beside
/// `path` that replaces it only once the chart is whole: a chart that fails
/// (a full disk, a file-size limit) leaves the previous one as it was,
/// never a truncated one, and is an error. (Regression: plotters' SVG
/// backend writes a file through a buffer that it drops without a flush,
/// so a chart under 8 KiB that could not be written was lost silently,
/// exit 0.)
fn staged(
    path: &Path,
    draw: impl FnOnce(&mut String) -> Result<(), Box<dyn std::error::Error>>,
) -> Result<(), ChartError> {
    let mut svg = String::new();
    draw(&mut svg).map_err(|e| ChartError::new(path, e))?;
    let file = crate::files::Staged::new(path).map_err(|e| ChartError::new(path, e.into()))?;
    std::fs::write(file.path(), svg).map_err(|e| ChartError::new(path, e.into()))?;
    file.commit().map_err(|e| ChartError::new(path, e.into()))
}

/// A chart could not be drawn or written.
#[derive(Debug, thiserror::Error)]
#[error("cannot draw the chart {}: {msg}", path.display())]
pub struct ChartError {
    /// The chart's file (regression: a failed write did not say which).
    path: std::path::PathBuf,
    msg: String,
}

impl ChartError {
    fn new(path: &Path, e: Box<dyn std::error::Error>) -> Self {
        ChartError {
            path: path.to_path_buf(),
            msg: e.to_string(),
        }
    }

    /// The same error, naming `path` (the chart's destination, when it was
    /// drawn into a temporary file beside it).
    pub fn at(self, path: &Path) -> Self {
        ChartError {
            path: path.to_path_buf(),
            ..self
        }
    }
}

fn draw(svg: &mut String, reports: &[&BenchReport]) -> Result<(), Box<dyn std::error::Error>> {
    let mut pts: Vec<(String, &'static str, f64, f64)> = Vec::new();
    for r in reports {
        for s in &r.structures {
            if let StructureReport::Ok(f) = s {
                pts.push((
                    r.scene.clone(),
                    f.name,
                    (f.bytes as f64 / (1 << 20) as f64).max(1e-3),
                    f.mrays_per_s,
                ));
            }
        }
    }
    if pts.is_empty() {
        return Err("no structure was measured".into());
    }
    let xmin = pts.iter().map(|p| p.2).fold(f64::INFINITY, f64::min) / 2.0;
    let xmax = pts.iter().map(|p| p.2).fold(0.0, f64::max) * 2.0;
    let ymax = pts.iter().map(|p| p.3).fold(0.0, f64::max) * 1.2;
    let root = SVGBackend::with_string(svg, (800, 520)).into_drawing_area();
    root.fill(&WHITE)?;
    let title = if reports.len() == 1 {
        format!(
            "{} {}x{}x{}, {}x{}, {} thread(s)",
            reports[0].scene,
            reports[0].size[0],
            reports[0].size[1],
            reports[0].size[2],
            reports[0].width,
            reports[0].height,
            reports[0].threads
        )
    } else {
        "memory against speed".to_string()
    };
    let mut chart = ChartBuilder::on(&root)
        .caption(title, ("sans-serif", 20))
        .margin(16)
        .x_label_area_size(40)
        .y_label_area_size(56)
        .build_cartesian_2d((xmin..xmax).log_scale(), 0.0..ymax.max(0.1))?;
    chart
        .configure_mesh()
        .x_desc("structure size (MiB, log)")
        .y_desc("primary rays (Mrays/s)")
        .draw()?;
    for (scene, name, x, y) in &pts {
        let c = color(name);
        chart.draw_series(std::iter::once(Circle::new((*x, *y), 6, c.filled())))?;
        let label = if reports.len() == 1 {
            name.to_string()
        } else {
            format!("{scene}/{name}")
        };
        chart.draw_series(std::iter::once(Text::new(
            label,
            (*x, *y),
            ("sans-serif", 14).into_font(),
        )))?;
    }
    root.present()?;
    Ok(())
}

/// A named series of points for [`xy_chart`].
pub struct Series<'a> {
    /// Legend label.
    pub name: &'a str,
    /// Colour.
    pub color: RGBColor,
    /// Points (non-finite or non-positive values are skipped on log axes).
    pub points: Vec<(f64, f64)>,
}

/// A log–log chart of one or more series, with markers and lines.
pub fn xy_chart(
    path: &Path,
    title: &str,
    x_desc: &str,
    y_desc: &str,
    series: &[Series],
) -> Result<(), ChartError> {
    staged(path, |tmp| draw_xy(tmp, title, x_desc, y_desc, series))
}

/// [`xy_chart`]'s SVG text, for a caller that writes it itself (`path`
/// names it in errors).
pub fn xy_svg(
    path: &Path,
    title: &str,
    x_desc: &str,
    y_desc: &str,
    series: &[Series],
) -> Result<String, ChartError> {
    let mut svg = String::new();
    draw_xy(&mut svg, title, x_desc, y_desc, series).map_err(|e| ChartError::new(path, e))?;
    Ok(svg)
}

fn draw_xy(
    svg: &mut String,
    title: &str,
    x_desc: &str,
    y_desc: &str,
    series: &[Series],
) -> Result<(), Box<dyn std::error::Error>> {
    let pts = || {
        series
            .iter()
            .flat_map(|s| s.points.iter())
            // Within 1e±300, so the axes' margins stay finite (regression:
            // a value of 1.7e308 made an infinite axis and a hang).
            .filter(|p| (1e-300..1e300).contains(&p.0) && (1e-300..1e300).contains(&p.1))
    };
    if pts().next().is_none() {
        return Err("nothing to plot".into());
    }
    let (x0, x1) = pts().fold((f64::INFINITY, 0.0f64), |(a, b), p| {
        (a.min(p.0), b.max(p.0))
    });
    let (y0, y1) = pts().fold((f64::INFINITY, 0.0f64), |(a, b), p| {
        (a.min(p.1), b.max(p.1))
    });
    let root = SVGBackend::with_string(svg, (800, 520)).into_drawing_area();
    root.fill(&WHITE)?;
    let mut chart = ChartBuilder::on(&root)
        .caption(title, ("sans-serif", 20))
        .margin(16)
        .x_label_area_size(40)
        .y_label_area_size(64)
        .build_cartesian_2d(
            log_axis(x0, x1, 1.5).log_scale(),
            log_axis(y0, y1, 2.0).log_scale(),
        )?;
    chart
        .configure_mesh()
        .x_desc(x_desc)
        .y_desc(y_desc)
        .x_label_formatter(&|v| tick_label(*v))
        .y_label_formatter(&|v| tick_label(*v))
        .draw()?;
    let on_log = |p: &(f64, f64)| p.0 > 0.0 && p.1 > 0.0 && p.0.is_finite() && p.1.is_finite();
    draw_series(&mut chart, series, on_log, true)?;
    root.present()?;
    Ok(())
}

/// Each series of `series` as a line (with markers if `markers`) of its
/// points that `keep` keeps, and the legend: what the log and the linear
/// charts draw alike.
fn draw_series<'a, X, Y>(
    chart: &mut ChartContext<'a, SVGBackend<'a>, Cartesian2d<X, Y>>,
    series: &[Series],
    keep: impl Fn(&(f64, f64)) -> bool,
    markers: bool,
) -> Result<(), Box<dyn std::error::Error>>
where
    X: Ranged<ValueType = f64>,
    Y: Ranged<ValueType = f64>,
{
    for s in series {
        let p: Vec<(f64, f64)> = s.points.iter().copied().filter(|q| keep(q)).collect();
        let c = s.color;
        chart
            .draw_series(LineSeries::new(p.clone(), c.stroke_width(2)))?
            .label(s.name)
            .legend(move |(x, y)| PathElement::new(vec![(x, y), (x + 20, y)], c.stroke_width(2)));
        if markers {
            chart.draw_series(p.into_iter().map(|q| Circle::new(q, 4, c.filled())))?;
        }
    }
    chart
        .configure_series_labels()
        .background_style(WHITE.mix(0.8))
        .border_style(BLACK)
        .draw()?;
    Ok(())
}

/// Like [`xy_svg`], with linear axes: a log axis clamps zeros and hides
/// a small change in a large total (researcher probe: a conserved total's
/// drift could not be seen), so a timeline's totals are drawn on these.
/// Values are drawn as they are, negative ones too; a flat line gets an
/// axis around it, labelled with as many decimals as its ticks need.
pub fn line_svg(
    path: &Path,
    title: &str,
    x_desc: &str,
    y_desc: &str,
    series: &[Series],
) -> Result<String, ChartError> {
    let mut svg = String::new();
    draw_lines(&mut svg, title, x_desc, y_desc, series).map_err(|e| ChartError::new(path, e))?;
    Ok(svg)
}

fn draw_lines(
    svg: &mut String,
    title: &str,
    x_desc: &str,
    y_desc: &str,
    series: &[Series],
) -> Result<(), Box<dyn std::error::Error>> {
    let usable = |p: &&(f64, f64)| p.0.abs() < 1e300 && p.1.abs() < 1e300;
    let pts = || series.iter().flat_map(|s| s.points.iter()).filter(usable);
    if pts().next().is_none() {
        return Err("nothing to plot".into());
    }
    let span = |f: fn(&(f64, f64)) -> f64| {
        let (lo, hi) = pts()
            .map(f)
            .fold((f64::INFINITY, f64::NEG_INFINITY), |(a, b), v| {
                (a.min(v), b.max(v))
            });
        // A flat line: an axis of a millionth of its value (or ±0.5) around it.
        let pad = if hi > lo {
            (hi - lo) * 0.05
        } else {
            (hi.abs() * 1e-6).max(0.5)
        };
        (lo - pad)..(hi + pad)
    };
    let (xs, ys) = (span(|p| p.0), span(|p| p.1));
    let digits = |r: &std::ops::Range<f64>| {
        (-((r.end - r.start) / 20.0).log10().floor()).clamp(0.0, 12.0) as usize
    };
    let (xd, yd) = (digits(&xs), digits(&ys));
    let root = SVGBackend::with_string(svg, (800, 520)).into_drawing_area();
    root.fill(&WHITE)?;
    let mut chart = ChartBuilder::on(&root)
        .caption(title, ("sans-serif", 20))
        .margin(16)
        .x_label_area_size(40)
        .y_label_area_size(110)
        .build_cartesian_2d(xs, ys)?;
    chart
        .configure_mesh()
        .x_desc(x_desc)
        .y_desc(y_desc)
        .x_label_formatter(&|v| format!("{v:.xd$}"))
        .y_label_formatter(&|v| format!("{v:.yd$}"))
        .draw()?;
    draw_series(&mut chart, series, |p| usable(&p), false)?;
    root.present()?;
    Ok(())
}

/// Most decades a log axis spans: plotters divides the axis's ends, and an
/// infinite ratio made its tick placement loop for ever (regression, panic
/// audit: a timeline with 1e-10 and 9e299 in one column hung `chart`).
const MOST_DECADES: i32 = 250;

/// A log axis from `lo` to `hi` (both within 1e±300) with a `margin` factor
/// at each end; past [`MOST_DECADES`] decades its low end is raised (the
/// points below it fall off the chart).
fn log_axis(lo: f64, hi: f64, margin: f64) -> std::ops::Range<f64> {
    let (lo, hi) = (lo / margin, hi * margin);
    lo.max(hi / 10f64.powi(MOST_DECADES))..hi
}

/// A log axis's tick as a person writes it: three significant digits at
/// most, no trailing zeros (plotters printed `0.30000000000000004`).
fn tick_label(v: f64) -> String {
    if v == 0.0 || !v.is_finite() {
        return format!("{v}");
    }
    let digits = (2 - v.abs().log10().floor() as i32).clamp(0, 12) as usize;
    let s = format!("{v:.digits$}");
    if s.contains('.') {
        s.trim_end_matches('0').trim_end_matches('.').to_string()
    } else {
        s
    }
}

#[cfg(test)]
mod tick_tests {
    #[test]
    fn a_chart_spanning_three_hundred_decades_is_drawn() {
        let series = [super::Series {
            name: "water",
            color: super::BLUE,
            points: vec![(1.0, 1e-10), (2.0, 9e299), (1e-299, 1e299)],
        }];
        let svg = super::xy_svg(std::path::Path::new("t.svg"), "t", "x", "y", &series).unwrap();
        assert!(svg.contains("<svg"), "{svg}");
    }

    #[test]
    fn linear_charts_draw_flat_negative_and_drifting_lines() {
        use plotters::style::RGBColor;
        let line = |pts: Vec<(f64, f64)>| super::Series {
            name: "t",
            color: RGBColor(0, 0, 0),
            points: pts,
        };
        let p = std::path::Path::new("t.svg");
        for pts in [
            vec![(1.0, 139284.0), (2.0, 139284.0)],
            vec![(1.0, -3.0), (5.0, -1.0)],
            vec![(0.0, 0.0), (1.0, 0.0)],
            vec![(1.0, 139284.0), (2.0, 139284.0 * (1.0 + 1e-9))],
        ] {
            let svg = super::line_svg(p, "t", "x", "y", &[line(pts.clone())]).unwrap();
            assert!(
                svg.contains("<polyline") || svg.contains("<path"),
                "{pts:?}"
            );
        }
        // A drift of a billionth shows in the labels' decimals.
        let svg = super::line_svg(
            p,
            "t",
            "x",
            "y",
            &[line(vec![(1.0, 139284.0), (2.0, 139284.0002)])],
        )
        .unwrap();
        assert!(svg.contains("139284.000"), "no decimals on a small span");
        assert!(super::line_svg(p, "t", "x", "y", &[line(vec![(1.0, f64::NAN)])]).is_err());
    }

    #[test]
    fn ticks_are_short() {
        assert_eq!(super::tick_label(0.30000000000000004), "0.3");
        assert_eq!(super::tick_label(10.0), "10");
        assert_eq!(super::tick_label(0.0123456), "0.0123");
        assert_eq!(super::tick_label(1234.6), "1235");
        assert_eq!(super::tick_label(2.5), "2.5");
    }
}
