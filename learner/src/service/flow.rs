//! How data flows through the distributed learner: the replay-ratio
//! counters, who waited for whom, the policy lag of stored transitions, and
//! the run's budget. Written by the training thread, read by `GetStatus`,
//! `/metrics` and TensorBoard.

use std::collections::VecDeque;

use crate::algo::rate_limiter::RateLimiter;

/// Policy lag of the most recently stored transitions.
#[derive(Debug, Clone)]
pub struct LagWindow {
    lags: VecDeque<u64>,
    capacity: usize,
}

impl Default for LagWindow {
    fn default() -> Self {
        LagWindow { lags: VecDeque::new(), capacity: 1000 }
    }
}

impl LagWindow {
    pub fn push(&mut self, lag: u64) {
        if self.lags.len() == self.capacity {
            self.lags.pop_front();
        }
        self.lags.push_back(lag);
    }

    /// (min, mean, max) over the window; zeros when empty.
    pub fn stats(&self) -> (u64, f64, u64) {
        if self.lags.is_empty() {
            return (0, 0.0, 0);
        }
        let min = self.lags.iter().copied().min().unwrap_or(0);
        let max = self.lags.iter().copied().max().unwrap_or(0);
        (min, self.lags.iter().sum::<u64>() as f64 / self.lags.len() as f64, max)
    }
}

/// Everything `GetStatus` reports about the flow of data.
#[derive(Debug, Clone, Default)]
pub struct FlowStats {
    /// The replay-ratio limiter, the one count of transitions inserted and
    /// sampled (unlimited for PPO and `--replay-ratio unlimited`).
    pub limiter: RateLimiter,
    /// Seconds inserts were refused (the learner was behind: actors waited).
    pub actors_waited_s: f64,
    /// Seconds samples were refused (actors were behind: the learner waited).
    pub learner_waited_s: f64,
    pub lag: LagWindow,
    /// The episode budget (0: none).
    pub budget_episodes: u64,
    /// The budget is reached: final checkpoint and summary written.
    pub finished: bool,
    /// Checkpoints that failed (a full disk, say): training went on.
    pub checkpoint_failures: u64,
    /// Policies not published because a weight was not finite (issue 71):
    /// actors keep the last finite one.
    pub non_finite_policies: u64,
}

impl FlowStats {
    /// Transitions inserted into the replay buffer or rollout.
    pub fn inserted(&self) -> u64 {
        self.limiter.inserts
    }

    /// Transitions sampled by updates (DDPG: batch_size per update).
    pub fn sampled(&self) -> u64 {
        self.limiter.samples
    }

    /// Target samples per insert; 0 when unlimited (or PPO).
    pub fn replay_ratio_target(&self) -> f64 {
        self.limiter.samples_per_insert
    }

    pub fn achieved_ratio(&self) -> f64 {
        self.limiter.achieved_ratio()
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn lag_window_keeps_the_newest_thousand() {
        let mut w = LagWindow::default();
        assert_eq!(w.stats(), (0, 0.0, 0));
        for lag in 0..1500u64 {
            w.push(lag);
        }
        let (min, mean, max) = w.stats();
        assert_eq!((min, max), (500, 1499));
        assert!((mean - 999.5).abs() < 1e-9);
    }
}
