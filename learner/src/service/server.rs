//! Thin gRPC handlers over [`Shared`] and the training thread's channel.

use std::pin::Pin;
use std::sync::atomic::Ordering;
use std::sync::{Arc, Mutex};

use lcrl_proto::v1::learner_server::Learner;
use lcrl_proto::v1::policy_server::Policy as PolicyApi;
use lcrl_proto::v1::{
    ActBatchRequest, ActBatchResponse, ActRequest, ActResponse, BatchAck, GetPolicyRequest, GetStatusRequest, LearnerStatus,
    PolicySnapshot, TransitionBatch, WatchPolicyRequest,
};
use lcrl_sim::Env;
use tokio::sync::mpsc;
use tokio_stream::wrappers::{ReceiverStream, WatchStream};
use tokio_stream::{Stream, StreamExt};
use tonic::{Request, Response, Status, Streaming};

use crate::policy::trained::Policy;
use crate::service::ingest::{Origin, Verdict};
use crate::service::serving_share::below_training;
use crate::service::shared::{Command, Shared};
use crate::service::watch_budget::WatchBudget;

type BoxStream<T> = Pin<Box<dyn Stream<Item = Result<T, Status>> + Send>>;

/// `lcrl.v1.Learner`.
pub struct LearnerService {
    pub shared: Arc<Shared>,
    pub commands: mpsc::Sender<Command>,
    pub watch_budget: WatchBudget,
    /// GetStatus calls per peer address (lcrl_runtime::peer_rate).
    pub status_rate: lcrl_runtime::peer_rate::PeerRate,
}

/// Counts a connected actor for as long as its stream lives, and frees
/// the actor ids its stream held when it ends.
struct Connected(Arc<Shared>, u64);

impl Drop for Connected {
    fn drop(&mut self) {
        self.0.connected_actors.fetch_sub(1, Ordering::Relaxed);
        self.0.ingest().release_stream(self.1);
    }
}

/// Numbers the learner's transition streams (0 is no stream).
static NEXT_STREAM: std::sync::atomic::AtomicU64 = std::sync::atomic::AtomicU64::new(1);

#[tonic::async_trait]
impl Learner for LearnerService {
    type StreamTransitionsStream = BoxStream<BatchAck>;
    type WatchPolicyStream = BoxStream<PolicySnapshot>;

    // long: one actor stream's life in one task: receive, refuse (with its status mapping), admit, acknowledge
    async fn stream_transitions(&self, request: Request<Streaming<TransitionBatch>>) -> Result<Response<Self::StreamTransitionsStream>, Status> {
        let origin = Origin { stream: NEXT_STREAM.fetch_add(1, Ordering::Relaxed), peer: request.remote_addr().map(|addr| addr.ip()) };
        let mut inbound = request.into_inner();
        let (acks, out) = mpsc::channel(16);
        let shared = self.shared.clone();
        let commands = self.commands.clone();
        let mut policy = shared.policy.subscribe();
        shared.connected_actors.fetch_add(1, Ordering::Relaxed);
        tokio::spawn(async move {
            let _connected = Connected(shared.clone(), origin.stream);
            let stopping = shared.stopping();
            tokio::pin!(stopping);
            loop {
                let batch = tokio::select! {
                    batch = inbound.next() => batch,
                    _ = &mut stopping => {
                        let _ = acks.send(Err(Status::unavailable("the learner is shutting down"))).await;
                        break;
                    }
                };
                let Some(batch) = batch else { break };
                let batch = match batch {
                    Ok(batch) => batch,
                    Err(status) => {
                        // A message over the size limit, or bytes that are no
                        // TransitionBatch: refused and counted; the stream ends.
                        let reason = match status.code() {
                            tonic::Code::ResourceExhausted if status.message().starts_with(lcrl_proto::codec::TOO_MANY_ENTRIES) => Some("too_many_entries"),
                            tonic::Code::ResourceExhausted if status.message().starts_with(lcrl_runtime::request_budget::BUDGET_SPENT) => Some("request_budget"),
                            tonic::Code::OutOfRange | tonic::Code::ResourceExhausted => Some("oversize"),
                            tonic::Code::Internal if status.message().contains("decode") => Some("undecodable"),
                            _ => None,
                        };
                        match reason {
                            Some(reason) => {
                                shared.record_rejection(reason);
                                tracing::warn!(reason, %status, "batch refused");
                                // tonic says OUT_OF_RANGE for a message over
                                // the limit; gRPC's code for it is
                                // RESOURCE_EXHAUSTED, what every refusal of
                                // size here answers.
                                let status = match reason {
                                    "oversize" => Status::resource_exhausted(format!(
                                        "{}: {} (this learner's --max-batch-bytes); send smaller batches (--batch)",
                                        lcrl_runtime::limits::TOO_LARGE,
                                        status.message()
                                    )),
                                    _ => status,
                                };
                                let _ = acks.send(Err(status)).await;
                            }
                            None => tracing::debug!(%status, "actor stream ended"),
                        }
                        break;
                    }
                };
                let span = tracing::debug_span!("batch", actor = %batch.actor_id, sequence = batch.sequence);
                let _entered = span.enter();
                let version = shared.policy_version();
                let verdict = shared.ingest().check_from(&batch, version, origin);
                let (stored, outcome) = match verdict {
                    Verdict::Accept(accepted) => match forward(&commands, accepted, &mut policy).await {
                        Some((stored, outcome)) => {
                            if outcome == "after_budget" {
                                // Counted as the training loop counts what it drops past the budget.
                                shared.record_dropped("after_budget", batch.transitions.len() as u64);
                            }
                            (stored, outcome)
                        }
                        None => {
                            let _ = acks.send(Err(Status::unavailable("the learner is shutting down"))).await;
                            break;
                        }
                    },
                    Verdict::Duplicate => (0, "duplicate"),
                    Verdict::Stale => (0, "stale"),
                    Verdict::Reject { reason, message } => {
                        tracing::warn!(reason, %message, "batch rejected");
                        let _ = acks.send(Err(rejection(reason, message))).await;
                        break;
                    }
                };
                let ack = BatchAck { sequence: batch.sequence, stored, outcome: outcome.into(), policy_version: shared.policy_version() };
                if acks.send(Ok(ack)).await.is_err() {
                    break;
                }
            }
        });
        Ok(Response::new(Box::pin(ReceiverStream::new(out))))
    }

