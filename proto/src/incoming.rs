//! Accepted connections of a server: plain TCP, or TLS done here rather
//! than inside tonic, so that a failed handshake (plain text to a TLS port,
//! a client certificate of another CA) is counted like a wrong token.
//! Handshakes run concurrently and time out, so a slow or silent client
//! never holds up the others. At most `--max-connections` are served at
//! once, and a connection whose peer stays silent for the idle timeout is
//! closed (crate::limits): idle sockets cannot use up the server's files.

use std::future::Future;
use std::io;
use std::pin::Pin;
use std::sync::atomic::Ordering;
use std::sync::Arc;
use std::task::{Context, Poll};
use std::time::Duration;

use tokio::io::{AsyncRead, AsyncWrite, ReadBuf};
use tokio::net::{TcpListener, TcpStream};
use tokio::sync::{OwnedSemaphorePermit, Semaphore};
use tokio::time::{Instant, Sleep};
use tokio_rustls::rustls;
use tokio_rustls::server::TlsStream;
use tokio_rustls::TlsAcceptor;
use tokio_stream::wrappers::ReceiverStream;
use tonic::transport::server::{Connected, TcpConnectInfo};

use crate::limits::{ConnectionRefusals, ServerLimitsArgs, FIRST_BYTE_TIMEOUT};

/// How long a client may take to finish its TLS handshake.
const HANDSHAKE_TIMEOUT: Duration = Duration::from_secs(10);

/// The byte stream of one accepted connection.
enum Stream {
    Plain(TcpStream),
    Tls(Box<TlsStream<TcpStream>>),
}

/// One accepted connection: its stream, its place among the server's
/// `--max-connections` (given back when tonic drops it), and the idle
/// timer that closes it when the peer sends nothing.
pub struct Conn {
    stream: Stream,
    _permit: OwnedSemaphorePermit,
    idle: Pin<Box<Sleep>>,
    idle_timeout: Duration,
    refusals: Arc<ConnectionRefusals>,
}

impl Conn {
    fn new(stream: Stream, permit: OwnedSemaphorePermit, limits: &Limits) -> Conn {
        // Until the peer's first byte the shorter of the two timeouts.
        let first = limits.idle_timeout.min(FIRST_BYTE_TIMEOUT);
        Conn { stream, _permit: permit, idle: Box::pin(tokio::time::sleep(first)), idle_timeout: limits.idle_timeout, refusals: limits.refusals.clone() }
    }
}

impl Connected for Conn {
    type ConnectInfo = TcpConnectInfo;

    fn connect_info(&self) -> TcpConnectInfo {
        match &self.stream {
            Stream::Plain(s) => s.connect_info(),
            Stream::Tls(s) => s.get_ref().0.connect_info(),
        }
    }
}

impl AsyncRead for Conn {
    fn poll_read(self: Pin<&mut Self>, cx: &mut Context<'_>, buf: &mut ReadBuf<'_>) -> Poll<io::Result<()>> {
        let this = self.get_mut();
        let before = buf.filled().len();
        let read = match &mut this.stream {
            Stream::Plain(s) => Pin::new(s).poll_read(cx, buf),
            Stream::Tls(s) => Pin::new(s.as_mut()).poll_read(cx, buf),
        };
        match read {
            Poll::Ready(Ok(())) if buf.filled().len() > before => {
                // The peer spoke: the silence starts over.
                let next = Instant::now() + this.idle_timeout;
                this.idle.as_mut().reset(next);
                Poll::Ready(Ok(()))
            }
            Poll::Pending if this.idle.as_mut().poll(cx).is_ready() => {
                this.refusals.idle.fetch_add(1, Ordering::Relaxed);
                tracing::debug!("closing a connection silent for its idle timeout");
                Poll::Ready(Err(io::Error::new(io::ErrorKind::TimedOut, "the peer sent nothing within the idle timeout")))
            }
            other => other,
        }
    }
}

