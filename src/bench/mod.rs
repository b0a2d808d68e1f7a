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
