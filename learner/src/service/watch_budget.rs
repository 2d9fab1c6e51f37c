//! The memory `WatchPolicy` streams may hold, all together. A reader that
//! does not read keeps the version it was sent in the connection's
//! buffers (the weights of the learner's own copy are shared by every
//! stream; what is encoded for the connection is the stream's). 64 slow
//! readers of a 4.2 MB policy once held 1.1 GiB, 17.4 MiB each (issue 71);
//! they now hold 7.8 MiB each, measured (scripts/chaos.sh --only
//! slow-watchers), and each stream takes a share of one budget while it
//! lives: twice its policy and 64 KiB. A stream beyond the budget is
//! refused with RESOURCE_EXHAUSTED.

use std::sync::Arc;

use tokio::sync::{OwnedSemaphorePermit, Semaphore};
use tonic::Status;

/// What a stream costs beside its policy: HTTP/2 stream state and the
/// encoder's buffer.
pub const STREAM_OVERHEAD_BYTES: usize = 64 << 10;

/// The budget, counted in KiB.
#[derive(Debug, Clone)]
pub struct WatchBudget {
    kib: Arc<Semaphore>,
    total_kib: u32,
}

/// A stream's share, handed back when the stream ends.
#[derive(Debug)]
pub struct WatchPlace {
    _permit: OwnedSemaphorePermit,
}

impl WatchBudget {
    /// A budget of `bytes` (at least one stream's worth of a small policy).
    pub fn new(bytes: u64) -> Self {
        let total_kib = (bytes / 1024).clamp(1, u64::from(u32::MAX >> 3)) as u32;
        WatchBudget { kib: Arc::new(Semaphore::new(total_kib as usize)), total_kib }
    }

    /// One stream's share for a policy of `policy_bytes` encoded bytes.
    pub fn cost_kib(policy_bytes: usize) -> u32 {
        (2 * policy_bytes + STREAM_OVERHEAD_BYTES).div_ceil(1024).min(u32::MAX as usize) as u32
    }

    /// How many streams of a policy of `policy_bytes` the budget holds.
    pub fn streams(&self, policy_bytes: usize) -> u32 {
        self.total_kib / Self::cost_kib(policy_bytes)
    }

    /// A place for one more stream, or RESOURCE_EXHAUSTED when the budget
    /// is spent (a stream never waits for one: its reader retries).
    pub fn admit(&self, policy_bytes: usize) -> Result<WatchPlace, Status> {
        let cost = Self::cost_kib(policy_bytes);
        self.kib.clone().try_acquire_many_owned(cost).map(|permit| WatchPlace { _permit: permit }).map_err(|_| {
            Status::resource_exhausted(format!(
                "the learner holds {} WatchPolicy streams of this policy ({} KiB each) at most (--watch-budget-mib); retry later",
                self.streams(policy_bytes),
                cost
            ))
        })
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
        let mut places: Vec<WatchPlace> = (0..3).map(|_| budget.admit(100 << 10).unwrap()).collect();
        assert_eq!(budget.used_kib(), 3 * 264);
        let refused = budget.admit(100 << 10).unwrap_err();
        assert_eq!(refused.code(), tonic::Code::ResourceExhausted);
        assert!(refused.message().contains("3 WatchPolicy streams"), "{}", refused.message());
        places.pop();
        assert!(budget.admit(100 << 10).is_ok(), "an ended stream's share is free again");
        drop(places);
        assert_eq!(budget.used_kib(), 0);
    }
}
