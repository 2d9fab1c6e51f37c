//! The distributed runtime as real processes on loopback: lcrl-learner and
//! lcrl-actor over gRPC, with the faults a cluster sees.

use std::path::Path;
use std::process::{Child, Command, Stdio};
use std::time::{Duration, Instant};

use lcrl_proto::v1::learner_client::LearnerClient;
use lcrl_proto::v1::policy_client::PolicyClient;
use lcrl_proto::v1::{ActBatchRequest, ActRequest, GetStatusRequest, LearnerStatus, Transition, TransitionBatch};

use super::common::{spawn_listening, workspace_bin};

const SMALL: &str = "[network]\nglobal_hidden = [32, 32]\nsubnet_hidden = [16, 16]\ncritic_hidden = [32, 32]\n\
[ddpg]\nwarmup_steps = 100\nbatch_size = 32\n[run]\ngraph_samples = 16\n";

/// A child process killed (SIGKILL) when dropped.
pub(super) struct Proc(pub(super) Child);

impl Drop for Proc {
    fn drop(&mut self) {
        let _ = self.0.kill();
        let _ = self.0.wait();
        // A killed process leaves its shared memory behind, and nothing
        // else will clean this test's namespace.
        lcrl_proto::shm::remove_dead_nodes_of(&super::common::shm_namespace());
    }
}

impl Proc {
    pub(super) fn signal(&self, signal: &str) {
        let _ = Command::new("kill").args([format!("-{signal}"), self.0.id().to_string()]).status();
    }
}

/// A free loopback port (bound, then released for the learner to take).
pub(super) fn free_port() -> u16 {
    std::net::TcpListener::bind("127.0.0.1:0").unwrap().local_addr().unwrap().port()
}

fn learner(run_dir: &Path, run_id: &str, port: u16) -> (Proc, String) {
    learner_with(run_dir, run_id, port, "ddpg")
}

fn learner_with(run_dir: &Path, run_id: &str, port: u16, algo: &str) -> (Proc, String) {
    learner_with_args(run_dir, run_id, port, algo, &[])
}

/// A small-network learner on lti-paper (global connection) with `extra` flags.
pub(super) fn learner_with_args(run_dir: &Path, run_id: &str, port: u16, algo: &str, extra: &[&str]) -> (Proc, String) {
    learner_with_run_settings(run_dir, run_id, port, algo, "", extra)
}

/// As [`learner_with_args`], with `run` added to the config's `[run]` table.
pub(super) fn learner_with_run_settings(run_dir: &Path, run_id: &str, port: u16, algo: &str, run: &str, extra: &[&str]) -> (Proc, String) {
    let config = run_dir.with_extension("toml");
    let small = SMALL.replace("[run]\n", &format!("[run]\n{run}"));
    std::fs::write(&config, format!("{small}[ppo]\nrollout_steps = 500\nminibatch_size = 100\n")).unwrap();
    // Checkpoints every half second unless `extra` says otherwise.
    let checkpoints: &[&str] = if extra.contains(&"--checkpoint-secs") { &[] } else { &["--checkpoint-secs", "0.5"] };
    let (child, _) = spawn_listening(
        workspace_bin("lcrl-learner")
            .args(["--env", "lti-paper", "--algo", algo, "--connection", "global", "--publish-every", "20", "--run-id", run_id])
            .args(checkpoints)
            .arg("--config")
            .arg(&config)
            .arg("--run-dir")
            .arg(run_dir)
            .args(["--listen", &format!("127.0.0.1:{port}")])
            .args(extra),
    );
    (Proc(child), format!("http://127.0.0.1:{port}"))
}

fn actor(url: &str, run_id: &str) -> Proc {
    actor_over(url, run_id, "grpc")
}

fn actor_over(url: &str, run_id: &str, transport: &str) -> Proc {
    actor_with_args(url, run_id, &["--transport", transport])
}

