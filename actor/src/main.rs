//! `lcrl-actor`: runs K environments with its local copy of the newest
//! policy plus exploration noise, and streams their transitions to the
//! learner in batches. It waits for the learner at start (until a
//! deadline), reconnects with backoff when the learner goes away, picks up
//! new policy versions without stopping, and never queues without bound:
//! the worker blocks when a few batches are waiting.

use std::collections::VecDeque;
use std::sync::atomic::{AtomicBool, Ordering};
use std::sync::Arc;
use std::time::{Duration, Instant};

mod metrics;

use anyhow::{bail, Context};
use clap::Parser;
use lcrl_proto::process::shutdown_signal;
use lcrl_learner::policy::Policy;
use lcrl_proto::v1::learner_client::LearnerClient;
use lcrl_proto::v1::{EpisodeSummary, GetPolicyRequest, PolicySnapshot, Transition, TransitionBatch, WatchPolicyRequest};
use rand::SeedableRng;
use rand_chacha::ChaCha8Rng;
use rand_distr::{Distribution, Normal};
use tokio::sync::{mpsc, watch};
use tokio_stream::wrappers::ReceiverStream;
use tokio_stream::StreamExt;
use lcrl_proto::security::{AuthChannel, ClientSecurity, ClientSecurityArgs};

/// Batches in flight or waiting: the bound on what an actor holds.
const MAX_PENDING_BATCHES: usize = 8;

#[derive(Debug, Clone, Copy, clap::ValueEnum)]
enum Transport {
    /// gRPC to the learner's URL (any host).
    Grpc,
    /// iceoryx2 shared memory (same host): transitions out and policies in,
    /// no network; --learner is not used.
    Shm,
}

#[derive(Debug, Parser)]
#[command(version, about = "An LCRL actor: simulators streaming transitions to the learner")]
struct Args {
    /// The learner's gRPC URL.
    #[arg(long, default_value = "http://127.0.0.1:50052")]
    learner: String,
    #[arg(long, value_enum, default_value_t = Transport::Grpc)]
    transport: Transport,
    /// Environment instances in this process.
    #[arg(long, default_value_t = 1)]
    envs: usize,
    /// The run to join (must match the learner's --run-id).
    #[arg(long, default_value = "default")]
    run_id: String,
    /// This actor's name (default: host name and process id).
    #[arg(long)]
    actor_id: Option<String>,
    /// Transitions per batch.
    #[arg(long, default_value_t = 64)]
    batch: usize,
    /// Exploration noise std in normalized action units (DDPG; PPO uses the
    /// policy's own std).
    #[arg(long, default_value_t = 0.1)]
    noise: f64,
    /// Seed of episodes and noise.
    #[arg(long, default_value_t = 0)]
    seed: u64,
    /// Give up when the learner stays unreachable this long, seconds (at
    /// start and after losing it).
    #[arg(long, default_value_t = 120)]
    connect_deadline: u64,
    /// Stop after this many episodes in total (default: run until stopped).
    #[arg(long)]
    episodes: Option<u64>,
    /// Serve Prometheus metrics on http://ADDR/metrics (port 0: any free
    /// port, printed as "metrics on ADDR").
    #[arg(long, value_name = "ADDR")]
    metrics_listen: Option<std::net::SocketAddr>,
    /// Log as JSON lines instead of human-readable text (level: RUST_LOG).
    #[arg(long)]
    log_json: bool,
    #[command(flatten)]
    security: ClientSecurityArgs,
}

fn main() -> std::process::ExitCode {
    let args = Args::parse();
    // The environments step on their own thread; the runtime only talks.
    lcrl_proto::process::run_service("lcrl-actor", args.log_json, 1, run(args))
}

