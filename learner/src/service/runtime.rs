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
use crate::service::ingest::{Accepted, Ingest};
use crate::snapshot::{encode_weights, Architecture};
use crate::trainer::{write_checkpoint, CheckpointMeta};
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
}

impl Shared {
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

    pub fn recent_return(&self) -> f64 {
        let returns = self.recent_returns.lock().map(|r| r.iter().copied().collect::<Vec<_>>()).unwrap_or_default();
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
}

/// Batches stored per loop turn before training gets its turn: with fast
/// actors the queue is never empty, and training must not starve.
const BATCHES_PER_TURN: usize = 8;

/// Encodes the agent's actor as the next policy version.
pub fn snapshot(agent: &dyn Agent, architecture: &Architecture, version: u64) -> Result<PolicySnapshot, LearnerError> {
    let weights = encode_weights(&agent.actor_variables())?;
    let architecture = serde_json::to_string(architecture).map_err(|e| LearnerError::Checkpoint(e.to_string()))?;
    Ok(PolicySnapshot { version, weights, architecture })
}

fn checkpoint(agent: &dyn Agent, shared: &Shared, schedule: &Schedule) -> Result<(), LearnerError> {
    let mut meta = schedule.meta.clone();
    meta.episode = shared.episodes.load(Ordering::Relaxed) as usize;
    meta.policy_version = shared.policy_version();
    meta.actor_sequences = shared.ingest.lock().map(|i| i.sequences().clone()).unwrap_or_default();
    let dir = write_checkpoint(&schedule.run_dir, agent, &meta)?;
    tracing::info!(checkpoint = %dir.display(), episodes = meta.episode, policy_version = meta.policy_version, "checkpoint written");
    Ok(())
}

/// The training loop; returns when told to stop or when every sender is
/// gone, after writing a checkpoint.
pub fn run_training(mut agent: Box<dyn Agent>, mut commands: mpsc::Receiver<Command>, shared: Arc<Shared>, schedule: Schedule) -> Result<(), LearnerError> {
    let mut last_published = agent.counters().updates;
    let mut last_checkpoint = std::time::Instant::now();
    let mut log = EpisodeLog::open(&shared.run_dir);
    loop {
        let mut stop = false;
        let mut received = false;
        for _ in 0..BATCHES_PER_TURN {
            match commands.try_recv() {
                Ok(Command::Batch(batch)) => {
                    received = true;
                    store(agent.as_mut(), &shared, &schedule, &mut log, batch);
                }
                Ok(Command::Stop) | Err(mpsc::error::TryRecvError::Disconnected) => {
                    stop = true;
                    break;
                }
                Err(mpsc::error::TryRecvError::Empty) => break,
            }
        }
        if stop {
            return checkpoint(agent.as_ref(), &shared, &schedule);
        }
        let before = agent.counters();
        // DDPG keeps at most one update per stored environment step (Algorithm
        // 2's ratio); PPO trains whenever a rollout is full.
        let may_train = schedule.train && (shared.algo == Algo::Ppo || before.updates < before.env_steps);
        if may_train {
            agent.train_step();
        }
        let after = agent.counters();
        shared.updates.store(after.updates, Ordering::Relaxed);
        shared.replay_size.store(agent.stored() as u64, Ordering::Relaxed);
        let trained = after.updates > before.updates;
        let publish = match shared.algo {
            Algo::Ppo => trained,
            Algo::Ddpg => after.updates >= last_published + schedule.publish_every,
        };
        if publish {
            last_published = after.updates;
            let version = shared.policy_version() + 1;
            let next = snapshot(agent.as_ref(), &shared.architecture, version)?;
            shared.policy.send_replace(Arc::new(next));
            tracing::debug!(version, updates = after.updates, "policy published");
        }
        if last_checkpoint.elapsed() >= schedule.checkpoint_interval {
            last_checkpoint = std::time::Instant::now();
            checkpoint(agent.as_ref(), &shared, &schedule)?;
        }
        if !received && !trained {
            // Nothing to do until the next batch arrives (or the next
            // checkpoint is due).
            let wait = schedule.checkpoint_interval.saturating_sub(last_checkpoint.elapsed()).max(std::time::Duration::from_millis(10));
            match recv_timeout(&mut commands, wait) {
                Some(Some(Command::Batch(batch))) => store(agent.as_mut(), &shared, &schedule, &mut log, batch),
                Some(Some(Command::Stop)) | Some(None) => return checkpoint(agent.as_ref(), &shared, &schedule),
                None => {}
            }
        }
    }
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
            Err(mpsc::error::TryRecvError::Empty) => std::thread::sleep(std::time::Duration::from_millis(2)),
        }
    }
}

