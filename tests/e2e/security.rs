//! Across hosts, safely: real processes over real TLS (certificates from
//! `lcrl certs`), tokens, refusals counted by reason, and reflection that
//! grpcio's own v1alpha client can use.

use std::path::{Path, PathBuf};
use std::process::{Command, Stdio};
use std::time::{Duration, Instant};

use lcrl_runtime::security::ClientSecurity;
use lcrl_proto::v1::learner_client::LearnerClient;
use lcrl_proto::v1::{GetStatusRequest, LearnerStatus};
use tonic_health::pb::{health_client::HealthClient, HealthCheckRequest};

use super::common::{lcrl, stderr, stdout, workspace_bin};
use super::distributed::{actor_with_args, free_port, learner_with_args, Proc};

fn certs(dir: &Path) -> PathBuf {
    let out = lcrl().arg("certs").arg("--out").arg(dir).output().unwrap();
    assert!(out.status.success(), "{}", stderr(&out));
    dir.to_path_buf()
}

fn s(p: PathBuf) -> String {
    p.display().to_string()
}

async fn get_status(url: &str, security: &ClientSecurity) -> Result<LearnerStatus, String> {
    let channel = security.connect(url).await.map_err(|e| e.to_string())?;
    LearnerClient::new(channel).get_status(GetStatusRequest {}).await.map(|r| r.into_inner()).map_err(|e| format!("{:?}: {}", e.code(), e.message()))
}

async fn wait_for(url: &str, security: &ClientSecurity, what: &str, ready: impl Fn(&LearnerStatus) -> bool) -> LearnerStatus {
    let deadline = Instant::now() + Duration::from_secs(60);
    loop {
        let status = get_status(url, security).await;
        if let Ok(s) = &status {
            if ready(s) {
                return s.clone();
            }
        }
        assert!(Instant::now() < deadline, "timed out waiting for {what}; last status {status:?}");
        tokio::time::sleep(Duration::from_millis(100)).await;
    }
}

