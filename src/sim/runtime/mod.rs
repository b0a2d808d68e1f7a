//! The script runtime shared by both grids: what a script declares
//! ([`spec`], read by [`declare`]), the sandboxed Luau VMs that run it under
//! budgets that cannot be caught ([`script`]), the Lua prelude that keeps
//! out-of-memory uncatchable and addresses hidden (`prelude`),
//! deterministic randomness ([`random`]), hot reload, and the scripts built
//! into the binary.

pub mod declare;
pub mod embedded;
pub(crate) mod interrupt;
pub mod log;
pub mod materials;
mod prelude;
pub mod random;
pub mod reload;
pub mod script;
pub mod spec;
pub mod vms;
