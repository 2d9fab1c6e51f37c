//! A bounded load test of hostile clients against a real learner with a
//! token: many concurrent streams of wrong-run, non-finite, oversize and
//! undecodable batches and wrong tokens, while a well-behaved actor trains.
//! Every bad stream is refused with a status and counted, the learner's
//! memory stays bounded, and the actor's steps keep growing throughout.

use std::time::Duration;

use bytes::{Buf, BufMut};
use lcrl_runtime::security::ClientSecurity;
use lcrl_proto::v1::learner_client::LearnerClient;
use lcrl_proto::v1::{GetPolicyRequest, GetStatusRequest, LearnerStatus, Transition, TransitionBatch, WatchPolicyRequest};
use tonic::codec::{Codec, DecodeBuf, Decoder, EncodeBuf, Encoder};
use tonic::Status;

use super::distributed::{actor_with_args, batch, free_port, learner_with_args};
use super::observability::{sample, scrape};

/// Sends raw bytes as messages: what a broken or malicious client writes.
#[derive(Clone, Default)]
struct RawCodec;

impl Codec for RawCodec {
    type Encode = Vec<u8>;
    type Decode = Vec<u8>;
    type Encoder = RawCodec;
    type Decoder = RawCodec;
    fn encoder(&mut self) -> RawCodec {
        RawCodec
    }
    fn decoder(&mut self) -> RawCodec {
        RawCodec
    }
}

impl Encoder for RawCodec {
    type Item = Vec<u8>;
    type Error = Status;
    fn encode(&mut self, item: Vec<u8>, dst: &mut EncodeBuf<'_>) -> Result<(), Status> {
        dst.put_slice(&item);
        Ok(())
    }
}

impl Decoder for RawCodec {
    type Item = Vec<u8>;
    type Error = Status;
    fn decode(&mut self, src: &mut DecodeBuf<'_>) -> Result<Option<Vec<u8>>, Status> {
        let bytes = src.chunk().to_vec();
        src.advance(bytes.len());
        Ok(Some(bytes))
    }
}

pub(super) fn rss_kib(pid: u32) -> u64 {
    let status = std::fs::read_to_string(format!("/proc/{pid}/status")).unwrap();
    status.lines().find_map(|l| l.strip_prefix("VmRSS:")).and_then(|v| v.split_whitespace().next()?.parse().ok()).unwrap()
}

async fn status(url: &str, security: &ClientSecurity) -> LearnerStatus {
    let mut client = LearnerClient::new(security.connect(url).await.unwrap());
    client.get_status(GetStatusRequest {}).await.unwrap().into_inner()
}

/// Sends `batches` on one stream; the first refusal's status code.
pub(super) async fn send_all(url: &str, security: &ClientSecurity, batches: Vec<TransitionBatch>) -> Option<tonic::Code> {
    let mut client = LearnerClient::new(security.connect(url).await.ok()?).max_encoding_message_size(64 << 20);
    match client.stream_transitions(tokio_stream::iter(batches)).await {
        Err(status) => Some(status.code()),
        Ok(response) => {
            let mut acks = response.into_inner();
            loop {
                match acks.message().await {
                    Ok(Some(_)) => continue,
                    Ok(None) => return None,
                    Err(status) => return Some(status.code()),
                }
            }
        }
    }
}