/// Connects, retrying with backoff until `deadline`.
async fn connect(url: &str, security: &ClientSecurity, deadline: Duration) -> anyhow::Result<LearnerClient<AuthChannel>> {
    let give_up = Instant::now() + deadline;
    let mut delay = Duration::from_millis(100);
    loop {
        match security.connect(url).await {
            Ok(channel) => return Ok(LearnerClient::new(channel).max_decoding_message_size(16 << 20).max_encoding_message_size(16 << 20)),
            Err(e) if Instant::now() < give_up => {
                tracing::warn!("learner at {url} unreachable ({e}); retrying in {:.1} s", delay.as_secs_f64());
                tokio::time::sleep(delay).await;
                delay = (delay * 2).min(Duration::from_secs(5));
            }
            Err(e) => bail!("the learner at {url} stayed unreachable for {} s ({e}); is lcrl-learner running?", deadline.as_secs()),
        }
    }
}

async fn run(args: Args) -> anyhow::Result<()> {
    if args.envs == 0 || args.batch == 0 {
        bail!("--envs and --batch must be at least 1");
    }
    if matches!(args.transport, Transport::Shm) && args.batch > lcrl_learner::service::shm::MAX_TRANSITIONS {
        bail!("--transport shm carries at most {} transitions per batch; lower --batch", lcrl_learner::service::shm::MAX_TRANSITIONS);
    }
    let deadline = Duration::from_secs(args.connect_deadline);
    let security = ClientSecurity::from_args(&args.security)?;
    let metrics = metrics::ActorMetrics::default();
    if let Some(addr) = args.metrics_listen {
        let registry = Arc::new(metrics.registry());
        let (listener, bound) = lcrl_learner::service::metrics::bind(addr).await.with_context(|| format!("cannot serve metrics on {addr}; is another process using it?"))?;
        // Not println!: a launcher may have stopped reading stdout.
        let _ = std::io::Write::write_fmt(&mut std::io::stdout(), format_args!("metrics on {bound}\n"));
        tokio::spawn(async move {
            if let Err(e) = lcrl_learner::service::metrics::serve(listener, registry, std::future::pending()).await {
                tracing::warn!("metrics endpoint stopped: {e}");
            }
        });
    }
    // gRPC actors get the policy from the learner's URL; shared-memory
    // actors from the run's broadcast, without any network.
    let (client, policy_source) = match args.transport {
        Transport::Grpc => {
            let mut client = connect(&args.learner, &security, deadline).await?;
            let first = client.get_policy(GetPolicyRequest {}).await.map_err(refused).context("asking the learner for its policy")?.into_inner();
            tracing::info!(version = first.version, learner = %args.learner, "connected");
            let (policy_tx, policy_rx) = watch::channel(Arc::new(first));
            tokio::spawn(watch_policy(args.learner.clone(), security.clone(), policy_tx));
            (Some(client), PolicySource::Grpc(policy_rx))
        }
        Transport::Shm => (None, PolicySource::Shm(args.run_id.clone(), deadline)),
    };
    let stop = Arc::new(AtomicBool::new(false));
    let finished = Arc::new(AtomicBool::new(false));
    let actor_id = args.actor_id.clone().unwrap_or_else(|| format!("{}-{}", hostname(), std::process::id()));
    let (sink, sender) = match client {
        Some(client) => {
            let (batches_tx, batches_rx) = mpsc::channel::<TransitionBatch>(2);
            (Sink::Grpc(batches_tx), Some(tokio::spawn(send_batches(args.learner.clone(), security.clone(), client, batches_rx, deadline, metrics.clone()))))
        }
        None => (Sink::Shm(args.run_id.clone()), None),
    };
    let worker = {
        let (stop, finished) = (stop.clone(), finished.clone());
        let settings = WorkerSettings { envs: args.envs, batch: args.batch, noise: args.noise, seed: args.seed, episodes: args.episodes, run_id: args.run_id.clone(), actor_id, metrics: metrics.clone() };
        std::thread::Builder::new().name("envs".into()).spawn(move || {
            let result = work(settings, policy_source, sink, stop);
            finished.store(true, Ordering::Relaxed);
            result
        })?
    };
    match sender {
        Some(sender) => tokio::select! {
            result = sender => result.context("the sender task panicked")??,
            _ = shutdown_signal() => tracing::info!("stopping"),
        },
        None => tokio::select! {
            _ = async { while !finished.load(Ordering::Relaxed) { tokio::time::sleep(Duration::from_millis(100)).await } } => {},
            _ = shutdown_signal() => tracing::info!("stopping"),
        },
    }
    stop.store(true, Ordering::Relaxed);
    // The worker checks `stop` between steps, but a send can block while the
    // learner's rate limiter holds this actor back. Stopping must not wait
    // on the learner: after a grace period the process exits without the
    // worker (its unsent batch is lost, as any unacknowledged batch is).
    let deadline = Instant::now() + Duration::from_secs(2);
    while !finished.load(Ordering::Relaxed) && Instant::now() < deadline {
        tokio::time::sleep(Duration::from_millis(20)).await;
    }
    if !finished.load(Ordering::Relaxed) {
        tracing::warn!("the environment thread is blocked sending to a learner that holds actors back; exiting without it");
        return Ok(());
    }
    worker.join().map_err(|_| anyhow::anyhow!("the environment thread panicked"))??;
    Ok(())
}

