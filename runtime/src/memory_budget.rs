//! A fixed number of bytes that peers may make a server hold, shared by
//! all of them: what `WatchPolicy` streams keep for their readers
//! (watch_budget.rs) and what requests keep while their messages arrive
//! (request_budget.rs). A share is taken at once or refused, never waited
//! for (the peer retries), and one peer address holds at most a quarter of
//! a budget: a host that opens streams and never finishes them cannot shut
//! out every other. Loopback addresses, where `lcrl run` starts its
//! actors, are not counted per peer (`crate::limits::counted_peer`).
//!
//! Memory freed is given back to the system: the allocator keeps what
//! peers' buffers used (a server held 460–660 MiB after the connections
//! that made it grow had closed, issue 82), so once a large share of a
//! budget has come back the server trims its heap (`malloc_trim`, at most
//! once a second; [`Trim`]).

use std::collections::HashMap;
use std::net::IpAddr;
use std::sync::atomic::{AtomicUsize, Ordering};
use std::sync::{Arc, Mutex};
use std::time::{Duration, Instant};

use tokio::sync::{OwnedSemaphorePermit, Semaphore};

/// The share of a budget one peer address may hold.
pub const PEER_SHARE: usize = 4;

/// A budget of bytes.
#[derive(Debug, Clone)]
pub struct MemoryBudget {
    bytes: Arc<Semaphore>,
    total: usize,
    /// Bytes held by each counted peer.
    by_peer: Arc<Mutex<HashMap<IpAddr, usize>>>,
    trim: Arc<Trim>,
}

/// When the heap is trimmed: after at least [`Trim::FLOOR`] bytes were
/// held at once and half of that peak has come back, at most once every
/// [`Trim::EVERY`].
#[derive(Debug)]
struct Trim {
    /// The most held at once since the last trim.
    peak: AtomicUsize,
    last: Mutex<Option<Instant>>,
    /// Trims done (for tests and curiosity).
    done: AtomicUsize,
}

impl Trim {
    const FLOOR: usize = 16 << 20;
    const EVERY: Duration = Duration::from_secs(1);

    fn new() -> Trim {
        Trim { peak: AtomicUsize::new(0), last: Mutex::new(None), done: AtomicUsize::new(0) }
    }

    /// After a share came back, with `used` bytes still held.
    fn on_return(&self, used: usize) {
        let peak = self.peak.load(Ordering::Relaxed);
        if peak < Self::FLOOR || used.saturating_mul(2) > peak {
            return;
        }
        let mut last = self.last.lock().unwrap_or_else(|poisoned| poisoned.into_inner());
        if last.is_some_and(|at| at.elapsed() < Self::EVERY) {
            return;
        }
        *last = Some(Instant::now());
        self.peak.store(used, Ordering::Relaxed);
        self.done.fetch_add(1, Ordering::Relaxed);
        trim_heap();
    }
}

/// Gives the allocator's free memory back to the system (glibc).
fn trim_heap() {
    #[cfg(all(target_os = "linux", target_env = "gnu"))]
    // SAFETY: malloc_trim only walks glibc's own arenas under their locks.
    unsafe {
        libc::malloc_trim(0);
    }
}

/// Why a share was refused.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Refusal {
    /// The peer holds its quarter of the budget.
    PeerShare(IpAddr),
    /// The budget is spent.
    Full,
}

/// A share of a budget, handed back when dropped.
#[derive(Debug)]
pub struct Held {
    /// None once merged into another share.
    permit: Option<OwnedSemaphorePermit>,
    peer: Option<(IpAddr, Arc<Mutex<HashMap<IpAddr, usize>>>)>,
    /// The budget's semaphore, size and trim, to trim once it came back.
    budget: (Arc<Semaphore>, usize, Arc<Trim>),
}

impl Drop for Held {
    fn drop(&mut self) {
        let bytes = self.bytes();
        // The permits go back first, so the trim sees what is still held.
        drop(self.permit.take());
        let (semaphore, total, trim) = &self.budget;
        trim.on_return(total - semaphore.available_permits());
        if let Some((peer, by_peer)) = &self.peer {
            let mut by_peer = by_peer.lock().unwrap_or_else(|poisoned| poisoned.into_inner());
            if let Some(held) = by_peer.get_mut(peer) {
                *held = held.saturating_sub(bytes);
                if *held == 0 {
                    by_peer.remove(peer);
                }
            }
        }
    }
}

impl Held {
    pub fn bytes(&self) -> usize {
        self.permit.as_ref().map_or(0, OwnedSemaphorePermit::num_permits)
    }

    /// Joins `other`, a share of the same budget and peer, into this one.
    pub fn merge(&mut self, mut other: Held) {
        match (&mut self.permit, other.permit.take()) {
            (Some(mine), Some(theirs)) => mine.merge(theirs),
            (mine @ None, theirs) => *mine = theirs,
            (Some(_), None) => {}
        }
    }
}

