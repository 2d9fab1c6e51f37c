//! The distributed learner's choice of its policy on held-out starts, as
//! `lcrl train` chooses (`crate::run::selection`: the same starts, the same
//! schedule, the same `RUN/selected/`), on a thread of its own so that
//! validation episodes never hold up updates.
//!
//! The training thread hands over a snapshot of the actor whenever a
//! validation is due ([`Validator::due`], the rule of
//! [`crate::run::selection::validation_due`]); snapshots are copies, so
//! validating one reads nothing the training thread writes and training is
//! the same with or without it. At the end of the budget the training
//! thread waits for the last validation and the confirmation
//! ([`Validator::finish`]) and serves the chosen policy from then on.

use std::path::{Path, PathBuf};
use std::sync::atomic::{AtomicU64, Ordering};
use std::sync::mpsc;
use std::sync::{Arc, Mutex, OnceLock};
use std::thread::JoinHandle;
use std::time::Instant;

use lcrl_proto::v1::PolicySnapshot;
use lcrl_sim::Env;

use crate::policy::checkpoint::CheckpointMeta;
use crate::run::selection::{selected_dir, validation_due, Selection, SelectionRecord};
use crate::LearnerError;

/// The policy chosen so far: its record and its snapshot.
#[derive(Debug, Clone, Default)]
pub struct Chosen {
    pub record: Option<SelectionRecord>,
    pub snapshot: Option<Arc<PolicySnapshot>>,
}

struct Job {
    snapshot: Arc<PolicySnapshot>,
    meta: CheckpointMeta,
}

/// The validation thread and what it has chosen.
pub struct Validator {
    jobs: Option<mpsc::Sender<Job>>,
    thread: Option<JoinHandle<Result<(), LearnerError>>>,
    chosen: Arc<Mutex<Chosen>>,
    every: usize,
    /// The episode count of the last validation handed over.
    last_submitted: Option<usize>,
    progress: Arc<Progress>,
}

/// What the validation thread shows of itself.
#[derive(Debug)]
struct Progress {
    /// Validations handed over and not yet started (shared with /metrics).
    pending: Arc<AtomicU64>,
    /// The kernel id of the thread that runs the validation episodes.
    worker: OnceLock<i64>,
}

impl std::fmt::Debug for Validator {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("Validator").field("every", &self.every).field("last_submitted", &self.last_submitted).finish()
    }
}

impl Validator {
    /// Starts the thread for `selection` (see [`Selection::new`]; a resumed
    /// run's choice is read back from `RUN/selected/`), validating in `env`;
    /// `pending` counts the validations handed over and not yet started.
    pub fn start(selection: Selection, env: Box<dyn Env>, run_dir: &Path, every: usize, pending: Arc<AtomicU64>) -> Result<Self, LearnerError> {
        let chosen = Chosen { record: selection.record(), snapshot: read_selected(run_dir)?.map(Arc::new) };
        let last_submitted = selection.last_validated();
        let chosen = Arc::new(Mutex::new(chosen));
        let (jobs, inbox) = mpsc::channel::<Job>();
        let thread_chosen = chosen.clone();
        let run_dir = run_dir.to_path_buf();
        let progress = Arc::new(Progress { pending, worker: OnceLock::new() });
        let thread_progress = progress.clone();
        let thread = std::thread::Builder::new()
            .name("validation".into())
            .spawn(move || validate_jobs(selection, env, &run_dir, &inbox, &thread_chosen, thread_progress))
            .map_err(|e| LearnerError::Config(format!("cannot start the validation thread: {e}")))?;
        Ok(Validator { jobs: Some(jobs), thread: Some(thread), chosen, every, last_submitted, progress })
    }

    /// The kernel id of the thread that runs the validation episodes, once
    /// it has started.
    #[cfg(test)]
    fn worker_thread(&self) -> Option<i64> {
        self.progress.worker.get().copied()
    }

    /// Whether the policy after `done` of `last` episodes is to be validated.
    pub fn due(&self, done: usize, last: usize) -> bool {
        validation_due(self.last_submitted, done, last, self.every)
    }

