//! The learner's training thread. It owns the agent: gRPC handlers (and
//! shared-memory subscribers) only check batches and hand them over through
//! a bounded channel, so ingestion never waits for an update and the queue
//! cannot grow without bound.
//!
//! [`TrainingLoop`] reads top to bottom as Algorithm 2 does across
//! processes (docs/method.md §5). Each turn it
//! 1. **admits** batches while the rate limiter lets them in (a refused
//!    batch is held, the command queue fills and the actors' sends block:
//!    backpressure, not dropped data), and ends the run at its budget;
//! 2. **trains** once, if the limiter lets the learner sample;
//! 3. **publishes** the policy when due, hands a snapshot to the validation
//!    thread when a validation is due (`service/validator.rs`), and
//!    checkpoints on its interval;
//! 4. **idles** until the next batch when there was nothing to do.
//!
//! At the end of the budget it waits for the last validation, serves the
//! chosen policy (`Policy.Act`, `GetStatus.served_version`), evaluates it
//! as `lcrl train` does and writes summary.json (crate::run::summary).

use std::path::PathBuf;
use std::sync::atomic::Ordering;
use std::sync::Arc;
use std::time::{Duration, Instant};

use lcrl_proto::v1::PolicySnapshot;
use tokio::sync::mpsc;

use crate::algo::agent::{Agent, Transition};
use crate::policy::checkpoint::{write_checkpoint, CheckpointMeta};
use crate::config::Algo;
use crate::algo::rate_limiter::RateLimiter;
use crate::service::ingest::Accepted;
use crate::run::selection::SelectionRecord;
use crate::service::shared::{Command, Served, Shared};
use crate::service::validator::Validator;
use crate::policy::snapshot::snapshot;
use crate::run::summary::{evaluate_hand_over, EvaluationPlan, PolicyLag, RunSummary, ServiceFigures};
use crate::LearnerError;

/// How often the training thread publishes and checkpoints.
#[derive(Debug)]
pub struct Schedule {
    /// Publish a new policy version every this many updates (PPO: after
    /// every PPO update).
    pub publish_every: u64,
    /// Checkpoint at this interval (and on stop). Time, not episodes: actors
    /// can finish hundreds of episodes a second.
    pub checkpoint_interval: Duration,
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
    /// resume). None: unlimited, at most one update per stored step. The
    /// loop hands it to the flow statistics, which then own the counts.
    pub limiter: Option<RateLimiter>,
    /// The choice of the run's policy on held-out starts (None:
    /// `run.validation_episodes` is 0, and the last policy is the run's).
    pub validator: Option<Validator>,
    /// A headroom reference to evaluate beside the handed-over policy
    /// (`lcrl-learner --headroom`), as `lcrl run` shows it.
    pub headroom: Option<lcrl_sim::tune::feedback::StoredPolicy>,
}

/// Batches stored per loop turn before training gets its turn: with fast
/// actors the queue is never empty, and training must not starve.
const BATCHES_PER_TURN: usize = 8;

/// What admitting batches for one turn saw.
struct Admitted {
    /// At least one batch was stored.
    received: bool,
    /// A Stop arrived, or every sender is gone.
    stop: bool,
}

/// The training thread's state between turns.
pub struct TrainingLoop {
    agent: Box<dyn Agent>,
    commands: mpsc::Receiver<Command>,
    shared: Arc<Shared>,
    schedule: Schedule,
    log: crate::service::episodes::EpisodeLog,
    /// A batch the limiter refused: stored first when it admits it.
    held: Option<Accepted>,
    /// Updates at the last published version.
    last_published: u64,
    /// How actors were last told to explore (DDPG).
    published_exploration: Option<(bool, f64)>,
    last_checkpoint: Instant,
    turn_started: Instant,
    /// When this process's training began (summary.json's total_seconds).
    started: Instant,
    /// The budget is reached: nothing more is stored or trained.
    finished: bool,
}

