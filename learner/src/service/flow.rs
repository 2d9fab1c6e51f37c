//! How data flows through the distributed learner: the replay-ratio
//! counters, who waited for whom, the policy lag of stored transitions, and
//! the run's budget. Written by the training thread, read by `GetStatus`,
//! `/metrics` and TensorBoard.

use std::collections::VecDeque;

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
    /// Transitions sampled by updates (DDPG: batch_size per update).
    pub sampled: u64,
    /// Transitions inserted into the replay buffer or rollout.
    pub inserted: u64,
    /// Target samples per insert; 0 when unlimited (or PPO).
    pub replay_ratio_target: f64,
    /// Seconds inserts were refused (the learner was behind: actors waited).
    pub actors_waited_s: f64,
    /// Seconds samples were refused (actors were behind: the learner waited).
    pub learner_waited_s: f64,
    pub lag: LagWindow,
    /// The episode budget (0: none).
    pub budget_episodes: u64,
    /// The budget is reached: final checkpoint and summary written.
    pub finished: bool,
}

impl FlowStats {
    pub fn achieved_ratio(&self) -> f64 {
        if self.inserted == 0 { 0.0 } else { self.sampled as f64 / self.inserted as f64 }
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