    /// Hands a snapshot over for validation as the policy after
    /// `meta.episode` episodes. Never blocks.
    pub fn submit(&mut self, snapshot: Arc<PolicySnapshot>, meta: CheckpointMeta) {
        self.last_submitted = Some(meta.episode);
        if let Some(jobs) = &self.jobs {
            // Counted before it is sent, so the thread never counts it down
            // first. A closed channel means the thread failed: `finish`
            // reports it.
            self.progress.pending.fetch_add(1, Ordering::Relaxed);
            if jobs.send(Job { snapshot, meta }).is_err() {
                self.progress.pending.fetch_sub(1, Ordering::Relaxed);
            }
        }
    }

    /// The choice so far (validations still queued are not in it).
    pub fn chosen(&self) -> Chosen {
        self.chosen.lock().unwrap_or_else(|poisoned| poisoned.into_inner()).clone()
    }

    /// Waits for every validation handed over, stops the thread and returns
    /// the final choice, or the error that stopped the thread.
    pub fn finish(&mut self) -> Result<Chosen, LearnerError> {
        drop(self.jobs.take());
        // Validation runs below training, so where cores were short it may
        // be behind: say how far, and how long the end waited for it.
        let (pending, started) = (self.progress.pending.load(Ordering::Relaxed), Instant::now());
        if let Some(thread) = self.thread.take() {
            thread.join().map_err(|_| LearnerError::Config("the validation thread panicked".into()))??;
        }
        if pending > 0 {
            tracing::info!(pending, waited_s = started.elapsed().as_secs_f64(), "the end of training waited for the validations still queued, and the confirmation");
        }
        Ok(self.chosen())
    }
}

fn validate_jobs(mut selection: Selection, env: Box<dyn Env>, run_dir: &Path, inbox: &mpsc::Receiver<Job>, chosen: &Mutex<Chosen>, progress: Arc<Progress>) -> Result<(), LearnerError> {
    // One thread, below training: validation runs beside training and
    // the actors, and must not take their cores (`lcrl train` pauses for
    // it and validates on every core instead). In one measured PPO run on
    // 2 cores its episodes were 38% of the learner's CPU (docs/scaling.md);
    // at nice +10 they take mostly what training leaves, and since each
    // validates a snapshot, in a run that is not interrupted when it runs
    // changes nothing it chooses. Only the pool's worker is lowered: this
    // thread also starts the confirmation on the global pool at the end,
    // whose workers would inherit its value.
    let worker = progress.clone();
    let pool = rayon::ThreadPoolBuilder::new()
        .num_threads(1)
        .thread_name(|_| "validation-worker".into())
        .start_handler(move |_| {
            super::priority::lower_this_thread("validation");
            let _ = worker.worker.set(super::priority::this_thread_id());
        })
        .build()
        .map_err(|e| LearnerError::Config(format!("cannot start the validation thread pool: {e}")))?;
    for job in inbox {
        progress.pending.fetch_sub(1, Ordering::Relaxed);
        let before = selection.record().map(|r| r.episode);
        let (_, selected) = pool.install(|| selection.validate_policy(env.as_ref(), &job.snapshot, run_dir, &job.meta))?;
        let moved = if selected {
            Some(Some(job.snapshot))
        } else if selection.record().map(|r| r.episode) != before {
            // A resumed run whose confirmation had chosen another policy
            // goes back to the best validation, which RUN/selected/ now holds.
            Some(read_selected(run_dir)?.map(Arc::new))
        } else {
            None
        };
        publish(chosen, &selection, moved);
    }
    // The inbox closes when training has ended (`Validator::finish`): the
    // confirmation has every core of the global pool to itself.
    let moved = if selection.confirm(env.as_ref(), run_dir)? { Some(read_selected(run_dir)?.map(Arc::new)) } else { None };
    publish(chosen, &selection, moved);
    Ok(())
}

/// Shows the selection's record to the training thread and, when the
/// choice moved to another policy, that policy's snapshot.
fn publish(chosen: &Mutex<Chosen>, selection: &Selection, moved: Option<Option<Arc<PolicySnapshot>>>) {
    let mut chosen = chosen.lock().unwrap_or_else(|poisoned| poisoned.into_inner());
    chosen.record = selection.record();
    if let Some(snapshot) = moved {
        chosen.snapshot = snapshot;
    }
}

/// The snapshot of the policy in RUN/selected/, if there is one (a resumed
/// run serves it if nothing better comes).
fn read_selected(run_dir: &Path) -> Result<Option<PolicySnapshot>, LearnerError> {
    let dir: PathBuf = selected_dir(run_dir);
    if !dir.join("checkpoint.json").is_file() {
        return Ok(None);
    }
    crate::policy::snapshot::read_snapshot(&dir).map(Some)
}

