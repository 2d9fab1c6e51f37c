//! Training configuration: one TOML file, every hyperparameter visible in
//! one place (cleanRL style), checked on load. The settings each
//! environment starts from and the loading are in `load`, the checks in
//! `validate`.

use serde::{Deserialize, Serialize};

/// Which algorithm trains the actor.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize, clap::ValueEnum)]
#[serde(rename_all = "kebab-case")]
pub enum Algo {
    Ddpg,
    Ppo,
}

/// How the actor is connected to the state (docs/method.md §5).
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize, clap::ValueEnum)]
#[serde(rename_all = "kebab-case")]
pub enum Connection {
    /// LCRL: subnetwork i sees only the states with G_ij = 1 (eq. 8).
    Local,
    /// GCRL baseline: one MLP over the whole state.
    Global,
    /// Ablation: n subnetworks that all see the whole state.
    FullSubnets,
}

/// The whole training configuration.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(try_from = "TrainConfigFile")]
pub struct TrainConfig {
    pub network: NetworkConfig,
    pub ddpg: DdpgConfig,
    pub ppo: PpoConfig,
    pub run: RunConfig,
    pub base: BaseConfig,
}

impl TrainConfig {
    /// The residual's reach s that `algo` acts with (learner/src/policy/action.rs,
    /// docs/peg.md "A base controller under the agent"): `[ddpg]
    /// residual_scale` where DDPG sets its own, else `[base] residual_scale`.
    pub fn residual_scale(&self, algo: Algo) -> f64 {
        match (algo, self.ddpg.residual_scale) {
            (Algo::Ddpg, Some(s)) => s,
            _ => self.base.residual_scale,
        }
    }
}

/// TrainConfig as a file may spell it: `[base]`, or its name until this
/// release, `[controller]` with `base = ...` (accepted with a deprecation
/// warning: in a peg TOML `[controller]` is the compliance controller).
#[derive(Deserialize)]
#[serde(deny_unknown_fields, default)]
struct TrainConfigFile {
    network: NetworkConfig,
    ddpg: DdpgConfig,
    ppo: PpoConfig,
    run: RunConfig,
    base: Option<BaseConfig>,
    controller: Option<LegacyBaseConfig>,
}

impl Default for TrainConfigFile {
    fn default() -> Self {
        let d = TrainConfig::default();
        TrainConfigFile { network: d.network, ddpg: d.ddpg, ppo: d.ppo, run: d.run, base: None, controller: None }
    }
}

/// `[controller]` as it was: the base under `base`.
#[derive(Deserialize)]
#[serde(deny_unknown_fields, default)]
#[derive(Default)]
struct LegacyBaseConfig {
    base: BaseController,
    best_constant_file: Option<std::path::PathBuf>,
}

/// The deprecation warning for `[controller]`.
pub const CONTROLLER_DEPRECATED: &str = "[controller] in a training config is deprecated: it is now [base], with `action` for `base` \
     (e.g. [base] action = \"best-constant\"); [controller] is still read in this release";

impl TryFrom<TrainConfigFile> for TrainConfig {
    type Error = String;

    fn try_from(file: TrainConfigFile) -> Result<Self, String> {
        let base = match (file.base, file.controller) {
            (Some(_), Some(_)) => return Err("both [base] and [controller] are set; keep [base] ([controller] is its deprecated name)".into()),
            (Some(base), None) => base,
            (None, Some(legacy)) => {
                tracing::warn!("{CONTROLLER_DEPRECATED}");
                BaseConfig { action: legacy.base, best_constant_file: legacy.best_constant_file, ..BaseConfig::default() }
            }
            (None, None) => BaseConfig::default(),
        };
        Ok(TrainConfig { network: file.network, ddpg: file.ddpg, ppo: file.ppo, run: file.run, base })
    }
}

/// `[ddpg]` keys of options measured not to help and removed (docs/peg.md,
/// "Measured and removed"), each with the value every file written before
/// its removal holds where the option was off. A file holding one at that
/// value (a checkpoint's recorded config, a study's resolved config) reads
/// as before; any other value is an unknown key, refused.
pub const REMOVED_DDPG_KEYS_AT_OFF: [(&str, RemovedOff); 4] = [
    ("warmup_actions", RemovedOff::Text("uniform")),
    ("actor_lr_warmup_updates", RemovedOff::Number),
    ("critic_disagreement", RemovedOff::Number),
    ("temporal_smoothness", RemovedOff::Number),
];

