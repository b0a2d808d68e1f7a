//! brickworld: a voxel world engine built on sparse 8³ bricks.
//!
//! - [`world`]: bricks, the sparse store with edit tracking, the brick grid.
//! - [`scene`]: deterministic scene sources (terrain, balls, hairball,
//!   heightmap PNGs, MagicaVoxel files).
//! - [`trace`]: the exact DDA, three interchangeable CPU tracers (dense grid,
//!   sparse voxel octree, brickmap), the camera and the tiled renderer.
//! - [`bench`](mod@bench): the `bench tracers` comparison and its chart.
//! - [`cli`], [`config`], [`app`]: the command line, its validation, and `run`.
#![warn(missing_docs)]
// The library serves the binary, its tests and examples: its docs are read
// with `--document-private-items` (as `.ci/local` builds them), where a
// link from a public item to a private one resolves.
#![allow(rustdoc::private_intra_doc_links)]

pub mod app;
pub mod bench;
pub mod cli;
pub mod config;
pub mod engine;
pub mod files;
pub mod gpu;
pub mod persist;
pub mod progress;
pub mod scene;
pub mod sim;
pub mod sim_cmd;
pub mod text;
pub mod trace;
pub mod verify;
pub mod world;

pub mod process_env;

/// `eprintln!` that never panics: standard error that is full or closed
/// (`2>/dev/full`, `2>&1 | head -1`) loses the line, not the run, whose
/// exit status still says how it went (regression, hostile probe: every
/// command panicked with status 101 at its first message there). Every
/// message of the crate goes through it.
#[macro_export]
macro_rules! say {
    ($($arg:tt)*) => {{
        use std::io::Write as _;
        // One line, whatever a path or name in it holds: control characters
        // are escaped (regression, odd-paths probe: a path with ESC set the
        // terminal's title, one with a newline split the error in two).
        let line = format!($($arg)*);
        let _ = writeln!(std::io::stderr(), "{}", $crate::text::escape_controls(&line, true));
    }};
}

/// `println!` for lines that echo user paths or names: control characters
/// are escaped, as [`say!`] does on standard error (regression, odd-paths
/// probe: a state folder with a newline in its name split `run`'s line).
#[macro_export]
macro_rules! tell {
    ($($arg:tt)*) => {{
        let line = format!($($arg)*);
        println!("{}", $crate::text::escape_controls(&line, true));
    }};
}

/// A path as a shell, and then the command, reads it back: quoted when it
/// holds anything but plain characters (regression, odd-paths probe: `init
/// 'my world'` suggested `brickworld run my world/world.toml`), and a
/// relative path that starts with `-` led by `./`, so that it is not read
/// as an option (review: an import's advice quoted `-x` as `'-x'`).
///
/// ```
/// use std::path::Path;
/// use brickworld::shell_quoted;
/// assert_eq!(shell_quoted(Path::new("w/world.toml")), "w/world.toml");
/// assert_eq!(shell_quoted(Path::new("my world/world.toml")), "'my world/world.toml'");
/// assert_eq!(shell_quoted(Path::new("it's")), r"'it'\''s'");
/// assert_eq!(shell_quoted(Path::new("-x")), "./-x");
/// ```
pub fn shell_quoted(p: &std::path::Path) -> String {
    if p.is_relative() && p.to_string_lossy().starts_with('-') {
        return shell_quoted(&std::path::Path::new(".").join(p));
    }
    let t = p.to_string_lossy();
    let plain = !t.is_empty()
        && !t.starts_with('-')
        && t.chars()
            .all(|c| c.is_ascii_alphanumeric() || "/._-+,:@%".contains(c));
    if plain {
        t.into_owned()
    } else {
        format!("'{}'", t.replace('\'', "'\\''"))
    }
}

