//! DDPG with the LCRL actor (docs/method.md §5, Algorithm 2).
//!
//! Per environment step: act with μ(s) + Gaussian noise (uniform random
//! during warm-up), store the
//! transition, and once warm do one update:
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
//! the run. `critic_warmup_updates` holds the actor still while the critic
//! learns from the first transitions. `preactivation_l2` pulls the actor
//! toward a zero residual (the base), `proximal_l2` toward its own target
//! (a trust region around the recent policy). (An actor learning-rate
//! ramp, pessimism toward the twin critics' disagreement, CAPS's temporal
//! smoothness and warm-up with the policy were measured not to help and
//! removed: docs/peg.md, "Measured and removed".)
//!
//! On a GPU each kind of update is captured once as a CUDA graph and
//! replayed (`run.cuda_graphs`; graphs.rs): the same arithmetic, its
//! changing inputs staged into fixed tensors.

mod graphs;

use std::path::Path;
use std::time::Instant;

use rand::SeedableRng;
use rand_chacha::ChaCha8Rng;
use rand_distr::{Distribution, Normal};
use serde::{Deserialize, Serialize};
use tch::{nn, Device, Kind, Tensor};

use crate::algo::adam::Adam;
use crate::device::cuda_graph::CudaGraph;
use crate::algo::agent::{
    build_critic, load_optimizer, load_vs, read_agent_state, read_tensors, save_optimizer, save_vs, write_agent_state, write_tensors, Agent, AgentSetup,
    Counters, RngState, Transition,
};
use crate::config::{DdpgConfig, NetworkConfig};
use crate::algo::exploration;
use crate::algo::flat::FlatParams;
use crate::algo::nets::{batch, ActorNet, Mlp};
use crate::algo::replay::{Batch, DeviceMirror, ReplayBuffer};
use crate::LearnerError;
use graphs::{CapturedUpdates, HostNumbers, UpdateKind, UpdateNumbers};

pub struct Ddpg {
    cfg: DdpgConfig,
    device: Device,
    obs_dim: usize,
    action_dim: usize,
    actor_vs: nn::VarStore,
    actor: ActorNet,
    actor_target_vs: nn::VarStore,
    actor_target: ActorNet,
    actor_opt: Adam,
    /// Q(s, a): one critic (Algorithm 2), or two with `twin_critics`. The
    /// actor follows the first.
    critics: Vec<Critic>,
    /// (target, source buffer) per network for the soft update.
    soft_pairs: Vec<(FlatParams, Tensor)>,
    replay: ReplayBuffer,
    /// On a GPU: the replay buffer's copy there, where minibatches are
    /// gathered (no host-to-device copy of a whole minibatch per update).
    mirror: Option<DeviceMirror>,
    rng: ChaCha8Rng,
    counters: Counters,
    critic_updates: u64,
    /// Share of the run done (0..1), for annealed settings.
    progress: f64,
    /// With `run.cuda_graphs` on a GPU: updates replayed from CUDA graphs.
    captured: Option<CapturedUpdates>,
    /// Where an update that leaves a NaN or ∞ rewinds to (issue 71).
    rewind: Option<RewindPoint>,
}

/// Updates between two checks for a NaN or ∞ in the buffers, and between
/// two rewind points (a multiple of it, so a point is always taken right
/// after a passed check). A check and a copy at every update cost about a
/// sixth of a small network's update (lti-paper, measured); these cost
/// little. A failed check undoes every update since the last point, at
/// most REWIND_EVERY + CHECK_EVERY; until then a non-finite policy is
/// neither published nor checkpointed (crate::policy::finite).
const CHECK_EVERY: u64 = 8;
const REWIND_EVERY: u64 = 32;

/// Every buffer an update writes, with the counts that go with them.
struct RewindPoint {
    buffers: Tensor,
    critic_updates: u64,
    updates: u64,
    /// Adam's steps: the actor's, then each critic's.
    steps: Vec<i64>,
}

