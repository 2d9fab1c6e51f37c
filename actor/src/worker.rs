//! The actor's rollout: K environments stepping with one policy plus
//! exploration noise, their transitions assembled into `TransitionBatch`es
//! (proto/lcrl.proto). No network here: [`crate::transport`] moves the
//! batches and the policies, and tests drive a [`Rollout`] directly.

use lcrl_learner::policy::action::ActionMap;
use lcrl_learner::algo::exploration;
use lcrl_learner::policy::trained::Policy;
use lcrl_proto::v1::{EpisodeSummary, PolicySnapshot, Transition, TransitionBatch};
use rand::SeedableRng;
use rand_chacha::ChaCha8Rng;

use crate::metrics::ActorMetrics;

/// How to explore with the current version (from its snapshot).
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Exploration {
    /// Uniformly random actions (the learner is warming up, DDPG).
    pub uniform: bool,
    /// Gaussian noise std the learner asks for (DDPG; 0: the actor's own).
    pub noise: f64,
}

impl Exploration {
    pub fn of(snapshot: &PolicySnapshot) -> Self {
        Exploration { uniform: snapshot.explore_uniform, noise: snapshot.exploration_noise }
    }
}

/// DDPG's default batch: a batch's steps all wait for the learner
/// together, so its size is policy lag (docs/scaling.md, "Policy lag").
pub const DDPG_BATCH: usize = 16;

/// PPO's default batch, the largest a shared-memory sample carries: every
/// batch end cuts each environment's stream, and there PPO's advantage
/// estimate (GAE) bootstraps from the value instead of running on, so small
/// batches bias PPO (docs/scaling.md, "Policy lag"). PPO discards stale
/// data anyway (`--max-staleness`), so a larger batch costs it no lag.
pub const PPO_BATCH: usize = 64;

/// What a rollout is asked to do.
#[derive(Debug, Clone)]
pub struct RolloutSettings {
    /// K, environment instances.
    pub envs: usize,
    /// Transitions per batch (None: [`DDPG_BATCH`] or [`PPO_BATCH`], by
    /// the policy's algorithm).
    pub batch: Option<usize>,
    /// Exploration noise std where the learner sets none (DDPG).
    pub noise: f64,
    pub seed: u64,
    /// Stop after this many episodes in total (None: never).
    pub episodes: Option<u64>,
    pub run_id: String,
    pub actor_id: String,
}

impl RolloutSettings {
    /// Actors differ by name (container replicas all run as process 1),
    /// and the same name and seed give the same episodes.
    fn salt(&self) -> u64 {
        use std::hash::{Hash, Hasher};
        let mut hasher = std::collections::hash_map::DefaultHasher::new();
        self.actor_id.hash(&mut hasher);
        hasher.finish()
    }

    /// Episode seeds are this plus 1, 2, ... in the order environments
    /// reset: training episodes' own seed range (lcrl_sim::seeds), one run
    /// seed per actor name.
    pub fn seed_before_first_episode(&self) -> u64 {
        lcrl_sim::seeds::training(self.seed.wrapping_add(self.salt()) % lcrl_sim::seeds::PER_RUN, 0)
    }
}

/// Exploration std per action component: the policy's own (PPO), or the
/// learner's schedule (DDPG; `noise` when the learner sets none), in
/// normalized action units.
fn exploration_std(policy: &Policy, exploration: Exploration, noise: f64) -> Vec<f64> {
    let noise = if exploration.noise > 0.0 { exploration.noise } else { noise };
    let std: Vec<f64> = policy.exploration_std().map_or_else(|| vec![noise; policy.architecture.shape.action_dim], |v| v.iter().map(|&x| f64::from(x)).collect());
    // A non-finite or negative std (a diverged policy, a bad flag) acts
    // greedily rather than failing.
    std.into_iter().map(|sd| if sd.is_finite() && sd >= 0.0 { sd } else { 0.0 }).collect()
}

