//! A trained actor loaded from a checkpoint, for evaluation and serving.

use std::path::Path;

use lcrl_sim::Env;
use tch::nn;

use crate::agent::{build_actor, load_vs};
use crate::nets::{batch, ActorNet};
use crate::trainer::{read_meta, CheckpointMeta};
use crate::LearnerError;

/// The deterministic policy of a checkpoint.
pub struct Policy {
    pub meta: CheckpointMeta,
    _vs: nn::VarStore,
    actor: ActorNet,
}

impl Policy {
    /// Loads `dir` (a `checkpoints/epNNNNNN` folder, or a run directory,
    /// meaning its newest checkpoint).
    pub fn load(dir: &Path) -> Result<Self, LearnerError> {
        let dir = if dir.join("checkpoint.json").is_file() {
            dir.to_path_buf()
        } else {
            crate::trainer::latest_checkpoint(dir)
                .ok_or_else(|| LearnerError::Checkpoint(format!("{} holds no checkpoint (checkpoint.json)", dir.display())))?
        };
        let meta = read_meta(&dir)?;
        let mut vs = nn::VarStore::new(tch::Device::Cpu);
        // The weights are overwritten by the checkpoint; the seed is irrelevant.
        let actor = build_actor(&vs.root(), meta.connection, &meta.mask, meta.state_dim, meta.action_dim, &meta.config.network, 0);
        load_vs(&mut vs, &dir.join("actor.safetensors"))?;
        Ok(Policy { meta, _vs: vs, actor })
    }

    /// The action for a raw environment state, in the environment's bounds.
    pub fn act(&self, env: &dyn Env, state: &[f64]) -> Vec<f64> {
        let obs: Vec<f32> = env.normalize_state(state).iter().map(|&v| v as f32).collect();
        let u: Vec<f32> = tch::no_grad(|| {
            Vec::<f32>::try_from(self.actor.forward(&batch(&obs, self.meta.state_dim, tch::Device::Cpu)).flatten(0, -1)).unwrap_or_default()
        });
        crate::trainer::to_env_action(env, &u)
    }

    /// Checks that the checkpoint fits `env`.
    pub fn check_env(&self, env: &dyn Env) -> Result<(), LearnerError> {
        let (m, n) = (env.spec().state_dim(), env.spec().action_dim());
        if (m, n) != (self.meta.state_dim, self.meta.action_dim) {
            return Err(LearnerError::Mismatch(format!(
                "the checkpoint was trained on {} ({} states, {} actions); {} has {m} states and {n} actions",
                self.meta.env, self.meta.state_dim, self.meta.action_dim, env.spec().name
            )));
        }
        Ok(())
    }
}
