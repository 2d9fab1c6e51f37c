//! Faults and hostile peers against real lcrl-learner and lcrl-actor
//! processes over real gRPC (docs/reliability.md): a restarted learner, a
//! silent server, a wrong run id, a spent budget, floods of entries,
//! sockets and oversized calls. Each test fails on a learner or actor that
//! does not hold.

use std::io::{Read, Write};
use std::process::Stdio;
use std::time::{Duration, Instant};

use lcrl_proto::v1::learner_client::LearnerClient;
use lcrl_proto::v1::policy_client::PolicyClient;
use lcrl_proto::v1::{ActBatchRequest, GetStatusRequest, LearnerStatus, Transition, TransitionBatch};

use super::common::{stderr, workspace_bin};
use lcrl_runtime::security::ClientSecurity;

use super::distributed::{actor_with_args, batch, free_port, learner_with_args, wait_for};
use super::hostile::{rss_kib, send_all};
use super::observability::{sample, scrape};

/// Whether the server closes `socket` by `deadline` (reading and dropping
/// whatever it writes before).
fn closed_by(socket: &mut std::net::TcpStream, deadline: Instant) -> bool {
    let mut buffer = [0u8; 512];
    loop {
        socket.set_read_timeout(Some(deadline.saturating_duration_since(Instant::now()).max(Duration::from_millis(1)))).unwrap();
        match socket.read(&mut buffer) {
            Ok(0) => return true,
            Ok(_) => continue,
            Err(e) if e.kind() == std::io::ErrorKind::ConnectionReset => return true,
            Err(_) => return false,
        }
    }
}

async fn status(url: &str) -> LearnerStatus {
    let mut client = LearnerClient::connect(url.to_string()).await.unwrap();
    client.get_status(GetStatusRequest {}).await.unwrap().into_inner()
}

/// GET `path` on the actor's metrics address: (status code, body).
pub(super) fn http_get(port: u16, path: &str) -> (u16, String) {
    let mut stream = std::net::TcpStream::connect(("127.0.0.1", port)).expect("metrics endpoint reachable");
    stream.set_read_timeout(Some(Duration::from_secs(10))).unwrap();
    write!(stream, "GET {path} HTTP/1.1\r\nHost: localhost\r\nConnection: close\r\n\r\n").unwrap();
    let mut response = String::new();
    stream.read_to_string(&mut response).unwrap();
    let code = response.split_whitespace().nth(1).and_then(|c| c.parse().ok()).unwrap_or(0);
    (code, response.split_once("\r\n\r\n").map(|(_, body)| body.to_string()).unwrap_or_default())
}

/// Waits up to `limit` for `child` to exit; its output, or None if it ran on.
fn wait_output(mut child: std::process::Child, limit: Duration) -> Option<std::process::Output> {
    let deadline = Instant::now() + limit;
    while Instant::now() < deadline {
        if child.try_wait().unwrap().is_some() {
            return Some(child.wait_with_output().unwrap());
        }
        std::thread::sleep(Duration::from_millis(100));
    }
    let _ = child.kill();
    let _ = child.wait();
    None
}


/// A batch of many empty transitions is a few bytes each on the wire and a
/// whole struct each decoded: it is refused before decoding, and a batch
/// over --max-batch-bytes before it is even read. Four at once leave the
/// learner's memory where it was; every refusal is counted by reason.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn floods_of_entries_and_bytes_are_refused_before_decoding() {
    let dir = tempfile::tempdir().unwrap();
    let metrics_port = free_port();
    let (learner, url) = learner_with_args(&dir.path().join("run"), "flood", free_port(), "ddpg", &["--metrics-listen", &format!("127.0.0.1:{metrics_port}")]);
    let rss_before = rss_kib(learner.0.id());
    // 1 MiB less a little, all empty transitions: ~500k entries.
    let empty = TransitionBatch { transitions: vec![Transition::default(); 500_000], ..batch("flood", 1, 3, 0.5) };
    let big = TransitionBatch { transitions: vec![Transition { state: vec![0.5; 1 << 20], ..Default::default() }; 4], ..batch("flood", 2, 3, 0.5) };
    let mut tasks = tokio::task::JoinSet::new();
    for k in 0..4 {
        let (url, batch) = (url.clone(), if k % 2 == 0 { empty.clone() } else { big.clone() });
        tasks.spawn(async move { send_all(&url, &ClientSecurity::default(), vec![batch]).await });
    }
    let mut codes = Vec::new();
    while let Some(done) = tasks.join_next().await {
        codes.push(done.unwrap());
    }
    codes.sort_by_key(|c| format!("{c:?}"));
    assert_eq!(codes, vec![Some(tonic::Code::ResourceExhausted); 4]);
    let grown_mib = rss_kib(learner.0.id()).saturating_sub(rss_before) / 1024;
    assert!(grown_mib < 64, "four refused batches grew the learner by {grown_mib} MiB");
    let s = status(&url).await;
    assert_eq!(s.rejected.get("too_many_entries"), Some(&2), "{:?}", s.rejected);
    assert_eq!(s.rejected.get("oversize"), Some(&2), "{:?}", s.rejected);
    let text = scrape(metrics_port);
    assert_eq!(sample(&text, "lcrl_learner_transitions_rejected_total{reason=\"too_many_entries\"}"), Some(2.0), "{text}");
    // An honest batch still goes in.
    assert!(send_all(&url, &ClientSecurity::default(), vec![batch("flood", 3, 3, 0.5)]).await.is_none());
    wait_for(&url, "the honest batch", |s| s.env_steps >= 4).await;
}

