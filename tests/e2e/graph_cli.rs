//! `lcrl graph` as a user runs it.

use std::fs;

use serde_json::Value;

use super::common::{assert_clean_failure, lcrl, stdout};

fn graph_json(dir: &tempfile::TempDir, name: &str, extra: &[&str]) -> Value {
    let path = dir.path().join(name);
    let out = lcrl()
        .args(["graph", "--env", "lti-paper", "--samples", "64", "--seed", "4", "--out"])
        .arg(&path)
        .args(extra)
        .output()
        .unwrap();
    assert!(out.status.success(), "{}", String::from_utf8_lossy(&out.stderr));
    serde_json::from_str(&fs::read_to_string(&path).unwrap()).unwrap()
}

#[test]
fn prints_table_and_writes_json_and_heatmap() {
    let dir = tempfile::tempdir().unwrap();
    let (json, png) = (dir.path().join("g.json"), dir.path().join("g.png"));
    let out = lcrl()
        .args(["graph", "--env", "lti-paper", "--samples", "32", "--out"])
        .arg(&json)
        .arg("--plot")
        .arg(&png)
        .output()
        .unwrap();
    assert!(out.status.success(), "{}", String::from_utf8_lossy(&out.stderr));
    let table = stdout(&out);
    assert!(table.contains("a2") && table.contains("s3") && table.contains("a1 [1, 0, 0]"), "{table}");
    assert!(table.contains("a2 [1, 1, 0]") && table.contains("a3 [0, 0, 1]"), "{table}");

    let v: Value = serde_json::from_str(&fs::read_to_string(&json).unwrap()).unwrap();
    for key in ["env", "state_names", "action_names", "samples", "threshold", "seed", "phi", "phi_normalized", "g", "stability", "elapsed_s"] {
        assert!(v.get(key).is_some(), "graph.json lacks {key}");
    }
    assert_eq!(v["g"], serde_json::json!([[1, 0, 0], [1, 1, 0], [0, 0, 1]]));
    assert_eq!(v["threshold"], serde_json::json!(0.1));
    assert_eq!(v["samples"], serde_json::json!(32));
    let column_sum: f64 = (0..3).map(|i| v["phi_normalized"][i][1].as_f64().unwrap()).sum();
    assert!((column_sum - 1.0).abs() < 1e-12);

    let bytes = fs::read(&png).unwrap();
    assert!(bytes.starts_with(b"\x89PNG") && bytes.len() > 2000, "not a real PNG");
    // No temporary files left next to the outputs.
    assert_eq!(fs::read_dir(dir.path()).unwrap().count(), 2);
}

#[test]
fn same_seed_one_or_two_threads_identical_phi() {
    let dir = tempfile::tempdir().unwrap();
    let one = graph_json(&dir, "one.json", &["--threads", "1"]);
    let two = graph_json(&dir, "two.json", &["--threads", "2"]);
    assert_eq!(one["phi"], two["phi"]);
    assert_eq!(one["stability"], two["stability"]);
}

#[test]
fn exact_mode_gives_the_lemma1_graph() {
    let dir = tempfile::tempdir().unwrap();
    let v = graph_json(&dir, "exact.json", &["--exact"]);
    assert_eq!(v["g"], serde_json::json!([[1, 0, 0], [1, 1, 0], [0, 0, 1]]));
    assert_eq!(v["exact"], serde_json::json!(true));
    assert_eq!(v["threshold"], Value::Null);
}

#[test]
fn lti_file_is_loaded() {
    let dir = tempfile::tempdir().unwrap();
    let file = dir.path().join("chain.toml");
    // s1' = s2, s2' = a1: a1 reaches s1 one step later; a2 moves nothing.
    fs::write(&file, "kind = \"lti\"\ne = [[0.0, 1.0], [0.0, 0.0]]\nf = [[0.0, 0.0], [1.0, 0.0]]\n").unwrap();
    let out = lcrl().args(["graph", "--samples", "16", "--exact", "--env"]).arg(&file).output().unwrap();
    assert!(out.status.success(), "{}", String::from_utf8_lossy(&out.stderr));
    let table = stdout(&out);
    assert!(table.contains("a1 [1, 1]") && table.contains("a2 [0, 0]"), "{table}");
}