impl TrainingLoop {
    pub fn new(agent: Box<dyn Agent>, commands: mpsc::Receiver<Command>, shared: Arc<Shared>, mut schedule: Schedule) -> Self {
        {
            let mut flow = shared.flow_mut();
            flow.budget_episodes = schedule.budget_episodes.unwrap_or(0);
            flow.limiter = schedule.limiter.take().unwrap_or_default();
        }
        let published_exploration = agent.exploration(shared.episodes.load(Ordering::Relaxed) as usize);
        // The starting version (no actor has it yet: the servers start
        // after this thread) learns how to explore, without a version of
        // its own.
        if let Some((uniform, noise)) = published_exploration {
            shared.policy.send_modify(|current| {
                let mut first = (**current).clone();
                first.explore_uniform = uniform;
                first.exploration_noise = noise;
                *current = Arc::new(first);
            });
        }
        let log = crate::service::episodes::EpisodeLog::open(&shared.run_dir, shared.episodes.load(Ordering::Relaxed));
        let last_published = agent.counters().updates;
        let mut training = TrainingLoop {
            agent,
            commands,
            shared,
            schedule,
            log,
            held: None,
            last_published,
            published_exploration,
            last_checkpoint: Instant::now(),
            turn_started: Instant::now(),
            started: Instant::now(),
            finished: false,
        };
        training.finished = training.budget_reached();
        training.shared.flow_mut().finished = training.finished;
        // A run resumed at its budget: its actors stop at once.
        if training.finished {
            tell_actors_finished(&training.shared);
        }
        training
    }

    /// Runs until told to stop, every sender is gone or the budget is
    /// reached; a checkpoint is written on the way out.
    pub fn run(mut self) -> Result<(), LearnerError> {
        // The starting policy is a candidate, as in `lcrl train` (with a
        // base controller it is the base itself).
        self.validate_if_due()?;
        loop {
            // Shutdown does not wait for a Stop through the queue: while
            // the limiter holds a batch the queue is full, and senders (the
            // Stop among them) would wait on this thread forever.
            if *self.shared.shutdown.borrow() {
                return self.checkpoint_unless_finished();
            }
            let turn_seconds = self.turn_started.elapsed().as_secs_f64();
            self.turn_started = Instant::now();
            if self.held.is_some() {
                self.shared.flow_mut().actors_waited_s += turn_seconds;
            }
            let admitted = self.admit()?;
            if admitted.stop {
                return self.checkpoint_unless_finished();
            }
            let trained = self.train(turn_seconds);
            self.publish_if_due(trained)?;
            self.validate_if_due()?;
            if !self.finished && self.last_checkpoint.elapsed() >= self.schedule.checkpoint_interval {
                // A failed checkpoint (a full disk) does not end training:
                // checkpoint() counted and logged it, the earlier
                // checkpoints stand, and the next interval tries again.
                let _ = self.checkpoint();
            }
            if self.idle(admitted.received, trained) {
                return self.checkpoint_unless_finished();
            }
        }
    }

    /// A checkpoint on the way out, unless the budget is spent: the final
    /// checkpoint already holds the run, and nothing has changed since
    /// (once finished, no batch is stored and no update made).
    fn checkpoint_unless_finished(&mut self) -> Result<(), LearnerError> {
        if self.finished {
            return Ok(());
        }
        self.checkpoint()
    }

    fn episodes(&self) -> u64 {
        self.shared.episodes.load(Ordering::Relaxed)
    }

    fn budget_reached(&self) -> bool {
        self.schedule.budget_episodes.is_some_and(|budget| self.episodes() >= budget)
    }

    /// Step 1: stores up to [`BATCHES_PER_TURN`] batches, as far as the
    /// budget and the rate limiter admit them.
    fn admit(&mut self) -> Result<Admitted, LearnerError> {
        let mut admitted = Admitted { received: false, stop: false };
        for _ in 0..BATCHES_PER_TURN {
            let mut batch = match self.held.take() {
                Some(batch) => batch,
                None => match self.commands.try_recv() {
                    Ok(Command::Batch(batch)) => batch,
                    Ok(Command::Stop) | Err(mpsc::error::TryRecvError::Disconnected) => {
                        admitted.stop = true;
                        break;
                    }
                    Err(mpsc::error::TryRecvError::Empty) => break,
                },
            };
            // Nothing past the budget's last episode is stored.
            let past_budget = match self.schedule.budget_episodes {
                _ if self.finished => std::mem::take(&mut batch.transitions).len(),
                Some(budget) => batch.keep_episodes(budget.saturating_sub(self.episodes()) as usize),
                None => 0,
            };
            self.shared.record_dropped("over_budget", past_budget as u64);
            if self.finished || batch.transitions.is_empty() {
                continue;
            }
            // Liveness: a batch too large for the window goes in when the
            // learner cannot sample either (one batch of error).
            let count = batch.transitions.len() as u64;
            let batch_size = self.agent.samples_per_update() as u64;
            let refused = {
                let flow = self.shared.flow_mut();
                !flow.limiter.can_insert(count) && flow.limiter.can_sample(batch_size)
            };
            if refused {
                self.held = Some(batch);
                break;
            }
            admitted.received = true;
            let stored = self.store(batch);
            self.shared.flow_mut().limiter.insert(stored);
            if self.budget_reached() {
                self.finish()?;
                break;
            }
        }
        Ok(admitted)
    }

