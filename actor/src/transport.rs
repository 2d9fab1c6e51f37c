//! How an actor talks to its learner: batches out and policies in, over
//! gRPC (any host) or iceoryx2 shared memory (same host). The rollout
//! itself ([`crate::worker`]) knows nothing of either.

use std::collections::VecDeque;
use std::sync::atomic::{AtomicBool, Ordering};
use std::sync::Arc;
use std::time::{Duration, Instant};

use anyhow::bail;
use lcrl_learner::policy::Policy;
use lcrl_proto::security::{AuthChannel, ClientSecurity};
use lcrl_proto::v1::learner_client::LearnerClient;
use lcrl_proto::v1::{PolicySnapshot, TransitionBatch, WatchPolicyRequest};
use tokio::sync::{mpsc, watch};
use tokio_stream::wrappers::ReceiverStream;
use tokio_stream::StreamExt;

use crate::metrics::ActorMetrics;
use crate::worker::Exploration;

/// Batches in flight or waiting: the bound on what an actor holds.
pub const MAX_PENDING_BATCHES: usize = 8;

/// Connects, retrying with backoff until `deadline`.
pub async fn connect(url: &str, security: &ClientSecurity, deadline: Duration) -> anyhow::Result<LearnerClient<AuthChannel>> {
    let give_up = Instant::now() + deadline;
    let mut delay = Duration::from_millis(100);
    loop {
        match security.connect(url).await {
            Ok(channel) => return Ok(LearnerClient::new(channel).max_decoding_message_size(16 << 20).max_encoding_message_size(16 << 20)),
            Err(e) if Instant::now() < give_up => {
                tracing::warn!("learner at {url} unreachable ({e}); retrying in {:.1} s", delay.as_secs_f64());
                tokio::time::sleep(delay).await;
                delay = (delay * 2).min(Duration::from_secs(5));
            }
            Err(e) => bail!("the learner at {url} stayed unreachable for {} s ({e}); is lcrl-learner running?", deadline.as_secs()),
        }
    }
}

/// Keeps `policy` at the learner's newest version, reconnecting forever.
pub async fn watch_policy(url: String, security: ClientSecurity, policy: watch::Sender<Arc<PolicySnapshot>>) {
    loop {
        let after = policy.borrow().version;
        let stream = async { LearnerClient::new(security.connect(&url).await?).max_decoding_message_size(16 << 20).watch_policy(WatchPolicyRequest { after_version: after }).await.map_err(anyhow::Error::from) };
        match stream.await {
            Ok(response) => {
                let mut updates = response.into_inner();
                while let Some(Ok(snapshot)) = updates.next().await {
                    if snapshot.version > policy.borrow().version {
                        policy.send_replace(Arc::new(snapshot));
                    }
                }
            }
            Err(e) => tracing::debug!("policy watch: {e}"),
        }
        tokio::time::sleep(Duration::from_millis(500)).await;
    }
}

/// Streams batches to the learner; resends unacknowledged ones after a
/// reconnect (the learner drops duplicates). Returns when the worker is done
/// and every batch is acknowledged, or fails after `deadline` without a
/// learner.
pub async fn send_batches(url: String, security: ClientSecurity, mut client: LearnerClient<AuthChannel>, mut batches: mpsc::Receiver<TransitionBatch>, deadline: Duration, metrics: ActorMetrics) -> anyhow::Result<()> {
    let mut pending: VecDeque<TransitionBatch> = VecDeque::new();
    let mut worker_done = false;
    loop {
        let (requests, request_rx) = mpsc::channel::<TransitionBatch>(MAX_PENDING_BATCHES);
        for batch in &pending {
            let _ = requests.try_send(batch.clone());
        }
        let acks = match client.stream_transitions(ReceiverStream::new(request_rx)).await {
            Ok(response) => Some(response.into_inner()),
            Err(status) if status.code() == tonic::Code::Unauthenticated => return Err(refused(status)),
            Err(status) => {
                tracing::warn!("cannot stream to the learner: {status}");
                None
            }
        };
        if let Some(mut acks) = acks {
            loop {
                if worker_done && pending.is_empty() {
                    return Ok(());
                }
                tokio::select! {
                    batch = batches.recv(), if !worker_done && pending.len() < MAX_PENDING_BATCHES => match batch {
                        Some(batch) => {
                            pending.push_back(batch.clone());
                            metrics.pending_batches.set(pending.len() as i64);
                            if requests.send(batch).await.is_err() {
                                break;
                            }
                        }
                        None => worker_done = true,
                    },
                    ack = acks.next() => match ack {
                        Some(Ok(ack)) => {
                            pending.retain(|b| b.sequence > ack.sequence);
                            metrics.pending_batches.set(pending.len() as i64);
                            if ack.outcome != "stored" {
                                tracing::debug!(sequence = ack.sequence, outcome = %ack.outcome, "batch not stored");
                            }
                        }
                        Some(Err(status)) if status.code() == tonic::Code::InvalidArgument => {
                            // The learner will never take this batch; drop it and go on.
                            tracing::error!("the learner rejected a batch: {}", status.message());
                            pending.pop_front();
                            break;
                        }
                        Some(Err(status)) if status.code() == tonic::Code::Unauthenticated => return Err(refused(status)),
                        Some(Err(status)) => {
                            tracing::warn!("lost the learner: {status}");
                            break;
                        }
                        None => break,
                    },
                }
            }
        }
        if worker_done && pending.is_empty() {
            return Ok(());
        }
        client = connect(&url, &security, deadline).await?;
        metrics.reconnects.inc();
    }
}