#[tokio::test]
async fn mutual_tls_and_a_token_guard_the_learner() {
    let dir = tempfile::tempdir().unwrap();
    let c = certs(&dir.path().join("certs"));
    let other = certs(&dir.path().join("other"));
    let port = free_port();
    let server_flags = [
        "--tls-cert".to_string(), s(c.join("server.pem")), "--tls-key".into(), s(c.join("server.key")),
        "--tls-client-ca".into(), s(c.join("ca.pem")), "--token-file".into(), s(c.join("token")),
    ];
    let flags: Vec<&str> = server_flags.iter().map(String::as_str).collect();
    let (_learner, _) = learner_with_args(&dir.path().join("run"), "tls", port, "ppo", &flags);
    let url = format!("https://127.0.0.1:{port}");
    let identity = (c.join("client.pem"), c.join("client.key"));
    let id = Some((identity.0.as_path(), identity.1.as_path()));
    let good = ClientSecurity::new(Some(&c.join("ca.pem")), id, Some(&c.join("token"))).unwrap();

    // An actor with mutual TLS and the token trains the learner.
    let client_flags = [
        "--tls-ca".to_string(), s(c.join("ca.pem")), "--tls-client-cert".into(), s(identity.0.clone()),
        "--tls-client-key".into(), s(identity.1.clone()), "--token-file".into(), s(c.join("token")),
    ];
    let _actor = actor_with_args(&url, "tls", &client_flags.iter().map(String::as_str).collect::<Vec<_>>());
    let first = wait_for(&url, &good, "training over TLS", |s| s.env_steps > 500 && s.updates > 0).await;
    wait_for(&url, &good, "training going on", |s| s.env_steps > first.env_steps + 500).await;

    // Refused: a wrong token, no token, a client certificate of another CA,
    // plain text to the TLS port.
    let wrong_token = dir.path().join("wrong");
    std::fs::write(&wrong_token, "not-the-token-0123456789abcdef").unwrap();
    let wrong = ClientSecurity::new(Some(&c.join("ca.pem")), id, Some(&wrong_token)).unwrap();
    assert!(get_status(&url, &wrong).await.unwrap_err().starts_with("Unauthenticated"));
    let tokenless = ClientSecurity::new(Some(&c.join("ca.pem")), id, None).unwrap();
    assert!(get_status(&url, &tokenless).await.unwrap_err().starts_with("Unauthenticated"));
    let (oc, ok) = (other.join("client.pem"), other.join("client.key"));
    let foreign = ClientSecurity::new(Some(&c.join("ca.pem")), Some((&oc, &ok)), Some(&c.join("token"))).unwrap();
    let err = get_status(&url, &foreign).await.unwrap_err();
    assert!(!err.starts_with("Unauthenticated"), "a foreign certificate never reaches the token check: {err}");
    let plain = ClientSecurity::default();
    assert!(get_status(&format!("http://127.0.0.1:{port}"), &plain).await.is_err(), "plain text to a TLS port");
    let status = get_status(&url, &good).await.unwrap();
    let refused = &status.unauthenticated;
    assert!(refused["wrong_token"] >= 1 && refused["missing_token"] >= 1, "{refused:?}");
    // A foreign client certificate and plain text fail the handshake; both counted.
    assert!(refused["tls_handshake"] >= 2, "{refused:?}");

    // Health checks need no token (probes know none).
    let channel = tokenless.connect(&url).await.unwrap();
    let health = HealthClient::new(channel).check(HealthCheckRequest { service: "lcrl.v1.Learner".into() }).await.unwrap().into_inner();
    assert_eq!(health.status, 1, "SERVING");

    // lcrl status over TLS with the token; the token never shows.
    let token = std::fs::read_to_string(c.join("token")).unwrap().trim().to_string();
    let out = lcrl().args(["status", &url]).args(&client_flags).output().unwrap();
    assert!(out.status.success(), "{}", stderr(&out));
    assert!(stdout(&out).contains("\"unauthenticated\"") && !stdout(&out).contains(&token));
    let refused = lcrl().args(["status", &url, "--tls-ca", &s(c.join("ca.pem")), "--tls-client-cert", &s(identity.0.clone()), "--tls-client-key", &s(identity.1.clone())]).output().unwrap();
    assert!(!refused.status.success() && stderr(&refused).contains("Bearer"), "{}", stderr(&refused));
    // A foreign client certificate is named as the likely cause, not left as
    // a bare "broken pipe" (issue 71).
    let foreign = lcrl().args(["status", &url, "--tls-ca", &s(c.join("ca.pem")), "--tls-client-cert", &s(oc.clone()), "--tls-client-key", &s(ok.clone()), "--token-file", &s(c.join("token"))]).output().unwrap();
    assert!(!foreign.status.success() && stderr(&foreign).contains("--tls-client-ca"), "{}", stderr(&foreign));

    // The Python client with mutual TLS and the token.
    let root = Path::new(env!("CARGO_MANIFEST_DIR"));
    let python = root.join(".venv/bin/python");
    let script = root.join("clients/python/lcrl_client.py");
    let run = |extra: &[&str]| {
        Command::new(&python).arg(&script).args(["--target", &format!("127.0.0.1:{port}"), "--state", "0.1", "0.2", "0.3"]).args(&client_flags[..6]).args(extra).output().unwrap()
    };
    let out = run(&["--token-file", &s(c.join("token"))]);
    assert!(out.status.success(), "{}{}", stdout(&out), stderr(&out));
    assert!(stdout(&out).lines().any(|l| l.starts_with("action ")), "{}", stdout(&out));
    let out = run(&[]);
    assert_eq!(out.status.code(), Some(2));
    assert!(stderr(&out).contains("UNAUTHENTICATED"), "{}", stderr(&out));
}