async fn send_garbage(url: &str, security: &ClientSecurity) -> Option<tonic::Code> {
    let channel = security.connect(url).await.ok()?;
    let mut grpc = tonic::client::Grpc::new(channel);
    grpc.ready().await.ok()?;
    let garbage = vec![vec![0xff_u8; 64], b"\x0a\xff\xff\xff\xff\xff\xff\xff\xff\xff\xff".to_vec()];
    let path = tonic::codegen::http::uri::PathAndQuery::from_static("/lcrl.v1.Learner/StreamTransitions");
    match grpc.streaming(tonic::Request::new(tokio_stream::iter(garbage)), path, RawCodec).await {
        Err(status) => Some(status.code()),
        Ok(response) => response.into_inner().message().await.err().map(|s| s.code()),
    }
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn hostile_streams_are_refused_and_counted_while_actors_train() {
    let dir = tempfile::tempdir().unwrap();
    let token = dir.path().join("token");
    std::fs::write(&token, "load-test-token-0123456789abcdef\n").unwrap();
    let wrong = dir.path().join("wrong");
    std::fs::write(&wrong, "another-token-0123456789abcdef\n").unwrap();
    let port = free_port();
    let token_flag = token.display().to_string();
    let metrics_port = free_port();
    let metrics_flag = format!("127.0.0.1:{metrics_port}");
    let (learner, url) = learner_with_args(&dir.path().join("run"), "load", port, "ddpg", &["--token-file", &token_flag, "--metrics-listen", &metrics_flag]);
    let good = ClientSecurity::new(None, None, Some(&token)).unwrap();
    let _actor = actor_with_args(&url, "load", &["--token-file", &token_flag]);
    let deadline = std::time::Instant::now() + Duration::from_secs(60);
    while status(&url, &good).await.env_steps < 300 {
        assert!(std::time::Instant::now() < deadline, "the actor never trained");
        tokio::time::sleep(Duration::from_millis(100)).await;
    }
    let rss_before = rss_kib(learner.0.id());
    let steps_before = status(&url, &good).await.env_steps;

    // 60 hostile streams at once.
    // Waves of 66 hostile streams at once: at least 4 s of attack, and on
    // until the actor has stored something during it (at most 60 s; on a
    // loaded machine its steps come slowly, but they must come).
    let wrong_token = ClientSecurity::new(None, None, Some(&wrong)).unwrap();
    let attack_started = std::time::Instant::now();
    let mut waves = 0u64;
    let mut outcomes: std::collections::BTreeMap<&str, Vec<Option<tonic::Code>>> = Default::default();
    let mut progressed = false;
    while waves == 0 || attack_started.elapsed() < Duration::from_secs(4) || (!progressed && attack_started.elapsed() < Duration::from_secs(60)) {
        waves += 1;
        let mut tasks = tokio::task::JoinSet::new();
        let mut spawn = |what: &'static str, security: &ClientSecurity, batches: Option<Vec<TransitionBatch>>| {
            let (url, security) = (url.clone(), security.clone());
            tasks.spawn(async move {
                let code = match batches {
                    Some(batches) => send_all(&url, &security, batches).await,
                    None => send_garbage(&url, &security).await,
                };
                (what, code)
            });
        };
        for k in 0..30u64 {
            spawn("unknown_run", &good, Some(vec![batch("someone-else", k, 3, 0.5); 3]));
        }
        for k in 0..10u64 {
            spawn("non_finite", &good, Some(vec![batch("load", 1_000_000 + k, 3, f32::NAN)]));
            spawn("dimensions", &good, Some(vec![batch("load", 2_000_000 + k, 7, 0.5)]));
        }
        for _ in 0..4 {
            // 17 MB: over the learner's 16 MB message limit.
            let huge = TransitionBatch { transitions: vec![Transition { state: vec![0.5; 1 << 20], ..Default::default() }; 4], ..batch("load", 3_000_000, 3, 0.5) };
            spawn("oversize", &good, Some(vec![huge]));
            spawn("undecodable", &good, None);
            spawn("wrong_token", &wrong_token, Some(vec![batch("load", 4_000_000, 3, 0.5)]));
        }
        drop(spawn);
        while let Some(done) = tasks.join_next().await {
            let (what, code) = done.unwrap();
            outcomes.entry(what).or_default().push(code);
        }
        progressed = status(&url, &good).await.env_steps > steps_before;
    }
    let attack_seconds = attack_started.elapsed().as_secs_f64();
    let expected = [
        // Another run's batch: the sender's --run-id is wrong, and retrying
        // cannot mend it.
        ("unknown_run", tonic::Code::FailedPrecondition),
        ("non_finite", tonic::Code::InvalidArgument),
        ("dimensions", tonic::Code::InvalidArgument),
        ("oversize", tonic::Code::ResourceExhausted),
        ("undecodable", tonic::Code::Internal),
        ("wrong_token", tonic::Code::Unauthenticated),
    ];
    for (what, code) in expected {
        assert!(outcomes[what].iter().all(|c| *c == Some(code)), "{what}: {:?}", outcomes[what]);
    }
    let after = status(&url, &good).await;
    for (reason, at_least) in [("unknown_run", 30 * 4), ("non_finite", 10 * 4), ("dimensions", 10 * 4), ("oversize", 4), ("undecodable", 4)] {
        assert!(after.rejected.get(reason).copied().unwrap_or(0) >= at_least * waves, "{reason} after {waves} waves: {:?}", after.rejected);
    }
    assert!(after.unauthenticated["wrong_token"] >= 4 * waves, "{:?}", after.unauthenticated);
    // The same counts in /metrics.
    let text = scrape(metrics_port);
    let value = |series: &str| sample(&text, series).unwrap_or_else(|| panic!("{series} missing from\n{text}"));
    assert!(value("lcrl_learner_unauthenticated_total{reason=\"wrong_token\"}") >= 4.0);
    assert!(value("lcrl_learner_transitions_rejected_total{reason=\"oversize\"}") >= 4.0);
    // The actor trained through the attack, and goes on after it.
    assert!(after.env_steps > steps_before, "the actor's steps went {steps_before} → {} during {attack_seconds:.1} s of attack ({waves} waves)", after.env_steps);
    let deadline = std::time::Instant::now() + Duration::from_secs(30);
    while status(&url, &good).await.env_steps < after.env_steps + 200 {
        assert!(std::time::Instant::now() < deadline, "the actor stopped training after the attack");
        tokio::time::sleep(Duration::from_millis(100)).await;
    }
    let grown_mib = rss_kib(learner.0.id()).saturating_sub(rss_before) / 1024;
    assert!(grown_mib < 256, "the learner grew by {grown_mib} MiB under the attack");
}

