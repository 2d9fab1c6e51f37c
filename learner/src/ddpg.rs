//! DDPG with the LCRL actor (METHOD.md §5, Algorithm 2).
//!
//! Per environment step: act with μ(s) + Gaussian noise (uniform random
//! during warm-up), store the transition, and once warm do one update:
//!   y      = r + γ (1 − done) Q'(s', μ'(s'))
//!   L_Q    = mean (Q(s, a) − y)²
//!   L_μ    = −mean Q(s, μ(s))
//!   θ'     ← τ θ + (1 − τ) θ'            (both targets)
//!
//! Optional stabilizers from TD3, off by default (Algorithm 2 as
//! published): `policy_delay` (actor and targets updated every d-th step),
//! `target_noise` (clipped noise on μ'(s') in y) and `twin_critics`
//! (y uses min(Q₁', Q₂'), against the overestimation that drives the actor
//! to saturated actions). `anneal_lr` lowers both learning rates to 0 over
//! the run.

use std::path::Path;
use std::time::Instant;

use rand::{Rng, SeedableRng};
use rand_chacha::ChaCha8Rng;
use rand_distr::{Distribution, Normal};
use serde::{Deserialize, Serialize};
use tch::{nn, Device, Kind, Tensor};

use crate::adam::Adam;
use crate::agent::{
    build_actor, build_critic, load_optimizers, load_vs, read_agent_state, read_tensors, save_optimizers, save_vs, write_agent_state, write_tensors, Agent,
    Counters, RngState, Transition,
};
use crate::config::{Connection, DdpgConfig, NetworkConfig};
use crate::nets::{batch, ActorNet, Mlp};
use crate::replay::ReplayBuffer;
use crate::LearnerError;

pub struct Ddpg {
    cfg: DdpgConfig,
    device: Device,
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
    /// Share of the run done (0..1), for annealed settings.
    progress: f64,
    /// TD3's second critic (with `twin_critics`).
    twin: Option<TwinCritic>,
}

/// The second critic of clipped double-Q learning, with its target and
/// optimizer.
struct TwinCritic {
    vs: nn::VarStore,
    net: Mlp,
    target_vs: nn::VarStore,
    target: Mlp,
    opt: Adam,
}

impl TwinCritic {
    fn new(cfg: &DdpgConfig, net: &NetworkConfig, inputs: usize, seed: u64, device: Device) -> Self {
        let vs = nn::VarStore::new(device);
        let critic = build_critic(&vs.root(), inputs, net, seed);
        let mut target_vs = nn::VarStore::new(device);
        let target = build_critic(&target_vs.root(), inputs, net, seed);
        let _ = target_vs.copy(&vs);
        TwinCritic { opt: Adam::new(&vs, cfg.critic_lr), vs, net: critic, target_vs, target }
    }
}

/// What state.json of a DDPG checkpoint holds besides tensors.
#[derive(Serialize, Deserialize)]
struct DdpgState {
    rng: RngState,
    counters: Counters,
    critic_updates: u64,
}

impl Ddpg {
    #[allow(clippy::too_many_arguments)]
    pub fn new(cfg: &DdpgConfig, net: &NetworkConfig, connection: Connection, mask: &[Vec<u8>], m: usize, n: usize, seed: u64, device: Device) -> Self {
        let actor_vs = nn::VarStore::new(device);
        let actor = build_actor(&actor_vs.root(), connection, mask, m, n, net, seed ^ 0xAC70);
        let mut actor_target_vs = nn::VarStore::new(device);
        let actor_target = build_actor(&actor_target_vs.root(), connection, mask, m, n, net, seed ^ 0xAC70);
        let critic_vs = nn::VarStore::new(device);
        let critic = build_critic(&critic_vs.root(), m + n, net, seed ^ 0xC717);
        let mut critic_target_vs = nn::VarStore::new(device);
        let critic_target = build_critic(&critic_target_vs.root(), m + n, net, seed ^ 0xC717);
        // Targets start as exact copies (same variable names by construction).
        let _ = actor_target_vs.copy(&actor_vs);
        let _ = critic_target_vs.copy(&critic_vs);
        let twin = cfg.twin_critics.then(|| TwinCritic::new(cfg, net, m + n, seed ^ 0xC718, device));
        let mut soft_pairs = Vec::new();
        let mut stores = vec![(&actor_target_vs, &actor_vs), (&critic_target_vs, &critic_vs)];
        if let Some(t) = &twin {
            stores.push((&t.target_vs, &t.vs));
        }
        for (target, source) in stores {
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
            device,
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
            progress: 0.0,
            twin,
        }
    }