impl AsyncWrite for Conn {
    fn poll_write(self: Pin<&mut Self>, cx: &mut Context<'_>, buf: &[u8]) -> Poll<io::Result<usize>> {
        match &mut self.get_mut().stream {
            Stream::Plain(s) => Pin::new(s).poll_write(cx, buf),
            Stream::Tls(s) => Pin::new(s.as_mut()).poll_write(cx, buf),
        }
    }

    fn poll_flush(self: Pin<&mut Self>, cx: &mut Context<'_>) -> Poll<io::Result<()>> {
        match &mut self.get_mut().stream {
            Stream::Plain(s) => Pin::new(s).poll_flush(cx),
            Stream::Tls(s) => Pin::new(s.as_mut()).poll_flush(cx),
        }
    }

    fn poll_shutdown(self: Pin<&mut Self>, cx: &mut Context<'_>) -> Poll<io::Result<()>> {
        match &mut self.get_mut().stream {
            Stream::Plain(s) => Pin::new(s).poll_shutdown(cx),
            Stream::Tls(s) => Pin::new(s.as_mut()).poll_shutdown(cx),
        }
    }
}

/// What [`incoming`] holds a server's connections to.
#[derive(Clone)]
pub struct Limits {
    pub max_connections: usize,
    pub idle_timeout: Duration,
    pub refusals: Arc<ConnectionRefusals>,
}

impl Limits {
    pub fn new(args: &ServerLimitsArgs, refusals: Arc<ConnectionRefusals>) -> Limits {
        Limits { max_connections: args.max_connections as usize, idle_timeout: args.idle_timeout(), refusals }
    }
}

/// Called once per failed TLS handshake (the server counts them).
pub type OnRefusedHandshake = Arc<dyn Fn() + Send + Sync>;

/// Accepts connections on `listener` (TCP_NODELAY: small request and
/// response messages), completing TLS handshakes where `tls` is set and
/// reporting each failed one to `refused`, within `limits`.
pub fn incoming(listener: TcpListener, tls: Option<Arc<rustls::ServerConfig>>, refused: OnRefusedHandshake, limits: Limits) -> ReceiverStream<io::Result<Conn>> {
    let (tx, rx) = tokio::sync::mpsc::channel(64);
    let acceptor = tls.map(TlsAcceptor::from);
    let places = Arc::new(Semaphore::new(limits.max_connections));
    tokio::spawn(async move {
        loop {
            let (stream, peer) = match listener.accept().await {
                Ok(accepted) => accepted,
                Err(e) => {
                    // Out of file descriptors and the like: the next
                    // accept may succeed; a closed server ends the loop.
                    tracing::warn!("accept failed: {e}");
                    if tx.is_closed() {
                        break;
                    }
                    tokio::time::sleep(Duration::from_millis(50)).await;
                    continue;
                }
            };
            // Over the limit: closed at once (dropping it), counted, so a
            // flood of sockets costs a file for a moment, not for ever.
            let Ok(permit) = places.clone().try_acquire_owned() else {
                limits.refusals.over_limit.fetch_add(1, Ordering::Relaxed);
                tracing::debug!(%peer, "connection refused: --max-connections reached");
                continue;
            };
            let _ = stream.set_nodelay(true);
            match &acceptor {
                None => {
                    if tx.send(Ok(Conn::new(Stream::Plain(stream), permit, &limits))).await.is_err() {
                        break;
                    }
                }
                Some(acceptor) => {
                    let (acceptor, tx, refused, limits) = (acceptor.clone(), tx.clone(), refused.clone(), limits.clone());
                    tokio::spawn(async move {
                        match tokio::time::timeout(HANDSHAKE_TIMEOUT, acceptor.accept(stream)).await {
                            Ok(Ok(tls)) => {
                                let _ = tx.send(Ok(Conn::new(Stream::Tls(Box::new(tls)), permit, &limits))).await;
                            }
                            outcome => {
                                refused();
                                let why = match outcome {
                                    Ok(Err(e)) => e.to_string(),
                                    _ => "timed out".to_string(),
                                };
                                tracing::info!(%peer, "TLS handshake refused: {why}");
                            }
                        }
                    });
                }
            }
        }
    });
    ReceiverStream::new(rx)
}
