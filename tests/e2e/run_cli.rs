//! `lcrl run`: the whole system from one preset.

use std::fs;
use std::path::{Path, PathBuf};
use std::process::{Child, Command, Stdio};
use std::time::{Duration, Instant};

use super::common::{assert_clean_failure, lcrl, stdout};

/// Processes whose command line mentions `needle` (other than this test).
pub(super) fn processes_mentioning(needle: &str) -> Vec<String> {
    let mut found = Vec::new();
    for entry in fs::read_dir("/proc").unwrap().flatten() {
        if let Ok(cmdline) = fs::read(entry.path().join("cmdline")) {
            let text = String::from_utf8_lossy(&cmdline).replace('\0', " ");
            if text.contains(needle) && !text.contains("e2e") {
                found.push(text);
            }
        }
    }
    found
}

#[test]
fn run_on_the_linear_preset_finishes_with_every_artifact_and_no_leftovers() {
    let dir = tempfile::tempdir().unwrap();
    let run = dir.path().join("run");
    let preset = Path::new(env!("CARGO_MANIFEST_DIR")).join("configs/lti-paper.toml");
    // Asynchronous PPO (lag at most 1 version): older batches are trained
    // on, staler ones dropped and counted.
    let out = lcrl().args(["run", "--episodes", "300", "--actors", "2", "--max-staleness", "1", "--config"]).arg(&preset).arg("--run-dir").arg(&run).output().unwrap();
    assert!(out.status.success(), "{}", String::from_utf8_lossy(&out.stderr));
    assert!(stdout(&out).contains("results in") && stdout(&out).contains("PPO, asynchronous, lag at most 1"), "{}", stdout(&out));
    // Actors that stop at the budget's end are not deaths: no restart.
    let summary: serde_json::Value = serde_json::from_str(&fs::read_to_string(run.join("summary.json")).unwrap()).unwrap();
    assert_eq!(summary["actor_restarts"], 0, "{}", String::from_utf8_lossy(&out.stderr));
    assert!(summary.get("ended_early").is_none(), "{summary}");
    assert!(summary["policy_lag"]["max"].as_u64().is_some_and(|lag| lag <= 1), "no batch staler than the bound is trained on: {summary}");
    assert!(summary["discarded_stale"].is_u64(), "PPO counts what it discarded: {summary}");
    let graph: serde_json::Value = serde_json::from_str(&fs::read_to_string(run.join("graph.json")).unwrap()).unwrap();
    assert_eq!(graph["g"], serde_json::json!([[1, 0, 0], [1, 1, 0], [0, 0, 1]]));
    // A bare `connection = "local"` trains T_rule, and the run says so and why.
    assert_eq!(graph["threshold"].as_f64(), Some(1.0));
    let why = "graph: eq. 7 at T = 1: T_rule, the above-average rule";
    assert!(stdout(&out).contains(why), "{}", stdout(&out));
    assert!(fs::read_to_string(run.join("config.toml")).unwrap().starts_with(&format!("# {}", why.replace("graph: ", "graph: measured, "))));
    let metrics = fs::read_to_string(run.join("learner/metrics.csv")).unwrap();
    assert!(metrics.lines().count() > 300, "{} rows", metrics.lines().count());
    // The same columns as `lcrl train`'s metrics.csv (learner/src/run/files.rs).
    assert_eq!(metrics.lines().next().unwrap(), lcrl_learner::run::files::METRICS_COLUMNS.join(","));
    assert!(metrics.lines().nth(1).unwrap().split(',').nth(1).unwrap().parse::<f64>().is_ok());
    assert_eq!(super::train_cli::tensorboard_returns(&run.join("learner")).len(), metrics.lines().count() - 1, "TensorBoard has every episode");
    let checkpoint = lcrl_learner::policy::checkpoint::latest_checkpoint(&run.join("learner")).expect("a final checkpoint");
    assert!(lcrl_learner::policy::checkpoint::read_meta(&checkpoint).unwrap().episode >= 300);
    for file in ["config.toml", "train.toml", "graph.png", "reward_curve.png", "logs/learner.log", "logs/actor-0.log", "logs/graph-builder.log"] {
        assert!(run.join(file).is_file(), "{file} missing");
    }
    assert!(fs::read(run.join("reward_curve.png")).unwrap().starts_with(b"\x89PNG"));
    assert_eq!(processes_mentioning(run.to_str().unwrap()), Vec::<String>::new(), "processes left behind");
    // The run used shared memory (the default transport); none of it is left.
    let run_id = stdout(&out).split("run ").nth(1).and_then(|rest| rest.split(':').next()).expect("the run id in the summary").to_string();
    assert_eq!(lcrl_proto::shm::services_of_in(&super::common::shm_namespace(), &run_id), Vec::<String>::new(), "shared-memory services left behind");
}