fn hostname() -> String {
    std::fs::read_to_string("/etc/hostname").map(|h| h.trim().to_string()).unwrap_or_else(|_| "actor".into())
}

/// Keeps `policy` at the learner's newest version, reconnecting forever.
async fn watch_policy(url: String, security: ClientSecurity, policy: watch::Sender<Arc<PolicySnapshot>>) {
    loop {
        let after = policy.borrow().version;
        let stream = async { LearnerClient::new(security.connect(&url).await?).max_decoding_message_size(16 << 20).watch_policy(WatchPolicyRequest { after_version: after }).await.map_err(anyhow::Error::from) };
        match stream.await {
            Ok(response) => {
                let mut updates = response.into_inner();
                while let Some(Ok(snapshot)) = updates.next().await {
                    if snapshot.version > policy.borrow().version {
                        policy.send_replace(Arc::new(snapshot));
                    }
                }
            }
            Err(e) => tracing::debug!("policy watch: {e}"),
        }
        tokio::time::sleep(Duration::from_millis(500)).await;
    }
}

/// Streams batches to the learner; resends unacknowledged ones after a
/// reconnect (the learner drops duplicates). Returns when the worker is done
/// and every batch is acknowledged, or fails after `deadline` without a
/// learner.
async fn send_batches(url: String, security: ClientSecurity, mut client: LearnerClient<AuthChannel>, mut batches: mpsc::Receiver<TransitionBatch>, deadline: Duration, metrics: metrics::ActorMetrics) -> anyhow::Result<()> {
    let mut pending: VecDeque<TransitionBatch> = VecDeque::new();
    let mut worker_done = false;
    loop {
        let (requests, request_rx) = mpsc::channel::<TransitionBatch>(MAX_PENDING_BATCHES);
        for batch in &pending {
            let _ = requests.try_send(batch.clone());
        }
        let acks = match client.stream_transitions(ReceiverStream::new(request_rx)).await {
            Ok(response) => Some(response.into_inner()),
            Err(status) if status.code() == tonic::Code::Unauthenticated => return Err(refused(status)),
            Err(status) => {
                tracing::warn!("cannot stream to the learner: {status}");
                None
            }
        };
        if let Some(mut acks) = acks {
            loop {
                if worker_done && pending.is_empty() {
                    return Ok(());
                }
                tokio::select! {
                    batch = batches.recv(), if !worker_done && pending.len() < MAX_PENDING_BATCHES => match batch {
                        Some(batch) => {
                            pending.push_back(batch.clone());
                            metrics.pending_batches.set(pending.len() as i64);
                            if requests.send(batch).await.is_err() {
                                break;
                            }
                        }
                        None => worker_done = true,
                    },
                    ack = acks.next() => match ack {
                        Some(Ok(ack)) => {
                            pending.retain(|b| b.sequence > ack.sequence);
                            metrics.pending_batches.set(pending.len() as i64);
                            if ack.outcome != "stored" {
                                tracing::debug!(sequence = ack.sequence, outcome = %ack.outcome, "batch not stored");
                            }
                        }
                        Some(Err(status)) if status.code() == tonic::Code::InvalidArgument => {
                            // The learner will never take this batch; drop it and go on.
                            tracing::error!("the learner rejected a batch: {}", status.message());
                            pending.pop_front();
                            break;
                        }
                        Some(Err(status)) if status.code() == tonic::Code::Unauthenticated => return Err(refused(status)),
                        Some(Err(status)) => {
                            tracing::warn!("lost the learner: {status}");
                            break;
                        }
                        None => break,
                    },
                }
            }
        }
        if worker_done && pending.is_empty() {
            return Ok(());
        }
        client = connect(&url, &security, deadline).await?;
        metrics.reconnects.inc();
    }
}

