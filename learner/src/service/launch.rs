//! The learner process, as a library function: `lcrl-learner` parses its
//! arguments ([`LearnerArgs`]) and calls [`run`], which reads as its steps:
//! prepare the run (graph, settings, checkpoint, incarnation, what the
//! threads share), start the training and shared-memory threads, serve
//! gRPC and /metrics until told to stop, then stop in order (servers,
//! threads, a final checkpoint). Tests drive it in-process.

use std::future::Future;
use std::net::SocketAddr;
use std::path::PathBuf;
use std::sync::atomic::Ordering;
use std::sync::{Arc, Mutex};
use std::time::{Duration, Instant};

use anyhow::{bail, Context};
use clap::Parser;
use lcrl_runtime::security::{ClientSecurity, ServerSecurity, ServerSecurityArgs};
use lcrl_proto::v1::graph_client::GraphClient;
use lcrl_proto::v1::learner_server::LearnerServer;
use lcrl_proto::v1::policy_server::PolicyServer;
use tokio::sync::mpsc;
use tonic::service::interceptor::InterceptedService;

use crate::algo::rate_limiter::RateLimiter;
use crate::config::{Algo, Connection, TrainConfig};
use crate::policy::snapshot::snapshot;
use crate::run::start::{prepare, GraphSource, Prepared, RunStart};
use crate::service::ingest::Ingest;
use crate::service::runtime::{Schedule, TrainingLoop};
use crate::service::server::{LearnerService, PolicyService};
use crate::service::shared::{Command, Shared};
use crate::service::validator::Validator;
use lcrl_runtime::request_budget::{Budgeted, RequestBudget};
use crate::service::watch_budget::WatchBudget;

/// The largest reply a server encodes.
const MAX_MESSAGE_BYTES: usize = 16 * 1024 * 1024;