#[test]
fn bad_presets_fail_cleanly() {
    let dir = tempfile::tempdir().unwrap();
    let preset = dir.path().join("p.toml");
    fs::write(&preset, "[ppo]\nclip = 0.2\n").unwrap();
    assert_clean_failure(&lcrl().args(["run", "--config"]).arg(&preset).output().unwrap(), "[job]");
    fs::write(&preset, "[job]\nenv = \"nope\"\nalgo = \"ppo\"\nconnection = \"local\"\nepisodes = 10\n").unwrap();
    assert_clean_failure(&lcrl().args(["run", "--config"]).arg(&preset).output().unwrap(), "unknown environment 'nope'");
    // A headroom reference that is missing, or made for another task, is
    // refused before anything starts (not after training).
    let job = "[job]\nenv = \"lti-paper\"\nalgo = \"ppo\"\nconnection = \"local\"\nepisodes = 10\n";
    fs::write(&preset, format!("{job}headroom = \"missing.json\"\n")).unwrap();
    assert_clean_failure(&lcrl().args(["run", "--config"]).arg(&preset).output().unwrap(), "job.headroom");
    let peg_reference = Path::new(env!("CARGO_MANIFEST_DIR")).join("references/peg-group1/best_policy.json");
    fs::write(&preset, format!("{job}headroom = {:?}\n", peg_reference.to_str().unwrap())).unwrap();
    assert_clean_failure(&lcrl().args(["run", "--config"]).arg(&preset).output().unwrap(), "has 6 actions and 12 states; lti-paper has 3 and 3");
    // graph_threshold is a number or "auto" (T_rule), nothing else.
    fs::write(&preset, format!("{job}graph_threshold = \"often\"\n")).unwrap();
    assert_clean_failure(&lcrl().args(["run", "--check", "--config"]).arg(&preset).output().unwrap(), "give \"auto\" (T_rule = 1");
    // A key measured not to help and removed (docs/peg.md) is an unknown
    // key now, in a preset and in a config given to the learner directly.
    fs::write(&preset, format!("{job}[run]\nfallback_margin = 2.0\nvalidation_episodes = 3\n")).unwrap();
    assert_clean_failure(&lcrl().args(["run", "--check", "--config"]).arg(&preset).output().unwrap(), "fallback_margin");
    let config = dir.path().join("train.toml");
    fs::write(&config, "[ddpg]\ntemporal_smoothness = 1.0\n").unwrap();
    let out = super::common::workspace_bin("lcrl-learner").args(["--env", "lti-paper", "--algo", "ddpg", "--connection", "global", "--run-dir"]).arg(dir.path().join("learner")).arg("--config").arg(&config).output().unwrap();
    assert_clean_failure(&out, "temporal_smoothness");
}

