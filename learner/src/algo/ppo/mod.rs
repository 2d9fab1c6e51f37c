//! PPO with the LCRL actor (docs/method.md §5): a Gaussian policy whose mean
//! for action i comes from subnetwork i (or the global MLP), with a
//! state-independent log standard deviation; a global value network V(s).
//!
//! Collect `rollout_steps` transitions, then:
//!   δ_t = r_t + γ (1 − terminated_t) V(s_{t+1}) − V(s_t)
//!   A_t = δ_t + γλ (1 − end_t) A_{t+1}            (GAE; end = terminated or truncated)
//! where t + 1 is the step after t in its own stream: the next row in
//! `lcrl train`, and across an actor's batch boundary (a cut) the row where
//! the same actor's stream goes on, when it arrives in the same rollout
//! (otherwise the cut ends the sum there, as a truncation would).
//!   R_t = A_t + V(s_t)
//! and for `epochs` passes over shuffled minibatches:
//!   ratio = exp(log π(u|s) − log π_old(u|s))
//!   L_π = −mean min(ratio Â, clip(ratio, 1 ± ε) Â) − c_H · entropy
//!   L_V = mean (V(s) − R)²

use std::f64::consts::PI;
use std::path::Path;
use std::time::Instant;

use rand::seq::SliceRandom;
use rand::SeedableRng;
use rand_chacha::ChaCha8Rng;
use serde::{Deserialize, Serialize};
use tch::{nn, Device, Kind, Tensor};

use crate::algo::adam::Adam;
use crate::algo::agent::{
    build_critic, load_optimizers, load_vs, read_agent_state, save_optimizers, save_vs, write_agent_state, Agent, AgentSetup,
    Counters, RngState, Transition,
};
use crate::config::{NetworkConfig, PpoConfig};
use crate::algo::exploration;
use crate::algo::nets::{batch, ActorNet, Mlp};
use crate::LearnerError;

/// The transitions of the current rollout, flat f32 rows.
#[derive(Debug, Default, Clone, Serialize, Deserialize)]
struct Rollout {
    obs: Vec<f32>,
    actions: Vec<f32>,
    log_probs: Vec<f32>,
    /// V(s_t) of the rows evaluated so far (none of those stored since the
    /// last update: see `unvalued_next_obs`).
    values: Vec<f32>,
    rewards: Vec<f32>,
    /// V(s_{t+1}), 0 where the step terminated, of the same rows.
    next_values: Vec<f32>,
    terminated: Vec<bool>,
    /// No step of the same stream follows in this rollout's order: an
    /// episode end or a cut (unless `joins` continues it).
    ended: Vec<bool>,
    /// Cuts whose stream went on in a later row: (cut row, next row).
    #[serde(default)]
    joins: Vec<(usize, usize)>,
    /// Cuts waiting for their stream's next step.
    #[serde(default)]
    open_cuts: Vec<OpenCut>,
    /// s_{t+1} of the rows stored since the values were last evaluated
    /// (rows `values.len()..`). The critic does not change between updates,
    /// so their values are computed in one batch when the rollout is used
    /// rather than two one-row forward passes per stored step.
    #[serde(default)]
    unvalued_next_obs: Vec<f32>,
    /// Rows stored without the behaviour policy's log-probability
    /// (`lcrl train`'s own steps, or a peer that sent none), 0 in
    /// `log_probs` until the rollout is used: then the learner's current
    /// policy's, in one batch. In one process that policy acted them (it
    /// too only changes in `update`); for a peer's steps it stands in for
    /// the version that acted, as it did when scored on arrival.
    #[serde(default)]
    unscored_rows: Vec<usize>,
}

/// A cut row and where its stream stands: the next step of the same
/// actor that starts from exactly this state continues it.
#[derive(Debug, Clone, Serialize, Deserialize)]
struct OpenCut {
    row: usize,
    stream: u64,
    next_obs: Vec<f32>,
}

