//! Falling back to the run's selected policy while the current one scores
//! below its base (the fourth round,
//! docs/research/2026-11-25-peg-safety-04-lighter-brake-and-fallback.md).
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
//! With the gate (`fallback_gate`), the current policy also acts only
//! while its latest validation (held-out starts, in simulation) scored
//! within the margin: a policy that fails its validation does not get to
//! try episodes on the robot, and the rule's retries after a bad episode
//! wait for a validation that passes instead of probing.
//!
//! The rule's state follows from the episode returns and the validations
//! alone, so a resumed run rebuilds it exactly from its metrics and its
//! selection record ([`Fallback::replayed`]).
//!
//! DDPG only: the selected policy's episodes are off-policy data, which
//! PPO cannot use.

impl crate::config::RunConfig {
    /// The fallback rule this run asks for, given its base's validation
    /// return (None when `fallback_margin` is unset). Here rather than in
    /// config: the configuration holds the numbers, this module the rule.
    pub fn fallback(&self, base_return: f64) -> Option<Fallback> {
        let rule = Fallback::new(base_return, self.fallback_margin?, self.fallback_episodes.unwrap_or(5));
        Some(if self.fallback_gate { rule.gated() } else { rule })
    }
}

/// The selected policy as it acts in a fallback episode: deterministic, or
/// (`fallback_explore`) with the run's exploration noise around it, so
/// that the critic also learns from actions beside the selected ones.
pub struct FallbackPolicy {
    policy: crate::policy::trained::Policy,
    /// The noise's standard deviation and its random stream, seeded per
    /// episode so that a resumed run draws the same noise.
    noise: Option<(Vec<f64>, rand_chacha::ChaCha8Rng)>,
}

impl FallbackPolicy {
    /// The selected policy of `run_dir`, acting in training episode
    /// `episode_seed`'s start; `noise_std`: explore with this deviation.
    pub fn load(run_dir: &std::path::Path, noise_std: Option<f64>, episode_seed: u64) -> Result<Self, crate::LearnerError> {
        use rand::SeedableRng;
        let policy = crate::policy::trained::Policy::load(&crate::policy::checkpoint::selected_dir(run_dir))?;
        let n = policy.architecture.shape.action_dim;
        Ok(FallbackPolicy { policy, noise: noise_std.map(|std| (vec![std; n], rand_chacha::ChaCha8Rng::seed_from_u64(episode_seed ^ 0xFA11_BAC4))) })
    }

    /// u for a normalized observation.
    pub fn act(&mut self, obs: &[f32]) -> Vec<f32> {
        let mean = self.policy.act_normalized(obs);
        match &mut self.noise {
            Some((std, rng)) => crate::algo::exploration::gaussian(&mean, std, true, rng),
            None => mean,
        }
    }
}

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
    /// Gate on validations: whether the current policy's latest one scored
    /// below the threshold (it may not act until one passes).
    gate: bool,
    failed_validation: bool,
    /// Episodes the selected policy acted so far.
    acted: usize,
}

impl Fallback {
    /// The rule for a run whose base scored `base_return` on the
    /// validation starts.
    pub fn new(base_return: f64, margin: f64, episodes: usize) -> Self {
        Fallback { below: base_return - margin, episodes, left: 0, gate: false, failed_validation: false, acted: 0 }
    }

    /// The same rule, with the gate on validations.
    pub fn gated(self) -> Self {
        Fallback { gate: true, ..self }
    }

    /// The rule after the episodes of `returns` (a resumed run's metrics)
    /// and the validations `(episodes done, mean return)` made between
    /// them, as it stood when they were run.
    pub fn replayed(mut self, returns: &[f64], validations: &[(usize, f64)]) -> Self {
        for (done, &episode_return) in returns.iter().enumerate() {
            for &(_, mean_return) in validations.iter().filter(|(episode, _)| *episode == done) {
                self.validated(mean_return);
            }
            self.record(self.next(), episode_return);
        }
        for &(_, mean_return) in validations.iter().filter(|(episode, _)| *episode == returns.len()) {
            self.validated(mean_return);
        }
        self
    }

    /// The policy that acts in the next training episode.
    pub fn next(&self) -> Acting {
        if self.left > 0 || (self.gate && self.failed_validation) { Acting::Selected } else { Acting::Current }
    }

    /// Records a validation of the current policy (its mean return on the
    /// held-out starts); only the gate reads it.
    pub fn validated(&mut self, mean_return: f64) {
        self.failed_validation = mean_return < self.below;
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
            assert_eq!(Fallback::new(-3.5, 2.0, 2).replayed(&returns[..cut], &[]), live, "after {cut} episodes");
        }
        // With the gate, validations after 0, 3 and 6 episodes (the one
        // after 3 fails) interleave with the episodes.
        let validations = [(0, -3.5), (3, -6.0), (6, -4.0), (9, -3.0)];
        for cut in 0..=returns.len() {
            let mut live = Fallback::new(-3.5, 2.0, 2).gated();
            for (done, &r) in returns[..cut].iter().enumerate() {
                validations.iter().filter(|v| v.0 == done).for_each(|v| live.validated(v.1));
                live.record(live.next(), r);
            }
            validations.iter().filter(|v| v.0 == cut).for_each(|v| live.validated(v.1));
            assert_eq!(Fallback::new(-3.5, 2.0, 2).gated().replayed(&returns[..cut], &validations), live, "after {cut} episodes");
        }
    }

    #[test]
    fn the_gate_keeps_a_policy_that_failed_its_validation_from_acting() {
        let mut rule = Fallback::new(-3.5, 2.0, 2).gated();
        rule.validated(-3.4);
        assert_eq!(rule.next(), Acting::Current);
        rule.validated(-6.0);
        // However many episodes pass, until a validation passes.
        for _ in 0..7 {
            assert_eq!(rule.next(), Acting::Selected);
            rule.record(Acting::Selected, -3.0);
        }
        rule.validated(-5.5);
        assert_eq!(rule.next(), Acting::Current, "−5.5 is not below −5.5");
        // Without the gate, a failed validation changes nothing.
        let mut plain = Fallback::new(-3.5, 2.0, 2);
        plain.validated(-60.0);
        assert_eq!(plain.next(), Acting::Current);
    }

    #[test]
    fn no_episodes_means_no_fallback() {
        let mut rule = Fallback::new(0.0, 1.0, 0);
        rule.record(Acting::Current, -100.0);
        assert_eq!(rule.next(), Acting::Current);
    }
}