/// Sockets opened and left silent cannot hold the server: when it is
/// full, each newcomer takes the place of the least recently heard silent
/// one, so a health check is answered at once in the middle of the flood;
/// the silent ones left are closed after 10 s. Both counted.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn idle_sockets_are_capped_and_closed_and_health_checks_answer() {
    let dir = tempfile::tempdir().unwrap();
    let metrics_port = free_port();
    let metrics_flag = format!("127.0.0.1:{metrics_port}");
    let (_learner, url) = learner_with_args(&dir.path().join("run"), "idle", free_port(), "ddpg", &["--max-connections", "8", "--idle-timeout-secs", "30", "--metrics-listen", &metrics_flag]);
    let addr = url.trim_start_matches("http://").to_string();
    let opened = Instant::now();
    let mut sockets: Vec<std::net::TcpStream> = (0..40).map(|_| std::net::TcpStream::connect(&addr).unwrap()).collect();
    // Well before the 10 s a silent socket is given, a health check and a
    // status call get in.
    let channel = tonic::transport::Endpoint::from_shared(url.clone()).unwrap().connect().await.unwrap();
    let health = tonic_health::pb::health_client::HealthClient::new(channel).check(tonic_health::pb::HealthCheckRequest { service: String::new() }).await;
    assert!(health.is_ok(), "{health:?}");
    let s = status(&url).await;
    assert!(opened.elapsed() < Duration::from_secs(8), "the health check took {:?}", opened.elapsed());
    assert!(s.connections_refused["evicted"] >= 32, "{:?}", s.connections_refused);
    // Every socket is closed by the server: for a newcomer, or after 10 s
    // of silence.
    let deadline = opened + Duration::from_secs(30);
    for socket in &mut sockets {
        // The server may write its HTTP/2 settings first; then it closes.
        assert!(closed_by(socket, deadline), "an idle socket was still open 30 s after it was opened");
    }
    // Silent for 10 s: closed as idle, or, as it is the same 10 s, as a
    // connection that made no authenticated call.
    let s = status(&url).await;
    assert!(s.connections_refused["idle"] + s.connections_refused["no_call"] >= 1, "{:?}", s.connections_refused);
    let text = scrape(metrics_port);
    assert!(sample(&text, "lcrl_learner_connections_refused_total{reason=\"evicted\"}").unwrap_or(0.0) >= 32.0, "{text}");
}

/// ActBatch holds at most --max-act-batch states; two at once are both
/// answered, and GetStatus with them.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn act_batch_is_capped_and_shares_the_server() {
    let dir = tempfile::tempdir().unwrap();
    let (_learner, url) = learner_with_args(&dir.path().join("run"), "act", free_port(), "ddpg", &["--max-act-batch", "100"]);
    let mut policy = PolicyClient::connect(url.clone()).await.unwrap();
    let refused = policy.act_batch(ActBatchRequest { count: 101, states: vec![0.1; 303] }).await.unwrap_err();
    assert_eq!(refused.code(), tonic::Code::InvalidArgument);
    assert!(refused.message().contains("--max-act-batch"), "{}", refused.message());
    let (mut a, mut b) = (policy.clone(), policy.clone());
    let (ra, rb, s) = tokio::join!(
        a.act_batch(ActBatchRequest { count: 100, states: vec![0.1; 300] }),
        b.act_batch(ActBatchRequest { count: 100, states: vec![0.2; 300] }),
        status(&url)
    );
    assert_eq!(ra.unwrap().into_inner().actions.len(), 300);
    assert_eq!(rb.unwrap().into_inner().actions.len(), 300);
    assert_eq!(s.run_id, "act");
}

