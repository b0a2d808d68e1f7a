//! The long-running engine: world configs and crash-safe checkpoints (the
//! daemon that runs them lands with issue 5).

pub mod checkpoint;
pub mod world_config;