impl Rollout {
    /// Its columns agree with its rows, and every row it names exists and
    /// is where it may be (a checkpoint's rollout, before it is used).
    fn check(&self, m: usize, n: usize) -> Result<(), String> {
        let rows = self.rewards.len();
        let valued = self.values.len();
        if valued > rows {
            return Err(format!("has {valued} values for {rows} rows"));
        }
        let unvalued = rows - valued;
        let columns = [
            ("obs", self.obs.len(), rows * m, rows),
            ("actions", self.actions.len(), rows * n, rows),
            ("log_probs", self.log_probs.len(), rows, rows),
            ("terminated", self.terminated.len(), rows, rows),
            ("ended", self.ended.len(), rows, rows),
            ("next_values", self.next_values.len(), valued, valued),
            ("unvalued_next_obs", self.unvalued_next_obs.len(), unvalued * m, unvalued),
        ];
        if let Some((name, len, expected, of)) = columns.iter().find(|(_, len, expected, _)| len != expected) {
            return Err(format!("has {len} numbers in {name}, {expected} expected for its {of} rows"));
        }
        // Rows are scored before they are valued, so an unscored row is an
        // unvalued one; a join's next row comes after its cut.
        if let Some(row) = self.unscored_rows.iter().find(|&&row| row < valued || row >= rows) {
            return Err(format!("lists row {row} as unscored, outside its unvalued rows {valued}..{rows}"));
        }
        if let Some((cut, next)) = self.joins.iter().find(|&&(cut, next)| cut >= next || next >= rows) {
            return Err(format!("joins row {cut} to row {next}, not a later one of its {rows}"));
        }
        if let Some(cut) = self.open_cuts.iter().find(|c| c.row >= rows || c.next_obs.len() != m) {
            return Err(format!("holds an open cut at row {} with {} state numbers, not one of its {rows} rows with {m}", cut.row, cut.next_obs.len()));
        }
        Ok(())
    }

    /// The row whose advantage carries into row t's (none at an end).
    fn successors(&self) -> Vec<Option<usize>> {
        let len = self.rewards.len();
        let mut next: Vec<Option<usize>> = (0..len).map(|t| (!self.ended[t] && t + 1 < len).then_some(t + 1)).collect();
        for &(cut, row) in &self.joins {
            next[cut] = Some(row);
        }
        next
    }

    /// Links a cut to this row if the row goes on from it (returns
    /// whether it did), and opens a cut.
    fn link(&mut self, t: &Transition) -> bool {
        let row = self.rewards.len();
        let joined = self.open_cuts.iter().position(|c| c.stream == t.stream && c.next_obs == t.obs);
        if let Some(k) = joined {
            let cut = self.open_cuts.swap_remove(k);
            self.joins.push((cut.row, row));
        }
        // An episode end goes on nowhere, whatever else a peer marked.
        if t.cut && !(t.terminated || t.truncated) {
            self.open_cuts.push(OpenCut { row, stream: t.stream, next_obs: t.next_obs.to_vec() });
        }
        joined.is_some()
    }
}

pub struct Ppo {
    cfg: PpoConfig,
    device: Device,
    obs_dim: usize,
    action_dim: usize,
    actor_vs: nn::VarStore,
    actor: ActorNet,
    log_std: Tensor,
    critic_vs: nn::VarStore,
    critic: Mlp,
    actor_opt: Adam,
    critic_opt: Adam,
    rollout: Rollout,
    rng: ChaCha8Rng,
    counters: Counters,
}

#[derive(Serialize, Deserialize)]
struct PpoState {
    rng: RngState,
    counters: Counters,
    rollout: Rollout,
}

impl Ppo {
    pub fn new(cfg: &PpoConfig, net: &NetworkConfig, setup: AgentSetup) -> Self {
        let (actor_vs, actor) = setup.new_actor(net);
        let AgentSetup { state_dim: m, action_dim: n, seed, device, .. } = setup;
        let log_std = actor_vs.root().var("log_std", &[n as i64], nn::Init::Const(cfg.log_std_init));
        let critic_vs = nn::VarStore::new(device);
        let critic = build_critic(&critic_vs.root(), m, net, seed ^ 0xC717);
        Ppo {
            actor_opt: Adam::new(&actor_vs, cfg.actor_lr),
            critic_opt: Adam::new(&critic_vs, cfg.critic_lr),
            cfg: cfg.clone(),
            device,
            obs_dim: m,
            action_dim: n,
            actor_vs,
            actor,
            log_std,
            critic_vs,
            critic,
            rollout: Rollout::default(),
            rng: ChaCha8Rng::seed_from_u64(seed ^ 0x0990),
            counters: Counters::default(),
        }
    }

