//! `lcrl train` and `lcrl sim --checkpoint` as a user runs them.

use std::fs;
use std::path::{Path, PathBuf};

use serde_json::Value;

use super::common::{assert_clean_failure, lcrl, stdout};

const TINY: &str = "[network]\nglobal_hidden = [16, 16]\nsubnet_hidden = [8, 8]\ncritic_hidden = [16, 16]\n\
[ddpg]\nwarmup_steps = 20\nbatch_size = 16\n[run]\nepisodes = 3\ncheckpoint_every = 1\neval_episodes = 2\ngraph_samples = 16\n";

/// TINY written into `work`, for `--config`.
fn tiny_config(work: &Path) -> PathBuf {
    let config = work.join("tiny.toml");
    fs::write(&config, TINY).unwrap();
    config
}

/// `lcrl train` of DDPG with the locally connected actor on lti-paper.
fn train(dir: &Path, config: &Path, extra: &[&str]) -> std::process::Output {
    train_connected("local", dir, config, extra)
}

fn train_connected(connection: &str, dir: &Path, config: &Path, extra: &[&str]) -> std::process::Output {
    lcrl()
        .args(["train", "--env", "lti-paper", "--algo", "ddpg", "--connection", connection, "--config"])
        .arg(config)
        .arg("--run-dir")
        .arg(dir)
        .args(extra)
        .output()
        .unwrap()
}

fn json(path: &Path) -> Value {
    serde_json::from_str(&fs::read_to_string(path).unwrap()).unwrap()
}

/// (step, value) of every `episode/return` scalar in the run's event files.
pub(super) fn tensorboard_returns(run: &Path) -> Vec<(i64, f32)> {
    let mut returns = Vec::new();
    for entry in fs::read_dir(run).unwrap() {
        let path = entry.unwrap().path();
        if path.file_name().unwrap().to_string_lossy().starts_with("events.out.tfevents.") {
            for event in lcrl_learner::run::tensorboard::read_events(&path).unwrap() {
                let values = event.summary.map(|s| s.value).unwrap_or_default();
                returns.extend(values.iter().filter(|v| v.tag == "episode/return").filter_map(|v| Some((event.step, v.simple_value?))));
            }
        }
    }
    returns.sort_by_key(|r| r.0);
    returns
}

/// metrics.csv without the wall-clock columns.
fn timeless_metrics(path: &Path) -> Vec<String> {
    fs::read_to_string(path).unwrap().lines().map(|l| l.split(',').take(6).collect::<Vec<_>>().join(",")).collect()
}

