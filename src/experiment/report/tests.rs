//! The report's cells, bars and comparisons on hand-made study folders.

use super::super::config::Experiment;
use super::super::plan::{cells, run_dir};
use super::super::study::fixtures::{write_best_constant, write_run};
use super::*;

/// The bar counts of a hand-made study: a run beats the best constant
/// only when strictly above it on the same starts, diverges when below
/// a = 0 (its own, else the best constant file's on the same starts),
/// and a cell with a run evaluated elsewhere gets no beat count at all.
#[test]
fn bar_counts_follow_the_runs_on_the_same_starts() {
    let text = "name = \"bars\"\nenvironments = [\"lti-paper\"]\nalgorithms = [\"ppo\"]\nconnections = [\"local@0.1\", \"global\"]\nseeds = 3\nepisodes = { ppo = 2 }\n";
    let e = Experiment::parse(text).unwrap();
    let tmp = tempfile::tempdir().unwrap();
    let out = tmp.path();
    write_best_constant(out, "lti-paper", -5.0, -8.0);
    let cell = |i: usize| cells(&e)[i].clone();
    let (local, global) = (cell(0), cell(1));
    write_run(&run_dir(out, &local, 0), "local", 0, -4.0, Some(0), Some(-8.0)); // beats
    write_run(&run_dir(out, &local, 1), "local", 1, -9.0, Some(0), Some(-8.0)); // diverged
    write_run(&run_dir(out, &local, 2), "local", 2, -5.0, Some(0), Some(-8.0)); // a tie: does not beat
    write_run(&run_dir(out, &global, 0), "global", 0, -9.0, Some(0), None); // diverged by the file's a = 0
    write_run(&run_dir(out, &global, 1), "global", 1, -6.0, Some(1 << 42), Some(-6.5)); // other starts
    // global seed 2 never finished.

    let report = gather(&e, out).unwrap().report();
    let (l, g) = (&report.cells[0], &report.cells[1]);
    assert_eq!((l.connection.as_str(), l.beat_best_constant, l.diverged), ("local@0.1", Some(1), 1));
    let per_seed: Vec<(Option<bool>, bool)> = l.per_seed.iter().map(|s| (s.beats_best_constant, s.diverged)).collect();
    assert_eq!(per_seed, [(Some(true), false), (Some(false), true), (Some(false), false)]);
    assert_eq!((g.connection.as_str(), g.beat_best_constant, g.diverged), ("global", None, 1));
    assert_eq!(g.per_seed.iter().map(|s| s.beats_best_constant).collect::<Vec<_>>(), [Some(false), None]);
    assert_eq!(report.missing_runs, ["lti-paper/ppo/global seed 2"]);

    let md = markdown(&report);
    let row = |label: &str| md.lines().find(|l| l.starts_with(&format!("| {label} |"))).unwrap().to_string();
    assert!(row("local@0.1").contains("| 1 of 3 | 1 of 3 |"), "{md}");
    assert!(row("global").contains("| — | 1 of 2 |"), "{md}");
    let json: serde_json::Value = serde_json::to_value(&report).unwrap();
    assert_eq!(json["cells"][0]["beat_best_constant"], 1);
    assert_eq!(json["cells"][1]["beat_best_constant"], serde_json::Value::Null);
}

/// Which cells are compared: every cell with a graph against global
/// and full-subnets, and a given graph against a random one (does the
/// structure matter, or only the count?); never two measured graphs.
#[test]
fn comparisons_pair_graphs_with_global_and_given_with_random() {
    let tmp = tempfile::tempdir().unwrap();
    let out = tmp.path();
    let given = out.join("g.json");
    let env = lcrl_sim::make_env("lti-paper").unwrap();
    lcrl_graph_builder::given::random(env.spec(), 4, 1).unwrap().write_json(&given).unwrap();
    let text = format!(
        "name = \"c\"\nenvironments = [\"lti-paper\"]\nalgorithms = [\"ppo\"]\nconnections = [\"local@0.1\", \"graph:{}\", \"random@4\", \"global\", \"global+match=local@0.1\"]\nseeds = 2\nepisodes = {{ ppo = 2 }}\n",
        given.display()
    );
    let e = Experiment::parse(&text).unwrap();
    for (k, cell) in cells(&e).iter().enumerate() {
        for seed in 0..2 {
            write_run(&run_dir(out, cell, seed), "local", seed, -4.0 - k as f64 - seed as f64 * 0.5, Some(0), None);
        }
    }
    let report = gather(&e, out).unwrap().report();
    let mut pairs: Vec<(String, String)> = report.comparisons.iter().filter(|c| c.metric == "eval_return").map(|c| (c.a.clone(), c.b.clone())).collect();
    pairs.sort();
    let graph = format!("graph:{}", given.display());
    let mut expected = vec![
        (graph.clone(), "global".to_string()),
        (graph, "random@4".to_string()),
        ("local@0.1".to_string(), "global".to_string()),
        // A matched global meets the one cell it is sized to.
        ("local@0.1".to_string(), "global+match=local@0.1".to_string()),
        ("local@0.1".to_string(), "random@4".to_string()),
        ("random@4".to_string(), "global".to_string()),
    ];
    expected.sort();
    assert_eq!(pairs, expected);
}