#[derive(Debug, Parser)]
#[command(version, about = "The LCRL learner process: ingests actors' transitions, trains, publishes policies")]
pub struct LearnerArgs {
    /// Environment (registered name, .toml path or grpc://HOST:PORT);
    /// actors run the same one.
    #[arg(long)]
    pub env: String,
    #[arg(long, value_enum)]
    pub algo: Algo,
    #[arg(long, value_enum)]
    pub connection: Connection,
    /// Training configuration (TOML); keys it leaves out keep the
    /// environment's settings, as `lcrl train --config` does (without a
    /// file: the environment's settings, e.g. configs/peg.toml on peg tasks).
    #[arg(long)]
    pub config: Option<PathBuf>,
    /// Where the networks compute (overrides run.device; a resumed run may
    /// change it).
    #[arg(long, value_parser = ["cpu", "cuda"])]
    pub device: Option<String>,
    /// libtorch intra-op threads (overrides run.threads; 0: the cores of
    /// this machine or container, at most 4; `lcrl run` passes the cores
    /// its actors leave over, at most 4).
    #[arg(long)]
    pub threads: Option<usize>,
    /// Run directory: graph.json, checkpoints; resumed if it holds one.
    #[arg(long, default_value = "runs/learner")]
    pub run_dir: PathBuf,
    /// Run id: actors must present it; keeps runs on one host apart.
    #[arg(long, default_value = "default")]
    pub run_id: String,
    /// Address to serve on (port 0: any free port; printed as "listening on").
    /// Beyond loopback it needs a token (--token-file) or --insecure.
    #[arg(long, default_value = "127.0.0.1:50052")]
    pub listen: SocketAddr,
    /// Serve beyond loopback without a token (anyone who reaches the
    /// address may send transitions and call every RPC): only on a network
    /// nobody else joins.
    #[arg(long)]
    pub insecure: bool,
    /// Connection local: the graph as a graph.json file.
    #[arg(long, conflicts_with = "graph_builder")]
    pub graph: Option<PathBuf>,
    /// Connection local: fetch the graph from this graph builder (gRPC URL).
    #[arg(long)]
    pub graph_builder: Option<String>,
    /// How long to wait for the graph builder, seconds (1 to 86400).
    #[arg(long, default_value_t = 300, value_parser = clap::value_parser!(u64).range(1..=86_400))]
    pub graph_timeout: u64,
    /// DDPG: publish a new policy version every this many updates. Every
    /// update between two versions is policy lag for the actors, and lag
    /// is what kept the distributed DDPG behind `lcrl train`
    /// (docs/scaling.md, "Policy lag"): 10 holds it near 40 updates.
    /// 1 to 1000000.
    #[arg(long, default_value_t = 10, value_parser = clap::value_parser!(u64).range(1..=1_000_000))]
    pub publish_every: u64,
    /// PPO: discard batches more than this many versions older than the
    /// newest. 0 (default): strictly on-policy, as `lcrl train`'s PPO.
    /// Above 0 (asynchronous PPO, docs/method.md §5): older batches are
    /// trained on, PPO's clipped ratio taken against the behaviour
    /// log-probability each transition carries.
    #[arg(long, default_value_t = 0)]
    pub max_staleness: u64,
    /// Checkpoint at this interval, seconds (and on SIGTERM/Ctrl-C); the
    /// newest 3 checkpoints are kept. More than 0, at most 604800 (a week).
    #[arg(long, default_value_t = 60.0, value_parser = checkpoint_secs)]
    pub checkpoint_secs: f64,
    /// Store transitions but never train (for ingestion benchmarks).
    #[arg(long)]
    pub no_train: bool,
    /// The run's episode budget: schedules (learning-rate annealing, the
    /// fading pre-tanh penalty, DDPG exploration noise) follow the episodes
    /// stored as in `lcrl train`, and at the budget the learner stops
    /// training and writes its final checkpoint and summary.json.
    #[arg(long)]
    pub episodes: Option<u64>,
    /// DDPG replay ratio: transitions sampled per transition inserted
    /// (Reverb's samples per insert). Default: Algorithm 2's, one update of
    /// ddpg.batch_size per environment step (times ddpg.gradient_steps /
    /// ddpg.update_every). `unlimited`: no limiter, at
    /// most one update per stored step, actors never wait (throughput
    /// experiments).
    #[arg(long, value_name = "SPI|unlimited")]
    pub replay_ratio: Option<String>,
    /// Slack of the replay-ratio limiter around its target, in inserted
    /// transitions (Reverb's error buffer divided by SPI). How far the
    /// actors may run ahead of the updates, so policy lag; the learner
    /// refuses a slack below half a shared-memory batch (33 at Algorithm
    /// 2's ratio), where inserts could stall. At most 1000000.
    #[arg(long, default_value_t = 40, value_parser = clap::value_parser!(u64).range(0..=1_000_000))]
    pub replay_slack: u64,
    /// Batches that may wait in the learner's queue before actors' sends
    /// block (over shared memory also in the subscriber's buffer, up to
    /// 4). Every queued batch is policy lag: the actors step that much
    /// further ahead of the policy they act with.
    #[arg(long, default_value_t = 1, value_parser = clap::value_parser!(u64).range(1..=1024))]
    pub queued_batches: u64,
    /// A headroom reference (`lcrl tune --headroom`'s JSON) to evaluate
    /// beside the handed-over policy in summary.json; `lcrl run` passes a
    /// preset's `job.headroom`.
    #[arg(long, value_name = "FILE")]
    pub headroom: Option<PathBuf>,
    /// The largest transition batch accepted, bytes: a larger one ends its
    /// stream with RESOURCE_EXHAUSTED before it is decoded (counted as
    /// "oversize"). The default holds 4096 transitions of the peg tasks.
    #[arg(long, default_value_t = lcrl_runtime::limits::MAX_BATCH_BYTES as u64, value_parser = clap::value_parser!(u64).range(1024..=(64 << 20)))]
    pub max_batch_bytes: u64,
    /// The most states one `Policy.ActBatch` call may hold.
    #[arg(long, default_value_t = 4096, value_parser = clap::value_parser!(u64).range(1..=1_000_000))]
    pub max_act_batch: u64,
    /// The share of one core's time that Act and ActBatch may compute
    /// (training has priority): after a query of d seconds the next waits
    /// d·(1 − s)/s; more than 64 waiting get RESOURCE_EXHAUSTED. 1: no pauses.
    #[arg(long, default_value_t = 0.25, value_parser = share_in_range)]
    pub serving_share: f64,
    /// Memory all WatchPolicy streams may hold together, MiB. Each is
    /// charged twice its policy and 64 KiB (a reader that stops reading was
    /// measured to hold 7.8 MiB of a 4.2 MB policy), so the default takes
    /// about 800 streams of the peg actor (0.26 MB) and 60 of a 4.2 MB
    /// policy; a stream beyond it gets RESOURCE_EXHAUSTED.
    #[arg(long, default_value_t = 512, value_parser = clap::value_parser!(u64).range(1..=1 << 20))]
    pub watch_budget_mib: u64,
    /// MiB that all health, Learner and Policy request streams together may
    /// hold: each the largest message it has declared, until it ends (a
    /// message is buffered whole before it is decoded); one remote peer
    /// address at most a quarter of it, which must hold one
    /// --max-batch-bytes batch. A stream beyond it ends with
    /// RESOURCE_EXHAUSTED, which actors retry.
    #[arg(long, default_value_t = 256, value_parser = clap::value_parser!(u64).range(1..=1 << 20))]
    pub request_budget_mib: u64,
    /// Serve Prometheus metrics on http://ADDR/metrics (port 0: any free
    /// port, logged as "metrics on").
    #[arg(long, value_name = "ADDR")]
    pub metrics_listen: Option<SocketAddr>,
    /// Log as JSON lines instead of human-readable text (level: RUST_LOG).
    #[arg(long)]
    pub log_json: bool,
    #[command(flatten)]
    pub security: ServerSecurityArgs,
    /// Trust this CA for the graph builder's certificate (an https://
    /// --graph-builder URL); with --tls-cert/--tls-key the learner shows its
    /// own certificate to it (mutual TLS). The token is --token-file's.
    #[arg(long, value_name = "PEM")]
    pub graph_builder_tls_ca: Option<PathBuf>,
}

