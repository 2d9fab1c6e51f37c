//! What operators watch: Prometheus /metrics on learner and actor, JSON logs.

use std::io::{Read, Write};
use std::time::{Duration, Instant};

use lcrl_proto::v1::policy_client::PolicyClient;
use lcrl_proto::v1::ActRequest;

use super::common::workspace_bin;
use super::distributed::{actor_with_args, batch, free_port, learner_with_args, send, wait_for};

/// GET /metrics over plain HTTP/1.1; the body.
pub(super) fn scrape(port: u16) -> String {
    let mut stream = std::net::TcpStream::connect(("127.0.0.1", port)).expect("metrics endpoint reachable");
    stream.set_read_timeout(Some(Duration::from_secs(10))).unwrap();
    write!(stream, "GET /metrics HTTP/1.1\r\nHost: localhost\r\nConnection: close\r\n\r\n").unwrap();
    let mut response = String::new();
    stream.read_to_string(&mut response).unwrap();
    assert!(response.starts_with("HTTP/1.1 200"), "{response}");
    assert!(response.contains("application/openmetrics-text"), "{response}");
    response.split_once("\r\n\r\n").map(|(_, body)| body.to_string()).unwrap_or_default()
}

/// The value of the sample line `series` (name with labels), if present.
pub(super) fn sample(text: &str, series: &str) -> Option<f64> {
    text.lines().find_map(|line| line.strip_prefix(series)?.strip_prefix(' ')?.split(' ').next()?.parse().ok())
}

#[tokio::test]
async fn learner_and_actor_serve_prometheus_metrics() {
    let dir = tempfile::tempdir().unwrap();
    let (learner_metrics, actor_metrics) = (free_port(), free_port());
    let (_learner, url) = learner_with_args(&dir.path().join("run"), "m1", free_port(), "ddpg", &["--metrics-listen", &format!("127.0.0.1:{learner_metrics}")]);
    let _actor = actor_with_args(&url, "m1", &["--metrics-listen", &format!("127.0.0.1:{actor_metrics}")]);
    assert!(send(&url, batch("m1", 1, 5, 0.0)).await.is_err(), "wrong dimensions are refused");
    let s = wait_for(&url, "training", |s| s.updates > 20 && s.policy_version >= 1).await;
    let mut policy = PolicyClient::connect(url.clone()).await.unwrap();
    policy.act(ActRequest { state: vec![0.1, 0.2, 0.3] }).await.unwrap();

    let text = scrape(learner_metrics);
    let value = |series: &str| sample(&text, series).unwrap_or_else(|| panic!("{series} missing from\n{text}"));
    assert!(value("lcrl_learner_env_steps_total") >= s.env_steps as f64);
    assert!(value("lcrl_learner_updates_total") >= s.updates as f64);
    assert!(value("lcrl_learner_transitions_accepted_total") >= s.env_steps as f64);
    assert_eq!(value("lcrl_learner_transitions_rejected_total{reason=\"dimensions\"}"), 4.0);
    assert!(value("lcrl_learner_policy_version") >= 1.0);
    assert!(value("lcrl_learner_replay_size") > 0.0);
    assert_eq!(value("lcrl_learner_connected_actors"), 1.0);
    assert!(value("lcrl_learner_training_queue_depth") >= 0.0);
    assert!(value("lcrl_learner_validations_pending") >= 0.0);
    assert_eq!(value("lcrl_learner_act_latency_seconds_count"), 1.0, "one Act call so far");
    assert!(text.trim_end().ends_with("# EOF"));

    // The actor's own view: it stepped, sent, and acts with a published policy.
    let deadline = Instant::now() + Duration::from_secs(30);
    let actor_text = loop {
        let text = scrape(actor_metrics);
        if sample(&text, "lcrl_actor_policy_version").is_some_and(|v| v >= 1.0) || Instant::now() > deadline {
            break text;
        }
        tokio::time::sleep(Duration::from_millis(200)).await;
    };
    let value = |series: &str| sample(&actor_text, series).unwrap_or_else(|| panic!("{series} missing from\n{actor_text}"));
    assert!(value("lcrl_actor_env_steps_total") >= value("lcrl_actor_transitions_sent_total"));
    assert!(value("lcrl_actor_transitions_sent_total") >= 25.0);
    assert!(value("lcrl_actor_batches_sent_total") >= 1.0);
    assert!(value("lcrl_actor_policy_version") >= 1.0, "picked up a published policy");
    assert!(value("lcrl_actor_pending_batches") <= 8.0, "bounded");
}

#[test]
fn a_taken_metrics_port_is_a_clear_error() {
    let taken = std::net::TcpListener::bind("127.0.0.1:0").unwrap();
    let port = taken.local_addr().unwrap().port();
    let out = workspace_bin("lcrl-actor")
        .args(["--learner", "http://127.0.0.1:1", "--connect-deadline", "1", "--metrics-listen", &format!("127.0.0.1:{port}")])
        .output()
        .unwrap();
    super::common::assert_clean_failure(&out, "cannot serve metrics");
}

#[test]
fn log_json_writes_one_json_object_per_line() {
    let out = workspace_bin("lcrl-actor")
        .args(["--learner", &format!("http://127.0.0.1:{}", free_port()), "--connect-deadline", "1", "--log-json"])
        .output()
        .unwrap();
    assert!(!out.status.success());
    let err = String::from_utf8_lossy(&out.stderr);
    let logs: Vec<&str> = err.lines().filter(|l| l.starts_with('{')).collect();
    assert!(!logs.is_empty(), "no JSON log lines in {err}");
    for line in logs {
        let value: serde_json::Value = serde_json::from_str(line).unwrap_or_else(|e| panic!("{line:?} is not JSON: {e}"));
        assert!(value.get("level").is_some() && value.get("fields").is_some(), "{line}");
    }
    assert!(err.contains("retrying"), "{err}");
}
