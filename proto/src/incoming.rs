//! Accepted connections of a server: plain TCP, or TLS done here rather
//! than inside tonic, so that a failed handshake (plain text to a TLS port,
//! a client certificate of another CA) is counted like a wrong token.
//! Handshakes run concurrently and time out, so a slow or silent client
//! never holds up the others. At most `--max-connections` are served at
//! once, and a connection whose peer stays silent for the idle timeout is
//! closed (crate::limits): idle sockets cannot use up the server's files.
//! When the server is full, a newcomer takes the place of the connection
//! heard from least recently among those that never spoke (no byte after
//! TCP and TLS) or have been quiet for [`QUIET_TO_EVICT`]: a flood of
//! sockets, silent or only answering pings, cannot keep a health check or
//! an actor out, while connections in use are never closed for it.

use std::future::Future;
use std::io;
use std::pin::Pin;
use std::collections::VecDeque;
use std::sync::atomic::{AtomicBool, Ordering};
use std::sync::{Arc, Mutex};
use std::task::{Context, Poll, Waker};
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

/// How long a connection that spoke must have been quiet before a
/// newcomer may take its place on a full server. Live clients are pinged
/// every 15 s and answer within milliseconds, so one that is quiet this
/// long is at most answering pings; one in use sends much more often.
pub const QUIET_TO_EVICT: Duration = Duration::from_secs(5);

/// Whether an accepted connection has spoken yet and when it was last
/// heard, and the server's word that it must make room (set by
/// [`Registry::evict`]).
#[derive(Default)]
struct Hush {
    spoken: AtomicBool,
    /// Milliseconds from the registry's epoch to the last byte read (or
    /// to the accept).
    heard_ms: std::sync::atomic::AtomicU64,
    evicted: AtomicBool,
    /// Woken on eviction: the TLS handshake or the connection's reader.
    waker: Mutex<Option<Waker>>,
}

impl Hush {
    fn poll_evicted(&self, cx: &mut Context<'_>) -> Poll<()> {
        if self.evicted.load(Ordering::Acquire) {
            return Poll::Ready(());
        }
        let mut slot = self.waker.lock().unwrap_or_else(|p| p.into_inner());
        if !slot.as_ref().is_some_and(|w| w.will_wake(cx.waker())) {
            *slot = Some(cx.waker().clone());
        }
        drop(slot);
        // Evicted between the check and the registration: seen now.
        if self.evicted.load(Ordering::Acquire) {
            Poll::Ready(())
        } else {
            Poll::Pending
        }
    }

    fn evict(&self) {
        self.evicted.store(true, Ordering::Release);
        if let Some(waker) = self.waker.lock().unwrap_or_else(|p| p.into_inner()).take() {
            waker.wake();
        }
    }
}

/// The server's open connections (an entry whose connection closed holds
/// the only reference to its [`Hush`], and is dropped on the next sweep).
struct Registry {
    epoch: std::time::Instant,
    open: Mutex<VecDeque<Arc<Hush>>>,
}

impl Registry {
    fn new() -> Self {
        Registry { epoch: std::time::Instant::now(), open: Mutex::new(VecDeque::new()) }
    }

    fn now_ms(&self) -> u64 {
        self.epoch.elapsed().as_millis() as u64
    }

    fn admit(&self, max_connections: usize) -> Arc<Hush> {
        let hush = Arc::new(Hush::default());
        hush.heard_ms.store(self.now_ms(), Ordering::Relaxed);
        let mut open = self.open.lock().unwrap_or_else(|p| p.into_inner());
        if open.len() >= 2 * max_connections {
            open.retain(|h| Arc::strong_count(h) > 1);
        }
        open.push_back(hush.clone());
        hush
    }

    /// Closes the open connection heard from least recently among those
    /// that never spoke or have been quiet for [`QUIET_TO_EVICT`]; false
    /// when there is none such.
    fn evict(&self) -> bool {
        let now = self.now_ms();
        let quiet = QUIET_TO_EVICT.as_millis() as u64;
        let mut open = self.open.lock().unwrap_or_else(|p| p.into_inner());
        open.retain(|h| Arc::strong_count(h) > 1 && !h.evicted.load(Ordering::Acquire));
        let evictable = |h: &&Arc<Hush>| !h.spoken.load(Ordering::Acquire) || now.saturating_sub(h.heard_ms.load(Ordering::Relaxed)) >= quiet;
        let Some(oldest) = open.iter().filter(evictable).min_by_key(|h| h.heard_ms.load(Ordering::Relaxed)) else { return false };
        oldest.evict();
        true
    }
}