/// A global critic Q(s, a) with its target network and optimizer, saved as
/// `{name}.safetensors`, `{name}_target.safetensors` and
/// `{name}_optimizer.safetensors`.
struct Critic {
    name: &'static str,
    vs: nn::VarStore,
    net: Mlp,
    target_vs: nn::VarStore,
    target: Mlp,
    opt: Adam,
}

impl Critic {
    fn new(name: &'static str, cfg: &DdpgConfig, net: &NetworkConfig, inputs: usize, seed: u64, device: Device) -> Self {
        let vs = nn::VarStore::new(device);
        let critic = build_critic(&vs.root(), inputs, net, seed);
        let mut target_vs = nn::VarStore::new(device);
        let target = build_critic(&target_vs.root(), inputs, net, seed);
        // The target starts as an exact copy (same variable names by construction).
        let _ = target_vs.copy(&vs);
        Critic { name, opt: Adam::new(&vs, cfg.critic_lr), vs, net: critic, target_vs, target }
    }

    fn save(&self, dir: &Path) -> Result<(), LearnerError> {
        save_vs(&self.vs, &dir.join(format!("{}.safetensors", self.name)))?;
        save_vs(&self.target_vs, &dir.join(format!("{}_target.safetensors", self.name)))?;
        save_optimizer(dir, self.name, &self.opt)
    }

