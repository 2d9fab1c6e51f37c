//! The checks every configuration passes on load: each value in its
//! range, and the settings that need one another, each error naming its
//! field.

use super::TrainConfig;
use crate::LearnerError;

impl TrainConfig {
    /// Checks every value, naming the field.
    // long: one flat list of checks, each naming its field, read top to bottom in the order they fail
    pub fn validate(&self) -> Result<(), LearnerError> {
        let bad = |field: &str, why: &str| Err(LearnerError::Config(format!("`{field}` {why}")));
        let positive = [
            ("ddpg.actor_lr", self.ddpg.actor_lr),
            ("ddpg.critic_lr", self.ddpg.critic_lr),
            ("ddpg.tau", self.ddpg.tau),
            ("ppo.actor_lr", self.ppo.actor_lr),
            ("ppo.critic_lr", self.ppo.critic_lr),
            ("ppo.clip", self.ppo.clip),
            ("ppo.max_grad_norm", self.ppo.max_grad_norm),
        ];
        for (field, v) in positive {
            if !(v.is_finite() && v > 0.0) {
                return bad(field, &format!("must be a finite number > 0, got {v}"));
            }
        }
        for (field, v) in [("ddpg.gamma", self.ddpg.gamma), ("ppo.gamma", self.ppo.gamma), ("ppo.gae_lambda", self.ppo.gae_lambda), ("ddpg.tau", self.ddpg.tau)] {
            if !(0.0..=1.0).contains(&v) {
                return bad(field, &format!("must be within [0, 1], got {v}"));
            }
        }
        for (field, v) in [("ddpg.noise_start", self.ddpg.noise_start), ("ddpg.noise_end", self.ddpg.noise_end), ("ddpg.target_noise", self.ddpg.target_noise), ("ddpg.preactivation_l2", self.ddpg.preactivation_l2), ("ddpg.proximal_l2", self.ddpg.proximal_l2), ("ddpg.huber_delta", self.ddpg.huber_delta), ("ppo.entropy_coef", self.ppo.entropy_coef)] {
            if !(v.is_finite() && v >= 0.0) {
                return bad(field, &format!("must be a finite number ≥ 0, got {v}"));
            }
        }
        let has_base = self.base.action != super::BaseController::None;
        for (field, reach) in [("base.residual_scale", Some(self.base.residual_scale)), ("ddpg.residual_scale", self.ddpg.residual_scale)] {
            let Some(reach) = reach else { continue };
            if !super::residual_scale_fits(reach, true) {
                return bad(field, &format!("must lie in (0, 1] (the share of the box's half-width the residual may move the base), got {reach}"));
            }
            if !super::residual_scale_fits(reach, has_base) {
                return bad(field, "needs a base controller (base.action): without one there is no residual to scale");
            }
        }
        if self.run.confirm_candidates > 0 {
            if self.run.validation_episodes == 0 {
                return bad("run.confirm_candidates", "needs validation (run.validation_episodes ≥ 1): it confirms the best validated policies");
            }
            if self.run.confirm_episodes == 0 {
                return bad("run.confirm_episodes", "must be at least 1 when run.confirm_candidates is set (0 candidates turns the confirmation off)");
            }
        }
        if !self.ppo.log_std_init.is_finite() {
            return bad("ppo.log_std_init", "must be finite");
        }
        let at_least_one = [
            ("ddpg.batch_size", self.ddpg.batch_size),
            ("ddpg.buffer_capacity", self.ddpg.buffer_capacity),
            ("ddpg.policy_delay", self.ddpg.policy_delay),
            ("ddpg.update_every", self.ddpg.update_every),
            ("ddpg.gradient_steps", self.ddpg.gradient_steps),
            ("ppo.rollout_steps", self.ppo.rollout_steps),
            ("ppo.epochs", self.ppo.epochs),
            ("ppo.minibatch_size", self.ppo.minibatch_size),
            ("run.episodes", self.run.episodes),
            ("run.checkpoint_every", self.run.checkpoint_every),
            ("run.graph_samples", self.run.graph_samples),
            ("run.validate_every", self.run.validate_every),
        ];
        for (field, v) in at_least_one {
            if v == 0 {
                return bad(field, "must be at least 1");
            }
        }
        // config.toml records every setting, and TOML's integers stop at i64.
        for (field, seed) in [("run.seed (--seed)", Some(self.run.seed)), ("run.eval_seed (--eval-seed)", self.run.eval_seed)] {
            if seed.is_some_and(|s| s > i64::MAX as u64) {
                return bad(field, &format!("must be at most {} (the largest integer config.toml can record), got {}", i64::MAX, seed.unwrap_or(0)));
            }
        }
        if !(self.run.graph_threshold.is_finite() && self.run.graph_threshold > 0.0) {
            return bad("run.graph_threshold", &format!("must be a finite number > 0 (the publication uses 0.1), got {}", self.run.graph_threshold));
        }
        for (field, sizes) in [("network.global_hidden", &self.network.global_hidden), ("network.subnet_hidden", &self.network.subnet_hidden), ("network.critic_hidden", &self.network.critic_hidden)] {
            if sizes.is_empty() || sizes.contains(&0) {
                return bad(field, "must list at least one layer width, each at least 1");
            }
        }
        if self.run.threads > super::MAX_THREADS {
            return bad("run.threads", &format!("must be 0 (automatic) or a thread count up to {}, got {}", super::MAX_THREADS, self.run.threads));
        }
        if !matches!(self.run.device.as_str(), "cpu" | "cuda") {
            return bad("run.device", &format!("must be \"cpu\" or \"cuda\", got \"{}\"", self.run.device));
        }
        Ok(())
    }
}
