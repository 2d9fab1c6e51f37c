//! The algorithms behind the [`Agent`] interface, chosen by name: the one
//! place that knows both DDPG and PPO, so that neither they nor agent.rs
//! import each other in a circle.

use crate::algo::agent::{Agent, AgentSetup};
use crate::config::Connection;
use crate::LearnerError;

/// Builds the agent (DDPG or PPO with the given actor) on `run.device`.
pub fn make_agent(
    algo: crate::config::Algo,
    connection: Connection,
    cfg: &crate::config::TrainConfig,
    mask: &[Vec<u8>],
    m: usize,
    n: usize,
) -> Result<Box<dyn Agent>, LearnerError> {
    use crate::config::Algo;
    let device = crate::device::torch::resolve_device(&cfg.run.device)?;
    let setup = AgentSetup { connection, mask, state_dim: m, action_dim: n, seed: cfg.run.seed, device };
    Ok(match algo {
        Algo::Ddpg => {
            let mut ddpg = crate::algo::ddpg::Ddpg::new(&cfg.ddpg, &cfg.network, setup);
            if device.is_cuda() && cfg.run.cuda_graphs {
                match ddpg.use_cuda_graphs() {
                    Ok(()) => tracing::info!("DDPG updates run as CUDA graphs"),
                    Err(why) => tracing::warn!("CUDA graphs unavailable, DDPG updates run eagerly: {why}"),
                }
            }
            Box::new(ddpg)
        }
        Algo::Ppo => Box::new(crate::algo::ppo::Ppo::new(&cfg.ppo, &cfg.network, setup)),
    })
}
