//! What the learner's threads share: counters, the newest policy, ingestion
//! and the flow statistics. gRPC handlers, shared-memory subscribers,
//! `/metrics` and the training thread all go through the methods here; no
//! caller locks a mutex of its own.

use std::collections::VecDeque;
use std::path::PathBuf;
use std::sync::atomic::{AtomicU32, AtomicU64};
use std::sync::{Arc, Mutex};

use lcrl_proto::v1::PolicySnapshot;
use tokio::sync::watch;

use crate::config::{Algo, Connection};
use crate::service::flow::FlowStats;
use crate::service::ingest::{Accepted, Ingest};
use crate::policy::snapshot::Architecture;

/// What the handlers send to the training thread.
pub enum Command {
    Batch(Accepted),
    /// Checkpoint and stop (SIGTERM / Ctrl-C).
    Stop,
}

/// The policy `Policy.Act` serves once training has ended, and why.
#[derive(Debug, Clone)]
pub struct Served {
    pub snapshot: Arc<PolicySnapshot>,
    pub reason: String,
}

/// Counters and the newest policy, shared by handlers and the training thread.
pub struct Shared {
    pub run_id: String,
    /// The name of the run's shared memory: the run id, and with a token a
    /// digest of it (lcrl_runtime::security::shm_run_key).
    pub shm_key: String,
    pub algo: Algo,
    pub connection: Connection,
    pub architecture: Architecture,
    pub env_steps: AtomicU64,
    pub updates: AtomicU64,
    pub replay_size: AtomicU64,
    pub episodes: AtomicU64,
    pub connected_actors: AtomicU32,
    /// Live shared-memory publishers (same-host actors), as the shm thread
    /// last counted them; GetStatus adds them to the gRPC streams.
    pub shm_actors: AtomicU32,
    pub recent_returns: Mutex<VecDeque<f64>>,
    pub ingest: Mutex<Ingest>,
    pub policy: watch::Sender<Arc<PolicySnapshot>>,
    /// Set when training has ended: the policy served from then on (the
    /// selected one). Actors keep following `policy`.
    pub served: Mutex<Option<Served>>,
    /// Set when the learner shuts down: long-lived streams end then, so the
    /// server's graceful shutdown does not wait on them forever.
    pub shutdown: watch::Sender<bool>,
    /// Where metrics.csv goes.
    pub run_dir: PathBuf,
    /// Replay ratio, waits, policy lag and the budget.
    pub flow: Mutex<FlowStats>,
    /// Calls refused for a missing or wrong token (GetStatus, /metrics).
    pub auth_refusals: Arc<lcrl_runtime::security::AuthRefusals>,
    /// Connections the server closed by its limits (GetStatus, /metrics).
    pub connection_refusals: Arc<lcrl_runtime::limits::ConnectionRefusals>,
    /// This process's incarnation: a random non-zero id drawn at start,
    /// carried by every published policy (0 in tests that need none).
    pub incarnation: u64,
    /// libtorch's intra-op threads as the training thread itself reads
    /// them (0 until it starts): OpenMP keeps the count per thread, so the
    /// count set where the run starts must be set again there (GetStatus).
    pub training_threads: AtomicU32,
    /// Validations handed to the validation thread and not yet started
    /// (it runs below training, so where cores are short it falls behind;
    /// /metrics).
    pub validations_pending: Arc<AtomicU64>,
}

/// Locks `mutex` whatever happened to its last holder. The policy for a
/// poisoned lock (a thread panicked while holding it): the state behind
/// these locks is counters, maps of sequence numbers and recent returns,
/// each left whole between statements, so the learner keeps serving with
/// it rather than failing every later call; the panic itself is reported
/// where it happened.
fn lock<T>(mutex: &Mutex<T>) -> std::sync::MutexGuard<'_, T> {
    mutex.lock().unwrap_or_else(|poisoned| poisoned.into_inner())
}

