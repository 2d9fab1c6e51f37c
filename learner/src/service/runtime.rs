//! The learner process's state and its training thread. The thread owns
//! the agent: gRPC handlers (and shared-memory subscribers) only check
//! batches and hand them over through a bounded channel, so ingestion never
//! waits for an update and the queue cannot grow without bound.

use std::collections::VecDeque;
use std::path::PathBuf;
use std::sync::atomic::{AtomicU32, AtomicU64, Ordering};
use std::sync::{Arc, Mutex};

use lcrl_proto::v1::PolicySnapshot;
use tokio::sync::{mpsc, watch};

use crate::agent::{Agent, Transition};
use crate::config::{Algo, Connection};
use crate::rate_limiter::RateLimiter;
use crate::service::flow::FlowStats;
use crate::service::ingest::{Accepted, Ingest};
use crate::snapshot::{encode_weights, Architecture};
use crate::checkpoint::{write_checkpoint, CheckpointMeta};
use crate::LearnerError;

/// What the handlers send to the training thread.
pub enum Command {
    Batch(Accepted),
    /// Checkpoint and stop (SIGTERM / Ctrl-C).
    Stop,
}

/// Counters and the newest policy, shared by handlers and the training thread.
pub struct Shared {
    pub run_id: String,
    pub algo: Algo,
    pub connection: Connection,
    pub architecture: Architecture,
    pub env_steps: AtomicU64,
    pub updates: AtomicU64,
    pub replay_size: AtomicU64,
    pub episodes: AtomicU64,
    pub connected_actors: AtomicU32,
    pub recent_returns: Mutex<VecDeque<f64>>,
    pub ingest: Mutex<Ingest>,
    pub policy: watch::Sender<Arc<PolicySnapshot>>,
    /// Set when the learner shuts down: long-lived streams end then, so the
    /// server's graceful shutdown does not wait on them forever.
    pub shutdown: watch::Sender<bool>,
    /// Where metrics.csv goes.
    pub run_dir: PathBuf,
    /// Replay ratio, waits, policy lag and the budget.
    pub flow: Mutex<FlowStats>,
    /// Calls refused for a missing or wrong token (GetStatus, /metrics).
    pub auth_refusals: Arc<lcrl_proto::security::AuthRefusals>,
}

/// Locks `mutex` whatever happened to its last holder. The policy for a
/// poisoned lock (a thread panicked while holding it): the state behind
/// these locks is counters, maps of sequence numbers and recent returns,
/// each left whole between statements, so the learner keeps serving with
/// it rather than failing every later call; the panic itself is reported
/// where it happened.
fn lock<T>(mutex: &Mutex<T>) -> std::sync::MutexGuard<'_, T> {
    mutex.lock().unwrap_or_else(|poisoned| poisoned.into_inner())
}

impl Shared {
    /// Ingestion's checks and counters (every transport goes through them).
    pub fn ingest(&self) -> std::sync::MutexGuard<'_, Ingest> {
        lock(&self.ingest)
    }

    /// Counts a stream or batch refused before ingestion could read it.
    pub fn record_rejection(&self, reason: &str) {
        self.ingest().refuse(reason);
    }

    /// Transitions accepted, and rejected by reason, so far.
    pub fn ingest_counts(&self) -> (u64, std::collections::BTreeMap<String, u64>) {
        let ingest = self.ingest();
        (ingest.accepted, ingest.rejected.clone())
    }

    /// The flow statistics, for the training thread to update.
    pub fn flow_mut(&self) -> std::sync::MutexGuard<'_, FlowStats> {
        lock(&self.flow)
    }

    pub fn policy_version(&self) -> u64 {
        self.policy.borrow().version
    }

    /// Resolves once shutdown has begun.
    pub fn stopping(&self) -> impl std::future::Future<Output = ()> + Send + 'static {
        let mut rx = self.shutdown.subscribe();
        async move {
            let _ = rx.wait_for(|stop| *stop).await;
        }
    }

    /// A copy of the flow statistics.
    pub fn flow(&self) -> FlowStats {
        self.flow_mut().clone()
    }

    pub fn recent_return(&self) -> f64 {
        let returns: Vec<f64> = lock(&self.recent_returns).iter().copied().collect();
        if returns.is_empty() { 0.0 } else { returns.iter().sum::<f64>() / returns.len() as f64 }
    }
}

