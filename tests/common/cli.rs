//! Helpers for tests that run the `brickworld` binary as a user would.

use std::path::Path;
use std::process::{Command, Output};

/// The binary under test.
pub fn bin() -> Command {
    Command::new(env!("CARGO_BIN_EXE_brickworld"))
}

/// The binary under a shell limit (`limit` as `ulimit` takes it, e.g.
/// `-v 1048576`); add its arguments with `.arg`/`.args`, passed as they
/// are (no quoting).
pub fn bin_limited(limit: &str) -> Command {
    let mut c = Command::new("bash");
    c.arg("-c")
        .arg(format!("ulimit {limit} && exec \"$0\" \"$@\""))
        .arg(env!("CARGO_BIN_EXE_brickworld"));
    c
}

/// The path `name` in a scratch folder of its own (`brickworld-TAG-…`),
/// removed when the returned guard is dropped, unless the test fails.
pub fn tmp(tag: &str, name: &str) -> super::scratch::Scratch {
    super::scratch::Scratch::file(tag, name)
}

/// Require a run to have succeeded, showing its stderr otherwise.
/// A run that succeeded with a panic in some thread is a bug too.
pub fn assert_success(out: &Output) {
    let err = String::from_utf8_lossy(&out.stderr);
    assert!(out.status.success(), "{err}");
    assert_no_panic(&err, "the run");
}

/// Read a JSON file the binary wrote.
pub fn read_json(path: &Path) -> serde_json::Value {
    serde_json::from_slice(&std::fs::read(path).unwrap()).unwrap()
}

/// Require `text` (a run's stderr or log) to show no panic: the panic
/// hook prints "internal bug" without `RUST_BACKTRACE` and Rust's own
/// "panicked" with it, so both are looked for (regression: tests looked for
/// "panicked" only, which CI's hook never prints).
pub fn assert_no_panic(text: &str, what: &str) {
    assert!(
        !text.contains("panicked")
            && !text.contains("internal bug")
            && !text.contains("RUST_BACKTRACE"),
        "{what} panicked: {text}"
    );
}

/// A failed run must exit with status 1 and one clear error line mentioning
/// `needle` (warnings before it allowed), never a panic or a backtrace, as
/// the README promises (regression, audit: only a non-zero exit was
/// checked).
pub fn assert_clear_failure(out: &Output, what: &str, needle: &str) {
    let err = String::from_utf8_lossy(&out.stderr);
    assert!(!out.status.success(), "{what} should fail");
    assert_eq!(out.status.code(), Some(1), "{what}: exit status, {err}");
    assert_no_panic(&err, what);
    let lines: Vec<&str> = err
        .lines()
        .filter(|l| !l.trim().is_empty() && !l.starts_with("warning:"))
        .collect();
    assert_eq!(lines.len(), 1, "{what}: one error line, got {err}");
    assert!(
        err.contains(needle),
        "{what}: '{err}' should mention '{needle}'"
    );
}

/// Make a FIFO at `path` (the tests of inputs that must not block).
#[allow(dead_code)]
pub fn mkfifo(path: &Path) {
    let made = std::process::Command::new("mkfifo")
        .arg(path)
        .status()
        .unwrap();
    assert!(made.success(), "mkfifo {}", path.display());
}