    /// Stores an accepted batch; returns the transitions stored (0 if stale).
    fn store(&mut self, batch: Accepted) -> u64 {
        let shared = &self.shared;
        let newest = shared.policy_version();
        if self.schedule.max_staleness.is_some_and(|bound| newest.saturating_sub(batch.policy_version) > bound) {
            // Nothing of a stale batch counts: its episodes are not data
            // the learner learned from, so they do not use up the budget
            // either (the budget means what it means in `lcrl train`).
            shared.record_dropped("stale", batch.transitions.len() as u64);
            return 0;
        }
        for t in &batch.transitions {
            self.agent.store(Transition {
                obs: &t.obs,
                action: &t.action,
                reward: t.reward,
                next_obs: &t.next_obs,
                terminated: t.terminated,
                truncated: t.truncated,
                log_prob: t.log_prob,
                cut: t.cut,
                stream: batch.stream,
            });
        }
        {
            let mut flow = shared.flow_mut();
            for t in &batch.transitions {
                flow.lag.push(newest.saturating_sub(t.policy_version));
            }
        }
        shared.env_steps.store(self.agent.counters().env_steps, Ordering::Relaxed);
        let first = shared.episodes.fetch_add(batch.episodes.len() as u64, Ordering::Relaxed);
        if !batch.episodes.is_empty() {
            if let Err(e) = self.log.append(first, &batch.episodes, shared) {
                tracing::warn!("cannot record episodes in {}: {e}", shared.run_dir.display());
            }
        }
        shared.record_returns(&batch.episodes);
        batch.transitions.len() as u64
    }

    /// The budget is reached: the updates the last inserts earned
    /// (Algorithm 2 gives every step its update, to the end of the run),
    /// then the final checkpoint and summary.
    fn finish(&mut self) -> Result<(), LearnerError> {
        self.finished = true;
        self.held = None;
        // First, so that no error below keeps the actors running.
        tell_actors_finished(&self.shared);
        let batch_size = self.agent.samples_per_update() as u64;
        let owed = |training: &Self| {
            let flow = training.shared.flow_mut();
            flow.limiter.is_limited() && training.schedule.train && batch_size > 0 && flow.limiter.owed() >= batch_size as f64
        };
        while owed(self) {
            if self.train_once() == 0 {
                break;
            }
        }
        self.shared.updates.store(self.agent.counters().updates, Ordering::Relaxed);
        // The final checkpoint publishes where training ended (see
        // publish_pending), so the served policy without validation, the
        // newest, is the one training ended with.
        // A full disk here is waited out (disk_full.rs): the final
        // checkpoint and summary.json are the run's result.
        let patience = (super::disk_full::WAIT_FOR_SPACE, super::disk_full::RETRY_EVERY);
        let shared = self.shared.clone();
        let stopped = move || *shared.shutdown.borrow();
        match super::disk_full::retry_while_full("the final checkpoint", patience, &stopped, || self.checkpoint()) {
            // Diverged weights are never written; the run still ends with
            // its summary, serving the last finite policy (issue 71).
            Err(LearnerError::Diverged(_)) => {}
            other => other?,
        }
        // The last policy is validated too, then the choice is final.
        self.validate_if_due()?;
        let chosen = self.schedule.validator.as_mut().map(Validator::finish).transpose()?;
        let served = match chosen.as_ref().and_then(|c| c.snapshot.clone().zip(c.record.clone())) {
            Some((snapshot, record)) => Served {
                reason: format!("selected: the policy after {} episodes, {}", record.episode, record.how_chosen()),
                snapshot,
            },
            None => Served { snapshot: self.shared.policy.borrow().clone(), reason: "newest: training ended without validation (run.validation_episodes = 0)".into() },
        };
        let snapshot = served.snapshot.clone();
        self.shared.serve(served);
        let record = chosen.and_then(|c| c.record);
        super::disk_full::retry_while_full("summary.json", patience, &stopped, || self.write_summary(&snapshot, record.clone()))?;
        self.shared.flow_mut().finished = true;
        tracing::info!(episodes = self.episodes(), "episode budget reached: training ends");
        Ok(())
    }