/// K environments mid-episode and the batch being assembled.
pub struct Rollout {
    settings: RolloutSettings,
    envs: Vec<Box<dyn lcrl_sim::Env>>,
    /// The base is part of the architecture, which newer weights never
    /// change, and the K environments share one spec: one map for the run.
    action_map: ActionMap,
    explore: Exploration,
    std: Vec<f64>,
    /// PPO samples its own Gaussian; the learner's uniform warm-up is DDPG's.
    own_distribution: bool,
    /// Transitions per batch.
    batch: usize,
    rng: ChaCha8Rng,
    episode_seed: u64,
    states: Vec<Vec<f64>>,
    returns: Vec<f64>,
    lengths: Vec<u32>,
    /// Each environment's transitions since the last batch: they stay
    /// contiguous in a batch, the last one marked as a cut, so the learner
    /// sees whole trajectory segments.
    segments: Vec<Vec<Transition>>,
    /// Each environment's episodes finished since the last batch: sent in
    /// segment order, so that they follow their ends in the batch.
    episodes_in_batch: Vec<Vec<EpisodeSummary>>,
    sequence: u64,
    episodes_done: u64,
    /// Unsound starts skipped before the first step, not yet counted in
    /// the actor's metrics (which `new` does not have).
    unsound_starts_uncounted: u64,
}

/// Refuses a batch size the learner would refuse (its default limits,
/// lcrl_runtime::limits): said at start, with the size that fits, rather
/// than a batch refused in the middle of a run. A batch closes at the
/// first whole round of the K environments at or past `batch`, so it may
/// hold up to `batch + K − 1` transitions.
pub fn check_batch_fits(batch: usize, envs: usize, state_dim: usize, action_dim: usize) -> anyhow::Result<()> {
    use lcrl_runtime::limits::{MAX_BATCH_BYTES, MAX_REPEATED_ENTRIES};
    // Upper bound of one encoded transition: state and next state, the
    // applied and the sampled action as f32, and its scalars and framing.
    let per_transition = 4 * (2 * state_dim + 2 * action_dim) + 64;
    let fits = MAX_REPEATED_ENTRIES.min(MAX_BATCH_BYTES / per_transition);
    let most = batch + envs - 1;
    if most > fits {
        anyhow::bail!(
            "a batch of --batch {batch} with --envs {envs} may hold {most} transitions of about {per_transition} bytes, but a learner takes at most \
             {fits} such transitions per batch ({MAX_REPEATED_ENTRIES} transitions, {MAX_BATCH_BYTES} bytes); lower --batch to at most {}",
            fits.saturating_sub(envs - 1).max(1)
        );
    }
    Ok(())
}

/// Most unsound start states in a row before the actor gives up on its
/// environment.
pub const MAX_UNSOUND_RESETS: u32 = 100;

/// Resets `env` at `seed`, and at the next seeds while its start state is
/// beyond the environment's bounds (lcrl_sim::state_out_of_bounds; issue
/// 82: a served environment's 1e30 start state ended a run): such a state
/// is never acted on nor sent, each one is warned of and told to
/// `on_unsound`, and after [`MAX_UNSOUND_RESETS`] in a row the actor stops
/// with the reason.
fn sound_reset(env: &mut dyn lcrl_sim::Env, seed: &mut u64, mut on_unsound: impl FnMut(&str)) -> anyhow::Result<Vec<f64>> {
    for _ in 0..MAX_UNSOUND_RESETS {
        let state = env.reset(*seed)?;
        let Some(why) = lcrl_sim::state_out_of_bounds(env, &state) else { return Ok(state) };
        tracing::warn!(episode_seed = *seed, "the environment's start state is unsound ({why}): that episode is skipped (diverged_env)");
        on_unsound(&why);
        *seed += 1;
    }
    anyhow::bail!("the environment gave {MAX_UNSOUND_RESETS} start states in a row beyond its bounds (lcrl_sim::STATE_LIMIT times its scale); its episodes cannot be trained on")
}