#[test]
fn every_shipped_preset_is_valid() {
    let configs = Path::new(env!("CARGO_MANIFEST_DIR")).join("configs");
    let mut checked = 0;
    for entry in fs::read_dir(&configs).unwrap().flatten() {
        let path = entry.path();
        let text = fs::read_to_string(&path).unwrap();
        if !text.contains("[job]") {
            continue; // a training-only config (lcrl train --config)
        }
        let out = lcrl().args(["run", "--check", "--config"]).arg(&path).output().unwrap();
        assert!(out.status.success(), "{}: {}", path.display(), String::from_utf8_lossy(&out.stderr));
        checked += 1;
    }
    assert!(checked >= 9, "expected the 8 peg presets and the linear one, found {checked}");
}

/// `lcrl run --tls-dir --token-file`: every process of the run speaks
/// mutual TLS with the token (the servers' logs say so), and it finishes.
#[test]
fn run_over_mutual_tls_with_a_token_finishes() {
    let dir = tempfile::tempdir().unwrap();
    let certs = dir.path().join("certs");
    assert!(lcrl().args(["certs", "--out"]).arg(&certs).output().unwrap().status.success());
    let run = dir.path().join("run");
    let preset = Path::new(env!("CARGO_MANIFEST_DIR")).join("configs/lti-paper.toml");
    let out = lcrl()
        .args(["run", "--episodes", "100", "--transport", "grpc", "--config"])
        .arg(&preset)
        .arg("--run-dir")
        .arg(&run)
        .arg("--tls-dir")
        .arg(&certs)
        .arg("--token-file")
        .arg(certs.join("token"))
        .output()
        .unwrap();
    assert!(out.status.success(), "{}", String::from_utf8_lossy(&out.stderr));
    assert!(stdout(&out).contains("results in"), "{}", stdout(&out));
    for server in ["learner", "graph-builder"] {
        let log = fs::read_to_string(run.join(format!("logs/{server}.log"))).unwrap();
        assert!(log.contains("TLS + token"), "{server} did not serve TLS with a token:\n{log}");
    }
    let actor_log = fs::read_to_string(run.join("logs/actor-0.log")).unwrap();
    assert!(!actor_log.contains("refused"), "{actor_log}");
    assert_clean_failure(
        &lcrl().args(["run", "--config"]).arg(&preset).arg("--tls-dir").arg(dir.path().join("nowhere")).output().unwrap(),
        "lcrl certs",
    );
}

/// `[job] graph = "random@K"`: the distributed run trains with a drawn
/// graph, written as its graph.json, and starts no graph builder; a bad
/// `graph:` file is refused before anything starts.
#[test]
fn run_with_a_given_graph_starts_no_graph_builder() {
    let dir = tempfile::tempdir().unwrap();
    let run = dir.path().join("run");
    let preset = dir.path().join("p.toml");
    let job = "[job]\nenv = \"lti-paper\"\nalgo = \"ppo\"\nconnection = \"local\"\nepisodes = 20\n";
    fs::write(&preset, format!("{job}graph = \"random@4\"\n[run]\neval_episodes = 5\n")).unwrap();
    // --eval-episodes and --eval-seed override the preset's evaluation.
    let out = lcrl().args(["run", "--eval-episodes", "4", "--eval-seed", "7", "--config"]).arg(&preset).arg("--run-dir").arg(&run).output().unwrap();
    assert!(out.status.success(), "{}", String::from_utf8_lossy(&out.stderr));
    let graph: serde_json::Value = serde_json::from_str(&fs::read_to_string(run.join("graph.json")).unwrap()).unwrap();
    assert_eq!(graph["origin"], "random@4, draw seed 0");
    let summary: serde_json::Value = serde_json::from_str(&fs::read_to_string(run.join("summary.json")).unwrap()).unwrap();
    assert_eq!((summary["eval_episodes"].as_u64(), summary["eval_seed"].as_u64()), (Some(4), Some(7)), "{summary}");
    assert!(!run.join("logs/graph-builder.log").exists(), "a graph builder was started");
    fs::write(&preset, format!("{job}graph = \"graph:missing.json\"\n")).unwrap();
    assert_clean_failure(&lcrl().args(["run", "--config"]).arg(&preset).output().unwrap(), "job.graph");
}

