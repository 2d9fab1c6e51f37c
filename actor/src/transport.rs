//! How an actor talks to its learner: batches out and policies in, over
//! gRPC (any host) or iceoryx2 shared memory (same host). The rollout
//! itself ([`crate::worker`]) knows nothing of either.

use std::collections::VecDeque;
use std::sync::atomic::{AtomicBool, Ordering};
use std::sync::Arc;
use std::time::{Duration, Instant};

use anyhow::{bail, Context};
use lcrl_learner::policy::trained::Policy;
use lcrl_runtime::limits::Backoff;
use lcrl_runtime::security::{AuthChannel, ClientSecurity};
use lcrl_proto::v1::learner_client::LearnerClient;
use lcrl_proto::v1::{BatchAck, GetPolicyRequest, PolicySnapshot, TransitionBatch, WatchPolicyRequest};
use tokio::sync::{mpsc, watch};
use tokio_stream::wrappers::ReceiverStream;
use tokio_stream::StreamExt;

use crate::metrics::ActorMetrics;
use crate::worker::Exploration;

/// Batches in flight or waiting: the bound on what an actor holds.
pub const MAX_PENDING_BATCHES: usize = 8;

/// Malformed batches in a row after which an actor stops.
pub const REJECTIONS_TO_STOP: usize = 3;

/// Duplicate acknowledgements in a row before the actor says so: one may
/// be a resend after a broken stream, several mean another sender.
const DUPLICATES_TO_SAY: usize = 3;

/// Connects, retrying with exponential backoff and jitter until
/// `deadline` (every call on the channel has lcrl_runtime::limits' call
/// deadline and keepalive, so a learner that accepts and never answers
/// fails calls instead of hanging them).
pub async fn connect(url: &str, security: &ClientSecurity, deadline: Duration) -> anyhow::Result<LearnerClient<AuthChannel>> {
    // Far deadlines (--connect-deadline is at most a day) cannot overflow.
    let give_up = Instant::now().checked_add(deadline).unwrap_or_else(|| Instant::now() + Duration::from_secs(86_400));
    let mut backoff = Backoff::new(Duration::from_millis(100), Duration::from_secs(5));
    loop {
        match security.connect(url).await {
            Ok(channel) => return Ok(LearnerClient::new(channel).max_decoding_message_size(16 << 20).max_encoding_message_size(16 << 20)),
            Err(e) if Instant::now() < give_up => {
                let delay = backoff.next_delay();
                tracing::warn!("learner at {url} unreachable ({e}); retrying in {:.1} s", delay.as_secs_f64());
                tokio::time::sleep(delay).await;
            }
            Err(e) => bail!("the learner at {url} stayed unreachable for {} s ({e}); is lcrl-learner running?", deadline.as_secs()),
        }
    }
}

/// The learner's current policy, asked for until `deadline` (issue 71): a
/// learner that is still loading its checkpoint, or busy, answers
/// UNAVAILABLE or not in time, which is retried with backoff; a refusal
/// (token, certificate, run id) ends the actor at once, as it says what to
/// fix.
pub async fn first_policy(client: &mut LearnerClient<AuthChannel>, url: &str, deadline: Duration) -> anyhow::Result<PolicySnapshot> {
    let give_up = Instant::now().checked_add(deadline).unwrap_or_else(|| Instant::now() + Duration::from_secs(86_400));
    let mut backoff = Backoff::new(Duration::from_millis(100), Duration::from_secs(2));
    loop {
        match client.get_policy(GetPolicyRequest {}).await {
            Ok(response) => return Ok(response.into_inner()),
            Err(status) if is_fatal(&status) => return Err(refused(status)).context("asking the learner for its policy"),
            Err(status) if Instant::now() < give_up => {
                let delay = backoff.next_delay();
                tracing::warn!("the learner at {url} gave no policy yet ({}: {}); asking again in {:.1} s", status.code(), status.message(), delay.as_secs_f64());
                tokio::time::sleep(delay).await;
            }
            Err(status) => {
                return Err(refused(status)).with_context(|| format!("the learner at {url} gave no policy within --connect-deadline {} s", deadline.as_secs()));
            }
        }
    }
}