    fn load(&mut self, dir: &Path) -> Result<(), LearnerError> {
        load_vs(&mut self.vs, &dir.join(format!("{}.safetensors", self.name)))?;
        load_vs(&mut self.target_vs, &dir.join(format!("{}_target.safetensors", self.name)))?;
        load_optimizer(dir, self.name, &mut self.opt)
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
    pub fn new(cfg: &DdpgConfig, net: &NetworkConfig, setup: AgentSetup) -> Self {
        let (actor_vs, actor) = setup.new_actor(net);
        let (mut actor_target_vs, actor_target) = setup.new_actor(net);
        let AgentSetup { state_dim: m, action_dim: n, seed, device, .. } = setup;
        // The target starts as an exact copy (same variable names by construction).
        let _ = actor_target_vs.copy(&actor_vs);
        let mut critics = vec![Critic::new("critic", cfg, net, m + n, seed ^ 0xC717, device)];
        if cfg.twin_critics {
            critics.push(Critic::new("critic2", cfg, net, m + n, seed ^ 0xC718, device));
        }
        let replay = ReplayBuffer::new(cfg.buffer_capacity, m, n);
        let mirror = device.is_cuda().then(|| DeviceMirror::new(&replay, device));
        let actor_opt = Adam::new(&actor_vs, cfg.actor_lr);
        // Each target's variables in one buffer laid out as its source's
        // (the optimizer's), so the soft update is a few operations per
        // network (flat.rs).
        let sources = std::iter::once((&actor_target_vs, &actor_opt)).chain(critics.iter().map(|c| (&c.target_vs, &c.opt)));
        let soft_pairs = sources
            .map(|(target, source)| {
                let target = FlatParams::new(target.variables());
                assert!(target.same_layout(source.params()), "a target network is built as its source");
                (target, source.params().flat().shallow_clone())
            })
            .collect();
        Ddpg {
            actor_opt,
            cfg: cfg.clone(),
            device,
            obs_dim: m,
            action_dim: n,
            actor_vs,
            actor,
            actor_target_vs,
            actor_target,
            critics,
            soft_pairs,
            replay,
            mirror,
            rng: ChaCha8Rng::seed_from_u64(seed ^ 0xDD96),
            counters: Counters::default(),
            critic_updates: 0,
            progress: 0.0,
            captured: None,
            rewind: None,
        }
    }

    /// Exploration noise standard deviation at `episode` (linear decay).
    pub fn noise_std(&self, episode: usize) -> f64 {
        let progress = (episode as f64 / self.cfg.noise_decay_episodes.max(1) as f64).min(1.0);
        self.cfg.noise_start + (self.cfg.noise_end - self.cfg.noise_start) * progress
    }

    /// Still in the warm-up: it acts uniformly there.
    fn warming_up_uniformly(&self) -> bool {
        self.replay.len() < self.cfg.warmup_steps
    }

    /// What the `critic_updates`-th update does besides the critics' step.
    fn kind_of(&self, critic_updates: u64) -> UpdateKind {
        if critic_updates % self.cfg.policy_delay as u64 != 0 {
            UpdateKind::Critics
        } else if critic_updates > self.cfg.critic_warmup_updates as u64 {
            UpdateKind::Full
        } else {
            // The actor waits for the critic's head start (`critic_warmup_updates`).
            UpdateKind::CriticsAndTargets
        }
    }

    /// Captures updates as CUDA graphs from now on (`run.cuda_graphs`; a
    /// learner on a GPU). Fails, changing nothing, where that is not
    /// possible: on the CPU, or without the graph shim (cuda_graph.rs).
    pub fn use_cuda_graphs(&mut self) -> Result<(), String> {
        if self.mirror.is_none() {
            return Err("CUDA graphs need the learner on a GPU".into());
        }
        let captured = CapturedUpdates::new(self.cfg.batch_size, self.obs_dim, self.action_dim, self.critics.len(), self.cfg.target_noise > 0.0, self.device)?;
        self.captured = Some(captured);
        Ok(())
    }

    /// How many update graphs are captured and in use (0: eager updates).
    pub fn captured_graphs(&self) -> usize {
        self.captured.as_ref().map_or(0, CapturedUpdates::len)
    }

    /// Target policy noise for a minibatch (`target_noise`: clipped
    /// Gaussian, TD3), drawn from the agent's generator; empty without.
    fn target_noise_values(&mut self, batch: usize) -> Vec<f32> {
        if self.cfg.target_noise <= 0.0 {
            return Vec::new();
        }
        let noise = Normal::new(0.0, self.cfg.target_noise).expect("validated target_noise");
        (0..batch * self.action_dim).map(|_| noise.sample(&mut self.rng).clamp(-0.5, 0.5) as f32).collect()
    }

    /// One DDPG update on a minibatch from the replay buffer: eager, or
    /// replayed from a CUDA graph (graphs.rs).
    fn update(&mut self) {
        // Eager or replayed, an update writes the same buffers in place
        // (a graph's inputs and outputs are the agent's own tensors), so one
        // guard covers both: a rewind point copied outside any capture, and
        // the check after the update.
        if self.rewind.is_none() || self.critic_updates.is_multiple_of(REWIND_EVERY) {
            self.rewind = Some(self.rewind_point());
        }
        self.critic_updates += 1;
        let kind = self.kind_of(self.critic_updates);
        // The numbers that change between updates, counted here on the
        // host whether the update runs eagerly or from a graph.
        let critics = self.critics.iter_mut().map(|c| c.opt.advance()).collect();
        let actor = (kind == UpdateKind::Full).then(|| self.actor_opt.advance());
        let l2 = if self.cfg.preactivation_anneal { self.cfg.preactivation_l2 * (1.0 - self.progress) } else { self.cfg.preactivation_l2 };
        let numbers = HostNumbers { critics, actor, preactivation_l2: l2 };
        match self.captured.take() {
            Some(mut captured) => match self.update_captured(&mut captured, kind, &numbers) {
                Ok(()) => self.captured = Some(captured),
                Err(why) => tracing::warn!("CUDA graphs turned off, updates run eagerly from now on: {why}"),
            },
            None => {
                let b = match self.mirror.as_mut() {
                    Some(mirror) => mirror.sample(&self.replay, self.cfg.batch_size, &mut self.rng),
                    None => self.replay.sample(self.cfg.batch_size, &mut self.rng).to_device(self.device),
                };
                let values = self.target_noise_values(self.cfg.batch_size);
                let noise = (!values.is_empty())
                    .then(|| crate::device::torch::to_device_async(Tensor::from_slice(&values), self.device).view([self.cfg.batch_size as i64, self.action_dim as i64]));
                self.apply_update(&b, noise.as_ref(), kind, &numbers.coefficients());
            }
        }
        if self.critic_updates.is_multiple_of(CHECK_EVERY) && !self.buffers_finite() {
            let undone = self.rewind_to_point();
            self.counters.skipped_updates += undone;
            // Logged at 1, 2, 4, 8, … undone updates: a poisoned replay
            // buffer would otherwise log every update.
            if self.counters.skipped_updates.is_power_of_two() {
                tracing::warn!(skipped = self.counters.skipped_updates, "update undone: it left a NaN or infinite number in the networks");
            }
            return;
        }
        if kind != UpdateKind::Critics {
            self.counters.updates += 1;
        }
    }

    /// Every buffer an update writes: each network's parameters with its
    /// Adam moments, and the target copies.
    fn buffers(&self) -> Vec<Tensor> {
        let mut out: Vec<Tensor> = self.actor_opt.buffers().iter().map(|t| t.shallow_clone()).collect();
        for critic in &self.critics {
            out.extend(critic.opt.buffers().iter().map(|t| t.shallow_clone()));
        }
        out.extend(self.soft_pairs.iter().map(|(target, _)| target.flat().shallow_clone()));
        out
    }

    /// All buffers in one copy (one operation: on small networks the
    /// guard's cost is the number of operations, not the bytes).
    fn copy_of_buffers(&self) -> Tensor {
        tch::no_grad(|| Tensor::cat(&self.buffers(), 0))
    }

    /// Whether no buffer holds a NaN or ∞: their sum in f64 (which no sum
    /// of f32 values overflows) is finite exactly then. Two operations and
    /// one read back.
    pub(crate) fn buffers_finite(&self) -> bool {
        let sum = tch::no_grad(|| Tensor::cat(&self.buffers(), 0).sum(Kind::Double));
        f64::try_from(sum).is_ok_and(f64::is_finite)
    }

    fn rewind_point(&self) -> RewindPoint {
        let mut steps = vec![self.actor_opt.steps_taken()];
        steps.extend(self.critics.iter().map(|c| c.opt.steps_taken()));
        RewindPoint { buffers: self.copy_of_buffers(), critic_updates: self.critic_updates, updates: self.counters.updates, steps }
    }

    /// Back to the rewind point: buffers, Adam's steps and the update
    /// counts as they were there. Returns the updates undone (this one and
    /// those since the point).
    fn rewind_to_point(&mut self) -> u64 {
        let Some(point) = self.rewind.as_ref() else { return 0 };
        tch::no_grad(|| {
            let buffers = self.buffers();
            let sizes: Vec<i64> = buffers.iter().map(|t| t.numel() as i64).collect();
            for (mut buffer, saved) in buffers.into_iter().zip(point.buffers.split_with_sizes(sizes.as_slice(), 0)) {
                buffer.copy_(&saved);
            }
        });
        self.actor_opt.set_steps_taken(point.steps[0]);
        for (critic, step) in self.critics.iter_mut().zip(&point.steps[1..]) {
            critic.opt.set_steps_taken(*step);
        }
        let undone = self.critic_updates - point.critic_updates;
        (self.critic_updates, self.counters.updates) = (point.critic_updates, point.updates);
        undone
    }

    /// The update from a graph: the minibatch, noise and numbers staged
    /// into `captured`'s tensors, then the graph of this kind replayed, or
    /// captured first (its warm-up is this update). An error leaves the
    /// update done, eagerly where the graph could not do it.
    fn update_captured(&mut self, captured: &mut CapturedUpdates, kind: UpdateKind, numbers: &HostNumbers) -> Result<(), String> {
        let mirror = self.mirror.as_mut().expect("captured updates run on a GPU, beside a device mirror");
        mirror.sample_into(&self.replay, captured.rows(), &mut self.rng);
        let noise = self.target_noise_values(self.cfg.batch_size);
        captured.stage(numbers, &noise);
        let (b, noise, numbers) = captured.inputs(self.obs_dim, self.action_dim, kind);
        if let Some(graph) = captured.graph(kind) {
            return graph.replay().inspect_err(|_| self.apply_update(&b, noise.as_ref(), kind, &numbers));
        }
        let (graph, ran) = CudaGraph::capture(|| self.apply_update(&b, noise.as_ref(), kind, &numbers));
        if !ran {
            self.apply_update(&b, noise.as_ref(), kind, &numbers);
        }
        captured.insert(kind, graph?);
        Ok(())
    }

    /// The update's arithmetic (docs/method.md §5), on tensors only, so
    /// that it can be captured: the numbers that change between updates
    /// come in `numbers`.
    fn apply_update(&mut self, b: &Batch, noise: Option<&Tensor>, kind: UpdateKind, numbers: &UpdateNumbers) {
        let target: Tensor = tch::no_grad(|| {
            let mut next_action = self.actor_target.forward(&b.next_obs);
            if let Some(noise) = noise {
                next_action = (next_action + noise).clamp(-1.0, 1.0);
            }
            // With twin critics, the smaller of the two target values (TD3).
            let next_input = Tensor::cat(&[&b.next_obs, &next_action], 1);
            let next_q = self.critics.iter().map(|c| c.target.forward(&next_input)).reduce(|a, b| a.minimum(&b)).expect("at least one critic");
            &b.reward + self.cfg.gamma * (1.0 - &b.done) * next_q
        });
        let input = Tensor::cat(&[&b.obs, &b.action], 1);
        for (critic, [step_size, bias2]) in self.critics.iter_mut().zip(&numbers.critics) {
            let q = critic.net.forward(&input);
            let loss = if self.cfg.huber_delta > 0.0 {
                q.huber_loss(&target, tch::Reduction::Mean, self.cfg.huber_delta)
            } else {
                (q - &target).square().mean(Kind::Float)
            };
            critic.opt.zero_grad();
            loss.backward();
            critic.opt.apply(step_size, bias2);
        }
        if kind == UpdateKind::Critics {
            return;
        }

        if let Some([step_size, bias2]) = &numbers.actor {
            let raw = self.actor.forward_raw(&b.obs);
            let input = Tensor::cat(&[&b.obs, &raw.tanh()], 1);
            let q = self.critics[0].net.forward(&input);
            let mut actor_loss = -q.mean(Kind::Float) + numbers.preactivation_l2.scale(&raw.square().mean(Kind::Float));
            if self.cfg.proximal_l2 > 0.0 {
                // The trust region toward the target actor (`proximal_l2`).
                // (tanh is applied again rather than shared with Q's input:
                // the gradient then sums in the order the documented runs
                // were measured with.)
                let anchor = tch::no_grad(|| self.actor_target.forward(&b.obs));
                actor_loss = actor_loss + self.cfg.proximal_l2 * (raw.tanh() - anchor).square().mean(Kind::Float);
            }
            self.actor_opt.zero_grad();
            actor_loss.backward();
            self.actor_opt.apply(step_size, bias2);
        }

        let tau = self.cfg.tau;
        tch::no_grad(|| {
            for (target, source) in &self.soft_pairs {
                let mixed = source * tau + target.flat() * (1.0 - tau);
                target.flat().shallow_clone().copy_(&mixed);
            }
        });
    }
}

impl Agent for Ddpg {
    fn explore(&mut self, obs: &[f32], episode: usize) -> Vec<f32> {
        if self.warming_up_uniformly() {
            return exploration::uniform(self.action_dim, &mut self.rng);
        }
        let std = vec![self.noise_std(episode); self.action_dim];
        exploration::gaussian(&self.act(obs), &std, true, &mut self.rng)
    }

