//! Calls a second per peer address: a token bucket for each peer, for the
//! calls that cost a server something and do nothing for training
//! (GetStatus, `/metrics`). Issue 82: floods of either, unauthenticated,
//! left training 0.28–0.29 of its updates, where a plain one-core CPU hog
//! left 0.48. A peer may make `burst` calls at once and `per_second` calls
//! a second after that; the next is refused (RESOURCE_EXHAUSTED,
//! HTTP 429). Every process on one host shares its loopback address, and
//! with it one bucket.

use std::collections::HashMap;
use std::net::{IpAddr, Ipv4Addr};
use std::sync::Mutex;
use std::time::Instant;

/// Peers a limiter remembers; a flood of new addresses beyond them is
/// refused until some buckets are full again (forgotten).
pub const MAX_PEERS: usize = 4096;

/// GetStatus calls a peer may make a second (and at once): `lcrl run`
/// asks twice a second, a dashboard a few times.
pub const STATUS_PER_SECOND: f64 = 20.0;
pub const STATUS_BURST: f64 = 40.0;
/// `/metrics` scrapes a peer may make a second (and at once): Prometheus
/// scrapes every 15 s or so; a scrape renders every series (about a
/// millisecond), so this rate costs a process about 1% of a core.
pub const METRICS_PER_SECOND: f64 = 10.0;
pub const METRICS_BURST: f64 = 20.0;

/// A token bucket for each peer address.
#[derive(Debug)]
pub struct PeerRate {
    per_second: f64,
    burst: f64,
    buckets: Mutex<HashMap<IpAddr, Bucket>>,
}

#[derive(Debug, Clone, Copy)]
struct Bucket {
    tokens: f64,
    at: Instant,
}

impl PeerRate {
    pub fn new(per_second: f64, burst: f64) -> Self {
        PeerRate { per_second, burst, buckets: Mutex::new(HashMap::new()) }
    }

    /// Whether `peer` may make a call now (None: a peer of no address, as
    /// in-process callers are; they share one bucket).
    pub fn admit(&self, peer: Option<IpAddr>) -> bool {
        self.admit_at(peer, Instant::now())
    }

    /// [`PeerRate::admit`] at a given time (tests).
    pub fn admit_at(&self, peer: Option<IpAddr>, now: Instant) -> bool {
        let peer = peer.unwrap_or(IpAddr::V4(Ipv4Addr::UNSPECIFIED));
        let Ok(mut buckets) = self.buckets.lock() else { return false };
        if !buckets.contains_key(&peer) && buckets.len() >= MAX_PEERS {
            // A full bucket says nothing a new one would not: forget those.
            let (per_second, burst) = (self.per_second, self.burst);
            buckets.retain(|_, b| b.refilled(now, per_second, burst) < burst);
            if buckets.len() >= MAX_PEERS {
                return false;
            }
        }
        let bucket = buckets.entry(peer).or_insert(Bucket { tokens: self.burst, at: now });
        bucket.tokens = bucket.refilled(now, self.per_second, self.burst);
        bucket.at = now;
        if bucket.tokens >= 1.0 {
            bucket.tokens -= 1.0;
            true
        } else {
            false
        }
    }
}

impl Bucket {
    fn refilled(&self, now: Instant, per_second: f64, burst: f64) -> f64 {
        (self.tokens + now.saturating_duration_since(self.at).as_secs_f64() * per_second).min(burst)
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use std::time::Duration;

    fn ip(last: u8) -> Option<IpAddr> {
        Some(IpAddr::V4(Ipv4Addr::new(10, 0, 0, last)))
    }

    /// A burst, then the rate: with 4 at once and 2 a second, a peer gets
    /// 4 calls at t = 0, none more until 0.5 s, one at 0.5 s; another peer
    /// has its own bucket, and a bucket never holds more than the burst.
    #[test]
    fn a_peer_gets_its_burst_then_its_rate() {
        let rate = PeerRate::new(2.0, 4.0);
        let t0 = Instant::now();
        assert_eq!((0..6).filter(|_| rate.admit_at(ip(1), t0)).count(), 4);
        assert!(!rate.admit_at(ip(1), t0 + Duration::from_millis(400)));
        assert!(rate.admit_at(ip(1), t0 + Duration::from_millis(500)));
        assert!(!rate.admit_at(ip(1), t0 + Duration::from_millis(600)));
        assert!(rate.admit_at(ip(2), t0), "another peer's bucket is its own");
        let later = t0 + Duration::from_secs(60);
        assert_eq!((0..6).filter(|_| rate.admit_at(ip(1), later)).count(), 4, "refilled to the burst, no more");
    }

    /// A flood of new addresses: beyond MAX_PEERS remembered, a new peer is
    /// refused while every bucket is in use, and admitted once idle
    /// buckets (full again) can be forgotten.
    #[test]
    fn new_peers_beyond_the_table_wait_for_idle_buckets() {
        let rate = PeerRate::new(1.0, 1.0);
        let t0 = Instant::now();
        for k in 0..MAX_PEERS {
            let peer = Some(IpAddr::V6(std::net::Ipv6Addr::from(k as u128 + 1)));
            assert!(rate.admit_at(peer, t0));
        }
        assert!(!rate.admit_at(ip(1), t0), "every bucket was used just now");
        assert!(rate.admit_at(ip(1), t0 + Duration::from_secs(2)), "idle buckets are forgotten");
        assert_eq!(rate.buckets.lock().unwrap().len(), 1);
    }
}