#[test]
fn bad_input_fails_with_one_clear_line() {
    let dir = tempfile::tempdir().unwrap();
    let run = |args: &[&str]| lcrl().arg("graph").args(args).output().unwrap();
    assert_clean_failure(&run(&["--env", "no-such-env"]), "unknown environment 'no-such-env'");
    assert_clean_failure(&run(&["--env", "lti-paper", "--samples", "0"]), "expected 1 to 100000000");
    assert_clean_failure(&run(&["--env", "lti-paper", "--threshold", "0"]), "--threshold");
    assert_clean_failure(&run(&["--env", "lti-paper", "--threshold", "-0.5"]), "--threshold");
    assert_clean_failure(&run(&["--env", "lti-paper", "--threshold", "NaN"]), "--threshold");
    assert_clean_failure(&run(&["--env", "lti-paper", "--out", "/nonexistent-dir/g.json"]), "/nonexistent-dir/g.json");

    let bad = dir.path().join("bad.toml");
    fs::write(&bad, "kind = \"lti\"\ne = [[1.0, 0.0], [0.0]]\nf = [[1.0], [1.0]]\n").unwrap();
    assert_clean_failure(&run(&["--env", bad.to_str().unwrap()]), "`e`");
    fs::write(&bad, "kind = \"lti\"\ne = [[1.0]\n").unwrap();
    assert_clean_failure(&run(&["--env", bad.to_str().unwrap()]), "bad.toml");
}

#[test]
fn failed_run_keeps_an_existing_output_file() {
    let dir = tempfile::tempdir().unwrap();
    let json = dir.path().join("g.json");
    fs::write(&json, "previous result").unwrap();
    let out = lcrl().args(["graph", "--env", "no-such-env", "--out"]).arg(&json).output().unwrap();
    assert!(!out.status.success());
    assert_eq!(fs::read_to_string(&json).unwrap(), "previous result");
}

#[test]
fn threshold_sweep_lists_each_g_its_edges_flips_and_margins() {
    let dir = tempfile::tempdir().unwrap();
    let (json, png) = (dir.path().join("g.json"), dir.path().join("g.png"));
    let out = lcrl()
        .args(["graph", "--env", "lti-paper", "--samples", "32", "--thresholds", "0.1,0.6,2.0", "--out"])
        .arg(&json)
        .arg("--plot")
        .arg(&png)
        .output()
        .unwrap();
    assert!(out.status.success(), "{}", String::from_utf8_lossy(&out.stderr));
    let text = stdout(&out);
    let v: Value = serde_json::from_str(&fs::read_to_string(&json).unwrap()).unwrap();
    // The first T is the graph's own.
    assert_eq!(v["threshold"], serde_json::json!(0.1));
    assert_eq!(v["start"], serde_json::json!("reset"));
    let sweep = v["sweep"].as_array().unwrap();
    assert_eq!(sweep.len(), 3);
    for entry in sweep {
        let g = entry["g"].as_array().unwrap();
        let ones = g.iter().flat_map(|r| r.as_array().unwrap()).filter(|x| x.as_u64() == Some(1)).count();
        assert_eq!(entry["edges"].as_u64().unwrap() as usize, ones);
        assert!(text.contains(&format!("T = {}: {ones} of 9 edges", entry["threshold"].as_f64().unwrap())), "{text}");
    }
    assert_eq!(sweep[0]["g"], v["g"]);
    // Edges only disappear as T grows, and each kept edge's margin is ≥ 1
    // while each dropped one's is < 1.
    let e: Vec<u64> = sweep.iter().map(|s| s["edges"].as_u64().unwrap()).collect();
    assert!(e[0] >= e[1] && e[1] >= e[2], "{e:?}");
    for entry in sweep {
        for i in 0..3 {
            for j in 0..3 {
                let (g, margin) = (entry["g"][i][j].as_u64().unwrap(), entry["margin"][i][j].as_f64().unwrap());
                assert_eq!(g == 1, margin >= 1.0, "T {}: ({i},{j}) margin {margin}", entry["threshold"]);
            }
        }
    }
    if e[0] != e[1] {
        assert!(text.contains("flips from T = 0.1 to T = 0.6: -a"), "{text}");
    }
    assert!(text.contains("margin of each kept edge"), "{text}");
    let bytes = fs::read(&png).unwrap();
    assert!(bytes.starts_with(b"\x89PNG"));
}

#[test]
fn trajectory_start_on_a_linear_system_keeps_lemma1_and_bad_sweeps_fail() {
    let dir = tempfile::tempdir().unwrap();
    let v = graph_json(&dir, "t.json", &["--start", "trajectory"]);
    assert_eq!(v["start"], serde_json::json!("trajectory"));
    // Lemma 1 does not depend on s_0: the graph is the same.
    assert_eq!(v["g"], serde_json::json!([[1, 0, 0], [1, 1, 0], [0, 0, 1]]));
    let out = lcrl().args(["graph", "--env", "lti-paper", "--thresholds", "0.1,-1"]).output().unwrap();
    assert_clean_failure(&out, "--threshold must be a finite number above 0");
}

