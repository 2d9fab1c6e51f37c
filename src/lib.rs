//! The `lcrl` command line's own library: what several commands share,
//! and what tests call without starting a process.
//!
//! - [`connection`]: what a connection names (local@T, graph:PATH, random@K, …).
//! - [`preset`]: a preset (configs/*.toml) and its command lines for the
//!   graph builder, the learner and the actors.
//! - [`run_security`]: TLS and the token as every process's flags.
//! - [`binaries`]: the workspace binaries and the Python a command starts.
//! - [`supervise`]: child processes that stop when dropped, health waits.
//! - [`run_summary`]: `lcrl run`'s summary.json, its learner's with the run's actors and wall time.
//! - [`plots`]: the PNG figures.
//! - [`experiment`]: `lcrl experiment`, a study of many runs.
//! - [`export`]: `lcrl export`, a trained policy as one TorchScript or ONNX file.
//! - [`output`]: writing result files.
//! - [`recorded_env`]: a file's recorded environment, followed only when safe.
//! - [`local_run`]: `lcrl run`, graph builder, learner and actors as child processes.
//! - [`train`]: `lcrl train`, a run in this process.

pub mod binaries;
pub mod connection;
pub mod experiment;
pub mod export;
pub mod local_run;
pub mod output;
pub mod plots;
pub mod preset;
pub mod recorded_env;
pub mod run_security;
pub mod run_summary;
pub mod supervise;
pub mod train;