    /// Step 2: one training step if the schedule and the limiter allow it.
    /// Returns whether the agent trained.
    fn train(&mut self, turn_seconds: f64) -> bool {
        // The budget drives every schedule, as in `lcrl train`.
        if let Some(budget) = self.schedule.budget_episodes {
            self.agent.set_progress(self.episodes() as f64 / budget.max(1) as f64);
        }
        let before = self.agent.counters();
        let batch_size = self.agent.samples_per_update() as u64;
        let allowed = {
            let flow = self.shared.flow_mut();
            match self.shared.algo {
                Algo::Ppo => true,
                Algo::Ddpg if flow.limiter.is_limited() => flow.limiter.can_sample(batch_size),
                // Unlimited: at most one update per stored step.
                Algo::Ddpg => before.updates < before.env_steps,
            }
        };
        let may_train = self.schedule.train && !self.finished && allowed;
        let drawn = if may_train { self.train_once() } else { 0 };
        let after = self.agent.counters();
        let warm = self.agent.stored() >= self.agent.min_size_to_sample();
        if self.schedule.train && !self.finished && !allowed && warm && self.shared.algo == Algo::Ddpg {
            self.shared.flow_mut().learner_waited_s += turn_seconds;
        }
        self.shared.updates.store(after.updates, Ordering::Relaxed);
        self.shared.replay_size.store(self.agent.stored() as u64, Ordering::Relaxed);
        // PPO updates draw nothing from a replay buffer: count its updates.
        drawn > 0 || after.updates > before.updates
    }

    /// One `train_step`, with the transitions it drew counted by the
    /// limiter. It counts transitions drawn (every critic minibatch), not
    /// actor updates: with a policy delay they differ.
    fn train_once(&mut self) -> u64 {
        let before = self.agent.samples_drawn();
        self.agent.train_step();
        let drawn = self.agent.samples_drawn() - before;
        self.shared.flow_mut().limiter.sample(drawn);
        drawn
    }

    /// Step 3: a new policy version after PPO's update, every
    /// `publish_every` DDPG updates, or when the exploration actors should
    /// use has changed.
    fn publish_if_due(&mut self, trained: bool) -> Result<(), LearnerError> {
        let updates = self.agent.counters().updates;
        let exploration = self.agent.exploration(self.episodes() as usize);
        let exploration_changed = match (exploration, self.published_exploration) {
            (Some((uniform, noise)), Some((was_uniform, was_noise))) => uniform != was_uniform || (noise - was_noise).abs() >= 0.005,
            _ => false,
        };
        let due = match self.shared.algo {
            Algo::Ppo => trained,
            Algo::Ddpg => updates >= self.last_published + self.schedule.publish_every,
        };
        if !(due || exploration_changed) {
            return Ok(());
        }
        self.publish(exploration)
    }

    /// Publishes the actor when it has changed since the last version.
    /// DDPG publishes every `publish_every` updates, so the agent is
    /// usually ahead of the published version; a checkpoint or a
    /// validation records a version number with the agent's weights, and
    /// that version must be the one actors and Policy.Act got with those
    /// weights.
    fn publish_pending(&mut self) -> Result<(), LearnerError> {
        if self.agent.counters().updates == self.last_published {
            return Ok(());
        }
        self.publish(self.agent.exploration(self.episodes() as usize))
    }