/// How often the training thread publishes and checkpoints.
#[derive(Debug, Clone)]
pub struct Schedule {
    /// Publish a new policy version every this many updates (PPO: after
    /// every PPO update).
    pub publish_every: u64,
    /// Checkpoint at this interval (and on stop). Time, not episodes: actors
    /// can finish hundreds of episodes a second.
    pub checkpoint_interval: std::time::Duration,
    pub run_dir: PathBuf,
    pub meta: CheckpointMeta,
    /// False: store only, never train (ingestion benchmarks).
    pub train: bool,
    /// PPO: batches more than this many versions behind the newest policy
    /// are dropped when they reach the training thread (they may have
    /// waited in the queue through an update). None: keep everything.
    pub max_staleness: Option<u64>,
    /// The run's episode budget: drives every schedule (learning-rate
    /// annealing, the fading pre-tanh penalty, DDPG's exploration noise)
    /// as `lcrl train` does, and ends training. None: run until stopped.
    pub budget_episodes: Option<u64>,
    /// DDPG's replay-ratio limiter (restored from the checkpoint on
    /// resume). None: unlimited, at most one update per stored step.
    pub limiter: Option<RateLimiter>,
}

/// Batches stored per loop turn before training gets its turn: with fast
/// actors the queue is never empty, and training must not starve.
const BATCHES_PER_TURN: usize = 8;

/// Encodes the agent's actor as the next policy version.
pub fn snapshot(agent: &dyn Agent, architecture: &Architecture, version: u64) -> Result<PolicySnapshot, LearnerError> {
    let weights = encode_weights(&agent.actor_variables())?;
    let architecture = serde_json::to_string(architecture).map_err(|e| LearnerError::Checkpoint(e.to_string()))?;
    Ok(PolicySnapshot { version, weights, architecture, explore_uniform: false, exploration_noise: 0.0 })
}

/// The learner's own summary at the end of its budget (run_dir/summary.json).
#[derive(Debug, Clone, serde::Serialize, serde::Deserialize)]
pub struct LearnerSummary {
    pub episodes: u64,
    pub env_steps: u64,
    pub updates: u64,
    pub sampled: u64,
    pub inserted: u64,
    /// sampled / inserted.
    pub replay_ratio: f64,
    /// The limiter's target (0: unlimited).
    pub replay_ratio_target: f64,
    pub policy_lag: PolicyLag,
    pub actors_waited_s: f64,
    pub learner_waited_s: f64,
    /// Mean return of the last 10 episodes (with exploration).
    pub final_return: f64,
    pub policy_version: u64,
}

/// Policy lag over the window of recently stored transitions.
#[derive(Debug, Clone, Copy, serde::Serialize, serde::Deserialize)]
pub struct PolicyLag {
    pub min: u64,
    pub mean: f64,
    pub max: u64,
}

fn write_summary(agent: &dyn Agent, shared: &Shared) -> Result<(), LearnerError> {
    let flow = shared.flow();
    let (min, mean, max) = flow.lag.stats();
    let counters = agent.counters();
    let summary = LearnerSummary {
        episodes: shared.episodes.load(Ordering::Relaxed),
        env_steps: counters.env_steps,
        updates: counters.updates,
        sampled: flow.sampled,
        inserted: flow.inserted,
        replay_ratio: flow.achieved_ratio(),
        replay_ratio_target: flow.replay_ratio_target,
        policy_lag: PolicyLag { min, mean, max },
        actors_waited_s: flow.actors_waited_s,
        learner_waited_s: flow.learner_waited_s,
        final_return: shared.recent_return(),
        policy_version: shared.policy_version(),
    };
    crate::run_files::write_summary(&shared.run_dir, &summary)
}

