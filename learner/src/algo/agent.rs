//! What the training loop needs from an algorithm, and the pieces DDPG and
//! PPO share: building the actor and critics, and saving/restoring an RNG.

use std::path::Path;

use rand::SeedableRng;
use rand_chacha::ChaCha8Rng;
use serde::{Deserialize, Serialize};
use tch::nn;

use crate::config::{Connection, NetworkConfig};
use crate::algo::nets::{ActorNet, Mlp, SubnetActor};
use crate::LearnerError;

/// What an agent is built for, besides its algorithm's settings: the
/// actor's connection and graph G (docs/method.md eq. 7: row i lists the
/// states action i sees), the dimensions m (states) and n (actions), the
/// seed of its initial weights and exploration, and the device.
#[derive(Clone, Copy, Debug)]
pub struct AgentSetup<'a> {
    pub connection: Connection,
    pub mask: &'a [Vec<u8>],
    pub state_dim: usize,
    pub action_dim: usize,
    pub seed: u64,
    pub device: tch::Device,
}

/// One environment step as the learner sees it (normalized units).
#[derive(Default)]
pub struct Transition<'a> {
    pub obs: &'a [f32],
    /// The normalized action the agent chose (before clipping to [−1, 1]
    /// for PPO's Gaussian samples).
    pub action: &'a [f32],
    pub reward: f32,
    pub next_obs: &'a [f32],
    pub terminated: bool,
    pub truncated: bool,
    /// log π(u|s) under the policy that acted, when the step came from an
    /// actor that sent it (PPO's behaviour log-probability). None: the agent
    /// evaluates it with its current policy on storing, which in
    /// `lcrl train`'s loop is the policy that acted.
    pub log_prob: Option<f32>,
    /// An actor's batch ended this environment's stream here, mid-episode
    /// (never in `lcrl train`, whose episodes arrive whole). Not an
    /// episode end: PPO carries its advantages on to the stream's next
    /// step when that arrives in the same rollout (docs/architecture.md,
    /// "One transition, one meaning").
    pub cut: bool,
    /// The actor the step came from (0 in `lcrl train`): a cut stream
    /// goes on only in steps of the same actor.
    pub stream: u64,
}

/// A raw state as the agent's input: normalized, f32. The one
/// normalization of both loops, the actors, serving and validation.
pub fn observe(env: &dyn lcrl_sim::Env, state: &[f64]) -> Vec<f32> {
    env.normalize_state(state).iter().map(|&v| v as f32).collect()
}

/// Counters carried across checkpoints.
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq, Serialize, Deserialize)]
pub struct Counters {
    pub env_steps: u64,
    /// Gradient steps of the actor.
    pub updates: u64,
    /// Gradient steps of the critic(s) that ran: DDPG's every update (the
    /// actor's one in `policy_delay`, none during a critic head start);
    /// PPO's, one with each actor step unless it was skipped.
    #[serde(default)]
    pub critic_updates: u64,
    /// Steps stored marked `cut` (an actor's batch end mid-episode), and
    /// how many of them PPO joined to their stream's next step.
    #[serde(default)]
    pub cuts: u64,
    #[serde(default)]
    pub cuts_joined: u64,
    /// Updates undone because they left a NaN or ∞ in the networks or
    /// their optimizers (a divergent batch): the weights before them stay.
    #[serde(default)]
    pub skipped_updates: u64,
    /// Episodes `lcrl train` ended because the environment diverged
    /// ([`Agent::end_stream`]); actors count theirs themselves.
    #[serde(default)]
    pub diverged_env: u64,
}

