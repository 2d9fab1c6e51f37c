//! DDPG with the LCRL actor (METHOD.md §5, Algorithm 2).
//!
//! Per environment step: act with μ(s) + Gaussian noise (uniform random
//! during warm-up), store the transition, and once warm do one update:
//!   y      = r + γ (1 − done) Q'(s', μ'(s'))
//!   L_Q    = mean (Q(s, a) − y)²
//!   L_μ    = −mean Q(s, μ(s))
//!   θ'     ← τ θ + (1 − τ) θ'            (both targets)
//!
//! Two optional stabilizers from TD3, off by default (Algorithm 2 as
//! published): `policy_delay` (actor and targets updated every d-th step)
//! and `target_noise` (clipped noise on μ'(s') in y).

use std::path::Path;
use std::time::Instant;

use rand::{Rng, SeedableRng};
use rand_chacha::ChaCha8Rng;
use rand_distr::{Distribution, Normal};
use serde::{Deserialize, Serialize};
use tch::{nn, Device, Kind, Tensor};

use crate::adam::Adam;
use crate::agent::{build_actor, build_critic, load_vs, read_tensors, save_vs, write_tensors, Agent, Counters, RngState, Transition};
use crate::config::{Connection, DdpgConfig, NetworkConfig};
use crate::nets::{batch, ActorNet, Mlp};
use crate::replay::ReplayBuffer;
use crate::LearnerError;

pub struct Ddpg {
    cfg: DdpgConfig,
    obs_dim: usize,
    action_dim: usize,
    actor_vs: nn::VarStore,
    actor: ActorNet,
    actor_target_vs: nn::VarStore,
    actor_target: ActorNet,
    critic_vs: nn::VarStore,
    critic: Mlp,
    critic_target_vs: nn::VarStore,
    critic_target: Mlp,
    actor_opt: Adam,
    critic_opt: Adam,
    /// (target, source) variable pairs for the soft update.
    soft_pairs: Vec<(Tensor, Tensor)>,
    replay: ReplayBuffer,
    rng: ChaCha8Rng,
    counters: Counters,
    critic_updates: u64,
}

/// What state.json of a DDPG checkpoint holds besides tensors.
#[derive(Serialize, Deserialize)]
struct DdpgState {
    rng: RngState,
    counters: Counters,
    critic_updates: u64,
}

impl Ddpg {
    pub fn new(cfg: &DdpgConfig, net: &NetworkConfig, connection: Connection, mask: &[Vec<u8>], m: usize, n: usize, seed: u64) -> Self {
        let device = Device::Cpu;
        let actor_vs = nn::VarStore::new(device);
        let actor = build_actor(&actor_vs.root(), connection, mask, m, n, net);
        let mut actor_target_vs = nn::VarStore::new(device);
        let actor_target = build_actor(&actor_target_vs.root(), connection, mask, m, n, net);
        let critic_vs = nn::VarStore::new(device);
        let critic = build_critic(&critic_vs.root(), m + n, net);
        let mut critic_target_vs = nn::VarStore::new(device);
        let critic_target = build_critic(&critic_target_vs.root(), m + n, net);
        // Targets start as exact copies (same variable names by construction).
        let _ = actor_target_vs.copy(&actor_vs);
        let _ = critic_target_vs.copy(&critic_vs);
        let mut soft_pairs = Vec::new();
        for (target, source) in [(&actor_target_vs, &actor_vs), (&critic_target_vs, &critic_vs)] {
            let sources = source.variables();
            for (name, t) in target.variables() {
                if let Some(s) = sources.get(&name) {
                    soft_pairs.push((t, s.shallow_clone()));
                }
            }
        }
        Ddpg {
            actor_opt: Adam::new(&actor_vs, cfg.actor_lr),
            critic_opt: Adam::new(&critic_vs, cfg.critic_lr),
            cfg: cfg.clone(),
            obs_dim: m,
            action_dim: n,
            actor_vs,
            actor,
            actor_target_vs,
            actor_target,
            critic_vs,
            critic,
            critic_target_vs,
            critic_target,
            soft_pairs,
            replay: ReplayBuffer::new(cfg.buffer_capacity, m, n),
            rng: ChaCha8Rng::seed_from_u64(seed ^ 0xDD96),
            counters: Counters::default(),
            critic_updates: 0,
        }
    }

    /// Exploration noise standard deviation at `episode` (linear decay).
    pub fn noise_std(&self, episode: usize) -> f64 {
        let progress = (episode as f64 / self.cfg.noise_decay_episodes.max(1) as f64).min(1.0);
        self.cfg.noise_start + (self.cfg.noise_end - self.cfg.noise_start) * progress
    }

    /// ∂Q/∂a of the current critic at (obs, action) (diagnostics, tests).
    pub fn critic_action_gradient(&self, obs: &[f32], action: &[f32]) -> Vec<f32> {
        let o = batch(obs, self.obs_dim, Device::Cpu);
        let a = batch(action, self.action_dim, Device::Cpu).set_requires_grad(true);
        let q = self.critic.forward(&Tensor::cat(&[&o, &a], 1)).sum(Kind::Float);
        let grads = Tensor::run_backward(&[q], &[&a], false, false);
        Vec::try_from(grads[0].flatten(0, -1)).unwrap_or_default()
    }

    pub fn replay_len(&self) -> usize {
        self.replay.len()
    }

