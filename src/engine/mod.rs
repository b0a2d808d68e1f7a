//! The long-running engine: world configs, the world store glue and the
//! single-file backups (checkpoints), the
//! control server, the daemon loop and its command-line client.

pub mod backup;
pub mod checkpoint;
pub mod control;
pub mod ctl;
pub mod daemon;
pub mod frames;
pub mod persistence;
pub mod render_thread;
pub mod state_dir;
pub mod streaming;
pub mod timeline;
pub mod world_config;
