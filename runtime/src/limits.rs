//! The bounds every lcrl server keeps against its peers, and the deadlines
//! and keepalives every lcrl client keeps against its servers
//! (docs/reliability.md).
//!
//! A server's memory is bounded per message (the decoding limit, and
//! lcrl_proto::codec's cap on repeated entries, checked before a message is
//! decoded: an empty `Transition` is 2 bytes on the wire and ~120 in
//! memory), per connection (HTTP/2 streams) and per server (connections,
//! and a timeout that closes the connections of silent peers). A client
//! never waits on a server without a deadline: connecting, each call, and
//! HTTP/2 pings that notice a peer that stopped answering.

use std::sync::atomic::{AtomicU64, Ordering};
use std::time::Duration;

use tonic::transport::{Endpoint, Server};

/// The largest honest `TransitionBatch`, bytes: an actor's default batch
/// is 16–64 transitions, a few hundred bytes each on the peg tasks (64
/// transitions of `lti-blocks-32`, the widest preset, are 50 kB); 1 MiB
/// leaves room for `--batch` in the thousands. Configurable on the learner
/// (`--max-batch-bytes`).
pub const MAX_BATCH_BYTES: usize = 1 << 20;

/// The start of the message of a batch refused for its size (over
/// `--max-batch-bytes`), as the learner answers it (RESOURCE_EXHAUSTED).
pub const TOO_LARGE: &str = "too large";

/// The most entries of one repeated field a message may hold, checked on
/// the wire before decoding (lcrl_proto::codec, where it lives).
pub use lcrl_proto::codec::MAX_REPEATED_ENTRIES;

/// The longest actor id the learner keeps, bytes (a pod name is at most 253).
pub const MAX_ACTOR_ID_BYTES: usize = 256;

/// HTTP/2 streams one connection may hold open at once: an actor holds two
/// (transitions and policy watch), a client a few calls in flight.
pub const MAX_STREAMS_PER_CONNECTION: u32 = 32;

/// How long a client waits for a TCP (and TLS) connection.
pub const CONNECT_TIMEOUT: Duration = Duration::from_secs(5);

/// How long a client waits for a call's response headers: a server that
/// accepts and never answers fails the call after this, instead of hanging
/// it. Streams, once answered, are watched by the keepalive.
pub const CALL_TIMEOUT: Duration = Duration::from_secs(15);

/// HTTP/2 ping interval and the time an unanswered ping ends the
/// connection, on both sides: a peer that vanished without closing (a
/// killed pod, a cut network) is noticed within about half a minute.
pub const KEEPALIVE_INTERVAL: Duration = Duration::from_secs(15);
pub const KEEPALIVE_TIMEOUT: Duration = Duration::from_secs(10);

/// Before its first byte a connection gets at most this long (or the idle
/// timeout, if shorter): sockets opened and left silent are closed soon.
pub const FIRST_BYTE_TIMEOUT: Duration = Duration::from_secs(10);

/// A connection must complete a call that passed the token check (any
/// call but a health check, where no token is set) within this long of
/// its accept, or it is closed, whatever else it sends: 520 connections
/// answering HTTP/2 pings were never idle and locked every client out
/// (issue 71). Health probes connect, ask and leave well within it.
pub const CALL_DEADLINE: Duration = Duration::from_secs(10);

/// The address a per-peer share counts `ip` under: IPv4 on an IPv6
/// listener (::ffff:a.b.c.d) as itself; None for loopback, where `lcrl run`
/// starts its own processes and no share applies. IPv6 counts per address,
/// not per /64, although one host may pick any address of its /64: a
/// Kubernetes node hands its pods addresses from one /64 (as cloud subnets
/// and LANs do), and a /64 share would hold every actor of a node as one
/// peer.
pub fn counted_peer(ip: std::net::IpAddr) -> Option<std::net::IpAddr> {
    Some(ip.to_canonical()).filter(|ip| !ip.is_loopback())
}

/// Connections one peer address may hold at once, beyond loopback
/// (`--max-connections-per-peer`): one host cannot take every place.
/// Loopback peers share 127.0.0.1 (every actor of `lcrl run`), so they
/// are held by `--max-connections` alone.
pub const DEFAULT_MAX_CONNECTIONS_PER_PEER: u32 = 64;

/// `--max-connections` and `--idle-timeout-secs` when not given.
pub const DEFAULT_MAX_CONNECTIONS: u32 = 512;
pub const DEFAULT_IDLE_TIMEOUT_SECS: u64 = 300;

