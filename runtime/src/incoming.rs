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
//! A connection that completes no authenticated call within
//! [`CALL_DEADLINE`] is closed whatever it sends (the token check marks
//! its connection, [`Connections::mark_called`]), and one peer address
//! beyond loopback holds at most `--max-connections-per-peer`.
//! When the server is full and none is quiet, the places are shared: with
//! k peers (a host, or on loopback a local process, crate::peer_process)
//! among those holding places and the newcomer, the peer holding the most
//! other than the newcomer's own gives up its least recently heard
//! connection, called or not, if it holds more than max / k and would still
//! hold more than the newcomer's peer afterwards. One process's
//! connections, however busy, cannot keep a health check or another
//! process's actor out; a newcomer never takes a place from its own peer.
//! Many small peers (processes forked by one attacker, addresses of one
//! IPv6 prefix) share the places as so many peers: the rule bounds one
//! peer, not a crowd.

use std::future::Future;
use std::io;
use std::pin::Pin;
use std::collections::{HashMap, VecDeque};
use std::net::{IpAddr, SocketAddr};
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

use crate::limits::{ConnectionRefusals, ServerLimitsArgs, CALL_DEADLINE, FIRST_BYTE_TIMEOUT};
use crate::peer_process::{remote_group, LocalSockets, PeerGroup};

/// How often a full server reads /proc to learn which local process holds
/// a loopback peer (crate::peer_process): a flood of newcomers costs at
/// most this many readings a second.
const LOCAL_SOCKETS_EVERY: Duration = Duration::from_millis(250);

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
    /// A call passed the token check on this connection.
    called: AtomicBool,
    peer: Option<SocketAddr>,
    /// Milliseconds from the registry's epoch to the last byte read (or
    /// to the accept).
    heard_ms: std::sync::atomic::AtomicU64,
    evicted: AtomicBool,
    /// Who the peer is, once known (crate::peer_process).
    group: std::sync::OnceLock<PeerGroup>,
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
    /// Open connections by peer address, for the token check to mark and
    /// for the per-peer cap.
    by_peer: Mutex<HashMap<SocketAddr, std::sync::Weak<Hush>>>,
    /// When /proc was last read for local peers' processes.
    sockets_read: Mutex<Option<std::time::Instant>>,
}

/// A server's connections as its token check sees them: the handle that
/// marks a connection as having completed an authenticated call.
#[derive(Clone)]
pub struct Connections(Arc<Registry>);

impl Default for Connections {
    fn default() -> Self {
        Connections(Arc::new(Registry::new()))
    }
}

impl Connections {
    /// The connection from `peer` completed a call that passed the token
    /// check: it is kept past [`CALL_DEADLINE`].
    pub fn mark_called(&self, peer: SocketAddr) {
        let by_peer = self.0.by_peer.lock().unwrap_or_else(|p| p.into_inner());
        if let Some(hush) = by_peer.get(&peer).and_then(std::sync::Weak::upgrade) {
            hush.called.store(true, Ordering::Relaxed);
        }
    }
}

impl Registry {
    fn new() -> Self {
        Registry { epoch: std::time::Instant::now(), open: Mutex::new(VecDeque::new()), by_peer: Mutex::new(HashMap::new()), sockets_read: Mutex::new(None) }
    }

    /// Whether `ip` (not loopback) holds `cap` open connections already.
    fn peer_full(&self, ip: IpAddr, cap: usize) -> bool {
        let Some(ip) = crate::limits::counted_peer(ip) else { return false };
        let mut by_peer = self.by_peer.lock().unwrap_or_else(|p| p.into_inner());
        // The open list holds one reference; the connection, the other.
        by_peer.retain(|_, hush| hush.strong_count() > 1);
        by_peer.keys().filter(|addr| addr.ip().to_canonical() == ip).count() >= cap
    }

    fn now_ms(&self) -> u64 {
        self.epoch.elapsed().as_millis() as u64
    }