/// A refusal as an error that says what to do (a wrong token never heals,
/// so the actor stops instead of retrying).
pub fn refused(status: tonic::Status) -> anyhow::Error {
    match status.code() {
        tonic::Code::Unauthenticated => anyhow::anyhow!("the learner refused this actor: {} (give the learner's token with --token-file or LCRL_TOKEN_FILE)", status.message()),
        _ => anyhow::anyhow!("{status}"),
    }
}

/// Where the worker's policy comes from.
pub enum PolicySource {
    /// Kept current by the WatchPolicy task.
    Grpc(watch::Receiver<Arc<PolicySnapshot>>),
    /// The run's shared-memory broadcast; wait at most this long for it.
    Shm(String, Duration),
}

/// The worker thread's open end of its policy source.
pub enum Feed {
    Grpc(watch::Receiver<Arc<PolicySnapshot>>),
    Shm(lcrl_learner::service::shm::PolicySubscriber),
}

/// Opens the source and returns it with the first policy.
pub fn open_feed(source: PolicySource, stop: &AtomicBool) -> anyhow::Result<(Feed, Policy, Exploration)> {
    match source {
        PolicySource::Grpc(mut rx) => {
            let snapshot = rx.borrow_and_update().clone();
            let policy = Policy::from_snapshot(&snapshot.architecture, &snapshot.weights, snapshot.version)?;
            Ok((Feed::Grpc(rx), policy, Exploration::of(&snapshot)))
        }
        PolicySource::Shm(run_id, deadline) => {
            let subscriber = lcrl_learner::service::shm::PolicySubscriber::open(&run_id).map_err(anyhow::Error::msg)?;
            let started = Instant::now();
            let mut last_log = Instant::now() - Duration::from_secs(10);
            loop {
                if let Some(snapshot) = subscriber.newest().map_err(anyhow::Error::msg)? {
                    tracing::info!(version = snapshot.version, "policy received over shared memory");
                    let policy = Policy::from_snapshot(&snapshot.architecture, &snapshot.weights, snapshot.version)?;
                    return Ok((Feed::Shm(subscriber), policy, Exploration::of(&snapshot)));
                }
                if stop.load(Ordering::Relaxed) {
                    bail!("stopped while waiting for the policy");
                }
                if started.elapsed() > deadline {
                    bail!("no policy of run '{run_id}' on shared memory within {} s; is lcrl-learner running on this host with --run-id {run_id}?", deadline.as_secs());
                }
                if last_log.elapsed() > Duration::from_secs(2) {
                    tracing::warn!("waiting for the policy of run '{run_id}' on shared memory; retrying");
                    last_log = Instant::now();
                }
                std::thread::sleep(Duration::from_millis(50));
            }
        }
    }
}

/// Where the worker's batches go.
pub enum Sink {
    /// To the gRPC sender task (bounded channel).
    Grpc(mpsc::Sender<TransitionBatch>),
    /// Straight into the run's shared-memory service.
    Shm(String),
}

/// The worker thread's open end of its sink.
pub enum Out {
    Grpc(mpsc::Sender<TransitionBatch>),
    Shm(lcrl_learner::service::shm::ShmPublisher),
}

impl Feed {
    /// Takes the newest policy version if there is one: updates `policy`
    /// in place and returns the version's exploration.
    pub fn poll(&mut self, policy: &mut Policy) -> anyhow::Result<Option<Exploration>> {
        match self {
            Feed::Grpc(rx) => {
                if rx.has_changed().unwrap_or(false) {
                    let newest = rx.borrow_and_update().clone();
                    policy.update(&newest.weights, newest.version)?;
                    return Ok(Some(Exploration::of(&newest)));
                }
            }
            Feed::Shm(subscriber) => {
                if let Some(newest) = subscriber.newest().map_err(anyhow::Error::msg)? {
                    if newest.version > policy.version {
                        policy.update(&newest.weights, newest.version)?;
                        return Ok(Some(Exploration::of(&newest)));
                    }
                }
            }
        }
        Ok(None)
    }
}

impl Sink {
    /// The worker thread's end (iceoryx2 ports stay on the thread that
    /// made them, so the shared-memory publisher is opened there).
    pub fn open(self) -> anyhow::Result<Out> {
        Ok(match self {
            Sink::Grpc(batches) => Out::Grpc(batches),
            Sink::Shm(run_id) => Out::Shm(lcrl_learner::service::shm::ShmPublisher::open(&run_id).map_err(anyhow::Error::msg)?),
        })
    }
}

impl Out {
    /// Hands a batch over, blocking while the learner is behind (bounded
    /// memory). False: the gRPC sender is gone (the actor is stopping).
    pub fn send(&self, batch: TransitionBatch) -> anyhow::Result<bool> {
        match self {
            Out::Shm(publisher) => publisher.send(&batch).map_err(anyhow::Error::msg).map(|()| true),
            Out::Grpc(batches) => Ok(batches.blocking_send(batch).is_ok()),
        }
    }
}