/// The longest `--checkpoint-secs`: a week (a longer interval would
/// overflow the clock's arithmetic long before it mattered).
const MAX_CHECKPOINT_SECS: f64 = 7.0 * 86_400.0;

/// `--checkpoint-secs`: a finite number of seconds in (0, a week], checked
/// as the arguments are parsed, before any work.
fn checkpoint_secs(text: &str) -> Result<f64, String> {
    match text.trim().parse::<f64>() {
        Ok(v) if v.is_finite() && v > 0.0 && v <= MAX_CHECKPOINT_SECS => Ok(v),
        _ => Err(format!("expected a number of seconds above 0 and at most {MAX_CHECKPOINT_SECS} (a week)")),
    }
}

/// G from a graph builder, retrying while it is unreachable or building.
async fn fetch_graph(url: &str, security: &ClientSecurity, timeout: Duration, n: usize, m: usize) -> anyhow::Result<Vec<Vec<u8>>> {
    let deadline = Instant::now() + timeout;
    let mut backoff = lcrl_runtime::limits::Backoff::new(Duration::from_millis(200), Duration::from_secs(5));
    loop {
        let attempt = async {
            let mut client = GraphClient::new(security.connect(url).await?);
            let graph = client.get_graph(lcrl_proto::v1::GetGraphRequest {}).await?.into_inner();
            anyhow::Ok(graph)
        };
        match attempt.await {
            // A malformed graph is refused at once: retrying would not mend it.
            Ok(graph) => return lcrl_graph_builder::report::mask_from_message(&graph, n, m).map_err(|e| anyhow::anyhow!("{url}: {e}")),
            Err(e) if Instant::now() < deadline => {
                tracing::info!("waiting for the graph builder at {url}: {e}");
                tokio::time::sleep(backoff.next_delay()).await;
            }
            Err(e) => bail!("no graph from {url} within {} s (last error: {e}); is lcrl-graph-builder running?", timeout.as_secs()),
        }
    }
}