/// A refusal as an error that says what to do (a wrong token never heals,
/// so the actor stops instead of retrying).
fn refused(status: tonic::Status) -> anyhow::Error {
    match status.code() {
        tonic::Code::Unauthenticated => anyhow::anyhow!("the learner refused this actor: {} (give the learner's token with --token-file or LCRL_TOKEN_FILE)", status.message()),
        _ => anyhow::anyhow!("{status}"),
    }
}

/// Where the worker's policy comes from.
enum PolicySource {
    /// Kept current by the WatchPolicy task.
    Grpc(watch::Receiver<Arc<PolicySnapshot>>),
    /// The run's shared-memory broadcast; wait at most this long for it.
    Shm(String, Duration),
}

/// The worker thread's open end of its policy source.
enum Feed {
    Grpc(watch::Receiver<Arc<PolicySnapshot>>),
    Shm(lcrl_learner::service::shm::PolicySubscriber),
}

/// How the worker explores with the current version (from its snapshot).
#[derive(Debug, Clone, Copy, PartialEq)]
struct Exploration {
    /// Uniformly random actions (the learner is warming up, DDPG).
    uniform: bool,
    /// Gaussian noise std the learner asks for (DDPG; 0: use --noise).
    noise: f64,
}

impl Exploration {
    fn of(snapshot: &PolicySnapshot) -> Self {
        Exploration { uniform: snapshot.explore_uniform, noise: snapshot.exploration_noise }
    }
}

/// Opens the source and returns it with the first policy.
fn open_feed(source: PolicySource, stop: &AtomicBool) -> anyhow::Result<(Feed, Policy, Exploration)> {
    match source {
        PolicySource::Grpc(mut rx) => {
            let snapshot = rx.borrow_and_update().clone();
            let policy = Policy::from_snapshot(&snapshot.architecture, &snapshot.weights, snapshot.version)?;
            Ok((Feed::Grpc(rx), policy, Exploration::of(&snapshot)))
        }
        PolicySource::Shm(run_id, deadline) => {
            let subscriber = lcrl_learner::service::shm::PolicySubscriber::open(&run_id).map_err(anyhow::Error::msg)?;
            let started = Instant::now();
            let mut last_log = Instant::now() - Duration::from_secs(10);
            loop {
                if let Some(snapshot) = subscriber.newest().map_err(anyhow::Error::msg)? {
                    tracing::info!(version = snapshot.version, "policy received over shared memory");
                    let policy = Policy::from_snapshot(&snapshot.architecture, &snapshot.weights, snapshot.version)?;
                    return Ok((Feed::Shm(subscriber), policy, Exploration::of(&snapshot)));
                }
                if stop.load(Ordering::Relaxed) {
                    bail!("stopped while waiting for the policy");
                }
                if started.elapsed() > deadline {
                    bail!("no policy of run '{run_id}' on shared memory within {} s; is lcrl-learner running on this host with --run-id {run_id}?", deadline.as_secs());
                }
                if last_log.elapsed() > Duration::from_secs(2) {
                    tracing::warn!("waiting for the policy of run '{run_id}' on shared memory; retrying");
                    last_log = Instant::now();
                }
                std::thread::sleep(Duration::from_millis(50));
            }
        }
    }
}

/// Where the worker's batches go.
enum Sink {
    /// To the gRPC sender task (bounded channel).
    Grpc(mpsc::Sender<TransitionBatch>),
    /// Straight into the run's shared-memory service.
    Shm(String),
}

/// The worker thread's open end of its sink.
enum Out {
    Grpc(mpsc::Sender<TransitionBatch>),
    Shm(lcrl_learner::service::shm::ShmPublisher),
}