/// Replace Rust's panic message with a one-line report (no backtrace unless
/// `RUST_BACKTRACE` is set): a panic is a bug, but users should not see a
/// wall of frames.
///
/// Standard output that is closed (`brickworld chart S | head -1`) or full
/// (`> /dev/full`) is not a bug: `println!` panics there, and the hook
/// ends the process as ripgrep does, quietly with status 0 for a closed
/// pipe, and with one line and status 1 for any other write error.
pub fn install_panic_hook() {
    let verbose = std::env::var_os("RUST_BACKTRACE").is_some();
    let default = std::panic::take_hook();
    std::panic::set_hook(Box::new(move |info| {
        let msg = info
            .payload()
            .downcast_ref::<&str>()
            .map(|s| s.to_string())
            .or_else(|| info.payload().downcast_ref::<String>().cloned())
            .unwrap_or_else(|| "unknown panic".into());
        if let Some(why) = msg.strip_prefix("failed printing to stdout: ") {
            if why.contains("Broken pipe") {
                std::process::exit(0);
            }
            crate::say!("error: cannot write to standard output: {why}");
            std::process::exit(1);
        }
        // std panics in a new thread whose signal stack cannot be mapped
        // (address space used up, as under `ulimit -v` with many threads):
        // out of memory, not a bug, and one line like the pool's own error
        // (regression: a backtrace, or a second line, now and then).
        if msg.starts_with("failed to allocate an alternative stack")
            || msg.starts_with("failed to set up alternative stack guard page")
        {
            crate::say!(
                "error: cannot start the worker threads: out of memory ({msg}) (ask for fewer with --threads or RAYON_NUM_THREADS)"
            );
            std::process::exit(1);
        }
        // redb panics on some corrupt stores (a page's bytes not what its
        // header says), and a second panic in its destructors then aborts:
        // a damaged file, not a bug of ours, so one line and status 1, at
        // once, before any destructor runs (regression, hostile probe:
        // flipped bytes in world.redb's system pages crashed `run` at its
        // first commit on every start, and `export` at its end).
        if let Some(l) = info.location()
            && is_redb_source(l.file())
        {
            if verbose {
                default(info);
            }
            crate::say!(
                "error: the world store is damaged (redb failed on it: {msg} at {}:{}): restore the state directory from a copy, or import a backup (brickworld import) into a new one",
                l.file().rsplit("/src/").next().unwrap_or(l.file()),
                l.line()
            );
            std::process::exit(1);
        }
        // A panic `catch_quietly` turns into an error prints nothing, even
        // with RUST_BACKTRACE set: it is handled, and its error is said.
        if QUIET_PANICS.with(|q| q.get()) {
            return;
        }
        if verbose {
            return default(info);
        }
        let at = info
            .location()
            .map(|l| format!(" at {}:{}", l.file(), l.line()))
            .unwrap_or_default();
        crate::say!(
            "error: internal bug: {msg}{at} (please report it; set RUST_BACKTRACE=1 for details)"
        );
    }));
}

/// Whether a source path is redb's: a registry or git checkout
/// (`redb-4.5.0/src/…`) or a vendored copy (`vendor/redb/src/…`), with
/// either separator.
fn is_redb_source(file: &str) -> bool {
    file.split(['/', '\\'])
        .any(|part| part == "redb" || part.starts_with("redb-"))
}

thread_local! {
    static QUIET_PANICS: std::cell::Cell<bool> = const { std::cell::Cell::new(false) };
}

/// A panic caught by [`catch_quietly`].
#[derive(Debug, thiserror::Error)]
#[error("the operation panicked")]
pub struct Panicked;

/// Run `f`, turning a panic inside it into `Err` without printing anything.
/// Used around third-party parsers fed untrusted files.
pub fn catch_quietly<T>(f: impl FnOnce() -> T + std::panic::UnwindSafe) -> Result<T, Panicked> {
    QUIET_PANICS.with(|q| q.set(true));
    let r = std::panic::catch_unwind(f);
    QUIET_PANICS.with(|q| q.set(false));
    r.map_err(|_| Panicked)
}

#[cfg(test)]
mod panic_hook_tests {
    /// The damaged-store exit takes redb's panics wherever redb was built
    /// from (found by review: only `/redb-` paths were), and no others.
    #[test]
    fn redb_sources_are_recognised_in_every_layout() {
        for f in [
            "/root/.cargo/registry/src/index.crates.io-x/redb-4.5.0/src/types.rs",
            "vendor/redb/src/tree_store/btree.rs",
            "C:\\cargo\\registry\\src\\x\\redb-4.5.0\\src\\types.rs",
        ] {
            assert!(super::is_redb_source(f), "{f}");
        }
        for f in [
            "src/persist/db/mod.rs",
            "/x/redbox/src/a.rs",
            "src/world.redb.rs",
        ] {
            assert!(!super::is_redb_source(f), "{f}");
        }
    }
}