/// The learner process until `shutdown` resolves or training fails:
/// `listening` is told the gRPC address once it is bound (`lcrl-learner`
/// prints it for its launchers).
pub async fn run(args: LearnerArgs, shutdown: impl Future<Output = ()>, listening: impl FnOnce(SocketAddr)) -> anyhow::Result<()> {
    // Certificates and tokens are checked before any work.
    let security = ServerSecurity::from_args(&args.security)?;
    // Issue 82: a token-less learner was open to every peer that reached
    // it. Without a token (or mutual TLS) it serves loopback only, unless
    // told otherwise; refused before anything is written.
    if !security.authenticates_peers() && !args.listen.ip().is_loopback() && !args.insecure {
        bail!(
            "--listen {} is reachable from other hosts and this learner has no token, so anyone who reaches it could send transitions and call every RPC: \
             give --token-file FILE (`lcrl certs` makes one) or mutual TLS (--tls-client-ca), listen on 127.0.0.1, or add --insecure (only on a network nobody else joins)",
            args.listen
        );
    }
    // One learner a run id on this host: refused before anything is
    // written (the shared-memory thread checks again as it opens).
    if let Err(taken @ lcrl_proto::shm::SubscriberError::RunTaken(_)) = lcrl_proto::shm::TransitionSubscriber::open(&security.shm_key(&args.run_id), 1).map(drop) {
        bail!("{taken}");
    }
    if let Some(0) = args.episodes {
        bail!("--episodes must be at least 1");
    }
    // A remote actor's batch (and its 5-byte prefix) must fit in its
    // peer's quarter, or it could never be stored and its actor would
    // retry for ever.
    let share = (args.request_budget_mib << 20) / lcrl_runtime::memory_budget::PEER_SHARE as u64;
    let batch = args.max_batch_bytes + 5;
    if share < batch {
        bail!(
            "--request-budget-mib {} leaves one peer address a quarter, {} KiB, which does not hold one batch of --max-batch-bytes {}; raise it to at least {} MiB",
            args.request_budget_mib,
            share >> 10,
            args.max_batch_bytes,
            (lcrl_runtime::memory_budget::PEER_SHARE as u64 * batch).div_ceil(1 << 20)
        );
    }
    // `_lock` holds the run directory until the training thread is joined.
    let Begun { training, commands, shared, state_dim, lock: _lock } = begin(&args, &security).await?;
    let threads = start_threads(&args, training, &shared, &commands)?;
    // From here an error return stops the threads too (a library caller's
    // process lives on): shared memory stops polling, training ends.
    let _stop_threads = StopOnDrop(shared.clone());
    let listener = tokio::net::TcpListener::bind(args.listen).await.with_context(|| format!("cannot listen on {}; is another process using it?", args.listen))?;
    let addr = listener.local_addr()?;
    if !security.authenticates_peers() && addr.ip().is_loopback() {
        tracing::info!(%addr, "no token: serving loopback only; every process on this host may call it (--token-file to require one)");
    }
    listening(addr);
    security.warn_if_exposed(addr);
    tracing::info!(%addr, security = %security.describe(), "serving");
    let mut server = serve(&args, &security, listener, &shared, &commands, state_dim).await?;
    let Threads { trainer, mut trainer_failure, shm, policy_broadcast } = threads;
    tokio::select! {
        _ = shutdown => {}
        _ = &mut trainer_failure => {}
        result = &mut server.task => {
            result.context("the gRPC server task panicked")?.context("the gRPC server failed")?;
        }
    }
    // Long-lived streams end now; connections still open after a grace
    // period (an actor mid-reconnect, say) are dropped rather than waited on.
    shared.shutdown.send_replace(true);
    let _ = server.stop.send(());
    if tokio::time::timeout(Duration::from_secs(5), &mut server.task).await.is_err() {
        tracing::warn!("connections still open after 5 s; closing them");
        server.task.abort();
    }
    let _ = tokio::task::spawn_blocking(move || (shm.join(), policy_broadcast.join())).await;
    tracing::info!("stopping: writing a checkpoint");
    let _ = commands.send(Command::Stop).await;
    drop(commands);
    trainer.join().map_err(|_| anyhow::anyhow!("the training thread panicked"))??;
    Ok(())
}

/// Tells every thread of the learner to stop when dropped.
struct StopOnDrop(Arc<Shared>);

impl Drop for StopOnDrop {
    fn drop(&mut self) {
        self.0.shutdown.send_replace(true);
    }
}

/// What [`begin`] hands on: the training loop not yet started, the queue
/// into it, and what every thread and handler shares.
struct Begun {
    training: TrainingLoop,
    commands: mpsc::Sender<Command>,
    shared: Arc<Shared>,
    state_dim: usize,
    /// The run directory, held until the learner has stopped.
    lock: Option<crate::run::lock::RunLock>,
}