struct WorkerSettings {
    envs: usize,
    batch: usize,
    noise: f64,
    seed: u64,
    episodes: Option<u64>,
    run_id: String,
    actor_id: String,
    metrics: metrics::ActorMetrics,
}

/// Exploration noise per action component: the policy's own std (PPO), or
/// the learner's schedule (DDPG; `noise` when the learner sets none), in
/// normalized action units.
fn exploration_normals(policy: &Policy, exploration: Exploration, noise: f64) -> Vec<Normal<f64>> {
    let noise = if exploration.noise > 0.0 { exploration.noise } else { noise };
    let std: Vec<f64> = policy.exploration_std().map_or_else(|| vec![noise; policy.architecture.action_dim], |v| v.iter().map(|&x| f64::from(x)).collect());
    // A non-finite or non-positive std (a diverged policy, a bad flag) acts
    // greedily rather than failing; the argument below is then always valid.
    std.iter()
        .map(|&sd| Normal::new(0.0, if sd.is_finite() && sd > 0.0 { sd } else { 1e-9 }).expect("finite positive std"))
        .collect()
}

/// The environment loop (blocking thread).
fn work(s: WorkerSettings, source: PolicySource, sink: Sink, stop: Arc<AtomicBool>) -> anyhow::Result<()> {
    tch::set_num_threads(1);
    // iceoryx2 ports stay on the thread that made them.
    let out = match sink {
        Sink::Grpc(batches) => Out::Grpc(batches),
        Sink::Shm(run_id) => Out::Shm(lcrl_learner::service::shm::ShmPublisher::open(&run_id).map_err(anyhow::Error::msg)?),
    };
    let (mut feed, mut policy, mut explore) = open_feed(source, &stop)?;
    let mut exploration = exploration_normals(&policy, explore, s.noise);
    // PPO samples its own Gaussian; the learner's uniform warm-up is DDPG's.
    let own_distribution = policy.exploration_std().is_some();
    s.metrics.policy_version.set(policy.version as i64);
    let env_name = policy.architecture.env.clone();
    let mut envs: Vec<Box<dyn lcrl_sim::Env>> = (0..s.envs).map(|_| lcrl_sim::make_env(&env_name)).collect::<Result<_, _>>()?;
    policy.check_env(envs[0].as_ref())?;
    // The base is part of the architecture, which newer weights never
    // change, and the K environments share one spec: one map for the run.
    let action_map = policy.action_map(envs[0].as_ref())?;
    // Actors differ by name (container replicas all run as process 1), and
    // the same name and seed give the same episodes.
    let salt = {
        use std::hash::{Hash, Hasher};
        let mut hasher = std::collections::hash_map::DefaultHasher::new();
        s.actor_id.hash(&mut hasher);
        hasher.finish()
    };
    let mut rng = ChaCha8Rng::seed_from_u64(s.seed ^ salt);
    let mut episode_seed = s.seed.wrapping_mul(1_000_003) ^ (salt << 20);
    let mut states: Vec<Vec<f64>> = envs
        .iter_mut()
        .map(|env| {
            episode_seed += 1;
            env.reset(episode_seed)
        })
        .collect::<Result<_, _>>()?;
    let mut returns = vec![0.0f64; s.envs];
    let mut lengths = vec![0u32; s.envs];
    // The learner keeps the highest sequence per actor id and drops what is
    // not above it. Starting from the clock (µs) keeps a restarted actor
    // with the same id (a container restart: same host name, process 1)
    // above everything its previous life sent.
    let mut sequence = std::time::SystemTime::now().duration_since(std::time::UNIX_EPOCH).map_or(0, |d| d.as_micros() as u64);
    let mut episodes_done = 0u64;
    let mut batch = TransitionBatch { run_id: s.run_id.clone(), actor_id: s.actor_id.clone(), ..Default::default() };
    // Each environment's transitions stay contiguous in a batch, its last
    // one marked as a cut, so the learner sees whole trajectory segments.
    let mut segments: Vec<Vec<Transition>> = vec![Vec::new(); s.envs];
    while !stop.load(Ordering::Relaxed) && s.episodes.is_none_or(|limit| episodes_done < limit) {
        let version = policy.version;
        match &mut feed {
            Feed::Grpc(rx) => {
                if rx.has_changed().unwrap_or(false) {
                    let newest = rx.borrow_and_update().clone();
                    policy.update(&newest.weights, newest.version)?;
                    explore = Exploration::of(&newest);
                }
            }
            Feed::Shm(subscriber) => {
                if let Some(newest) = subscriber.newest().map_err(anyhow::Error::msg)? {
                    if newest.version > policy.version {
                        policy.update(&newest.weights, newest.version)?;
                        explore = Exploration::of(&newest);
                    }
                }
            }
        }
        if policy.version != version {
            exploration = exploration_normals(&policy, explore, s.noise);
            s.metrics.policy_version.set(policy.version as i64);
        }
        let mut actions = Vec::with_capacity(envs.len());
        for (k, env) in envs.iter().enumerate() {
            let obs = lcrl_learner::trainer::observe(env.as_ref(), &states[k]);
            let u: Vec<f32> = if explore.uniform && !own_distribution {
                // The learner is filling its replay buffer: uniformly random
                // actions, as `lcrl train` warms up.
                (0..policy.architecture.action_dim).map(|_| rand::Rng::random_range(&mut rng, -1.0f32..=1.0)).collect()
            } else {
                policy
                    .act_normalized(&obs)
                    .iter()
                    .zip(&exploration)
                    .map(|(&a, noise)| (f64::from(a) + noise.sample(&mut rng)).clamp(-1.0, 1.0) as f32)
                    .collect()
            };
            actions.push(action_map.to_env(&u));
        }
        // All K environments at once: one call when a server serves them.
        let steps = lcrl_sim::step_all(&mut envs, &actions)?;
        for (k, (step, action)) in steps.into_iter().zip(&actions).enumerate() {
            returns[k] += step.reward;
            lengths[k] += 1;
            s.metrics.env_steps.inc();
            segments[k].push(Transition {
                state: states[k].iter().map(|&v| v as f32).collect(),
                action: action.iter().map(|&v| v as f32).collect(),
                reward: step.reward as f32,
                next_state: step.state.iter().map(|&v| v as f32).collect(),
                terminated: step.terminated,
                // A batch boundary is not an episode end, but each env's
                // stream is cut there for PPO's advantage estimates.
                truncated: step.truncated,
                policy_version: policy.version,
            });
            if step.terminated || step.truncated {
                batch.episodes.push(EpisodeSummary { episode_return: returns[k], length: lengths[k], success: envs[k].episode_metrics().success });
                episodes_done += 1;
                s.metrics.episodes.inc();
                returns[k] = 0.0;
                lengths[k] = 0;
                episode_seed += 1;
                states[k] = envs[k].reset(episode_seed)?;
            } else {
                states[k] = step.state;
            }
        }
        let done = s.episodes.is_some_and(|limit| episodes_done >= limit);
        let collected: usize = segments.iter().map(Vec::len).sum();
        if collected >= s.batch || (done && collected > 0) {
            for segment in segments.iter_mut() {
                if let Some(last) = segment.last_mut() {
                    last.truncated |= !last.terminated;
                }
                batch.transitions.append(segment);
            }
            sequence += 1;
            batch.sequence = sequence;
            batch.episode_id = episodes_done;
            batch.policy_version = policy.version;
            let full = std::mem::replace(&mut batch, TransitionBatch { run_id: s.run_id.clone(), actor_id: s.actor_id.clone(), ..Default::default() });
            s.metrics.batches_sent.inc();
            s.metrics.transitions_sent.inc_by(full.transitions.len() as u64);
            // Both sinks block while the learner is behind: bounded memory.
            match &out {
                Out::Shm(publisher) => publisher.send(&full).map_err(anyhow::Error::msg)?,
                Out::Grpc(batches) => {
                    if batches.blocking_send(full).is_err() {
                        break;
                    }
                }
            }
        }
    }
    Ok(())
}
