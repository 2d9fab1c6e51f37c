//! The actor's Prometheus metrics (served by `--metrics-listen`).

use prometheus_client::metrics::counter::Counter;
use prometheus_client::metrics::gauge::Gauge;
use prometheus_client::registry::Registry;
use std::sync::atomic::AtomicU64;

/// Counters the worker thread and the sender task update as they go.
/// Cloning shares the same counters.
#[derive(Debug, Clone, Default)]
pub struct ActorMetrics {
    pub env_steps: Counter,
    pub episodes: Counter,
    pub batches_sent: Counter,
    pub transitions_sent: Counter,
    pub reconnects: Counter,
    /// Episodes ended because the environment diverged (a non-finite or
    /// out-of-bounds state or reward, `lcrl_sim::diverged`): not sent.
    pub diverged_env: Counter,
    pub policy_version: Gauge,
    /// Batches handed to the sender and not yet acknowledged (gRPC).
    pub pending_batches: Gauge,
    /// Seconds the environment thread spent handing batches over: blocked
    /// while the learner held actors back (its queue full, or an on-policy
    /// learner updating). Over a window, its share of the wall time is the
    /// actor's idle share (`lcrl scale`).
    pub send_wait_seconds: Counter<f64, AtomicU64>,
    /// When the wait going on now began (milliseconds since the Unix
    /// epoch), 0 when none is: a reader adds the part of a long wait that
    /// `send_wait_seconds` does not hold yet.
    pub send_waiting_since_ms: Gauge,
}

impl ActorMetrics {
    pub fn registry(&self) -> Registry {
        let mut registry = Registry::with_prefix("lcrl_actor");
        registry.register("env_steps", "Environment steps taken", self.env_steps.clone());
        registry.register("episodes", "Episodes finished", self.episodes.clone());
        registry.register("batches_sent", "Transition batches handed to the transport", self.batches_sent.clone());
        registry.register("transitions_sent", "Transitions handed to the transport", self.transitions_sent.clone());
        registry.register("reconnects", "Reconnections to the learner after losing it", self.reconnects.clone());
        registry.register("diverged_env", "Episodes ended unsent because the environment diverged (non-finite or out-of-bounds state or reward)", self.diverged_env.clone());
        registry.register("policy_version", "Version of the policy acting now", self.policy_version.clone());
        registry.register("pending_batches", "Batches sent but not yet acknowledged by the learner (gRPC)", self.pending_batches.clone());
        registry.register("send_wait_seconds", "Seconds the environment thread waited to hand batches over (backpressure: the learner holding actors back, or the transport)", self.send_wait_seconds.clone());
        registry.register("send_waiting_since_ms", "When the wait to hand a batch over going on now began, ms since the Unix epoch; 0 when none is", self.send_waiting_since_ms.clone());
        registry
    }
}
