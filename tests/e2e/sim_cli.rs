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

/// episodes.csv has one row per start, in seed order, that agrees with
/// summary.json; a start that exceeded a limit is marked failed; and a
/// start run alone (`--seed S --episodes 1`, to trace it) repeats its row.
#[test]
fn episodes_csv_finds_the_failed_starts_and_each_reruns_alone() {
    let dir = tempfile::tempdir().unwrap();
    let sim = |out: &std::path::Path, seed: &str, episodes: &str| {
        // Lateral compliance off, rotational at its maximum: jams from most
        // starts (sim/src/peg/physics_tests.rs).
        let run = lcrl()
            .args(["sim", "--env", "peg-group1", "--action", "-1,-1,2,4,4,4", "--seed", seed, "--episodes", episodes, "--out"])
            .arg(out)
            .output()
            .unwrap();
        assert!(run.status.success(), "{}", String::from_utf8_lossy(&run.stderr));
        let summary: Value = serde_json::from_str(&fs::read_to_string(out.join("summary.json")).unwrap()).unwrap();
        let mut rows = csv_rows(&out.join("episodes.csv"));
        let header = rows.remove(0);
        (summary, header, rows)
    };
    let (summary, header, rows) = sim(&dir.path().join("all"), "20", "6");
    assert_eq!(header, ["seed", "steps", "return", "terminated", "success", "failed", "peak_force_n", "peak_moment_nm", "max_penetration_mm", "max_action_jump"]);
    let col = |name: &str| header.iter().position(|h| h == name).unwrap();
    let seeds: Vec<&str> = rows.iter().map(|r| r[col("seed")].as_str()).collect();
    assert_eq!(seeds, ["20", "21", "22", "23", "24", "25"]);
    let number = |row: &Vec<String>, name: &str| -> f64 { row[col(name)].parse().unwrap() };
    let mean_return = rows.iter().map(|r| number(r, "return")).sum::<f64>() / 6.0;
    assert!((mean_return - summary["mean_return"].as_f64().unwrap()).abs() < 1e-9, "{mean_return} against {summary}");
    // A constant action never jumps.
    assert!(rows.iter().all(|r| number(r, "max_action_jump") == 0.0), "{rows:?}");
    let max_force = rows.iter().map(|r| number(r, "peak_force_n")).fold(f64::MIN, f64::max);
    assert_eq!(max_force, summary["max_peak_force_n"].as_f64().unwrap());
    // A failed start exceeded a limit (50 N or 1.5 N·m) and paid the charge.
    let failed: Vec<&Vec<String>> = rows.iter().filter(|r| r[col("failed")] == "true").collect();
    assert!(!failed.is_empty(), "the jamming action failed no start: {rows:?}");
    for row in &failed {
        assert!(number(row, "peak_force_n") > 50.0 || number(row, "peak_moment_nm") > 1.5, "{row:?}");
        assert!(number(row, "return") < -600.0 && row[col("success")] == "false", "{row:?}");
    }
    // The first failed start, alone, repeats its row exactly.
    let (_, _, alone) = sim(&dir.path().join("alone"), &failed[0][col("seed")], "1");
    assert_eq!(&alone[0], failed[0]);
}

fn csv_rows(path: &std::path::Path) -> Vec<Vec<String>> {
    fs::read_to_string(path).unwrap().lines().map(|l| l.split(',').map(str::to_string).collect()).collect()
}

/// `--action` runs any constant action; summary.json splits the return into
/// its reward terms, which add up to it.
#[test]
fn constant_action_runs_and_its_return_terms_add_up() {
    let dir = tempfile::tempdir().unwrap();
    let out = lcrl()
        .args(["sim", "--env", "peg-group1", "--episodes", "3", "--action", "2,2,0,-0.5,0,1", "--out"])
        .arg(dir.path())
        .output()
        .unwrap();
    assert!(out.status.success(), "{}", String::from_utf8_lossy(&out.stderr));
    let s: Value = serde_json::from_str(&fs::read_to_string(dir.path().join("summary.json")).unwrap()).unwrap();
    assert!(s["controller"].as_str().unwrap().contains("[2.0, 2.0, 0.0, -0.5, 0.0, 1.0]"), "{s}");
    let terms: f64 = ["return_depth", "return_force", "return_moment", "return_bonus", "return_failure"].iter().map(|k| s[*k].as_f64().unwrap()).sum();
    assert!((terms - s["mean_return"].as_f64().unwrap()).abs() < 1e-9, "{s}");
    // Depth in metres: about 1 per 50-step episode of 30 mm, not 80.
    assert!(s["return_depth"].as_f64().unwrap() > -2.0, "{s}");
    let trace = fs::read_to_string(dir.path().join("trace.csv")).unwrap();
    assert!(trace.lines().nth(2).unwrap().contains(",2,2,0,-0.5,0,1,"), "the trace records the action");

    let run = |action: &str| lcrl().args(["sim", "--env", "peg-group1", "--episodes", "1", "--action", action, "--out"]).arg(dir.path()).output().unwrap();
    assert_clean_failure(&run("1,2,3,4,5"), "5 components");
    assert_clean_failure(&run("3,0,0,0,0,0"), "outside the action box");
    assert_clean_failure(&run("0,0,nan,0,0,0"), "finite");
}

