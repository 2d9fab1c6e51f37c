//! The memory `WatchPolicy` streams may hold, all together. A reader that
//! does not read keeps the version it was sent in the connection's
//! buffers (the weights of the learner's own copy are shared by every
//! stream; what is encoded for the connection is the stream's). 64 slow
//! readers of a 4.2 MB policy once held 1.1 GiB, 17.4 MiB each (issue 71);
//! they now hold 7.8 MiB each, measured (scripts/chaos.sh --only
//! slow-watchers), and each stream takes a share of one budget while it
//! lives: twice its policy and 64 KiB. A stream beyond the budget is
//! refused with RESOURCE_EXHAUSTED.

use std::net::IpAddr;

use tonic::Status;

use lcrl_runtime::memory_budget::{Held, MemoryBudget, Refusal};

/// What a stream costs beside its policy: HTTP/2 stream state and the
/// encoder's buffer.
pub const STREAM_OVERHEAD_BYTES: usize = 64 << 10;

/// The budget of all `WatchPolicy` streams (`--watch-budget-mib`).
#[derive(Debug, Clone)]
pub struct WatchBudget(MemoryBudget);

/// A stream's share, handed back when the stream ends.
pub type WatchPlace = Held;

impl WatchBudget {
    /// A budget of `bytes` (at least one stream's worth of a small policy).
    pub fn new(bytes: u64) -> Self {
        WatchBudget(MemoryBudget::new(bytes))
    }

    /// One stream's share for a policy of `policy_bytes` encoded bytes, in
    /// KiB.
    pub fn cost_kib(policy_bytes: usize) -> u32 {
        (2 * policy_bytes + STREAM_OVERHEAD_BYTES).div_ceil(1024).min(u32::MAX as usize) as u32
    }

    /// How many streams of a policy of `policy_bytes` the budget holds.
    pub fn streams(&self, policy_bytes: usize) -> usize {
        self.0.total() / (Self::cost_kib(policy_bytes) as usize * 1024)
    }

    /// A place for one more stream of `peer`, or RESOURCE_EXHAUSTED when
    /// the budget, or the peer's share of it, is spent (a stream never
    /// waits for one: its reader retries).
    pub fn admit(&self, policy_bytes: usize, peer: Option<IpAddr>) -> Result<WatchPlace, Status> {
        let cost = Self::cost_kib(policy_bytes) as usize * 1024;
        self.0.take(cost, peer).map_err(|refusal| match refusal {
            Refusal::PeerShare(ip) => Status::resource_exhausted(format!(
                "{ip} holds its share of the learner's WatchPolicy budget, {} streams of this policy (a quarter of --watch-budget-mib); retry later",
                self.0.peer_share() / cost
            )),
            Refusal::Full => Status::resource_exhausted(format!(
                "the learner holds {} WatchPolicy streams of this policy ({} KiB each) at most (--watch-budget-mib); retry later",
                self.streams(policy_bytes),
                cost / 1024
            )),
        })
    }

    /// KiB in use by live streams.
    pub fn used_kib(&self) -> usize {
        self.0.used() / 1024
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

    /// A peer's refusal names the peer and its share.
    #[test]
    fn a_peer_over_its_share_is_told_so() {
        let budget = WatchBudget::new(4 << 20);
        let peer = Some("203.0.113.9".parse::<IpAddr>().unwrap());
        let _held: Vec<WatchPlace> = (0..3).map(|_| budget.admit(100 << 10, peer).unwrap()).collect();
        let refused = budget.admit(100 << 10, peer).unwrap_err();
        assert!(refused.message().contains("203.0.113.9 holds its share") && refused.message().contains("3 streams"), "{}", refused.message());
    }
}
