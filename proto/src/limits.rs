//! The bounds every lcrl server keeps against its peers, and the deadlines
//! and keepalives every lcrl client keeps against its servers
//! (docs/reliability.md).
//!
//! A server's memory is bounded per message (the decoding limit, and
//! [`crate::codec`]'s cap on repeated entries, checked before a message is
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

/// The most entries of one repeated field a message may hold (transitions
/// of a batch, sessions of an environment call), checked on the wire
/// before decoding ([`crate::codec`]).
pub const MAX_REPEATED_ENTRIES: usize = 4096;

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
}

impl Default for ServerLimitsArgs {
    fn default() -> Self {
        ServerLimitsArgs { max_connections: DEFAULT_MAX_CONNECTIONS, idle_timeout_secs: DEFAULT_IDLE_TIMEOUT_SECS }
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
}

impl ConnectionRefusals {
    pub fn counts(&self) -> [(&'static str, u64); 3] {
        [
            ("connections", self.over_limit.load(Ordering::Relaxed)),
            ("idle", self.idle.load(Ordering::Relaxed)),
            ("evicted", self.evicted.load(Ordering::Relaxed)),
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
        let short = ServerLimitsArgs { max_connections: 1, idle_timeout_secs: 2 };
        assert_eq!(short.keepalive_interval(), Duration::from_secs(1));
        assert_eq!(ServerLimitsArgs::default().keepalive_interval(), KEEPALIVE_INTERVAL);
    }
}