    /// Publishes the agent's actor as the next policy version.
    fn publish(&mut self, exploration: Option<(bool, f64)>) -> Result<(), LearnerError> {
        let updates = self.agent.counters().updates;
        self.last_published = updates;
        let version = self.shared.policy_version() + 1;
        let mut next = snapshot(self.agent.as_ref(), &self.shared.architecture, version)?;
        // A diverged actor is never served: actors and validation keep the
        // last finite version (issue 71).
        if !crate::policy::finite::all_finite(&next.weights)? {
            let refused = {
                let mut flow = self.shared.flow_mut();
                flow.non_finite_policies += 1;
                flow.non_finite_policies
            };
            // Logged at 1, 2, 4, 8, … refusals: a diverged run would
            // otherwise log every turn.
            if refused.is_power_of_two() {
                tracing::error!(version, updates, refused, "policy not published: a weight is NaN or infinite");
            }
            return Ok(());
        }
        self.published_exploration = exploration;
        next.incarnation = self.shared.incarnation;
        // A version published after the budget (a change of exploration)
        // still says so: actors that join late stop too.
        next.training_finished = self.finished;
        if let Some((uniform, noise)) = exploration {
            next.explore_uniform = uniform;
            next.exploration_noise = noise;
        }
        self.shared.policy.send_replace(Arc::new(next));
        tracing::debug!(version, updates, "policy published");
        Ok(())
    }

    /// Step 4: waits for the next batch when the turn did nothing. Returns
    /// true when told to stop meanwhile.
    fn idle(&mut self, received: bool, trained: bool) -> bool {
        if self.held.is_some() && !trained {
            // Refused inserts and nothing to train: should not happen (the
            // limiter admits a batch whenever the learner cannot sample),
            // but never spin.
            std::thread::sleep(Duration::from_millis(1));
        } else if self.held.is_none() && !received && !trained {
            // Nothing to do until the next batch arrives (or the next
            // checkpoint is due).
            let wait = self.schedule.checkpoint_interval.saturating_sub(self.last_checkpoint.elapsed()).max(Duration::from_millis(10));
            match recv_timeout(&mut self.commands, wait) {
                Some(Some(Command::Batch(batch))) => self.held = Some(batch),
                Some(Some(Command::Stop)) | Some(None) => return true,
                None => {}
            }
        }
        false
    }

    /// Writes a checkpoint. A failure has left nothing of it on disk
    /// (`write_folder`); it is counted (`checkpoint_failures` in /metrics)
    /// and logged here, and returned for the caller to decide: the final
    /// checkpoint's is the run's error, an interval's is retried.
    fn checkpoint(&mut self) -> Result<(), LearnerError> {
        self.last_checkpoint = Instant::now();
        self.publish_pending()?;
        let mut meta = self.schedule.meta.clone();
        {
            let flow = self.shared.flow_mut();
            meta.rate_limiter = flow.limiter.is_limited().then(|| flow.limiter.clone());
        }
        meta.episode = self.episodes() as usize;
        meta.policy_version = self.shared.policy_version();
        meta.actor_sequences = self.shared.ingest().sequences().clone();
        let dir = write_checkpoint(&self.schedule.run_dir, self.agent.as_ref(), &meta).inspect_err(|e| {
            self.shared.flow_mut().checkpoint_failures += 1;
            tracing::error!(episodes = meta.episode, "checkpoint failed: {e}");
        })?;
        tracing::info!(checkpoint = %dir.display(), episodes = meta.episode, policy_version = meta.policy_version, "checkpoint written");
        Ok(())
    }

    /// Hands the current actor to the validation thread when a validation
    /// is due: at the start, every `run.validate_every` episodes and at the
    /// end of the budget, as `lcrl train` validates.
    fn validate_if_due(&mut self) -> Result<(), LearnerError> {
        let done = self.episodes() as usize;
        let last = self.schedule.budget_episodes.map_or(usize::MAX, |b| b as usize);
        if !self.schedule.validator.as_ref().is_some_and(|v| v.due(done, last)) {
            return Ok(());
        }
        self.publish_pending()?;
        let Some(validator) = self.schedule.validator.as_mut() else { return Ok(()) };
        let version = self.shared.policy_version();
        let snapshot = Arc::new(snapshot(self.agent.as_ref(), &self.shared.architecture, version)?);
        if !crate::policy::finite::all_finite(&snapshot.weights)? {
            tracing::error!(episodes = done, "validation skipped: a weight is NaN or infinite");
            return Ok(());
        }
        let meta = CheckpointMeta { episode: done, policy_version: version, ..self.schedule.meta.clone() };
        validator.submit(snapshot, meta);
        Ok(())
    }