    /// log π(u | s) for rows of u given the means, summed over components.
    fn log_prob(&self, mean: &Tensor, actions: &Tensor) -> Tensor {
        let std = self.log_std.exp();
        let z = (actions - mean) / &std;
        (z.square() * -0.5 - &self.log_std - 0.5 * (2.0 * PI).ln()).sum_dim_intlist(-1, false, Kind::Float)
    }

    /// Fills in what the rows stored since the last update lack: the
    /// missing log-probabilities in one forward pass of the actor, then
    /// V(s_t) and V(s_{t+1}) in one of the critic. Both networks only
    /// change in `update`, after this, so every row gets (up to a
    /// product's rounding) what the networks current when it was stored
    /// gave it, as a per-step evaluation did.
    fn evaluate_pending(&mut self) {
        let log_probs = self.unscored_log_probs();
        let values = self.unvalued_values();
        let r = &mut self.rollout;
        for (&row, log_prob) in r.unscored_rows.iter().zip(log_probs) {
            r.log_probs[row] = log_prob;
        }
        r.unscored_rows.clear();
        let from = r.values.len();
        let rows = r.rewards.len() - from;
        r.values.extend_from_slice(&values[..rows]);
        let terminated = &r.terminated[from..];
        r.next_values.extend(values[rows..].iter().zip(terminated).map(|(&v, &end)| if end { 0.0 } else { v }));
        r.unvalued_next_obs.clear();
    }

    /// log π(u|s) of the rows stored without one, in their order.
    fn unscored_log_probs(&self) -> Vec<f32> {
        let r = &self.rollout;
        if r.unscored_rows.is_empty() {
            return Vec::new();
        }
        let rows: Vec<i64> = r.unscored_rows.iter().map(|&row| row as i64).collect();
        let index = Tensor::from_slice(&rows).to_device(self.device);
        let obs = batch(&r.obs, self.obs_dim, self.device).index_select(0, &index);
        let actions = batch(&r.actions, self.action_dim, self.device).index_select(0, &index);
        let log_probs = tch::no_grad(|| self.log_prob(&self.actor.forward(&obs), &actions).to_device(Device::Cpu));
        // A CPU float tensor always converts; 0 was the old fallback.
        Vec::<f32>::try_from(log_probs).unwrap_or_else(|_| vec![0.0; rows.len()])
    }

    /// V(s_t) of the unvalued rows, then V(s_{t+1}) of the same rows.
    fn unvalued_values(&self) -> Vec<f32> {
        let (r, m) = (&self.rollout, self.obs_dim);
        let from = r.values.len();
        let rows = r.rewards.len() - from;
        if rows == 0 {
            return Vec::new();
        }
        let states = [&r.obs[from * m..], &r.unvalued_next_obs[..]].concat();
        let values = tch::no_grad(|| self.critic.forward(&batch(&states, m, self.device)).flatten(0, -1).to_device(Device::Cpu));
        // A CPU float tensor always converts; zeros are the old fallback.
        Vec::<f32>::try_from(values).unwrap_or_else(|_| vec![0.0; 2 * rows])
    }

    /// GAE advantages and returns of the rollout.
    fn advantages(&mut self) -> (Vec<f32>, Vec<f32>) {
        self.evaluate_pending();
        let r = &self.rollout;
        let (gamma, lambda) = (self.cfg.gamma as f32, self.cfg.gae_lambda as f32);
        let mut advantages = vec![0.0f32; r.rewards.len()];
        // A successor's row is always later than its step's, so one
        // backward pass has every A_{t+1} ready.
        for (t, next) in r.successors().into_iter().enumerate().rev() {
            let bootstrap = if r.terminated[t] { 0.0 } else { gamma * r.next_values[t] };
            let delta = r.rewards[t] + bootstrap - r.values[t];
            let carry = next.map_or(0.0, |row| gamma * lambda * advantages[row]);
            advantages[t] = delta + carry;
        }
        let returns = advantages.iter().zip(&r.values).map(|(a, v)| a + v).collect();
        (advantages, returns)
    }