/// The run as it stands ([`load`]), a new incarnation, the first policy,
/// ingestion, the shared counters and the training loop.
async fn begin(args: &LearnerArgs, security: &ServerSecurity) -> anyhow::Result<Begun> {
    let (Prepared { config, checkpoint, meta, agent, actions, lock, .. }, m) = load(args).await?;
    let architecture = meta.architecture();
    // A fresh id per start: actors notice a restarted learner by it.
    let incarnation = crate::service::incarnation::begin(&args.run_dir, meta.episode, meta.policy_version)?;
    tracing::info!(incarnation = %format!("{incarnation:016x}"), "incarnation");
    let mut first = snapshot(agent.as_ref(), &architecture, meta.policy_version)?;
    first.incarnation = incarnation;
    let staleness = (args.algo == Algo::Ppo).then_some(args.max_staleness);
    let ingest = Ingest::new(&args.run_id, lcrl_sim::make_env(&args.env)?, staleness)
        .with_actions(actions)
        .with_sequences(meta.actor_sequences.clone())
        .with_incarnation(incarnation);
    let mut shared = Shared::new(&args.run_id, architecture, first, ingest, args.run_dir.clone(), security.refusals())
        .with_connection_refusals(security.connection_refusals());
    shared.shm_key = security.shm_key(&args.run_id);
    // A resumed run's counters.
    let counters = agent.counters();
    shared.env_steps.store(counters.env_steps, Ordering::Relaxed);
    shared.updates.store(counters.updates, Ordering::Relaxed);
    shared.replay_size.store(agent.stored() as u64, Ordering::Relaxed);
    shared.episodes.store(meta.episode as u64, Ordering::Relaxed);
    let shared = Arc::new(shared);
    let restored = checkpoint.as_ref().and_then(|_| meta.rate_limiter.clone());
    let limiter = replay_limiter(args, &config, agent.as_ref(), restored)?;
    // Few batches in flight: every queued batch is policy lag (an actor a
    // whole queue ahead acts with a policy that many updates old), and the
    // rate limiter holds actors back through this queue.
    let (commands, inbox) = mpsc::channel(args.queued_batches as usize);
    // The run's policy is chosen on held-out starts as `lcrl train` chooses
    // it (run.validation_episodes, run.validate_every), on its own thread.
    let validator = match crate::run::selection::Selection::new(&config.run, &args.run_dir, checkpoint.is_some())? {
        Some(selection) => Some(Validator::start(selection, lcrl_sim::make_env(&args.env)?, &args.run_dir, config.run.validate_every, shared.validations_pending.clone())?),
        None => None,
    };
    let schedule = Schedule {
        publish_every: args.publish_every.max(1),
        checkpoint_interval: Duration::from_secs_f64(args.checkpoint_secs),
        run_dir: args.run_dir.clone(),
        meta,
        train: !args.no_train,
        max_staleness: staleness,
        budget_episodes: args.episodes,
        limiter,
        validator,
        headroom: headroom(args)?,
    };
    // Built here, before any server starts: it hands the limiter's
    // restored counters and the budget to the flow statistics, which
    // GetStatus reads from the first request on.
    let training = TrainingLoop::new(agent, inbox, shared.clone(), schedule);
    Ok(Begun { training, commands, shared, state_dim: m, lock })
}

/// The run directory's state: its graph (asked of a graph builder only for
/// a new run: a resumed one has its mask in the checkpoint), settings, and
/// agent from the newest checkpoint; with the environment's state count.
async fn load(args: &LearnerArgs) -> anyhow::Result<(Prepared, usize)> {
    let own_identity = args.security.tls_cert.as_deref().zip(args.security.tls_key.as_deref());
    let graph_builder_security = ClientSecurity::new(args.graph_builder_tls_ca.as_deref(), own_identity, args.security.token_file.as_deref())?;
    let env = lcrl_sim::make_env(&args.env)?;
    let (m, n) = (env.spec().state_dim(), env.spec().action_dim());
    // The graph builder is asked only for a new run: a resumed one has its
    // mask in the checkpoint.
    let resuming = crate::policy::checkpoint::latest_checkpoint(&args.run_dir).is_some();
    let graph = match (args.connection, &args.graph, &args.graph_builder) {
        (Connection::Local, None, Some(url)) if !resuming => GraphSource::Mask(fetch_graph(url, &graph_builder_security, Duration::from_secs(args.graph_timeout), n, m).await?),
        (_, Some(path), _) => GraphSource::File(path),
        _ => GraphSource::Measure,
    };
    let config = match &args.config {
        // One fallback rule with `lcrl train`: the environment's settings.
        Some(path) => TrainConfig::load_for_env(path, &args.env)?,
        None => TrainConfig::for_env(&args.env).0,
    };
    let start = RunStart {
        env: &args.env,
        algo: args.algo,
        connection: args.connection,
        run_dir: &args.run_dir,
        config,
        graph,
        // A learner always continues its run directory (a restart after a
        // crash or a rescheduled pod).
        resume: true,
        device: args.device.clone(),
        threads: args.threads,
    };
    let prepared = prepare(start, env.as_ref())?;
    if let Some(dir) = &prepared.checkpoint {
        tracing::info!(checkpoint = %dir.display(), episodes = prepared.meta.episode, "resuming");
    }
    // A graph built here is kept beside the run's records.
    if let Some(report) = prepared.graph.as_ref().filter(|_| args.graph.is_none()) {
        report.write_json(&args.run_dir.join("graph.json"))?;
    }
    tracing::info!(device = %prepared.config.run.device, threads = prepared.threads, "learner compute");
    Ok((prepared, m))
}