/// A graph builder that serves a malformed graph: G one entry short of the
/// environment's 3 × 3.
struct ShortGraph;

#[tonic::async_trait]
impl lcrl_proto::v1::graph_server::Graph for ShortGraph {
    type WatchGraphStream = tokio_stream::Empty<Result<lcrl_proto::v1::ConnectionGraph, Status>>;

    async fn get_graph(&self, _: tonic::Request<lcrl_proto::v1::GetGraphRequest>) -> Result<tonic::Response<lcrl_proto::v1::ConnectionGraph>, Status> {
        let graph = lcrl_proto::v1::ConnectionGraph { env: "lti-paper".into(), actions: 3, states: 3, g: vec![1, 0, 0, 1, 1, 0, 0, 0], ..Default::default() };
        Ok(tonic::Response::new(graph))
    }

    async fn watch_graph(&self, _: tonic::Request<lcrl_proto::v1::WatchGraphRequest>) -> Result<tonic::Response<Self::WatchGraphStream>, Status> {
        Ok(tonic::Response::new(tokio_stream::empty()))
    }
}

/// The learner refuses a malformed graph from a hostile graph builder with
/// a clear error and a non-zero exit, instead of reshaping it into a
/// network (a panic in `Tensor::view`) or retrying forever.
/// WatchPolicy streams share one memory budget (issue 71): with
/// `--watch-budget-mib 1`, the learner serves as many streams as the budget
/// holds at twice the policy and 64 KiB each, refuses the next with
/// RESOURCE_EXHAUSTED naming the flag, and an ended stream frees its place.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn watch_policy_streams_share_one_memory_budget() {
    let dir = tempfile::tempdir().unwrap();
    let (_learner, url) = learner_with_args(&dir.path().join("run"), "watch-budget", free_port(), "ddpg", &["--watch-budget-mib", "1"]);
    let mut client = LearnerClient::connect(url).await.unwrap();
    let policy_bytes = client.get_policy(GetPolicyRequest {}).await.unwrap().into_inner().weights.len();
    let holds = 1024 / lcrl_learner::service::watch_budget::WatchBudget::cost_kib(policy_bytes) as usize;
    assert!(holds >= 2, "a {policy_bytes}-byte policy: the test needs room for two streams");
    let mut streams = Vec::new();
    let refused = loop {
        match client.watch_policy(WatchPolicyRequest::default()).await {
            Ok(response) => {
                let mut stream = response.into_inner();
                assert!(stream.message().await.unwrap().is_some(), "an admitted stream gets the policy");
                streams.push(stream);
            }
            Err(status) => break status,
        }
        assert!(streams.len() <= holds, "more streams than the budget holds");
    };
    assert_eq!(streams.len(), holds);
    assert_eq!(refused.code(), tonic::Code::ResourceExhausted, "{refused:?}");
    assert!(refused.message().contains("--watch-budget-mib"), "{}", refused.message());
    // The client's reset reaches the server's stream soon after: polled,
    // with a bound.
    drop(streams.pop());
    let mut admitted = false;
    for _ in 0..100 {
        if client.watch_policy(WatchPolicyRequest::default()).await.is_ok() {
            admitted = true;
            break;
        }
        tokio::time::sleep(Duration::from_millis(50)).await;
    }
    assert!(admitted, "an ended stream's place is free again");
}