#[cfg(test)]
mod tests {
    use std::time::Duration;

    use lcrl_proto::v1::EpisodeSummary;
    use rand::{Rng, SeedableRng};
    use tokio::sync::mpsc as queue;

    use super::*;
    use crate::policy::checkpoint::latest_checkpoint;
    use crate::run::selection::read_record;
    use crate::config::{Algo, Connection, TrainConfig};
    use crate::service::ingest::{Accepted, AgentTransition, Ingest};
    use crate::service::runtime::{Schedule, TrainingLoop};
    use crate::policy::snapshot::snapshot;
    use crate::service::shared::{Command, Shared};

    /// The same 60 batches (2 episodes of 10 steps each) through the
    /// training thread, with or without validation every 2 episodes,
    /// publishing every `publish_every` updates; the final actor's weights
    /// and, with validation, the selection.
    fn train(dir: &Path, validate: bool, publish_every: u64) -> (Vec<u8>, Option<SelectionRecord>, u64) {
        tch::set_num_threads(1);
        let mut cfg = TrainConfig::for_env("lti-paper").0;
        cfg.network.global_hidden = vec![16];
        cfg.network.critic_hidden = vec![16];
        cfg.ddpg.warmup_steps = 40;
        cfg.ddpg.batch_size = 16;
        // Many updates a turn: the training thread runs one train_step per turn.
        cfg.ddpg.gradient_steps = 25;
        cfg.run.validation_episodes = if validate { 4 } else { 0 };
        cfg.run.validate_every = 2;
        // A constant noise: exploration changes (and publishes) only when
        // the warm-up ends, so `publish_every` alone says when the rest do.
        cfg.ddpg.noise_end = cfg.ddpg.noise_start;
        let mask = vec![vec![1u8; 3]; 3];
        let agent = crate::algo::algorithms::make_agent(Algo::Ddpg, Connection::Global, &cfg, &mask, 3, 3).unwrap();
        let meta = CheckpointMeta::start("lti-paper", Algo::Ddpg, Connection::Global, 3, 3, mask, cfg.clone());
        let architecture = meta.architecture();
        let first = snapshot(agent.as_ref(), &architecture, 0).unwrap();
        let ingest = Ingest::new("r", lcrl_sim::make_env("lti-paper").unwrap(), None);
        let shared = Arc::new(Shared::new("r", architecture, first, ingest, dir.to_path_buf(), Default::default()));
        let selection = Selection::new(&cfg.run, dir, false).unwrap();
        let validator = selection.map(|s| Validator::start(s, lcrl_sim::make_env("lti-paper").unwrap(), dir, cfg.run.validate_every, shared.validations_pending.clone()).unwrap());
        let (commands, inbox) = queue::channel(128);
        let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(9);
        let mut row = |n: usize| (0..n).map(|_| rng.random_range(-1.0f32..1.0)).collect::<Vec<_>>();
        for _ in 0..60 {
            let transitions = (0..20)
                .map(|k| AgentTransition { obs: row(3), action: row(3), log_prob: None, reward: -1.0, next_obs: row(3), terminated: false, truncated: k % 10 == 9, cut: false, policy_version: 0 })
                .collect();
            let episodes = vec![EpisodeSummary { episode_return: -10.0, length: 10, ..Default::default() }; 2];
            commands.try_send(Command::Batch(Accepted { transitions, episodes, policy_version: 0, stream: 0 })).unwrap();
        }
        commands.try_send(Command::Stop).unwrap();
        let schedule = Schedule {
            publish_every,
            checkpoint_interval: Duration::from_secs(3600),
            run_dir: dir.to_path_buf(),
            meta,
            train: true,
            max_staleness: None,
            budget_episodes: Some(120),
            limiter: None,
            validator,
            headroom: None,
        };
        TrainingLoop::new(agent, inbox, shared.clone(), schedule).run().unwrap();
        // The end waited for every validation handed over.
        assert_eq!(shared.validations_pending.load(std::sync::atomic::Ordering::Relaxed), 0);
        let last = latest_checkpoint(dir).unwrap();
        let updates = shared.updates.load(std::sync::atomic::Ordering::Relaxed);
        (std::fs::read(last.join("actor.safetensors")).unwrap(), read_record(&selected_dir(dir)).unwrap(), updates)
    }

