//! Benchmarks run from the binary (`brickworld bench …`): measured figures,
//! JSON that other tools read, and SVG charts.

pub mod chart;
pub mod flight;
pub mod gpu;
pub mod lod;
pub mod sim;
pub mod soak;
pub mod store;
pub mod stream;
pub mod tracers;
pub mod voxels;

/// Write a command's JSON results through a temporary beside `json`,
/// replacing it only once written (the flag was checked before the work
/// with [`crate::config::check_bench_outputs`]).
pub fn write_json(json: &std::path::Path, value: &impl serde::Serialize) -> anyhow::Result<()> {
    let text = serde_json::to_string_pretty(value)? + "\n";
    write_outputs(json, &text, None, |_| Ok(()))
}

/// Write a bench's JSON and, if asked, its chart (`draw` draws it into the
/// file it is given), so that a failure leaves
/// both files as they were: the chart is drawn into a temporary file beside
/// its destination, the JSON written beside its own, and both replace
/// their destinations only once both are written (regression, hostile
/// probe: a chart that failed, on a full disk or with nothing to plot,
/// after the JSON had replaced the previous results).
pub fn write_outputs(
    json: &std::path::Path,
    text: &str,
    chart: Option<&std::path::Path>,
    draw: impl Fn(&std::path::Path) -> Result<(), chart::ChartError>,
) -> anyhow::Result<()> {
    use anyhow::Context;
    let cannot = |p: &std::path::Path| format!("cannot write {}", p.display());
    let drawn = match chart {
        Some(path) => {
            let st = crate::files::Staged::new(path).with_context(|| cannot(path))?;
            draw(st.path()).map_err(|e| e.at(path))?;
            Some((st, path))
        }
        None => None,
    };
    let st = crate::files::Staged::new(json).with_context(|| cannot(json))?;
    std::fs::write(st.path(), text).with_context(|| cannot(json))?;
    st.commit().with_context(|| cannot(json))?;
    if let Some((st, path)) = drawn {
        st.commit().with_context(|| cannot(path))?;
    }
    Ok(())
}

/// The views a bench renders: the one given, or the scene's three default
/// views (overview, medium, close-up) with the `--fov` override.
pub(crate) fn views(
    world: &crate::scene::SceneWorld,
    view: &crate::config::ViewSettings,
) -> Vec<crate::scene::View> {
    match view.view {
        Some(v) => vec![v],
        None => world
            .default_views()
            .into_iter()
            .map(|mut v| {
                if let Some(f) = view.fov {
                    v.fov = f;
                }
                v
            })
            .collect(),
    }
}
