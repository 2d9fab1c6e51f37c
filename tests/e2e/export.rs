//! `lcrl export` (issue 64): the exported file is the served policy. A
//! short distributed run on peg-group1 and on the lti-paper preset, each
//! exported as TorchScript and as ONNX; on 1,000 states the TorchScript
//! module (torch.jit.load, in the project's Python), the ONNX file (ONNX
//! Runtime) and the learner's `Policy.Act` give the same actions within
//! 1e-5. And the C++ example of docs/export.md, compiled against the
//! .venv's libtorch, runs an exported file.

use std::path::{Path, PathBuf};
use std::process::{Command, Stdio};

use lcrl_proto::v1::policy_client::PolicyClient;
use lcrl_proto::v1::ActRequest;
use rand::{Rng, SeedableRng};
use rand_chacha::ChaCha8Rng;
use serde_json::Value;

use super::common::{assert_clean_failure, lcrl, spawn_listening, stderr, stdout, workspace_bin};
use super::distributed::{free_port, wait_for, Proc};

const TOLERANCE: f64 = 1e-5;
const STATES: usize = 1000;

fn root() -> &'static Path {
    Path::new(env!("CARGO_MANIFEST_DIR"))
}

fn python() -> PathBuf {
    let python = root().join(".venv/bin/python");
    assert!(python.is_file(), "run scripts/setup.sh first (it makes .venv with torch, onnx and onnxruntime)");
    python
}

/// One short run to export.
struct Case {
    name: &'static str,
    env: &'static str,
    algo: &'static str,
    connection: &'static str,
    flags: &'static [&'static str],
    /// Added to the environment's own settings.
    config: &'static str,
    episodes: u64,
}

/// peg-group1: the locally connected PPO actor on the publication's graph
/// (eq. 21), acting around the best constant; without validation, so the
/// learner serves, and `lcrl export` takes, its newest policy (trained:
/// a large step size moves it far from its near-zero start).
const PEG: Case = Case {
    name: "peg-group1",
    env: "peg-group1",
    algo: "ppo",
    connection: "local",
    flags: &["--graph", "references/peg-eq21/graph.json"],
    config: "[ppo]\nrollout_steps = 250\nminibatch_size = 50\nepochs = 5\nactor_lr = 1e-2\n\
             [run]\neval_episodes = 2\nvalidation_episodes = 0\nconfirm_candidates = 0\nthreads = 1\n",
    episodes: 30,
};

/// lti-paper with its preset's settings (PPO, local connection, its graph
/// measured by CS3), with validation: the learner serves, and `lcrl
/// export` takes, the selected policy.
const LTI: Case = Case {
    name: "lti-paper",
    env: "lti-paper",
    algo: "ppo",
    connection: "local",
    flags: &[],
    config: "[run]\neval_episodes = 2\nvalidation_episodes = 2\nvalidate_every = 10\nconfirm_candidates = 0\nthreads = 1\n",
    episodes: 100,
};

/// Trains `case` with a learner and one actor to its budget; returns the
/// learner (still serving) and its address.
async fn train(case: &Case, dir: &Path) -> (Proc, String, PathBuf) {
    let run = dir.join(case.name);
    let config = dir.join(format!("{}.toml", case.name));
    std::fs::write(&config, case.config).unwrap();
    let port = free_port();
    let run_id = format!("export-{}-{}", case.name, std::process::id());
    let (child, _) = spawn_listening(
        workspace_bin("lcrl-learner")
            .current_dir(root())
            .args(["--env", case.env, "--algo", case.algo, "--connection", case.connection, "--run-id", &run_id])
            .args(case.flags)
            .arg("--config")
            .arg(&config)
            .arg("--run-dir")
            .arg(&run)
            .args(["--episodes", &case.episodes.to_string(), "--checkpoint-secs", "600", "--listen", &format!("127.0.0.1:{port}")]),
    );
    let learner = Proc(child);
    let url = format!("http://127.0.0.1:{port}");
    let _actor = Proc(
        workspace_bin("lcrl-actor")
            .args(["--learner", &url, "--run-id", &run_id, "--envs", "1", "--connect-deadline", "30"])
            .stdout(Stdio::null())
            .stderr(Stdio::null())
            .spawn()
            .unwrap(),
    );
    wait_for(&url, "the end of the budget", |s| s.finished).await;
    (learner, url, run)
}