fn checkpoint(agent: &dyn Agent, shared: &Shared, schedule: &Schedule) -> Result<(), LearnerError> {
    let mut meta = schedule.meta.clone();
    meta.rate_limiter = schedule.limiter.clone();
    meta.episode = shared.episodes.load(Ordering::Relaxed) as usize;
    meta.policy_version = shared.policy_version();
    meta.actor_sequences = shared.ingest().sequences().clone();
    let dir = write_checkpoint(&schedule.run_dir, agent, &meta)?;
    tracing::info!(checkpoint = %dir.display(), episodes = meta.episode, policy_version = meta.policy_version, "checkpoint written");
    Ok(())
}

/// Adds `seconds` to one of the wait counters.
fn waited(shared: &Shared, seconds: f64, actors: bool) {
    {
        let mut flow = shared.flow_mut();
        if actors {
            flow.actors_waited_s += seconds;
        } else {
            flow.learner_waited_s += seconds;
        }
    }
}

/// The training loop; returns when told to stop or when every sender is
/// gone, after writing a checkpoint.
///
/// Each turn: store batches while the rate limiter admits them (a batch it
/// refuses is held, so the command queue fills and the actors' sends block:
/// backpressure, not dropped data); follow the budget's schedules; train
/// once if the limiter lets the learner sample; publish; checkpoint.
pub fn run_training(mut agent: Box<dyn Agent>, mut commands: mpsc::Receiver<Command>, shared: Arc<Shared>, mut schedule: Schedule) -> Result<(), LearnerError> {
    let mut last_published = agent.counters().updates;
    let mut published_exploration = exploration_of(agent.as_ref(), &shared);
    // The starting version (no actor has it yet: the servers start after
    // this thread) learns how to explore, without a version of its own.
    if let Some((uniform, noise)) = published_exploration {
        shared.policy.send_modify(|current| {
            let mut first = (**current).clone();
            first.explore_uniform = uniform;
            first.exploration_noise = noise;
            *current = Arc::new(first);
        });
    }
    let mut last_checkpoint = std::time::Instant::now();
    let mut log = EpisodeLog::open(&shared.run_dir);
    let mut held: Option<Accepted> = None;
    let mut turn = std::time::Instant::now();
    let budget = schedule.budget_episodes;
    let budget_reached = |shared: &Shared| budget.is_some_and(|b| shared.episodes.load(Ordering::Relaxed) >= b);
    {
        let mut flow = shared.flow_mut();
        flow.budget_episodes = schedule.budget_episodes.unwrap_or(0);
        flow.replay_ratio_target = schedule.limiter.as_ref().map_or(0.0, |l| l.samples_per_insert);
        if let Some(l) = &schedule.limiter {
            (flow.inserted, flow.sampled) = (l.inserts, l.samples);
        }
    }
    let mut finished = budget_reached(&shared);
    set_finished(&shared, finished);
    loop {
        // Shutdown does not wait for a Stop through the queue: while the
        // limiter holds a batch the queue is full, and senders (the Stop
        // among them) would wait on this thread forever.
        if *shared.shutdown.borrow() {
            return checkpoint(agent.as_ref(), &shared, &schedule);
        }
        let turn_seconds = turn.elapsed().as_secs_f64();
        turn = std::time::Instant::now();
        if held.is_some() {
            waited(&shared, turn_seconds, true);
        }
        let mut stop = false;
        let mut received = false;
        for _ in 0..BATCHES_PER_TURN {
            let batch = match held.take() {
                Some(batch) => batch,
                None => match commands.try_recv() {
                    Ok(Command::Batch(batch)) => batch,
                    Ok(Command::Stop) | Err(mpsc::error::TryRecvError::Disconnected) => {
                        stop = true;
                        break;
                    }
                    Err(mpsc::error::TryRecvError::Empty) => break,
                },
            };
            let mut batch = batch;
            // Nothing past the budget's last episode is stored.
            let past_budget = match budget {
                _ if finished => std::mem::take(&mut batch.transitions).len(),
                Some(b) => batch.keep_episodes(b.saturating_sub(shared.episodes.load(Ordering::Relaxed)) as usize),
                None => 0,
            };
            if past_budget > 0 {
                {
        let mut ingest = shared.ingest();
                    *ingest.rejected.entry("over_budget".into()).or_insert(0) += past_budget as u64;
                }
            }
            if finished || batch.transitions.is_empty() {
                continue;
            }
            let count = batch.transitions.len() as u64;
            if let Some(limiter) = &schedule.limiter {
                // Liveness: a batch too large for the window goes in when
                // the learner cannot sample either (one batch of error).
                let batch_size = agent.samples_per_update() as u64;
                if !limiter.can_insert(count) && limiter.can_sample(batch_size) {
                    held = Some(batch);
                    break;
                }
            }
            received = true;
            let stored = store(agent.as_mut(), &shared, &schedule, &mut log, batch);
            if let Some(limiter) = &mut schedule.limiter {
                limiter.insert(stored);
            }
            {
        let mut flow = shared.flow_mut();
                flow.inserted += stored;
            }
            if budget_reached(&shared) {
                finished = true;
                held = None;
                // The updates the last inserts earned (Algorithm 2 gives
                // every step its update, to the end of the run).
                let batch_size = agent.samples_per_update() as u64;
                while schedule.limiter.as_ref().is_some_and(|l| schedule.train && batch_size > 0 && l.owed() >= batch_size as f64) {
                    if train_and_count(agent.as_mut(), &mut schedule, &shared) == 0 {
                        break;
                    }
                }
                shared.updates.store(agent.counters().updates, Ordering::Relaxed);
                checkpoint(agent.as_ref(), &shared, &schedule)?;
                write_summary(agent.as_ref(), &shared)?;
                set_finished(&shared, true);
                tracing::info!(episodes = shared.episodes.load(Ordering::Relaxed), "episode budget reached: training ends");
                break;
            }
        }
        if stop {
            return checkpoint(agent.as_ref(), &shared, &schedule);
        }
        // The budget drives every schedule, as in `lcrl train`.
        let episodes = shared.episodes.load(Ordering::Relaxed);
        if let Some(budget) = schedule.budget_episodes {
            agent.set_progress(episodes as f64 / budget.max(1) as f64);
        }
        let before = agent.counters();
        let batch_size = agent.samples_per_update() as u64;
        let limited = match (&schedule.limiter, shared.algo) {
            (_, Algo::Ppo) => true,
            (Some(limiter), Algo::Ddpg) => limiter.can_sample(batch_size),
            // Unlimited: at most one update per stored step.
            (None, Algo::Ddpg) => before.updates < before.env_steps,
        };
        let may_train = schedule.train && !finished && limited;
        let drawn = if may_train { train_and_count(agent.as_mut(), &mut schedule, &shared) } else { 0 };
        let after = agent.counters();
        let warm = agent.stored() >= agent.min_size_to_sample();
        if schedule.train && !finished && !limited && warm && shared.algo == Algo::Ddpg {
            waited(&shared, turn_seconds, false);
        }
        shared.updates.store(after.updates, Ordering::Relaxed);
        shared.replay_size.store(agent.stored() as u64, Ordering::Relaxed);
        // PPO updates draw nothing from a replay buffer: count its updates.
        let trained = drawn > 0 || after.updates > before.updates;
        let exploration = exploration_of(agent.as_ref(), &shared);
        let exploration_changed = match (exploration, published_exploration) {
            (Some((uniform, noise)), Some((was_uniform, was_noise))) => uniform != was_uniform || (noise - was_noise).abs() >= 0.005,
            _ => false,
        };
        let publish_now = exploration_changed
            || match shared.algo {
                Algo::Ppo => trained,
                Algo::Ddpg => after.updates >= last_published + schedule.publish_every,
            };
        if publish_now {
            last_published = after.updates;
            published_exploration = exploration;
            publish(agent.as_ref(), &shared, exploration)?;
        }
        if last_checkpoint.elapsed() >= schedule.checkpoint_interval {
            last_checkpoint = std::time::Instant::now();
            checkpoint(agent.as_ref(), &shared, &schedule)?;
        }
        if held.is_some() && !trained {
            // Refused inserts and nothing to train: should not happen (the
            // limiter admits a batch whenever the learner cannot sample),
            // but never spin.
            std::thread::sleep(std::time::Duration::from_millis(1));
        } else if held.is_none() && !received && !trained {
            // Nothing to do until the next batch arrives (or the next
            // checkpoint is due).
            let wait = schedule.checkpoint_interval.saturating_sub(last_checkpoint.elapsed()).max(std::time::Duration::from_millis(10));
            match recv_timeout(&mut commands, wait) {
                Some(Some(Command::Batch(batch))) => held = Some(batch),
                Some(Some(Command::Stop)) | Some(None) => return checkpoint(agent.as_ref(), &shared, &schedule),
                None => {}
            }
        }
    }
}

