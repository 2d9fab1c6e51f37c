//! The actor process, as a library function: `lcrl-actor` parses its
//! arguments ([`ActorArgs`]) and calls [`run`], which reads as its steps:
//! check the flags, serve /metrics, reach the learner (gRPC) or the run's
//! broadcast (shared memory), start the sender task and the environment
//! thread ([`work`]), wait until either ends or the process is told to
//! stop, then stop the thread within a grace period.
//!
//! The actor waits for the learner at start (until a deadline), reconnects
//! with backoff when the learner goes away, picks up new policy versions
//! without stopping, and never queues without bound: the worker blocks
//! when a few batches are waiting.

use std::future::Future;
use std::net::SocketAddr;
use std::sync::atomic::{AtomicBool, Ordering};
use std::sync::Arc;
use std::time::{Duration, Instant};

use anyhow::{bail, Context};
use clap::Parser;
use lcrl_runtime::security::{AuthChannel, ClientSecurity, ClientSecurityArgs};
use lcrl_proto::v1::learner_client::LearnerClient;
use lcrl_proto::v1::TransitionBatch;
use tokio::sync::{mpsc, watch};

use crate::metrics::ActorMetrics;
use crate::transport::{connect, first_policy, open_feed, send_batches, watch_policy, BatchSender, Out, PolicySource, Progress, Sink};
use crate::worker::{check_batch_fits, Rollout, RolloutSettings};

#[derive(Debug, Clone, Copy, clap::ValueEnum)]
pub enum Transport {
    /// gRPC to the learner's URL (any host).
    Grpc,
    /// iceoryx2 shared memory (same host): transitions out and policies in,
    /// no network; --learner is not used.
    Shm,
}

#[derive(Debug, Parser)]
#[command(version, about = "An LCRL actor: simulators streaming transitions to the learner")]
pub struct ActorArgs {
    /// The learner's gRPC URL.
    #[arg(long, default_value = "http://127.0.0.1:50052")]
    pub learner: String,
    #[arg(long, value_enum, default_value_t = Transport::Grpc)]
    pub transport: Transport,
    /// Environment instances in this process (1 to 1024).
    #[arg(long, default_value_t = 1, value_parser = lcrl_runtime::process::count_in::<1, MAX_ENVS>)]
    pub envs: usize,
    /// The run to join (must match the learner's --run-id).
    #[arg(long, default_value = "default")]
    pub run_id: String,
    /// This actor's name (default: host name and process id).
    #[arg(long)]
    pub actor_id: Option<String>,
    /// Transitions per batch. Default: 16 for DDPG (a batch's steps all
    /// wait for the learner together, so a smaller batch is less policy
    /// lag), 64 for PPO (each batch end cuts PPO's advantage estimates);
    /// docs/scaling.md, "Policy lag". 1 to 4096.
    #[arg(long, value_parser = lcrl_runtime::process::count_in::<1, MAX_BATCH>)]
    pub batch: Option<usize>,
    /// Exploration noise std in normalized action units (DDPG; PPO uses the
    /// policy's own std). A finite number ≥ 0.
    #[arg(long, default_value_t = 0.1, value_parser = noise_std)]
    pub noise: f64,
    /// Seed of episodes and noise.
    #[arg(long, default_value_t = 0)]
    pub seed: u64,
    /// Give up when the learner stays unreachable this long, seconds (at
    /// start and after losing it); 1 to 86400 (a day).
    #[arg(long, default_value_t = 120, value_parser = clap::value_parser!(u64).range(1..=MAX_CONNECT_DEADLINE_S))]
    pub connect_deadline: u64,
    /// Stop after this many episodes in total (default: run until stopped).
    #[arg(long)]
    pub episodes: Option<u64>,
    /// `/healthz` on the metrics address answers 503 when the learner has
    /// acknowledged no batch and sent no policy for this long, seconds
    /// (Kubernetes' liveness probe then restarts the actor).
    #[arg(long, default_value_t = 300, value_parser = clap::value_parser!(u64).range(1..=86_400))]
    pub liveness_secs: u64,
    /// Serve Prometheus metrics and /healthz on http://ADDR (port 0: any
    /// free port, printed as "metrics on ADDR").
    #[arg(long, value_name = "ADDR")]
    pub metrics_listen: Option<SocketAddr>,
    /// Log as JSON lines instead of human-readable text (level: RUST_LOG).
    #[arg(long)]
    pub log_json: bool,
    #[command(flatten)]
    pub security: ClientSecurityArgs,
}