    fn admit(&self, max_connections: usize, peer: SocketAddr) -> Arc<Hush> {
        let hush = Arc::new(Hush { peer: Some(peer), ..Hush::default() });
        hush.heard_ms.store(self.now_ms(), Ordering::Relaxed);
        self.by_peer.lock().unwrap_or_else(|p| p.into_inner()).insert(peer, Arc::downgrade(&hush));
        let mut open = self.open.lock().unwrap_or_else(|p| p.into_inner());
        if open.len() >= 2 * max_connections {
            open.retain(|h| Arc::strong_count(h) > 1);
        }
        open.push_back(hush.clone());
        hush
    }

    /// Closes the open connection heard from least recently among those
    /// that never spoke, never called, or have been quiet for
    /// [`QUIET_TO_EVICT`]; false when there is none such.
    fn evict_quiet(&self) -> bool {
        let now = self.now_ms();
        let quiet = QUIET_TO_EVICT.as_millis() as u64;
        let mut open = self.open.lock().unwrap_or_else(|p| p.into_inner());
        open.retain(|h| Arc::strong_count(h) > 1 && !h.evicted.load(Ordering::Acquire));
        let evictable = |h: &&Arc<Hush>| {
            !h.spoken.load(Ordering::Acquire) || !h.called.load(Ordering::Relaxed) || now.saturating_sub(h.heard_ms.load(Ordering::Relaxed)) >= quiet
        };
        evict_least_recently_heard(open.iter().filter(evictable))
    }

    /// The loopback peers whose process is not known yet, the newcomer's
    /// among them, when /proc may be read again (at most every
    /// [`LOCAL_SOCKETS_EVERY`]); empty otherwise.
    fn local_peers_to_read(&self, newcomer: SocketAddr) -> Vec<SocketAddr> {
        let mut read = self.sockets_read.lock().unwrap_or_else(|p| p.into_inner());
        if read.is_some_and(|at| at.elapsed() < LOCAL_SOCKETS_EVERY) {
            return Vec::new();
        }
        let open = self.open.lock().unwrap_or_else(|p| p.into_inner());
        let mut peers: Vec<SocketAddr> = open.iter().filter(|h| h.group.get().is_none()).filter_map(|h| h.peer).filter(|p| remote_group(*p).is_none()).collect();
        if remote_group(newcomer).is_none() {
            peers.push(newcomer);
        }
        if !peers.is_empty() {
            *read = Some(std::time::Instant::now());
        }
        peers
    }

    /// With none quiet: the places are shared among the peers holding them
    /// and the newcomer's (k peers, `max_connections` / k each). The peer
    /// holding the most, other than the newcomer's own, gives up its least
    /// recently heard connection if it holds more than that share and would
    /// still hold more than the newcomer's peer afterwards; a newcomer never
    /// takes a place from its own peer (no churn among one peer's
    /// connections). `sockets`: a reading of the local processes.
    fn evict_over_share(&self, max_connections: usize, newcomer: SocketAddr, sockets: Option<&LocalSockets>) -> bool {
        let mut open = self.open.lock().unwrap_or_else(|p| p.into_inner());
        open.retain(|h| Arc::strong_count(h) > 1 && !h.evicted.load(Ordering::Acquire));
        // A peer not found (yet) counts as an unknown local peer.
        for h in open.iter().filter(|h| h.group.get().is_none()) {
            if let Some(known) = h.peer.and_then(|peer| known_group(peer, sockets)) {
                let _ = h.group.set(known);
            }
        }
        let group = |h: &Arc<Hush>| h.group.get().copied().unwrap_or(PeerGroup::Local);
        let theirs = known_group(newcomer, sockets).unwrap_or(PeerGroup::Local);
        let mut held: HashMap<PeerGroup, usize> = HashMap::new();
        for h in open.iter() {
            *held.entry(group(h)).or_default() += 1;
        }
        let peers = held.len() + usize::from(!held.contains_key(&theirs));
        let share = (max_connections / peers.max(1)).max(1);
        let Some((&largest, &count)) = held.iter().filter(|(g, _)| **g != theirs).max_by_key(|(_, &n)| n) else { return false };
        // Over its share, and still ahead of the newcomer's peer once the
        // place has moved (count − 1 > theirs + 1): two peers can never
        // take places from each other in turn.
        let newcomers = held.get(&theirs).copied().unwrap_or(0);
        if count <= share || count <= newcomers + 2 {
            return false;
        }
        evict_least_recently_heard(open.iter().filter(|h| group(h) == largest))
    }
}

