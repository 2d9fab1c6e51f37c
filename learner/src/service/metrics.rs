//! Prometheus `/metrics` (OpenMetrics text format) for the learner and the
//! actors.
//!
//! The learner's counters already live in [`Shared`] (they feed `GetStatus`
//! too), so [`LearnerCollector`] reads them at scrape time instead of
//! keeping a second set in step. Only the `Policy.Act` latency histogram is
//! a metric of its own. Rendering is a plain function ([`render`]) that
//! tests call without a network; [`serve`] puts it on HTTP.

use std::future::Future;
use std::net::SocketAddr;
use std::sync::atomic::Ordering;
use std::sync::Arc;

use axum::response::IntoResponse;
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

/// The registry in the OpenMetrics text format.
pub fn render(registry: &Registry) -> Result<String, std::fmt::Error> {
    let mut text = String::new();
    prometheus_client::encoding::text::encode(&mut text, registry)?;
    Ok(text)
}

/// Serves `GET /metrics` on `listener` until `stop` resolves.
pub async fn serve(
    listener: tokio::net::TcpListener,
    registry: Arc<Registry>,
    stop: impl std::future::Future<Output = ()> + Send + 'static,
    live: impl Fn() -> Result<(), String> + Clone + Send + Sync + 'static,
) -> std::io::Result<()> {
    let app = axum::Router::new()
        // Liveness for a supervisor (Kubernetes' livenessProbe): 200 while
        // the process makes progress, 503 with the reason when it does not.
        .route(
            "/healthz",
            axum::routing::get(move || {
                let live = live.clone();
                async move {
                    match live() {
                        Ok(()) => (axum::http::StatusCode::OK, "ok\n".to_string()).into_response(),
                        Err(why) => (axum::http::StatusCode::SERVICE_UNAVAILABLE, format!("{why}\n")).into_response(),
                    }
                }
            }),
        )
        .route(
        "/metrics",
        axum::routing::get(move || {
            let registry = registry.clone();
            async move {
                match render(&registry) {
                    Ok(text) => ([(axum::http::header::CONTENT_TYPE, "application/openmetrics-text; version=1.0.0; charset=utf-8")], text).into_response(),
                    Err(_) => axum::http::StatusCode::INTERNAL_SERVER_ERROR.into_response(),
                }
            }
        }),
    );
    axum::serve(BoundedListener::new(listener), app).with_graceful_shutdown(stop).await
}

/// Connections the /metrics server holds at once; more are closed on
/// accept. 1,100 unfinished GETs once used up the learner's 1,024 files,
/// and with them its gRPC health, checkpoints and actors (issue 71).
pub const METRICS_MAX_CONNECTIONS: usize = 64;
/// How long a /metrics connection may live: a scrape takes milliseconds,
/// so a slow or silent client is closed here (a scraper that keeps its
/// connection alive reconnects).
pub const METRICS_CONNECTION_LIFETIME: std::time::Duration = std::time::Duration::from_secs(10);

/// The /metrics listener within its file budget: at most
/// [`METRICS_MAX_CONNECTIONS`] connections, each for at most
/// [`METRICS_CONNECTION_LIFETIME`].
pub struct BoundedListener {
    inner: tokio::net::TcpListener,
    places: Arc<tokio::sync::Semaphore>,
}

impl BoundedListener {
    pub fn new(inner: tokio::net::TcpListener) -> Self {
        BoundedListener { inner, places: Arc::new(tokio::sync::Semaphore::new(METRICS_MAX_CONNECTIONS)) }
    }
}

impl axum::serve::Listener for BoundedListener {
    type Io = BoundedStream;
    type Addr = SocketAddr;

    async fn accept(&mut self) -> (Self::Io, Self::Addr) {
        loop {
            let (stream, addr) = match self.inner.accept().await {
                Ok(accepted) => accepted,
                Err(e) => {
                    // Out of files and the like: the next accept may work.
                    tracing::warn!("metrics: accept failed: {e}");
                    tokio::time::sleep(std::time::Duration::from_millis(50)).await;
                    continue;
                }
            };
            match self.places.clone().try_acquire_owned() {
                Ok(permit) => return (BoundedStream { stream, _permit: permit, deadline: Box::pin(tokio::time::sleep(METRICS_CONNECTION_LIFETIME)) }, addr),
                Err(_) => tracing::debug!(%addr, "metrics: connection closed on accept, {METRICS_MAX_CONNECTIONS} are open"),
            }
        }
    }

