//! `lcrl bench transport`: the distributed runtime's figures, measured on
//! real lcrl-learner and lcrl-actor processes on loopback.

use std::io::{BufRead, BufReader};
use std::process::{Child, Command, Stdio};
use std::time::{Duration, Instant};

use lcrl::binaries::sibling;
use anyhow::Context;
use lcrl_runtime::security::ClientSecurity;
use lcrl_proto::v1::learner_client::LearnerClient;
use lcrl_proto::v1::policy_client::PolicyClient;
use lcrl_proto::v1::{ActRequest, GetStatusRequest, Transition, TransitionBatch};

struct Proc(Child);

impl Drop for Proc {
    fn drop(&mut self) {
        let _ = self.0.kill();
        let _ = self.0.wait();
    }
}

/// How the bench's clients reach a learner: plain text, or mutual TLS
/// and a token (certificates made for the bench by `lcrl certs`' code).
struct Link {
    label: &'static str,
    server_flags: Vec<String>,
    client: ClientSecurity,
}

impl Link {
    fn plain() -> Link {
        Link { label: "plain text", server_flags: Vec::new(), client: ClientSecurity::default() }
    }

    fn tls(dir: &std::path::Path) -> anyhow::Result<Link> {
        let certs = dir.join("certs");
        crate::cmd::certs::write_set(&certs, &["127.0.0.1".to_string()], 1)?;
        let file = |name: &str| certs.join(name).display().to_string();
        let server_flags = ["--tls-cert", &file("server.pem"), "--tls-key", &file("server.key"), "--tls-client-ca", &file("ca.pem"), "--token-file", &file("token")]
            .map(String::from)
            .to_vec();
        let client = ClientSecurity::new(Some(&certs.join("ca.pem")), Some((&certs.join("client.pem"), &certs.join("client.key"))), Some(&certs.join("token")))?;
        Ok(Link { label: "mutual TLS + token", server_flags, client })
    }

    fn url(&self, addr: &str) -> String {
        if self.server_flags.is_empty() { format!("http://{addr}") } else { format!("https://{addr}") }
    }
}

/// Starts a learner on a free port; returns it with its URL.
fn learner(dir: &std::path::Path, env: &str, extra: &[&str], link: &Link) -> anyhow::Result<(Proc, String)> {
    let mut child = Command::new(sibling("lcrl-learner")?)
        .args(["--env", env, "--algo", "ddpg", "--connection", "global", "--listen", "127.0.0.1:0", "--checkpoint-secs", "3600"])
        .arg("--run-dir")
        .arg(dir)
        .args(extra)
        .args(&link.server_flags)
        .stdout(Stdio::piped())
        .stderr(Stdio::null())
        .spawn()?;
    let mut line = String::new();
    BufReader::new(child.stdout.take().context("learner stdout")?).read_line(&mut line)?;
    let addr = line.trim().strip_prefix("listening on").context("learner did not start")?.trim().to_string();
    Ok((Proc(child), link.url(&addr)))
}

pub fn run(seconds: f64) -> anyhow::Result<()> {
    let runtime = tokio::runtime::Builder::new_multi_thread().worker_threads(2).enable_all().build()?;
    runtime.block_on(async move {
        let work = tempfile::tempdir()?;
        let (plain, tls) = (Link::plain(), Link::tls(work.path())?);
        ingest(&work.path().join("plain"), seconds, &plain).await?;
        ingest(&work.path().join("tls"), seconds, &tls).await?;
        ingest_shm(work.path(), seconds).await?;
        // Plain and TLS alternately on two learners, so machine noise hits both alike.
        let plain_p50 = act_latency(&work.path().join("act-plain"), &plain).await?;
        let tls_p50 = act_latency(&work.path().join("act-tls"), &tls).await?;
        println!("Policy.Act p50 with mutual TLS + token / plain text: {:.2}×", tls_p50 / plain_p50);
        end_to_end(work.path(), seconds).await
    })
}