/// Closes the least recently heard of `candidates`; false when there is none.
fn evict_least_recently_heard<'a>(candidates: impl Iterator<Item = &'a Arc<Hush>>) -> bool {
    match candidates.min_by_key(|h| h.heard_ms.load(Ordering::Relaxed)) {
        Some(oldest) => {
            oldest.evict();
            true
        }
        None => false,
    }
}

/// Who `peer` is, where known: a host beyond loopback, or the local
/// process `sockets` found holding its socket.
fn known_group(peer: SocketAddr, sockets: Option<&LocalSockets>) -> Option<PeerGroup> {
    remote_group(peer).or_else(|| sockets.map(|s| s.group(peer)).filter(|g| matches!(g, PeerGroup::Process(_))))
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
    /// When the connection must have completed an authenticated call.
    call_deadline: Instant,
    refusals: Arc<ConnectionRefusals>,
}

impl Conn {
    fn new(stream: Stream, permit: OwnedSemaphorePermit, hush: Arc<Hush>, registry: Arc<Registry>, limits: &Limits) -> Conn {
        // Until the peer's first byte the shorter of the two timeouts.
        let first_byte_timeout = limits.idle_timeout.min(FIRST_BYTE_TIMEOUT);
        let idle = Box::pin(tokio::time::sleep(first_byte_timeout.min(limits.call_deadline)));
        let call_deadline = Instant::now() + limits.call_deadline;
        Conn { stream, _permit: permit, hush, registry, idle, first_byte_timeout, idle_timeout: limits.idle_timeout, call_deadline, refusals: limits.refusals.clone() }
    }