    async fn get_policy(&self, _request: Request<GetPolicyRequest>) -> Result<Response<PolicySnapshot>, Status> {
        Ok(Response::new((**self.shared.policy.borrow()).clone()))
    }

    async fn watch_policy(&self, request: Request<WatchPolicyRequest>) -> Result<Response<Self::WatchPolicyStream>, Status> {
        let peer = request.remote_addr().map(|addr| addr.ip());
        let request = request.into_inner();
        let after = request.after_version;
        // A client that knew another process of this learner (it
        // restarted) gets the newest version whatever its number: versions
        // count from the checkpoint again.
        let other_incarnation = request.incarnation != 0 && request.incarnation != self.shared.incarnation;
        let place = self.watch_budget.admit(self.shared.policy.borrow().weights.len(), peer)?;
        let versions = WatchStream::new(self.shared.policy.subscribe()).filter(move |snapshot| {
            other_incarnation || snapshot.version > after || (after == 0 && snapshot.version == 0) || snapshot.training_finished
        });
        // Pulled, not pushed: the connection asks for the next message only
        // once it has room, so a reader that does not read holds the one
        // version it was sent, never a queue of them, and gets the newest
        // when it reads again. The weights are shared (a clone is a
        // count); the stream's place in the budget ends with it, and the
        // stream ends at shutdown.
        let versions = versions.map(move |snapshot| {
            let _place = &place;
            Some(Ok((*snapshot).clone()))
        });
        let stop = WatchStream::new(self.shared.shutdown.subscribe()).filter(|stopping| *stopping).map(|_| None);
        let stream = versions.merge(stop).take_while(Option::is_some).filter_map(|next| next);
        Ok(Response::new(Box::pin(stream)))
    }

    async fn get_status(&self, request: Request<GetStatusRequest>) -> Result<Response<LearnerStatus>, Status> {
        use lcrl_runtime::peer_rate::{STATUS_BURST, STATUS_PER_SECOND};
        if !self.status_rate.admit(request.remote_addr().map(|addr| addr.ip())) {
            return Err(Status::resource_exhausted(format!(
                "GetStatus takes {STATUS_PER_SECOND} calls a second from one peer address ({STATUS_BURST} at once); ask less often"
            )));
        }
        let s = &self.shared;
        let rejected = s.ingest_counts().1.into_iter().collect();
        let flow = s.flow();
        let lag = flow.lag.stats();
        let served = s.served();
        Ok(Response::new(LearnerStatus {
            run_id: s.run_id.clone(),
            algo: format!("{:?}", s.algo).to_lowercase(),
            connection: format!("{:?}", s.connection).to_lowercase(),
            episodes: s.episodes.load(Ordering::Relaxed),
            env_steps: s.env_steps.load(Ordering::Relaxed),
            updates: s.updates.load(Ordering::Relaxed),
            replay_size: s.replay_size.load(Ordering::Relaxed),
            policy_version: s.policy_version(),
            connected_actors: s.connected_actors.load(Ordering::Relaxed) + s.shm_actors.load(Ordering::Relaxed),
            rejected,
            recent_return: s.recent_return(),
            policy_lag_min: lag.0,
            policy_lag_mean: lag.1,
            policy_lag_max: lag.2,
            sampled: flow.sampled(),
            inserted: flow.inserted(),
            replay_ratio_target: flow.replay_ratio_target(),
            actors_waited_s: flow.actors_waited_s,
            learner_waited_s: flow.learner_waited_s,
            budget_episodes: flow.budget_episodes,
            finished: flow.finished,
            unauthenticated: s.auth_refusals.counts().into_iter().map(|(reason, n)| (reason.to_string(), n)).collect(),
            served_version: served.snapshot.version,
            served_reason: served.reason,
            incarnation: s.incarnation,
            training_threads: s.training_threads.load(Ordering::Relaxed),
            connections_refused: s.connection_refusals.counts().into_iter().map(|(reason, n)| (reason.to_string(), n)).collect(),
        }))
    }
}