/// After kill -9 and a restart, the learner is a new incarnation whose
/// versions start again below what the actor last saw; the actor acts with
/// the new learner's policy anyway. While the learner is away the actor's
/// /healthz says so.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn actors_follow_a_restarted_learner_and_report_when_it_is_gone() {
    let dir = tempfile::tempdir().unwrap();
    let run = dir.path().join("run");
    let port = free_port();
    // No periodic checkpoint: the restart begins again from version 0.
    let (learner, url) = learner_with_args(&run, "restart", port, "ddpg", &["--checkpoint-secs", "3600"]);
    let first = status(&url).await.incarnation;
    assert_ne!(first, 0);
    let actor_metrics = free_port();
    let _actor = actor_with_args(&url, "restart", &["--metrics-listen", &format!("127.0.0.1:{actor_metrics}"), "--liveness-secs", "2"]);
    // None until the actor's endpoint is up.
    let actor_version = || std::net::TcpStream::connect(("127.0.0.1", actor_metrics)).ok().and_then(|_| sample(&scrape(actor_metrics), "lcrl_actor_policy_version"));
    let deadline = Instant::now() + Duration::from_secs(60);
    while actor_version().unwrap_or(0.0) < 100.0 {
        assert!(Instant::now() < deadline, "the actor never got version 100");
        // Within /metrics' rate per peer (lcrl_runtime::peer_rate).
        tokio::time::sleep(Duration::from_millis(200)).await;
    }
    assert_eq!(http_get(actor_metrics, "/healthz").0, 200);
    learner.signal("KILL");
    drop(learner);
    let before = actor_version().unwrap();
    let deadline = Instant::now() + Duration::from_secs(30);
    loop {
        let (code, body) = http_get(actor_metrics, "/healthz");
        if code == 503 {
            assert!(body.contains("no answer from the learner"), "{body}");
            break;
        }
        assert!(Instant::now() < deadline, "the actor stayed live without its learner");
        tokio::time::sleep(Duration::from_millis(200)).await;
    }
    // The restarted learner stores but does not train: its versions stay
    // far below the actor's, whatever the timing.
    let (_restarted, url) = learner_with_args(&run, "restart", port, "ddpg", &["--checkpoint-secs", "3600", "--no-train"]);
    let second = status(&url).await.incarnation;
    assert_ne!(second, first, "a restart is a new incarnation");
    let restarted = Instant::now();
    loop {
        let now = actor_version().unwrap();
        if now < before {
            eprintln!("the actor acted with the restarted learner's version {now} {:.2} s after it listened", restarted.elapsed().as_secs_f64());
            break;
        }
        assert!(restarted.elapsed() < Duration::from_secs(45), "the actor kept version {now} (before the kill: {before}) after the restart");
        tokio::time::sleep(Duration::from_millis(100)).await;
    }
    assert!(std::fs::read_to_string(run.join("incarnations.csv")).unwrap().lines().count() == 3, "a header and two starts");
    wait_for(&url, "the actor's batches in the new learner", |s| s.env_steps > 0).await;
    assert_eq!(http_get(actor_metrics, "/healthz").0, 200);
}

/// A wrong run id is refused as such, and the actor stops with what to
/// fix, instead of reconnecting for ever.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn an_actor_with_the_wrong_run_id_stops_and_says_why() {
    let dir = tempfile::tempdir().unwrap();
    let (_learner, url) = learner_with_args(&dir.path().join("run"), "right", free_port(), "ddpg", &[]);
    let child = workspace_bin("lcrl-actor")
        .args(["--learner", &url, "--run-id", "wrong", "--envs", "1", "--batch", "10", "--connect-deadline", "10"])
        .stdout(Stdio::null())
        .stderr(Stdio::piped())
        .spawn()
        .unwrap();
    let out = tokio::task::spawn_blocking(move || wait_output(child, Duration::from_secs(30))).await.unwrap().expect("the actor still ran after 30 s");
    assert!(!out.status.success());
    let err = stderr(&out);
    assert!(err.contains("--run-id") && err.contains("'wrong' is not this learner's run"), "{err}");
    let s = status(&url).await;
    // One stream's worth (batches already in flight when the refusal came),
    // not a loop of reconnects.
    assert!(s.rejected.get("unknown_run").copied().unwrap_or(0) <= 10 * 8, "the actor kept sending: {:?}", s.rejected);
}