/// Whether `next` replaces `current` as the policy to act with: a newer
/// version of the same learner process, any version of another one (a
/// restarted learner counts versions from its checkpoint again), or the
/// news that training has finished.
pub fn supersedes(next: &PolicySnapshot, current: &PolicySnapshot) -> bool {
    next.incarnation != current.incarnation || next.version > current.version || (next.training_finished && !current.training_finished)
}

/// Keeps `policy` at the learner's newest version, reconnecting forever
/// (backoff with jitter; a stream that delivered starts the backoff over).
pub async fn watch_policy(url: String, security: ClientSecurity, policy: watch::Sender<Arc<PolicySnapshot>>, progress: Progress) {
    // At most a second between attempts: every second without the
    // watch is a second of acting with a policy that may be gone.
    let mut backoff = Backoff::new(Duration::from_millis(200), Duration::from_secs(1));
    loop {
        let request = { let current = policy.borrow(); WatchPolicyRequest { after_version: current.version, incarnation: current.incarnation } };
        let stream = async { LearnerClient::new(security.connect(&url).await?).max_decoding_message_size(16 << 20).watch_policy(request).await.map_err(anyhow::Error::from) };
        match stream.await {
            Ok(response) => {
                let mut updates = response.into_inner();
                while let Some(Ok(snapshot)) = updates.next().await {
                    progress.mark();
                    backoff = Backoff::new(Duration::from_millis(200), Duration::from_secs(1));
                    if supersedes(&snapshot, &policy.borrow()) {
                        if snapshot.incarnation != policy.borrow().incarnation {
                            tracing::info!(version = snapshot.version, incarnation = %format!("{:016x}", snapshot.incarnation), "the learner restarted: acting with its policy");
                        }
                        policy.send_replace(Arc::new(snapshot));
                    }
                }
            }
            // A learner whose WatchPolicy budget is spent: the actor acts
            // on its last policy meanwhile, which its operator should see.
            Err(e) if e.downcast_ref::<tonic::Status>().is_some_and(|s| s.code() == tonic::Code::ResourceExhausted) => tracing::warn!("policy watch refused, acting on policy v{} meanwhile: {e}", policy.borrow().version),
            Err(e) => tracing::debug!("policy watch: {e}"),
        }
        tokio::time::sleep(backoff.next_delay()).await;
    }
}

/// When the actor last heard from its learner (an acknowledged batch, a
/// policy): what its liveness endpoint reports, so an actor stuck on a
/// learner that stopped answering is restarted by its supervisor.
#[derive(Clone)]
pub struct Progress(Arc<std::sync::Mutex<Instant>>);

impl Default for Progress {
    fn default() -> Self {
        Progress(Arc::new(std::sync::Mutex::new(Instant::now())))
    }
}

impl Progress {
    pub fn mark(&self) {
        *self.0.lock().unwrap_or_else(|poisoned| poisoned.into_inner()) = Instant::now();
    }

    pub fn since(&self) -> Duration {
        self.0.lock().unwrap_or_else(|poisoned| poisoned.into_inner()).elapsed()
    }
}

/// What a gRPC sender holds: the learner (its URL, to reconnect to) and
/// how to reach it (credentials, the connection open now, how long a
/// reconnect may take), and what it reports to (the actor's counters, and
/// its liveness, marked on every acknowledgement).
pub struct BatchSender {
    pub learner: String,
    pub security: ClientSecurity,
    pub client: LearnerClient<AuthChannel>,
    pub deadline: Duration,
    pub metrics: ActorMetrics,
    pub progress: Progress,
}