/// A process as /proc shows it: its id and command line, so a reused pid
/// is not taken for it.
#[derive(Debug, Clone, PartialEq)]
struct Proc {
    pid: u32,
    cmdline: String,
}

impl Proc {
    /// Still running: present with the same command line and not a zombie
    /// (an orphan's zombie waits for whoever adopted it).
    fn alive(&self) -> bool {
        let Ok(stat) = fs::read_to_string(format!("/proc/{}/stat", self.pid)) else { return false };
        let state = stat.rsplit_once(')').and_then(|(_, rest)| rest.split_whitespace().next()).unwrap_or("X");
        let cmdline = fs::read(format!("/proc/{}/cmdline", self.pid)).map(|c| String::from_utf8_lossy(&c).replace('\0', " ")).unwrap_or_default();
        !matches!(state, "Z" | "X") && cmdline == self.cmdline
    }
}

/// The children of `parent` (from /proc/PID/stat's ppid field).
fn children_of(parent: u32) -> Vec<Proc> {
    let mut found = Vec::new();
    for entry in fs::read_dir("/proc").unwrap().flatten() {
        let Ok(pid) = entry.file_name().to_string_lossy().parse::<u32>() else { continue };
        let Ok(stat) = fs::read_to_string(entry.path().join("stat")) else { continue };
        let ppid = stat.rsplit_once(')').and_then(|(_, rest)| rest.split_whitespace().nth(1)).and_then(|p| p.parse::<u32>().ok());
        if ppid == Some(parent) {
            let cmdline = fs::read(entry.path().join("cmdline")).map(|c| String::from_utf8_lossy(&c).replace('\0', " ")).unwrap_or_default();
            found.push(Proc { pid, cmdline });
        }
    }
    found
}

/// A long `lcrl run` on the linear preset (a budget it never reaches),
/// its output in files under `dir`, with the preparation of `prepare`.
struct LongRun {
    child: Child,
    run: PathBuf,
    dir: PathBuf,
    children: Vec<Proc>,
}

impl LongRun {
    /// Starts it and waits until its graph builder, learner and actor run
    /// and the learner has stored episodes (metrics.csv has rows).
    fn start(dir: &Path, prepare: impl FnOnce(&mut Command)) -> LongRun {
        let run = dir.join("run");
        let preset = Path::new(env!("CARGO_MANIFEST_DIR")).join("configs/lti-paper.toml");
        let mut cmd = lcrl();
        cmd.args(["run", "--episodes", "100000000", "--config"]).arg(&preset).arg("--run-dir").arg(&run);
        cmd.stdin(Stdio::null()).stdout(fs::File::create(dir.join("stdout")).unwrap()).stderr(fs::File::create(dir.join("stderr")).unwrap());
        prepare(&mut cmd);
        let mut long = LongRun { child: cmd.spawn().unwrap(), run, dir: dir.to_path_buf(), children: Vec::new() };
        let deadline = Instant::now() + Duration::from_secs(180);
        loop {
            long.children = children_of(long.child.id());
            let has = |binary: &str| long.children.iter().any(|c| c.cmdline.contains(binary));
            let rows = fs::read_to_string(long.run.join("learner/metrics.csv")).map(|t| t.lines().count()).unwrap_or(0);
            if has("lcrl-graph-builder") && has("lcrl-learner") && has("lcrl-actor") && rows > 5 {
                return long;
            }
            if let Ok(Some(status)) = long.child.try_wait() {
                panic!("lcrl run ended early ({status}): {}", long.output());
            }
            assert!(Instant::now() < deadline, "lcrl run did not start its processes and train within 180 s: {:?}\n{}", long.children, long.output());
            std::thread::sleep(Duration::from_millis(100));
        }
    }

