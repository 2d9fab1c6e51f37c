//! The LCRL learner (docs/method.md §5): networks, DDPG and PPO, the replay
//! buffer, checkpoints, and a single-process training loop. Everything is a
//! plain Rust type that tests call directly; the distributed runtime
//! ([`service`]) wraps them.
//!
//! The crate is six rooms; a room imports only the rooms listed below it
//! (arrows point down, docs/architecture.md):
//!
//! - [`service`]: the distributed learner (`lcrl-learner`): ingestion, training thread, gRPC, shared memory.
//! - [`run`]: a training run and its records: how it starts, the single-process loop, metrics.csv, summary.json, TensorBoard, the policy chosen on held-out starts.
//! - [`policy`]: a trained actor stored, sent and served: architecture, action map, checkpoints, snapshots, the loaded policy.
//! - [`algo`]: networks, the algorithm interface, DDPG and PPO, Adam, the replay buffer and its rate limiter, exploration, the LQR ceiling.
//! - [`device`]: the libtorch device (CUDA loaded at run time), intra-op threads, CUDA graphs.
//! - [`config`]: every hyperparameter, from one TOML file; imports no other room.

pub mod algo;
pub mod config;
pub mod device;
pub mod policy;
pub mod run;
pub mod service;

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
    /// A checkpoint not written because a weight is NaN or ∞: training
    /// diverged where no update guard runs (PPO, captured CUDA graphs).
    /// The run goes on to its summary; the last finite checkpoint stays.
    #[error("checkpoint not written: {0}")]
    Diverged(String),
    #[error("{0}")]
    Mismatch(String),
}

/// `map_err` for an I/O error on `path`: the error names the file.
pub(crate) fn io(path: &Path) -> impl FnOnce(std::io::Error) -> LearnerError + '_ {
    move |source| LearnerError::Io { path: path.to_path_buf(), source }
}