/// Transitions per second acknowledged by a learner that only ingests.
async fn ingest(dir: &std::path::Path, seconds: f64, link: &Link) -> anyhow::Result<()> {
    let (_learner, url) = learner(&dir.join("ingest"), "peg-group1", &["--no-train"], link)?;
    let transition = Transition { state: vec![0.1; 12], action: vec![0.5; 6], reward: -1.0, next_state: vec![0.2; 12], terminated: false, truncated: false, policy_version: 0, ..Default::default() };
    let (streams, per_batch) = (4usize, 1000usize);
    let deadline = Instant::now() + Duration::from_secs_f64(seconds);
    let started = Instant::now();
    let mut tasks = Vec::new();
    for s in 0..streams {
        let (url, security) = (url.clone(), link.client.clone());
        let transition = transition.clone();
        tasks.push(tokio::spawn(async move {
            let mut client = LearnerClient::new(security.connect(&url).await?).max_encoding_message_size(16 << 20);
            let (tx, rx) = tokio::sync::mpsc::channel(8);
            let mut acks = client.stream_transitions(tokio_stream::wrappers::ReceiverStream::new(rx)).await?.into_inner();
            let sender = tokio::spawn(async move {
                let mut sequence = 0u64;
                while Instant::now() < deadline {
                    sequence += 1;
                    let batch = TransitionBatch {
                        run_id: "default".into(),
                        actor_id: format!("bench-{s}"),
                        sequence,
                        transitions: vec![transition.clone(); per_batch],
                        ..Default::default()
                    };
                    if tx.send(batch).await.is_err() {
                        break;
                    }
                }
            });
            let mut stored = 0u64;
            while let Some(ack) = acks.message().await? {
                stored += u64::from(ack.stored);
                if sender.is_finished() && Instant::now() > deadline + Duration::from_millis(500) {
                    break;
                }
            }
            anyhow::Ok(stored)
        }));
    }
    let mut stored = 0;
    for task in tasks {
        stored += task.await??;
    }
    let elapsed = started.elapsed().as_secs_f64();
    println!("gRPC ingestion, {} (learner storing only, {streams} streams, batches of {per_batch}): {:.0} transitions/s", link.label, stored as f64 / elapsed);
    Ok(())
}

/// Transitions per second into a learner that only ingests, from two
/// shared-memory publisher threads (batches of 64, the sample's maximum).
async fn ingest_shm(dir: &std::path::Path, seconds: f64) -> anyhow::Result<()> {
    let run_id = format!("bench-{}", std::process::id());
    let (_learner, url) = learner(&dir.join("ingest-shm"), "peg-group1", &["--no-train", "--run-id", &run_id], &Link::plain())?;
    let mut client = LearnerClient::connect(url).await?;
    tokio::time::sleep(Duration::from_millis(500)).await;
    let transition = Transition { state: vec![0.1; 12], action: vec![0.5; 6], reward: -1.0, next_state: vec![0.2; 12], terminated: false, truncated: false, policy_version: 0, ..Default::default() };
    let first = client.get_status(GetStatusRequest {}).await?.into_inner().env_steps;
    let started = Instant::now();
    let publishers: Vec<_> = (0..2)
        .map(|p| {
            let (run_id, transition) = (run_id.clone(), transition.clone());
            std::thread::spawn(move || -> Result<(), String> {
                let publisher = lcrl_proto::shm::ShmPublisher::open(&run_id)?;
                let mut sequence = 0;
                while started.elapsed().as_secs_f64() < seconds {
                    sequence += 1;
                    let batch = TransitionBatch { run_id: run_id.clone(), actor_id: format!("shm-bench-{p}"), sequence, transitions: vec![transition.clone(); 64], ..Default::default() };
                    publisher.send(&batch)?;
                }
                Ok(())
            })
        })
        .collect();
    for p in publishers {
        p.join().map_err(|_| anyhow::anyhow!("publisher panicked"))?.map_err(anyhow::Error::msg)?;
    }
    tokio::time::sleep(Duration::from_millis(500)).await;
    let stored = client.get_status(GetStatusRequest {}).await?.into_inner().env_steps - first;
    println!("iceoryx2 ingestion (learner storing only, 2 publishers, batches of 64): {:.0} transitions/s", stored as f64 / started.elapsed().as_secs_f64());
    Ok(())
}

