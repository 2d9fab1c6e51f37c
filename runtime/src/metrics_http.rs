//! The HTTP side of Prometheus `/metrics` (OpenMetrics text format) and
//! `/healthz`, for the learner and the actors alike: a registry rendered
//! by a plain function ([`render`], which tests call without a network)
//! and served ([`serve`]) within a file budget of its own. What a registry
//! holds is each process's: the learner's collector is in lcrl-learner's
//! service/metrics.rs.

use std::future::Future;
use std::net::SocketAddr;
use std::sync::Arc;

use axum::response::IntoResponse;
use prometheus_client::registry::Registry;

use crate::peer_rate::{PeerRate, METRICS_BURST, METRICS_PER_SECOND};

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
    // Scrapes per peer address (issue 82: a flood cost training more than
    // a CPU hog did); /healthz is never limited.
    let rate = Arc::new(PeerRate::new(METRICS_PER_SECOND, METRICS_BURST));
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
        axum::routing::get(move |axum::extract::ConnectInfo(Peer(peer)): axum::extract::ConnectInfo<Peer>| {
            let (registry, rate) = (registry.clone(), rate.clone());
            async move {
                if !rate.admit(Some(peer.ip())) {
                    let why = format!("/metrics takes {METRICS_PER_SECOND} scrapes a second from one peer address ({METRICS_BURST} at once)\n");
                    return (axum::http::StatusCode::TOO_MANY_REQUESTS, why).into_response();
                }
                match render(&registry) {
                    Ok(text) => ([(axum::http::header::CONTENT_TYPE, "application/openmetrics-text; version=1.0.0; charset=utf-8")], text).into_response(),
                    Err(_) => axum::http::StatusCode::INTERNAL_SERVER_ERROR.into_response(),
                }
            }
        }),
    );
    axum::serve(BoundedListener::new(listener), app.into_make_service_with_connect_info::<Peer>()).with_graceful_shutdown(stop).await
}

/// The address a /metrics request came from (axum's ConnectInfo).
#[derive(Debug, Clone, Copy)]
pub struct Peer(pub SocketAddr);

impl axum::extract::connect_info::Connected<axum::serve::IncomingStream<'_, BoundedListener>> for Peer {
    fn connect_info(stream: axum::serve::IncomingStream<'_, BoundedListener>) -> Self {
        Peer(*stream.remote_addr())
    }
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