    fn act(&self, obs: &[f32]) -> Vec<f32> {
        tch::no_grad(|| {
            let action = self.actor.forward(&batch(obs, self.obs_dim, self.device));
            Vec::<f32>::try_from(action.flatten(0, -1).to_device(Device::Cpu)).unwrap_or_default()
        })
    }

    fn store(&mut self, t: Transition) {
        // Ingestion checks every field's length before a transition gets
        // here; a transition that still does not fit is refused, not stored
        // misaligned (or a panic on overwrite).
        match self.replay.push(t.obs, t.action, t.reward, t.next_obs, t.terminated) {
            Ok(()) => self.counters.env_steps += 1,
            Err(e) => tracing::warn!("{e}"),
        }
    }

    /// One round: `gradient_steps` updates (1: Algorithm 2's one).
    fn train_step(&mut self) -> f64 {
        if self.replay.len() < self.cfg.warmup_steps.max(self.cfg.batch_size) {
            return 0.0;
        }
        let started = Instant::now();
        for _ in 0..self.cfg.gradient_steps.max(1) {
            self.update();
        }
        started.elapsed().as_secs_f64()
    }

    /// Single-process Algorithm 2 with the throughput settings: a round of
    /// updates every `update_every` stored steps.
    fn observe(&mut self, transition: Transition) -> f64 {
        self.store(transition);
        if self.counters.env_steps % self.cfg.update_every.max(1) as u64 != 0 {
            return 0.0;
        }
        self.train_step()
    }