/// Where finished episodes are recorded: metrics.csv (episode, return,
/// length, success; what `lcrl compare` and the reward curve read) and
/// TensorBoard scalars beside it.
struct EpisodeLog {
    csv: std::path::PathBuf,
    tensorboard: Option<crate::tensorboard::EventWriter>,
}

impl EpisodeLog {
    fn open(run_dir: &std::path::Path) -> EpisodeLog {
        let tensorboard = crate::tensorboard::EventWriter::create(run_dir)
            .map_err(|e| tracing::warn!("no TensorBoard events in {}: {e}", run_dir.display()))
            .ok();
        EpisodeLog { csv: run_dir.join("metrics.csv"), tensorboard }
    }

    fn append(&mut self, first: u64, episodes: &[lcrl_proto::v1::EpisodeSummary], shared: &Shared) -> std::io::Result<()> {
        use std::io::Write;
        let new = !self.csv.exists();
        let mut file = std::fs::OpenOptions::new().create(true).append(true).open(&self.csv)?;
        if new {
            writeln!(file, "episode,return,length,success,peak_force_n,peak_moment_nm,wall_s,optimization_s")?;
        }
        for (k, e) in episodes.iter().enumerate() {
            let success = e.success.map_or(String::new(), |s| s.to_string());
            writeln!(file, "{},{},{},{success},,,,", first + k as u64 + 1, e.episode_return, e.length)?;
        }
        if let Some(tb) = &mut self.tensorboard {
            for (k, e) in episodes.iter().enumerate() {
                tb.scalars((first + k as u64 + 1) as i64, &[("episode/return", e.episode_return), ("episode/length", f64::from(e.length))])?;
            }
            let step = (first + episodes.len() as u64) as i64;
            let learner = [
                ("learner/env_steps", shared.env_steps.load(Ordering::Relaxed) as f64),
                ("learner/updates", shared.updates.load(Ordering::Relaxed) as f64),
                ("learner/policy_version", shared.policy_version() as f64),
            ];
            tb.scalars(step, &learner)?;
            tb.flush()?;
        }
        Ok(())
    }
}

fn store(agent: &mut dyn Agent, shared: &Shared, schedule: &Schedule, log: &mut EpisodeLog, batch: Accepted) {
    let newest = shared.policy_version();
    let stale = schedule.max_staleness.is_some_and(|bound| newest.saturating_sub(batch.policy_version) > bound);
    if stale {
        if let Ok(mut ingest) = shared.ingest.lock() {
            *ingest.rejected.entry("stale".into()).or_insert(0) += batch.transitions.len() as u64;
        }
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
    shared.env_steps.store(agent.counters().env_steps, Ordering::Relaxed);
    let first = shared.episodes.fetch_add(batch.episodes.len() as u64, Ordering::Relaxed);
    if !batch.episodes.is_empty() {
        if let Err(e) = log.append(first, &batch.episodes, shared) {
            tracing::warn!("cannot record episodes in {}: {e}", shared.run_dir.display());
        }
    }
    if let Ok(mut returns) = shared.recent_returns.lock() {
        for episode in &batch.episodes {
            returns.push_back(episode.episode_return);
            while returns.len() > 10 {
                returns.pop_front();
            }
        }
    }
}