impl Shared {
    /// A run's shared state with every counter at zero: `first` is the
    /// policy served until the training thread publishes, and algo and
    /// connection are the architecture's.
    pub fn new(
        run_id: &str,
        architecture: Architecture,
        first: PolicySnapshot,
        ingest: Ingest,
        run_dir: PathBuf,
        auth_refusals: Arc<lcrl_runtime::security::AuthRefusals>,
    ) -> Self {
        let first_incarnation = first.incarnation;
        Shared {
            run_id: run_id.to_string(),
            shm_key: run_id.to_string(),
            algo: architecture.shape.algo,
            connection: architecture.shape.connection,
            architecture,
            env_steps: AtomicU64::new(0),
            updates: AtomicU64::new(0),
            replay_size: AtomicU64::new(0),
            episodes: AtomicU64::new(0),
            connected_actors: AtomicU32::new(0),
            shm_actors: AtomicU32::new(0),
            recent_returns: Mutex::new(VecDeque::new()),
            ingest: Mutex::new(ingest),
            policy: watch::channel(Arc::new(first)).0,
            served: Mutex::new(None),
            shutdown: watch::channel(false).0,
            run_dir,
            flow: Mutex::new(Default::default()),
            auth_refusals,
            connection_refusals: Default::default(),
            incarnation: first_incarnation,
            training_threads: AtomicU32::new(0),
            validations_pending: Arc::new(AtomicU64::new(0)),
        }
    }

    /// Counts into `refusals` the connections the server closes.
    pub fn with_connection_refusals(mut self, refusals: Arc<lcrl_runtime::limits::ConnectionRefusals>) -> Self {
        self.connection_refusals = refusals;
        self
    }

    /// Ingestion's checks and counters (every transport goes through them).
    pub fn ingest(&self) -> std::sync::MutexGuard<'_, Ingest> {
        lock(&self.ingest)
    }

    /// Counts a stream or batch refused before ingestion could read it.
    pub fn record_rejection(&self, reason: &str) {
        self.ingest().refuse(reason);
    }

    /// Transitions accepted, and rejected by reason, so far.
    pub fn ingest_counts(&self) -> (u64, std::collections::BTreeMap<String, u64>) {
        let ingest = self.ingest();
        (ingest.accepted, ingest.rejected.clone())
    }

    /// The flow statistics, for the training thread to update.
    pub fn flow_mut(&self) -> std::sync::MutexGuard<'_, FlowStats> {
        lock(&self.flow)
    }

    pub fn policy_version(&self) -> u64 {
        self.policy.borrow().version
    }

    /// The policy `Policy.Act` serves and why: the newest during training,
    /// the one training ended with ([`Shared::serve`]) after.
    pub fn served(&self) -> Served {
        match lock(&self.served).as_ref() {
            Some(served) => served.clone(),
            None => Served { snapshot: self.policy.borrow().clone(), reason: "newest: training".into() },
        }
    }

    /// Serves `served` from now on (the end of training).
    pub fn serve(&self, served: Served) {
        tracing::info!(version = served.snapshot.version, reason = %served.reason, "serving");
        *lock(&self.served) = Some(served);
    }

    /// Resolves once shutdown has begun.
    pub fn stopping(&self) -> impl std::future::Future<Output = ()> + Send + 'static {
        let mut rx = self.shutdown.subscribe();
        async move {
            let _ = rx.wait_for(|stop| *stop).await;
        }
    }

    /// A copy of the flow statistics.
    pub fn flow(&self) -> FlowStats {
        self.flow_mut().clone()
    }

    pub fn recent_return(&self) -> f64 {
        let returns = lock(&self.recent_returns);
        if returns.is_empty() { 0.0 } else { returns.iter().sum::<f64>() / returns.len() as f64 }
    }

    /// Records finished episodes' returns (the newest 10 are kept).
    pub fn record_returns(&self, episodes: &[lcrl_proto::v1::EpisodeSummary]) {
        let mut returns = lock(&self.recent_returns);
        for episode in episodes {
            returns.push_back(episode.episode_return);
            while returns.len() > RECENT_RETURNS {
                returns.pop_front();
            }
        }
    }

    /// Counts `count` transitions refused for `reason` after ingestion
    /// accepted them (over the budget, stale when their turn came).
    pub fn record_dropped(&self, reason: &str, count: u64) {
        if count > 0 {
            *self.ingest().rejected.entry(reason.into()).or_insert(0) += count;
        }
    }
}

/// Episodes behind `recent_return` (GetStatus, the learner's summary).
const RECENT_RETURNS: usize = 10;