#[tokio::test]
async fn a_malformed_graph_from_a_graph_builder_is_refused() {
    let listener = tokio::net::TcpListener::bind("127.0.0.1:0").await.unwrap();
    let url = format!("http://{}", listener.local_addr().unwrap());
    let server = tokio::spawn(
        tonic::transport::Server::builder()
            .add_service(lcrl_proto::v1::graph_server::GraphServer::new(ShortGraph))
            .serve_with_incoming(tokio_stream::wrappers::TcpListenerStream::new(listener)),
    );
    let work = tempfile::tempdir().unwrap();
    let run_dir = work.path().join("learner");
    let mut learner = super::common::workspace_bin("lcrl-learner");
    learner.args(["--env", "lti-paper", "--algo", "ddpg", "--connection", "local", "--listen", "127.0.0.1:0", "--graph-timeout", "20", "--graph-builder", &url]);
    learner.arg("--run-dir").arg(&run_dir);
    // Waited for off the runtime's thread, which serves the graph meanwhile.
    let out = tokio::task::spawn_blocking(move || learner.output()).await.unwrap().unwrap();
    server.abort();
    super::common::assert_clean_failure(&out, "G has 8 entries but a 3×3 graph needs 9");
    assert!(!run_dir.join("checkpoints").exists(), "no training started on the malformed graph");
}

/// Whatever a user types on a command line is refused with an error that
/// names the option and what it accepts, a non-zero exit and no panic:
/// durations that would overflow the clock (`Duration::from_secs_f64(1e300)`,
/// `Instant::now() + u64::MAX s` used to panic), NaN noise (used to be
/// accepted silently), counts that would allocate or fork without bound,
/// and an `lti-blocks-N` whose N would not fit in memory (used to abort).
/// A missing `--config` file is reported once, not its cause twice.
#[test]
fn bad_numbers_on_the_command_line_are_refused_without_a_panic() {
    use super::common::{assert_clean_failure, lcrl, stderr, workspace_bin};
    let work = tempfile::tempdir().unwrap();
    let run_dir = work.path().join("learner");
    let run_dir = run_dir.to_str().unwrap();
    let learner = |extra: &[&str]| {
        let mut cmd = workspace_bin("lcrl-learner");
        cmd.args(["--env", "lti-paper", "--algo", "ddpg", "--listen", "127.0.0.1:0", "--run-dir", run_dir]).args(extra);
        cmd
    };
    let actor = |extra: &[&str]| {
        let mut cmd = workspace_bin("lcrl-actor");
        // Nothing listens on port 1: an accepted value would fail later
        // (within a second), with another message.
        cmd.args(["--learner", "http://127.0.0.1:1"]).args(extra);
        cmd
    };
    let graph_builder = |extra: &[&str]| {
        let mut cmd = workspace_bin("lcrl-graph-builder");
        cmd.args(["--listen", "127.0.0.1:0"]).args(extra);
        cmd
    };
    let cases: Vec<(std::process::Command, &[&str])> = vec![
        (learner(&["--connection", "global", "--checkpoint-secs", "1e300"]), &["--checkpoint-secs", "604800"]),
        (learner(&["--connection", "global", "--checkpoint-secs", "nan"]), &["--checkpoint-secs", "604800"]),
        (learner(&["--connection", "global", "--checkpoint-secs", "0"]), &["--checkpoint-secs", "above 0"]),
        (learner(&["--connection", "local", "--graph-builder", "http://127.0.0.1:1", "--graph-timeout", "18446744073709551615"]), &["--graph-timeout", "86400"]),
        ({
            let mut cmd = workspace_bin("lcrl-learner");
            cmd.args(["--env", "lti-blocks-1099511627776", "--algo", "ddpg", "--connection", "global", "--run-dir", run_dir]);
            cmd
        }, &["lti-blocks-N", "256"]),
        (actor(&["--connect-deadline", "18446744073709551615"]), &["--connect-deadline", "86400"]),
        (actor(&["--connect-deadline", "0"]), &["--connect-deadline", "86400"]),
        (actor(&["--noise", "nan"]), &["--noise", "finite"]),
        (actor(&["--noise=-1"]), &["--noise", "≥ 0"]),
        (actor(&["--noise", "inf"]), &["--noise", "finite"]),
        (actor(&["--envs", "100000000000"]), &["--envs", "1024"]),
        (actor(&["--batch", "0"]), &["--batch", "4096"]),
        (graph_builder(&["--env", "lti-paper", "--samples", "18446744073709551615"]), &["--samples", "100000000"]),
        (graph_builder(&["--env", "lti-paper", "--threads", "1000000000"]), &["--threads", "1024"]),
        (graph_builder(&["--env", "lti-blocks-1099511627776"]), &["lti-blocks-N", "256"]),
        ({
            let mut cmd = lcrl();
            cmd.args(["health", "http://127.0.0.1:1", "--timeout", "1e300"]);
            cmd
        }, &["--timeout", "3600"]),
        ({
            let mut cmd = lcrl();
            cmd.args(["run", "--config", concat!(env!("CARGO_MANIFEST_DIR"), "/configs/lti-paper.toml"), "--actors", "1000000", "--check"]);
            cmd
        }, &["job.actors", "256"]),
        ({
            let mut cmd = lcrl();
            cmd.args(["bench", "busy", "--seconds", "0.5"]);
            cmd
        }, &["--seconds", "600"]),
        ({
            let mut cmd = lcrl();
            cmd.args(["bench", "learner", "--rounds", "0"]);
            cmd
        }, &["--rounds", "50"]),
    ];
    for (mut cmd, needles) in cases {
        let shown = format!("{cmd:?}");
        let out = cmd.output().unwrap();
        assert_clean_failure(&out, needles[0]);
        let err = stderr(&out);
        for needle in needles {
            assert!(err.contains(needle), "{shown}: the error should say {needle:?}: {err}");
        }
    }
    assert!(!std::path::Path::new(run_dir).join("checkpoints").exists(), "nothing trained on a refused option");

    // `--config missing.toml`: one error line, the OS's reason once.
    let missing = work.path().join("missing.toml");
    let missing = missing.to_str().unwrap();
    let mut train = lcrl();
    train.args(["train", "--env", "lti-paper", "--algo", "ddpg", "--connection", "global", "--config", missing]).arg("--run-dir").arg(work.path().join("train"));
    for mut cmd in [learner(&["--connection", "global", "--config", missing]), train] {
        let out = cmd.output().unwrap();
        assert_clean_failure(&out, "missing.toml");
        let err = stderr(&out);
        assert_eq!(err.matches("No such file or directory").count(), 1, "the cause is printed once: {err}");
    }
}