#[test]
fn train_writes_the_run_directory_resumes_and_evaluates() {
    let work = tempfile::tempdir().unwrap();
    let config = tiny_config(work.path());
    let run = work.path().join("run");
    let out = train(&run, &config, &[]);
    assert!(out.status.success(), "{}", String::from_utf8_lossy(&out.stderr));
    assert!(stdout(&out).contains("actor parameters"), "{}", stdout(&out));
    for file in ["config.toml", "graph.json", "metrics.csv", "summary.json", "reward_curve.png"] {
        assert!(run.join(file).is_file(), "{file} missing");
    }
    let summary = json(&run.join("summary.json"));
    for key in ["final_return", "episodes", "graph_seconds", "optimization_seconds", "total_seconds", "lqr_return"] {
        assert!(summary.get(key).is_some_and(|v| !v.is_null()), "summary.json lacks {key}");
    }
    assert_eq!(summary["episodes"], 3);
    assert_eq!(fs::read_to_string(run.join("metrics.csv")).unwrap().lines().count(), 4);
    let returns = tensorboard_returns(&run);
    assert_eq!(returns.len(), 3, "one TensorBoard return per episode");
    let csv_first: f64 = fs::read_to_string(run.join("metrics.csv")).unwrap().lines().nth(1).unwrap().split(',').nth(1).unwrap().parse().unwrap();
    assert_eq!(returns[0], (1, csv_first as f32), "TensorBoard and metrics.csv agree");
    let checkpoint = run.join("checkpoints/ep000003");
    for file in ["actor.safetensors", "critic.safetensors", "actor_target.safetensors", "actor_optimizer.safetensors", "replay.safetensors", "checkpoint.json"] {
        assert!(checkpoint.join(file).is_file(), "checkpoint lacks {file}");
    }

    // Running again into the same directory needs --resume.
    assert_clean_failure(&train(&run, &config, &[]), "--resume");
    let out = train(&run, &config, &["--resume", "--episodes", "5"]);
    assert!(out.status.success(), "{}", String::from_utf8_lossy(&out.stderr));
    assert_eq!(json(&run.join("summary.json"))["episodes"], 5);
    assert_eq!(fs::read_to_string(run.join("metrics.csv")).unwrap().lines().count(), 6);

    // The trained policy, evaluated with the same outputs as the constant controller.
    let sim = work.path().join("sim");
    let out = lcrl().args(["sim", "--episodes", "2", "--checkpoint"]).arg(&run).arg("--out").arg(&sim).output().unwrap();
    assert!(out.status.success(), "{}", String::from_utf8_lossy(&out.stderr));
    let summary = json(&sim.join("summary.json"));
    assert!(summary["controller"].as_str().unwrap().contains("ddpg/local"), "{summary}");
    assert!(sim.join("trace.csv").is_file() && sim.join("trace.png").is_file());
    // A checkpoint does not fit another environment.
    let out = lcrl().args(["sim", "--env", "peg-group1", "--checkpoint"]).arg(&run).arg("--out").arg(&sim).output().unwrap();
    assert_clean_failure(&out, "peg-group1");
}

#[test]
fn same_seed_one_thread_gives_identical_metrics() {
    let work = tempfile::tempdir().unwrap();
    let config = tiny_config(work.path());
    let (a, b) = (work.path().join("a"), work.path().join("b"));
    for dir in [&a, &b] {
        let out = train(dir, &config, &["--seed", "3", "--threads", "1"]);
        assert!(out.status.success(), "{}", String::from_utf8_lossy(&out.stderr));
    }
    assert_eq!(timeless_metrics(&a.join("metrics.csv")), timeless_metrics(&b.join("metrics.csv")));
}