/// One training step, with the transitions it drew counted in the limiter
/// and the flow statistics. The limiter counts transitions drawn (every
/// critic minibatch), not actor updates: with a policy delay they differ.
fn train_and_count(agent: &mut dyn Agent, schedule: &mut Schedule, shared: &Shared) -> u64 {
    let before = agent.samples_drawn();
    agent.train_step();
    let drawn = agent.samples_drawn() - before;
    if drawn > 0 {
        if let Some(limiter) = &mut schedule.limiter {
            limiter.sample(drawn);
        }
        {
        let mut flow = shared.flow_mut();
            flow.sampled += drawn;
        }
    }
    drawn
}

fn set_finished(shared: &Shared, finished: bool) {
    {
        let mut flow = shared.flow_mut();
        flow.finished = finished;
    }
}

/// The exploration actors should use now (DDPG), from the episodes stored.
fn exploration_of(agent: &dyn Agent, shared: &Shared) -> Option<(bool, f64)> {
    agent.exploration(shared.episodes.load(Ordering::Relaxed) as usize)
}

/// Publishes the agent's actor as the next policy version, with how actors
/// should explore with it.
fn publish(agent: &dyn Agent, shared: &Shared, exploration: Option<(bool, f64)>) -> Result<(), LearnerError> {
    let version = shared.policy_version() + 1;
    let mut next = snapshot(agent, &shared.architecture, version)?;
    if let Some((uniform, noise)) = exploration {
        next.explore_uniform = uniform;
        next.exploration_noise = noise;
    }
    shared.policy.send_replace(Arc::new(next));
    tracing::debug!(version, updates = agent.counters().updates, "policy published");
    Ok(())
}