    /// The hand-over: the served policy (and the last, when selection
    /// chose another) evaluated on `run.eval_episodes` starts beside the
    /// references, as `lcrl train` evaluates, then summary.json.
    fn write_summary(&self, served: &PolicySnapshot, selection: Option<SelectionRecord>) -> Result<(), LearnerError> {
        let meta = &self.schedule.meta;
        let config = &meta.config;
        let env = lcrl_sim::make_env(&meta.shape.env)?;
        // The last policy is the agent as training left it (the final
        // checkpoint's); the served one is evaluated apart when it differs.
        let last = snapshot(self.agent.as_ref(), &self.shared.architecture, self.shared.policy_version())?;
        let chosen = (served.weights != last.weights).then_some(served);
        let plan = EvaluationPlan {
            episodes: config.run.eval_episodes,
            first_seed: config.run.first_eval_seed(),
            local_mask: (meta.shape.connection == crate::config::Connection::Local).then_some(meta.shape.mask.as_slice()),
            headroom: self.schedule.headroom.as_ref(),
        };
        let evaluation = evaluate_hand_over(env.as_ref(), chosen, &last, &plan)?;
        // Read before the flow's lock is taken (one lock at a time).
        let discarded_stale = super::ingest::discarded_stale(&self.shared.ingest_counts().1);
        let flow = self.shared.flow();
        let (min, mean, max) = flow.lag.stats();
        let counters = self.agent.counters();
        let ppo = meta.shape.algo == crate::config::Algo::Ppo;
        let (actor_params, critic_params) = self.agent.param_counts();
        let summary = RunSummary {
            env: meta.shape.env.clone(),
            algo: meta.shape.algo,
            connection: meta.shape.connection,
            seed: config.run.seed,
            episodes: self.episodes() as usize,
            final_return: self.shared.recent_return(),
            evaluation,
            selection,
            graph_seconds: meta.graph_seconds,
            graph: None,
            optimization_seconds: 0.0,
            total_seconds: meta.elapsed_seconds + self.started.elapsed().as_secs_f64(),
            env_steps: counters.env_steps,
            updates: counters.updates,
            critic_updates: counters.critic_updates,
            skipped_updates: counters.skipped_updates,
            diverged_env: 0,
            samples_drawn: flow.sampled(),
            actor_params,
            critic_params,
            service: Some(ServiceFigures {
                sampled: flow.sampled(),
                inserted: flow.inserted(),
                replay_ratio: flow.achieved_ratio(),
                replay_ratio_target: flow.replay_ratio_target(),
                policy_lag: PolicyLag { min, mean, max },
                actors_waited_s: flow.actors_waited_s,
                learner_waited_s: flow.learner_waited_s,
                policy_version: self.shared.policy_version(),
                served_version: served.version,
                cuts: ppo.then_some(counters.cuts),
                cuts_joined: ppo.then_some(counters.cuts_joined),
                discarded_stale: ppo.then_some(discarded_stale),
                actors: None,
                transport: None,
                actor_restarts: None,
                ended_early: None,
            }),
        };
        drop(flow);
        crate::run::summary::write_summary(&self.shared.run_dir, &summary)
    }
}

/// Marks the published policy as the last: actors learn it from their
/// policy feed (gRPC and shared memory) and stop, as nothing they send
/// from now on is stored.
fn tell_actors_finished(shared: &Shared) {
    shared.policy.send_modify(|current| {
        let mut last = (**current).clone();
        last.training_finished = true;
        *current = Arc::new(last);
    });
}

/// Blocks for the next command up to `timeout`: Some(command or None for
/// closed), or None when the time ran out. Asleep meanwhile (idle.rs), and
/// woken at once by a batch.
fn recv_timeout(commands: &mut mpsc::Receiver<Command>, timeout: Duration) -> Option<Option<Command>> {
    crate::service::idle::wait_for(timeout, commands.recv())
}