/// The most environments one actor process runs (`--envs`).
const MAX_ENVS: usize = 1024;
/// The most transitions per batch (`--batch`): a gRPC batch stays far
/// below the learner's message limit.
const MAX_BATCH: usize = 4096;
/// The longest `--connect-deadline`, seconds (a day): a longer one would
/// overflow the clock's deadline arithmetic.
const MAX_CONNECT_DEADLINE_S: u64 = 86_400;

/// `--noise`: a finite standard deviation ≥ 0 (NaN would poison every
/// action it is added to).
fn noise_std(text: &str) -> Result<f64, String> {
    match text.trim().parse::<f64>() {
        Ok(v) if v.is_finite() && v >= 0.0 => Ok(v),
        _ => Err("expected a finite number ≥ 0 (a standard deviation in normalized action units)".to_string()),
    }
}

/// The actor process until its environments are done, the learner is
/// gone past `--connect-deadline`, or `shutdown` resolves (`lcrl-actor`
/// passes SIGTERM/Ctrl-C).
pub async fn run(args: ActorArgs, shutdown: impl Future<Output = ()>) -> anyhow::Result<()> {
    if args.envs == 0 || args.batch == Some(0) {
        bail!("--envs and --batch must be at least 1");
    }
    if matches!(args.transport, Transport::Shm) && args.batch.is_some_and(|b| b > lcrl_proto::shm::MAX_TRANSITIONS) {
        bail!("--transport shm carries at most {} transitions per batch; lower --batch", lcrl_proto::shm::MAX_TRANSITIONS);
    }
    let deadline = Duration::from_secs(args.connect_deadline);
    let security = ClientSecurity::from_args(&args.security)?;
    let metrics = ActorMetrics::default();
    let progress = Progress::default();
    if let Some(addr) = args.metrics_listen {
        serve_metrics(addr, &args, &metrics, &progress).await?;
    }
    // gRPC actors get the policy from the learner's URL; shared-memory
    // actors from the run's broadcast, without any network.
    let (client, policy_source) = match args.transport {
        Transport::Grpc => {
            let (client, policy_source) = reach_learner(&args, &security, deadline, &progress).await?;
            (Some(client), policy_source)
        }
        // The run's shared memory goes by a name its token derives (a
        // token-protected learner's cannot be found without it).
        Transport::Shm => (None, PolicySource::Shm(security.shm_key(&args.run_id), deadline)),
    };
    let flags = Flags::default();
    let actor_id = args.actor_id.clone().unwrap_or_else(|| format!("{}-{}", hostname(), std::process::id()));
    let (sink, sender) = match client {
        Some(client) => {
            let (batches_tx, batches_rx) = mpsc::channel::<TransitionBatch>(2);
            let sender = BatchSender { learner: args.learner.clone(), security, client, deadline, metrics: metrics.clone(), progress };
            (Sink::Grpc(batches_tx), Some(tokio::spawn(send_batches(sender, batches_rx))))
        }
        None => (Sink::Shm(security.shm_key(&args.run_id)), None),
    };
    let settings = RolloutSettings { envs: args.envs, batch: args.batch, noise: args.noise, seed: args.seed, episodes: args.episodes, run_id: args.run_id.clone(), actor_id };
    let worker = spawn_envs(settings, policy_source, sink, &flags, metrics)?;
    wait(sender, &flags, shutdown).await?;
    stop_envs(worker, &flags).await
}

/// What the process and its environment thread tell each other.
#[derive(Debug, Clone, Default)]
struct Flags {
    /// Set by the process: the thread stops between steps.
    stop: Arc<AtomicBool>,
    /// Set by the thread when it returns.
    finished: Arc<AtomicBool>,
    /// Set when the learner says its budget is spent (as opposed to this
    /// actor's own --episodes): nothing unsent matters any more.
    budget_spent: Arc<AtomicBool>,
}