/// DDPG's replay-ratio limiter (`--replay-ratio`, run.ddpg's ratio by
/// default); none for PPO, `unlimited`, or a learner that never samples
/// (`--no-train`: ingestion benchmarks must not wait for samples). A
/// resumed run keeps its counters (no burst of updates on a buffer that
/// the checkpoint restored).
fn replay_limiter(args: &LearnerArgs, config: &TrainConfig, agent: &dyn crate::algo::agent::Agent, restored: Option<RateLimiter>) -> anyhow::Result<Option<RateLimiter>> {
    let spi = match (args.algo, args.replay_ratio.as_deref()) {
        _ if args.no_train => return Ok(None),
        (Algo::Ppo, _) | (Algo::Ddpg, Some("unlimited")) => return Ok(None),
        (Algo::Ddpg, None) => config.ddpg.samples_per_insert(),
        (Algo::Ddpg, Some(text)) => text.parse::<f64>().map_err(|_| anyhow::anyhow!("--replay-ratio must be a number of samples per insert or `unlimited`, got {text}"))?,
    };
    let fresh = RateLimiter::new(spi, agent.min_size_to_sample() as u64, spi * args.replay_slack as f64).map_err(|e| anyhow::anyhow!("--replay-ratio: {e}"))?;
    fresh.check_steps(lcrl_proto::shm::MAX_TRANSITIONS as u64, agent.samples_per_update() as u64).map_err(|e| anyhow::anyhow!("{e}; raise --replay-slack"))?;
    Ok(Some(match restored {
        Some(saved) => RateLimiter { samples_per_insert: spi, error_buffer: fresh.error_buffer, ..saved },
        None => fresh,
    }))
}

/// `--headroom`: the stored feedback policy evaluated beside the run's.
fn headroom(args: &LearnerArgs) -> anyhow::Result<Option<lcrl_sim::tune::feedback::StoredPolicy>> {
    let Some(path) = &args.headroom else { return Ok(None) };
    let stored = lcrl_sim::tune::feedback::StoredPolicy::read(path).with_context(|| format!("--headroom {}", path.display()))?;
    // A served environment is checked by its own evaluation.
    if !lcrl_sim::remote::is_served(&args.env) {
        stored.check_env(lcrl_sim::make_env(&args.env)?.as_ref()).with_context(|| format!("--headroom {}", path.display()))?;
    }
    Ok(Some(stored))
}

/// The threads beside the async runtime: training (a failure is reported
/// on `trainer_failure`: a learner that cannot learn exits with the error,
/// not keep accepting transitions), and shared-memory ingestion and
/// policy broadcast for same-host actors.
struct Threads {
    trainer: std::thread::JoinHandle<Result<(), crate::LearnerError>>,
    trainer_failure: tokio::sync::oneshot::Receiver<String>,
    shm: std::thread::JoinHandle<()>,
    policy_broadcast: std::thread::JoinHandle<()>,
}

