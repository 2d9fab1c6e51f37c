//! Training configuration: one TOML file, every hyperparameter visible in
//! one place (cleanRL style), checked on load.

use std::path::Path;

use serde::{Deserialize, Serialize};

use crate::LearnerError;

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
                BaseConfig { action: legacy.base, best_constant_file: legacy.best_constant_file }
            }
            (None, None) => BaseConfig::default(),
        };
        Ok(TrainConfig { network: file.network, ddpg: file.ddpg, ppo: file.ppo, run: file.run, base })
    }
}

/// Renames a deprecated `[controller]` table of a config (as a TOML table)
/// to `[base]`, warning once, so that overrides laid over defaults mean
/// what they meant.
pub fn migrate_legacy_tables(table: &mut toml::Table) {
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

/// The controller under the agent (residual RL, learner/src/action.rs):
/// a = clip(base + u·(ub − lb)/2, lb, ub). `[base]` in a training TOML.
#[derive(Debug, Clone, Default, PartialEq, Serialize, Deserialize)]
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
}

impl BaseConfig {
    /// The base action once resolved (learner/src/action.rs): numbers, or
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

/// How DDPG acts while its replay buffer warms up (`warmup_steps`).
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "lowercase")]
pub enum WarmupActions {
    /// Uniform over the whole normalized box: the usual random start, which
    /// shows the critic every action but drives a robot with them.
    Uniform,
    /// The initial policy plus the exploration noise (`noise_start`), as
    /// after the warm-up, only without updates. The last layer's init makes
    /// the initial residual ≈ 0, so under a base controller this explores
    /// around the base (docs/peg.md, "Training that stays near its base").
    Policy,
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
    /// Environment steps before updates start, acted as `warmup_actions` says.
    pub warmup_steps: usize,
    /// What the agent does during those steps: uniformly random actions
    /// (the default), or its initial policy with the exploration noise.
    pub warmup_actions: WarmupActions,
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
    /// Weight κ of the twin critics' disagreement in the actor's objective:
    /// the actor maximizes mean(Q₁, Q₂) − κ·|Q₁ − Q₂| instead of Q₁ (κ = 0.5
    /// is min(Q₁, Q₂)). Two critics fitted to the same targets agree where
    /// the buffer has data and drift apart where they extrapolate, so the
    /// actor is held back from actions only an extrapolating critic
    /// praises (docs/peg.md, "Training that stays near its base"). Needs
    /// `twin_critics`; 0 (the default) follows the first critic alone.
    pub critic_disagreement: f64,
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
    /// carry it to an arbitrary residual (docs/peg.md, "The critic's head
    /// start"). The critic's target still follows it meanwhile.
    pub critic_warmup_updates: usize,
    /// Raise the actor's learning rate linearly from 0 to `actor_lr` over
    /// its first this many updates (0: full rate from the first). Adam's
    /// step is about lr per weight however weak ∂Q/∂a is, so an actor at
    /// full rate leaves its base at full speed on an untrained critic
    /// (docs/peg.md, "Training that stays near its base"); the ramp slows
    /// only the start, where the trust region (`proximal_l2`) brakes all run.
    pub actor_lr_warmup_updates: usize,
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
    /// Write a checkpoint every this many episodes (and at the end).
    pub checkpoint_every: usize,
    /// Keep the replay buffer in checkpoints (exact DDPG resume; larger files).
    pub save_replay: bool,
    /// CS3 samples when the graph is built before training.
    pub graph_samples: usize,
    /// T of eq. 7 when the graph is built before training (a `local@T`
    /// connection sets it; the publication's 0.1 by default).
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
    /// Choosing the run's policy on held-out starts (learner/src/selection.rs):
    /// every `validate_every` episodes, and at the start and the end, the
    /// deterministic policy runs this many validation starts, and the run's
    /// policy (RUN/selected/) is the best one seen. 0: the run's policy is
    /// its last.
    pub validation_episodes: usize,
    pub validate_every: usize,
    /// Falling back to the run's selected policy (learner/src/fallback.rs):
    /// a training episode of the current policy that returns less than the
    /// base's validation return minus this margin hands the next
    /// `fallback_episodes` training episodes to the selected policy. Unset
    /// (the default): off. `lcrl train` with DDPG and validation only.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub fallback_margin: Option<f64>,
    /// Episodes the selected policy acts after each such episode; unset: 5.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub fallback_episodes: Option<usize>,
    /// The fallback's gate: the current policy also acts only while its
    /// latest validation scored within the margin.
    #[serde(skip_serializing_if = "std::ops::Not::not")]
    pub fallback_gate: bool,
    /// The selected policy acts in fallback episodes with the run's
    /// exploration noise around it (off: deterministic).
    #[serde(skip_serializing_if = "std::ops::Not::not")]
    pub fallback_explore: bool,
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
            warmup_actions: WarmupActions::Uniform,
            noise_start: 0.3,
            noise_end: 0.05,
            noise_decay_episodes: 150,
            policy_delay: 1,
            target_noise: 0.0,
            preactivation_l2: 0.0,
            preactivation_anneal: false,
            proximal_l2: 0.0,
            critic_disagreement: 0.0,
            twin_critics: false,
            anneal_lr: false,
            critic_warmup_updates: 0,
            actor_lr_warmup_updates: 0,
            huber_delta: 0.0,
            update_every: 1,
            gradient_steps: 1,
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
    /// The fallback rule this run asks for, given its base's validation
    /// return (None when `fallback_margin` is unset).
    pub fn fallback(&self, base_return: f64) -> Option<crate::fallback::Fallback> {
        let rule = crate::fallback::Fallback::new(base_return, self.fallback_margin?, self.fallback_episodes.unwrap_or(5));
        Some(if self.fallback_gate { rule.gated() } else { rule })
    }