/// A server that accepts connections and never answers: the actor's call
/// deadline ends the wait with an error instead of a silent hang.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn an_actor_against_a_silent_server_fails_instead_of_hanging() {
    let listener = std::net::TcpListener::bind("127.0.0.1:0").unwrap();
    let url = format!("http://{}", listener.local_addr().unwrap());
    // Accepts and holds every connection, reads nothing, writes nothing.
    std::thread::spawn(move || {
        let mut held = Vec::new();
        for stream in listener.incoming().flatten() {
            held.push(stream);
        }
    });
    let child = workspace_bin("lcrl-actor")
        .args(["--learner", &url, "--envs", "1", "--connect-deadline", "2"])
        .stdout(Stdio::null())
        .stderr(Stdio::piped())
        .spawn()
        .unwrap();
    let started = Instant::now();
    let limit = lcrl_runtime::limits::CALL_TIMEOUT + Duration::from_secs(20);
    let out = tokio::task::spawn_blocking(move || wait_output(child, limit)).await.unwrap().expect("the actor hung on a silent server");
    assert!(!out.status.success());
    let err = stderr(&out);
    assert!(err.contains("did not answer") || err.contains("unreachable"), "after {:?}: {err}", started.elapsed());
}

/// When the learner's episode budget is spent, its actors stop on their
/// own (over gRPC and shared memory), instead of simulating for nothing.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn actors_stop_when_the_budget_is_spent() {
    let dir = tempfile::tempdir().unwrap();
    let (_learner, url) = learner_with_args(&dir.path().join("run"), "budget", free_port(), "ddpg", &["--episodes", "6"]);
    let spawn = |transport: &str| {
        workspace_bin("lcrl-actor")
            .args(["--learner", &url, "--run-id", "budget", "--envs", "1", "--batch", "25", "--connect-deadline", "30", "--transport", transport])
            .stdout(Stdio::null())
            .stderr(Stdio::piped())
            .spawn()
            .unwrap()
    };
    let (grpc, shm) = (spawn("grpc"), spawn("shm"));
    let outs = tokio::task::spawn_blocking(move || (wait_output(grpc, Duration::from_secs(90)), wait_output(shm, Duration::from_secs(90)))).await.unwrap();
    let s = status(&url).await;
    assert!(s.finished, "{s:?}");
    for (transport, out) in [("grpc", outs.0), ("shm", outs.1)] {
        let out = out.unwrap_or_else(|| panic!("the {transport} actor ran on after the budget"));
        assert!(out.status.success(), "{transport}: {}", stderr(&out));
        assert!(stderr(&out).contains("episode budget is spent"), "{transport}: {}", stderr(&out));
    }
}

/// An actor whose first GetPolicy is answered UNAVAILABLE (a learner still
/// loading its checkpoint: here a stand-in gRPC server in Python) asks
/// again with backoff until `--connect-deadline`, instead of exiting on the
/// first refusal (issue 71), and trains once the learner takes the port.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn an_actor_asks_again_while_the_learner_answers_no_policy() {
    const STAND_IN: &str = r#"
import sys, time, grpc
from concurrent import futures
class Unavailable(grpc.GenericRpcHandler):
    calls = 0
    def service(self, details):
        def refuse(request, context):
            Unavailable.calls += 1
            context.abort(grpc.StatusCode.UNAVAILABLE, "loading its checkpoint")
        return grpc.unary_unary_rpc_method_handler(refuse, request_deserializer=lambda b: b, response_serializer=lambda b: b)
server = grpc.server(futures.ThreadPoolExecutor(max_workers=2), handlers=[Unavailable()])
server.add_insecure_port("127.0.0.1:" + sys.argv[1])
server.start()
deadline = time.monotonic() + 30
while Unavailable.calls < 3 and time.monotonic() < deadline:
    time.sleep(0.05)
server.stop(None).wait()
print(Unavailable.calls)
"#;
    let port = free_port();
    let python = std::path::Path::new(env!("CARGO_MANIFEST_DIR")).join(".venv/bin/python");
    let stand_in = std::process::Command::new(python).args(["-c", STAND_IN, &port.to_string()]).stdout(Stdio::piped()).stderr(Stdio::piped()).spawn().unwrap();
    // Until the stand-in listens, the actor's connect is what retries.
    std::thread::sleep(Duration::from_millis(500));
    let url = format!("http://127.0.0.1:{port}");
    let mut actor = actor_with_args(&url, "retry", &[]); // --connect-deadline 30
    let out = tokio::task::spawn_blocking(move || stand_in.wait_with_output().unwrap()).await.unwrap();
    let refused: u32 = String::from_utf8_lossy(&out.stdout).trim().parse().unwrap_or_else(|_| panic!("the stand-in: {}", String::from_utf8_lossy(&out.stderr)));
    assert!(refused >= 3, "the actor asked {refused} times");
    assert!(actor.0.try_wait().unwrap().is_none(), "the actor exited after {refused} refusals");
    let dir = tempfile::tempdir().unwrap();
    let (_learner, url) = learner_with_args(&dir.path().join("run"), "retry", port, "ddpg", &[]);
    wait_for(&url, "the actor's transitions", |s| s.env_steps > 0).await;
}

