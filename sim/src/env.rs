//! The environment contract shared by CS3, the learner and the actors.

use thiserror::Error;

/// What an environment is: its dimensions, names and action bounds.
#[derive(Debug, Clone, PartialEq)]
pub struct EnvSpec {
    /// Registered name or the path of the file it came from.
    pub name: String,
    /// m names, one per state component (docs/method.md §1).
    pub state_names: Vec<String>,
    /// n names, one per action component.
    pub action_names: Vec<String>,
    /// Lower action bounds lb (length n). Each contains 0, the neutral action.
    pub action_low: Vec<f64>,
    /// Upper action bounds ub (length n).
    pub action_high: Vec<f64>,
}

impl EnvSpec {
    /// m, the state dimension.
    pub fn state_dim(&self) -> usize {
        self.state_names.len()
    }

    /// n, the action dimension.
    pub fn action_dim(&self) -> usize {
        self.action_names.len()
    }

    /// Rejects an action of the wrong length or with a non-finite component.
    pub fn check_action(&self, action: &[f64]) -> Result<(), EnvError> {
        if action.len() != self.action_dim() {
            return Err(EnvError::ActionDim { expected: self.action_dim(), got: action.len() });
        }
        if let Some(index) = action.iter().position(|a| !a.is_finite()) {
            return Err(EnvError::NonFiniteAction { index, value: action[index] });
        }
        Ok(())
    }

    /// Clips every component into [lb, ub].
    pub fn clip_action(&self, action: &[f64]) -> Vec<f64> {
        action
            .iter()
            .zip(self.action_low.iter().zip(&self.action_high))
            .map(|(a, (lo, hi))| a.clamp(*lo, *hi))
            .collect()
    }
}

/// Maps u ∈ [−1, 1]ⁿ (clipped) onto the action box.
pub fn action_of(spec: &EnvSpec, u: &[f64]) -> Vec<f64> {
    u.iter()
        .zip(spec.action_low.iter().zip(&spec.action_high))
        .map(|(u, (lo, hi))| lo + (u.clamp(-1.0, 1.0) + 1.0) / 2.0 * (hi - lo))
        .collect()
}

/// The u of an action (inverse of [`action_of`]).
pub fn u_of(spec: &EnvSpec, action: &[f64]) -> Vec<f64> {
    action
        .iter()
        .zip(spec.action_low.iter().zip(&spec.action_high))
        .map(|(a, (lo, hi))| if hi > lo { 2.0 * (a - lo) / (hi - lo) - 1.0 } else { 0.0 })
        .collect()
}

/// How far a sound state may lie from its scale: every component of
/// `normalize_state` (order 1 by construction) stays within ±this. Beyond
/// it the simulation has diverged (docs/reliability.md, "Finite weights
/// only"): actors and `lcrl train` end the episode as `diverged_env`, and
/// the learner refuses such a transition at its door ("bounds").
pub const STATE_LIMIT: f64 = 1e4;
/// The largest magnitude of one step's reward a sound episode gives. The
/// peg task's largest single charge is its failure charge (100 × the
/// largest step cost, docs/peg.md), far below; a linear system's quadratic
/// cost reaches it near |x| ≈ 10³, long after it diverged.
pub const REWARD_LIMIT: f64 = 1e6;
/// How far beyond [−1, 1] the agent's own sampled u may lie (PPO samples
/// an unclipped Gaussian; DDPG clips into [−1, 1]).
pub const SAMPLED_ACTION_LIMIT: f64 = 1e3;
/// The largest |u| the learner takes, and an actor sends: 1 + the limit.
pub const SAMPLED_ACTION_BOUND: f64 = 1.0 + SAMPLED_ACTION_LIMIT;

/// Why a step's outcome cannot be a sound continuation of an episode: a
/// non-finite or out-of-bounds state, or a reward beyond
/// [`REWARD_LIMIT`]. None when it is sound.
pub fn diverged(env: &dyn Env, step: &Step) -> Option<String> {
    if !step.reward.is_finite() || step.reward.abs() > REWARD_LIMIT {
        return Some(format!("reward {} is beyond ±{REWARD_LIMIT:e}", step.reward));
    }
    state_out_of_bounds(env, &step.state)
}

/// Why `state` lies beyond the environment's scale by more than
/// [`STATE_LIMIT`] (or is not finite); None when it lies within.
pub fn state_out_of_bounds(env: &dyn Env, state: &[f64]) -> Option<String> {
    // On every actor step and ingested transition: no allocation.
    let scale = |k: usize| env.state_scale().and_then(|s| s.get(k)).copied().unwrap_or(1.0);
    let k = state.iter().enumerate().position(|(k, v)| !v.is_finite() || (v / scale(k)).abs() > STATE_LIMIT)?;
    Some(format!(
        "state component {k} ({}) is {}, {} times its scale; at most {STATE_LIMIT:e}",
        env.spec().state_names.get(k).map_or("?", String::as_str),
        state[k],
        state[k] / scale(k)
    ))
}