    /// The validation episodes run below training (nice +10 over the
    /// thread that started the validator, at most 19), read back from
    /// /proc for the validator's own worker as any tool would see it; the
    /// starter keeps its own value.
    #[cfg(target_os = "linux")]
    #[test]
    fn validation_runs_below_training() {
        let starter = crate::service::priority::this_thread_nice();
        if starter >= 19 {
            eprintln!("skipped: the tests run at nice 19, no thread can run below them");
            return;
        }
        let dir = tempfile::tempdir().unwrap();
        let mut cfg = TrainConfig::for_env("lti-paper").0;
        cfg.run.validation_episodes = 2;
        let selection = Selection::new(&cfg.run, dir.path(), false).unwrap().expect("validation is on");
        let mut validator = Validator::start(selection, lcrl_sim::make_env("lti-paper").unwrap(), dir.path(), 2, Default::default()).unwrap();
        // The worker starts with the validation thread: wait for it, for a while.
        let deadline = std::time::Instant::now() + Duration::from_secs(10);
        let worker = loop {
            match validator.worker_thread() {
                Some(tid) => break tid,
                None if std::time::Instant::now() < deadline => std::thread::sleep(Duration::from_millis(10)),
                None => panic!("the validation worker did not start in 10 s"),
            }
        };
        let stat = std::fs::read_to_string(format!("/proc/self/task/{worker}/stat")).unwrap();
        // Field 19 of stat, the 17th after the command's ")".
        let nice: i32 = stat.rsplit_once(')').unwrap().1.split_whitespace().nth(16).unwrap().parse().unwrap();
        assert_eq!(nice, (starter + crate::service::priority::BELOW_TRAINING_NICE).min(19), "the validation worker's nice value");
        assert_eq!(crate::service::priority::this_thread_nice(), starter);
        validator.finish().unwrap();
    }

    /// Validation reads snapshots on its own thread: the training thread
    /// makes the same updates with and without it, and the validations
    /// follow `lcrl train`'s schedule (the start, every 2 episodes, the end).
    #[test]
    fn validation_does_not_change_what_is_trained() {
        let (with, without) = (tempfile::tempdir().unwrap(), tempfile::tempdir().unwrap());
        let (validated_weights, record, updates) = train(with.path(), true, 5);
        let (plain_weights, none, plain_updates) = train(without.path(), false, 5);
        assert!(updates >= 50, "training trained: {updates} updates");
        assert_eq!(updates, plain_updates);
        assert_eq!(validated_weights, plain_weights, "the same updates with and without validation");
        assert!(none.is_none());
        let record = record.expect("a selection");
        let episodes: Vec<usize> = record.history.iter().map(|v| v.episode).collect();
        // The starting policy, then one per turn of the training thread
        // (it stores several batches a turn, each past a multiple of 2),
        // and the last policy at the budget.
        assert_eq!((episodes.first(), episodes.last()), (Some(&0), Some(&120)), "{episodes:?}");
        assert!(episodes.len() >= 4 && episodes.windows(2).all(|w| w[0] < w[1]), "{episodes:?}");
        assert!(selected_dir(with.path()).join("actor.safetensors").is_file());
    }

    /// DDPG publishes every `publish_every` updates, so training can end
    /// between two versions (here it publishes only when the exploration
    /// changes): the learner publishes where training ended, and without
    /// validation serves that policy, whose version the final checkpoint
    /// records. Served any earlier version, summary.json would evaluate
    /// it apart from the last policy (`last_eval_return`).
    #[test]
    fn the_served_policy_is_the_one_training_ended_with() {
        let dir = tempfile::tempdir().unwrap();
        let (_, none, updates) = train(dir.path(), false, u64::MAX / 2);
        assert!(none.is_none() && updates >= 50, "{updates} updates");
        let summary: serde_json::Value = serde_json::from_str(&std::fs::read_to_string(dir.path().join("summary.json")).unwrap()).unwrap();
        let meta = crate::policy::checkpoint::read_meta(&latest_checkpoint(dir.path()).unwrap()).unwrap();
        assert_eq!(summary["served_version"].as_u64(), Some(meta.policy_version), "{summary}");
        assert_eq!(summary["policy_version"], summary["served_version"], "{summary}");
        assert!(summary.get("last_eval_return").is_none_or(serde_json::Value::is_null), "the served policy is not the last: {summary}");
    }
}