/// The "off" value of a removed key: this text, or the number 0.
#[derive(Debug, Clone, Copy)]
pub enum RemovedOff {
    Text(&'static str),
    Number,
}

impl RemovedOff {
    fn is_toml(self, value: &toml::Value) -> bool {
        match (self, value) {
            (RemovedOff::Text(off), toml::Value::String(s)) => s == off,
            (RemovedOff::Number, toml::Value::Integer(0)) => true,
            (RemovedOff::Number, toml::Value::Float(v)) => *v == 0.0,
            _ => false,
        }
    }

    fn is_json(self, value: &serde_json::Value) -> bool {
        match (self, value) {
            (RemovedOff::Text(off), serde_json::Value::String(s)) => s == off,
            (RemovedOff::Number, serde_json::Value::Number(n)) => n.as_f64() == Some(0.0),
            _ => false,
        }
    }
}

/// Drops the removed `[ddpg]` keys that hold their "off" value from a
/// config as a TOML table ([`REMOVED_DDPG_KEYS_AT_OFF`]).
pub fn drop_removed_keys_at_off(table: &mut toml::Table) {
    if let Some(toml::Value::Table(ddpg)) = table.get_mut("ddpg") {
        for (key, off) in REMOVED_DDPG_KEYS_AT_OFF {
            if ddpg.get(key).is_some_and(|v| off.is_toml(v)) {
                ddpg.remove(key);
            }
        }
    }
}

/// The same for a config as JSON (a checkpoint's `config`).
pub fn drop_removed_json_keys_at_off(config: &mut serde_json::Value) {
    if let Some(serde_json::Value::Object(ddpg)) = config.get_mut("ddpg") {
        for (key, off) in REMOVED_DDPG_KEYS_AT_OFF {
            if ddpg.get(key).is_some_and(|v| off.is_json(v)) {
                ddpg.remove(key);
            }
        }
    }
}

/// Renames a deprecated `[controller]` table of a config (as a TOML table)
/// to `[base]`, warning once, so that overrides laid over defaults mean
/// what they meant; drops removed keys at their "off" value
/// ([`drop_removed_keys_at_off`]).
pub fn migrate_legacy_tables(table: &mut toml::Table) {
    drop_removed_keys_at_off(table);
    if let Some(toml::Value::Table(mut legacy)) = table.remove("controller") {
        tracing::warn!("{CONTROLLER_DEPRECATED}");
        if let Some(action) = legacy.remove("base") {
            legacy.insert("action".into(), action);
        }
        let base = table.entry("base").or_insert_with(|| toml::Value::Table(toml::Table::new()));
        if let toml::Value::Table(base) = base {
            base.extend(legacy);
        }
    }
}

/// The controller under the agent (residual RL, learner/src/policy/action.rs):
/// a = clip(base + s·u·(ub − lb)/2, lb, ub). `[base]` in a training TOML.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct BaseConfig {
    /// "none" (the plain map onto the box, Table I), "a = 0" (on peg
    /// tasks the constant compliance controller), "best-constant", or an
    /// action [a1, …, an]. A run records the resolved numbers.
    pub action: BaseController,
    /// best_constant.json of `lcrl tune` for action = "best-constant"
    /// (default: the constant measured for a registered peg preset).
    #[serde(skip_serializing_if = "Option::is_none")]
    pub best_constant_file: Option<std::path::PathBuf>,
    /// s, the residual's reach: u = ±1 moves each action s half-widths of
    /// its box from the base, so the policy never leaves base ± s·(ub − lb)/2
    /// (1, the default: anywhere in the box). Needs a base controller.
    #[serde(skip_serializing_if = "is_full_reach")]
    pub residual_scale: f64,
}

/// Whether a residual scale is the whole box (1): left out of JSON and TOML.
pub(crate) fn is_full_reach(s: &f64) -> bool {
    *s == 1.0
}

/// Whether `s` is a residual reach a map can take: within (0, 1], and the
/// whole box (1) when there is no base to reach around. Configurations and
/// snapshots are checked with it.
pub fn residual_scale_fits(s: f64, has_base: bool) -> bool {
    s > 0.0 && s <= 1.0 && (has_base || s == 1.0)
}

impl Default for BaseConfig {
    fn default() -> Self {
        BaseConfig { action: BaseController::None, best_constant_file: None, residual_scale: 1.0 }
    }
}

impl BaseConfig {
    /// The base action once resolved (learner/src/policy/action.rs): numbers, or
    /// zeros for "a = 0"; None without a base.
    pub fn base_action(&self, action_dim: usize) -> Option<Vec<f64>> {
        match &self.action {
            BaseController::Action(a) => Some(a.clone()),
            BaseController::Zero => Some(vec![0.0; action_dim]),
            BaseController::None | BaseController::BestConstant => None,
        }
    }
}