/// An actor with 2 envs and batches of 25, with `extra` flags.
pub(super) fn actor_with_args(url: &str, run_id: &str, extra: &[&str]) -> Proc {
    Proc(
        workspace_bin("lcrl-actor")
            .args(["--learner", url, "--run-id", run_id, "--envs", "2", "--batch", "25", "--connect-deadline", "30"])
            .args(extra)
            .stdout(Stdio::null())
            .stderr(Stdio::null())
            .spawn()
            .unwrap(),
    )
}

pub(super) async fn status(url: &str) -> Option<LearnerStatus> {
    let mut client = LearnerClient::connect(url.to_string()).await.ok()?;
    Some(client.get_status(GetStatusRequest {}).await.ok()?.into_inner())
}

/// Polls the learner's status until `ready` holds (or fails after 60 s).
pub(super) async fn wait_for(url: &str, what: &str, ready: impl Fn(&LearnerStatus) -> bool) -> LearnerStatus {
    let deadline = Instant::now() + Duration::from_secs(60);
    loop {
        if let Some(s) = status(url).await {
            if ready(&s) {
                return s;
            }
        }
        assert!(Instant::now() < deadline, "timed out waiting for {what}; last status {:?}", status(url).await);
        tokio::time::sleep(Duration::from_millis(100)).await;
    }
}

pub(super) fn batch(run_id: &str, sequence: u64, state_len: usize, value: f32) -> TransitionBatch {
    TransitionBatch {
        run_id: run_id.into(),
        actor_id: "test".into(),
        sequence,
        episode_id: 0,
        policy_version: 0,
        transitions: vec![Transition { state: vec![value; state_len], action: vec![0.1; 3], reward: -1.0, next_state: vec![0.0; state_len], terminated: false, truncated: false, policy_version: 0, ..Default::default() }; 4],
        ..Default::default()
    }
}

/// Sends one batch on a fresh stream; returns the first ack or the error.
pub(super) async fn send(url: &str, batch: TransitionBatch) -> Result<lcrl_proto::v1::BatchAck, tonic::Status> {
    let mut client = LearnerClient::connect(url.to_string()).await.unwrap();
    let mut acks = client.stream_transitions(tokio_stream::iter(vec![batch])).await?.into_inner();
    acks.message().await?.ok_or_else(|| tonic::Status::unknown("no ack"))
}

#[tokio::test]
async fn actors_train_the_learner_which_serves_the_policy() {
    let dir = tempfile::tempdir().unwrap();
    let (learner_proc, url) = learner(&dir.path().join("run"), "r1", free_port());
    let _actor = actor(&url, "r1");
    let s = wait_for(&url, "updates and a published policy", |s| s.updates > 50 && s.policy_version >= 1 && s.connected_actors == 1).await;
    assert!(s.env_steps >= s.updates, "DDPG keeps at most one update per step");

    let mut policy = PolicyClient::connect(url.clone()).await.unwrap();
    // Training goes on meanwhile: compare the two calls when they were
    // answered by the same policy version (a new one may land between).
    let mut compared = false;
    for _ in 0..50 {
        let act = policy.act(ActRequest { state: vec![0.5, -0.2, 0.1] }).await.unwrap().into_inner();
        assert_eq!(act.action.len(), 3);
        assert!(act.action.iter().all(|a| (-1.0..=1.0).contains(a)) && act.policy_version >= 1);
        let many = policy.act_batch(ActBatchRequest { count: 2, states: vec![0.5, -0.2, 0.1, 0.0, 0.0, 0.0] }).await.unwrap().into_inner();
        assert_eq!(many.actions.len(), 6);
        if many.policy_version == act.policy_version {
            assert_eq!(&many.actions[..3], &act.action[..], "same state, same version, same deterministic action");
            compared = true;
            break;
        }
    }
    assert!(compared, "never two answers from the same policy version");
    let wrong = policy.act(ActRequest { state: vec![0.5, -0.2] }).await.unwrap_err();
    assert_eq!(wrong.code(), tonic::Code::InvalidArgument);
    let nan = policy.act(ActRequest { state: vec![0.5, f32::NAN, 0.1] }).await.unwrap_err();
    assert_eq!(nan.code(), tonic::Code::InvalidArgument);

    // SIGTERM: the learner checkpoints and exits cleanly.
    let episodes = status(&url).await.unwrap().episodes;
    learner_proc.signal("TERM");
    let mut learner_proc = learner_proc;
    let code = learner_proc.0.wait().unwrap();
    assert!(code.success(), "learner exit {code:?}");
    let newest = lcrl_learner::policy::checkpoint::latest_checkpoint(&dir.path().join("run")).expect("a checkpoint on SIGTERM");
    assert!(lcrl_learner::policy::checkpoint::read_meta(&newest).unwrap().episode >= episodes as usize);
}

