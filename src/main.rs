//! The `brickworld` binary: parse the command line, run, report errors.

use std::process::ExitCode;

use clap::Parser;

fn main() -> ExitCode {
    brickworld::install_panic_hook();
    let cli = brickworld::cli::Cli::parse();
    match brickworld::app::run(cli) {
        Ok(()) => ExitCode::SUCCESS,
        Err(e) => {
            eprintln!("error: {e:#}");
            ExitCode::FAILURE
        }
    }
}