fn start_threads(args: &LearnerArgs, training: TrainingLoop, shared: &Arc<Shared>, commands: &mpsc::Sender<Command>) -> anyhow::Result<Threads> {
    // Shared memory first: a run id a live learner on this host already
    // serves is refused before anything trains (issue 82: two learners
    // under one run id both took every transition).
    let (shm_shared, shm_commands, shm_buffer) = (shared.clone(), commands.clone(), args.queued_batches as usize);
    let (opened_tx, opened) = std::sync::mpsc::sync_channel(1);
    let shm = std::thread::Builder::new()
        .name("shm-ingest".into())
        .spawn(move || {
            if let Err(e) = crate::service::shm::run_subscriber(shm_shared, shm_commands, shm_buffer, opened_tx) {
                tracing::warn!("shared-memory transport unavailable: {e}");
            }
        })
        .context("cannot start the shared-memory thread")?;
    if let Ok(Err(taken @ lcrl_proto::shm::SubscriberError::RunTaken(_))) = opened.recv_timeout(Duration::from_secs(30)) {
        bail!("{taken}");
    }
    let (trainer_failed, trainer_failure) = tokio::sync::oneshot::channel::<String>();
    // OpenMP's thread count is per thread: the count run.threads set on
    // this thread (crate::device::torch::apply_threads) is not the new
    // thread's, which would start with one spinning thread per core.
    let threads = tch::get_num_threads().max(1) as usize;
    let trainer_shared = shared.clone();
    let trainer = std::thread::Builder::new()
        .name("training".into())
        .spawn(move || {
            let here = crate::device::torch::set_threads_here(threads).unwrap_or(threads);
            trainer_shared.training_threads.store(here as u32, std::sync::atomic::Ordering::Relaxed);
            let result = training.run();
            if let Err(e) = &result {
                tracing::error!("training stopped: {e}");
                let _ = trainer_failed.send(e.to_string());
            }
            result
        })
        .context("cannot start the training thread")?;
    let publisher_shared = shared.clone();
    let policy_broadcast = std::thread::Builder::new()
        .name("shm-policy".into())
        .spawn(move || {
            if let Err(e) = crate::service::shm::run_policy_publisher(publisher_shared) {
                tracing::warn!("shared-memory policy broadcast unavailable: {e}");
            }
        })
        .context("cannot start the policy broadcast thread")?;
    Ok(Threads { trainer, trainer_failure, shm, policy_broadcast })
}

/// The gRPC server task (health, Learner, Policy, reflection) and the
/// sender that stops it.
struct Server {
    task: tokio::task::JoinHandle<Result<(), tonic::transport::Error>>,
    stop: tokio::sync::oneshot::Sender<()>,
}

/// Serves gRPC on `listener` (and /metrics where asked), every service but
/// health behind the token when there is one.
async fn serve(args: &LearnerArgs, security: &ServerSecurity, listener: tokio::net::TcpListener, shared: &Arc<Shared>, commands: &mpsc::Sender<Command>, m: usize) -> anyhow::Result<Server> {
    let (health, health_service) = lcrl_runtime::process::health_service();
    health.set_serving::<LearnerServer<LearnerService>>().await;
    health.set_serving::<PolicyServer<PolicyService>>().await;
    let check = security.token_check();
    let watch_budget = WatchBudget::new(args.watch_budget_mib << 20);
    let request_budget = RequestBudget::new(args.request_budget_mib << 20, "learner");
    let learner = LearnerServer::new(LearnerService {
        shared: shared.clone(),
        commands: commands.clone(),
        watch_budget,
        status_rate: lcrl_runtime::peer_rate::PeerRate::new(lcrl_runtime::peer_rate::STATUS_PER_SECOND, lcrl_runtime::peer_rate::STATUS_BURST),
    })
        .max_decoding_message_size(args.max_batch_bytes as usize)
        .max_encoding_message_size(MAX_MESSAGE_BYTES);
    let act_latency = crate::service::metrics::act_latency_histogram();
    if let Some(addr) = args.metrics_listen {
        serve_metrics(addr, shared, commands, act_latency.clone()).await?;
    }
    let policy = PolicyService {
        shared: shared.clone(),
        env: Mutex::new(lcrl_sim::make_env(&args.env)?),
        serving: Mutex::new(None),
        act_latency,
        max_act_batch: args.max_act_batch as usize,
        share: crate::service::serving_share::ServingShare::new(args.serving_share),
    };
    // Its largest request: --max-act-batch states of f32, and some framing.
    let act_batch_bytes = (args.max_act_batch as usize * m * 4 + 1024).max(64 << 10);
    let policy = PolicyServer::new(policy)
        .max_decoding_message_size(act_batch_bytes)
        .max_encoding_message_size(MAX_MESSAGE_BYTES);
    let (stop, stopped) = tokio::sync::oneshot::channel::<()>();
    let router = security
        .server_builder()
        .trace_fn(|req| tracing::info_span!("grpc", path = %req.uri().path()))
        .add_service(Budgeted::new(health_service, request_budget.clone()))
        .add_service(InterceptedService::new(Budgeted::new(learner, request_budget.clone()), check.clone()))
        .add_service(InterceptedService::new(Budgeted::new(policy, request_budget.clone()), check.clone()));
    // TLS where configured; TCP_NODELAY on accepted sockets.
    let serving = lcrl_runtime::process::add_reflection(router, &check, &request_budget).serve_with_incoming_shutdown(security.incoming(listener), async move {
        let _ = stopped.await;
    });
    Ok(Server { task: tokio::spawn(serving), stop })
}