impl Rollout {
    /// K fresh environments of the policy's environment, reset.
    pub fn new(settings: RolloutSettings, policy: &Policy, explore: Exploration) -> anyhow::Result<Self> {
        if settings.envs == 0 || settings.batch == Some(0) {
            anyhow::bail!("a rollout needs at least one environment and one transition per batch");
        }
        let name = &policy.architecture.shape.env;
        let mut envs: Vec<Box<dyn lcrl_sim::Env>> = (0..settings.envs).map(|_| lcrl_sim::make_env(name)).collect::<Result<_, _>>()?;
        policy.check_env(envs[0].as_ref())?;
        let action_map = policy.action_map(envs[0].as_ref())?;
        let salt = settings.salt();
        let mut episode_seed = settings.seed_before_first_episode();
        let mut unsound = 0;
        let states = envs
            .iter_mut()
            .map(|env| {
                episode_seed += 1;
                sound_reset(env.as_mut(), &mut episode_seed, |_| unsound += 1)
            })
            .collect::<Result<_, _>>()?;
        let k = settings.envs;
        let own_distribution = policy.exploration_std().is_some();
        let batch = settings.batch.unwrap_or(if own_distribution { PPO_BATCH } else { DDPG_BATCH });
        Ok(Rollout {
            batch,
            rng: ChaCha8Rng::seed_from_u64(settings.seed ^ salt),
            std: exploration_std(policy, explore, settings.noise),
            own_distribution,
            explore,
            action_map,
            envs,
            episode_seed,
            states,
            returns: vec![0.0; k],
            lengths: vec![0; k],
            segments: vec![Vec::new(); k],
            episodes_in_batch: vec![Vec::new(); k],
            // The learner keeps the highest sequence per actor id and drops
            // what is not above it. Starting from the clock (µs) keeps a
            // restarted actor with the same id above everything its
            // previous life sent.
            sequence: lcrl_learner::service::ingest::now_micros(),
            episodes_done: unsound,
            unsound_starts_uncounted: unsound,
            settings,
        })
    }

    /// After a new policy version: its exploration (and, for PPO, its std).
    pub fn set_exploration(&mut self, policy: &Policy, explore: Exploration) {
        self.explore = explore;
        self.std = exploration_std(policy, explore, self.settings.noise);
    }

    /// Whether the episode budget is used up.
    pub fn finished(&self) -> bool {
        self.settings.episodes.is_some_and(|limit| self.episodes_done >= limit)
    }

    pub fn episodes_done(&self) -> u64 {
        self.episodes_done
    }

    /// Transitions per batch (`--batch`, or the algorithm's default).
    pub fn batch_size(&self) -> usize {
        self.batch
    }

    /// Steps every environment once with `policy`; returns a batch when
    /// `batch` transitions are collected (or the budget ends).
    pub fn step(&mut self, policy: &Policy, metrics: &ActorMetrics) -> anyhow::Result<Option<TransitionBatch>> {
        if self.unsound_starts_uncounted > 0 {
            metrics.diverged_env.inc_by(std::mem::take(&mut self.unsound_starts_uncounted));
        }
        let mut actions = Vec::with_capacity(self.envs.len());
        let mut sampled = Vec::with_capacity(self.envs.len());
        for (k, env) in self.envs.iter().enumerate() {
            let obs = lcrl_learner::algo::agent::observe(env.as_ref(), &self.states[k]);
            // u is sampled as `lcrl train`'s agents sample it (one function
            // for both loops), and sent as sampled: the learner stores u.
            let (u, log_prob) = if self.explore.uniform && !self.own_distribution {
                // The learner is filling its replay buffer: uniformly random
                // actions, as `lcrl train` warms up.
                (exploration::uniform(policy.architecture.shape.action_dim, &mut self.rng), None)
            } else {
                let mean = policy.act_normalized(&obs);
                // PPO samples its own Gaussian, unclipped, and sends log π(u|s)
                // of this version; DDPG's noise is clipped to [−1, 1].
                let mut u = exploration::gaussian(&mean, &self.std, !self.own_distribution, &mut self.rng);
                // The learner refuses a batch with a u beyond its door's
                // bound ("bounds", issue 71): a policy whose mean has run
                // far off would have every batch refused. Such a u acts
                // as ±1 all the same; log π is taken of the u sent.
                let limit = lcrl_sim::SAMPLED_ACTION_BOUND as f32;
                u.iter_mut().for_each(|x| *x = x.clamp(-limit, limit));
                // (None where a degenerate std makes it non-finite: the learner
                // then evaluates it itself.)
                let log_prob = self.own_distribution.then(|| exploration::gaussian_log_prob(&mean, &self.std, &u)).filter(|lp| lp.is_finite());
                (u, log_prob)
            };
            actions.push(self.action_map.to_env(&u));
            sampled.push((u, log_prob));
        }
        // All K environments at once: one call when a server serves them.
        let steps = lcrl_sim::step_all(&mut self.envs, &actions)?;
        for (k, ((step, action), (u, log_prob))) in steps.into_iter().zip(&actions).zip(sampled).enumerate() {
            if let Some(why) = lcrl_sim::diverged(self.envs[k].as_ref(), &step) {
                self.end_diverged(k, &why, metrics)?;
                continue;
            }
            self.returns[k] += step.reward;
            self.lengths[k] += 1;
            metrics.env_steps.inc();
            self.segments[k].push(Transition {
                state: self.states[k].iter().map(|&v| v as f32).collect(),
                action: action.iter().map(|&v| v as f32).collect(),
                reward: step.reward as f32,
                next_state: step.state.iter().map(|&v| v as f32).collect(),
                terminated: step.terminated,
                truncated: step.truncated,
                policy_version: policy.version,
                sampled_action: u,
                log_prob,
                cut: false,
            });
            if step.terminated || step.truncated {
                let measured = self.envs[k].episode_metrics();
                self.episodes_in_batch[k].push(EpisodeSummary {
                    episode_return: self.returns[k],
                    length: self.lengths[k],
                    success: measured.success,
                    peak_force_n: measured.peak_force_n,
                    peak_moment_nm: measured.peak_moment_nm,
                    return_terms: measured.return_terms.map(|t| lcrl_proto::v1::ReturnTerms { depth: t.depth, force: t.force, moment: t.moment, bonus: t.bonus, failure: t.failure }),
                });
                self.episodes_done += 1;
                metrics.episodes.inc();
                (self.returns[k], self.lengths[k]) = (0.0, 0);
                self.episode_seed += 1;
                self.reset_sound(k, metrics)?;
            } else {
                self.states[k] = step.state;
            }
        }
        let collected: usize = self.segments.iter().map(Vec::len).sum();
        if collected < self.batch && !(self.finished() && collected > 0) {
            return Ok(None);
        }
        Ok(self.take_batch(policy.version))
    }