/// Streams batches to the learner; resends unacknowledged ones after a
/// reconnect (the learner drops duplicates). Returns when the worker is done
/// and every batch is acknowledged, or fails after `deadline` without a
/// learner.
pub async fn send_batches(sender: BatchSender, mut batches: mpsc::Receiver<TransitionBatch>) -> anyhow::Result<()> {
    let BatchSender { learner, security, mut client, deadline, metrics, progress } = sender;
    let mut outbox = Outbox::new();
    loop {
        let (requests, request_rx) = mpsc::channel::<TransitionBatch>(MAX_PENDING_BATCHES);
        for batch in &outbox.pending {
            let _ = requests.try_send(batch.clone());
        }
        match client.stream_transitions(ReceiverStream::new(request_rx)).await {
            Ok(response) => outbox.stream(&requests, response.into_inner(), &mut batches, &metrics, &progress).await?,
            Err(status) if is_fatal(&status) => return Err(refused(status)),
            Err(status) => tracing::warn!("cannot stream to the learner: {status}"),
        }
        if outbox.done() {
            return Ok(());
        }
        tokio::time::sleep(outbox.reconnect.next_delay()).await;
        client = connect(&learner, &security, deadline).await?;
        metrics.reconnects.inc();
    }
}

/// What [`send_batches`] keeps from one stream to the next.
struct Outbox {
    /// Sent and not yet acknowledged, oldest first: resent on a new stream.
    pending: VecDeque<TransitionBatch>,
    /// The worker has closed its channel: no more batches will come.
    worker_done: bool,
    /// This process's key (TransitionBatch.actor_key): after a connection
    /// that broke unnoticed, the learner knows the new one for this actor's.
    actor_key: u64,
    /// Batches rejected as malformed since the last one stored: a few is a
    /// bad step (a non-finite number); many in a row is an actor that does
    /// not fit the run (another environment), which retrying cannot mend.
    rejected_in_a_row: usize,
    /// Batches the learner took as duplicates since the last one stored:
    /// another sender has used this actor id with later sequences.
    duplicates_in_a_row: usize,
    /// Between streams: a learner that ends every stream (full, restarting)
    /// is not hammered with reconnects.
    reconnect: Backoff,
}

impl Outbox {
    fn new() -> Self {
        Outbox {
            pending: VecDeque::new(),
            worker_done: false,
            actor_key: rand::random::<u64>().max(1),
            rejected_in_a_row: 0,
            duplicates_in_a_row: 0,
            reconnect: Backoff::new(Duration::from_millis(100), Duration::from_secs(5)),
        }
    }

    /// Every batch the worker will hand over is acknowledged.
    fn done(&self) -> bool {
        self.worker_done && self.pending.is_empty()
    }