    fn stored(&self) -> usize {
        self.replay.len()
    }

    fn set_progress(&mut self, fraction: f64) {
        self.progress = fraction.clamp(0.0, 1.0);
        if self.cfg.anneal_lr {
            let left = 1.0 - self.progress;
            self.actor_opt.set_lr(self.cfg.actor_lr * left);
            for critic in &mut self.critics {
                critic.opt.set_lr(self.cfg.critic_lr * left);
            }
        }
    }

    fn exploration(&self, episodes: usize) -> Option<(bool, f64)> {
        Some((self.warming_up_uniformly(), self.noise_std(episodes)))
    }

    fn samples_per_update(&self) -> usize {
        self.cfg.batch_size * self.cfg.gradient_steps.max(1)
    }

    fn samples_drawn(&self) -> u64 {
        self.critic_updates * self.cfg.batch_size as u64
    }

    fn min_size_to_sample(&self) -> usize {
        self.cfg.warmup_steps.max(self.cfg.batch_size)
    }

    fn counters(&self) -> Counters {
        Counters { critic_updates: self.critic_updates, ..self.counters }
    }

    /// Replay keeps transitions apart: nothing links the last one to a
    /// next step, so only the count changes.
    fn end_stream(&mut self) {
        self.counters.diverged_env += 1;
    }