/// run.threads reaches the thread that trains: OpenMP keeps its count per
/// thread, so a count set only where the learner starts would leave the
/// training thread with one thread per core (2 on a 2-core machine, where
/// `threads = 1` tells the two apart). The thread reads OpenMP's own count
/// (omp_get_max_threads, not libtorch's lazily set one); without the fix
/// this test read 2 for `threads = 1`.
#[tokio::test]
async fn the_training_thread_computes_with_the_configured_threads() {
    let dir = tempfile::tempdir().unwrap();
    for threads in [1, 2] {
        let (_learner, url) = learner_with_run_settings(&dir.path().join(format!("run{threads}")), "r1", free_port(), "ddpg", &format!("threads = {threads}\n"), &[]);
        let s = wait_for(&url, "the training thread", |s| s.training_threads > 0).await;
        assert_eq!(s.training_threads, threads, "run.threads = {threads}");
    }
}

#[tokio::test]
async fn bad_batches_are_rejected_counted_and_never_stored() {
    let dir = tempfile::tempdir().unwrap();
    let (_learner, url) = learner(&dir.path().join("run"), "r2", free_port());
    // Another run's batch: the sender's --run-id is wrong, which retrying
    // cannot mend (FAILED_PRECONDITION); the others are malformed.
    let cases = [
        (batch("r2", 1, 4, 0.0), "dimensions", tonic::Code::InvalidArgument),
        (batch("r2", 1, 3, f32::INFINITY), "non_finite", tonic::Code::InvalidArgument),
        (batch("other-run", 1, 3, 0.0), "unknown_run", tonic::Code::FailedPrecondition),
    ];
    for (bad, reason, code) in cases {
        let err = send(&url, bad).await.unwrap_err();
        assert_eq!(err.code(), code, "{reason}: {err:?}");
        let s = status(&url).await.unwrap();
        assert_eq!(s.rejected.get(reason), Some(&4), "{reason}: {:?}", s.rejected);
    }
    let s = status(&url).await.unwrap();
    assert_eq!((s.env_steps, s.replay_size), (0, 0));

    // A replayed batch (same actor, same sequence) is stored once.
    assert_eq!(send(&url, batch("r2", 7, 3, 0.2)).await.unwrap().outcome, "stored");
    assert_eq!(send(&url, batch("r2", 7, 3, 0.2)).await.unwrap().outcome, "duplicate");
    let s = wait_for(&url, "the stored batch", |s| s.env_steps == 4).await;
    assert_eq!(s.rejected.get("duplicate"), Some(&4));
}

#[tokio::test]
async fn a_killed_actor_can_rejoin() {
    let dir = tempfile::tempdir().unwrap();
    let (_learner, url) = learner(&dir.path().join("run"), "r3", free_port());
    // The same actor id before and after, as a restarted container has.
    let first = actor_with_args(&url, "r3", &["--actor-id", "worker-1"]);
    wait_for(&url, "first actor's transitions", |s| s.env_steps > 500).await;
    first.signal("KILL");
    drop(first);
    let after_kill = wait_for(&url, "the stream to close", |s| s.connected_actors == 0).await;
    let _second = actor_with_args(&url, "r3", &["--actor-id", "worker-1"]);
    let s = wait_for(&url, "the new actor's transitions", |s| s.env_steps > after_kill.env_steps + 200 && s.connected_actors == 1).await;
    assert!(s.updates >= after_kill.updates);
    assert_eq!(s.rejected.get("duplicate"), None, "the restarted actor's batches are new, not replays");
}