    /// Exploration noise standard deviation at `episode` (linear decay).
    pub fn noise_std(&self, episode: usize) -> f64 {
        let progress = (episode as f64 / self.cfg.noise_decay_episodes.max(1) as f64).min(1.0);
        self.cfg.noise_start + (self.cfg.noise_end - self.cfg.noise_start) * progress
    }

    /// One DDPG update on a minibatch from the replay buffer.
    fn update(&mut self) {
        let b = self.replay.sample(self.cfg.batch_size, &mut self.rng).to_device(self.device);
        let target: Tensor = tch::no_grad(|| {
            let mut next_action = self.actor_target.forward(&b.next_obs);
            if self.cfg.target_noise > 0.0 {
                let noise = Normal::new(0.0, self.cfg.target_noise).expect("validated target_noise");
                let values: Vec<f32> = (0..next_action.numel()).map(|_| noise.sample(&mut self.rng).clamp(-0.5, 0.5) as f32).collect();
                let noise = Tensor::from_slice(&values).to_device(self.device).view_as(&next_action);
                next_action = (next_action + noise).clamp(-1.0, 1.0);
            }
            let next_input = Tensor::cat(&[&b.next_obs, &next_action], 1);
            let mut next_q = self.critic_target.forward(&next_input);
            if let Some(twin) = &self.twin {
                next_q = next_q.minimum(&twin.target.forward(&next_input));
            }
            &b.reward + self.cfg.gamma * (1.0 - &b.done) * next_q
        });
        let input = Tensor::cat(&[&b.obs, &b.action], 1);
        let loss = |q: Tensor| {
            if self.cfg.huber_delta > 0.0 {
                q.huber_loss(&target, tch::Reduction::Mean, self.cfg.huber_delta)
            } else {
                (q - &target).square().mean(Kind::Float)
            }
        };
        let critic_loss = loss(self.critic.forward(&input));
        self.critic_opt.zero_grad();
        critic_loss.backward();
        self.critic_opt.step();
        if let Some(twin) = &mut self.twin {
            let twin_loss = loss(twin.net.forward(&input));
            twin.opt.zero_grad();
            twin_loss.backward();
            twin.opt.step();
        }
        self.critic_updates += 1;
        if self.critic_updates % self.cfg.policy_delay as u64 != 0 {
            return;
        }

        let raw = self.actor.forward_raw(&b.obs);
        let q = self.critic.forward(&Tensor::cat(&[&b.obs, &raw.tanh()], 1));
        let l2 = if self.cfg.preactivation_anneal { self.cfg.preactivation_l2 * (1.0 - self.progress) } else { self.cfg.preactivation_l2 };
        let actor_loss = -q.mean(Kind::Float) + l2 * raw.square().mean(Kind::Float);
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
        tch::no_grad(|| {
            let action = self.actor.forward(&batch(obs, self.obs_dim, self.device));
            Vec::<f32>::try_from(action.flatten(0, -1).to_device(Device::Cpu)).unwrap_or_default()
        })
    }

    fn store(&mut self, t: Transition) {
        self.replay.push(t.obs, t.action, t.reward, t.next_obs, t.terminated);
        self.counters.env_steps += 1;
    }

    fn train_step(&mut self) -> f64 {
        if self.replay.len() < self.cfg.warmup_steps.max(self.cfg.batch_size) {
            return 0.0;
        }
        let started = Instant::now();
        self.update();
        started.elapsed().as_secs_f64()
    }

    fn stored(&self) -> usize {
        self.replay.len()
    }