/// The environment thread: its result, once `finished` is set.
type Envs = std::thread::JoinHandle<anyhow::Result<()>>;

/// Serves Prometheus metrics and /healthz on `addr`, and prints the bound
/// address as "metrics on ADDR".
async fn serve_metrics(addr: SocketAddr, args: &ActorArgs, metrics: &ActorMetrics, progress: &Progress) -> anyhow::Result<()> {
    let registry = Arc::new(metrics.registry());
    let (listener, bound) = lcrl_runtime::metrics_http::bind(addr).await.with_context(|| format!("cannot serve metrics on {addr}; is another process using it?"))?;
    // Not println!: a launcher may have stopped reading stdout.
    let _ = std::io::Write::write_fmt(&mut std::io::stdout(), format_args!("metrics on {bound}\n"));
    // Live while the learner answers: a batch acknowledged or a policy
    // received within --liveness-secs (shared memory: the learner is on
    // this host, and the process is live).
    let (heard, limit, grpc) = (progress.clone(), Duration::from_secs(args.liveness_secs), matches!(args.transport, Transport::Grpc));
    let live = move || match heard.since() {
        silent if grpc && silent > limit => Err(format!("no answer from the learner for {} s (--liveness-secs {})", silent.as_secs(), limit.as_secs())),
        _ => Ok(()),
    };
    tokio::spawn(async move {
        if let Err(e) = lcrl_runtime::metrics_http::serve(listener, registry, std::future::pending(), live).await {
            tracing::warn!("metrics endpoint stopped: {e}");
        }
    });
    Ok(())
}

/// Connects to the learner at `--learner` and takes its first policy,
/// both within `deadline`; newer versions arrive from a watch task.
async fn reach_learner(args: &ActorArgs, security: &ClientSecurity, deadline: Duration, progress: &Progress) -> anyhow::Result<(LearnerClient<AuthChannel>, PolicySource)> {
    let started = Instant::now();
    let mut client = connect(&args.learner, security, deadline).await?;
    // One deadline for connecting and the first policy together.
    let first = first_policy(&mut client, &args.learner, deadline.saturating_sub(started.elapsed())).await?;
    tracing::info!(version = first.version, learner = %args.learner, "connected");
    let (policy_tx, policy_rx) = watch::channel(Arc::new(first));
    tokio::spawn(watch_policy(args.learner.clone(), security.clone(), policy_tx, progress.clone()));
    Ok((client, PolicySource::Grpc(policy_rx)))
}

/// Starts the environment thread ("envs"): [`work`], then `finished`.
fn spawn_envs(settings: RolloutSettings, source: PolicySource, sink: Sink, flags: &Flags, metrics: ActorMetrics) -> anyhow::Result<Envs> {
    let Flags { stop, finished, budget_spent } = flags.clone();
    let worker = std::thread::Builder::new().name("envs".into()).spawn(move || {
        let result = work(settings, source, sink, stop, &budget_spent, metrics);
        finished.store(true, Ordering::Relaxed);
        result
    })?;
    Ok(worker)
}

/// Until the sender is done (gRPC: every batch acknowledged) or the
/// environment thread is (shared memory), the learner's budget is spent
/// and the last batches stay unanswered, or `shutdown` resolves.
async fn wait(sender: Option<tokio::task::JoinHandle<anyhow::Result<()>>>, flags: &Flags, shutdown: impl Future<Output = ()>) -> anyhow::Result<()> {
    match sender {
        Some(sender) => tokio::select! {
            result = sender => result.context("the sender task panicked")??,
            _ = budget_spent_then(&flags.budget_spent, Duration::from_secs(5)) => {
                // A learner at its budget's end may wait long for its final
                // checkpoint (a full disk is waited out: issue 71); the
                // last batches' answers are not worth waiting for.
                tracing::info!("the learner's budget is spent and it has not answered the last batches within 5 s: stopping");
            }
            _ = shutdown => tracing::info!("stopping"),
        },
        None => tokio::select! {
            _ = async { while !flags.finished.load(Ordering::Relaxed) { tokio::time::sleep(Duration::from_millis(100)).await } } => {},
            _ = shutdown => tracing::info!("stopping"),
        },
    }
    Ok(())
}