impl MemoryBudget {
    /// A budget of `bytes` (at least 1).
    pub fn new(bytes: u64) -> Self {
        let total = (bytes.max(1) as usize).min(Semaphore::MAX_PERMITS);
        MemoryBudget { bytes: Arc::new(Semaphore::new(total)), total, by_peer: Arc::default(), trim: Arc::new(Trim::new()) }
    }

    pub fn total(&self) -> usize {
        self.total
    }

    /// The most one counted peer may hold.
    pub fn peer_share(&self) -> usize {
        self.total / PEER_SHARE
    }

    /// Bytes held now.
    pub fn used(&self) -> usize {
        self.total - self.bytes.available_permits()
    }

    /// `bytes` more for `peer`, or why not.
    pub fn take(&self, bytes: usize, peer: Option<IpAddr>) -> Result<Held, Refusal> {
        let counted = peer.and_then(crate::limits::counted_peer);
        let mut by_peer = self.by_peer.lock().unwrap_or_else(|poisoned| poisoned.into_inner());
        if let Some(ip) = counted {
            if by_peer.get(&ip).copied().unwrap_or(0).saturating_add(bytes) > self.peer_share() {
                return Err(Refusal::PeerShare(ip));
            }
        }
        let permits = u32::try_from(bytes).map_err(|_| Refusal::Full)?;
        let permit = self.bytes.clone().try_acquire_many_owned(permits).map_err(|_| Refusal::Full)?;
        let peer = counted.map(|ip| {
            *by_peer.entry(ip).or_insert(0) += bytes;
            (ip, self.by_peer.clone())
        });
        self.trim.peak.fetch_max(self.used(), Ordering::Relaxed);
        Ok(Held { permit: Some(permit), peer, budget: (self.bytes.clone(), self.total, self.trim.clone()) })
    }

    /// Times the heap was trimmed after shares came back.
    pub fn trims(&self) -> usize {
        self.trim.done.load(Ordering::Relaxed)
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// Shares are taken while the budget lasts and given back on drop; one
    /// remote peer holds at most a quarter, another peer and loopback
    /// (IPv4-mapped included) still get theirs.
    #[test]
    fn shares_are_bounded_in_all_and_per_peer_and_come_back() {
        let budget = MemoryBudget::new(4000);
        let peer = |ip: &str| Some(ip.parse::<IpAddr>().unwrap());
        let first = budget.take(600, peer("203.0.113.9")).unwrap();
        assert_eq!(budget.take(401, peer("203.0.113.9")).unwrap_err(), Refusal::PeerShare("203.0.113.9".parse().unwrap()));
        assert!(budget.take(401, peer("::ffff:203.0.113.9")).is_err(), "IPv4-mapped is the same peer");
        let second = budget.take(400, peer("203.0.113.9")).unwrap();
        let _other = budget.take(1000, peer("198.51.100.4")).unwrap();
        let local = budget.take(2000, peer("127.0.0.1")).unwrap();
        assert_eq!((budget.used(), first.bytes() + second.bytes()), (4000, 1000));
        assert_eq!(budget.take(1, None).unwrap_err(), Refusal::Full);
        drop((first, local));
        assert_eq!(budget.used(), 1400);
        assert!(budget.take(600, peer("203.0.113.9")).is_ok(), "a dropped share is the peer's again");
    }

    /// Merged shares are one, handed back together, to the budget and to
    /// the peer's count.
    /// The heap is trimmed once a large share has come back (half of a
    /// peak of at least 16 MiB), not for small ones, and not twice within
    /// a second.
    #[test]
    fn the_heap_is_trimmed_once_a_large_share_came_back() {
        let budget = MemoryBudget::new(64 << 20);
        drop(budget.take(1 << 20, None).unwrap());
        assert_eq!(budget.trims(), 0, "a peak under 16 MiB");
        let big: Vec<Held> = (0..4).map(|_| budget.take(8 << 20, None).unwrap()).collect();
        let mut big = big.into_iter();
        drop(big.next());
        assert_eq!(budget.trims(), 0, "24 of a 32 MiB peak still held");
        drop(big.next());
        assert_eq!(budget.trims(), 1, "half of the peak came back");
        drop(big);
        assert_eq!(budget.trims(), 1, "not again within a second");
    }

    #[test]
    fn merged_shares_are_one() {
        let budget = MemoryBudget::new(4000);
        let peer = Some("203.0.113.9".parse::<IpAddr>().unwrap());
        let mut held = budget.take(300, peer).unwrap();
        held.merge(budget.take(500, peer).unwrap());
        assert_eq!((held.bytes(), budget.used()), (800, 800));
        assert!(budget.take(201, peer).is_err(), "the peer holds 800 of its 1000");
        drop(held);
        assert_eq!(budget.used(), 0);
        assert!(budget.take(1000, peer).is_ok(), "all of it came back");
    }
}