    /// The PPO update on a full rollout.
    fn update(&mut self) {
        let (advantages, returns) = self.advantages();
        let len = advantages.len();
        let r = std::mem::take(&mut self.rollout);
        let obs = batch(&r.obs, self.obs_dim, self.device);
        let actions = batch(&r.actions, self.action_dim, self.device);
        let old_log_probs = Tensor::from_slice(&r.log_probs).to_device(self.device);
        let advantages = Tensor::from_slice(&advantages).to_device(self.device);
        let returns = Tensor::from_slice(&returns).to_device(self.device);
        let mut order: Vec<i64> = (0..len as i64).collect();
        for _ in 0..self.cfg.epochs {
            order.shuffle(&mut self.rng);
            for chunk in order.chunks(self.cfg.minibatch_size) {
                let index = Tensor::from_slice(chunk).to_device(self.device);
                let adv = advantages.index_select(0, &index);
                // A last minibatch of one has no spread (its unbiased std
                // is NaN): its advantage normalizes to 0.
                let adv = if chunk.len() > 1 { (&adv - adv.mean(Kind::Float)) / (adv.std(true) + 1e-8) } else { adv.zeros_like() };
                let mb_obs = obs.index_select(0, &index);
                let log_probs = self.log_prob(&self.actor.forward(&mb_obs), &actions.index_select(0, &index));
                // π_θ(u|s) / μ(u|s): μ is the policy that acted, whose
                // log-probability the actor sent, so batches a few versions
                // old are corrected by the same clipped ratio
                // (docs/method.md §5, "Asynchronous PPO").
                let ratio = (log_probs - old_log_probs.index_select(0, &index)).exp();
                let clipped = ratio.clamp(1.0 - self.cfg.clip, 1.0 + self.cfg.clip);
                let surrogate = -(&ratio * &adv).minimum(&(clipped * &adv)).mean(Kind::Float);
                // Without an entropy bonus (the presets') its term adds
                // exactly 0 to the loss and its gradients: not computed.
                let policy_loss = if self.cfg.entropy_coef == 0.0 {
                    surrogate
                } else {
                    let entropy = (&self.log_std + 0.5 * (2.0 * PI * std::f64::consts::E).ln()).sum(Kind::Float);
                    surrogate - self.cfg.entropy_coef * entropy
                };
                let actor_stepped = guarded_step(&mut self.actor_opt, &policy_loss, self.cfg.max_grad_norm);

                let values = self.critic.forward(&mb_obs).flatten(0, -1);
                let value_loss = (values - returns.index_select(0, &index)).square().mean(Kind::Float);
                let critic_stepped = guarded_step(&mut self.critic_opt, &value_loss, self.cfg.max_grad_norm);
                self.counters.updates += u64::from(actor_stepped);
                self.counters.critic_updates += u64::from(critic_stepped);
                if !(actor_stepped && critic_stepped) {
                    self.counters.skipped_updates += 1;
                    if self.counters.skipped_updates.is_power_of_two() {
                        tracing::warn!(skipped = self.counters.skipped_updates, "PPO update skipped: its loss or gradients were not finite");
                    }
                }
            }
        }
    }
}

/// One optimizer step on `loss`, taken only when the loss and the global
/// gradient norm are finite (issue 71: a rollout of states near 3e38 makes
/// both infinite); otherwise the weights and Adam's moments stay as they
/// were. With the gradients clipped to `max_norm`, a finite norm keeps the
/// step finite, so nothing has to be undone (DDPG's guard, ddpg/mod.rs,
/// checks the networks after its updates and rewinds instead).
fn guarded_step(opt: &mut Adam, loss: &Tensor, max_norm: f64) -> bool {
    opt.zero_grad();
    let loss_finite = f64::try_from(loss.detach()).is_ok_and(f64::is_finite);
    if !loss_finite {
        return false;
    }
    loss.backward();
    if !opt.clip_grad_norm(max_norm).is_finite() {
        opt.zero_grad();
        return false;
    }
    opt.step();
    true
}

impl Agent for Ppo {
    fn explore(&mut self, obs: &[f32], _episode: usize) -> Vec<f32> {
        let std: Vec<f32> = Vec::try_from(self.log_std.exp().detach().to_device(Device::Cpu)).unwrap_or_default();
        exploration::gaussian(&self.act(obs), &std.iter().map(|&s| f64::from(s)).collect::<Vec<_>>(), false, &mut self.rng)
    }