/// A server's connection limits (flags of every lcrl server).
#[derive(Debug, Clone, clap::Args)]
pub struct ServerLimitsArgs {
    /// Connections served at once. When all are taken, a newcomer takes
    /// the place of the least recently heard connection that never spoke
    /// or has been quiet for 5 s (`connections_refused{reason="evicted"}`
    /// in /metrics); with none such, it is closed (`reason="connections"`).
    #[arg(long, default_value_t = DEFAULT_MAX_CONNECTIONS, value_parser = clap::value_parser!(u32).range(1..=65_536))]
    pub max_connections: u32,
    /// A connection whose peer sends nothing for this long is closed,
    /// seconds (live clients answer the server's pings, every 15 s or half
    /// this, whichever is shorter). Before its first byte a connection gets
    /// at most 10 s.
    #[arg(long, default_value_t = DEFAULT_IDLE_TIMEOUT_SECS, value_parser = clap::value_parser!(u64).range(1..=86_400))]
    pub idle_timeout_secs: u64,
    /// Connections one peer address may hold at once (loopback peers
    /// excepted: they are every local process); more are refused on accept
    /// (`connections_refused{reason="per_peer"}`).
    #[arg(long, default_value_t = DEFAULT_MAX_CONNECTIONS_PER_PEER, value_parser = clap::value_parser!(u32).range(1..=65_536))]
    pub max_connections_per_peer: u32,
}

impl Default for ServerLimitsArgs {
    fn default() -> Self {
        ServerLimitsArgs { max_connections: DEFAULT_MAX_CONNECTIONS, idle_timeout_secs: DEFAULT_IDLE_TIMEOUT_SECS, max_connections_per_peer: DEFAULT_MAX_CONNECTIONS_PER_PEER }
    }
}

impl ServerLimitsArgs {
    pub fn idle_timeout(&self) -> Duration {
        Duration::from_secs(self.idle_timeout_secs)
    }

    /// The server's ping interval: often enough that a live but quiet
    /// client is never taken for an idle one.
    pub fn keepalive_interval(&self) -> Duration {
        KEEPALIVE_INTERVAL.min(self.idle_timeout() / 2).max(Duration::from_millis(200))
    }

    /// A tonic server with these limits: streams per connection, pings.
    pub fn server(&self) -> Server {
        Server::builder()
            .max_concurrent_streams(MAX_STREAMS_PER_CONNECTION)
            .http2_keepalive_interval(Some(self.keepalive_interval()))
            .http2_keepalive_timeout(Some(KEEPALIVE_TIMEOUT))
    }
}

/// Connections a server refused or closed, by reason.
#[derive(Debug, Default)]
pub struct ConnectionRefusals {
    /// Closed on accept: the server held `--max-connections` already.
    pub over_limit: AtomicU64,
    /// Closed after the peer sent nothing for the idle timeout.
    pub idle: AtomicU64,
    /// Closed, while the server was full, to make room for a newcomer:
    /// the least recently heard of those silent since accepted or quiet
    /// for 5 s (crate::incoming).
    pub evicted: AtomicU64,
    /// Closed for completing no authenticated call within [`CALL_DEADLINE`].
    pub no_call: AtomicU64,
    /// Refused on accept: the peer address held
    /// `--max-connections-per-peer` already.
    pub per_peer: AtomicU64,
    /// Closed, while the server was full and none was quiet, to make room
    /// for a newcomer: its peer (a host, or a local process) held more
    /// than its share of the places (crate::incoming).
    pub over_share: AtomicU64,
}

impl ConnectionRefusals {
    pub fn counts(&self) -> [(&'static str, u64); 6] {
        [
            ("connections", self.over_limit.load(Ordering::Relaxed)),
            ("idle", self.idle.load(Ordering::Relaxed)),
            ("evicted", self.evicted.load(Ordering::Relaxed)),
            ("no_call", self.no_call.load(Ordering::Relaxed)),
            ("per_peer", self.per_peer.load(Ordering::Relaxed)),
            ("over_share", self.over_share.load(Ordering::Relaxed)),
        ]
    }
}

/// The client side: an endpoint that never waits without a deadline.
pub fn client_endpoint(endpoint: Endpoint) -> Endpoint {
    endpoint
        .connect_timeout(CONNECT_TIMEOUT)
        .timeout(CALL_TIMEOUT)
        .http2_keep_alive_interval(KEEPALIVE_INTERVAL)
        .keep_alive_timeout(KEEPALIVE_TIMEOUT)
        .keep_alive_while_idle(true)
}

/// Exponential backoff with "equal" jitter (a random wait between half
/// and all of a delay that doubles up to `max`): many actors that lost one
/// learner do not all come back in the same instant, and none retries
/// sooner than half its delay.
#[derive(Debug, Clone)]
pub struct Backoff {
    next: Duration,
    max: Duration,
    state: u64,
}

impl Backoff {
    pub fn new(first: Duration, max: Duration) -> Self {
        // Seeded per process and instance; quality needs are low.
        let seed = std::process::id() as u64 ^ (std::time::SystemTime::now().duration_since(std::time::UNIX_EPOCH).map_or(0, |d| d.as_nanos() as u64));
        Backoff { next: first, max, state: seed | 1 }
    }

