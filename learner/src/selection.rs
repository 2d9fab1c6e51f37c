//! Choosing the run's policy on held-out starts.
//!
//! A run's last policy is one draw from the sequence of policies training
//! went through, and on the peg tasks a DDPG draw now and then pushes too
//! hard from a few starts and fails them (docs/peg.md, "Choosing the
//! run's policy"). Model selection on held-out starts is the standard
//! remedy: at the start, every `run.validate_every` episodes and at the end,
//! the deterministic policy runs `run.validation_episodes` starts from the
//! run's own validation range (`lcrl_sim::seeds::validation`, disjoint from
//! training and from every evaluation), and the run's policy is the best one
//! seen. The starting policy is a candidate too: with a base controller it
//! is the base itself, so a run never hands over less than its base did on
//! these starts. The evaluation that reports the run never sees them.
//!
//! `RUN/selected/` holds the choice (checkpoint.json and actor.safetensors,
//! which `Policy::load` reads, and selection.json with every validation).
//! It is replaced whole whenever a better policy is found, so an
//! interrupted run resumes its selection. Training is untouched: the
//! checkpoints under `RUN/checkpoints/` go on from the last policy, and the
//! validation episodes run in an environment of their own.

use std::path::{Path, PathBuf};

use lcrl_proto::v1::PolicySnapshot;
use lcrl_sim::Env;

use crate::agent::Agent;
use crate::policy::evaluate_snapshot;
use crate::checkpoint::{write_folder, CheckpointMeta};
use crate::run_files::write_atomically;
use crate::config::RunConfig;
use crate::LearnerError;

// The records are run files (summary.json embeds them); selection.rs fills them.
pub use crate::run_files::{SelectionRecord, Validation};

/// The folder of a run's selected policy.
pub fn selected_dir(run_dir: &Path) -> PathBuf {
    run_dir.join("selected")
}

/// The running choice of a run's policy: every validation so far; the
/// choice is the first of the best among them.
pub struct Selection {
    run_seed: u64,
    starts: usize,
    every: usize,
    history: Vec<Validation>,
}

impl Selection {
    /// The selection `run` asks for (None when `validation_episodes` is 0).
    /// Resuming picks up RUN/selected/; a fresh run discards any left there.
    pub fn new(run: &RunConfig, run_dir: &Path, resume: bool) -> Result<Option<Selection>, LearnerError> {
        let dir = selected_dir(run_dir);
        if !resume && dir.exists() {
            std::fs::remove_dir_all(&dir).map_err(|source| LearnerError::Io { path: dir.clone(), source })?;
        }
        if run.validation_episodes == 0 {
            return Ok(None);
        }
        let record = if resume { read_record(&dir)? } else { None };
        if let Some(r) = &record {
            if r.starts != run.validation_episodes {
                return Err(LearnerError::Mismatch(format!(
                    "{} chose its policy on {} validation starts, but run.validation_episodes is {}; resume with the run's own setting",
                    dir.display(),
                    r.starts,
                    run.validation_episodes
                )));
            }
        }
        let history = record.map(|r| r.history).unwrap_or_default();
        Ok(Some(Selection { run_seed: run.seed, starts: run.validation_episodes, every: run.validate_every.max(1), history }))
    }

    /// Whether the policy after `done` episodes is validated: at the start,
    /// every `validate_every` episodes and at `last`, once each. Episodes
    /// may arrive several at a time (a distributed learner stores whole
    /// batches): a multiple of `validate_every` passed since the last
    /// validation counts as reached.
    pub fn due(&self, done: usize, last: usize) -> bool {
        validation_due(self.last_validated(), done, last, self.every)
    }

    /// The most recent validation, if any.
    pub fn last_validated(&self) -> Option<usize> {
        self.history.last().map(|v| v.episode)
    }

    /// The first validation's mean return: the starting policy's (with a
    /// base controller, the base's own), the fallback rule's reference.
    pub fn first_return(&self) -> Option<f64> {
        self.history.first().map(|v| v.mean_return)
    }