/// The outcome of one control step.
#[derive(Debug, Clone, PartialEq)]
pub struct Step {
    /// The next state s_{t+1} (length m).
    pub state: Vec<f64>,
    pub reward: f64,
    /// The episode ended by the task itself (success or failure).
    pub terminated: bool,
    /// The episode was cut by the step cap.
    pub truncated: bool,
}

/// An environment: a controlled system with bounded actions.
///
/// Contract:
/// - `reset(seed)` draws a fresh initial state; equal seeds give equal
///   episodes (together with equal actions).
/// - `step` rejects a wrong-length or non-finite action with an error and
///   leaves the environment unchanged; it clips finite actions to the bounds.
/// - `snapshot` returns an exact copy: stepping the copy and the original
///   with the same actions gives bit-identical results. CS3 runs its two
///   branches on snapshots (docs/method.md §2).
/// - `reset`, `step` and `snapshot` fail only for environments in another
///   process ([`crate::remote`]): the server is gone, or cannot copy.
pub trait Env: Send + Sync {
    fn spec(&self) -> &EnvSpec;
    fn reset(&mut self, seed: u64) -> Result<Vec<f64>, EnvError>;
    fn state(&self) -> &[f64];
    fn step(&mut self, action: &[f64]) -> Result<Step, EnvError>;
    /// An exact, independent copy of the environment in its current state.
    fn snapshot(&self) -> Result<Box<dyn Env>, EnvError>;
    /// A new instance of the same environment, not yet reset (cheap: no
    /// copy of the current state). For what needs the environment's spec
    /// and scales beside a running episode, and for fresh episodes.
    fn fresh(&self) -> Box<dyn Env>;
    /// Whether `snapshot` can work at all, so CS3 can refuse at once with
    /// the reason instead of failing in its first rollout.
    fn check_snapshot(&self) -> Result<(), EnvError> {
        Ok(())
    }
    /// The environment as its own type, for callers that need one kind
    /// (`LtiEnv::of` for the LQR reference, the served environments'
    /// batched step): the contract names no implementation.
    fn as_any(&self) -> &dyn std::any::Any;
    fn as_any_mut(&mut self) -> &mut dyn std::any::Any;
    /// Re-seeds the environment's own randomness (process noise) without
    /// changing its physical state. Deterministic environments ignore it.
    fn reseed_noise(&mut self, _seed: u64) {}
    /// Whether steps draw randomness of their own (process noise).
    fn is_stochastic(&self) -> bool {
        false
    }
    /// Divisors that bring each state component to order 1 for learning
    /// (length m); None: all ones (the state is used as it is).
    fn state_scale(&self) -> Option<&[f64]> {
        None
    }
    /// The state scaled for learning: each component over its
    /// [`Env::state_scale`]. Called every step: borrows the scales.
    fn normalize_state(&self, state: &[f64]) -> Vec<f64> {
        match self.state_scale() {
            Some(scale) => state.iter().zip(scale).map(|(v, s)| v / s).collect(),
            None => state.to_vec(),
        }
    }
    /// Seconds of simulated time per step (for traces).
    fn control_period_s(&self) -> f64 {
        1.0
    }
    /// The remaining depth (state index 2, mm) at the hole entrance, for
    /// tasks that insert something; None elsewhere.
    fn depth_reference_mm(&self) -> Option<f64> {
        None
    }
    /// Whether CS3 should by default draw its start states along an episode
    /// of the neutral controller (a = 0) instead of from `reset` alone
    /// (docs/method.md §2): true for tasks whose states of interest occur
    /// only mid-episode, such as contact in the peg-in-hole task.
    fn prefers_trajectory_starts(&self) -> bool {
        false
    }
    /// What the current episode achieved so far, where the task defines it.
    fn episode_metrics(&self) -> EpisodeMetrics {
        EpisodeMetrics::default()
    }
}

/// Task-level figures of an episode; `None` where the task has no such notion.
#[derive(Debug, Clone, Copy, Default, PartialEq)]
pub struct EpisodeMetrics {
    pub success: Option<bool>,
    pub peak_force_n: Option<f64>,
    pub peak_moment_nm: Option<f64>,
    pub max_penetration_mm: Option<f64>,
    /// The episode's return split into its reward terms, where the task's
    /// reward has terms (peg-in-hole, docs/method.md eqs. 16–17).
    pub return_terms: Option<ReturnTerms>,
}

/// An episode's return as the sum of its reward terms (docs/peg.md): each
/// field is that term summed over the episode, with its sign, so the five
/// add up to the return.
#[derive(Debug, Clone, Copy, Default, PartialEq, serde::Serialize, serde::Deserialize)]
pub struct ReturnTerms {
    /// −h_z Σ z (remaining depth, m).
    pub depth: f64,
    /// −h_F Σ ‖F‖ (N).
    pub force: f64,
    /// −h_M Σ ‖M‖ (N·m).
    pub moment: f64,
    /// +r_s on a successful insertion.
    pub bonus: f64,
    /// The failure charge when a force or moment limit was exceeded.
    pub failure: f64,
}