/// The base controller setting. In TOML a string or a list of numbers.
#[derive(Debug, Clone, Default, PartialEq)]
pub enum BaseController {
    #[default]
    None,
    Zero,
    BestConstant,
    Action(Vec<f64>),
}

impl Serialize for BaseController {
    fn serialize<S: serde::Serializer>(&self, s: S) -> Result<S::Ok, S::Error> {
        match self {
            BaseController::None => s.serialize_str("none"),
            BaseController::Zero => s.serialize_str("a = 0"),
            BaseController::BestConstant => s.serialize_str("best-constant"),
            BaseController::Action(a) => a.serialize(s),
        }
    }
}

impl<'de> Deserialize<'de> for BaseController {
    fn deserialize<D: serde::Deserializer<'de>>(d: D) -> Result<Self, D::Error> {
        #[derive(Deserialize)]
        #[serde(untagged)]
        enum Raw {
            Name(String),
            Action(Vec<f64>),
        }
        match Raw::deserialize(d).map_err(|_| {
            serde::de::Error::custom("base.action must be \"none\", \"a = 0\", \"best-constant\" or a list of numbers")
        })? {
            Raw::Name(name) => match name.as_str() {
                "none" => Ok(BaseController::None),
                "a = 0" | "zero" => Ok(BaseController::Zero),
                "best-constant" => Ok(BaseController::BestConstant),
                other => Err(serde::de::Error::custom(format!(
                    "base.action = {other:?}: use \"none\", \"a = 0\", \"best-constant\" or a list of numbers"
                ))),
            },
            Raw::Action(a) => Ok(BaseController::Action(a)),
        }
    }
}

/// Network sizes. The defaults give local and global actors comparable
/// parameter counts on the 12-state, 6-action peg task (≈64k vs ≈71k).
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct NetworkConfig {
    /// Hidden layer widths of the global actor.
    pub global_hidden: Vec<usize>,
    /// Hidden layer widths of each subnetwork (local and full-subnets).
    pub subnet_hidden: Vec<usize>,
    /// Hidden layer widths of the critic (always globally connected).
    pub critic_hidden: Vec<usize>,
    /// relu, tanh or elu.
    pub activation: Activation,
}

#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "lowercase")]
pub enum Activation {
    Relu,
    Tanh,
    Elu,
}

/// DDPG (Algorithm 2). Defaults from docs/method.md Table I where it gives them.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct DdpgConfig {
    pub actor_lr: f64,
    pub critic_lr: f64,
    /// Soft update rate of the target networks.
    pub tau: f64,
    pub gamma: f64,
    pub batch_size: usize,
    pub buffer_capacity: usize,
    /// Environment steps before updates start, acted uniformly at random.
    pub warmup_steps: usize,
    /// Gaussian exploration noise (normalized action units), decaying
    /// linearly from start to end over `noise_decay_episodes`.
    pub noise_start: f64,
    pub noise_end: f64,
    pub noise_decay_episodes: usize,
    /// Update the actor (and targets) every this many critic updates; 1 is
    /// Algorithm 2 as published, 2 is TD3's delayed policy update.
    pub policy_delay: usize,
    /// Critic loss: Huber with this δ (robust to the huge TD errors an early,
    /// diverging policy leaves in the buffer); 0 means plain mean squared
    /// error as in Algorithm 2.
    pub huber_delta: f64,
    /// Throughput trade-offs (docs/scaling.md). Train every this many
    /// environment steps (1: Algorithm 2, an update per step) ...
    pub update_every: usize,
    /// ... doing this many updates of `batch_size` each time. Samples per
    /// insert are batch_size · gradient_steps / update_every: a 4× batch
    /// with update_every = 4 keeps Algorithm 2's ratio with 4× fewer, larger
    /// updates; update_every = gradient_steps = 4 keeps the updates too, in
    /// bursts (fewer policy refreshes between steps).
    pub gradient_steps: usize,
    /// Weight of mean(raw²) on the actor's pre-tanh outputs in its loss:
    /// keeps the actor out of tanh saturation, where its gradient vanishes
    /// and a wrong early push can never be undone.
    pub preactivation_l2: f64,
    /// Lower `preactivation_l2` linearly to zero over the run: the penalty
    /// steadies the start but biases actions toward zero, so it is gone by
    /// the end.
    pub preactivation_anneal: bool,
    /// Weight of mean‖μ(s) − μ'(s)‖² in the actor's loss, μ' the target
    /// actor (τ-averaged): a trust region toward the recent policy. It
    /// limits how fast the actor moves, not where it settles, unlike the
    /// residual penalty, which pulls toward the base all run.
    pub proximal_l2: f64,
    /// Std of clipped Gaussian noise on the target action (TD3's target
    /// policy smoothing); 0 is plain DDPG.
    pub target_noise: f64,
    /// TD3's clipped double-Q: a second critic, and targets from the
    /// smaller of the two target critics.
    pub twin_critics: bool,
    /// Anneal both learning rates linearly to 0 over the run (as PPO's
    /// `anneal_lr`): the final policy settles instead of jittering with the
    /// last minibatches, which matters where the return is decided by a
    /// few steps of each episode.
    pub anneal_lr: bool,
    /// Critic updates before the actor's first (0: from the start, as in
    /// Algorithm 2). Under a base controller the actor starts as the base;
    /// following an untrained critic's ∂Q/∂a, Adam's first few dozen steps
    /// carry it to an arbitrary residual (the critic's head start, second
    /// round: docs/research/2026-11-25-peg-safety-02-trust-region.md). The
    /// critic's target still follows it meanwhile.
    pub critic_warmup_updates: usize,
    /// DDPG's own reach around the base, in place of `[base]
    /// residual_scale` (same meaning, (0, 1], needs a base); PPO ignores
    /// it. A preset sets it where the reach that keeps DDPG's exploration
    /// safe would cost PPO return for nothing (configs/peg-group2.toml).
    /// A `[base] residual_scale` the user sets is the reach for both
    /// algorithms: laid over an environment's settings it replaces the
    /// preset's DDPG reach ([`TrainConfig::for_env_with`]).
    #[serde(skip_serializing_if = "Option::is_none")]
    pub residual_scale: Option<f64>,
}