/// Every number a peer can send that is finite but huge (issue 71: states
/// of 3e38 once made every weight NaN, and the NaN checkpoints were resumed
/// from): states of 3e38 and 1e12, sampled actions of 1e12, a reward of
/// 3e38, a claimed episode return of 1e308 and a sequence of 2⁶⁴ − 1 are
/// each refused and counted, training goes on beside an honest actor, the
/// served policy acts finitely, and no checkpoint on disk holds a NaN or ∞.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn huge_but_finite_numbers_are_refused_and_no_checkpoint_holds_a_non_finite_number() {
    use lcrl_proto::v1::{policy_client::PolicyClient, ActRequest, EpisodeSummary};
    use super::distributed::{send, wait_for};
    let dir = tempfile::tempdir().unwrap();
    let run = dir.path().join("run");
    let (_learner, url) = learner_with_args(&run, "huge", free_port(), "ddpg", &[]);
    let _actor = actor_with_args(&url, "huge", &["--actor-id", "honest"]);
    wait_for(&url, "updates", |s| s.updates > 20).await;
    let from = |id: &str, sequence: u64, state: f32| TransitionBatch { actor_id: id.into(), ..batch("huge", sequence, 3, state) };
    let mut huge_action = from("evil-action", 1, 0.1);
    // The agent's own sample: an applied action is clipped into the
    // environment's box as the environment clips it, and stored.
    huge_action.transitions.iter_mut().for_each(|t| t.sampled_action = vec![1e12; 3]);
    let mut huge_reward = from("evil-reward", 1, 0.1);
    huge_reward.transitions.iter_mut().for_each(|t| t.reward = 3e38);
    let mut huge_return = from("evil-return", 1, 0.1);
    huge_return.transitions.truncate(1);
    huge_return.transitions[0].terminated = true;
    huge_return.episodes = vec![EpisodeSummary { episode_return: 1e308, length: 1, ..Default::default() }];
    let attacks = [
        ("states 3e38", from("evil-3e38", 1, 3e38), "bounds"),
        ("states 1e12", from("evil-1e12", 1, 1e12), "bounds"),
        ("sampled actions 1e12", huge_action, "bounds"),
        ("reward 3e38", huge_reward, "bounds"),
        ("return 1e308", huge_return, "returns"),
        ("sequence 2^64 - 1", from("evil-sequence", u64::MAX, 0.1), "sequence"),
    ];
    let before = status(&url, &ClientSecurity::default()).await;
    for (what, batch, _) in &attacks {
        let refused = send(&url, batch.clone()).await.expect_err(what);
        assert_eq!(refused.code(), tonic::Code::InvalidArgument, "{what}: {refused:?}");
    }
    let after = wait_for(&url, "training after the attacks", |s| s.updates > before.updates + 100 && s.env_steps > before.env_steps).await;
    // Refusals count transitions: each batch's, under its own reason.
    for reason in ["bounds", "returns", "sequence"] {
        let expected: u64 = attacks.iter().filter(|(_, _, r)| *r == reason).map(|(_, b, _)| b.transitions.len() as u64).sum();
        let counted = after.rejected.get(reason).copied().unwrap_or(0) - before.rejected.get(reason).copied().unwrap_or(0);
        assert_eq!(counted, expected, "{reason}: {:?}", after.rejected);
    }
    assert!(after.recent_return.is_finite() && after.recent_return.abs() < 1e6, "recent return {}", after.recent_return);
    let action = PolicyClient::connect(url.clone()).await.unwrap().act(ActRequest { state: vec![0.1, 0.2, 0.3], ..Default::default() }).await.unwrap().into_inner().action;
    assert!(action.iter().all(|a| a.is_finite()), "{action:?}");
    // Checkpoints every half second: the ones written after the attacks are
    // on disk by now. A folder pruned while it is read is skipped.
    tokio::time::sleep(Duration::from_secs(1)).await;
    let mut scanned = 0;
    for file in glob::glob(&format!("{}/**/*.safetensors", run.display())).unwrap().flatten() {
        let Ok(tensors) = tch::Tensor::read_safetensors(&file) else { continue };
        for (name, t) in tensors.iter().filter(|(_, t)| t.is_floating_point()) {
            assert!(bool::try_from(t.isfinite().all()).unwrap(), "{}: {name} holds a non-finite number", file.display());
        }
        scanned += 1;
    }
    assert!(scanned > 0, "no checkpoint under {}", run.display());
}