    /// Ends environment k's episode after a step that diverged: the step
    /// is not sent (the learner would refuse it: "bounds"), the steps
    /// before it end in a cut, so the agent bootstraps from the last sound
    /// state, and no summary is sent: the learner counts sound episodes
    /// only. The episode counts against this actor's own budget, so a
    /// simulator that always diverges cannot keep it running forever.
    fn end_diverged(&mut self, k: usize, why: &str, metrics: &ActorMetrics) -> anyhow::Result<()> {
        tracing::warn!(episode_seed = self.episode_seed, steps = self.lengths[k], "the environment diverged ({why}): its episode ends here, unsent (diverged_env)");
        if let Some(last) = self.segments[k].last_mut().filter(|t| !(t.terminated || t.truncated)) {
            last.cut = true;
        }
        metrics.diverged_env.inc();
        self.episodes_done += 1;
        (self.returns[k], self.lengths[k]) = (0.0, 0);
        self.episode_seed += 1;
        self.reset_sound(k, metrics)
    }

    /// Resets environment k to a sound start ([`sound_reset`]); each
    /// unsound one counts as a diverged episode against the budget.
    fn reset_sound(&mut self, k: usize, metrics: &ActorMetrics) -> anyhow::Result<()> {
        let mut unsound = 0;
        self.states[k] = sound_reset(self.envs[k].as_mut(), &mut self.episode_seed, |_| unsound += 1)?;
        metrics.diverged_env.inc_by(unsound);
        self.episodes_done += unsound;
        Ok(())
    }

    /// The transitions collected so far as a batch of `version` (None when
    /// there are none): what `step` sends when a batch is full, and what
    /// goes out early when the policy that acted is about to change hands
    /// (a restarted learner), so that no batch mixes two learners' policies.
    pub fn take_batch(&mut self, version: u64) -> Option<TransitionBatch> {
        if self.segments.iter().all(Vec::is_empty) {
            return None;
        }
        let mut batch = TransitionBatch { run_id: self.settings.run_id.clone(), actor_id: self.settings.actor_id.clone(), ..Default::default() };
        for (segment, episodes) in self.segments.iter_mut().zip(&mut self.episodes_in_batch) {
            // A batch boundary is not an episode end, but each
            // environment's stream is cut there (PPO's advantages stop).
            if let Some(last) = segment.last_mut() {
                last.cut = !(last.terminated || last.truncated);
            }
            batch.transitions.append(segment);
            batch.episodes.append(episodes);
        }
        // Rising, and with the clock: a sequence a peer sent ahead under
        // this id (at most the learner's SEQUENCE_AHEAD) is passed once
        // the clock gets there, not after as many batches.
        self.sequence = (self.sequence + 1).max(lcrl_learner::service::ingest::now_micros());
        batch.sequence = self.sequence;
        batch.episode_id = self.episodes_done;
        batch.policy_version = version;
        Some(batch)
    }
}

#[cfg(test)]
mod tests;