/// PPO with a Gaussian policy whose mean comes from the actor.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct PpoConfig {
    pub actor_lr: f64,
    pub critic_lr: f64,
    pub gamma: f64,
    /// GAE λ.
    pub gae_lambda: f64,
    pub clip: f64,
    /// Environment steps per rollout (policy update).
    pub rollout_steps: usize,
    pub epochs: usize,
    pub minibatch_size: usize,
    /// Initial state-independent log standard deviation.
    pub log_std_init: f64,
    pub entropy_coef: f64,
    pub max_grad_norm: f64,
    /// Anneal both learning rates linearly to 0 over the run (cleanRL's
    /// default; steadies the end of training).
    pub anneal_lr: bool,
}

/// Everything about the run that is not the algorithm.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct RunConfig {
    pub episodes: usize,
    pub seed: u64,
    /// libtorch intra-op threads; 0 (the default): automatic, the cores
    /// for `lcrl train`, the cores left over after the actors for a
    /// distributed learner (`lcrl run`), the container's own for a learner
    /// alone in its pod, in each case at most 4 (more make an update at
    /// these sizes slower: `device::AUTO_MAX_THREADS`).
    pub threads: usize,
    /// Where the learner's networks compute: "cpu" or "cuda" (actors always
    /// run on the CPU).
    pub device: String,
    /// On a GPU, DDPG updates are captured once as CUDA graphs and replayed
    /// (learner/src/algo/ddpg/graphs.rs; docs/scaling.md): the same arithmetic
    /// without libtorch's per-operation dispatch. false: eager updates.
    /// Ignored on the CPU and by PPO.
    #[serde(skip_serializing_if = "is_true")]
    pub cuda_graphs: bool,
    /// Write a checkpoint every this many episodes (and at the end).
    pub checkpoint_every: usize,
    /// Keep the replay buffer in checkpoints (exact DDPG resume; larger files).
    pub save_replay: bool,
    /// CS3 samples when the graph is built before training.
    pub graph_samples: usize,
    /// T of eq. 7 when the graph is built before training (a `local@T`
    /// connection sets it). Default T_rule = 1, the above-average rule
    /// (docs/method.md, "Choosing T"), by the decision of
    /// experiments/default-graph.toml; "auto" in TOML names it; the
    /// publication's is 0.1.
    #[serde(deserialize_with = "lcrl_graph_builder::choose_t::deserialize_threshold")]
    pub graph_threshold: f64,
    /// Episodes of the deterministic policy evaluated at the end.
    pub eval_episodes: usize,
    /// The first start of that evaluation. Unset (the default): the run's
    /// own range (`lcrl_sim::seeds::run_evaluation`). A number S: starts S,
    /// S+1, …, the ones `lcrl sim --seed S` and `lcrl tune`'s evaluation
    /// use, so runs, a = 0 and the best constant are compared on the same
    /// starts (`lcrl experiment` sets it). Training, validation and tuning
    /// never use seeds below 2⁴⁰ other than tuning's 1 000 000 and up.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub eval_seed: Option<u64>,
    /// Choosing the run's policy on held-out starts (learner/src/run/selection.rs):
    /// every `validate_every` episodes, and at the start and the end, the
    /// deterministic policy runs this many validation starts, and the run's
    /// policy (RUN/selected/) is the best one seen. 0: the run's policy is
    /// its last.
    pub validation_episodes: usize,
    pub validate_every: usize,
    /// Confirming the choice at the end (learner/src/run/selection.rs): the
    /// best `confirm_candidates` validated policies, and the starting one,
    /// each run `confirm_episodes` starts of their own, and the best of
    /// them is handed over. 30 validation starts rank policies but cannot
    /// see a failure that comes once in 100–200 starts (docs/peg.md); a
    /// few hundred starts do. 0: the best validation is handed over.
    pub confirm_candidates: usize,
    pub confirm_episodes: usize,
}