/// Policy.Act round trips on loopback, one at a time; returns the p50, µs.
async fn act_latency(dir: &std::path::Path, link: &Link) -> anyhow::Result<f64> {
    let (_learner, url) = learner(&dir.join("act"), "peg-group1", &[], link)?;
    let mut client = PolicyClient::new(link.client.connect(&url).await?);
    let state = vec![0.01f32, -0.02, 20.0, 0.1, -0.1, 0.0, 0.5, -0.5, 2.0, 0.01, -0.01, 0.0];
    for _ in 0..100 {
        client.act(ActRequest { state: state.clone() }).await?;
    }
    let mut micros: Vec<f64> = Vec::with_capacity(2000);
    for _ in 0..2000 {
        let started = Instant::now();
        client.act(ActRequest { state: state.clone() }).await?;
        micros.push(started.elapsed().as_secs_f64() * 1e6);
    }
    micros.sort_by(f64::total_cmp);
    let pct = |p: f64| micros[((micros.len() as f64 - 1.0) * p) as usize];
    println!("Policy.Act over gRPC loopback, {} (peg-group1, default actor): p50 {:.0} µs, p99 {:.0} µs", link.label, pct(0.5), pct(0.99));
    // The floor: a trivial call (health check) on the same server.
    let channel = link.client.connect(&url).await?;
    let mut health = tonic_health::pb::health_client::HealthClient::new(channel);
    let mut floor: Vec<f64> = Vec::with_capacity(2000);
    for _ in 0..2000 {
        let started = Instant::now();
        health.check(tonic_health::pb::HealthCheckRequest { service: String::new() }).await?;
        floor.push(started.elapsed().as_secs_f64() * 1e6);
    }
    floor.sort_by(f64::total_cmp);
    println!("  a trivial call on the same server (grpc.health.v1.Health/Check): p50 {:.0} µs", floor[floor.len() / 2]);
    // The same work without the network: what the handler itself costs.
    let mut learner_client = LearnerClient::new(link.client.connect(&url).await?).max_decoding_message_size(16 << 20);
    let snapshot = learner_client.get_policy(lcrl_proto::v1::GetPolicyRequest {}).await?.into_inner();
    let policy = lcrl_learner::policy::trained::Policy::from_snapshot(&snapshot.architecture, &snapshot.weights, snapshot.version)?;
    let env = lcrl_sim::make_env("peg-group1")?;
    let raw: Vec<f64> = state.iter().map(|&v| f64::from(v)).collect();
    let started = Instant::now();
    for _ in 0..2000 {
        std::hint::black_box(policy.act(env.as_ref(), &raw));
    }
    println!("  of which in-process Policy::act (normalize, libtorch forward, scale): {:.0} µs per call", started.elapsed().as_secs_f64() * 1e6 / 2000.0);
    Ok(pct(0.5))
}

/// Environment steps per second with the learner training and N actors,
/// against the same environments and policy stepped alone in this process.
async fn end_to_end(dir: &std::path::Path, seconds: f64) -> anyhow::Result<()> {
    let env_name = "peg-group1";
    // Alone: one env stepped with a policy forward per step.
    let policy = {
        let (_learner, url) = learner(&dir.join("alone"), env_name, &[], &Link::plain())?;
        let mut client = LearnerClient::connect(url).await?.max_decoding_message_size(16 << 20);
        let snapshot = client.get_policy(lcrl_proto::v1::GetPolicyRequest {}).await?.into_inner();
        lcrl_learner::policy::trained::Policy::from_snapshot(&snapshot.architecture, &snapshot.weights, snapshot.version)?
    };
    let alone = tokio::task::block_in_place(|| -> anyhow::Result<f64> {
        tch::set_num_threads(1);
        let mut env = lcrl_sim::make_env(env_name)?;
        let mut state = env.reset(0)?;
        let (started, mut steps, mut seed) = (Instant::now(), 0u64, 0u64);
        while started.elapsed().as_secs_f64() < seconds {
            let step = env.step(&policy.act(env.as_ref(), &state))?;
            steps += 1;
            state = if step.terminated || step.truncated {
                seed += 1;
                env.reset(seed)?
            } else {
                step.state
            };
        }
        Ok(steps as f64 / started.elapsed().as_secs_f64())
    })?;
    println!("{env_name} stepped alone with the policy, one thread: {alone:.0} env steps/s");
    for actors in [1usize, 2] {
        let (_learner, url) = learner(&dir.join(format!("e2e{actors}")), env_name, &[], &Link::plain())?;
        let _actors: Vec<Proc> = (0..actors)
            .map(|_| Command::new(sibling("lcrl-actor")?).args(["--learner", &url, "--envs", "1"]).stdout(Stdio::null()).stderr(Stdio::null()).spawn().map(Proc).map_err(anyhow::Error::from))
            .collect::<anyhow::Result<_>>()?;
        let mut client = LearnerClient::connect(url.clone()).await?;
        // Let the actors connect and warm up before measuring.
        tokio::time::sleep(Duration::from_secs(2)).await;
        let first = client.get_status(GetStatusRequest {}).await?.into_inner();
        let started = Instant::now();
        tokio::time::sleep(Duration::from_secs_f64(seconds)).await;
        let last = client.get_status(GetStatusRequest {}).await?.into_inner();
        let rate = (last.env_steps - first.env_steps) as f64 / started.elapsed().as_secs_f64();
        let updates = (last.updates - first.updates) as f64 / started.elapsed().as_secs_f64();
        println!(
            "{actors} actor(s) + training learner: {rate:.0} env steps/s ({:.2}× one env alone), {updates:.0} updates/s",
            rate / alone
        );
    }
    Ok(())
}