/// `--choose-t` prints T_rule with its reason and the table, writes the
/// same choice as JSON, and refuses a threshold beside it. On lti-blocks-8
/// (G known, Lemma 1) the rule keeps Lemma 1's 3 inputs an action, 24
/// edges on every seed, and no moved state unseen (the graph itself is
/// checked entry by entry in graph-builder/src/tests.rs).
#[test]
fn choose_t_prints_t_rule_and_why() {
    let dir = tempfile::tempdir().unwrap();
    let json = dir.path().join("choice.json");
    let out = lcrl().args(["graph", "--env", "lti-blocks-8", "--samples", "16", "--choose-t", "--choose-seeds", "3", "--out"]).arg(&json).output().unwrap();
    assert!(out.status.success(), "{}", String::from_utf8_lossy(&out.stderr));
    let text = stdout(&out);
    let v: Value = serde_json::from_str(&fs::read_to_string(&json).unwrap()).unwrap();
    assert_eq!(v["seeds"], serde_json::json!([0, 1, 2]));
    assert_eq!(v["candidates"].as_array().unwrap().len(), 20);
    assert_eq!(v["chosen"].as_f64(), Some(1.0));
    assert_eq!(v["row_edges"], serde_json::json!([3, 3, 3, 3, 3, 3, 3, 3]));
    assert!(text.contains("T_rule = 1 (the publication's T = 0.1): the above-average rule"), "{text}");
    assert!(text.contains("Inputs per action at T_rule (seed 0): a1 3, a2 3"), "{text}");
    let at_rule = v["candidates"].as_array().unwrap().iter().find(|c| c["threshold"].as_f64() == Some(1.0)).unwrap();
    assert_eq!((at_rule["edges"].clone(), at_rule["unseen_states"].as_u64()), (serde_json::json!([24, 24, 24]), Some(0)));
    let both = lcrl().args(["graph", "--env", "lti-paper", "--choose-t", "--threshold", "1"]).output().unwrap();
    assert_clean_failure(&both, "cannot be used with");
    // The graph at T_rule, from the command line, is Lemma 1's entry by
    // entry on the smallest and largest sizes the rule is held to: a_k sees
    // x_k, y_k and its partner's x.
    for n in [8usize, 32] {
        let g = dir.path().join(format!("g{n}.json"));
        let out = lcrl().args(["graph", "--env", &format!("lti-blocks-{n}"), "--samples", "16", "--threshold", "1", "--out"]).arg(&g).output().unwrap();
        assert!(out.status.success(), "{}", String::from_utf8_lossy(&out.stderr));
        let v: Value = serde_json::from_str(&fs::read_to_string(&g).unwrap()).unwrap();
        let lemma1: Vec<Vec<u8>> = (0..n).map(|k| (0..2 * n).map(|j| u8::from(j == 2 * k || j == 2 * k + 1 || j == 2 * (k ^ 1))).collect()).collect();
        assert_eq!(v["g"], serde_json::json!(lemma1), "lti-blocks-{n}");
    }
}

/// `--random-rows GRAPH` keeps every action's number of inputs and draws
/// which states, by --seed.
#[test]
fn random_rows_keep_the_degrees_of_the_graph_they_come_from() {
    let dir = tempfile::tempdir().unwrap();
    let source = graph_json(&dir, "measured.json", &["--threshold", "0.5"]);
    let degrees = |g: &Value| g["g"].as_array().unwrap().iter().map(|row| row.as_array().unwrap().iter().filter(|e| e.as_u64() == Some(1)).count()).collect::<Vec<_>>();
    let draw = |seed: &str, name: &str| {
        let path = dir.path().join(name);
        let out = lcrl().args(["graph", "--env", "lti-paper", "--random-rows"]).arg(dir.path().join("measured.json")).args(["--seed", seed, "--out"]).arg(&path).output().unwrap();
        assert!(out.status.success(), "{}", String::from_utf8_lossy(&out.stderr));
        serde_json::from_str::<Value>(&fs::read_to_string(&path).unwrap()).unwrap()
    };
    let (a, again) = (draw("11", "a.json"), draw("11", "again.json"));
    assert_eq!(degrees(&a), degrees(&source));
    assert_eq!(a["g"], again["g"], "the same draw seed gives the same draw");
    assert!(a["origin"].as_str().unwrap().starts_with("random rows of degrees"), "{}", a["origin"]);
    let missing = lcrl().args(["graph", "--env", "lti-paper", "--random-rows"]).arg(dir.path().join("none.json")).output().unwrap();
    assert_clean_failure(&missing, "none.json");
}