/// Return terms as the named columns of summary.json and metrics.csv
/// (`return_depth`, …), null (JSON) or blank (CSV) where the task's reward
/// has no terms.
#[derive(Debug, Clone, Copy, Default, PartialEq, serde::Serialize, serde::Deserialize)]
pub struct ReturnColumns {
    #[serde(default, deserialize_with = "number_or_blank")]
    pub return_depth: Option<f64>,
    #[serde(default, deserialize_with = "number_or_blank")]
    pub return_force: Option<f64>,
    #[serde(default, deserialize_with = "number_or_blank")]
    pub return_moment: Option<f64>,
    #[serde(default, deserialize_with = "number_or_blank")]
    pub return_bonus: Option<f64>,
    #[serde(default, deserialize_with = "number_or_blank")]
    pub return_failure: Option<f64>,
}

/// A number, or none for null or a blank field. Flattened into a CSV row
/// (metrics.csv), a column reaches serde as its text, before anyone says
/// it is an `Option<f64>`; the blank of a task without terms is none there.
fn number_or_blank<'de, D: serde::Deserializer<'de>>(deserializer: D) -> Result<Option<f64>, D::Error> {
    use serde::Deserialize;
    #[derive(serde::Deserialize)]
    #[serde(untagged)]
    enum Field {
        Number(f64),
        Text(String),
    }
    match Option::<Field>::deserialize(deserializer)? {
        None => Ok(None),
        Some(Field::Number(x)) => Ok(Some(x)),
        Some(Field::Text(text)) if text.trim().is_empty() => Ok(None),
        Some(Field::Text(text)) => text.trim().parse().map(Some).map_err(|_| serde::de::Error::custom(format!("expected a number or nothing, got {text:?}"))),
    }
}

impl From<Option<ReturnTerms>> for ReturnColumns {
    fn from(terms: Option<ReturnTerms>) -> Self {
        match terms {
            Some(t) => ReturnColumns {
                return_depth: Some(t.depth),
                return_force: Some(t.force),
                return_moment: Some(t.moment),
                return_bonus: Some(t.bonus),
                return_failure: Some(t.failure),
            },
            None => ReturnColumns::default(),
        }
    }
}

impl ReturnTerms {
    pub fn total(&self) -> f64 {
        self.depth + self.force + self.moment + self.bonus + self.failure
    }

    /// Component-wise sum (accumulating steps, or averaging episodes).
    pub fn add(&self, other: &ReturnTerms) -> ReturnTerms {
        ReturnTerms {
            depth: self.depth + other.depth,
            force: self.force + other.force,
            moment: self.moment + other.moment,
            bonus: self.bonus + other.bonus,
            failure: self.failure + other.failure,
        }
    }

    pub fn scale(&self, k: f64) -> ReturnTerms {
        ReturnTerms { depth: self.depth * k, force: self.force * k, moment: self.moment * k, bonus: self.bonus * k, failure: self.failure * k }
    }

    /// The mean of several episodes' terms; None when any has none.
    pub fn mean<'a>(terms: impl Iterator<Item = Option<&'a ReturnTerms>>) -> Option<ReturnTerms> {
        let all: Option<Vec<&ReturnTerms>> = terms.collect();
        let all = all?;
        if all.is_empty() {
            return None;
        }
        let sum = all.iter().fold(ReturnTerms::default(), |acc, t| acc.add(t));
        Some(sum.scale(1.0 / all.len() as f64))
    }
}

/// Everything that can go wrong when making or stepping an environment.
#[derive(Debug, Error)]
pub enum EnvError {
    #[error("action has {got} components, the environment expects {expected}")]
    ActionDim { expected: usize, got: usize },
    #[error("action component {index} is {value}; actions must be finite")]
    NonFiniteAction { index: usize, value: f64 },
    #[error("the episode has ended (terminated); call reset before stepping again")]
    EpisodeOver,
    #[error("unknown environment '{name}': use one of {known}, a path to a .toml file, or grpc://HOST:PORT for a served environment (python -m lcrl_env serve)")]
    Unknown { name: String, known: String },
    #[error("cannot read environment file {path}: {source}")]
    Read { path: String, source: std::io::Error },
    #[error("environment file {path}: {message}")]
    Parse { path: String, message: String },
    #[error("environment config, field `{field}`: {message}")]
    Invalid { field: String, message: String },
    #[error("environment server {url}: {message}")]
    Remote { url: String, message: String },
    #[error(
        "the environment at {url} cannot fork ({reason}); CS3 runs its two branches from exact copies of one state \
         (docs/method.md §2), so it needs an environment that can fork: a MuJoCo environment, or one that copy.deepcopy copies exactly"
    )]
    ForkUnavailable { url: String, reason: String },
    #[error("the environment has not been reset yet; call reset before step")]
    NotReset,
}

impl EnvError {
    pub(crate) fn invalid(field: impl Into<String>, message: impl Into<String>) -> Self {
        EnvError::Invalid { field: field.into(), message: message.into() }
    }
}