    /// One stream: the worker's batches out (at most
    /// [`MAX_PENDING_BATCHES`] unacknowledged), acknowledgements in, until
    /// [`Outbox::done`] or the stream ends; an error for a refusal that
    /// retrying cannot mend.
    async fn stream(&mut self, requests: &mpsc::Sender<TransitionBatch>, mut acks: tonic::Streaming<BatchAck>, batches: &mut mpsc::Receiver<TransitionBatch>, metrics: &ActorMetrics, progress: &Progress) -> anyhow::Result<()> {
        loop {
            if self.done() {
                return Ok(());
            }
            tokio::select! {
                batch = batches.recv(), if !self.worker_done && self.pending.len() < MAX_PENDING_BATCHES => match batch {
                    Some(mut batch) => {
                        batch.actor_key = self.actor_key;
                        self.pending.push_back(batch.clone());
                        metrics.pending_batches.set(self.pending.len() as i64);
                        if requests.send(batch).await.is_err() {
                            return Ok(());
                        }
                    }
                    None => self.worker_done = true,
                },
                ack = acks.next() => match ack {
                    Some(Ok(ack)) => {
                        progress.mark();
                        self.rejected_in_a_row = 0;
                        // The learner answers: the next loss starts the
                        // backoff over.
                        self.reconnect = Backoff::new(Duration::from_millis(100), Duration::from_secs(5));
                        self.pending.retain(|b| b.sequence > ack.sequence);
                        metrics.pending_batches.set(self.pending.len() as i64);
                        if ack.outcome != "stored" {
                            tracing::debug!(sequence = ack.sequence, outcome = %ack.outcome, "batch not stored");
                        }
                        self.duplicates_in_a_row = if ack.outcome == "duplicate" { self.duplicates_in_a_row + 1 } else { 0 };
                        if self.duplicates_in_a_row == DUPLICATES_TO_SAY {
                            tracing::warn!(
                                "the learner took the last {DUPLICATES_TO_SAY} batches as duplicates and stored none: a sender has used this actor id with later sequences; \
                                 they pass within {} s, or give this actor another --actor-id",
                                lcrl_learner::service::ingest::SEQUENCE_AHEAD.as_secs()
                            );
                        }
                    }
                    Some(Err(status)) if status.code() == tonic::Code::InvalidArgument => {
                        // The learner will never take this batch; drop it and go on.
                        tracing::error!("the learner rejected a batch: {}", status.message());
                        self.pending.pop_front();
                        self.rejected_in_a_row += 1;
                        if self.rejected_in_a_row >= REJECTIONS_TO_STOP {
                            // A sequence ahead of the learner's clock is this
                            // host's clock running ahead, not a wrong environment.
                            let hint = if status.message().contains("ahead of this learner's clock") {
                                "this host's clock runs ahead of the learner's: keep the hosts' clocks within 10 s (NTP)"
                            } else {
                                "does this actor run the learner's environment?"
                            };
                            bail!("the learner rejected {} batches in a row, the last: {} ({hint})", self.rejected_in_a_row, status.message());
                        }
                        return Ok(());
                    }
                    Some(Err(status)) if is_fatal(&status) => return Err(refused(status)),
                    Some(Err(status)) => {
                        tracing::warn!("lost the learner: {status}");
                        return Ok(());
                    }
                    None => return Ok(()),
                },
            }
        }
    }
}

/// Refusals that retrying cannot mend: a wrong token or certificate, a
/// wrong run id, a batch too large for the learner. The actor stops with
/// what to fix instead of looping.
pub fn is_fatal(status: &tonic::Status) -> bool {
    use tonic::Code;
    matches!(status.code(), Code::Unauthenticated | Code::PermissionDenied | Code::FailedPrecondition | Code::OutOfRange)
        || (status.code() == Code::ResourceExhausted
            && (status.message().starts_with(lcrl_proto::codec::TOO_MANY_ENTRIES) || status.message().starts_with(lcrl_runtime::limits::TOO_LARGE)))
}

/// A refusal as an error that says what to do.
pub fn refused(status: tonic::Status) -> anyhow::Error {
    use tonic::Code;
    match status.code() {
        Code::Unauthenticated => anyhow::anyhow!("the learner refused this actor: {} (give the learner's token with --token-file or LCRL_TOKEN_FILE)", status.message()),
        Code::PermissionDenied => anyhow::anyhow!("the learner refused this actor: {} (its certificate is not one the learner accepts; see `lcrl certs`)", status.message()),
        Code::FailedPrecondition => anyhow::anyhow!("the learner refused this actor: {} (give the learner's run id with --run-id)", status.message()),
        Code::OutOfRange | Code::ResourceExhausted => anyhow::anyhow!("the learner refused a batch as too large: {} (lower --batch)", status.message()),
        Code::DeadlineExceeded | Code::Cancelled => anyhow::anyhow!("the learner did not answer within {} s: {} (is it overloaded or stuck? check its log)", lcrl_runtime::limits::CALL_TIMEOUT.as_secs(), status.message()),
        _ => anyhow::anyhow!("{status}"),
    }
}

/// Where the worker's policy comes from.
pub enum PolicySource {
    /// Kept current by the WatchPolicy task.
    Grpc(watch::Receiver<Arc<PolicySnapshot>>),
    /// The run's shared-memory broadcast, by its name (the run id, with a
    /// token's digest: ClientSecurity::shm_key); wait at most this long.
    Shm(String, Duration),
}