/// One accepted connection: its stream, its place among the server's
/// `--max-connections` (given back when tonic drops it), and the idle
/// timer that closes it when the peer sends nothing.
pub struct Conn {
    stream: Stream,
    _permit: OwnedSemaphorePermit,
    hush: Arc<Hush>,
    registry: Arc<Registry>,
    /// Fires at the idle deadline as it was when last set; reads only
    /// record when the peer was heard, and the timer is moved on when it
    /// fires early (no timer work per read).
    idle: Pin<Box<Sleep>>,
    first_byte_timeout: Duration,
    idle_timeout: Duration,
    refusals: Arc<ConnectionRefusals>,
}

impl Conn {
    fn new(stream: Stream, permit: OwnedSemaphorePermit, hush: Arc<Hush>, registry: Arc<Registry>, limits: &Limits) -> Conn {
        // Until the peer's first byte the shorter of the two timeouts.
        let first_byte_timeout = limits.idle_timeout.min(FIRST_BYTE_TIMEOUT);
        let idle = Box::pin(tokio::time::sleep(first_byte_timeout));
        Conn { stream, _permit: permit, hush, registry, idle, first_byte_timeout, idle_timeout: limits.idle_timeout, refusals: limits.refusals.clone() }
    }

    /// Whether the peer has been silent past its timeout (registering the
    /// task to be woken at the deadline otherwise).
    fn silent_too_long(&mut self, cx: &mut Context<'_>) -> bool {
        while self.idle.as_mut().poll(cx).is_ready() {
            let timeout = if self.hush.spoken.load(Ordering::Relaxed) { self.idle_timeout } else { self.first_byte_timeout };
            let heard = self.registry.epoch + Duration::from_millis(self.hush.heard_ms.load(Ordering::Relaxed));
            let deadline = Instant::from_std(heard + timeout);
            if deadline <= Instant::now() {
                return true;
            }
            self.idle.as_mut().reset(deadline);
        }
        false
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
        let evicted = || Poll::Ready(Err(io::Error::new(io::ErrorKind::ConnectionAborted, "closed, quiet, to make room for a newcomer on a full server")));
        if this.hush.evicted.load(Ordering::Acquire) {
            return evicted();
        }
        let before = buf.filled().len();
        let read = match &mut this.stream {
            Stream::Plain(s) => Pin::new(s).poll_read(cx, buf),
            Stream::Tls(s) => Pin::new(s.as_mut()).poll_read(cx, buf),
        };
        match read {
            Poll::Ready(Ok(())) if buf.filled().len() > before => {
                // The peer spoke: the silence starts over.
                if !this.hush.spoken.load(Ordering::Relaxed) {
                    this.hush.spoken.store(true, Ordering::Release);
                }
                this.hush.heard_ms.store(this.registry.now_ms(), Ordering::Relaxed);
                Poll::Ready(Ok(()))
            }
            // Waiting for the peer: woken by its bytes, an eviction or the
            // idle deadline.
            Poll::Pending if this.hush.poll_evicted(cx).is_ready() => evicted(),
            Poll::Pending if this.silent_too_long(cx) => {
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
    let registry = Arc::new(Registry::new());
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
            // Full: the least recently heard quiet connection makes room
            // (its reader fails and tonic drops it, giving its place back
            // at once); with none quiet the newcomer is closed, so a flood of
            // sockets costs a file for a moment, not for ever.
            let permit = match places.clone().try_acquire_owned() {
                Ok(permit) => permit,
                Err(_) if registry.evict() => {
                    limits.refusals.evicted.fetch_add(1, Ordering::Relaxed);
                    match tokio::time::timeout(Duration::from_millis(500), places.clone().acquire_owned()).await {
                        Ok(Ok(permit)) => permit,
                        _ => {
                            limits.refusals.over_limit.fetch_add(1, Ordering::Relaxed);
                            continue;
                        }
                    }
                }
                Err(_) => {
                    limits.refusals.over_limit.fetch_add(1, Ordering::Relaxed);
                    tracing::debug!(%peer, "connection refused: --max-connections reached, none quiet");
                    continue;
                }
            };
            let hush = registry.admit(limits.max_connections);
            let _ = stream.set_nodelay(true);
            match &acceptor {
                None => {
                    if tx.send(Ok(Conn::new(Stream::Plain(stream), permit, hush, registry.clone(), &limits))).await.is_err() {
                        break;
                    }
                }
                Some(acceptor) => {
                    let (acceptor, tx, refused, limits, registry) = (acceptor.clone(), tx.clone(), refused.clone(), limits.clone(), registry.clone());
                    tokio::spawn(async move {
                        // A handshake is silence too: evictable until the
                        // first byte after it.
                        let evicted = std::future::poll_fn(|cx| hush.poll_evicted(cx));
                        let handshake = tokio::select! {
                            outcome = tokio::time::timeout(HANDSHAKE_TIMEOUT, acceptor.accept(stream)) => outcome,
                            () = evicted => return,
                        };
                        match handshake {
                            Ok(Ok(tls)) => {
                                let _ = tx.send(Ok(Conn::new(Stream::Tls(Box::new(tls)), permit, hush, registry, &limits))).await;
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