    /// Why the connection is to be closed: silent past its timeout, or no
    /// authenticated call by its deadline (registering the task to be
    /// woken at the next deadline otherwise).
    fn overdue(&mut self, cx: &mut Context<'_>) -> Option<Overdue> {
        while self.idle.as_mut().poll(cx).is_ready() {
            let now = Instant::now();
            let called = self.hush.called.load(Ordering::Relaxed);
            if !called && self.call_deadline <= now {
                return Some(Overdue::NoCall);
            }
            let timeout = if self.hush.spoken.load(Ordering::Relaxed) { self.idle_timeout } else { self.first_byte_timeout };
            let heard = self.registry.epoch + Duration::from_millis(self.hush.heard_ms.load(Ordering::Relaxed));
            let deadline = Instant::from_std(heard + timeout);
            if deadline <= now {
                return Some(Overdue::Silent);
            }
            self.idle.as_mut().reset(if called { deadline } else { deadline.min(self.call_deadline) });
        }
        None
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
            Poll::Pending => match this.overdue(cx) {
                Some(Overdue::Silent) => {
                    this.refusals.idle.fetch_add(1, Ordering::Relaxed);
                    tracing::debug!("closing a connection silent for its idle timeout");
                    Poll::Ready(Err(io::Error::new(io::ErrorKind::TimedOut, "the peer sent nothing within the idle timeout")))
                }
                Some(Overdue::NoCall) => {
                    this.refusals.no_call.fetch_add(1, Ordering::Relaxed);
                    tracing::debug!(peer = ?this.hush.peer, "closing a connection that made no authenticated call within {} s", CALL_DEADLINE.as_secs());
                    Poll::Ready(Err(io::Error::new(io::ErrorKind::TimedOut, "no authenticated call within the deadline")))
                }
                None => Poll::Pending,
            },
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

/// Why [`Conn::overdue`] closes a connection.
enum Overdue {
    Silent,
    NoCall,
}

/// What [`incoming`] holds a server's connections to.
#[derive(Clone)]
pub struct Limits {
    pub max_connections: usize,
    pub max_connections_per_peer: usize,
    pub idle_timeout: Duration,
    /// [`CALL_DEADLINE`] (shorter in tests).
    pub call_deadline: Duration,
    pub refusals: Arc<ConnectionRefusals>,
}

impl Limits {
    pub fn new(args: &ServerLimitsArgs, refusals: Arc<ConnectionRefusals>) -> Limits {
        Limits {
            max_connections: args.max_connections as usize,
            max_connections_per_peer: args.max_connections_per_peer as usize,
            idle_timeout: args.idle_timeout(),
            call_deadline: CALL_DEADLINE,
            refusals,
        }
    }
}

/// Called once per failed TLS handshake (the server counts them).
pub type OnRefusedHandshake = Arc<dyn Fn() + Send + Sync>;

/// Accepts connections on `listener` (TCP_NODELAY: small request and
/// response messages), completing TLS handshakes where `tls` is set and
/// reporting each failed one to `refused`, within `limits`.
pub fn incoming(listener: TcpListener, tls: Option<Arc<rustls::ServerConfig>>, refused: OnRefusedHandshake, limits: Limits, connections: Connections) -> ReceiverStream<io::Result<Conn>> {
    let (tx, rx) = tokio::sync::mpsc::channel(64);
    let acceptor = tls.map(TlsAcceptor::from);
    let places = Arc::new(Semaphore::new(limits.max_connections));
    let registry = connections.0;
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
            if registry.peer_full(peer.ip(), limits.max_connections_per_peer) {
                limits.refusals.per_peer.fetch_add(1, Ordering::Relaxed);
                tracing::debug!(%peer, "connection refused: --max-connections-per-peer reached");
                continue;
            }
            let Some(permit) = place(&places, &registry, &limits, peer).await else { continue };
            let hush = registry.admit(limits.max_connections, peer);
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

/// A place among `--max-connections` for a newcomer from `peer`. When
/// full, the least recently heard quiet connection makes room (its reader
/// fails and tonic drops it, giving its place back at once), or with none
/// quiet one of a peer over its share; with neither, None (counted): the
/// newcomer is closed, so a flood of sockets costs a file for a moment,
/// not for ever.
async fn place(places: &Arc<Semaphore>, registry: &Arc<Registry>, limits: &Limits, peer: SocketAddr) -> Option<OwnedSemaphorePermit> {
    if let Ok(permit) = places.clone().try_acquire_owned() {
        return Some(permit);
    }
    let made_room = if registry.evict_quiet() {
        limits.refusals.evicted.fetch_add(1, Ordering::Relaxed);
        true
    } else {
        // Who the local peers are is read from /proc off this task's
        // thread (a few milliseconds, at most every LOCAL_SOCKETS_EVERY).
        let wanted = registry.local_peers_to_read(peer);
        let sockets = if wanted.is_empty() { None } else { tokio::task::spawn_blocking(move || LocalSockets::read_for(&wanted)).await.ok() };
        let over = registry.evict_over_share(limits.max_connections, peer, sockets.as_ref());
        if over {
            limits.refusals.over_share.fetch_add(1, Ordering::Relaxed);
        }
        over
    };
    if !made_room {
        limits.refusals.over_limit.fetch_add(1, Ordering::Relaxed);
        tracing::debug!(%peer, "connection refused: --max-connections reached, none quiet and no peer over its share");
        return None;
    }
    match tokio::time::timeout(Duration::from_millis(500), places.clone().acquire_owned()).await {
        Ok(Ok(permit)) => Some(permit),
        _ => {
            limits.refusals.over_limit.fetch_add(1, Ordering::Relaxed);
            None
        }
    }
}

#[cfg(test)]
mod tests;
