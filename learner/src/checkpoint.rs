//! The checkpoint store of a run directory: `checkpoints/epNNNNNN/`, each
//! the agent's tensors (weights, optimizer state, replay) beside
//! `checkpoint.json` (this [`CheckpointMeta`]), written atomically, the
//! newest [`KEEP_CHECKPOINTS`] kept. `lcrl train` and the distributed
//! learner both write and resume from it.

use std::path::{Path, PathBuf};

use serde::{Deserialize, Serialize};

use crate::agent::Agent;
use crate::config::{Algo, Connection, TrainConfig};
use crate::snapshot::ActorShape;
use crate::{io, LearnerError};


/// Written next to the tensors of every checkpoint.
#[derive(Debug, Clone, Serialize, Deserialize)]
pub struct CheckpointMeta {
    /// Episodes completed when the checkpoint was written.
    pub episode: usize,
    #[serde(flatten)]
    pub shape: ActorShape,
    pub config: TrainConfig,
    pub graph_seconds: f64,
    pub optimization_seconds: f64,
    /// Wall time of the run so far (graph, set-up, training), seconds.
    pub elapsed_seconds: f64,
    /// Distributed runs: the policy version at the checkpoint.
    #[serde(default)]
    pub policy_version: u64,
    /// Distributed runs: the highest batch sequence stored per actor, so a
    /// restarted learner still rejects replayed batches.
    #[serde(default)]
    pub actor_sequences: std::collections::HashMap<String, u64>,
    /// Distributed DDPG runs: the replay-ratio limiter's settings and
    /// counters, so a restarted learner keeps the ratio.
    #[serde(default)]
    pub rate_limiter: Option<crate::rate_limiter::RateLimiter>,
}

impl CheckpointMeta {
    /// The metadata of a run at its start (episode 0, nothing timed, no
    /// distributed state): what every writer fills in from.
    #[allow(clippy::too_many_arguments)]
    pub fn start(env: &str, algo: Algo, connection: Connection, state_dim: usize, action_dim: usize, mask: Vec<Vec<u8>>, config: TrainConfig) -> Self {
        CheckpointMeta {
            episode: 0,
            shape: ActorShape { env: env.to_string(), algo, connection, state_dim, action_dim, mask },
            config,
            graph_seconds: 0.0,
            optimization_seconds: 0.0,
            elapsed_seconds: 0.0,
            policy_version: 0,
            actor_sequences: Default::default(),
            rate_limiter: None,
        }
    }

    /// The actor's architecture, as a published policy describes it.
    pub fn architecture(&self) -> crate::snapshot::Architecture {
        crate::snapshot::Architecture {
            shape: self.shape.clone(),
            network: self.config.network.clone(),
            base: self.config.base.base_action(self.shape.action_dim),
            residual_scale: self.config.residual_scale(self.shape.algo),
        }
    }
}

/// The newest complete checkpoint under `run_dir`, if any.
pub fn latest_checkpoint(run_dir: &Path) -> Option<PathBuf> {
    complete_checkpoints(&run_dir.join("checkpoints")).pop()
}

/// The complete checkpoints in `root`, oldest first: folders holding a
/// checkpoint.json, but not [`write_folder`]'s staging folders
/// (`.NAME.partial`), which a process killed while writing leaves behind
/// with a checkpoint.json that may be empty.
fn complete_checkpoints(root: &Path) -> Vec<PathBuf> {
    let Ok(entries) = std::fs::read_dir(root) else { return Vec::new() };
    let mut complete: Vec<PathBuf> = entries
        .filter_map(|e| e.ok().map(|e| e.path()))
        .filter(|p| !p.file_name().is_some_and(|n| n.to_string_lossy().starts_with('.')))
        .filter(|p| p.join("checkpoint.json").is_file())
        .collect();
    complete.sort();
    complete
}

pub fn read_meta(dir: &Path) -> Result<CheckpointMeta, LearnerError> {
    let path = dir.join("checkpoint.json");
    let text = std::fs::read_to_string(&path).map_err(io(&path))?;
    serde_json::from_str(&text).map_err(|e| LearnerError::Checkpoint(format!("{}: {e}", path.display())))
}

/// Writes a checkpoint atomically: into a temporary folder, then renamed.
pub fn write_checkpoint(run_dir: &Path, agent: &dyn Agent, meta: &CheckpointMeta) -> Result<PathBuf, LearnerError> {
    let root = run_dir.join("checkpoints");
    std::fs::create_dir_all(&root).map_err(io(&root))?;
    let target = root.join(format!("ep{:06}", meta.episode));
    write_folder(&target, meta, |staging| agent.save(staging, meta.config.run.save_replay))?;
    prune_checkpoints(&root, KEEP_CHECKPOINTS);
    Ok(target)
}

/// Writes the folder `target` whole or not at all: `fill` writes the
/// tensors into a staging folder beside it, `meta` goes in as
/// checkpoint.json, and the staging folder is renamed over `target`.
pub fn write_folder(target: &Path, meta: &CheckpointMeta, fill: impl FnOnce(&Path) -> Result<(), LearnerError>) -> Result<(), LearnerError> {
    let name = target.file_name().map(|n| n.to_string_lossy().into_owned()).unwrap_or_default();
    let staging = target.with_file_name(format!(".{name}.partial"));
    let _ = std::fs::remove_dir_all(&staging);
    std::fs::create_dir_all(&staging).map_err(io(&staging))?;
    fill(&staging)?;
    let text = serde_json::to_string_pretty(meta).map_err(|e| LearnerError::Checkpoint(e.to_string()))?;
    std::fs::write(staging.join("checkpoint.json"), text).map_err(io(&staging))?;
    if target.exists() {
        std::fs::remove_dir_all(target).map_err(io(target))?;
    }
    std::fs::rename(&staging, target).map_err(io(target))
}

/// Checkpoints kept per run: each can hold a replay buffer of hundreds of
/// megabytes, so only the newest few stay.
pub const KEEP_CHECKPOINTS: usize = 3;

/// Deletes all but the newest `keep` complete checkpoints.
fn prune_checkpoints(root: &Path, keep: usize) {
    let complete = complete_checkpoints(root);
    let excess = complete.len().saturating_sub(keep);
    for old in &complete[..excess] {
        if let Err(e) = std::fs::remove_dir_all(old) {
            tracing::warn!("cannot remove old checkpoint {}: {e}", old.display());
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// A process killed inside `write_folder` leaves its staging folder
    /// with an empty checkpoint.json (the e2e study killed with SIGKILL hit
    /// it): resuming must take the newest complete checkpoint, or none.
    #[test]
    fn a_staging_folder_left_by_a_kill_is_never_the_checkpoint() {
        let run = tempfile::tempdir().unwrap();
        let root = run.path().join("checkpoints");
        let staging = root.join(".ep000025.partial");
        std::fs::create_dir_all(&staging).unwrap();
        std::fs::write(staging.join("checkpoint.json"), "").unwrap();
        assert_eq!(latest_checkpoint(run.path()), None);
        for name in ["ep000010", "ep000020"] {
            std::fs::create_dir_all(root.join(name)).unwrap();
            std::fs::write(root.join(name).join("checkpoint.json"), "{}").unwrap();
        }
        std::fs::create_dir_all(root.join("ep000030")).unwrap(); // no checkpoint.json: not complete
        assert_eq!(latest_checkpoint(run.path()), Some(root.join("ep000020")));
        assert_eq!(complete_checkpoints(&root), vec![root.join("ep000010"), root.join("ep000020")]);
    }
}
