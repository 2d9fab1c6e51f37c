//! The distributed learner: actors stream transitions in, the training
//! thread learns from them, and new policy versions go back out. The top
//! room of the crate, and the `lcrl-learner` binary's (main.rs) only user.
//!
//! May import: every other room ([`crate::run`], [`crate::policy`],
//! [`crate::algo`], [`crate::device`], [`crate::config`]); none imports it.
//!
//! - [`ingest`]: checks, deduplicates and normalizes batches (plain Rust).
//! - [`episode_sums`]: episode returns summed by the learner over an actor's batches.
//! - [`incarnation`]: the learner process's id, so restarts are noticed.
//! - [`shared`]: what the threads share (counters, the newest policy, ingestion, flow).
//! - [`launch`]: the learner process as a library function (`lcrl-learner` parses its arguments and calls it).
//! - [`runtime`]: the training thread ([`runtime::TrainingLoop`]: admit, train, publish).
//! - [`disk_full`]: the end of a run waits out a full disk.
//! - [`episodes`]: metrics.csv and TensorBoard records of actors' episodes.
//! - [`flow`]: replay ratio, waits, policy lag and the budget, as reported.
//! - [`server`]: the `lcrl.v1.Learner` and `lcrl.v1.Policy` gRPC handlers.
//! - [`serving_share`]: policy queries within their share of the time.
//! - [`priority`]: threads that must not take training's core run nicer.
//! - [`metrics`]: the learner's Prometheus metrics (served by `lcrl_runtime::metrics_http`).
//! - [`shm`]: the learner's ends of the same-host transport (its format: `lcrl_proto::shm`).
//! - [`validator`]: the run's policy chosen on held-out starts, on a thread of its own.
//! - [`watch_budget`]: the memory all `WatchPolicy` streams may hold together
//!   (a `lcrl_runtime::memory_budget`; requests take from
//!   `lcrl_runtime::request_budget`, as every server's do).
//! - [`idle`]: the learner's own threads asleep until something happens.

pub mod disk_full;
pub mod episode_sums;
pub mod episodes;
pub mod flow;
pub mod idle;
pub mod incarnation;
pub mod ingest;
pub mod launch;
pub mod metrics;
pub mod priority;
pub mod runtime;
pub mod server;
pub mod serving_share;
pub mod shared;
pub mod shm;
pub mod shm_turns;
pub mod validator;
pub mod watch_budget;

// Hostile input, property-tested: batches, shared-memory samples, snapshots.
#[cfg(test)]
mod hostile_tests;