/// 1,000 raw states: 700 along episodes of random actions (contact,
/// insertion, the states a controller meets) and 300 drawn up to three
/// scales around zero (saturated actions, the box clipping them).
fn states(env_name: &str, scale: &[f64]) -> Vec<Vec<f32>> {
    let mut env = lcrl_sim::make_env(env_name).unwrap();
    let spec = env.spec().clone();
    let mut rng = ChaCha8Rng::seed_from_u64(64);
    let mut rows = Vec::new();
    let mut seed = 0;
    while rows.len() < 700 {
        let mut state = env.reset(seed).unwrap();
        seed += 1;
        for _ in 0..100 {
            rows.push(state.iter().map(|&v| v as f32).collect::<Vec<f32>>());
            let action: Vec<f64> = spec.action_low.iter().zip(&spec.action_high).map(|(lo, hi)| rng.random_range(*lo..=*hi)).collect();
            let step = env.step(&action).unwrap();
            if step.terminated || step.truncated || rows.len() >= 700 {
                break;
            }
            state = step.state;
        }
    }
    while rows.len() < STATES {
        rows.push(scale.iter().map(|s| (rng.random_range(-3.0..=3.0) * s) as f32).collect());
    }
    rows
}

fn max_difference(a: &[Vec<f32>], b: &[Vec<f32>]) -> f64 {
    assert_eq!(a.len(), b.len());
    a.iter().zip(b).flat_map(|(x, y)| x.iter().zip(y).map(|(p, q)| (f64::from(*p) - f64::from(*q)).abs())).fold(0.0, |m, d| if d.is_nan() { f64::INFINITY } else { m.max(d) })
}

fn rows(value: &Value) -> Vec<Vec<f32>> {
    value.as_array().unwrap().iter().map(|row| row.as_array().unwrap().iter().map(|v| v.as_f64().unwrap() as f32).collect()).collect()
}

/// Exports `run` in both formats into `out`; returns policy.json.
fn export_both(run: &Path, out: &Path) -> Value {
    for (file, format) in [("policy.pt", "torchscript"), ("policy.onnx", "onnx")] {
        let result = lcrl().current_dir(root()).arg("export").arg(run).arg("--out").arg(out.join(file)).args(["--format", format]).output().unwrap();
        assert!(result.status.success(), "lcrl export --format {format}: {}{}", stdout(&result), stderr(&result));
        assert!(stdout(&result).contains("checked on"), "{}", stdout(&result));
    }
    serde_json::from_str(&std::fs::read_to_string(out.join("policy.json")).unwrap()).unwrap()
}