    /// The wait before the next attempt: uniform in [next/2, next], then
    /// `next` doubles up to `max`.
    pub fn next_delay(&mut self) -> Duration {
        // xorshift64*
        self.state ^= self.state >> 12;
        self.state ^= self.state << 25;
        self.state ^= self.state >> 27;
        let unit = (self.state.wrapping_mul(0x2545_f491_4f6c_dd1d) >> 11) as f64 / (1u64 << 53) as f64;
        let delay = self.next.mul_f64(0.5 + 0.5 * unit);
        self.next = (self.next * 2).min(self.max);
        delay
    }
}

/// Files a server keeps beyond its connections: checkpoints, logs,
/// shared memory, the /metrics server's connections (64).
pub const RESERVED_FILES: u64 = 256;

/// Raises this process's open-file limit (the soft one, up to the hard
/// one) so that `max_connections` connections leave [`RESERVED_FILES`]
/// for the rest: full of connections, a server still writes its
/// checkpoints. Returns the limit, or why it stays too low.
pub fn reserve_files(max_connections: u32) -> Result<u64, String> {
    let needed = u64::from(max_connections) + RESERVED_FILES;
    let mut limit = libc::rlimit { rlim_cur: 0, rlim_max: 0 };
    // SAFETY: getrlimit and setrlimit read and write the one struct given.
    if unsafe { libc::getrlimit(libc::RLIMIT_NOFILE, &mut limit) } != 0 {
        return Err(format!("cannot read the open-file limit: {}", std::io::Error::last_os_error()));
    }
    if limit.rlim_cur >= needed {
        return Ok(limit.rlim_cur);
    }
    let raised = libc::rlimit { rlim_cur: needed.min(limit.rlim_max), rlim_max: limit.rlim_max };
    // SAFETY: as above.
    if unsafe { libc::setrlimit(libc::RLIMIT_NOFILE, &raised) } != 0 || raised.rlim_cur < needed {
        return Err(format!(
            "the open-file limit is {} (hard {}), below --max-connections {max_connections} + {RESERVED_FILES} for checkpoints and logs; \
             raise it (ulimit -n) or lower --max-connections",
            raised.rlim_cur.max(limit.rlim_cur),
            limit.rlim_max
        ));
    }
    Ok(raised.rlim_cur)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn backoff_doubles_to_its_cap_with_jitter_in_the_upper_half() {
        let mut backoff = Backoff::new(Duration::from_millis(100), Duration::from_secs(2));
        let delays: Vec<Duration> = (0..8).map(|_| backoff.next_delay()).collect();
        let bounds = [100u64, 200, 400, 800, 1600, 2000, 2000, 2000];
        for (delay, bound) in delays.iter().zip(bounds) {
            let bound = Duration::from_millis(bound);
            assert!(*delay <= bound && *delay >= bound / 2, "{delay:?} outside [{:?}, {bound:?}]", bound / 2);
        }
        // Two actors that start together do not retry in lockstep.
        let mut other = Backoff { state: 0x9e37_79b9_7f4a_7c15, ..Backoff::new(Duration::from_millis(100), Duration::from_secs(2)) };
        let theirs: Vec<Duration> = (0..8).map(|_| other.next_delay()).collect();
        assert_ne!(delays, theirs);
    }

    #[test]
    fn the_ping_interval_stays_below_the_idle_timeout() {
        let short = ServerLimitsArgs { max_connections: 1, idle_timeout_secs: 2, ..Default::default() };
        assert_eq!(short.keepalive_interval(), Duration::from_secs(1));
        assert_eq!(ServerLimitsArgs::default().keepalive_interval(), KEEPALIVE_INTERVAL);
    }

    #[test]
    fn peers_are_counted_per_address() {
        let peer = |s: &str| counted_peer(s.parse().unwrap()).map(|ip| ip.to_string());
        assert_ne!(peer("2001:db8:1:2::5"), peer("2001:db8:1:2::6"), "two pods of one node's /64 are two peers");
        assert_eq!(peer("::ffff:192.0.2.7").as_deref(), Some("192.0.2.7"), "IPv4 on an IPv6 listener is itself");
        assert_eq!((peer("127.0.0.1"), peer("::1"), peer("::ffff:127.0.0.1")), (None, None, None), "loopback is not counted");
    }
}