/// A training algorithm over a normalized action space [−1, 1]^n.
pub trait Agent: Send {
    /// The action to take while training (with exploration).
    fn explore(&mut self, obs: &[f32], episode: usize) -> Vec<f32>;
    /// The deterministic action of the current policy.
    fn act(&self, obs: &[f32]) -> Vec<f32>;
    /// Stores a transition (replay buffer or rollout) without training.
    fn store(&mut self, transition: Transition);
    /// Trains once if it is time (DDPG: one update once warm; PPO: the PPO
    /// update once a rollout is full). Returns the seconds spent.
    fn train_step(&mut self) -> f64;
    /// Single-process Algorithm 2: store, then train once.
    fn observe(&mut self, transition: Transition) -> f64 {
        self.store(transition);
        self.train_step()
    }
    /// Ends `lcrl train`'s stream without an episode end: its environment
    /// diverged (`lcrl_sim::diverged`), so the step that did is not stored
    /// and the last stored one bootstraps from its sound next state, as at
    /// a cut nothing continues. Counted as `diverged_env`.
    fn end_stream(&mut self);
    /// Transitions held (replay size, or the current rollout's length).
    fn stored(&self) -> usize;
    /// Tells the agent how far training is (0 at the start, 1 at the end),
    /// for schedules such as PPO's learning-rate annealing.
    fn set_progress(&mut self, _fraction: f64) {}
    /// How actors of a distributed run explore with the current policy
    /// after `episodes` episodes, as `explore` would: (uniformly random
    /// while warming up, Gaussian noise std). None: the policy samples its
    /// own distribution (PPO).
    fn exploration(&self, _episodes: usize) -> Option<(bool, f64)> {
        None
    }
    /// Transitions one `train_step` samples (DDPG: its minibatches), for
    /// the replay-ratio limiter; 0 where updates do not sample a replay
    /// buffer.
    fn samples_per_update(&self) -> usize {
        0
    }
    /// Transitions drawn from the replay buffer so far (DDPG: one minibatch
    /// per critic update, whatever the policy delay), for the limiter.
    fn samples_drawn(&self) -> u64 {
        0
    }
    /// Transitions stored before the first update can happen.
    fn min_size_to_sample(&self) -> usize {
        0
    }
    fn counters(&self) -> Counters;
    /// Parameter counts of (actor, critic).
    fn param_counts(&self) -> (usize, usize);
    /// Writes everything needed to continue exactly (weights, optimizer
    /// state, buffers, RNG) into `dir`.
    fn save(&self, dir: &Path, include_buffer: bool) -> Result<(), LearnerError>;
    fn load(&mut self, dir: &Path) -> Result<(), LearnerError>;
    /// The actor's named variables, for publishing the policy.
    fn actor_variables(&self) -> Vec<(String, tch::Tensor)>;
}

/// What an actor network's wiring is: its connection pattern, G (n × m,
/// for `Local`; ignored otherwise) and its sizes. An [`AgentSetup`] and a
/// published policy's shape (policy::snapshot::ActorShape) each give one.
#[derive(Debug, Clone, Copy)]
pub struct ActorLayout<'a> {
    pub connection: Connection,
    pub mask: &'a [Vec<u8>],
    pub state_dim: usize,
    pub action_dim: usize,
}

impl AgentSetup<'_> {
    pub fn layout(&self) -> ActorLayout<'_> {
        ActorLayout { connection: self.connection, mask: self.mask, state_dim: self.state_dim, action_dim: self.action_dim }
    }

    /// A new actor of this setup in a variable store of its own on its
    /// device (both agents' actors, DDPG's target too, are built so).
    pub fn new_actor(&self, cfg: &NetworkConfig) -> (nn::VarStore, ActorNet) {
        let vs = nn::VarStore::new(self.device);
        let actor = build_actor(&vs.root(), self.layout(), cfg, self.seed ^ 0xAC70);
        (vs, actor)
    }
}

/// Builds the actor of a layout (eq. 8 for `Local`). Initial weights come
/// from `seed` alone.
pub fn build_actor(path: &nn::Path, layout: ActorLayout, cfg: &NetworkConfig, seed: u64) -> ActorNet {
    let ActorLayout { connection, mask, state_dim: m, action_dim: n } = layout;
    let rng = &mut ChaCha8Rng::seed_from_u64(seed);
    match connection {
        Connection::Local => ActorNet::Subnets(SubnetActor::new(path, mask, &cfg.subnet_hidden, cfg.activation, rng)),
        Connection::FullSubnets => ActorNet::Subnets(SubnetActor::new(path, &vec![vec![1; m]; n], &cfg.subnet_hidden, cfg.activation, rng)),
        Connection::Global => {
            let mut sizes = vec![m];
            sizes.extend_from_slice(&cfg.global_hidden);
            sizes.push(n);
            ActorNet::Global(Mlp::new(path, &sizes, cfg.activation, rng))
        }
    }
}

/// A globally connected critic with `inputs` inputs and one output.
pub fn build_critic(path: &nn::Path, inputs: usize, cfg: &NetworkConfig, seed: u64) -> Mlp {
    let mut sizes = vec![inputs];
    sizes.extend_from_slice(&cfg.critic_hidden);
    sizes.push(1);
    Mlp::new(path, &sizes, cfg.activation, &mut ChaCha8Rng::seed_from_u64(seed))
}

/// An RNG's exact position, for checkpoints.
#[derive(Debug, Clone, Serialize, Deserialize)]
pub struct RngState {
    seed: Vec<u8>,
    stream: u64,
    /// u128 as a decimal string (JSON numbers cannot hold it).
    word_pos: String,
}