/// Requests share one memory budget (issue 71: unfinished messages on
/// every stream once could hold 16 GiB): each stream holds the largest
/// message it has declared until it ends. With `--request-budget-mib 1`,
/// streams that each sent one batch and stay open are admitted while the
/// budget holds them; the next is refused with RESOURCE_EXHAUSTED naming
/// the flag and counted as `request_budget`, and an ended stream's share
/// is free again. A budget whose peer quarter cannot hold one batch is
/// refused at start.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn requests_share_one_memory_budget() {
    use prost::Message;
    let dir = tempfile::tempdir().unwrap();
    let (_learner, url) = learner_with_args(&dir.path().join("run"), "budget", free_port(), "ddpg", &["--request-budget-mib", "1", "--max-batch-bytes", "200000"]);
    let sized = |k: usize| {
        let mut b = TransitionBatch { actor_id: format!("holder-{k}"), ..batch("budget", 1, 3, 0.5) };
        let one = b.transitions[0].clone();
        b.transitions = vec![one; 1500];
        b
    };
    let held = 5 + sized(0).encoded_len();
    let holds = (1 << 20) / held;
    assert!((3..40).contains(&holds), "a {held}-byte batch: the test wants a few streams");
    let mut open = Vec::new();
    let refused = loop {
        let mut client = LearnerClient::connect(url.clone()).await.unwrap();
        let (tx, rx) = tokio::sync::mpsc::channel(1);
        tx.send(sized(open.len())).await.unwrap();
        let mut acks = client.stream_transitions(tokio_stream::wrappers::ReceiverStream::new(rx)).await.unwrap().into_inner();
        match acks.message().await {
            Ok(Some(_)) => open.push((tx, acks)),
            Ok(None) => panic!("stream {} ended without an ack", open.len()),
            Err(status) => break status,
        }
        assert!(open.len() <= holds, "more open streams than the budget holds");
    };
    assert_eq!(open.len(), holds, "{held} bytes a stream");
    assert_eq!(refused.code(), tonic::Code::ResourceExhausted, "{refused:?}");
    assert!(refused.message().starts_with(lcrl_runtime::request_budget::BUDGET_SPENT) && refused.message().contains("--request-budget-mib"), "{}", refused.message());
    assert_eq!(status(&url, &ClientSecurity::default()).await.rejected.get("request_budget"), Some(&1));
    // An ended stream frees its share: polled, with a bound.
    drop(open.pop());
    let mut admitted = false;
    for k in 0..100 {
        let mut client = LearnerClient::connect(url.clone()).await.unwrap();
        let (tx, rx) = tokio::sync::mpsc::channel(1);
        tx.send(sized(1000 + k)).await.unwrap();
        let mut acks = client.stream_transitions(tokio_stream::wrappers::ReceiverStream::new(rx)).await.unwrap().into_inner();
        if matches!(acks.message().await, Ok(Some(_))) {
            admitted = true;
            break;
        }
        tokio::time::sleep(Duration::from_millis(50)).await;
    }
    assert!(admitted, "an ended stream's share is free again");
    let out = super::common::workspace_bin("lcrl-learner")
        .args(["--env", "lti-paper", "--algo", "ddpg", "--connection", "global", "--listen", "127.0.0.1:0", "--run-dir"])
        .arg(dir.path().join("small"))
        .args(["--request-budget-mib", "1", "--max-batch-bytes", "1048576"])
        .output()
        .unwrap();
    super::common::assert_clean_failure(&out, "--request-budget-mib 1 leaves one peer address a quarter");
}

