//! Helpers for running the project's binaries.

use std::io::{BufRead, BufReader};
use std::path::{Path, PathBuf};
use std::process::{Child, Command, Output, Stdio};

/// `lcrl`, built by cargo for this test binary.
pub fn lcrl() -> Command {
    let mut cmd = Command::new(env!("CARGO_BIN_EXE_lcrl"));
    cmd.env(lcrl_proto::shm::NAMESPACE_ENV, shm_namespace());
    cmd
}

/// This test's shared-memory namespace (lcrl_proto::shm::NAMESPACE_ENV),
/// given to every process it starts: tests running side by side never
/// meet in shared memory, whatever run ids they use (one learner a run id
/// on a host). nextest runs each test in a process of its own.
pub fn shm_namespace() -> String {
    format!("test-{}", std::process::id())
}

/// Another workspace binary (lcrl-graph-builder, ...). Cargo builds only this
/// package's binaries for its tests, so the test command builds the whole
/// workspace first (`cargo build --workspace --bins`).
pub fn workspace_bin(name: &str) -> Command {
    let dir = PathBuf::from(env!("CARGO_BIN_EXE_lcrl")).parent().expect("target dir").to_path_buf();
    let path = dir.join(name);
    assert!(path.is_file(), "{} is missing: run `cargo build --workspace --bins` before the tests", path.display());
    let mut cmd = Command::new(path);
    cmd.env(lcrl_proto::shm::NAMESPACE_ENV, shm_namespace());
    cmd
}

/// Starts a server (learner, graph builder) and waits for the line it
/// prints once its port is bound, `listening on ADDR`; returns the child
/// and ADDR. Its stderr is discarded.
pub fn spawn_listening(command: &mut Command) -> (Child, String) {
    let mut child = command.stdout(Stdio::piped()).stderr(Stdio::null()).spawn().unwrap();
    let mut line = String::new();
    BufReader::new(child.stdout.take().unwrap()).read_line(&mut line).unwrap();
    match line.trim().strip_prefix("listening on ") {
        Some(addr) => (child, addr.to_string()),
        None => {
            // Not left running behind the failed test.
            let _ = child.kill();
            let _ = child.wait();
            panic!("the server said {line:?}, not \"listening on ADDR\"")
        }
    }
}

pub fn stdout(out: &Output) -> String {
    String::from_utf8_lossy(&out.stdout).into_owned()
}

pub fn stderr(out: &Output) -> String {
    String::from_utf8_lossy(&out.stderr).into_owned()
}

/// Asserts a failed run: non-zero exit, one clear `error:` line, no panic.
pub fn assert_clean_failure(out: &Output, needle: &str) {
    let err = stderr(out);
    assert!(!out.status.success(), "expected failure, got success; stderr: {err}");
    assert!(!err.contains("panicked"), "panicked instead of a clear error: {err}");
    let lines: Vec<&str> = err.lines().filter(|l| l.contains("error")).collect();
    assert_eq!(lines.len(), 1, "expected exactly one error line, got: {err}");
    assert!(lines[0].contains(needle), "error line {:?} should mention {needle:?}", lines[0]);
}

/// Every YAML document of a manifest file.
pub fn load_docs(path: &Path) -> Vec<serde_yaml::Value> {
    let text = std::fs::read_to_string(path).unwrap_or_else(|e| panic!("{}: {e}", path.display()));
    serde_yaml::Deserializer::from_str(&text)
        .map(|doc| <serde_yaml::Value as serde::Deserialize>::deserialize(doc).unwrap_or_else(|e| panic!("{} is not YAML: {e}", path.display())))
        .collect()
}

pub fn str_of<'a>(v: &'a serde_yaml::Value, path: &[&str]) -> &'a str {
    let mut at = v;
    for key in path {
        at = &at[*key];
    }
    at.as_str().unwrap_or_else(|| panic!("{path:?} is not a string in {v:?}"))
}

pub fn seq<'a>(v: &'a serde_yaml::Value, key: &str) -> Vec<&'a serde_yaml::Value> {
    v[key].as_sequence().map(|s| s.iter().collect()).unwrap_or_default()
}

/// A peg run's metrics.csv, whichever loop wrote it: every row carries the
/// episode's peak force and moment, and reward terms that add up to its
/// return. Returns the number of rows.
pub fn assert_peg_rows_measured(metrics: &Path) -> usize {
    let mut rows = csv::Reader::from_path(metrics).unwrap();
    let header: Vec<String> = rows.headers().unwrap().iter().map(str::to_string).collect();
    assert_eq!(header, lcrl_learner::run::files::METRICS_COLUMNS.map(String::from), "{}", metrics.display());
    let mut count = 0;
    for row in rows.records() {
        let row = row.unwrap();
        let (force, moment): (f64, f64) = (row[4].parse().unwrap(), row[5].parse().unwrap());
        assert!(force.is_finite() && force >= 0.0 && moment.is_finite() && moment >= 0.0, "{row:?}");
        let total: f64 = row[1].parse().unwrap();
        let parts: f64 = (8..13).map(|k| row[k].parse::<f64>().unwrap()).sum();
        assert!((total - parts).abs() < 1e-9, "{row:?}");
        count += 1;
    }
    count
}

/// The repository root (README.md, scripts/, configs/).
pub fn repo() -> PathBuf {
    PathBuf::from(env!("CARGO_MANIFEST_DIR"))
}