/// `lcrl compare`: Table II's time split for each run, the reward curves in
/// one PNG, and clear refusals before any work for a plot name that is not
/// .png or a directory that holds no finished run.
#[test]
fn compare_tabulates_runs_and_refuses_bad_paths() {
    let work = tempfile::tempdir().unwrap();
    let config = tiny_config(work.path());
    let (local, global) = (work.path().join("local"), work.path().join("global"));
    for out in [train(&local, &config, &[]), train_connected("global", &global, &config, &[])] {
        assert!(out.status.success(), "{}", String::from_utf8_lossy(&out.stderr));
    }

    let plot = work.path().join("curves.png");
    let out = lcrl().arg("compare").arg(&local).arg(&global).arg("--out").arg(&plot).output().unwrap();
    assert!(out.status.success(), "{}", String::from_utf8_lossy(&out.stderr));
    let table = stdout(&out);
    // Each run's row carries its own summary.json figures (Table II columns).
    for (label, dir) in [("ddpg/local", &local), ("ddpg/global", &global)] {
        let summary = json(&dir.join("summary.json"));
        let row = table.lines().find(|l| l.starts_with(label)).unwrap_or_else(|| panic!("no {label} row in {table}"));
        let cells: Vec<&str> = row.rsplit(')').next().unwrap().split_whitespace().collect();
        let expected: Vec<String> = ["graph_seconds", "optimization_seconds", "total_seconds"].iter().map(|k| format!("{:.2}", summary[*k].as_f64().unwrap())).collect();
        assert_eq!(cells[0], "3", "{row}");
        assert_eq!(&cells[1..4], &expected[..], "{row}");
    }
    assert_eq!(&fs::read(&plot).unwrap()[1..4], b"PNG");

    // The bar of `lcrl tune` beside the runs: a row and a line.
    let bar = work.path().join("tune");
    let out = lcrl().args(["tune", "--env", "lti-paper", "--episodes", "2", "--evaluations", "8", "--eval-episodes", "2", "--out"]).arg(&bar).output().unwrap();
    assert!(out.status.success(), "{}", String::from_utf8_lossy(&out.stderr));
    let bar = bar.join("best_constant.json");
    let out = lcrl().arg("compare").arg(&local).arg(&global).arg("--best-constant").arg(&bar).arg("--out").arg(&plot).output().unwrap();
    assert!(out.status.success(), "{}", String::from_utf8_lossy(&out.stderr));
    let mean = json(&bar)["mean_return"].as_f64().unwrap();
    assert!(stdout(&out).lines().any(|l| l.starts_with("best constant") && l.contains(&format!("{mean:.3}"))), "{}", stdout(&out));
    // One set of starts: the runs (evaluated on their own held-out starts)
    // are evaluated again on the best constant's, as `lcrl sim` does there.
    assert!(stdout(&out).contains("every row evaluated on the same 2 starts (seeds 0 on"), "{}", stdout(&out));
    assert!(String::from_utf8_lossy(&out.stderr).contains("evaluated again on the common starts"), "{}", String::from_utf8_lossy(&out.stderr));
    let sim_dir = work.path().join("sim-local");
    let sim = lcrl().args(["sim", "--episodes", "2", "--seed", "0", "--out"]).arg(&sim_dir).arg("--checkpoint").arg(&local).output().unwrap();
    assert!(sim.status.success(), "{}", String::from_utf8_lossy(&sim.stderr));
    let on_bar_starts = json(&sim_dir.join("summary.json"))["mean_return"].as_f64().unwrap();
    let row = stdout(&out).lines().find(|l| l.starts_with("ddpg/local")).unwrap().to_string();
    assert!(row.contains(&format!("{on_bar_starts:.3}")), "{row} against lcrl sim's {on_bar_starts:.3}");
    let mut other = json(&bar);
    other["env"] = Value::from("peg-group1");
    let other_path = work.path().join("other.json");
    fs::write(&other_path, other.to_string()).unwrap();
    let out = lcrl().arg("compare").arg(&local).arg("--best-constant").arg(&other_path).arg("--out").arg(&plot).output().unwrap();
    assert_clean_failure(&out, "best constant is for peg-group1");

    let out = lcrl().arg("compare").arg(&local).arg("--out").arg(work.path().join("curves")).output().unwrap();
    assert_clean_failure(&out, ".png");
    let out = lcrl().arg("compare").arg(&local).arg(work.path()).arg("--out").arg(&plot).output().unwrap();
    assert_clean_failure(&out, "not a finished run");
    let out = lcrl().args(["graph", "--env", "lti-paper", "--samples", "8", "--plot", "g.svg"]).output().unwrap();
    assert_clean_failure(&out, ".png");
}