impl Default for TrainConfig {
    fn default() -> Self {
        TrainConfig {
            network: NetworkConfig::default(),
            ddpg: DdpgConfig::default(),
            ppo: PpoConfig::default(),
            run: RunConfig::default(),
            base: BaseConfig::default(),
        }
    }
}

impl Default for NetworkConfig {
    fn default() -> Self {
        NetworkConfig {
            global_hidden: vec![256, 256],
            subnet_hidden: vec![96, 96],
            critic_hidden: vec![256, 256],
            activation: Activation::Relu,
        }
    }
}

impl DdpgConfig {
    /// Transitions sampled per transition stored, once warm: Algorithm 2's
    /// batch_size, scaled by the throughput settings.
    pub fn samples_per_insert(&self) -> f64 {
        (self.batch_size * self.gradient_steps) as f64 / self.update_every.max(1) as f64
    }
}

impl Default for DdpgConfig {
    fn default() -> Self {
        DdpgConfig {
            actor_lr: 1e-3,
            critic_lr: 1e-2,
            tau: 1e-3,
            gamma: 0.99,
            batch_size: 256,
            buffer_capacity: 1_000_000,
            warmup_steps: 1000,
            noise_start: 0.3,
            noise_end: 0.05,
            noise_decay_episodes: 150,
            policy_delay: 1,
            target_noise: 0.0,
            preactivation_l2: 0.0,
            preactivation_anneal: false,
            proximal_l2: 0.0,
            twin_critics: false,
            anneal_lr: false,
            critic_warmup_updates: 0,
            huber_delta: 0.0,
            update_every: 1,
            gradient_steps: 1,
            residual_scale: None,
        }
    }
}

impl Default for PpoConfig {
    fn default() -> Self {
        PpoConfig {
            actor_lr: 1e-4,
            critic_lr: 1e-3,
            gamma: 0.99,
            gae_lambda: 0.95,
            clip: 0.2,
            rollout_steps: 2048,
            epochs: 10,
            minibatch_size: 64,
            log_std_init: -0.5,
            entropy_coef: 0.0,
            max_grad_norm: 0.5,
            anneal_lr: true,
        }
    }
}

impl RunConfig {
    /// The final evaluation's first start: `eval_seed`, or the run's own
    /// evaluation range.
    pub fn first_eval_seed(&self) -> u64 {
        self.eval_seed.unwrap_or_else(|| lcrl_sim::seeds::run_evaluation(self.seed, 0))
    }
}

/// The most intra-op threads `run.threads` accepts: far above any machine
/// this runs on, low enough to catch a typo (a count, not a core mask).
pub const MAX_THREADS: usize = 1024;

fn is_true(value: &bool) -> bool {
    *value
}

impl Default for RunConfig {
    fn default() -> Self {
        RunConfig {
            episodes: 200,
            seed: 0,
            threads: 0,
            device: "cpu".into(),
            cuda_graphs: true,
            checkpoint_every: 50,
            save_replay: true,
            graph_samples: 64,
            graph_threshold: lcrl_graph_builder::choose_t::RULE_THRESHOLD,
            eval_episodes: 10,
            eval_seed: None,
            validation_episodes: 0,
            validate_every: 20,
            confirm_candidates: 0,
            confirm_episodes: 300,
        }
    }
}

mod load;
mod validate;

#[cfg(test)]
mod tests;
#[cfg(test)]
mod usage_table;
// The settings the tests of every room start from.
#[cfg(test)]
pub(crate) mod test_config;