    fn output(&self) -> String {
        let read = |name: &str| fs::read_to_string(self.dir.join(name)).unwrap_or_default();
        format!("stdout:\n{}\nstderr:\n{}", read("stdout"), read("stderr"))
    }

    /// Waits up to `limit` for every child to be gone; returns those left.
    fn wait_for_children(&self, limit: Duration) -> Vec<Proc> {
        let deadline = Instant::now() + limit;
        loop {
            let left: Vec<Proc> = self.children.iter().filter(|c| c.alive()).cloned().collect();
            if left.is_empty() || Instant::now() > deadline {
                return left;
            }
            std::thread::sleep(Duration::from_millis(50));
        }
    }
}

impl Drop for LongRun {
    /// Nothing outlives the test, whatever it found.
    fn drop(&mut self) {
        let _ = self.child.kill();
        let _ = self.child.wait();
        for c in self.children.iter().filter(|c| c.alive()) {
            let _ = Command::new("kill").args(["-KILL", &c.pid.to_string()]).status();
        }
    }
}

/// kill -9 of `lcrl run` leaves nothing behind (issue 61): its graph
/// builder, learner and actor get their parent-death signal (SIGTERM),
/// the learner writes a final checkpoint, and all are gone within 15 s.
#[test]
fn killing_a_run_with_sigkill_stops_every_process_it_started() {
    let dir = tempfile::tempdir().unwrap();
    let mut long = LongRun::start(dir.path(), |_| {});
    let episodes = fs::read_to_string(long.run.join("learner/metrics.csv")).unwrap().lines().count() as u64 - 1;
    let started = Instant::now();
    long.child.kill().unwrap();
    long.child.wait().unwrap();
    let left = long.wait_for_children(Duration::from_secs(15));
    assert!(left.is_empty(), "left running {:.0} s after kill -9 of lcrl run: {left:#?}", started.elapsed().as_secs_f64());
    eprintln!("every child of the killed run gone after {:.2} s", started.elapsed().as_secs_f64());
    // Written on the way out (the periodic one comes later, every
    // --checkpoint-secs): it holds every episode stored before the kill.
    let checkpoint = lcrl_learner::policy::checkpoint::latest_checkpoint(&long.run.join("learner")).expect("the learner's final checkpoint");
    let meta = lcrl_learner::policy::checkpoint::read_meta(&checkpoint).unwrap();
    assert!(meta.episode as u64 >= episodes, "the final checkpoint holds {} episodes, {episodes} were stored before the kill", meta.episode);
}

/// Ctrl-C at a terminal (SIGINT to the whole process group): the run stops
/// its actors and learner, the learner writes a final checkpoint, the run
/// reports itself interrupted and exits, leaving nothing behind.
#[test]
fn ctrl_c_stops_a_run_with_a_final_checkpoint_and_leaves_nothing() {
    use std::os::unix::process::CommandExt;
    let dir = tempfile::tempdir().unwrap();
    // Its own process group, as a shell gives a foreground job.
    let mut long = LongRun::start(dir.path(), |cmd| {
        cmd.process_group(0);
    });
    let group = long.child.id();
    assert!(Command::new("kill").args(["-INT", "--", &format!("-{group}")]).status().unwrap().success());
    let deadline = Instant::now() + Duration::from_secs(120);
    let status = loop {
        if let Some(status) = long.child.try_wait().unwrap() {
            break status;
        }
        assert!(Instant::now() < deadline, "lcrl run did not stop within 120 s of Ctrl-C: {}", long.output());
        std::thread::sleep(Duration::from_millis(100));
    };
    assert!(status.success(), "lcrl run failed after Ctrl-C ({status}): {}", long.output());
    assert!(long.output().contains("interrupted: run"), "{}", long.output());
    let left = long.wait_for_children(Duration::from_secs(5));
    assert!(left.is_empty(), "left running after Ctrl-C: {left:#?}");
    let checkpoint = lcrl_learner::policy::checkpoint::latest_checkpoint(&long.run.join("learner")).expect("the learner's final checkpoint");
    assert!(lcrl_learner::policy::checkpoint::read_meta(&checkpoint).unwrap().episode > 0);
}