async fn exported_files_act_as_the_served_policy(case: &Case) {
    let dir = tempfile::tempdir().unwrap();
    let (_learner, url, run) = train(case, dir.path()).await;
    let status = super::distributed::status(&url).await.unwrap();
    let out = dir.path().join("export");
    let manifest = export_both(&run, &out);
    // policy.json names what it is and where it came from: the policy the
    // learner serves.
    let source = &manifest["source"];
    assert_eq!(source["policy_version"].as_u64(), Some(status.served_version), "{manifest}");
    let chosen = source["chosen"].as_str().unwrap();
    assert!(status.served_reason.starts_with(if chosen == "selected" { "selected" } else { "newest" }), "{chosen} / {}", status.served_reason);
    assert_eq!(manifest["env"], case.env);
    assert!(manifest["files"]["torchscript"]["bytes"].as_u64().unwrap() > 0 && manifest["files"]["onnx"]["bytes"].as_u64().unwrap() > 0, "{manifest}");
    let scale: Vec<f64> = manifest["state"].as_array().unwrap().iter().map(|s| s["scale"].as_f64().unwrap()).collect();
    let low: Vec<f64> = manifest["action"].as_array().unwrap().iter().map(|a| a["low"].as_f64().unwrap()).collect();
    let high: Vec<f64> = manifest["action"].as_array().unwrap().iter().map(|a| a["high"].as_f64().unwrap()).collect();

    let states = states(case.env, &scale);
    let mut client = PolicyClient::connect(url.clone()).await.unwrap();
    let mut served = Vec::with_capacity(states.len());
    for state in &states {
        let reply = client.act(ActRequest { state: state.clone() }).await.unwrap().into_inner();
        assert_eq!(reply.policy_version, status.served_version);
        served.push(reply.action);
    }
    let states_path = dir.path().join("states.json");
    std::fs::write(&states_path, serde_json::json!({ "states": states }).to_string()).unwrap();
    let actions_path = dir.path().join("actions.json");
    let result = Command::new(python())
        .arg(root().join("clients/python/lcrl_export_check.py"))
        .arg("--torchscript")
        .arg(out.join("policy.pt"))
        .arg("--onnx")
        .arg(out.join("policy.onnx"))
        .arg("--states")
        .arg(&states_path)
        .arg("--out")
        .arg(&actions_path)
        .output()
        .unwrap();
    assert!(result.status.success(), "lcrl_export_check.py: {}", stderr(&result));
    let actions: Value = serde_json::from_str(&std::fs::read_to_string(&actions_path).unwrap()).unwrap();
    let (torchscript, onnx) = (rows(&actions["torchscript"]), rows(&actions["onnx"]));
    let pairs = [
        ("TorchScript vs Policy.Act", max_difference(&torchscript, &served)),
        ("ONNX vs Policy.Act", max_difference(&onnx, &served)),
        ("TorchScript vs ONNX", max_difference(&torchscript, &onnx)),
    ];
    println!("{}: largest action difference on {STATES} states: {pairs:?}", case.name);
    for (what, difference) in pairs {
        assert!(difference <= TOLERANCE, "{}: {what} differ by {difference:e}", case.name);
    }
    // The check means something: the policy's actions move across the
    // states (by a share of each component's range), and stay in the box.
    let spread = (0..low.len())
        .map(|i| {
            let column = served.iter().map(|a| f64::from(a[i]));
            (column.clone().fold(f64::INFINITY, f64::min), column.fold(f64::NEG_INFINITY, f64::max))
        })
        .enumerate()
        .map(|(i, (lo, hi))| {
            assert!(lo >= low[i] - 1e-6 && hi <= high[i] + 1e-6, "{}: action {i} leaves its box", case.name);
            (hi - lo) / (high[i] - low[i])
        })
        .fold(0.0, f64::max);
    println!("{}: the widest action component spans {:.0}% of its range", case.name, 100.0 * spread);
    assert!(spread > 0.05, "{}: the served policy is nearly constant (spread {spread}); the check would be weak", case.name);
}

#[tokio::test(flavor = "multi_thread")]
async fn peg_group1_exports_act_as_the_served_policy() {
    exported_files_act_as_the_served_policy(&PEG).await;
}

#[tokio::test(flavor = "multi_thread")]
async fn lti_paper_exports_act_as_the_served_policy() {
    exported_files_act_as_the_served_policy(&LTI).await;
}

/// A quick `lcrl train` run to export (about a second).
fn quick_run(dir: &Path, env: &str, connection: &str, run_settings: &str) -> PathBuf {
    let run = dir.join(format!("run-{env}"));
    let config = dir.join(format!("{env}.toml"));
    std::fs::write(&config, format!("[ppo]\nrollout_steps = 250\nminibatch_size = 50\nactor_lr = 1e-2\n[run]\neval_episodes = 1\nconfirm_candidates = 0\n{run_settings}")).unwrap();
    let out = lcrl()
        .current_dir(root())
        .args(["train", "--env", env, "--algo", "ppo", "--connection", connection, "--episodes", "10", "--config"])
        .arg(&config)
        .arg("--run-dir")
        .arg(&run)
        .output()
        .unwrap();
    assert!(out.status.success(), "lcrl train: {}", stderr(&out));
    run
}

/// The fenced blocks of `language` in a Markdown page.
fn code_blocks(page: &str, language: &str) -> Vec<String> {
    let fence = format!("```{language}\n");
    page.split(fence.as_str()).skip(1).map(|rest| rest.split("\n```").next().unwrap_or_default().to_string()).collect()
}

/// A C++ compiler on this machine ($CXX, c++, g++ or clang++), if any.
fn cxx() -> Option<String> {
    let candidates = std::env::var("CXX").into_iter().chain(["c++", "g++", "clang++"].map(String::from));
    candidates.into_iter().find(|c| Command::new(c).arg("--version").stdout(Stdio::null()).stderr(Stdio::null()).status().is_ok_and(|s| s.success()))
}

