//! The `brickworld` binary: parse the command line, run, report errors.

use std::process::ExitCode;

use clap::Parser;

fn main() -> ExitCode {
    brickworld::install_panic_hook();
    // Mesa prints "XDG_RUNTIME_DIR is invalid" (twice) when the variable is
    // missing, which reads like a failure: give it a private directory.
    brickworld::runtime_dir::ensure();
    let cli = brickworld::cli::Cli::parse();
    match brickworld::app::run(cli) {
        Ok(()) => ExitCode::SUCCESS,
        Err(e) => {
            eprintln!("error: {e:#}");
            ExitCode::FAILURE
        }
    }
}
