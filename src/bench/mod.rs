//! Benchmarks run from the binary (`brickworld bench …`): measured figures,
//! JSON that other tools read, and SVG charts.

pub mod chart;
pub mod flight;
pub mod lod;
pub mod sim;
pub mod soak;
pub mod store;
pub mod stream;
pub mod tracers;
pub mod voxels;

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