/// The worker thread's open end of its policy source, with the snapshot
/// whose policy it acts with now (`current`: not the newest received,
/// which may not be installed yet).
pub enum Feed {
    Grpc { rx: watch::Receiver<Arc<PolicySnapshot>>, current: Arc<PolicySnapshot> },
    /// The broadcast, and the snapshot acted with now.
    Shm { subscriber: lcrl_proto::shm::PolicySubscriber, current: PolicySnapshot },
}

/// Opens the source and returns it with the first policy.
pub fn open_feed(source: PolicySource, stop: &AtomicBool) -> anyhow::Result<(Feed, Policy, Exploration)> {
    match source {
        PolicySource::Grpc(mut rx) => {
            let snapshot = rx.borrow_and_update().clone();
            let policy = Policy::from_snapshot(&snapshot.architecture, &snapshot.weights, snapshot.version)?;
            let explore = Exploration::of(&snapshot);
            Ok((Feed::Grpc { rx, current: snapshot }, policy, explore))
        }
        PolicySource::Shm(key, deadline) => {
            let subscriber = lcrl_proto::shm::PolicySubscriber::open(&key).map_err(anyhow::Error::msg)?;
            let started = Instant::now();
            let mut last_log = Instant::now() - Duration::from_secs(10);
            loop {
                if let Some(snapshot) = subscriber.newest().map_err(anyhow::Error::msg)? {
                    tracing::info!(version = snapshot.version, "policy received over shared memory");
                    let policy = Policy::from_snapshot(&snapshot.architecture, &snapshot.weights, snapshot.version)?;
                    let explore = Exploration::of(&snapshot);
                    return Ok((Feed::Shm { subscriber, current: snapshot }, policy, explore));
                }
                if stop.load(Ordering::Relaxed) {
                    bail!("stopped while waiting for the policy");
                }
                if started.elapsed() > deadline {
                    bail!(
                        "no policy on shared memory under '{key}' within {} s; is lcrl-learner running on this host with this --run-id, and with the token this actor has \
                         (a learner with a token names its shared memory after it: give the actor the same --token-file)?",
                        deadline.as_secs()
                    );
                }
                if last_log.elapsed() > Duration::from_secs(2) {
                    tracing::warn!("waiting for the policy on shared memory under '{key}'; retrying");
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
    /// Straight into the run's shared-memory service, by its name (as
    /// [`PolicySource::Shm`]).
    Shm(String),
}

/// The worker thread's open end of its sink.
pub enum Out {
    Grpc(mpsc::Sender<TransitionBatch>),
    Shm(lcrl_proto::shm::ShmPublisher),
}

impl Feed {
    /// The incarnation of the learner whose policy the actor acts with
    /// (batches carry it).
    pub fn incarnation(&self) -> u64 {
        match self {
            Feed::Grpc { current, .. } => current.incarnation,
            Feed::Shm { current, .. } => current.incarnation,
        }
    }

    /// The learner said its episode budget is spent: the actor stops.
    pub fn training_finished(&self) -> bool {
        match self {
            Feed::Grpc { current, .. } => current.training_finished,
            Feed::Shm { current, .. } => current.training_finished,
        }
    }

    /// Takes the newest policy version if there is one: updates `policy`
    /// in place and returns the version's exploration.
    pub fn poll(&mut self, policy: &mut Policy) -> anyhow::Result<Option<Exploration>> {
        match self {
            Feed::Grpc { rx, current } => {
                if rx.has_changed().unwrap_or(false) {
                    let newest = rx.borrow_and_update().clone();
                    policy.update(&newest.weights, newest.version)?;
                    let explore = Exploration::of(&newest);
                    *current = newest;
                    return Ok(Some(explore));
                }
            }
            Feed::Shm { subscriber, current } => {
                if let Some(newest) = subscriber.newest().map_err(anyhow::Error::msg)? {
                    if supersedes(&newest, current) {
                        policy.update(&newest.weights, newest.version)?;
                        let explore = Exploration::of(&newest);
                        *current = newest;
                        return Ok(Some(explore));
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
            Sink::Shm(run_id) => Out::Shm(lcrl_proto::shm::ShmPublisher::open(&run_id).map_err(anyhow::Error::msg)?),
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