    fn act(&self, obs: &[f32]) -> Vec<f32> {
        tch::no_grad(|| {
            let mean = self.actor.forward(&batch(obs, self.obs_dim, self.device));
            Vec::<f32>::try_from(mean.flatten(0, -1).to_device(Device::Cpu)).unwrap_or_default()
        })
    }

    /// log π_old(u|s) is the actor's own when it sent one (the version that
    /// acted); otherwise, as V(s) and V(s') in both loops, it is evaluated
    /// with the current networks when the rollout is used
    /// (`evaluate_pending`): in one process, the policy that acted.
    fn store(&mut self, t: Transition) {
        let r = &mut self.rollout;
        let log_prob = t.log_prob.unwrap_or_else(|| {
            r.unscored_rows.push(r.rewards.len());
            0.0
        });
        self.counters.cuts_joined += u64::from(r.link(&t));
        self.counters.cuts += u64::from(t.cut);
        r.obs.extend_from_slice(t.obs);
        r.actions.extend_from_slice(t.action);
        r.log_probs.push(log_prob);
        r.rewards.push(t.reward);
        r.unvalued_next_obs.extend_from_slice(t.next_obs);
        r.terminated.push(t.terminated);
        r.ended.push(t.terminated || t.truncated || t.cut);
        self.counters.env_steps += 1;
    }

    fn train_step(&mut self) -> f64 {
        if self.rollout.rewards.len() < self.cfg.rollout_steps {
            return 0.0;
        }
        let started = Instant::now();
        self.update();
        started.elapsed().as_secs_f64()
    }

    fn stored(&self) -> usize {
        self.rollout.rewards.len()
    }

    fn set_progress(&mut self, fraction: f64) {
        if self.cfg.anneal_lr {
            let left = (1.0 - fraction).clamp(0.0, 1.0);
            self.actor_opt.set_lr(self.cfg.actor_lr * left);
            self.critic_opt.set_lr(self.cfg.critic_lr * left);
        }
    }

    /// The rollout's last row, if the stream's, ends there (`lcrl train`
    /// has one stream; a rollout just used for an update holds none).
    fn end_stream(&mut self) {
        self.counters.diverged_env += 1;
        if let Some(ended) = self.rollout.ended.last_mut() {
            *ended = true;
        }
    }

    fn counters(&self) -> Counters {
        self.counters
    }

    fn param_counts(&self) -> (usize, usize) {
        (self.actor.param_count() + self.action_dim, self.critic.param_count())
    }

    fn save(&self, dir: &Path, _include_buffer: bool) -> Result<(), LearnerError> {
        save_vs(&self.actor_vs, &dir.join("actor.safetensors"))?;
        save_vs(&self.critic_vs, &dir.join("critic.safetensors"))?;
        save_optimizers(dir, &self.actor_opt, &self.critic_opt)?;
        // The unfinished rollout is part of the state: PPO resumes
        // mid-rollout. Its pending rows are written pending, so a resumed
        // run evaluates them in the same batch as an uninterrupted one
        // (a product's rounding may depend on its batch size).
        let state = PpoState { rng: RngState::of(&self.rng), counters: self.counters, rollout: self.rollout.clone() };
        write_agent_state(dir, &state)
    }

    fn load(&mut self, dir: &Path) -> Result<(), LearnerError> {
        let state: PpoState = read_agent_state(dir)?;
        state.rollout.check(self.obs_dim, self.action_dim).map_err(|e| LearnerError::Checkpoint(format!("{}: the PPO rollout {e}", dir.join("agent.json").display())))?;
        load_vs(&mut self.actor_vs, &dir.join("actor.safetensors"))?;
        load_vs(&mut self.critic_vs, &dir.join("critic.safetensors"))?;
        load_optimizers(dir, &mut self.actor_opt, &mut self.critic_opt)?;
        self.rng = state.rng.restore()?;
        self.counters = state.counters;
        if self.counters.critic_updates == 0 {
            // Checkpoints from before PPO counted its critic's steps apart
            // moved both networks in every update.
            self.counters.critic_updates = self.counters.updates;
        }
        self.rollout = state.rollout;
        Ok(())
    }

    fn actor_variables(&self) -> Vec<(String, Tensor)> {
        crate::algo::agent::sorted_variables(&self.actor_vs)
    }
}

#[cfg(test)]
mod tests;