    /// Every validation so far: (episodes done, mean return).
    pub fn validations(&self) -> Vec<(usize, f64)> {
        self.history.iter().map(|v| (v.episode, v.mean_return)).collect()
    }

    /// The chosen validation: the best mean return, the earliest of equals.
    fn best(&self) -> Option<&Validation> {
        self.history.iter().fold(None, |best: Option<&Validation>, v| match best {
            Some(b) if b.mean_return >= v.mean_return => Some(b),
            _ => Some(v),
        })
    }

    /// Validates the agent's current policy; if it beats every earlier one
    /// (strictly: a tie keeps the earlier), it becomes RUN/selected/.
    pub fn validate(&mut self, env: &dyn Env, agent: &dyn Agent, run_dir: &Path, meta: &CheckpointMeta) -> Result<Validation, LearnerError> {
        let snapshot = crate::snapshot::snapshot(agent, &meta.architecture(), meta.policy_version)?;
        self.validate_policy(env, &snapshot, run_dir, meta).map(|(validation, _)| validation)
    }

    /// Validates the deterministic policy of `snapshot` as the policy after
    /// `meta.episode` episodes, its starts on every core of the current
    /// rayon pool; if it beats every earlier one, RUN/selected/ is replaced
    /// by `meta` and the snapshot's weights. Returns the validation and
    /// whether it was selected.
    pub fn validate_policy(&mut self, env: &dyn Env, snapshot: &PolicySnapshot, run_dir: &Path, meta: &CheckpointMeta) -> Result<(Validation, bool), LearnerError> {
        let _span = tracing::info_span!("validation", episode = meta.episode).entered();
        let first = lcrl_sim::seeds::validation(self.run_seed, 0);
        let (summary, _) = evaluate_snapshot(env, "validation", snapshot, self.starts, first, &|_| {})?;
        let validation = Validation { episode: meta.episode, mean_return: summary.mean_return, success_rate: summary.success_rate };
        let better = self.best().is_none_or(|best| validation.mean_return > best.mean_return);
        self.history.push(validation);
        if better {
            write_folder(&selected_dir(run_dir), meta, |staging| {
                let path = staging.join("actor.safetensors");
                std::fs::write(&path, &snapshot.weights).map_err(|source| LearnerError::Io { path, source })
            })?;
        }
        self.write_record(run_dir)?;
        tracing::info!(episode = validation.episode, mean_return = validation.mean_return, selected = better, "validated");
        Ok((validation, better))
    }

    /// The choice so far, with every validation.
    pub fn record(&self) -> Option<SelectionRecord> {
        self.best().map(|best| SelectionRecord {
            episode: best.episode,
            validation_return: best.mean_return,
            validation_success_rate: best.success_rate,
            starts: self.starts,
            history: self.history.clone(),
        })
    }

    fn write_record(&self, run_dir: &Path) -> Result<(), LearnerError> {
        let Some(record) = self.record() else { return Ok(()) };
        let path = selected_dir(run_dir).join("selection.json");
        let text = serde_json::to_string_pretty(&record).map_err(|e| LearnerError::Checkpoint(e.to_string()))?;
        write_atomically(&path, text.as_bytes())
    }
}

/// The validation schedule (see [`Selection::due`]): the first policy, then
/// the first policy at or past each multiple of `every`, and the last.
pub fn validation_due(last_validated: Option<usize>, done: usize, last: usize, every: usize) -> bool {
    let every = every.max(1);
    match last_validated {
        None => true,
        Some(v) if v >= done => false,
        Some(v) => done / every > v / every || done >= last,
    }
}

/// RUN/selected/selection.json, if the run has chosen a policy.
pub fn read_record(dir: &Path) -> Result<Option<SelectionRecord>, LearnerError> {
    let path = dir.join("selection.json");
    if !path.is_file() {
        return Ok(None);
    }
    let text = std::fs::read_to_string(&path).map_err(|source| LearnerError::Io { path: path.clone(), source })?;
    serde_json::from_str(&text).map(Some).map_err(|e| LearnerError::Checkpoint(format!("{}: {e}; delete RUN/selected to start the selection over", path.display())))
}