/// Hands an accepted batch to the training loop: (transitions stored,
/// outcome), or None when the learner is shutting down. Once the budget is
/// spent the loop may be busy for long (its final checkpoint waits out a
/// full disk, issue 71): a batch waiting then is answered at once as
/// `after_budget`, unstored, so that no actor blocks on a finished run.
async fn forward(commands: &mpsc::Sender<Command>, accepted: crate::service::ingest::Accepted, policy: &mut tokio::sync::watch::Receiver<Arc<PolicySnapshot>>) -> Option<(u32, &'static str)> {
    let count = accepted.transitions.len();
    if policy.borrow().training_finished {
        return Some((0, "after_budget"));
    }
    tokio::select! {
        // Biased: a batch the loop takes is stored, never also answered
        // as after_budget (Sender::send is cancel-safe).
        biased;
        sent = commands.send(Command::Batch(accepted)) => sent.ok().map(|()| (count as u32, "stored")),
        Ok(_) = policy.wait_for(|p| p.training_finished) => Some((0, "after_budget")),
    }
}

/// A rejected batch's status: the actor can mend nothing by retrying a
/// batch of another run (its --run-id is wrong: FAILED_PRECONDITION), and
/// a full learner is RESOURCE_EXHAUSTED; the rest are malformed batches.
fn rejection(reason: &str, message: String) -> Status {
    match reason {
        "unknown_run" => Status::failed_precondition(message),
        "actors" | "actors_per_peer" => Status::resource_exhausted(message),
        // The id's stream may be one that died without a word: the actor
        // retries, and gets its id back once that stream is gone.
        "actor_id_bound" => Status::aborted(message),
        _ => Status::invalid_argument(message),
    }
}

/// `lcrl.v1.Policy`: the served policy (the newest during training, the
/// selected one after), rebuilt when another version is served.
pub struct PolicyService {
    pub shared: Arc<Shared>,
    pub env: Mutex<Box<dyn Env>>,
    pub serving: Mutex<Option<Policy>>,
    /// Handling time of Act/ActBatch, for `/metrics`.
    pub act_latency: prometheus_client::metrics::histogram::Histogram,
    /// States one ActBatch call may hold (`--max-act-batch`).
    pub max_act_batch: usize,
    /// Turns for Act and ActBatch computations (one at a time, within
    /// their share of the time).
    pub share: super::serving_share::ServingShare,
}

impl PolicyService {
    /// Runs `f` with the served policy (rebuilding it if another version is
    /// served now): the newest during training, the selected one after.
    fn with_policy<T>(&self, f: impl FnOnce(&Policy, &dyn Env) -> T) -> Result<(T, u64), Status> {
        let snapshot = self.shared.served().snapshot;
        let mut serving = self.serving.lock().map_err(|_| Status::internal("policy state poisoned"))?;
        let stale = serving.as_ref().is_none_or(|p| p.version != snapshot.version);
        if stale {
            let policy = Policy::from_snapshot(&snapshot.architecture, &snapshot.weights, snapshot.version)
                .map_err(|e| Status::internal(e.to_string()))?;
            *serving = Some(policy);
        }
        let policy = serving.as_ref().ok_or_else(|| Status::internal("no policy"))?;
        let env = self.env.lock().map_err(|_| Status::internal("environment state poisoned"))?;
        Ok((f(policy, env.as_ref()), snapshot.version))
    }

    fn check_states(&self, states: &[f32], count: usize) -> Result<usize, Status> {
        let m = self.shared.architecture.shape.state_dim;
        if count == 0 || states.len() != count * m {
            return Err(Status::invalid_argument(format!("expected {count} state(s) of {m} numbers, got {} numbers", states.len())));
        }
        if states.iter().any(|v| !v.is_finite()) {
            return Err(Status::invalid_argument("states must be finite"));
        }
        Ok(m)
    }
}