/// Blocks for the next command up to `timeout`: Some(command or None for
/// closed), or None when the time ran out.
fn recv_timeout(commands: &mut mpsc::Receiver<Command>, timeout: std::time::Duration) -> Option<Option<Command>> {
    let deadline = std::time::Instant::now() + timeout;
    loop {
        match commands.try_recv() {
            Ok(command) => return Some(Some(command)),
            Err(mpsc::error::TryRecvError::Disconnected) => return Some(None),
            Err(mpsc::error::TryRecvError::Empty) if std::time::Instant::now() >= deadline => return None,
            Err(mpsc::error::TryRecvError::Empty) => std::thread::sleep(std::time::Duration::from_micros(250)),
        }
    }
}

/// Where finished episodes are recorded: metrics.csv (episode, return,
/// length, success; what `lcrl compare` and the reward curve read) and
/// TensorBoard scalars beside it.
struct EpisodeLog {
    /// None when the file cannot be opened (warned once; training goes on).
    csv: Option<crate::run_files::MetricsLog>,
    tensorboard: Option<crate::tensorboard::EventWriter>,
}

impl EpisodeLog {
    fn open(run_dir: &std::path::Path) -> EpisodeLog {
        let tensorboard = crate::tensorboard::EventWriter::create(run_dir)
            .map_err(|e| tracing::warn!("no TensorBoard events in {}: {e}", run_dir.display()))
            .ok();
        let csv = crate::run_files::MetricsLog::append(&run_dir.join("metrics.csv")).map_err(|e| tracing::warn!("no metrics.csv: {e}")).ok();
        EpisodeLog { csv, tensorboard }
    }

