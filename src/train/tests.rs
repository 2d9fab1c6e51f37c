//! `lcrl train`'s wiring driven in this process: no binary started.

use std::path::Path;

use clap::Parser;

use super::{run, TrainArgs};

const TINY: &str = "[network]\nglobal_hidden = [16, 16]\nsubnet_hidden = [8, 8]\ncritic_hidden = [16, 16]\n\
[ddpg]\nwarmup_steps = 20\nbatch_size = 16\n[run]\nepisodes = 3\ncheckpoint_every = 1\neval_episodes = 2\ngraph_samples = 16\n";

#[derive(clap::Parser)]
struct Cli {
    #[command(flatten)]
    train: TrainArgs,
}

/// `lcrl train` of DDPG on lti-paper with the tiny settings, parsed as the
/// binary parses it.
fn args(work: &Path, run_dir: &Path, extra: &[&str]) -> TrainArgs {
    let config = work.join("tiny.toml");
    std::fs::write(&config, TINY).unwrap();
    let (config, run_dir) = (config.to_str().unwrap().to_string(), run_dir.to_str().unwrap().to_string());
    let line = ["lcrl-train", "--env", "lti-paper", "--algo", "ddpg", "--config", &config, "--run-dir", &run_dir].into_iter().chain(extra.iter().copied());
    Cli::try_parse_from(line).expect("the test's command line parses").train
}

fn json(path: &Path) -> serde_json::Value {
    serde_json::from_str(&std::fs::read_to_string(path).unwrap_or_else(|e| panic!("{}: {e}", path.display()))).unwrap()
}

/// The steps end to end: settings with the command line's overrides, the
/// graph, training, the evaluation the command line asked for, the record.
#[test]
fn a_local_run_writes_its_record_with_the_evaluation_asked_for() {
    let work = tempfile::tempdir().unwrap();
    let dir = work.path().join("run");
    run(&args(work.path(), &dir, &["--connection", "local", "--episodes", "2", "--eval-episodes", "3", "--eval-seed", "11"])).expect("a tiny run trains");
    let summary = json(&dir.join("summary.json"));
    assert_eq!(summary["episodes"].as_u64(), Some(2), "{summary}");
    assert_eq!((summary["eval_episodes"].as_u64(), summary["eval_seed"].as_u64()), (Some(3), Some(11)), "{summary}");
    let rows = std::fs::read_to_string(dir.join("metrics.csv")).unwrap().lines().count();
    assert_eq!(rows, 1 + 2, "metrics.csv: a header and one row per episode");
    for file in ["graph.json", "reward_curve.png", "config.toml"] {
        assert!(dir.join(file).is_file(), "{file} is missing");
    }
}

/// A study's controls and a matched size without a global actor are
/// refused with the way to do it by hand, and nothing is trained.
#[test]
fn what_one_run_cannot_do_is_refused_before_training() {
    let work = tempfile::tempdir().unwrap();
    let graph = work.path().join("graph.json");
    let graph_arg = graph.to_str().unwrap().to_string();
    for (extra, needle) in [
        (vec!["--connection", "random-rows@local@0.5"], "lcrl graph --env ENV --random-rows"),
        (vec!["--connection", "local@1+per-seed"], "lcrl graph --threshold T"),
        (vec!["--connection", "local", "--match-params", &graph_arg], "--match-params sizes a global actor"),
        (vec!["--connection", "global+match=local@1"], "--connection global --match-params graph.json"),
        (vec!["--connection", "global", "--graph", &graph_arg], "--graph only applies"),
    ] {
        let dir = work.path().join("refused");
        let err = run(&args(work.path(), &dir, &extra)).expect_err(&format!("{extra:?} was accepted"));
        assert!(format!("{err:#}").contains(needle), "{extra:?}: {err:#}");
        assert!(!dir.join("summary.json").exists() && !dir.join("metrics.csv").exists(), "{extra:?}: a refused run trained");
    }
}

#[test]
fn evaluation_episodes_out_of_range_are_refused_by_the_parser() {
    let err = Cli::try_parse_from(["lcrl-train", "--env", "lti-paper", "--algo", "ddpg", "--eval-episodes", "0"]).err().expect("--eval-episodes 0 was accepted");
    assert!(err.to_string().contains("--eval-episodes"), "{err}");
}