    /// The final evaluation's first start: `eval_seed`, or the run's own
    /// evaluation range.
    pub fn first_eval_seed(&self) -> u64 {
        self.eval_seed.unwrap_or_else(|| lcrl_sim::seeds::run_evaluation(self.seed, 0))
    }
}

impl Default for RunConfig {
    fn default() -> Self {
        RunConfig {
            episodes: 200,
            seed: 0,
            threads: 0,
            device: "cpu".into(),
            checkpoint_every: 50,
            save_replay: true,
            graph_samples: 64,
            graph_threshold: lcrl_graph_builder::PAPER_THRESHOLD,
            eval_episodes: 10,
            eval_seed: None,
            validation_episodes: 0,
            validate_every: 20,
            fallback_margin: None,
            fallback_episodes: None,
            fallback_gate: false,
            fallback_explore: false,
        }
    }
}

/// configs/lti-fast.toml, compiled in: the settings that work on lti-paper.
const LTI_FAST: &str = include_str!("../../configs/lti-fast.toml");
/// configs/peg.toml, compiled in: the settings that work on the peg tasks.
const PEG: &str = include_str!("../../configs/peg.toml");
/// configs/peg-experiment.toml, compiled in: peg-experiment's DDPG
/// settings, laid over configs/peg.toml.
const PEG_EXPERIMENT: &str = include_str!("../../configs/peg-experiment.toml");
/// configs/peg-rand.toml, compiled in: the randomized presets' DDPG
/// settings, laid over configs/peg.toml.
const PEG_RAND: &str = include_str!("../../configs/peg-rand.toml");
/// configs/peg-group1.toml, compiled in: peg-group1's DDPG settings, laid
/// over configs/peg.toml.
const PEG_GROUP1: &str = include_str!("../../configs/peg-group1.toml");