    fn append(&mut self, first: u64, episodes: &[lcrl_proto::v1::EpisodeSummary], shared: &Shared) -> std::io::Result<()> {
        if let Some(csv) = &mut self.csv {
            for (k, e) in episodes.iter().enumerate() {
                // The actors report return, length and success; the rest
                // of the row is `lcrl train`'s own.
                let row = crate::run_files::EpisodeRow {
                    episode: (first + k as u64 + 1) as usize,
                    episode_return: e.episode_return,
                    length: e.length as usize,
                    success: e.success,
                    ..Default::default()
                };
                csv.push(&row).map_err(std::io::Error::other)?;
            }
        }
        if let Some(tb) = &mut self.tensorboard {
            for (k, e) in episodes.iter().enumerate() {
                tb.scalars((first + k as u64 + 1) as i64, &[("episode/return", e.episode_return), ("episode/length", f64::from(e.length))])?;
            }
            let step = (first + episodes.len() as u64) as i64;
            // Read under the lock: no copy of the lag window per batch.
            let (ratio, (lag_min, lag_mean, lag_max), actors_waited, learner_waited) = {
                let f = shared.flow_mut();
                (f.achieved_ratio(), f.lag.stats(), f.actors_waited_s, f.learner_waited_s)
            };
            let learner = [
                ("learner/env_steps", shared.env_steps.load(Ordering::Relaxed) as f64),
                ("learner/updates", shared.updates.load(Ordering::Relaxed) as f64),
                ("learner/policy_version", shared.policy_version() as f64),
                ("learner/replay_ratio", ratio),
                ("learner/policy_lag_min", lag_min as f64),
                ("learner/policy_lag_mean", lag_mean),
                ("learner/policy_lag_max", lag_max as f64),
                ("learner/actors_waited_s", actors_waited),
                ("learner/learner_waited_s", learner_waited),
            ];
            tb.scalars(step, &learner)?;
            tb.flush()?;
        }
        Ok(())
    }
}

/// Stores an accepted batch; returns the transitions stored (0 if stale).
fn store(agent: &mut dyn Agent, shared: &Shared, schedule: &Schedule, log: &mut EpisodeLog, batch: Accepted) -> u64 {
    let newest = shared.policy_version();
    let stale = schedule.max_staleness.is_some_and(|bound| newest.saturating_sub(batch.policy_version) > bound);
    if stale {
        // Nothing of a stale batch counts: its episodes are not data the
        // learner learned from, so they do not use up the budget either
        // (the budget means what it means in `lcrl train`).
        {
        let mut ingest = shared.ingest();
            *ingest.rejected.entry("stale".into()).or_insert(0) += batch.transitions.len() as u64;
        }
        return 0;
    }
    for t in batch.transitions.iter().filter(|_| !stale) {
        agent.store(Transition {
            obs: &t.obs,
            action: &t.action,
            reward: t.reward,
            next_obs: &t.next_obs,
            terminated: t.terminated,
            truncated: t.truncated,
        });
    }
    {
        let mut flow = shared.flow_mut();
        for t in batch.transitions.iter().filter(|_| !stale) {
            flow.lag.push(newest.saturating_sub(t.policy_version));
        }
    }
    shared.env_steps.store(agent.counters().env_steps, Ordering::Relaxed);
    let first = shared.episodes.fetch_add(batch.episodes.len() as u64, Ordering::Relaxed);
    if !batch.episodes.is_empty() {
        if let Err(e) = log.append(first, &batch.episodes, shared) {
            tracing::warn!("cannot record episodes in {}: {e}", shared.run_dir.display());
        }
    }
    {
        let mut returns = lock(&shared.recent_returns);
        for episode in &batch.episodes {
            returns.push_back(episode.episode_return);
            while returns.len() > 10 {
                returns.pop_front();
            }
        }
    }
    batch.transitions.len() as u64
}