#[tokio::test]
async fn a_killed_learner_resumes_and_actors_reconnect() {
    let dir = tempfile::tempdir().unwrap();
    let run = dir.path().join("run");
    let port = free_port();
    let (first, url) = learner(&run, "r4", port);
    let _actor = actor(&url, "r4");
    wait_for(&url, "training", |s| s.episodes >= 15 && s.policy_version >= 1).await;
    // Wait for a checkpoint on disk that holds that progress.
    let deadline = Instant::now() + Duration::from_secs(30);
    let saved = loop {
        let meta = lcrl_learner::policy::checkpoint::latest_checkpoint(&run).and_then(|dir| lcrl_learner::policy::checkpoint::read_meta(&dir).ok());
        match meta {
            Some(meta) if meta.episode >= 15 && meta.policy_version >= 1 => break meta,
            _ => {
                assert!(Instant::now() < deadline, "no checkpoint with progress");
                tokio::time::sleep(Duration::from_millis(100)).await;
            }
        }
    };
    first.signal("KILL");
    drop(first);
    let (_second, url) = learner(&run, "r4", port);
    let resumed = status(&url).await.unwrap();
    assert!(resumed.episodes as usize >= saved.episode && resumed.policy_version >= saved.policy_version, "{resumed:?} vs {saved:?}");
    assert!(resumed.env_steps > 0, "the replay buffer came back");
    // The actor finds the new learner by itself.
    wait_for(&url, "the actor to reconnect", |s| s.connected_actors == 1 && s.env_steps > resumed.env_steps + 100).await;
}

#[test]
fn an_unreachable_learner_stops_the_actor_after_its_deadline() {
    let started = Instant::now();
    let out = workspace_bin("lcrl-actor")
        .args(["--learner", &format!("http://127.0.0.1:{}", free_port()), "--connect-deadline", "2"])
        .output()
        .unwrap();
    let err = String::from_utf8_lossy(&out.stderr);
    assert!(!out.status.success());
    assert!(err.contains("retrying"), "a clear retry line: {err}");
    assert!(err.contains("stayed unreachable for 2 s"), "{err}");
    assert!(started.elapsed() < Duration::from_secs(20));
}

#[tokio::test]
async fn runs_with_different_ids_do_not_mix() {
    let dir = tempfile::tempdir().unwrap();
    let (_a, url_a) = learner(&dir.path().join("a"), "run-a", free_port());
    let (_b, url_b) = learner(&dir.path().join("b"), "run-b", free_port());
    // An actor of run-a pointed at run-b's learner: every batch is refused.
    let _stray = actor(&url_b, "run-a");
    let _proper = actor(&url_a, "run-a");
    wait_for(&url_a, "run-a's transitions", |s| s.env_steps > 200).await;
    let b = wait_for(&url_b, "run-b's refusals", |s| s.rejected.get("unknown_run").copied().unwrap_or(0) > 0).await;
    assert_eq!(b.env_steps, 0, "nothing of run-a reached run-b");
}

/// The Python client (grpcio, stubs generated from proto/lcrl.proto by
/// scripts/setup.sh) checks health and gets an action from a real learner.
#[test]
fn python_client_queries_the_policy() {
    let dir = tempfile::tempdir().unwrap();
    let port = free_port();
    let (_learner, _url) = learner(&dir.path().join("run"), "py", port);
    let root = Path::new(env!("CARGO_MANIFEST_DIR"));
    let python = root.join(".venv/bin/python");
    assert!(python.is_file(), "run scripts/setup.sh first (it installs grpcio and generates the stubs)");
    let script = root.join("clients/python/lcrl_client.py");
    let run = |state: &[&str]| Command::new(&python).arg(&script).args(["--target", &format!("127.0.0.1:{port}"), "--state"]).args(state).output().unwrap();
    let out = run(&["0.1", "0.2", "0.3"]);
    let text = String::from_utf8_lossy(&out.stdout);
    assert!(out.status.success(), "{text}{}", String::from_utf8_lossy(&out.stderr));
    assert!(text.contains("health lcrl.v1.Policy: SERVING"), "{text}");
    let action: Vec<f64> = text.lines().find_map(|l| l.strip_prefix("action ")).unwrap().split_whitespace().map(|v| v.parse().unwrap()).collect();
    assert_eq!(action.len(), 3);
    assert!(action.iter().all(|a| (-1.0..=1.0).contains(a)));
    let wrong = run(&["0.1", "0.2"]);
    assert_eq!(wrong.status.code(), Some(2));
    assert!(String::from_utf8_lossy(&wrong.stderr).contains("INVALID_ARGUMENT"));
}