    fn set_progress(&mut self, fraction: f64) {
        self.progress = fraction.clamp(0.0, 1.0);
        if self.cfg.anneal_lr {
            let left = 1.0 - self.progress;
            self.actor_opt.set_lr(self.cfg.actor_lr * left);
            self.critic_opt.set_lr(self.cfg.critic_lr * left);
            if let Some(twin) = &mut self.twin {
                twin.opt.set_lr(self.cfg.critic_lr * left);
            }
        }
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
        save_optimizers(dir, &self.actor_opt, &self.critic_opt)?;
        if let Some(twin) = &self.twin {
            save_vs(&twin.vs, &dir.join("critic2.safetensors"))?;
            save_vs(&twin.target_vs, &dir.join("critic2_target.safetensors"))?;
            write_tensors(&dir.join("critic2_optimizer.safetensors"), &twin.opt.state())?;
        }
        if include_buffer {
            write_tensors(&dir.join("replay.safetensors"), &self.replay.to_tensors())?;
        }
        let state = DdpgState { rng: RngState::of(&self.rng), counters: self.counters, critic_updates: self.critic_updates };
        write_agent_state(dir, &state)
    }

    fn load(&mut self, dir: &Path) -> Result<(), LearnerError> {
        load_vs(&mut self.actor_vs, &dir.join("actor.safetensors"))?;
        load_vs(&mut self.actor_target_vs, &dir.join("actor_target.safetensors"))?;
        load_vs(&mut self.critic_vs, &dir.join("critic.safetensors"))?;
        load_vs(&mut self.critic_target_vs, &dir.join("critic_target.safetensors"))?;
        load_optimizers(dir, &mut self.actor_opt, &mut self.critic_opt)?;
        if let Some(twin) = &mut self.twin {
            load_vs(&mut twin.vs, &dir.join("critic2.safetensors"))?;
            load_vs(&mut twin.target_vs, &dir.join("critic2_target.safetensors"))?;
            twin.opt.load_state(&read_tensors(&dir.join("critic2_optimizer.safetensors"))?).map_err(LearnerError::Checkpoint)?;
        }
        let replay = dir.join("replay.safetensors");
        if replay.is_file() {
            self.replay = ReplayBuffer::from_tensors(self.cfg.buffer_capacity, self.obs_dim, self.action_dim, &read_tensors(&replay)?)
                .map_err(LearnerError::Checkpoint)?;
        }
        let state: DdpgState = read_agent_state(dir)?;
        self.rng = state.rng.restore()?;
        self.counters = state.counters;
        self.critic_updates = state.critic_updates;
        Ok(())
    }

    fn actor_variables(&self) -> Vec<(String, Tensor)> {
        crate::agent::sorted_variables(&self.actor_vs)
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::config::TrainConfig;

    /// The update rule, without the on-policy feedback loop: on exploratory
    /// data of s' = s + a with r = −(s² + 0.1a²), DDPG's actor must move to
    /// the optimal gain. With γ = 0.95 the Riccati solution is P ≈ 1.09 and
    /// a* = −γP/(0.1 + γP)·s ≈ −0.91·s. Also with twin critics: the minimum
    /// of two critics in y must not bias the gain away from the optimum.
    #[test]
    fn update_rule_finds_the_optimal_gain_on_exploratory_data() {
        // One intra-op thread, as training runs use: libtorch's default (one
        // per core) spin-waits against the other test process on 2 cores.
        tch::set_num_threads(1);
        for twin_critics in [false, true] {
            let mut cfg = TrainConfig::default();
            cfg.network.global_hidden = vec![64, 64];
            cfg.network.critic_hidden = vec![64, 64];
            let ddpg = DdpgConfig { actor_lr: 1e-3, critic_lr: 1e-3, tau: 0.01, gamma: 0.95, batch_size: 128, warmup_steps: 0, twin_critics, ..cfg.ddpg };
            let mut agent = Ddpg::new(&ddpg, &cfg.network, Connection::Global, &[vec![1]], 1, 1, 3, Device::Cpu);
            assert_eq!(agent.twin.is_some(), twin_critics);
            let mut rng = ChaCha8Rng::seed_from_u64(4);
            for _ in 0..5000 {
                let s: f32 = rng.random_range(-2.0..2.0);
                let a: f32 = rng.random_range(-1.0..1.0);
                agent.replay.push(&[s], &[a], -(s * s + 0.1 * a * a), &[s + a], false);
            }
            for _ in 0..4000 {
                agent.update();
            }
            for s in [-0.5f32, -0.25, 0.25, 0.5] {
                let a = agent.act(&[s])[0];
                assert!((a + 0.91 * s).abs() < 0.1, "twin critics {twin_critics}: μ({s}) = {a}, optimum {}", -0.91 * s);
            }
        }
    }
}