/// /metrics on `addr`, until the learner stops; the bound address is the
/// second line of stdout, after "listening on", for launchers and tests.
async fn serve_metrics(addr: SocketAddr, shared: &Arc<Shared>, commands: &mpsc::Sender<Command>, act_latency: prometheus_client::metrics::histogram::Histogram) -> anyhow::Result<()> {
    let registry = Arc::new(crate::service::metrics::learner_registry(shared.clone(), commands.clone(), act_latency));
    let (listener, bound) = lcrl_runtime::metrics_http::bind(addr).await.with_context(|| format!("cannot serve metrics on {addr}; is another process using it?"))?;
    // Not println!: a launcher may have stopped reading stdout.
    let _ = std::io::Write::write_fmt(&mut std::io::stdout(), format_args!("metrics on {bound}\n"));
    let stopping = shared.stopping();
    tokio::spawn(async move {
        if let Err(e) = lcrl_runtime::metrics_http::serve(listener, registry, stopping, || Ok(())).await {
            tracing::warn!("metrics endpoint stopped: {e}");
        }
    });
    Ok(())
}

/// `--serving-share`: a number in [0.01, 1].
fn share_in_range(text: &str) -> Result<f64, String> {
    let share: f64 = text.parse().map_err(|_| format!("{text:?} is not a number"))?;
    if (0.01..=1.0).contains(&share) { Ok(share) } else { Err(format!("{share} is outside [0.01, 1]")) }
}

#[cfg(test)]
mod tests {
    use clap::Parser;
    use lcrl_proto::v1::learner_client::LearnerClient;
    use lcrl_proto::v1::{GetPolicyRequest, GetStatusRequest};

    use super::{run, LearnerArgs};

    fn args(dir: &std::path::Path, extra: &[&str]) -> LearnerArgs {
        let run_dir = dir.display().to_string();
        let base = ["lcrl-learner", "--env", "lti-paper", "--algo", "ddpg", "--connection", "global", "--listen", "127.0.0.1:0", "--run-id", "in-process", "--run-dir", &run_dir];
        LearnerArgs::try_parse_from(base.iter().chain(extra)).unwrap()
    }

    /// The learner, driven in this process from its parsed arguments:
    /// it tells where it listens, serves its status and first policy, and
    /// once told to stop ends cleanly with a checkpoint and its
    /// incarnation recorded.
    #[tokio::test(flavor = "multi_thread", worker_threads = 2)]
    async fn the_learner_runs_in_process_and_stops_with_a_checkpoint() {
        let dir = tempfile::tempdir().unwrap();
        let (stop, stopped) = tokio::sync::oneshot::channel::<()>();
        let (bound, listening) = tokio::sync::oneshot::channel();
        let learner = tokio::spawn(run(args(dir.path(), &[]), async move { let _ = stopped.await; }, move |addr| {
            let _ = bound.send(addr);
        }));
        let addr = listening.await.expect("the learner tells where it listens");
        let mut client = LearnerClient::connect(format!("http://{addr}")).await.unwrap();
        let status = client.get_status(GetStatusRequest {}).await.unwrap().into_inner();
        assert_eq!((status.run_id.as_str(), status.episodes, status.algo.as_str()), ("in-process", 0, "ddpg"));
        let policy = client.get_policy(GetPolicyRequest {}).await.unwrap().into_inner();
        assert_eq!((policy.version, policy.incarnation), (0, status.incarnation));
        assert!(!policy.weights.is_empty());
        let _ = stop.send(());
        learner.await.unwrap().unwrap();
        assert!(crate::policy::checkpoint::latest_checkpoint(dir.path()).is_some(), "stopping writes a checkpoint");
        let incarnations = std::fs::read_to_string(dir.path().join("incarnations.csv")).unwrap();
        assert!(incarnations.contains(&format!("{:016x}", status.incarnation)), "{incarnations}");
    }

    /// A budget of no episodes is refused before any work: no run
    /// directory is made.
    #[tokio::test]
    async fn a_budget_of_no_episodes_is_refused_before_any_work() {
        let dir = tempfile::tempdir().unwrap();
        let run_dir = dir.path().join("run");
        let error = run(args(&run_dir, &["--episodes", "0"]), std::future::pending(), |_| {}).await.unwrap_err();
        assert!(error.to_string().contains("--episodes must be at least 1"), "{error}");
        assert!(!run_dir.exists());
    }
}
