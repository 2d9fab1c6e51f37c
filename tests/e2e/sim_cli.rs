//! `lcrl sim` as a user runs it.

use std::fs;

use serde_json::Value;

use super::common::{assert_clean_failure, lcrl, stdout};

#[test]
fn constant_controller_writes_summary_trace_and_plot() {
    let dir = tempfile::tempdir().unwrap();
    let out = lcrl().args(["sim", "--env", "peg-group1", "--episodes", "3", "--seed", "7", "--out"]).arg(dir.path()).output().unwrap();
    assert!(out.status.success(), "{}", String::from_utf8_lossy(&out.stderr));
    assert!(stdout(&out).contains("success rate"));

    let summary: Value = serde_json::from_str(&fs::read_to_string(dir.path().join("summary.json")).unwrap()).unwrap();
    for key in ["episodes", "success_rate", "mean_steps_to_insert", "mean_peak_force_n", "mean_peak_moment_nm", "max_penetration_mm", "mean_return", "control_steps_per_sec"] {
        assert!(summary.get(key).is_some_and(|v| !v.is_null()), "summary.json lacks {key}: {summary}");
    }
    assert_eq!(summary["episodes"], 3);
    assert!(summary["max_penetration_mm"].as_f64().unwrap() < 0.01);

    let mut trace = csv_rows(&dir.path().join("trace.csv"));
    let header = trace.remove(0);
    assert_eq!(&header[..4], &["step", "time_s", "x", "y"]);
    assert!(header.contains(&"Fz".to_string()) && header.contains(&"action_dgamma".to_string()));
    assert_eq!(header.last().unwrap(), "reward");
    // Row 0 is the initial state; the remaining depth falls as the peg goes in.
    let z = header.iter().position(|h| h == "z").unwrap();
    let first: f64 = trace[0][z].parse().unwrap();
    let last: f64 = trace.last().unwrap()[z].parse().unwrap();
    assert!(first > 30.0 && last < 1.0, "z from {first} to {last}");

    let png = fs::read(dir.path().join("trace.png")).unwrap();
    assert!(png.starts_with(b"\x89PNG") && png.len() > 10_000);
}

#[test]
fn linear_environment_works_too() {
    let dir = tempfile::tempdir().unwrap();
    let out = lcrl().args(["sim", "--env", "lti-paper", "--episodes", "2", "--out"]).arg(dir.path()).output().unwrap();
    assert!(out.status.success(), "{}", String::from_utf8_lossy(&out.stderr));
    let summary: Value = serde_json::from_str(&fs::read_to_string(dir.path().join("summary.json")).unwrap()).unwrap();
    assert_eq!(summary["success_rate"], Value::Null);
    assert!(dir.path().join("trace.png").is_file());
}

#[test]
fn bad_input_fails_cleanly() {
    let dir = tempfile::tempdir().unwrap();
    let run = |args: &[&str]| lcrl().arg("sim").args(args).output().unwrap();
    assert_clean_failure(&run(&["--env", "peg-group7"]), "unknown environment 'peg-group7'");
    assert_clean_failure(&run(&["--env", "peg-group1", "--episodes", "0"]), "--episodes");
    assert_clean_failure(&run(&["--env", "peg-group1", "--out", "/proc/lcrl-cannot-write"]), "/proc/lcrl-cannot-write");
    let bad = dir.path().join("bad.toml");
    fs::write(&bad, "kind = \"peg\"\n[contact]\nfriction = -1.0\n").unwrap();
    assert_clean_failure(&run(&["--env", bad.to_str().unwrap()]), "contact.friction");
    fs::write(&bad, "kind = \"peg\"\n[geometry]\npeg_length = 3.0\n").unwrap();
    assert_clean_failure(&run(&["--env", bad.to_str().unwrap()]), "peg_length");
}

fn csv_rows(path: &std::path::Path) -> Vec<Vec<String>> {
    fs::read_to_string(path).unwrap().lines().map(|l| l.split(',').map(str::to_string).collect()).collect()
}
