//! The learner's Prometheus metrics (served by lcrl-proto's
//! `metrics_http`, as the actors' are).
//!
//! The learner's counters already live in [`Shared`] (they feed `GetStatus`
//! too), so [`LearnerCollector`] reads them at scrape time instead of
//! keeping a second set in step. Only the `Policy.Act` latency histogram is
//! a metric of its own.

use std::sync::atomic::Ordering;
use std::sync::Arc;

use prometheus_client::collector::Collector;
use prometheus_client::encoding::{DescriptorEncoder, EncodeMetric};
use prometheus_client::metrics::counter::ConstCounter;
use prometheus_client::metrics::gauge::ConstGauge;
use prometheus_client::metrics::histogram::{exponential_buckets, Histogram};
use prometheus_client::registry::Registry;
use tokio::sync::mpsc;

use super::shared::{Command, Shared};

/// Buckets of the `Policy.Act` latency histogram, seconds: 20 µs to ~42 ms
/// doubling, around the measured ~230 µs loopback median.
pub fn act_latency_histogram() -> Histogram {
    Histogram::new(exponential_buckets(20e-6, 2.0, 12))
}

/// The learner's registry: everything in `GetStatus`, the training queue's
/// depth and the `Policy.Act` latency.
pub fn learner_registry(shared: Arc<Shared>, queue: mpsc::Sender<Command>, act_latency: Histogram) -> Registry {
    let mut registry = Registry::with_prefix("lcrl_learner");
    registry.register("act_latency_seconds", "Policy.Act and ActBatch handling time (server side)", act_latency);
    registry.register_collector(Box::new(LearnerCollector { shared, queue }));
    registry
}

/// Reads the learner's shared counters at scrape time.
pub struct LearnerCollector {
    shared: Arc<Shared>,
    queue: mpsc::Sender<Command>,
}

impl std::fmt::Debug for LearnerCollector {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("LearnerCollector").field("run_id", &self.shared.run_id).finish_non_exhaustive()
    }
}

fn counter(encoder: &mut DescriptorEncoder, name: &str, help: &str, value: u64) -> Result<(), std::fmt::Error> {
    let metric = ConstCounter::new(value);
    metric.encode(encoder.encode_descriptor(name, help, None, metric.metric_type())?)
}

fn gauge(encoder: &mut DescriptorEncoder, name: &str, help: &str, value: i64) -> Result<(), std::fmt::Error> {
    let metric = ConstGauge::new(value);
    metric.encode(encoder.encode_descriptor(name, help, None, metric.metric_type())?)
}

impl Collector for LearnerCollector {
    fn encode(&self, mut encoder: DescriptorEncoder) -> Result<(), std::fmt::Error> {
        let s = &self.shared;
        counter(&mut encoder, "env_steps", "Environment steps stored (replay buffer or rollout)", s.env_steps.load(Ordering::Relaxed))?;
        counter(&mut encoder, "episodes", "Episodes reported by actors", s.episodes.load(Ordering::Relaxed))?;
        counter(&mut encoder, "updates", "Gradient updates", s.updates.load(Ordering::Relaxed))?;
        let flow = s.flow();
        let (lag_min, lag_mean, lag_max) = flow.lag.stats();
        counter(&mut encoder, "replay_sampled", "Transitions sampled by updates (DDPG minibatches)", flow.sampled())?;
        counter(&mut encoder, "replay_inserted", "Transitions inserted into the replay buffer or rollout", flow.inserted())?;
        counter(&mut encoder, "checkpoint_failures", "Checkpoints that failed to write (a full disk, say); training goes on and retries", flow.checkpoint_failures)?;
        counter(&mut encoder, "non_finite_policies", "Policies not published because a weight was NaN or infinite; actors keep the last finite one", flow.non_finite_policies)?;
        gauge(&mut encoder, "policy_lag_min", "Smallest policy lag of the last 1000 stored transitions (versions)", lag_min as i64)?;
        gauge(&mut encoder, "policy_lag_mean_milli", "Mean policy lag of the last 1000 stored transitions, in thousandths of a version", (lag_mean * 1000.0) as i64)?;
        gauge(&mut encoder, "policy_lag_max", "Largest policy lag of the last 1000 stored transitions (versions)", lag_max as i64)?;
        gauge(&mut encoder, "actors_waited_milliseconds", "Time the rate limiter held actors back (the learner was behind)", (flow.actors_waited_s * 1000.0) as i64)?;
        gauge(&mut encoder, "learner_waited_milliseconds", "Time the learner waited for data (actors were behind)", (flow.learner_waited_s * 1000.0) as i64)?;
        gauge(&mut encoder, "replay_size", "Transitions held (DDPG replay buffer, PPO rollout)", s.replay_size.load(Ordering::Relaxed) as i64)?;
        gauge(&mut encoder, "policy_version", "Newest published policy version", s.policy_version() as i64)?;
        gauge(&mut encoder, "connected_actors", "Actors with an open gRPC transition stream", i64::from(s.connected_actors.load(Ordering::Relaxed)))?;
        gauge(&mut encoder, "shm_actors", "Live shared-memory publishers (same-host actors)", i64::from(s.shm_actors.load(Ordering::Relaxed)))?;
        gauge(&mut encoder, "validations_pending", "Validations of the run's policy handed over and not yet started (they run below training and catch up where cores are free)", s.validations_pending.load(Ordering::Relaxed) as i64)?;
        let queued = self.queue.max_capacity() - self.queue.capacity();
        gauge(&mut encoder, "training_queue_depth", "Accepted batches waiting for the training thread", queued as i64)?;
        let (accepted, rejected) = s.ingest_counts();
        counter(&mut encoder, "transitions_accepted", "Transitions accepted by ingestion", accepted)?;
        let family = ConstCounter::new(0u64);
        let mut by_reason = encoder.encode_descriptor("transitions_rejected", "Transitions rejected or dropped, by reason", None, family.metric_type())?;
        for (reason, count) in rejected {
            ConstCounter::new(count).encode(by_reason.encode_family(&vec![("reason".to_string(), reason)])?)?;
        }
        drop(by_reason);
        let mut refused = encoder.encode_descriptor("unauthenticated", "Calls refused with UNAUTHENTICATED, by reason", None, family.metric_type())?;
        for (reason, count) in s.auth_refusals.counts() {
            ConstCounter::new(count).encode(refused.encode_family(&vec![("reason".to_string(), reason.to_string())])?)?;
        }
        drop(refused);
        let mut closed = encoder.encode_descriptor(
            "connections_refused",
            "Connections the server closed by its limits, by reason (connections: over --max-connections, none to evict; evicted: quiet, for a newcomer; idle: silent past --idle-timeout-secs)",
            None,
            family.metric_type(),
        )?;
        for (reason, count) in s.connection_refusals.counts() {
            ConstCounter::new(count).encode(closed.encode_family(&vec![("reason".to_string(), reason.to_string())])?)?;
        }
        Ok(())
    }
}