/// Connections that keep a learner's places without working (issue 71):
/// HTTP/2 connections that only answer and send pings are closed once
/// they have made no authenticated call for `CALL_DEADLINE`, and 70
/// unfinished GETs on /metrics are held at most its lifetime each; health
/// checks are answered meanwhile, and /metrics serves again after.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn pinging_connections_and_unfinished_metrics_requests_are_closed() {
    let dir = tempfile::tempdir().unwrap();
    let metrics_port = free_port();
    let metrics_flag = format!("127.0.0.1:{metrics_port}");
    let (_learner, url) = learner_with_args(&dir.path().join("run"), "pings", free_port(), "ddpg", &["--metrics-listen", &metrics_flag]);
    let addr = url.trim_start_matches("http://").to_string();
    let frame = |kind: u8, flags: u8, payload: &[u8]| [&(payload.len() as u32).to_be_bytes()[1..], &[kind, flags], &[0, 0, 0, 0], payload].concat();
    let started = Instant::now();
    let limit = lcrl_runtime::limits::CALL_DEADLINE + Duration::from_secs(10);
    let pingers: Vec<_> = (0..3)
        .map(|_| {
            let addr = addr.clone();
            std::thread::spawn(move || -> Option<Duration> {
                let mut s = std::net::TcpStream::connect(&addr).unwrap();
                s.write_all(&[b"PRI * HTTP/2.0\r\n\r\nSM\r\n\r\n".as_slice(), &frame(4, 0, &[]), &frame(4, 1, &[])].concat()).unwrap();
                s.set_read_timeout(Some(Duration::from_millis(500))).unwrap();
                let mut buffer = [0u8; 4096];
                while started.elapsed() < limit {
                    if s.write_all(&frame(6, 0, &[7; 8])).is_err() {
                        return Some(started.elapsed());
                    }
                    match s.read(&mut buffer) {
                        Ok(0) => return Some(started.elapsed()),
                        Err(e) if e.kind() == std::io::ErrorKind::ConnectionReset || e.kind() == std::io::ErrorKind::BrokenPipe => return Some(started.elapsed()),
                        _ => {}
                    }
                }
                None
            })
        })
        .collect();
    let loris: Vec<std::net::TcpStream> = (0..70)
        .filter_map(|_| {
            let mut s = std::net::TcpStream::connect(("127.0.0.1", metrics_port)).ok()?;
            s.write_all(b"GET /metrics HTTP/1.1\r\nHost: x\r\n").ok()?;
            Some(s)
        })
        .collect();
    // Meanwhile health checks are answered.
    let channel = tonic::transport::Endpoint::from_shared(url.clone()).unwrap().connect().await.unwrap();
    let t0 = Instant::now();
    let health = tonic_health::pb::health_client::HealthClient::new(channel).check(tonic_health::pb::HealthCheckRequest { service: String::new() }).await;
    assert!(health.is_ok() && t0.elapsed() < Duration::from_secs(5), "{health:?} after {:?}", t0.elapsed());
    for pinger in pingers {
        let closed = tokio::task::spawn_blocking(move || pinger.join().unwrap()).await.unwrap();
        let at = closed.expect("a connection that only pings was still open");
        assert!(at >= lcrl_runtime::limits::CALL_DEADLINE - Duration::from_secs(1), "closed after {at:?}, before its deadline");
    }
    assert!(status(&url).await.connections_refused["no_call"] >= 3);
    // The unfinished GETs are closed within their lifetime (and /metrics
    // answers again).
    let deadline = Instant::now() + lcrl_runtime::metrics_http::METRICS_CONNECTION_LIFETIME + Duration::from_secs(10);
    for mut s in loris {
        assert!(closed_by(&mut s, deadline), "an unfinished /metrics request was still held past its lifetime");
    }
    assert!(sample(&scrape(metrics_port), "lcrl_learner_connections_refused_total{reason=\"no_call\"}").unwrap_or(0.0) >= 3.0);
}