#[tonic::async_trait]
impl PolicyApi for PolicyService {
    #[tracing::instrument(skip_all, name = "Act")]
    async fn act(&self, request: Request<ActRequest>) -> Result<Response<ActResponse>, Status> {
        let started = std::time::Instant::now();
        let state = request.into_inner().state;
        self.check_states(&state, 1)?;
        let raw: Vec<f64> = state.iter().map(|&v| f64::from(v)).collect();
        // Waits for its turn without a thread, then computes off the event
        // loop (an ActBatch may be computing).
        let turn = self.share.turn().await?;
        let computed = tokio::task::block_in_place(|| below_training(|| self.with_policy(|policy, env| policy.act(env, &raw))));
        self.share.done(turn);
        let (action, version) = computed?;
        self.act_latency.observe(started.elapsed().as_secs_f64());
        Ok(Response::new(ActResponse { action: action.iter().map(|&a| a as f32).collect(), policy_version: version }))
    }

    #[tracing::instrument(skip_all, name = "ActBatch")]
    async fn act_batch(&self, request: Request<ActBatchRequest>) -> Result<Response<ActBatchResponse>, Status> {
        let started = std::time::Instant::now();
        let request = request.into_inner();
        if request.count as usize > self.max_act_batch {
            return Err(Status::invalid_argument(format!("{} states in one ActBatch; this learner takes at most {} (--max-act-batch): split the call", request.count, self.max_act_batch)));
        }
        let m = self.check_states(&request.states, request.count as usize)?;
        let turn = self.share.turn().await?;
        // Off the event loop: health checks and GetStatus stay answered
        // while a large batch computes.
        let computed = tokio::task::block_in_place(|| {
            below_training(|| {
                self.with_policy(|policy, env| {
                    request.states.chunks(m).flat_map(|row| {
                        let raw: Vec<f64> = row.iter().map(|&v| f64::from(v)).collect();
                        policy.act(env, &raw)
                    }).map(|a| a as f32).collect::<Vec<f32>>()
                })
            })
        });
        self.share.done(turn);
        let (actions, version) = computed?;
        self.act_latency.observe(started.elapsed().as_secs_f64());
        Ok(Response::new(ActBatchResponse { actions, policy_version: version }))
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::service::ingest::{Accepted, AgentTransition};
    use std::time::Duration;

    fn accepted(n: usize) -> Accepted {
        let t = AgentTransition { obs: vec![0.0; 3], action: vec![0.0; 3], log_prob: None, reward: -1.0, next_obs: vec![0.0; 3], terminated: false, truncated: false, cut: false, policy_version: 0 };
        Accepted { transitions: vec![t; n], episodes: Vec::new(), policy_version: 0, stream: 1 }
    }

    /// A batch waits for the training loop while the loop is busy; once
    /// the budget is spent it is answered at once, unstored, so an actor
    /// never blocks on a finished run (a full disk at the end, issue 71).
    #[tokio::test]
    async fn a_waiting_batch_is_answered_as_after_budget_once_the_budget_is_spent() {
        let (commands, mut loop_side) = mpsc::channel(1);
        let (policy_tx, mut policy) = tokio::sync::watch::channel(Arc::new(PolicySnapshot::default()));
        assert_eq!(forward(&commands, accepted(5), &mut policy).await, Some((5, "stored")));
        // The loop takes nothing more: the next batch waits ...
        let waiting = forward(&commands, accepted(7), &mut policy);
        tokio::pin!(waiting);
        assert!(tokio::time::timeout(Duration::from_millis(50), &mut waiting).await.is_err(), "a batch went past a full loop");
        // ... until the budget is spent.
        policy_tx.send_modify(|p| *p = Arc::new(PolicySnapshot { training_finished: true, ..PolicySnapshot::default() }));
        assert_eq!(waiting.await, Some((0, "after_budget")));
        // Once the budget is spent, a batch is answered so at once, even
        // with room in the loop's queue.
        let (room, _loop_with_room) = mpsc::channel(8);
        assert_eq!(forward(&room, accepted(2), &mut policy_tx.subscribe()).await, Some((0, "after_budget")));
        assert!(matches!(loop_side.recv().await, Some(Command::Batch(b)) if b.transitions.len() == 5));
        drop(loop_side);
        let (_finished_tx, mut running) = tokio::sync::watch::channel(Arc::new(PolicySnapshot::default()));
        assert_eq!(forward(&commands, accepted(1), &mut running).await, None, "a closed loop is a learner shutting down");
    }
}
