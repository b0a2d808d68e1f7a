//! The `brickworld` binary: parse the command line, run, report errors.

use std::process::ExitCode;

use clap::error::ErrorKind;
use clap::{CommandFactory, FromArgMatches};

/// The command line as `Cli` derives it, with negative numbers taken as
/// values everywhere (`--fov -1` reached the validator, which names the
/// flag, instead of clap's "unexpected argument '-1'").
fn command() -> clap::Command {
    fn negatives(c: clap::Command) -> clap::Command {
        c.allow_negative_numbers(true).mut_subcommands(negatives)
    }
    negatives(brickworld::cli::Cli::command())
}

/// Parse the command line. Help and version print as clap prints them; any
/// other error is one line on stderr and exit code 1, as all bad input is.
fn parse() -> Result<brickworld::cli::Cli, ExitCode> {
    let cmd = command();
    let args = help_flags_as_topics(&cmd, std::env::args_os().collect());
    let parsed = cmd
        .try_get_matches_from(args)
        .and_then(|m| brickworld::cli::Cli::from_arg_matches(&m));
    parsed.map_err(|e| match e.kind() {
        ErrorKind::DisplayHelp | ErrorKind::DisplayVersion => printed(
            e.print()
                .and_then(|()| std::io::Write::flush(&mut std::io::stdout())),
        ),
        ErrorKind::DisplayHelpOnMissingArgumentOrSubcommand => {
            // `brickworld`, `brickworld bench` …: one line naming the
            // subcommands, exit 1 (newcomer walk: the whole help, exit 2).
            let args = std::env::args_os().skip(1);
            brickworld::say!(
                "{}",
                missing_subcommand(args.map(|a| a.to_string_lossy().into_owned()))
            );
            ExitCode::FAILURE
        }
        _ => {
            // clap's message up to its first blank line (what is wrong, and
            // any names it lists), joined into one line; no usage or tips.
            let text = e.to_string();
            let what: Vec<&str> = text
                .lines()
                .take_while(|l| !l.trim().is_empty())
                .map(str::trim)
                .collect();
            brickworld::say!("{} (see --help)", what.join(" "));
            ExitCode::FAILURE
        }
    })
}

/// The exit code after printing help or the version: clap's own `exit`
/// ignored write errors, so `--help > /dev/full` printed nothing and
/// exited 0 (regression, twenty-fourth session). A closed pipe is quiet
/// with status 0 (`brickworld --help | head -1`), as everywhere.
fn printed(result: std::io::Result<()>) -> ExitCode {
    match result {
        Ok(()) => ExitCode::SUCCESS,
        Err(e) if e.kind() == std::io::ErrorKind::BrokenPipe => ExitCode::SUCCESS,
        Err(e) => {
            brickworld::say!("error: cannot write to standard output: {e}");
            ExitCode::FAILURE
        }
    }
}

/// clap's `help` subcommands take no flags: `brickworld help --help` and
/// `brickworld bench help -h` said "unrecognized subcommand '--help'"
/// (regressions, hostile probe and review of the twenty-fourth session).
/// After a `help` reached through subcommand names, `-h` and `--help` are
/// dropped, and a `help` with nothing else left asks for the help of
/// `help` itself. So is a `--` (`help -- -h` said "unrecognized
/// subcommand '--'"; `help -- run` is `help run`).
fn help_flags_as_topics(
    cli: &clap::Command,
    mut args: Vec<std::ffi::OsString>,
) -> Vec<std::ffi::OsString> {
    let mut cmd = cli;
    let mut at = 1;
    while let Some(a) = args.get(at).and_then(|a| a.to_str()) {
        if a == "help" && cmd.has_subcommands() {
            let asked: Vec<_> = args.drain(at + 1..).collect();
            let topics: Vec<_> = asked
                .iter()
                .filter(|a| *a != "-h" && *a != "--help" && *a != "--")
                .cloned()
                .collect();
            if topics.is_empty() && !asked.is_empty() {
                args.push("help".into());
            }
            args.extend(topics);
            break;
        }
        match cmd.find_subcommand(a) {
            Some(sub) => {
                cmd = sub;
                at += 1;
            }
            None => break,
        }
    }
    args
}

/// "error: `brickworld bench` needs a subcommand: …" for the command
/// `args` name, its subcommands listed.
fn missing_subcommand(args: impl Iterator<Item = String>) -> String {
    let mut cmd = command();
    let mut path = vec![cmd.get_name().to_string()];
    for a in args {
        match cmd.find_subcommand(&a) {
            Some(sub) => {
                let sub = sub.clone();
                path.push(sub.get_name().to_string());
                cmd = sub;
            }
            None => break,
        }
    }
    let subs: Vec<&str> = cmd
        .get_subcommands()
        .map(|c| c.get_name())
        .filter(|n| *n != "help")
        .collect();
    format!(
        "error: `{}` needs a subcommand: {} (see --help)",
        path.join(" "),
        subs.join(", ")
    )
}

fn main() -> ExitCode {
    brickworld::install_panic_hook();
    // One re-exec where the environment lacks what the process needs: a
    // private XDG_RUNTIME_DIR for Mesa, glibc's mmap threshold for the
    // engine (see the module).
    brickworld::process_env::ensure();
    // After `ensure`: a failed exec leaves the signal mask empty.
    brickworld::files::no_signal_from_writes();
    let cli = match parse() {
        Ok(cli) => cli,
        Err(code) => return code,
    };
    match brickworld::app::run(cli) {
        Ok(()) => ExitCode::SUCCESS,
        Err(e) => {
            brickworld::say!("error: {e:#}");
            ExitCode::FAILURE
        }
    }
}