/// One learner a run id on a host (issue 82: two learners under one run id
/// both took every transition, and the actors' policy flip-flopped between
/// them): a second learner under a live one's run id exits at once with
/// the run id and what to do, before it listens, and the first goes on
/// storing its actor's steps.
#[tokio::test]
async fn a_second_learner_under_a_live_run_id_is_refused() {
    let dir = tempfile::tempdir().unwrap();
    let id = format!("one-learner-{}", std::process::id());
    let (_first, url) = learner(&dir.path().join("first"), &id, free_port());
    let _actor = actor_over(&url, &id, "shm");
    let before = wait_for(&url, "the first learner's steps", |s| s.env_steps > 100).await;
    let out = workspace_bin("lcrl-learner")
        .args(["--env", "lti-paper", "--algo", "ddpg", "--connection", "global", "--run-id", &id, "--listen", "127.0.0.1:0", "--run-dir"])
        .arg(dir.path().join("second"))
        .output()
        .unwrap();
    super::common::assert_clean_failure(&out, &format!("already serves run id '{id}'"));
    assert!(String::from_utf8_lossy(&out.stderr).contains("--run-id"), "{}", String::from_utf8_lossy(&out.stderr));
    assert!(!String::from_utf8_lossy(&out.stdout).contains("listening on"), "it never served");
    wait_for(&url, "the first learner storing on", |s| s.env_steps > before.env_steps + 100 && s.rejected.values().sum::<u64>() == 0).await;
}

/// Same-host actors over iceoryx2: transitions flow, a SIGKILLed actor's
/// shared memory is cleaned up and a new one flows again, and another run's
/// actor publishes into its own service, never this learner's.
#[tokio::test]
async fn shared_memory_actors_feed_their_own_run_only() {
    let dir = tempfile::tempdir().unwrap();
    let (id_a, id_b) = (format!("shm-a-{}", std::process::id()), format!("shm-b-{}", std::process::id()));
    let (_a, url_a) = learner(&dir.path().join("a"), &id_a, free_port());
    let (_b, url_b) = learner(&dir.path().join("b"), &id_b, free_port());
    let first = actor_over(&url_a, &id_a, "shm");
    let s = wait_for(&url_a, "shared-memory transitions", |s| s.env_steps > 500 && s.updates > 0).await;
    assert_eq!(s.rejected.values().sum::<u64>(), 0);
    // A same-host actor counts as connected (issue 85: it read 0).
    wait_for(&url_a, "the shared-memory actor counted", |s| s.connected_actors == 1).await;
    let services = lcrl_proto::shm::services_of_in(&super::common::shm_namespace(), &id_a);
    assert!(services.contains(&format!("lcrl/{id_a}/transitions")) && services.contains(&format!("lcrl/{id_a}/policy")), "{services:?}");
    first.signal("KILL");
    drop(first);
    let after = status(&url_a).await.unwrap().env_steps;
    let _second = actor_over(&url_a, &id_a, "shm");
    wait_for(&url_a, "the restarted actor's transitions", |s| s.env_steps > after + 500).await;
    let b = status(&url_b).await.unwrap();
    assert_eq!((b.env_steps, b.episodes), (0, 0), "run B saw run A's transitions");
}

/// PPO keeps only batches at most one version old, so the learner can get
/// several versions ahead only if the shared-memory actor receives each new
/// policy from the broadcast.
#[tokio::test]
async fn shared_memory_actor_follows_new_policies() {
    let dir = tempfile::tempdir().unwrap();
    let run_id = format!("shm-ppo-{}", std::process::id());
    let (_learner, url) = learner_with(&dir.path().join("run"), &run_id, free_port(), "ppo");
    let _actor = actor_over(&url, &run_id, "shm");
    let s = wait_for(&url, "several PPO policy versions", |s| s.policy_version >= 4).await;
    // Four PPO updates, each on a full rollout of 500 stored steps.
    assert!(s.env_steps >= 4 * 500, "{s:?}");
}