#[test]
fn bad_input_fails_cleanly() {
    let work = tempfile::tempdir().unwrap();
    let config = tiny_config(work.path());
    let bad = work.path().join("bad.toml");
    fs::write(&bad, "[ddpg]\nactor_lr = -0.001\n").unwrap();
    assert_clean_failure(&train(&work.path().join("r1"), &bad, &[]), "ddpg.actor_lr");

    let out = lcrl().args(["train", "--env", "lti-paper", "--algo", "sac", "--connection", "local"]).output().unwrap();
    assert_clean_failure(&out, "sac");
    // The largest u64 seed cannot be recorded in config.toml: said so, before any work.
    let out = lcrl().args(["train", "--env", "lti-paper", "--algo", "ddpg", "--seed", "18446744073709551615", "--run-dir"]).arg(work.path().join("r0")).output().unwrap();
    assert_clean_failure(&out, "`run.seed (--seed)` must be at most 9223372036854775807");
    assert!(!work.path().join("r0").join("metrics.csv").exists());

    // A graph of lti-paper (3×3) used for peg-group1 (6 actions × 12 states).
    let graph = work.path().join("graph.json");
    let out = lcrl().args(["graph", "--env", "lti-paper", "--samples", "8", "--out"]).arg(&graph).output().unwrap();
    assert!(out.status.success());
    let out = lcrl()
        .args(["train", "--env", "peg-group1", "--algo", "ddpg", "--connection", "local", "--config"])
        .arg(&config)
        .arg("--graph")
        .arg(&graph)
        .arg("--run-dir")
        .arg(work.path().join("r2"))
        .output()
        .unwrap();
    assert_clean_failure(&out, "3×3");

    let out = lcrl()
        .args(["train", "--env", "lti-paper", "--algo", "ppo", "--connection", "global", "--graph"])
        .arg(&graph)
        .output()
        .unwrap();
    assert_clean_failure(&out, "--graph only applies");

    // Options measured not to help were removed (docs/peg.md, "Measured
    // and removed"): a config naming one is refused before anything runs.
    let removed = work.path().join("removed.toml");
    for (text, key) in [("[run]\nfallback_margin = 2.0\n", "fallback_margin"), ("[ddpg]\nwarmup_actions = \"policy\"\n", "warmup_actions"), ("[ddpg]\ncritic_disagreement = 1.0\n", "critic_disagreement"), ("[ddpg]\nactor_lr_warmup_updates = 10\n", "actor_lr_warmup_updates")] {
        fs::write(&removed, text).unwrap();
        assert_clean_failure(&train(&work.path().join("r4"), &removed, &[]), key);
        assert!(!work.path().join("r4").exists(), "a refused run leaves no folder");
    }
}

/// `--match-params`: a global actor sized to the local actor of a graph
/// has its parameter count (within the step of one width), records the
/// widths it got, and is refused with any other connection.
#[test]
fn matched_global_has_the_local_actors_parameter_count() {
    let work = tempfile::tempdir().unwrap();
    let config = tiny_config(work.path());
    let local = work.path().join("local");
    let out = train(&local, &config, &[]);
    assert!(out.status.success(), "{}", String::from_utf8_lossy(&out.stderr));
    let graph = local.join("graph.json");
    let matched = work.path().join("matched");
    let out = train_connected("global", &matched, &config, &["--match-params", graph.to_str().unwrap()]);
    assert!(out.status.success(), "{}", String::from_utf8_lossy(&out.stderr));
    assert!(String::from_utf8_lossy(&out.stderr).contains("global actor matched to the local actor of"));
    let (local_params, matched_params) = (json(&local.join("summary.json"))["actor_params"].as_f64().unwrap(), json(&matched.join("summary.json"))["actor_params"].as_f64().unwrap());
    // lti-paper (3 states, 3 actions), subnetworks [8, 8]: a global [w, w]
    // actor gains 2w + 9 parameters a width, so the nearest width lands
    // within half of that (w ≈ 14: 19) of the local count.
    assert!((matched_params - local_params).abs() <= 20.0, "matched {matched_params} against local {local_params}");
    let stderr = String::from_utf8_lossy(&out.stderr).to_string();
    let width = stderr.split("hidden [").nth(1).and_then(|rest| rest.split(',').next()).unwrap().to_string();
    assert_ne!(width, "16", "the widths were not changed: {stderr}");
    let recorded = fs::read_to_string(matched.join("config.toml")).unwrap();
    assert!(recorded.contains(&format!("global_hidden = [\n    {width},\n    {width},\n]")), "{recorded}");

    let refused = train_connected("local", &work.path().join("r"), &config, &["--match-params", graph.to_str().unwrap()]);
    assert_clean_failure(&refused, "use it with --connection global");
    let refused = train_connected("global+match=local@0.1", &work.path().join("r"), &config, &[]);
    assert_clean_failure(&refused, "--match-params graph.json");
}

