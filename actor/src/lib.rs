//! The LCRL actor (`lcrl-actor`): K simulators acting with the newest
//! policy and streaming their transitions to the learner.
//!
//! - [`process`]: the actor process (`lcrl-actor`'s flags and loop): the
//!   environment thread, the sender task, liveness, stopping.
//! - [`worker`]: the K-environment rollout and batch assembly (no network).
//! - [`transport`]: batches out and policies in, over gRPC or shared memory.
//! - [`metrics`]: the actor's Prometheus counters.

pub mod metrics;
pub mod process;
pub mod transport;
pub mod worker;