#[tokio::test]
async fn the_learner_fetches_its_graph_over_tls_with_the_token() {
    let dir = tempfile::tempdir().unwrap();
    let c = certs(&dir.path().join("certs"));
    let graph_port = free_port();
    let mut builder = workspace_bin("lcrl-graph-builder");
    builder
        .args(["--env", "lti-paper", "--samples", "16", "--listen", &format!("127.0.0.1:{graph_port}")])
        .args(["--tls-cert", &s(c.join("server.pem")), "--tls-key", &s(c.join("server.key")), "--tls-client-ca", &s(c.join("ca.pem"))])
        .args(["--token-file", &s(c.join("token"))])
        .stdout(Stdio::null())
        .stderr(Stdio::null());
    let _builder = Proc(builder.spawn().unwrap());
    let port = free_port();
    let mut learner = workspace_bin("lcrl-learner");
    learner
        .args(["--env", "lti-paper", "--algo", "ppo", "--connection", "local", "--run-id", "g"])
        .arg("--run-dir")
        .arg(dir.path().join("run"))
        .args(["--listen", &format!("127.0.0.1:{port}"), "--graph-builder", &format!("https://127.0.0.1:{graph_port}")])
        .args(["--graph-builder-tls-ca", &s(c.join("ca.pem")), "--tls-cert", &s(c.join("server.pem")), "--tls-key", &s(c.join("server.key"))])
        .args(["--token-file", &s(c.join("token"))])
        .stdout(Stdio::null())
        .stderr(Stdio::null());
    let _learner = Proc(learner.spawn().unwrap());
    let url = format!("https://127.0.0.1:{port}");
    let good = ClientSecurity::new(Some(&c.join("ca.pem")), None, Some(&c.join("token"))).unwrap();
    let status = wait_for(&url, &good, "the learner, serving once it has the graph", |_| true).await;
    assert_eq!(status.connection, "local");
}

/// A client written only against grpcio-reflection (v1alpha) lists the
/// services and calls lcrl.v1.Policy/Act through fetched descriptors.
#[test]
fn grpcio_reflection_v1alpha_client_calls_act() {
    let dir = tempfile::tempdir().unwrap();
    let port = free_port();
    let (_learner, _) = learner_with_args(&dir.path().join("run"), "refl", port, "ppo", &[]);
    let root = Path::new(env!("CARGO_MANIFEST_DIR"));
    let out = Command::new(root.join(".venv/bin/python"))
        .arg(root.join("clients/python/reflect_act.py"))
        .args(["--target", &format!("127.0.0.1:{port}"), "--state", "0.1", "0.2", "0.3"])
        .output()
        .unwrap();
    let text = stdout(&out);
    assert!(out.status.success(), "{text}{}", stderr(&out));
    let services = text.lines().find_map(|l| l.strip_prefix("services ")).unwrap();
    // Each reflection version lists itself beside the services (v1, which
    // grpcurl speaks, is checked in reflection_v1_lists_services_behind_the_token).
    for service in ["lcrl.v1.Policy", "lcrl.v1.Learner", "grpc.health.v1.Health", "grpc.reflection.v1alpha.ServerReflection"] {
        assert!(services.split(' ').any(|s| s == service), "{service} not listed: {services}");
    }
    let action: Vec<f64> = text.lines().find_map(|l| l.strip_prefix("action ")).unwrap().split_whitespace().map(|v| v.parse().unwrap()).collect();
    assert_eq!(action.len(), 3);
}

/// A server reachable from other hosts without TLS warns at start; the
/// token never shows in a launcher's dry run.
#[test]
fn exposed_plain_text_warns_and_tokens_stay_secret() {
    use std::io::{BufRead, BufReader};
    let mut builder = workspace_bin("lcrl-graph-builder");
    builder.args(["--env", "lti-paper", "--samples", "8", "--listen", "0.0.0.0:0"]).stdout(Stdio::null()).stderr(Stdio::piped());
    let mut child = Proc(builder.spawn().unwrap());
    let stderr_lines = BufReader::new(child.0.stderr.take().unwrap()).lines();
    // The warning comes before the graph is built; stop reading there.
    let warned = stderr_lines
        .map_while(Result::ok)
        .take_while(|l| !l.contains("graph built"))
        .any(|l| l.contains("plain text on a non-loopback address"));
    assert!(warned, "no warning for a plain-text server on 0.0.0.0");
    drop(child);

    let dir = tempfile::tempdir().unwrap();
    let token = dir.path().join("token");
    std::fs::write(&token, "very-secret-token-0123456789").unwrap();
    let config = Path::new(env!("CARGO_MANIFEST_DIR")).join("configs/lti-paper.toml");
    let out = lcrl().args(["launch", "actor", "--config"]).arg(&config).arg("--token-file").arg(&token).arg("--dry-run").output().unwrap();
    assert!(out.status.success(), "{}", stderr(&out));
    assert!(stdout(&out).contains("--token-file") && !stdout(&out).contains("very-secret"), "{}", stdout(&out));
    let wrong = lcrl().args(["status", "http://127.0.0.1:1", "--token-file"]).arg(&token).output().unwrap();
    assert!(!stderr(&wrong).contains("very-secret"));
}

