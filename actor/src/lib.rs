//! The LCRL actor (`lcrl-actor`): K simulators acting with the newest
//! policy and streaming their transitions to the learner.
//!
//! - [`worker`]: the K-environment rollout and batch assembly (no network).
//! - [`transport`]: batches out and policies in, over gRPC or shared memory.
//! - [`metrics`]: the actor's Prometheus counters.

pub mod metrics;
pub mod transport;
pub mod worker;