/// docs/export.md's examples run on an exported peg-group1 policy: each
/// Python block (TorchScript, ONNX Runtime) in the export's folder, and
/// the C++ block compiled against the .venv's libtorch, whose action for
/// a state is the served policy's.
#[test]
fn the_examples_of_docs_export_md_run_an_exported_policy() {
    let dir = tempfile::tempdir().unwrap();
    let run = quick_run(dir.path(), "peg-group1", "graph:references/peg-eq21/graph.json", "validation_episodes = 0\n");
    let out = dir.path().join("export");
    export_both(&run, &out);
    let page = std::fs::read_to_string(root().join("docs/export.md")).unwrap();
    let python_blocks = code_blocks(&page, "python");
    assert_eq!(python_blocks.len(), 2, "docs/export.md shows TorchScript and ONNX Runtime from Python");
    for (k, block) in python_blocks.iter().enumerate() {
        let script = out.join(format!("example_{k}.py"));
        std::fs::write(&script, block).unwrap();
        let result = Command::new(python()).arg(&script).current_dir(&out).output().unwrap();
        assert!(result.status.success(), "docs/export.md's Python example {k}: {}", stderr(&result));
        assert!(stdout(&result).contains("'dgamma': "), "{}", stdout(&result));
    }

    let headers = root().join(".venv/libtorch/include/torch/script.h");
    let Some(compiler) = cxx() else {
        println!("skipping docs/export.md's C++ example: no C++ compiler ($CXX, c++, g++, clang++)");
        return;
    };
    if !headers.is_file() {
        println!("skipping docs/export.md's C++ example: {} is missing (scripts/setup.sh installs libtorch into .venv)", headers.display());
        return;
    }
    let cpp = code_blocks(&page, "cpp");
    assert_eq!(cpp.len(), 1, "docs/export.md shows one C++ program");
    let source = dir.path().join("run_policy.cpp");
    std::fs::write(&source, &cpp[0]).unwrap();
    let libtorch = std::fs::canonicalize(root().join(".venv/libtorch")).unwrap();
    let binary = dir.path().join("run_policy");
    // The flags of docs/export.md's build line.
    let build = Command::new(&compiler)
        .args(["-std=c++20", "-O2"])
        .arg(&source)
        .arg(format!("-I{}", libtorch.join("include").display()))
        .arg(format!("-I{}", libtorch.join("include/torch/csrc/api/include").display()))
        .arg(format!("-L{}", libtorch.join("lib").display()))
        .arg(format!("-Wl,-rpath,{}", libtorch.join("lib").display()))
        .args(["-Wl,--no-as-needed", "-ltorch", "-ltorch_cpu", "-lc10", "-o"])
        .arg(&binary)
        .output()
        .unwrap();
    assert!(build.status.success(), "{compiler} docs/export.md's run_policy.cpp: {}", stderr(&build));
    // A state mid-episode, in contact.
    let mut env = lcrl_sim::make_env("peg-group1").unwrap();
    let mut state = env.reset(3).unwrap();
    for _ in 0..20 {
        state = env.step(&[0.0; 6]).unwrap().state;
    }
    let state: Vec<f32> = state.iter().map(|&v| v as f32).collect();
    let result = Command::new(&binary).arg(out.join("policy.pt")).args(state.iter().map(|v| format!("{v:e}"))).output().unwrap();
    assert!(result.status.success(), "run_policy: {}", stderr(&result));
    let action: Vec<f64> = stdout(&result).split_whitespace().map(|v| v.parse().unwrap()).collect();
    let policy = lcrl_learner::policy::trained::Policy::load(&run).unwrap();
    let served = policy.act(env.as_ref(), &state.iter().map(|&v| f64::from(v)).collect::<Vec<_>>());
    assert_eq!(action.len(), served.len());
    let difference = action.iter().zip(&served).map(|(a, b)| (a - f64::from(*b as f32)).abs()).fold(0.0, f64::max);
    println!("C++ example: action {action:?}, served {served:?}, largest difference {difference:e}");
    assert!(difference <= TOLERANCE, "C++ {action:?} against served {served:?}");
}