/// Tells the environment thread to stop and joins it, or leaves it after
/// a grace period.
async fn stop_envs(worker: Envs, flags: &Flags) -> anyhow::Result<()> {
    flags.stop.store(true, Ordering::Relaxed);
    // The worker checks `stop` between steps, but a send can block while the
    // learner's rate limiter holds this actor back. Stopping must not wait
    // on the learner: after a grace period the process exits without the
    // worker (its unsent batch is lost, as any unacknowledged batch is).
    let deadline = Instant::now() + Duration::from_secs(2);
    while !flags.finished.load(Ordering::Relaxed) && Instant::now() < deadline {
        tokio::time::sleep(Duration::from_millis(20)).await;
    }
    if !flags.finished.load(Ordering::Relaxed) {
        tracing::warn!("the environment thread is blocked sending to a learner that holds actors back; exiting without it");
        return Ok(());
    }
    worker.join().map_err(|_| anyhow::anyhow!("the environment thread panicked"))??;
    Ok(())
}

/// Returns `grace` after `budget_spent` is set.
async fn budget_spent_then(budget_spent: &AtomicBool, grace: Duration) {
    while !budget_spent.load(Ordering::Relaxed) {
        tokio::time::sleep(Duration::from_millis(100)).await;
    }
    tokio::time::sleep(grace).await;
}

fn hostname() -> String {
    std::fs::read_to_string("/etc/hostname").map(|h| h.trim().to_string()).unwrap_or_else(|_| "actor".into())
}

/// The environment loop (blocking thread): the newest policy, one step of
/// every environment, a batch out when one is full.
fn work(settings: RolloutSettings, source: PolicySource, sink: Sink, stop: Arc<AtomicBool>, budget_spent: &AtomicBool, metrics: ActorMetrics) -> anyhow::Result<()> {
    tch::set_num_threads(1);
    let out = sink.open()?;
    let (mut feed, mut policy, explore) = open_feed(source, &stop)?;
    metrics.policy_version.set(policy.version as i64);
    let envs = settings.envs;
    let mut rollout = Rollout::new(settings, &policy, explore)?;
    let shape = &policy.architecture.shape;
    check_batch_fits(rollout.batch_size(), envs, shape.state_dim, shape.action_dim)?;
    while !stop.load(Ordering::Relaxed) && !rollout.finished() {
        let (acting, version) = (feed.incarnation(), policy.version);
        if let Some(explore) = feed.poll(&mut policy)? {
            if feed.incarnation() != acting {
                // The learner restarted. What was collected so far was
                // acted by its previous process: it goes out under that
                // name (an on-policy learner drops it), never mixed into a
                // batch of the new one.
                if let Some(mut batch) = rollout.take_batch(version) {
                    batch.incarnation = acting;
                    if !send(&out, batch, &metrics)? {
                        break;
                    }
                }
            }
            rollout.set_exploration(&policy, explore);
            metrics.policy_version.set(policy.version as i64);
        }
        if feed.training_finished() {
            tracing::info!(episodes = rollout.episodes_done(), "the learner's episode budget is spent: stopping");
            budget_spent.store(true, Ordering::Relaxed);
            break;
        }
        if let Some(mut batch) = rollout.step(&policy, &metrics)? {
            // The learner process whose policy acted (a PPO learner drops
            // the batches of its previous process after a restart).
            batch.incarnation = feed.incarnation();
            if !send(&out, batch, &metrics)? {
                break;
            }
        }
    }
    Ok(())
}

/// Hands a batch to the transport, counted, with the time it waited;
/// false when the sender is gone.
fn send(out: &Out, batch: TransitionBatch, metrics: &ActorMetrics) -> anyhow::Result<bool> {
    metrics.batches_sent.inc();
    metrics.transitions_sent.inc_by(batch.transitions.len() as u64);
    let started = std::time::Instant::now();
    let since = std::time::SystemTime::now().duration_since(std::time::UNIX_EPOCH).map_or(0, |d| d.as_millis() as i64);
    metrics.send_waiting_since_ms.set(since.max(1));
    let sent = out.send(batch);
    metrics.send_wait_seconds.inc_by(started.elapsed().as_secs_f64());
    metrics.send_waiting_since_ms.set(0);
    sent
}
