//! The LCRL learner (docs/method.md §5): networks, DDPG and PPO, the replay
//! buffer, checkpoints, and a single-process training loop. Everything is a
//! plain Rust type that tests call directly; the distributed runtime
//! ([`service`]) wraps them.
//!
//! - [`config`]: every hyperparameter, from one TOML file.
//! - [`nets`]: locally connected (batched, masked), full-subnets and global actors; critics.
//! - [`action`]: normalized actions to the environment's box, around an optional base controller (residual RL).
//! - [`device`]: the libtorch device (CUDA loaded at run time) and intra-op threads.
//! - [`adam`]: Adam with savable state, over [`flat`] parameters (one buffer per network). [`replay`]: the replay buffer (mirrored on a GPU).
//! - [`rate_limiter`]: the replay-ratio limiter of the distributed learner (Reverb's semantics).
//! - [`agent`]: the algorithm interface and the state normalization; [`ddpg`] and [`ppo`] implement it, [`algorithms`] builds one by name.
//! - [`exploration`]: how a training action is sampled, for `lcrl train` and the actors alike.
//! - [`tensorboard`]: TensorBoard event files of a run.
//! - [`lqr`]: the LQR ceiling for linear environments.
//! - [`run_files`]: metrics.csv, the selection record and the one atomic writer, for both loops.
//! - [`summary`]: summary.json of every loop, and the one evaluation of a handed-over policy.
//! - [`checkpoint`]: the checkpoint store (atomic writes, newest kept, resume).
//! - [`run_start`]: how a run starts (`prepare`: the checkpoint to resume or the new settings, the mask, the base controller, the agent), for both loops.
//! - [`selection`]: the run's policy chosen on held-out validation starts.
//! - [`trainer`]: the single-process loop: episodes, metrics.csv, summary.json, resume.
//! - [`policy`]: a trained actor loaded from a checkpoint or a snapshot.
//! - [`architecture`]: what identifies an actor, held by snapshots and checkpoints alike.
//! - [`snapshot`]: a policy on the wire (architecture + safetensors weights).
//! - [`service`]: the distributed learner (`lcrl-learner`): ingestion, training thread, gRPC.

pub mod action;
pub mod adam;
pub mod agent;
pub mod algorithms;
pub mod architecture;
pub mod checkpoint;
pub mod config;
pub mod cuda_graph;
pub mod ddpg;
pub mod device;
pub mod exploration;
pub mod flat;
pub mod fallback;
pub mod lqr;
pub mod nets;
pub mod policy;
pub mod ppo;
pub mod rate_limiter;
pub mod replay;
pub mod run_files;
pub mod run_start;
pub mod selection;
pub mod service;
pub mod snapshot;
pub mod summary;
pub mod tensorboard;
pub mod trainer;

use std::path::{Path, PathBuf};

pub use config::{Algo, Connection, TrainConfig};

#[derive(Debug, thiserror::Error)]
pub enum LearnerError {
    #[error(transparent)]
    Env(#[from] lcrl_sim::EnvError),
    #[error(transparent)]
    Graph(#[from] lcrl_graph_builder::GraphError),
    #[error("training config: {0}")]
    Config(String),
    #[error("{path}: {source}")]
    Io { path: PathBuf, source: std::io::Error },
    #[error("checkpoint: {0}")]
    Checkpoint(String),
    #[error("{0}")]
    Mismatch(String),
}
#[cfg(test)]
mod tests;
#[cfg(test)]
mod hostile_tests;

/// `map_err` for an I/O error on `path`: the error names the file.
pub(crate) fn io(path: &Path) -> impl FnOnce(std::io::Error) -> LearnerError + '_ {
    move |source| LearnerError::Io { path: path.to_path_buf(), source }
}