impl TrainConfig {
    /// The training settings that work on a registered environment, used
    /// when no --config is given, and where they come from. lti-paper gets
    /// configs/lti-fast.toml and the peg presets configs/peg.toml (Table
    /// I's defaults diverge on both; docs/peg.md), with
    /// configs/peg-experiment.toml over it on peg-experiment and
    /// configs/peg-rand.toml on the randomized presets; every other environment
    /// gets Table I's defaults (configs/table1-ddpg.toml, table1-ppo.toml).
    pub fn for_env(env: &str) -> (TrainConfig, &'static str) {
        let peg = lcrl_sim::peg::PegConfig::preset(env);
        let embedded: Option<(&[&str], &str)> = match (env, peg) {
            ("lti-paper", _) => Some((&[LTI_FAST], "configs/lti-fast.toml (the settings for lti-paper)")),
            (name, _) if lcrl_sim::lti::LtiConfig::blocks_size(name).is_some() => Some((&[LTI_FAST], "configs/lti-fast.toml (the linear systems' settings, used for lti-blocks-N)")),
            ("peg-experiment", _) => Some((&[PEG, PEG_EXPERIMENT], "configs/peg.toml with configs/peg-experiment.toml (the settings for peg-experiment)")),
            (_, Some(peg)) if peg.randomize.is_some() => Some((&[PEG, PEG_RAND], "configs/peg.toml with configs/peg-rand.toml (the settings for the randomized peg presets)")),
            ("peg-group1", _) => Some((&[PEG, PEG_GROUP1], "configs/peg.toml with configs/peg-group1.toml (the settings for peg-group1)")),
            (_, Some(_)) => Some((&[PEG], "configs/peg.toml (the settings for the peg presets)")),
            (_, None) => None,
        };
        // The embedded files are checked by a unit test; a parse failure
        // here would be a build defect, and Table I's defaults stand in.
        let layered = |files: &[&str]| -> Option<TrainConfig> {
            let mut merged = toml::Table::new();
            for text in files {
                lcrl_sim::overlay(&mut merged, &toml::from_str::<toml::Table>(text).ok()?);
            }
            toml::Value::Table(merged).try_into().ok()
        };
        match embedded.and_then(|(files, source)| Some((layered(files)?, source))) {
            Some((cfg, source)) => (cfg, source),
            None => (TrainConfig::default(), "Table I defaults"),
        }
    }

    /// `env`'s settings (see [`TrainConfig::for_env`]) with a table of
    /// overrides laid over them (sections merge key by key), checked.
    pub fn for_env_with(env: &str, overrides: &toml::Table) -> Result<TrainConfig, LearnerError> {
        let (defaults, _) = Self::for_env(env);
        let mut merged = toml::Table::try_from(&defaults).map_err(|e| LearnerError::Config(e.to_string()))?;
        let mut overrides = overrides.clone();
        migrate_legacy_tables(&mut overrides);
        lcrl_sim::overlay(&mut merged, &overrides);
        let cfg: TrainConfig = toml::Value::Table(merged).try_into().map_err(|e: toml::de::Error| LearnerError::Config(e.to_string()))?;
        cfg.validate()?;
        Ok(cfg)
    }

    /// Reads a TOML file whose missing keys keep `env`'s settings.
    pub fn load_for_env(path: &Path, env: &str) -> Result<Self, LearnerError> {
        let text = std::fs::read_to_string(path).map_err(|source| LearnerError::Io { path: path.into(), source })?;
        Self::parse_for_env(&text, env).map_err(|e| LearnerError::Config(format!("{}: {e}", path.display())))
    }

    /// [`TrainConfig::load_for_env`] on a file's text (fuzzed by
    /// fuzz/fuzz_targets/toml_config.rs).
    pub fn parse_for_env(text: &str, env: &str) -> Result<Self, LearnerError> {
        let table: toml::Table = toml::from_str(text).map_err(|e| LearnerError::Config(e.to_string()))?;
        Self::for_env_with(env, &table)
    }

    /// Reads a TOML file (missing keys keep their defaults).
    pub fn load(path: &Path) -> Result<Self, LearnerError> {
        let text = std::fs::read_to_string(path).map_err(|source| LearnerError::Io { path: path.into(), source })?;
        let cfg: TrainConfig =
            toml::from_str(&text).map_err(|e| LearnerError::Config(format!("{}: {e}", path.display())))?;
        cfg.validate()?;
        Ok(cfg)
    }

