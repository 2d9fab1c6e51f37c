//! The learner's ends of the same-host transport (the wire format and its
//! ports are lcrl-proto's shm.rs): a thread that receives transition
//! samples, checks them as gRPC batches are checked and hands them to the
//! training thread, and a thread that broadcasts every new policy version.

use std::sync::Arc;
use std::time::Duration;

use lcrl_proto::shm::{remove_dead_nodes, service_name, PolicyPublisher, TransitionSubscriber};
use tokio::sync::mpsc;

use crate::service::ingest::Verdict;
use crate::service::shared::{Command, Shared};

/// The learner's end, on its own thread: receives samples, checks them like
/// gRPC batches and hands them to the training thread, until shutdown.
/// `buffer`: samples that may wait in shared memory (1 to
/// [`lcrl_proto::shm::SUBSCRIBER_MAX_BUFFER`]); each is policy lag.
pub fn run_subscriber(shared: Arc<Shared>, commands: mpsc::Sender<Command>, buffer: usize) -> Result<(), String> {
    let cleaned = remove_dead_nodes();
    if cleaned > 0 {
        tracing::info!(cleaned, "removed shared-memory resources of crashed processes");
    }
    let subscriber = TransitionSubscriber::open(&shared.run_id, buffer)?;
    tracing::info!(service = %service_name(&shared.run_id), "shared-memory transport ready");
    let stop = shared.shutdown.subscribe();
    // Poll fast while data flows, back off to 2 ms when idle, so an idle
    // learner does not keep a core busy with wake-ups.
    let mut idle = Duration::from_micros(200);
    while !*stop.borrow() {
        let Some(batch) = subscriber.receive()? else {
            std::thread::sleep(idle);
            idle = (idle * 2).min(Duration::from_millis(2));
            continue;
        };
        idle = Duration::from_micros(200);
        let version = shared.policy_version();
        let verdict = shared.ingest().check(&batch, version);
        match verdict {
            Verdict::Accept(accepted) => {
                if commands.blocking_send(Command::Batch(accepted)).is_err() {
                    break;
                }
            }
            Verdict::Reject { reason, message } => tracing::warn!(reason, %message, "shared-memory batch rejected"),
            Verdict::Duplicate | Verdict::Stale => {}
        }
    }
    Ok(())
}

/// The learner's policy broadcaster, on its own thread: publishes every new
/// version of `shared.policy` until shutdown.
pub fn run_policy_publisher(shared: Arc<Shared>) -> Result<(), String> {
    let publisher = PolicyPublisher::open(&shared.run_id)?;
    let mut versions = shared.policy.subscribe();
    let stop = shared.shutdown.subscribe();
    tracing::info!(service = %format!("lcrl/{}/policy", shared.run_id), "shared-memory policy broadcast ready");
    let mut first = true;
    while !*stop.borrow() {
        if !first && !versions.has_changed().unwrap_or(false) {
            if let Err(e) = publisher.update_connections() {
                tracing::debug!("updating shared-memory connections: {e}");
            }
            std::thread::sleep(Duration::from_millis(5));
            continue;
        }
        first = false;
        let snapshot = versions.borrow_and_update().clone();
        publisher.publish(&snapshot)?;
        tracing::debug!(version = snapshot.version, bytes = snapshot.weights.len(), "policy broadcast on shared memory");
    }
    Ok(())
}