/// A dead actor is noticed, reaped (no zombie) and started again with
/// backoff, and training goes on with it; an actor that keeps dying ends
/// the run after the stated restarts with a clear message, a non-zero
/// exit, a final checkpoint holding every stored episode, and summary.json
/// saying why.
#[test]
fn dead_actors_are_restarted_then_end_the_run_with_the_reason() {
    let dir = tempfile::tempdir().unwrap();
    let mut long = LongRun::start(dir.path(), |_| {});
    let actor_of = |long: &LongRun| children_of(long.child.id()).into_iter().find(|c| c.cmdline.contains("lcrl-actor") && c.alive());
    let mut killed = Vec::new();
    for death in 0..=lcrl::local_run::MAX_ACTOR_RESTARTS {
        let deadline = Instant::now() + Duration::from_secs(60);
        let actor = loop {
            match actor_of(&long) {
                Some(actor) if !killed.contains(&actor.pid) => break actor,
                _ => assert!(Instant::now() < deadline, "no new actor within 60 s after death {death}: {}", long.output()),
            }
            std::thread::sleep(Duration::from_millis(100));
        };
        if death == 1 {
            // The restarted actor trains: the learner stores new episodes.
            let rows = || fs::read_to_string(long.run.join("learner/metrics.csv")).map(|t| t.lines().count()).unwrap_or(0);
            let before = rows();
            let until = Instant::now() + Duration::from_secs(60);
            while rows() <= before + 2 {
                assert!(Instant::now() < until, "no episode stored after the restart: {}", long.output());
                std::thread::sleep(Duration::from_millis(100));
            }
        }
        assert!(Command::new("kill").args(["-KILL", &actor.pid.to_string()]).status().unwrap().success());
        killed.push(actor.pid);
        long.children.push(actor.clone());
        // Reaped by the run within its next looks: not left a zombie.
        let until = Instant::now() + Duration::from_secs(5);
        while std::path::Path::new(&format!("/proc/{}", actor.pid)).exists() {
            assert!(Instant::now() < until, "actor {} left a zombie: {}", actor.pid, long.output());
            std::thread::sleep(Duration::from_millis(50));
        }
    }
    let deadline = Instant::now() + Duration::from_secs(120);
    let status = loop {
        if let Some(status) = long.child.try_wait().unwrap() {
            break status;
        }
        assert!(Instant::now() < deadline, "lcrl run did not end after its actor kept dying: {}", long.output());
        std::thread::sleep(Duration::from_millis(100));
    };
    let output = long.output();
    assert!(!status.success(), "{output}");
    assert!(output.contains("restarting it in 1 s (1 of 3 restarts") && output.contains("died (signal: 9 (SIGKILL)) after 3 restarts"), "{output}");
    assert!(output.contains("the run ended before its budget"), "{output}");
    let summary: serde_json::Value = serde_json::from_str(&fs::read_to_string(long.run.join("summary.json")).expect("summary.json")).unwrap();
    assert_eq!(summary["actor_restarts"], 3, "{summary}");
    assert!(summary["ended_early"].as_str().unwrap_or_default().contains("after 3 restarts"), "{summary}");
    let stored = fs::read_to_string(long.run.join("learner/metrics.csv")).unwrap().lines().count() as u64 - 1;
    let checkpoint = lcrl_learner::policy::checkpoint::latest_checkpoint(&long.run.join("learner")).expect("the learner's final checkpoint");
    assert!(lcrl_learner::policy::checkpoint::read_meta(&checkpoint).unwrap().episode as u64 >= stored, "the final checkpoint lost stored episodes");
    assert!(long.wait_for_children(Duration::from_secs(15)).is_empty(), "children left: {output}");
}