/// `lcrl tune` on a linear system (fast): best_constant.json holds the bar
/// with its figures, the search never ends below a = 0 on its own starts,
/// and `lcrl sim --action` reproduces the reported return exactly.
#[test]
fn tune_writes_the_bar_that_sim_reproduces() {
    let dir = tempfile::tempdir().unwrap();
    let out = lcrl()
        .args(["tune", "--env", "lti-paper", "--episodes", "4", "--evaluations", "24", "--eval-episodes", "5", "--eval-seed", "3", "--out"])
        .arg(dir.path())
        .output()
        .unwrap();
    assert!(out.status.success(), "{}", String::from_utf8_lossy(&out.stderr));
    let bar: Value = serde_json::from_str(&fs::read_to_string(dir.path().join("best_constant.json")).unwrap()).unwrap();
    for key in ["action", "mean_return", "success_rate", "mean_peak_force_n", "return_depth", "zero_action", "evaluations", "method"] {
        assert!(bar.get(key).is_some(), "best_constant.json lacks {key}: {bar}");
    }
    assert!(bar["best"]["tuning_return"].as_f64().unwrap() >= bar["zero_action"]["tuning_return"].as_f64().unwrap());
    let action: Vec<String> = bar["action"].as_array().unwrap().iter().map(|a| format!("{}", a.as_f64().unwrap())).collect();
    let sim = dir.path().join("sim");
    let out = lcrl()
        .args(["sim", "--env", "lti-paper", "--episodes", "5", "--seed", "3"])
        .arg(format!("--action={}", action.join(",")))
        .arg("--out")
        .arg(&sim)
        .output()
        .unwrap();
    assert!(out.status.success(), "{}", String::from_utf8_lossy(&out.stderr));
    let s: Value = serde_json::from_str(&fs::read_to_string(sim.join("summary.json")).unwrap()).unwrap();
    assert_eq!(s["mean_return"], bar["mean_return"]);

    let out = lcrl().args(["tune", "--env", "lti-paper", "--evaluations", "1", "--out"]).arg(dir.path()).output().unwrap();
    assert_clean_failure(&out, "--evaluations");
}

/// A checkpoint is data, never an address: one whose checkpoint.json names
/// a served environment is refused with a clear message, nothing connects
/// to that address (no token leaves), and the address is not echoed.
#[test]
fn a_checkpoint_never_chooses_where_lcrl_connects() {
    let dir = tempfile::tempdir().unwrap();
    let run = dir.path().join("run");
    let trained = lcrl().args(["train", "--env", "lti-paper", "--algo", "ddpg", "--connection", "global", "--episodes", "2", "--run-dir"]).arg(&run).output().unwrap();
    assert!(trained.status.success(), "{}", String::from_utf8_lossy(&trained.stderr));
    let trap = std::net::TcpListener::bind("127.0.0.1:0").unwrap();
    trap.set_nonblocking(true).unwrap();
    let address = format!("grpc://{}", trap.local_addr().unwrap());
    let mut checkpoints: Vec<_> = fs::read_dir(run.join("checkpoints")).unwrap().flatten().map(|e| e.path()).collect();
    checkpoints.extend(Some(run.join("selected")).filter(|s| s.join("checkpoint.json").is_file()));
    for folder in &checkpoints {
        let path = folder.join("checkpoint.json");
        let mut meta: Value = serde_json::from_str(&fs::read_to_string(&path).unwrap()).unwrap();
        meta["env"] = Value::String(address.clone());
        fs::write(&path, serde_json::to_string(&meta).unwrap()).unwrap();
    }
    let token = dir.path().join("token");
    fs::write(&token, "0123456789abcdef0123456789abcdef\n").unwrap();
    for args in [vec!["sim", "--episodes", "1", "--out", dir.path().join("sim").to_str().unwrap(), "--checkpoint"], vec!["export", "--out", dir.path().join("p.pt").to_str().unwrap()]] {
        let out = lcrl().args(&args).arg(&run).env("LCRL_TOKEN_FILE", &token).output().unwrap();
        assert_clean_failure(&out, "a file never chooses where lcrl connects");
        let said = String::from_utf8_lossy(&out.stderr);
        assert!(!said.contains(&address[7..]), "the address was echoed: {said}");
        assert!(trap.accept().is_err(), "{args:?} connected to the address the checkpoint named");
    }
}

/// A long command is never silent where stderr is a log or a pipe: `lcrl
/// tune`'s first line of progress comes before its first candidate is
/// evaluated (0 of them done), and more follow as it works.
#[test]
fn tune_shows_progress_at_once_in_a_log() {
    use std::io::BufRead;
    let dir = tempfile::tempdir().unwrap();
    let mut child = lcrl()
        .args(["tune", "--env", "peg-group1", "--evaluations", "40", "--out"])
        .arg(dir.path())
        .stdout(std::process::Stdio::null())
        .stderr(std::process::Stdio::piped())
        .spawn()
        .unwrap();
    let mut lines = std::io::BufReader::new(child.stderr.take().unwrap()).lines();
    let first = lines.next().unwrap().unwrap();
    assert!(first.starts_with("candidates [") && first.contains(" 0/40"), "{first}");
    let rest: Vec<String> = lines.map_while(Result::ok).collect();
    assert!(child.wait().unwrap().success(), "{rest:?}");
    assert!(dir.path().join("best_constant.json").is_file());
}