impl RngState {
    pub fn of(rng: &ChaCha8Rng) -> Self {
        RngState { seed: rng.get_seed().to_vec(), stream: rng.get_stream(), word_pos: rng.get_word_pos().to_string() }
    }

    pub fn restore(&self) -> Result<ChaCha8Rng, LearnerError> {
        let seed: [u8; 32] = self.seed.as_slice().try_into().map_err(|_| LearnerError::Checkpoint("bad RNG seed".into()))?;
        let word_pos: u128 = self.word_pos.parse().map_err(|_| LearnerError::Checkpoint("bad RNG position".into()))?;
        let mut rng = ChaCha8Rng::from_seed(seed);
        rng.set_stream(self.stream);
        rng.set_word_pos(word_pos);
        Ok(rng)
    }
}

/// Saves named tensors as safetensors, mapping errors.
pub fn write_tensors(path: &Path, named: &[(String, tch::Tensor)]) -> Result<(), LearnerError> {
    tch::Tensor::write_safetensors(named, path).map_err(|e| LearnerError::Checkpoint(format!("{}: {e}", path.display())))
}

pub fn read_tensors(path: &Path) -> Result<Vec<(String, tch::Tensor)>, LearnerError> {
    tch::Tensor::read_safetensors(path).map_err(|e| LearnerError::Checkpoint(format!("{}: {e}", path.display())))
}

pub fn save_vs(vs: &nn::VarStore, path: &Path) -> Result<(), LearnerError> {
    vs.save(path).map_err(|e| LearnerError::Checkpoint(format!("{}: {e}", path.display())))
}

pub fn load_vs(vs: &mut nn::VarStore, path: &Path) -> Result<(), LearnerError> {
    vs.load(path).map_err(|e| LearnerError::Checkpoint(format!("{}: {e}", path.display())))
}

/// Saves the actor and critic optimizers' state next to the weights.
pub fn save_optimizers(dir: &Path, actor: &crate::algo::adam::Adam, critic: &crate::algo::adam::Adam) -> Result<(), LearnerError> {
    save_optimizer(dir, "actor", actor)?;
    save_optimizer(dir, "critic", critic)
}

/// Restores what [`save_optimizers`] wrote.
pub fn load_optimizers(dir: &Path, actor: &mut crate::algo::adam::Adam, critic: &mut crate::algo::adam::Adam) -> Result<(), LearnerError> {
    load_optimizer(dir, "actor", actor)?;
    load_optimizer(dir, "critic", critic)
}

/// Writes one optimizer's state as `{name}_optimizer.safetensors`.
pub fn save_optimizer(dir: &Path, name: &str, opt: &crate::algo::adam::Adam) -> Result<(), LearnerError> {
    write_tensors(&dir.join(format!("{name}_optimizer.safetensors")), &opt.state())
}

/// Restores what [`save_optimizer`] wrote.
pub fn load_optimizer(dir: &Path, name: &str, opt: &mut crate::algo::adam::Adam) -> Result<(), LearnerError> {
    opt.load_state(&read_tensors(&dir.join(format!("{name}_optimizer.safetensors")))?).map_err(LearnerError::Checkpoint)
}

/// Writes an agent's non-tensor state (RNG, counters, …) as `agent.json`.
pub fn write_agent_state<T: Serialize>(dir: &Path, state: &T) -> Result<(), LearnerError> {
    let path = dir.join("agent.json");
    let text = serde_json::to_string(state).map_err(|e| LearnerError::Checkpoint(e.to_string()))?;
    std::fs::write(&path, text).map_err(|source| LearnerError::Io { path, source })
}

/// Reads what [`write_agent_state`] wrote.
pub fn read_agent_state<T: serde::de::DeserializeOwned>(dir: &Path) -> Result<T, LearnerError> {
    let path = dir.join("agent.json");
    let text = std::fs::read_to_string(&path).map_err(|source| LearnerError::Io { path: path.clone(), source })?;
    serde_json::from_str(&text).map_err(|e| LearnerError::Checkpoint(format!("{}: {e}", path.display())))
}

/// A VarStore's variables sorted by name (stable order for publishing).
pub fn sorted_variables(vs: &nn::VarStore) -> Vec<(String, tch::Tensor)> {
    let mut named: Vec<(String, tch::Tensor)> = vs.variables().into_iter().collect();
    named.sort_by(|a, b| a.0.cmp(&b.0));
    named
}
