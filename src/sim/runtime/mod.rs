//! The script runtime shared by both grids: what a script declares
//! ([`spec`], read by [`declare`]), the sandboxed Luau VMs that run it under
//! budgets that cannot be caught ([`script`]), the Lua prelude that keeps
//! out-of-memory uncatchable and addresses hidden (`prelude`),
//! deterministic randomness ([`random`]), script files ([`source_file`]), hot reload, the scripts built
//! into the binary, and how source becomes code in each VM ([`compile`]).

pub mod compile;
pub(crate) mod cpu_clock;
pub mod declare;
pub mod embedded;
mod errors;
pub(crate) mod interrupt;
pub mod log;
pub mod materials;
mod prelude;
pub mod random;
pub mod reload;
mod sandbox;
pub mod script;
pub mod source_file;
pub mod spec;
mod strict;
pub mod vms;