    fn param_counts(&self) -> (usize, usize) {
        (self.actor.param_count(), self.critics[0].net.param_count())
    }

    fn save(&self, dir: &Path, include_buffer: bool) -> Result<(), LearnerError> {
        save_vs(&self.actor_vs, &dir.join("actor.safetensors"))?;
        save_vs(&self.actor_target_vs, &dir.join("actor_target.safetensors"))?;
        save_optimizer(dir, "actor", &self.actor_opt)?;
        for critic in &self.critics {
            critic.save(dir)?;
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
        load_optimizer(dir, "actor", &mut self.actor_opt)?;
        for critic in &mut self.critics {
            critic.load(dir)?;
        }
        let replay = dir.join("replay.safetensors");
        if replay.is_file() {
            self.replay = ReplayBuffer::from_tensors(self.cfg.buffer_capacity, self.obs_dim, self.action_dim, &read_tensors(&replay)?)
                .map_err(LearnerError::Checkpoint)?;
            if self.mirror.is_some() {
                self.mirror = Some(DeviceMirror::new(&self.replay, self.device));
            }
        }
        let state: DdpgState = read_agent_state(dir)?;
        self.rng = state.rng.restore()?;
        self.counters = state.counters;
        self.critic_updates = state.critic_updates;
        if let Some(captured) = self.captured.as_mut() {
            captured.clear();
        }
        // A rewind point from before the load would restore other weights.
        self.rewind = None;
        Ok(())
    }

    fn actor_variables(&self) -> Vec<(String, Tensor)> {
        crate::algo::agent::sorted_variables(&self.actor_vs)
    }
}

#[cfg(test)]
mod tests;