/// Peg runs record the return's terms per episode (metrics.csv) and for the
/// evaluation (summary.json), with the a = 0 reference beside them.
#[test]
fn peg_run_splits_returns_into_reward_terms() {
    let work = tempfile::tempdir().unwrap();
    let config = tiny_config(work.path());
    let run = work.path().join("peg");
    let out = lcrl()
        .args(["train", "--env", "peg-group1", "--algo", "ddpg", "--connection", "global", "--episodes", "2", "--config"])
        .arg(&config)
        .arg("--run-dir")
        .arg(&run)
        .output()
        .unwrap();
    assert!(out.status.success(), "{}", String::from_utf8_lossy(&out.stderr));
    let s = json(&run.join("summary.json"));
    let terms: f64 = ["return_depth", "return_force", "return_moment", "return_bonus", "return_failure"].iter().map(|k| s[*k].as_f64().unwrap()).sum();
    assert!((terms - s["eval_return"].as_f64().unwrap()).abs() < 1e-9, "{s}");
    assert!(s["zero_action_return"].as_f64().is_some() && s["eval_success_rate"].as_f64().is_some(), "{s}");
    // The references of `lcrl run`'s evaluator, on the same starts: a = 0
    // and the recorded best constant.
    let names: Vec<&str> = s["references"].as_array().unwrap().iter().map(|r| r["controller"].as_str().unwrap()).collect();
    assert_eq!(names, ["a = 0", "best constant"], "{s}");
    assert_eq!(s["references"][0]["mean_return"], s["zero_action_return"]);
    assert_eq!(super::common::assert_peg_rows_measured(&run.join("metrics.csv")), 2);
}

/// With no --config, a registered environment gets the settings that work
/// on it, recorded in the run's config.toml.
#[test]
fn lti_paper_without_config_gets_its_working_settings() {
    let work = tempfile::tempdir().unwrap();
    let run = work.path().join("r");
    let out = lcrl()
        .args(["train", "--env", "lti-paper", "--algo", "ddpg", "--connection", "global", "--episodes", "2", "--run-dir"])
        .arg(&run)
        .output()
        .unwrap();
    assert!(out.status.success(), "{}", String::from_utf8_lossy(&out.stderr));
    let config = fs::read_to_string(run.join("config.toml")).unwrap();
    assert!(config.contains("# settings from: configs/lti-fast.toml"), "{config}");
    assert!(config.contains("activation = \"elu\"") && config.contains("buffer_capacity = 20000"), "{config}");
}

/// A base controller that cannot be used stops `lcrl train` before any
/// work, naming the file or the component: a missing file, a file that
/// is not `lcrl tune`'s, an action outside the box, the wrong length.
#[test]
fn train_refuses_a_bad_base_action() {
    let work = tempfile::tempdir().unwrap();
    let config = tiny_config(work.path());
    let base_train = |file: &Path| {
        lcrl()
            .args(["train", "--env", "peg-group1", "--algo", "ddpg", "--connection", "global", "--config"])
            .arg(&config)
            .arg("--run-dir")
            .arg(work.path().join("run"))
            .arg("--base-action")
            .arg(file)
            .output()
            .unwrap()
    };
    let missing = work.path().join("missing.json");
    assert_clean_failure(&base_train(&missing), "missing.json");
    let cases = [
        ("not-tune.json", "{\"best\": 1}", "not a best_constant.json"),
        ("outside.json", "{\"action\": [2.0, 2.0, 0.0, 9.0, 0.0, 0.0]}", "base.action[3] = 9 lies outside the action box"),
        ("short.json", "{\"action\": [0.0, 0.0]}", "base.action has 2 components"),
    ];
    for (name, text, needle) in cases {
        let file = work.path().join(name);
        fs::write(&file, text).unwrap();
        assert_clean_failure(&base_train(&file), needle);
    }
    assert!(!work.path().join("run").join("checkpoints").exists(), "nothing was trained");
}

