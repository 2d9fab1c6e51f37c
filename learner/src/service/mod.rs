//! The distributed learner: actors stream transitions in, the training
//! thread learns from them, and new policy versions go back out.
//!
//! - [`ingest`]: checks, deduplicates and normalizes batches (plain Rust).
//! - [`runtime`]: shared counters and the training thread.
//! - [`flow`]: replay ratio, waits, policy lag and the budget, as reported.
//! - [`server`]: the `lcrl.v1.Learner` and `lcrl.v1.Policy` gRPC handlers.
//! - [`metrics`]: Prometheus `/metrics` for learner and actors.
//! - [`shm`]: the same-host transport over iceoryx2 shared memory.

pub mod flow;
pub mod ingest;
pub mod metrics;
pub mod runtime;
pub mod server;
pub mod shm;