/// A forged episode (issue 82): one step claiming 10⁶ steps and a return of
/// 9.9e11 passes the door (at most 10⁶ a step it claims beyond the batch),
/// but the record counts only the steps that arrived. metrics.csv holds it
/// as one step with that step's reward, the recent return stays near the
/// honest actor's, and the honest episodes recorded before it are kept.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_forged_episode_counts_only_the_steps_that_arrived() {
    use lcrl_proto::v1::EpisodeSummary;
    use super::distributed::{send, wait_for};
    let dir = tempfile::tempdir().unwrap();
    let run = dir.path().join("run");
    let (_learner, url) = learner_with_args(&run, "forge", free_port(), "ddpg", &[]);
    let _actor = actor_with_args(&url, "forge", &["--actor-id", "honest"]);
    let before = wait_for(&url, "honest episodes", |s| s.episodes >= 4).await;
    let rows = |run: &std::path::Path| -> Vec<(f64, u64)> {
        let text = std::fs::read_to_string(run.join("metrics.csv")).unwrap_or_default();
        text.lines().skip(1).filter_map(|l| {
            let mut f = l.split(',').skip(1);
            Some((f.next()?.parse().ok()?, f.next()?.parse().ok()?))
        }).collect()
    };
    let honest = rows(&run);
    assert!(honest.len() >= 4 && honest.iter().all(|&(r, n)| n > 1 && r.abs() < 1e6), "{honest:?}");
    let mut forged = TransitionBatch { actor_id: "forger".into(), ..batch("forge", 1, 3, 0.1) };
    forged.transitions.truncate(1);
    forged.transitions[0].terminated = true;
    forged.transitions[0].reward = -2.5;
    forged.episodes = vec![EpisodeSummary { episode_return: 9.9e11, length: 1_000_000, ..Default::default() }];
    send(&url, forged).await.expect("within the door's bounds: taken");
    let deadline = std::time::Instant::now() + Duration::from_secs(60);
    while !rows(&run).contains(&(-2.5, 1)) {
        assert!(std::time::Instant::now() < deadline, "the forged episode never reached metrics.csv as one step of -2.5: {:?}", rows(&run));
        tokio::time::sleep(Duration::from_millis(100)).await;
    }
    let after = rows(&run);
    assert!(after.iter().all(|&(r, n)| n < 1_000_000 && r.abs() < 1e6), "a claim was taken: {after:?}");
    assert_eq!(&after[..honest.len()], &honest[..], "the honest episodes recorded before are kept");
    let s = status(&url, &ClientSecurity::default()).await;
    assert!(s.episodes > before.episodes && s.recent_return.abs() < 1e4, "recent return {} after the forgery", s.recent_return);
}