/// The throughput settings keep the replay ratio they promise: a round of
/// `gradient_steps` updates of `batch_size` every `update_every` stored
/// steps once the buffer holds max(warmup, batch) — exactly, as counted in
/// summary.json.
#[test]
fn throughput_settings_keep_their_replay_ratio() {
    let work = tempfile::tempdir().unwrap();
    // (batch, update_every, gradient_steps): Algorithm 2; a 4× batch on
    // every 4th step; 4 updates on every 4th step.
    for (batch, every, steps) in [(16u64, 1u64, 1u64), (64, 4, 1), (16, 4, 4)] {
        let config = work.path().join(format!("b{batch}-e{every}-g{steps}.toml"));
        let text = TINY.replace("batch_size = 16", &format!("batch_size = {batch}\nupdate_every = {every}\ngradient_steps = {steps}"));
        fs::write(&config, text).unwrap();
        let dir = work.path().join(format!("run-{batch}-{every}-{steps}"));
        let out = train_connected("global", &dir, &config, &[]);
        assert!(out.status.success(), "{}", String::from_utf8_lossy(&out.stderr));
        let summary = json(&dir.join("summary.json"));
        let env_steps = summary["env_steps"].as_u64().unwrap();
        let min_size = batch.max(20);
        let rounds = (1..=env_steps).filter(|k| k % every == 0 && *k >= min_size).count() as u64;
        assert_eq!(summary["samples_drawn"].as_u64().unwrap(), rounds * steps * batch, "batch {batch}, every {every}, steps {steps}");
        // Samples per insert after warm-up: batch · steps / every = 16 or 64.
        let ratio = summary["samples_drawn"].as_u64().unwrap() as f64 / (env_steps - min_size + 1) as f64;
        let promised = (batch * steps) as f64 / every as f64;
        assert!((ratio - promised).abs() <= promised * every as f64 / (env_steps - min_size + 1) as f64 + 1e-9, "ratio {ratio} vs {promised}");
    }
}

/// Graphs given, not measured: `random@K` trains with K random edges,
/// recorded in the run's graph.json with its draw, the same draw for any
/// --seed and another for another --graph-seed; `graph:PATH` trains with
/// that file; a bad file fails before any work, naming it.
#[test]
fn given_graphs_train_and_are_recorded_in_the_run() {
    let work = tempfile::tempdir().unwrap();
    let config = tiny_config(work.path());
    let graph_of = |dir: &Path| json(&dir.join("graph.json"));
    let (a, b, c) = (work.path().join("a"), work.path().join("b"), work.path().join("c"));
    assert!(train_connected("random@4", &a, &config, &["--seed", "1"]).status.success());
    assert!(train_connected("random@4", &b, &config, &["--seed", "2"]).status.success());
    let drawn = graph_of(&a);
    assert_eq!(drawn["origin"], "random@4, draw seed 0");
    assert_eq!(drawn["g"].as_array().unwrap().iter().flat_map(|r| r.as_array().unwrap().clone()).filter(|v| v == 1).count(), 4);
    assert_eq!(drawn["g"], graph_of(&b)["g"], "the seeds of a cell share one draw");
    let checkpoint_mask = |dir: &Path| fs::read_to_string(dir.join("config.toml")).unwrap();
    assert!(checkpoint_mask(&a).contains("Local"), "a random graph trains the locally connected actor");

    let given = work.path().join("given.json");
    fs::copy(a.join("graph.json"), &given).unwrap();
    let out = train_connected(&format!("graph:{}", given.display()), &c, &config, &[]);
    assert!(out.status.success(), "{}", String::from_utf8_lossy(&out.stderr));
    assert_eq!(graph_of(&c)["g"], drawn["g"]);

    fs::write(&given, "{\"g\": 3}").unwrap();
    let bad = train_connected(&format!("graph:{}", given.display()), &work.path().join("d"), &config, &[]);
    assert_clean_failure(&bad, "not a valid graph.json");
    assert!(super::common::stderr(&bad).contains("given.json"));
    let too_few = train_connected("random@2", &work.path().join("e"), &config, &[]);
    assert_clean_failure(&too_few, "random@2: K must be between 3 and 9");
}