/// One writer per run directory (issue 82): while a learner holds its run,
/// a second learner and `lcrl train` on the same directory fail at once,
/// naming the holder, and the first learner goes on with its files intact.
#[tokio::test]
async fn a_second_writer_of_a_run_directory_is_refused_naming_the_holder() {
    let dir = tempfile::tempdir().unwrap();
    let run = dir.path().join("run");
    let (first, url) = learner(&run, "r1", free_port());
    let _actor = actor(&url, "r1");
    wait_for(&url, "stored episodes", |s| s.episodes >= 2).await;
    let holder = format!("pid {}", first.0.id());
    let second = workspace_bin("lcrl-learner")
        .args(["--env", "lti-paper", "--algo", "ddpg", "--connection", "global", "--run-id", "r2", "--listen", "127.0.0.1:0", "--run-dir"])
        .arg(&run)
        .stdout(Stdio::piped())
        .stderr(Stdio::piped())
        .output()
        .unwrap();
    let said = String::from_utf8_lossy(&second.stderr).to_string();
    assert!(!second.status.success() && said.contains("is in use by another run") && said.contains(&holder), "{said}");
    let train = workspace_bin("lcrl").args(["train", "--env", "lti-paper", "--algo", "ddpg", "--connection", "global", "--episodes", "2", "--resume", "--run-dir"]).arg(&run).output().unwrap();
    let said = String::from_utf8_lossy(&train.stderr).to_string();
    assert!(!train.status.success() && said.contains("is in use by another run") && said.contains(&holder), "{said}");
    // The holder still trains and stores.
    let before = status(&url).await.unwrap().episodes;
    wait_for(&url, "more episodes after the refusals", |s| s.episodes > before).await;
}

/// No peer can pre-claim an actor's id (issue 82): a batch whose sequence
/// runs far ahead of the clock is refused and not remembered, so the
/// honest actor of that id stores at once; one just inside the bound holds
/// the actor's batches as duplicates for seconds only, and the actor says
/// so in its log.
#[tokio::test]
async fn a_pre_claimed_actor_id_stores_within_seconds() {
    let now = || std::time::SystemTime::now().duration_since(std::time::UNIX_EPOCH).unwrap().as_micros() as u64;
    let dir = tempfile::tempdir().unwrap();
    let (_learner, url) = learner(&dir.path().join("run"), "r1", free_port());
    let far = TransitionBatch { actor_id: "a1".into(), ..batch("r1", now() + 59 * 60 * 1_000_000, 3, 0.1) };
    let refused = send(&url, far).await.unwrap_err();
    assert_eq!(refused.code(), tonic::Code::InvalidArgument, "{refused:?}");
    assert!(refused.message().contains("ahead of this learner's clock"), "{refused:?}");
    let near = TransitionBatch { actor_id: "a1".into(), ..batch("r1", now() + 8_000_000, 3, 0.1) };
    assert_eq!(send(&url, near).await.unwrap().outcome, "stored");
    let stored_before = status(&url).await.unwrap().env_steps;
    let log = dir.path().join("actor.log");
    let _actor = Proc(
        workspace_bin("lcrl-actor")
            .args(["--learner", &url, "--run-id", "r1", "--actor-id", "a1", "--envs", "2", "--batch", "25", "--transport", "grpc"])
            .stdout(Stdio::null())
            .stderr(std::fs::File::create(&log).unwrap())
            .spawn()
            .unwrap(),
    );
    let started = Instant::now();
    wait_for(&url, "the honest actor's steps stored", |s| s.env_steps > stored_before + 100).await;
    assert!(started.elapsed() < Duration::from_secs(30), "the honest actor waited {:?}", started.elapsed());
    let said = std::fs::read_to_string(&log).unwrap();
    assert!(said.contains("as duplicates and stored none: a sender has used this actor id"), "{said}");
}
