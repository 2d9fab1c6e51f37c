//! The settings the learner's tests start from, one copy for every room:
//! configs/lti-fast.toml as it is, or made very small for the tests of
//! mechanics.

use std::path::Path;

use super::TrainConfig;

/// configs/lti-fast.toml: the settings that learn lti-paper.
pub(crate) fn lti_fast() -> TrainConfig {
    TrainConfig::load(Path::new(concat!(env!("CARGO_MANIFEST_DIR"), "/../configs/lti-fast.toml"))).unwrap()
}

/// A very small DDPG and PPO setting for tests of mechanics, not of
/// learning quality: 4 episodes, a checkpoint every 2, 2 evaluation
/// episodes.
pub(crate) fn tiny() -> TrainConfig {
    let mut cfg = lti_fast();
    (cfg.ddpg.warmup_steps, cfg.ddpg.batch_size) = (40, 16);
    (cfg.ppo.rollout_steps, cfg.ppo.minibatch_size, cfg.ppo.epochs) = (64, 16, 2);
    (cfg.run.episodes, cfg.run.checkpoint_every, cfg.run.eval_episodes) = (4, 2, 2);
    cfg
}

/// [`tiny`] with another episode budget.
pub(crate) fn tiny_with_episodes(episodes: usize) -> TrainConfig {
    let mut cfg = tiny();
    cfg.run.episodes = episodes;
    cfg
}