/// grpc.reflection.v1 (grpcurl's) lists the services, and like every
/// service but health it needs the token.
#[tokio::test]
async fn reflection_v1_lists_services_behind_the_token() {
    use tonic_reflection::pb::v1::server_reflection_client::ServerReflectionClient;
    use tonic_reflection::pb::v1::server_reflection_request::MessageRequest;
    use tonic_reflection::pb::v1::server_reflection_response::MessageResponse;
    use tonic_reflection::pb::v1::ServerReflectionRequest;
    let dir = tempfile::tempdir().unwrap();
    let token = dir.path().join("token");
    std::fs::write(&token, "reflection-token-0123456789").unwrap();
    let port = free_port();
    let (_learner, url) = learner_with_args(&dir.path().join("run"), "r1", port, "ppo", &["--token-file", &s(token.clone())]);
    let list = |security: ClientSecurity| {
        let url = url.clone();
        async move {
            let mut client = ServerReflectionClient::new(security.connect(&url).await.unwrap());
            let request = ServerReflectionRequest { host: String::new(), message_request: Some(MessageRequest::ListServices(String::new())) };
            let mut replies = client.server_reflection_info(tokio_stream::iter(vec![request])).await?.into_inner();
            let reply = replies.message().await?.and_then(|r| r.message_response);
            Ok::<_, tonic::Status>(match reply {
                Some(MessageResponse::ListServicesResponse(list)) => list.service.into_iter().map(|s| s.name).collect::<Vec<_>>(),
                other => panic!("unexpected reply {other:?}"),
            })
        }
    };
    let services = list(ClientSecurity::new(None, None, Some(&token)).unwrap()).await.unwrap();
    for service in ["lcrl.v1.Policy", "lcrl.v1.Learner", "grpc.health.v1.Health", "grpc.reflection.v1.ServerReflection"] {
        assert!(services.iter().any(|s| s == service), "{service} not in {services:?}");
    }
    let refused = list(ClientSecurity::default()).await.unwrap_err();
    assert_eq!(refused.code(), tonic::Code::Unauthenticated);
}

/// A learner without a token serves loopback only (issue 82: a token-less
/// learner was open to every peer that reached it): beyond loopback it
/// refuses to start, naming the three ways on, unless it has a token or
/// `--insecure` is said.
#[test]
fn a_learner_without_a_token_serves_loopback_only() {
    use std::os::unix::fs::PermissionsExt;
    let dir = tempfile::tempdir().unwrap();
    let learner = |extra: &[&str], run: &str| {
        let mut cmd = workspace_bin("lcrl-learner");
        cmd.args(["--env", "lti-paper", "--algo", "ddpg", "--connection", "global", "--run-id", run, "--listen", "0.0.0.0:0", "--run-dir"])
            .arg(dir.path().join(run))
            .args(extra)
            .env_remove(lcrl_runtime::security::TOKEN_FILE_ENV);
        cmd
    };
    let out = learner(&[], "bare").output().unwrap();
    super::common::assert_clean_failure(&out, "has no token");
    for way in ["--token-file FILE", "127.0.0.1", "--insecure"] {
        assert!(stderr(&out).contains(way), "{way}: {}", stderr(&out));
    }
    let token = dir.path().join("token");
    std::fs::write(&token, "very-secret-token-0123456789").unwrap();
    std::fs::set_permissions(&token, std::fs::Permissions::from_mode(0o600)).unwrap();
    for (extra, run) in [(vec!["--token-file", token.to_str().unwrap()], "tokened"), (vec!["--insecure"], "insecure")] {
        let (child, address) = super::common::spawn_listening(&mut learner(&extra, run));
        drop(Proc(child));
        assert!(address.starts_with("0.0.0.0:"), "{run}: {address}");
    }
}