    /// Checks every value, naming the field.
    pub fn validate(&self) -> Result<(), LearnerError> {
        let bad = |field: &str, why: &str| Err(LearnerError::Config(format!("`{field}` {why}")));
        let positive = [
            ("ddpg.actor_lr", self.ddpg.actor_lr),
            ("ddpg.critic_lr", self.ddpg.critic_lr),
            ("ddpg.tau", self.ddpg.tau),
            ("ppo.actor_lr", self.ppo.actor_lr),
            ("ppo.critic_lr", self.ppo.critic_lr),
            ("ppo.clip", self.ppo.clip),
            ("ppo.max_grad_norm", self.ppo.max_grad_norm),
        ];
        for (field, v) in positive {
            if !(v.is_finite() && v > 0.0) {
                return bad(field, &format!("must be a finite number > 0, got {v}"));
            }
        }
        for (field, v) in [("ddpg.gamma", self.ddpg.gamma), ("ppo.gamma", self.ppo.gamma), ("ppo.gae_lambda", self.ppo.gae_lambda), ("ddpg.tau", self.ddpg.tau)] {
            if !(0.0..=1.0).contains(&v) {
                return bad(field, &format!("must be within [0, 1], got {v}"));
            }
        }
        for (field, v) in [("ddpg.noise_start", self.ddpg.noise_start), ("ddpg.noise_end", self.ddpg.noise_end), ("ddpg.target_noise", self.ddpg.target_noise), ("ddpg.preactivation_l2", self.ddpg.preactivation_l2), ("ddpg.proximal_l2", self.ddpg.proximal_l2), ("ddpg.critic_disagreement", self.ddpg.critic_disagreement), ("ddpg.huber_delta", self.ddpg.huber_delta), ("ppo.entropy_coef", self.ppo.entropy_coef)] {
            if !(v.is_finite() && v >= 0.0) {
                return bad(field, &format!("must be a finite number ≥ 0, got {v}"));
            }
        }
        if self.ddpg.critic_disagreement > 0.0 && !self.ddpg.twin_critics {
            return bad("ddpg.critic_disagreement", "needs ddpg.twin_critics = true (the disagreement is between the two critics)");
        }
        if let Some(margin) = self.run.fallback_margin {
            if !(margin.is_finite() && margin >= 0.0) {
                return bad("run.fallback_margin", &format!("must be a finite number ≥ 0 (a return below the base's by more hands over), got {margin}"));
            }
            if self.run.validation_episodes == 0 {
                return bad("run.fallback_margin", "needs validation (run.validation_episodes ≥ 1): the fallback acts with the run's selected policy");
            }
        }
        for (field, set) in [("run.fallback_gate", self.run.fallback_gate), ("run.fallback_explore", self.run.fallback_explore)] {
            if set && self.run.fallback_margin.is_none() {
                return bad(field, "needs run.fallback_margin (the fallback's threshold is the base's validation return minus it)");
            }
        }
        if self.run.fallback_episodes == Some(0) {
            return bad("run.fallback_episodes", "must be at least 1");
        }
        if !self.ppo.log_std_init.is_finite() {
            return bad("ppo.log_std_init", "must be finite");
        }
        let at_least_one = [
            ("ddpg.batch_size", self.ddpg.batch_size),
            ("ddpg.buffer_capacity", self.ddpg.buffer_capacity),
            ("ddpg.policy_delay", self.ddpg.policy_delay),
            ("ddpg.update_every", self.ddpg.update_every),
            ("ddpg.gradient_steps", self.ddpg.gradient_steps),
            ("ppo.rollout_steps", self.ppo.rollout_steps),
            ("ppo.epochs", self.ppo.epochs),
            ("ppo.minibatch_size", self.ppo.minibatch_size),
            ("run.episodes", self.run.episodes),
            ("run.checkpoint_every", self.run.checkpoint_every),
            ("run.graph_samples", self.run.graph_samples),
            ("run.validate_every", self.run.validate_every),
        ];
        for (field, v) in at_least_one {
            if v == 0 {
                return bad(field, "must be at least 1");
            }
        }
        if !(self.run.graph_threshold.is_finite() && self.run.graph_threshold > 0.0) {
            return bad("run.graph_threshold", &format!("must be a finite number > 0 (the publication uses 0.1), got {}", self.run.graph_threshold));
        }
        for (field, sizes) in [("network.global_hidden", &self.network.global_hidden), ("network.subnet_hidden", &self.network.subnet_hidden), ("network.critic_hidden", &self.network.critic_hidden)] {
            if sizes.is_empty() || sizes.contains(&0) {
                return bad(field, "must list at least one layer width, each at least 1");
            }
        }
        if self.run.threads > crate::device::MAX_THREADS {
            return bad("run.threads", &format!("must be 0 (automatic) or a thread count up to {}, got {}", crate::device::MAX_THREADS, self.run.threads));
        }
        if !matches!(self.run.device.as_str(), "cpu" | "cuda") {
            return bad("run.device", &format!("must be \"cpu\" or \"cuda\", got \"{}\"", self.run.device));
        }
        Ok(())
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// `[controller] base = …`, the deprecated name of `[base] action = …`,
    /// still loads, to the same config, from a file, through overrides laid
    /// over an environment's settings, and from a checkpoint's JSON; both
    /// at once are refused.
    #[test]
    fn the_deprecated_controller_table_still_loads() {
        let new: TrainConfig = toml::from_str("[base]\naction = \"a = 0\"\n").unwrap();
        let old: TrainConfig = toml::from_str("[controller]\nbase = \"a = 0\"\n").unwrap();
        assert_eq!(new, old);
        assert_eq!(new.base.action, BaseController::Zero);
        let overrides = |text: &str| TrainConfig::for_env_with("peg-group1", &toml::from_str(text).unwrap()).unwrap();
        let (new, old) = (overrides("[base]\naction = \"a = 0\"\n"), overrides("[controller]\nbase = \"a = 0\"\n"));
        assert_eq!(new, old);
        assert_eq!(old.base.action, BaseController::Zero, "the override wins over peg.toml's best constant");
        let json = serde_json::to_value(&new).unwrap();
        let mut legacy = json.as_object().unwrap().clone();
        let base = legacy.remove("base").unwrap();
        legacy.insert("controller".into(), serde_json::json!({ "base": base["action"] }));
        assert_eq!(serde_json::from_value::<TrainConfig>(serde_json::Value::Object(legacy)).unwrap(), new);
        let both = toml::from_str::<TrainConfig>("[base]\naction = \"none\"\n[controller]\nbase = \"a = 0\"\n").unwrap_err().to_string();
        assert!(both.contains("both [base] and [controller]"), "{both}");
    }

    #[test]
    fn defaults_follow_table_1_and_validate() {
        let cfg = TrainConfig::default();
        cfg.validate().unwrap();
        assert_eq!((cfg.ddpg.actor_lr, cfg.ddpg.critic_lr, cfg.ddpg.tau), (1e-3, 1e-2, 1e-3));
        assert_eq!((cfg.ppo.actor_lr, cfg.ppo.critic_lr), (1e-4, 1e-3));
    }

    #[test]
    fn registered_environments_get_their_working_settings() {
        let (lti, source) = TrainConfig::for_env("lti-paper");
        assert!(source.contains("lti-fast"), "{source}");
        let file: TrainConfig = toml::from_str(LTI_FAST).unwrap();
        assert_eq!(lti, file);
        lti.validate().unwrap();
        assert_eq!(lti.run.episodes, 1000, "lti-fast.toml's budget is 1000 episodes");
        assert_eq!(lti.network.activation, Activation::Elu);
        let (peg, source) = TrainConfig::for_env("peg-group2");
        assert!(source.contains("configs/peg.toml"), "{source}");
        assert_eq!(peg, toml::from_str::<TrainConfig>(PEG).unwrap());
        peg.validate().unwrap();
        // peg-group1: peg.toml with the trust region, nothing else.
        let (group1, source) = TrainConfig::for_env("peg-group1");
        assert!(source.contains("configs/peg-group1.toml"), "{source}");
        group1.validate().unwrap();
        assert_eq!((group1.ddpg.proximal_l2, peg.ddpg.proximal_l2), (3.0, 0.0));
        let ddpg = DdpgConfig { proximal_l2: 0.0, ..group1.ddpg.clone() };
        assert_eq!(TrainConfig { ddpg, ..group1 }, peg, "peg-group1.toml changes only [ddpg] proximal_l2");
        // The randomized presets: peg.toml with the residual penalty, nothing else.
        for name in ["peg-group1-rand", "peg-group2-rand"] {
            let (rand, source) = TrainConfig::for_env(name);
            assert!(source.contains("configs/peg-rand.toml"), "{source}");
            rand.validate().unwrap();
            assert_eq!((rand.ddpg.critic_warmup_updates, rand.ddpg.preactivation_l2), (0, 10.0), "{name}");
            let ddpg = DdpgConfig { preactivation_l2: peg.ddpg.preactivation_l2, ..rand.ddpg.clone() };
            assert_eq!(TrainConfig { ddpg, ..rand }, peg, "peg-rand.toml changes only [ddpg] preactivation_l2 ({name})");
        }
        // peg-experiment: peg.toml with its own DDPG keys over it, nothing else.
        let (experiment, source) = TrainConfig::for_env("peg-experiment");
        assert!(source.contains("configs/peg-experiment.toml"), "{source}");
        experiment.validate().unwrap();
        assert_eq!((experiment.ddpg.critic_warmup_updates, experiment.ddpg.preactivation_l2), (5000, 10.0));
        let with_peg_ddpg = TrainConfig { ddpg: peg.ddpg.clone(), ..experiment.clone() };
        assert_eq!(with_peg_ddpg, peg, "peg-experiment.toml changes only [ddpg]");
        assert_eq!(TrainConfig::for_env("grpc://127.0.0.1:1").0, TrainConfig::default());
    }

    /// The named Table I files hold exactly the publication's settings
    /// (the defaults of this file), whatever environment they are laid
    /// over: a study can put them beside the working settings.
    #[test]
    fn table1_files_are_table1_over_any_environment() {
        for name in ["table1-ddpg.toml", "table1-ppo.toml"] {
            let path = Path::new(env!("CARGO_MANIFEST_DIR")).join("../configs").join(name);
            for env in ["peg-group1", "lti-paper"] {
                let cfg = TrainConfig::load_for_env(&path, env).unwrap();
                let table1 = TrainConfig::default();
                if name.contains("ddpg") {
                    assert_eq!((&cfg.ddpg, &cfg.network, &cfg.base), (&table1.ddpg, &table1.network, &table1.base), "{name} over {env}");
                } else {
                    assert_eq!((&cfg.ppo, &cfg.network, &cfg.base), (&table1.ppo, &table1.network, &table1.base), "{name} over {env}");
                }
            }
        }
    }

    #[test]
    fn bad_values_name_the_field() {
        let err = |text: &str| -> String {
            match toml::from_str::<TrainConfig>(text).map_err(|e| e.to_string()).and_then(|c| c.validate().map_err(|e| e.to_string())) {
                Err(e) => e,
                Ok(()) => panic!("accepted {text}"),
            }
        };
        assert!(err("[ddpg]\nactor_lr = -0.001\n").contains("ddpg.actor_lr"));
        assert!(err("[ppo]\ngamma = 1.5\n").contains("ppo.gamma"));
        assert!(err("[network]\nsubnet_hidden = []\n").contains("network.subnet_hidden"));
        assert!(err("[run]\ndevice = \"tpu\"\n").contains("run.device"));
        assert!(err("[ddpg]\nactor_rate = 0.1\n").contains("actor_rate"));
        assert!(err("[ddpg]\ncritic_disagreement = 1.0\n").contains("needs ddpg.twin_critics"));
        assert!(err("[ddpg]\ntwin_critics = true\ncritic_disagreement = -1.0\n").contains("ddpg.critic_disagreement"));
    }
}