/// What a user gets wrong is said, with what to do: a folder that is not
/// a run, one without a policy, a checkpoint that is not there, an --out
/// that would be policy.json itself, an environment that does not fit,
/// no Python or a Python without torch for ONNX. And `--checkpoint` picks
/// another policy, named in policy.json.
#[test]
fn export_says_what_is_wrong_and_takes_another_checkpoint() {
    let dir = tempfile::tempdir().unwrap();
    let run = quick_run(dir.path(), "lti-paper", "global", "validation_episodes = 0\ncheckpoint_every = 5\n");
    let out = dir.path().join("out/policy.pt");
    let export = |args: &[&str]| lcrl().current_dir(root()).arg("export").args(args).output().unwrap();
    let path = |p: &Path| p.to_str().unwrap().to_string();

    assert_clean_failure(&export(&[&path(&dir.path().join("nothing")), "--out", &path(&out)]), "is not a folder");
    std::fs::create_dir(dir.path().join("empty")).unwrap();
    assert_clean_failure(&export(&[&path(&dir.path().join("empty")), "--out", &path(&out)]), "holds no policy");
    assert_clean_failure(&export(&[&path(&run), "--checkpoint", "ep999999", "--out", &path(&out)]), "ep000010");
    assert_clean_failure(&export(&[&path(&run), "--out", &path(&dir.path().join("policy.json"))]), "must name the policy file");
    assert_clean_failure(&export(&[&path(&run), "--env", "peg-group1", "--out", &path(&out)]), "trained on lti-paper (3 states, 3 actions)");

    // Without a selection, the newest checkpoint; --checkpoint another.
    let newest = export(&[&path(&run), "--out", &path(&out)]);
    assert!(newest.status.success(), "{}", stderr(&newest));
    let manifest: Value = serde_json::from_str(&std::fs::read_to_string(out.with_extension("json")).unwrap()).unwrap();
    assert!(manifest["source"]["chosen"].as_str().unwrap().starts_with("newest checkpoint"), "{manifest}");
    assert_eq!(manifest["source"]["episode"], 10);
    assert_eq!(manifest["graph"]["connection"], "global");
    // Without --out: beside the run, never in the working folder.
    let beside = export(&[&path(&run)]);
    assert!(beside.status.success(), "{}", stderr(&beside));
    assert!(run.join("policy.pt").is_file() && run.join("policy.json").is_file());
    assert!(!root().join("policy.pt").exists(), "written into the working folder");
    let earlier = export(&[&path(&run), "--checkpoint", "ep000005", "--out", &path(&out)]);
    assert!(earlier.status.success(), "{}", stderr(&earlier));
    let manifest: Value = serde_json::from_str(&std::fs::read_to_string(out.with_extension("json")).unwrap()).unwrap();
    assert_eq!((manifest["source"]["chosen"].as_str(), manifest["source"]["episode"].as_u64()), (Some("given"), Some(5)), "{manifest}");

    // `lcrl run` keeps its learner's records in RUN/learner/.
    let wrapper = dir.path().join("lcrl-run");
    std::fs::create_dir(&wrapper).unwrap();
    std::os::unix::fs::symlink(&run, wrapper.join("learner")).unwrap();
    let from_run = export(&[&path(&wrapper), "--out", &path(&out)]);
    assert!(from_run.status.success(), "{}", stderr(&from_run));

    // ONNX needs Python with torch: missing, then without torch.
    let onnx = |python: &Path| {
        lcrl().current_dir(root()).env("LCRL_PYTHON", python).args(["export", &path(&run), "--format", "onnx", "--out", &path(&dir.path().join("p.onnx"))]).output().unwrap()
    };
    assert_clean_failure(&onnx(&dir.path().join("no-python")), "scripts/setup.sh");
    let bare = dir.path().join("bare");
    let made = Command::new(python()).args(["-m", "venv", "--without-pip"]).arg(&bare).output().unwrap();
    assert!(made.status.success(), "{}", stderr(&made));
    let failed = onnx(&bare.join("bin/python"));
    assert_clean_failure(&failed, "lacks torch");
    assert!(stderr(&failed).contains("scripts/setup.sh"), "{}", stderr(&failed));
    assert!(!dir.path().join("p.onnx").exists() && !dir.path().join("p.json").exists(), "nothing is left of a failed export");
}

/// Issue 72: an `lcrl train` run's policy is named by the training behind
/// it, not as "policy version 0", in the output and in policy.json.
#[test]
fn a_trained_policy_is_named_by_its_training() {
    let dir = tempfile::tempdir().unwrap();
    let run = quick_run(dir.path(), "lti-paper", "local", "");
    let out = lcrl().current_dir(root()).arg("export").arg(&run).arg("--out").arg(dir.path().join("p.onnx")).args(["--format", "onnx"]).output().unwrap();
    assert!(out.status.success(), "{}", stderr(&out));
    let text = stdout(&out);
    assert!(text.contains("after episode 10, ") && text.contains(" actor updates") && !text.contains("policy version"), "{text}");
    let manifest: Value = serde_json::from_str(&std::fs::read_to_string(dir.path().join("p.json")).unwrap()).unwrap();
    assert!(manifest["source"]["updates"].as_u64().is_some_and(|u| u > 0), "{manifest}");
}