/// GetStatus and /metrics are rate bounded per peer address (issue 82:
/// floods of either left training 0.28–0.29 of its updates, less than a
/// CPU hog did): 100 GetStatus calls at once get the burst and are then
/// refused with RESOURCE_EXHAUSTED saying why; 40 scrapes get HTTP 429
/// past theirs; /healthz is never limited; and once the rate refills, both
/// answer again. Training goes on throughout.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn status_and_metrics_floods_are_rate_bounded_per_peer() {
    use lcrl_runtime::peer_rate::{METRICS_BURST, STATUS_BURST};
    use super::distributed::wait_for;
    let dir = tempfile::tempdir().unwrap();
    let metrics_port = free_port();
    let (_learner, url) = learner_with_args(&dir.path().join("run"), "rate", free_port(), "ddpg", &["--metrics-listen", &format!("127.0.0.1:{metrics_port}")]);
    let _actor = actor_with_args(&url, "rate", &[]);
    let before = wait_for(&url, "training", |s| s.updates > 20).await;
    // wait_for's own calls drew on the bucket: let it refill first.
    tokio::time::sleep(Duration::from_secs(3)).await;
    use lcrl_runtime::peer_rate::{METRICS_PER_SECOND, STATUS_PER_SECOND};
    // At most the burst and what the rate refills while the calls run
    // (timed, so a slow machine widens the bound instead of failing it).
    let most = |burst: f64, per_second: f64, started: std::time::Instant| (burst + (per_second * started.elapsed().as_secs_f64()).ceil() + 1.0) as usize;
    let mut client = LearnerClient::connect(url.clone()).await.unwrap();
    let mut refused = Vec::new();
    let started = std::time::Instant::now();
    for _ in 0..100 {
        if let Err(e) = client.get_status(GetStatusRequest {}).await {
            refused.push(e);
        }
    }
    let answered = 100 - refused.len();
    let bound = most(STATUS_BURST, STATUS_PER_SECOND, started);
    assert!(answered >= STATUS_BURST as usize && answered <= bound, "{answered} of 100 answered, at most {bound} allowed");
    assert!(refused.iter().all(|e| e.code() == tonic::Code::ResourceExhausted && e.message().contains("a second from one peer address")), "{:?}", refused.first());
    let started = std::time::Instant::now();
    let codes: Vec<u16> = (0..40).map(|_| super::faults::http_get(metrics_port, "/metrics").0).collect();
    let ok = codes.iter().filter(|&&c| c == 200).count();
    let bound = most(METRICS_BURST, METRICS_PER_SECOND, started);
    assert!(ok >= METRICS_BURST as usize && ok <= bound && codes.iter().all(|&c| c == 200 || c == 429), "{ok} scrapes answered, at most {bound} allowed: {codes:?}");
    assert_eq!(super::faults::http_get(metrics_port, "/healthz").0, 200, "health is never limited");
    tokio::time::sleep(Duration::from_secs(1)).await;
    assert!(client.get_status(GetStatusRequest {}).await.is_ok(), "refilled");
    assert_eq!(super::faults::http_get(metrics_port, "/metrics").0, 200, "refilled");
    wait_for(&url, "training after the floods", |s| s.updates > before.updates + 100).await;
}

/// A token-protected run's shared memory goes by a name its token derives
/// (issue 82): an actor on this host without the token finds nothing to
/// feed (it stops within its deadline, naming --token-file, and nothing
/// it simulated is stored), while one with the token trains.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn shared_memory_of_a_token_protected_run_needs_the_token() {
    use std::os::unix::fs::PermissionsExt;
    let dir = tempfile::tempdir().unwrap();
    let token = dir.path().join("token");
    std::fs::write(&token, "shm-test-token-0123456789abcdef0123456789\n").unwrap();
    std::fs::set_permissions(&token, std::fs::Permissions::from_mode(0o600)).unwrap();
    let token_arg = token.to_str().unwrap();
    let (_learner, url) = learner_with_args(&dir.path().join("run"), "shmtok", free_port(), "ddpg", &["--token-file", token_arg]);
    let with_token = ClientSecurity::new(None, None, Some(&token)).unwrap();
    let without = super::common::workspace_bin("lcrl-actor")
        .args(["--learner", &url, "--run-id", "shmtok", "--transport", "shm", "--envs", "1", "--connect-deadline", "3"])
        .env_remove("LCRL_TOKEN_FILE")
        .output()
        .unwrap();
    super::common::assert_clean_failure(&without, "--token-file");
    assert_eq!(status(&url, &with_token).await.env_steps, 0, "an actor without the token stored nothing");
    let _actor = actor_with_args(&url, "shmtok", &["--transport", "shm", "--token-file", token_arg]);
    let deadline = std::time::Instant::now() + Duration::from_secs(60);
    while status(&url, &with_token).await.env_steps == 0 {
        assert!(std::time::Instant::now() < deadline, "the actor with the token stored nothing in 60 s");
        tokio::time::sleep(Duration::from_millis(100)).await;
    }
}