    fn local_addr(&self) -> std::io::Result<Self::Addr> {
        self.inner.local_addr()
    }
}

/// A /metrics connection: its place, and the deadline that closes it.
pub struct BoundedStream {
    stream: tokio::net::TcpStream,
    _permit: tokio::sync::OwnedSemaphorePermit,
    deadline: std::pin::Pin<Box<tokio::time::Sleep>>,
}

impl tokio::io::AsyncRead for BoundedStream {
    fn poll_read(mut self: std::pin::Pin<&mut Self>, cx: &mut std::task::Context<'_>, buf: &mut tokio::io::ReadBuf<'_>) -> std::task::Poll<std::io::Result<()>> {
        if self.deadline.as_mut().poll(cx).is_ready() {
            return std::task::Poll::Ready(Err(std::io::Error::new(std::io::ErrorKind::TimedOut, "a /metrics connection lives at most 10 s")));
        }
        std::pin::Pin::new(&mut self.stream).poll_read(cx, buf)
    }
}

impl tokio::io::AsyncWrite for BoundedStream {
    fn poll_write(mut self: std::pin::Pin<&mut Self>, cx: &mut std::task::Context<'_>, buf: &[u8]) -> std::task::Poll<std::io::Result<usize>> {
        std::pin::Pin::new(&mut self.stream).poll_write(cx, buf)
    }

    fn poll_flush(mut self: std::pin::Pin<&mut Self>, cx: &mut std::task::Context<'_>) -> std::task::Poll<std::io::Result<()>> {
        std::pin::Pin::new(&mut self.stream).poll_flush(cx)
    }

    fn poll_shutdown(mut self: std::pin::Pin<&mut Self>, cx: &mut std::task::Context<'_>) -> std::task::Poll<std::io::Result<()>> {
        std::pin::Pin::new(&mut self.stream).poll_shutdown(cx)
    }
}

/// Binds the metrics address (a clear error when taken) and returns the
/// listener with the address actually bound (port 0 picks a free one).
pub async fn bind(addr: SocketAddr) -> Result<(tokio::net::TcpListener, SocketAddr), std::io::Error> {
    let listener = tokio::net::TcpListener::bind(addr).await?;
    let local = listener.local_addr()?;
    Ok((listener, local))
}

#[cfg(test)]
mod tests {
    use super::*;
    use tokio::io::{AsyncReadExt, AsyncWriteExt};

    async fn get(addr: SocketAddr) -> std::io::Result<String> {
        let mut client = tokio::net::TcpStream::connect(addr).await?;
        client.write_all(b"GET /healthz HTTP/1.1\r\nhost: x\r\nconnection: close\r\n\r\n").await?;
        let mut text = String::new();
        tokio::time::timeout(std::time::Duration::from_secs(5), client.read_to_string(&mut text)).await??;
        Ok(text)
    }

    /// Silent connections hold at most METRICS_MAX_CONNECTIONS files: the
    /// next is closed on accept, and a freed place serves again.
    #[tokio::test]
    async fn the_metrics_server_holds_a_bounded_number_of_connections() {
        let (listener, addr) = bind("127.0.0.1:0".parse().unwrap()).await.unwrap();
        let server = tokio::spawn(serve(listener, Arc::new(Registry::default()), std::future::pending(), || Ok(())));
        assert!(get(addr).await.unwrap().starts_with("HTTP/1.1 200"));
        let mut silent = Vec::new();
        for _ in 0..METRICS_MAX_CONNECTIONS {
            silent.push(tokio::net::TcpStream::connect(addr).await.unwrap());
        }
        // Accepted by the kernel, closed by the server: no answer.
        let refused = get(addr).await;
        assert!(refused.as_ref().map_or(true, String::is_empty), "{refused:?}");
        silent.pop();
        let mut served = None;
        for _ in 0..50 {
            match get(addr).await {
                Ok(text) if !text.is_empty() => {
                    served = Some(text);
                    break;
                }
                _ => tokio::time::sleep(std::time::Duration::from_millis(20)).await,
            }
        }
        assert!(served.is_some_and(|t| t.starts_with("HTTP/1.1 200")));
        server.abort();
    }
}
