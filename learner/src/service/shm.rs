//! The learner's ends of the same-host transport (the wire format and its
//! ports are lcrl-proto's shm.rs): a thread that receives transition
//! samples, checks them as gRPC batches are checked and hands them to the
//! training thread, and a thread that broadcasts every new policy version.

use std::collections::HashSet;
use std::sync::Arc;
use std::time::{Duration, Instant};

use lcrl_proto::shm::{remove_dead_nodes, service_name, PolicyPublisher, SubscriberError, TransitionSubscriber, PUBLISHER_STREAM};
use tokio::sync::mpsc;

use crate::service::ingest::{Origin, Verdict};
use crate::service::shared::{Command, Shared};
use crate::service::shm_turns::PublisherTurns;

/// The learner's end, on its own thread: receives samples, checks them like
/// gRPC batches and hands them to the training thread, until shutdown.
/// `buffer`: samples that may wait in shared memory (1 to
/// [`lcrl_proto::shm::SUBSCRIBER_MAX_BUFFER`]); each is policy lag.
/// `opened` is told whether the run's service opened (a live learner
/// already serving this run id refuses it: one learner a run).
pub fn run_subscriber(shared: Arc<Shared>, commands: mpsc::Sender<Command>, buffer: usize, opened: std::sync::mpsc::SyncSender<Result<(), SubscriberError>>) -> Result<(), String> {
    let cleaned = remove_dead_nodes();
    if cleaned > 0 {
        tracing::info!(cleaned, "removed shared-memory resources of crashed processes");
    }
    let subscriber = match TransitionSubscriber::open(&shared.shm_key, buffer) {
        Ok(subscriber) => subscriber,
        // The launcher reports a taken run id (and exits); shared memory
        // that is unavailable here is this thread's warning.
        Err(SubscriberError::RunTaken(id)) => {
            let _ = opened.send(Err(SubscriberError::RunTaken(id)));
            return Ok(());
        }
        Err(e) => {
            let _ = opened.send(Err(e.clone()));
            return Err(e.to_string());
        }
    };
    let _ = opened.send(Ok(()));
    tracing::info!(service = %service_name(&shared.shm_key), "shared-memory transport ready");
    let stop = shared.shutdown.subscribe();
    // Poll fast while data flows, back off to 2 ms when idle, and to 20 ms
    // after a second of nothing, so an idle learner does not keep a core
    // busy with wake-ups (iceoryx2's subscriber has no wake-up of its own;
    // the first batch after a pause waits at most 20 ms).
    let mut idle = Duration::from_micros(200);
    let mut last_batch = Instant::now();
    let mut turns = PublisherTurns::default();
    let (mut publishers_checked, mut live) = (Instant::now(), subscriber.live_publishers());
    while !*stop.borrow() {
        if publishers_checked.elapsed() >= PUBLISHER_CHECK {
            publishers_checked = Instant::now();
            live = publishers_now(&shared, &subscriber);
            turns.keep_live(&live);
        }
        // A round: every waiting actor's slots, served in turn.
        turns.fill(&subscriber, live.len().max(1) * (buffer + 2))?;
        let Some((mut batch, publisher)) = turns.next() else {
            std::thread::sleep(idle);
            let longest = if last_batch.elapsed() < Duration::from_secs(1) { Duration::from_millis(2) } else { IDLE_POLL_MAX };
            idle = (idle * 2).min(longest);
            continue;
        };
        (idle, last_batch) = (Duration::from_micros(200), Instant::now());
        // The service's name is the run's shared-memory key (the run id
        // and its token's digest): what arrives on it is of this run.
        batch.run_id.clone_from(&shared.run_id);
        let version = shared.policy_version();
        // An actor id is bound to the publisher that first sent it, as to a
        // gRPC stream (docs/reliability.md): another process on this host
        // cannot send under a live actor's id.
        let verdict = shared.ingest().check_from(&batch, version, Origin { stream: publisher, peer: None });
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

/// How often the subscriber looks for publishers that left.
const PUBLISHER_CHECK: Duration = Duration::from_secs(1);

/// The publishers attached now, after freeing the ids bound to those that
/// are gone (a restarted actor comes back under its id on a new
/// publisher). A crashed actor's publisher is listed until its dead node
/// is removed.
fn publishers_now(shared: &Shared, subscriber: &TransitionSubscriber) -> HashSet<u64> {
    if shared.ingest().holds_streams(is_publisher) {
        remove_dead_nodes();
    }
    let live = subscriber.live_publishers();
    shared.ingest().release_streams(|stream| is_publisher(stream) && !live.contains(&stream));
    shared.shm_actors.store(live.len() as u32, std::sync::atomic::Ordering::Relaxed);
    live
}

fn is_publisher(stream: u64) -> bool {
    stream & PUBLISHER_STREAM != 0
}

/// The learner's policy broadcaster, on its own thread: publishes every new
/// version of `shared.policy` until shutdown.
pub fn run_policy_publisher(shared: Arc<Shared>) -> Result<(), String> {
    let publisher = PolicyPublisher::open(&shared.shm_key)?;
    let mut versions = shared.policy.subscribe();
    let stop = shared.shutdown.subscribe();
    tracing::info!(service = %format!("lcrl/{}/policy", shared.shm_key), "shared-memory policy broadcast ready");
    let mut first = true;
    while !*stop.borrow() {
        if !first && !versions.has_changed().unwrap_or(false) {
            if let Err(e) = publisher.update_connections() {
                tracing::debug!("updating shared-memory connections: {e}");
            }
            // Asleep until the next version, with a look at new
            // subscribers and the shutdown flag every 100 ms. `changed`
            // marks the version seen, so a new one is published at once,
            // not left to `has_changed` (which would no longer see it).
            match crate::service::idle::wait_for(Duration::from_millis(100), versions.changed()) {
                Some(Ok(())) => {}
                Some(Err(_)) => {
                    std::thread::sleep(Duration::from_millis(100)); // the policy's sender is gone: shutting down
                    continue;
                }
                None => continue,
            }
        }
        first = false;
        let snapshot = versions.borrow_and_update().clone();
        publisher.publish(&snapshot)?;
        tracing::debug!(version = snapshot.version, bytes = snapshot.weights.len(), "policy broadcast on shared memory");
    }
    Ok(())
}

/// The longest pause of an idle shared-memory subscriber between looks.
const IDLE_POLL_MAX: Duration = Duration::from_millis(20);
