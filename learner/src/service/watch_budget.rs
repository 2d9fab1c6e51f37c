//! The memory `WatchPolicy` streams may hold, all together. A reader that
//! does not read keeps the version it was sent in the connection's
//! buffers (the weights of the learner's own copy are shared by every
//! stream; what is encoded for the connection is the stream's). 64 slow
//! readers of a 4.2 MB policy once held 1.1 GiB, 17.4 MiB each (issue 71);
//! they now hold 7.8 MiB each, measured (scripts/chaos.sh --only
//! slow-watchers), and each stream takes a share of one budget while it
//! lives: twice its policy and 64 KiB. A stream beyond the budget is
//! refused with RESOURCE_EXHAUSTED.

use std::collections::HashMap;
use std::net::IpAddr;
use std::sync::{Arc, Mutex};

use tokio::sync::{OwnedSemaphorePermit, Semaphore};
use tonic::Status;

/// What a stream costs beside its policy: HTTP/2 stream state and the
/// encoder's buffer.
pub const STREAM_OVERHEAD_BYTES: usize = 64 << 10;

/// The share of the budget one peer address may hold (loopback, where
/// `lcrl run` starts its actors, is not counted): one host that opens
/// streams and never reads cannot shut out every other actor's.
pub const PEER_SHARE: u32 = 4;

/// The budget, counted in KiB.
#[derive(Debug, Clone)]
pub struct WatchBudget {
    kib: Arc<Semaphore>,
    total_kib: u32,
    /// KiB held by each counted peer.
    by_peer: Arc<Mutex<HashMap<IpAddr, u32>>>,
}

/// A stream's share, handed back when the stream ends.
#[derive(Debug)]
pub struct WatchPlace {
    _permit: OwnedSemaphorePermit,
    peer: Option<(IpAddr, u32, Arc<Mutex<HashMap<IpAddr, u32>>>)>,
}

impl Drop for WatchPlace {
    fn drop(&mut self) {
        if let Some((peer, cost, by_peer)) = &self.peer {
            let mut by_peer = by_peer.lock().unwrap_or_else(|poisoned| poisoned.into_inner());
            if let Some(held) = by_peer.get_mut(peer) {
                *held = held.saturating_sub(*cost);
                if *held == 0 {
                    by_peer.remove(peer);
                }
            }
        }
    }
}

impl WatchBudget {
    /// A budget of `bytes` (at least one stream's worth of a small policy).
    pub fn new(bytes: u64) -> Self {
        let total_kib = (bytes / 1024).clamp(1, u64::from(u32::MAX >> 3)) as u32;
        WatchBudget { kib: Arc::new(Semaphore::new(total_kib as usize)), total_kib, by_peer: Arc::default() }
    }

    /// One stream's share for a policy of `policy_bytes` encoded bytes.
    pub fn cost_kib(policy_bytes: usize) -> u32 {
        (2 * policy_bytes + STREAM_OVERHEAD_BYTES).div_ceil(1024).min(u32::MAX as usize) as u32
    }

    /// How many streams of a policy of `policy_bytes` the budget holds.
    pub fn streams(&self, policy_bytes: usize) -> u32 {
        self.total_kib / Self::cost_kib(policy_bytes)
    }

    /// A place for one more stream of `peer`, or RESOURCE_EXHAUSTED when
    /// the budget, or the peer's share of it, is spent (a stream never
    /// waits for one: its reader retries).
    pub fn admit(&self, policy_bytes: usize, peer: Option<IpAddr>) -> Result<WatchPlace, Status> {
        let cost = Self::cost_kib(policy_bytes);
        let counted = peer.and_then(lcrl_proto::limits::counted_peer);
        let mut by_peer = self.by_peer.lock().unwrap_or_else(|poisoned| poisoned.into_inner());
        if let Some(ip) = counted {
            let share = self.total_kib / PEER_SHARE;
            if by_peer.get(&ip).copied().unwrap_or(0).saturating_add(cost) > share {
                return Err(Status::resource_exhausted(format!(
                    "{ip} holds its share of the learner's WatchPolicy budget, {} streams of this policy (a quarter of --watch-budget-mib); retry later",
                    share / cost
                )));
            }
        }
        let permit = self.kib.clone().try_acquire_many_owned(cost).map_err(|_| {
            Status::resource_exhausted(format!(
                "the learner holds {} WatchPolicy streams of this policy ({} KiB each) at most (--watch-budget-mib); retry later",
                self.streams(policy_bytes),
                cost
            ))
        })?;
        let peer = counted.map(|ip| {
            *by_peer.entry(ip).or_insert(0) += cost;
            (ip, cost, self.by_peer.clone())
        });
        Ok(WatchPlace { _permit: permit, peer })
    }

    /// KiB in use by live streams.
    pub fn used_kib(&self) -> u32 {
        self.total_kib - self.kib.available_permits() as u32
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// A 1 MiB budget holds 3 streams of a 100 KiB policy (264 KiB each),
    /// refuses the 4th, and takes a new one once a stream ends.
    #[test]
    fn the_budget_admits_what_it_holds_and_frees_what_ends() {
        let budget = WatchBudget::new(1 << 20);
        assert_eq!(WatchBudget::cost_kib(100 << 10), 264);
        assert_eq!(budget.streams(100 << 10), 3);
        let mut places: Vec<WatchPlace> = (0..3).map(|_| budget.admit(100 << 10, None).unwrap()).collect();
        assert_eq!(budget.used_kib(), 3 * 264);
        let refused = budget.admit(100 << 10, None).unwrap_err();
        assert_eq!(refused.code(), tonic::Code::ResourceExhausted);
        assert!(refused.message().contains("3 WatchPolicy streams"), "{}", refused.message());
        places.pop();
        assert!(budget.admit(100 << 10, None).is_ok(), "an ended stream's share is free again");
        drop(places);
        assert_eq!(budget.used_kib(), 0);
    }

    /// One remote peer holds at most a quarter of the budget; another peer
    /// and loopback (IPv4-mapped included) still get places, and the
    /// peer's share comes back as its streams end.
    #[test]
    fn one_peer_holds_at_most_its_share() {
        let budget = WatchBudget::new(4 << 20);
        let peer = |ip: &str| Some(ip.parse::<IpAddr>().unwrap());
        let mut first: Vec<WatchPlace> = (0..3).map(|_| budget.admit(100 << 10, peer("203.0.113.9")).unwrap()).collect();
        let refused = budget.admit(100 << 10, peer("203.0.113.9")).unwrap_err();
        assert!(refused.message().contains("203.0.113.9 holds its share"), "{}", refused.message());
        assert!(budget.admit(100 << 10, peer("::ffff:203.0.113.9")).is_err(), "IPv4-mapped is the same peer");
        let _other = budget.admit(100 << 10, peer("198.51.100.4")).unwrap();
        let _local: Vec<WatchPlace> = (0..4).map(|_| budget.admit(100 << 10, peer("127.0.0.1")).unwrap()).collect();
        first.pop();
        assert!(budget.admit(100 << 10, peer("203.0.113.9")).is_ok(), "an ended stream gives the share back");
    }
}
