//! The script runtime shared by both grids: sandboxed Luau VMs, declarations,
//! budgets that cannot be caught, deterministic randomness ([`script::StepKey`]),
//! hot reload, and the scripts built into the binary.

pub mod embedded;
pub(crate) mod interrupt;
pub mod log;
pub mod materials;
pub mod reload;
pub mod script;
pub mod vms;
