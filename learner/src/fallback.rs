//! Falling back to the run's selected policy while the current one scores
//! below its base (docs/peg.md, "Training that stays near its base").
//!
//! A robot that trains lives through every training episode. Residual
//! DDPG's curve dips well below its base while the actor leaves it (the
//! dips of peg-group1 and peg-group2), and a brake on the actor (the trust
//! region) holds the curve only by slowing what the run learns. This rule
//! guards the episodes instead of the updates: when a training episode of
//! the current policy returns less than the base's validation return
//! minus `margin`, the next `episodes` training episodes act with the
//! run's selected policy (RUN/selected/, the best of its validations,
//! deterministic), and then the current policy is tried again. Every
//! episode's transitions go to the replay buffer and the updates go on as
//! always, so the current policy keeps learning while it is not acting.
//!
//! The rule's state follows from the episode returns alone, so a resumed
//! run rebuilds it exactly from its metrics ([`Fallback::replayed`]).
//! DDPG only: the selected policy's episodes are off-policy data, which
//! PPO cannot use.

/// Which policy acts in a training episode.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Acting {
    /// The policy being trained, with its exploration.
    Current,
    /// The run's selected policy, deterministic.
    Selected,
}

/// The fallback rule and where it stands.
#[derive(Debug, Clone, PartialEq)]
pub struct Fallback {
    /// A current-policy episode below this return hands the next episodes
    /// to the selected policy: the base's validation return minus the margin.
    below: f64,
    /// How many episodes the selected policy then acts.
    episodes: usize,
    /// Selected-policy episodes left before the current policy acts again.
    left: usize,
    /// Episodes the selected policy acted so far.
    acted: usize,
}

impl Fallback {
    /// The rule for a run whose base scored `base_return` on the
    /// validation starts.
    pub fn new(base_return: f64, margin: f64, episodes: usize) -> Self {
        Fallback { below: base_return - margin, episodes, left: 0, acted: 0 }
    }

    /// The rule after the episodes of `returns` (a resumed run's metrics),
    /// as it stood when they were run.
    pub fn replayed(base_return: f64, margin: f64, episodes: usize, returns: impl IntoIterator<Item = f64>) -> Self {
        let mut rule = Fallback::new(base_return, margin, episodes);
        for episode_return in returns {
            rule.record(rule.next(), episode_return);
        }
        rule
    }

    /// The policy that acts in the next training episode.
    pub fn next(&self) -> Acting {
        if self.left > 0 { Acting::Selected } else { Acting::Current }
    }

    /// Records a finished training episode: who acted and its return.
    pub fn record(&mut self, acting: Acting, episode_return: f64) {
        match acting {
            Acting::Current if episode_return < self.below => self.left = self.episodes,
            Acting::Current => {}
            Acting::Selected => {
                self.left = self.left.saturating_sub(1);
                self.acted += 1;
            }
        }
    }

    /// The return below which a current-policy episode hands over.
    pub fn threshold(&self) -> f64 {
        self.below
    }

    /// Episodes the selected policy acted so far.
    pub fn selected_episodes(&self) -> usize {
        self.acted
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn an_episode_below_the_margin_hands_the_next_ones_to_the_selected_policy() {
        // Base −3.5, margin 2: the threshold is −5.5.
        let mut rule = Fallback::new(-3.5, 2.0, 3);
        assert_eq!(rule.threshold(), -5.5);
        let mut acted = Vec::new();
        // Current −5.0 (above), current −6.0 (below): three selected
        // episodes, whatever they score, then the current policy again.
        for episode_return in [-5.0, -6.0, -20.0, -3.0, -3.0, -5.6, -4.0, -5.5] {
            let who = rule.next();
            acted.push(who);
            rule.record(who, episode_return);
        }
        use Acting::{Current as C, Selected as S};
        assert_eq!(acted, [C, C, S, S, S, C, S, S]);
        assert_eq!(rule.selected_episodes(), 5);
        // −5.5 is not below −5.5; the third selected episode is still due.
        assert_eq!(rule.next(), S);
    }

    #[test]
    fn a_resumed_rule_stands_where_the_run_left_it() {
        let returns = [-4.0, -9.0, -3.6, -3.7, -12.0, -3.5, -4.1, -4.2, -3.9];
        for cut in 0..=returns.len() {
            let mut live = Fallback::new(-3.5, 2.0, 2);
            for &r in &returns[..cut] {
                live.record(live.next(), r);
            }
            assert_eq!(Fallback::replayed(-3.5, 2.0, 2, returns[..cut].iter().copied()), live, "after {cut} episodes");
        }
    }

    #[test]
    fn no_episodes_means_no_fallback() {
        let mut rule = Fallback::new(0.0, 1.0, 0);
        rule.record(Acting::Current, -100.0);
        assert_eq!(rule.next(), Acting::Current);
    }
}