    /// One DDPG update on a minibatch from the replay buffer.
    fn update(&mut self) {
        let b = self.replay.sample(self.cfg.batch_size, &mut self.rng);
        let target: Tensor = tch::no_grad(|| {
            let mut next_action = self.actor_target.forward(&b.next_obs);
            if self.cfg.target_noise > 0.0 {
                let noise = (next_action.randn_like() * self.cfg.target_noise).clamp(-0.5, 0.5);
                next_action = (next_action + noise).clamp(-1.0, 1.0);
            }
            let next_q = self.critic_target.forward(&Tensor::cat(&[&b.next_obs, &next_action], 1));
            &b.reward + self.cfg.gamma * (1.0 - &b.done) * next_q
        });
        let q = self.critic.forward(&Tensor::cat(&[&b.obs, &b.action], 1));
        let critic_loss = (q - target).square().mean(Kind::Float);
        self.critic_opt.zero_grad();
        critic_loss.backward();
        self.critic_opt.step();
        self.critic_updates += 1;
        if self.critic_updates % self.cfg.policy_delay as u64 != 0 {
            return;
        }

        let raw = self.actor.forward_raw(&b.obs);
        let q = self.critic.forward(&Tensor::cat(&[&b.obs, &raw.tanh()], 1));
        let actor_loss = -q.mean(Kind::Float) + self.cfg.preactivation_l2 * raw.square().mean(Kind::Float);
        self.actor_opt.zero_grad();
        actor_loss.backward();
        self.actor_opt.step();

        let tau = self.cfg.tau;
        tch::no_grad(|| {
            for (target, source) in &mut self.soft_pairs {
                let mixed = source.as_ref() * tau + target.as_ref() * (1.0 - tau);
                target.copy_(&mixed);
            }
        });
        self.counters.updates += 1;
    }
}

impl Agent for Ddpg {
    fn explore(&mut self, obs: &[f32], episode: usize) -> Vec<f32> {
        if self.replay.len() < self.cfg.warmup_steps {
            return (0..self.action_dim).map(|_| self.rng.random_range(-1.0..=1.0)).collect();
        }
        let std = self.noise_std(episode);
        let mean = self.act(obs);
        // Cannot fail: std is finite and ≥ 0 (validated config).
        let noise = Normal::new(0.0, std).expect("validated noise");
        mean.iter().map(|&a| (f64::from(a) + noise.sample(&mut self.rng)).clamp(-1.0, 1.0) as f32).collect()
    }

    fn act(&self, obs: &[f32]) -> Vec<f32> {
        tch::no_grad(|| Vec::<f32>::try_from(self.actor.forward(&batch(obs, self.obs_dim, Device::Cpu)).flatten(0, -1)).unwrap_or_default())
    }

    fn observe(&mut self, t: Transition) -> f64 {
        self.replay.push(t.obs, t.action, t.reward, t.next_obs, t.terminated);
        self.counters.env_steps += 1;
        if self.replay.len() < self.cfg.warmup_steps.max(self.cfg.batch_size) {
            return 0.0;
        }
        let started = Instant::now();
        self.update();
        started.elapsed().as_secs_f64()
    }

    fn counters(&self) -> Counters {
        self.counters
    }

    fn param_counts(&self) -> (usize, usize) {
        (self.actor.param_count(), self.critic.param_count())
    }

    fn save(&self, dir: &Path, include_buffer: bool) -> Result<(), LearnerError> {
        save_vs(&self.actor_vs, &dir.join("actor.safetensors"))?;
        save_vs(&self.actor_target_vs, &dir.join("actor_target.safetensors"))?;
        save_vs(&self.critic_vs, &dir.join("critic.safetensors"))?;
        save_vs(&self.critic_target_vs, &dir.join("critic_target.safetensors"))?;
        write_tensors(&dir.join("actor_optimizer.safetensors"), &self.actor_opt.state())?;
        write_tensors(&dir.join("critic_optimizer.safetensors"), &self.critic_opt.state())?;
        if include_buffer {
            write_tensors(&dir.join("replay.safetensors"), &self.replay.to_tensors())?;
        }
        let state = DdpgState { rng: RngState::of(&self.rng), counters: self.counters, critic_updates: self.critic_updates };
        let text = serde_json::to_string_pretty(&state).map_err(|e| LearnerError::Checkpoint(e.to_string()))?;
        std::fs::write(dir.join("agent.json"), text).map_err(|source| LearnerError::Io { path: dir.join("agent.json"), source })
    }

    fn load(&mut self, dir: &Path) -> Result<(), LearnerError> {
        load_vs(&mut self.actor_vs, &dir.join("actor.safetensors"))?;
        load_vs(&mut self.actor_target_vs, &dir.join("actor_target.safetensors"))?;
        load_vs(&mut self.critic_vs, &dir.join("critic.safetensors"))?;
        load_vs(&mut self.critic_target_vs, &dir.join("critic_target.safetensors"))?;
        self.actor_opt.load_state(&read_tensors(&dir.join("actor_optimizer.safetensors"))?).map_err(LearnerError::Checkpoint)?;
        self.critic_opt.load_state(&read_tensors(&dir.join("critic_optimizer.safetensors"))?).map_err(LearnerError::Checkpoint)?;
        let replay = dir.join("replay.safetensors");
        if replay.is_file() {
            self.replay = ReplayBuffer::from_tensors(self.cfg.buffer_capacity, self.obs_dim, self.action_dim, &read_tensors(&replay)?)
                .map_err(LearnerError::Checkpoint)?;
        }
        let path = dir.join("agent.json");
        let text = std::fs::read_to_string(&path).map_err(|source| LearnerError::Io { path: path.clone(), source })?;
        let state: DdpgState = serde_json::from_str(&text).map_err(|e| LearnerError::Checkpoint(format!("{}: {e}", path.display())))?;
        self.rng = state.rng.restore()?;
        self.counters = state.counters;
        self.critic_updates = state.critic_updates;
        Ok(())
    }

    fn actor(&self) -> &ActorNet {
        &self.actor
    }
}
