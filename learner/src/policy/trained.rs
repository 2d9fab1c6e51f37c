//! A trained actor, loaded from a checkpoint or a published snapshot, for
//! evaluation, serving (`Policy.Act`) and actors.

use std::path::Path;

use lcrl_proto::v1::PolicySnapshot;
use lcrl_sim::evaluate::{evaluate_parallel_with, EpisodeRecord, Summary};
use lcrl_sim::{Env, EnvError};
use tch::nn;

use crate::policy::action::ActionMap;
use crate::algo::agent::build_actor;
use crate::algo::nets::{batch, ActorNet};
use crate::policy::snapshot::{decode_weights, Architecture};
use crate::policy::checkpoint::{latest_checkpoint, CheckpointMeta};
use crate::{io, LearnerError};

/// The deterministic policy of a checkpoint or snapshot.
pub struct Policy {
    pub architecture: Architecture,
    /// Training episodes behind a checkpoint (None for a snapshot).
    pub episode: Option<usize>,
    /// Policy version (0 for a checkpoint of a single-process run).
    pub version: u64,
    vs: nn::VarStore,
    actor: ActorNet,
    /// PPO: the Gaussian policy's log standard deviation, if the snapshot has one.
    log_std: Option<Vec<f32>>,
}

impl Policy {
    fn empty(architecture: Architecture) -> (nn::VarStore, ActorNet, Architecture) {
        let vs = nn::VarStore::new(tch::Device::Cpu);
        let a = &architecture;
        // The weights are overwritten right after; the seed is irrelevant.
        let actor = build_actor(&vs.root(), a.shape.layout(), &a.network, 0);
        (vs, actor, architecture)
    }

    /// Loads `dir`: a `checkpoints/epNNNNNN` or `selected` folder, or a run
    /// directory, meaning the run's policy: the one selection chose
    /// (RUN/selected/) if the run has one, else its newest checkpoint.
    pub fn load(dir: &Path) -> Result<Self, LearnerError> {
        let dir = policy_dir(dir)?;
        let meta_path = dir.join("checkpoint.json");
        let weights_path = dir.join("actor.safetensors");
        let meta = std::fs::read_to_string(&meta_path).map_err(io(&meta_path))?;
        let weights = std::fs::read(&weights_path).map_err(io(&weights_path))?;
        Self::from_checkpoint(&meta, &weights).map_err(|e| LearnerError::Checkpoint(format!("{}: {e}", dir.display())))
    }

    /// The policy of a checkpoint's `checkpoint.json` text and
    /// `actor.safetensors` bytes, checked as a peer's snapshot is (the
    /// architecture before anything is built, then every weight's name,
    /// shape and finiteness). Fuzzed by fuzz/fuzz_targets/checkpoint.rs.
    pub fn from_checkpoint(meta_json: &str, weights: &[u8]) -> Result<Self, LearnerError> {
        let meta: CheckpointMeta = serde_json::from_str(meta_json).map_err(|e| LearnerError::Checkpoint(format!("checkpoint.json: {e}")))?;
        let architecture = meta.architecture();
        architecture.validate()?;
        let (vs, actor, architecture) = Self::empty(architecture);
        let mut policy = Policy { architecture, episode: Some(meta.episode), version: meta.policy_version, vs, actor, log_std: None };
        policy.update(weights, meta.policy_version)?;
        Ok(policy)
    }

    /// Builds the policy of a published snapshot.
    pub fn from_snapshot(architecture_json: &str, weights: &[u8], version: u64) -> Result<Self, LearnerError> {
        let architecture: Architecture =
            serde_json::from_str(architecture_json).map_err(|e| LearnerError::Checkpoint(format!("policy architecture: {e}")))?;
        architecture.validate()?;
        let (vs, actor, architecture) = Self::empty(architecture);
        let mut policy = Policy { architecture, episode: None, version, vs, actor, log_std: None };
        policy.update(weights, version)?;
        Ok(policy)
    }

    /// Replaces the weights with those of a newer snapshot of the same actor.
    pub fn update(&mut self, weights: &[u8], version: u64) -> Result<(), LearnerError> {
        let named = decode_weights(weights)?;
        let log_std = named.iter().find(|(n, _)| n == "log_std").and_then(|(_, t)| Vec::<f32>::try_from(t).ok());
        if log_std.as_ref().is_some_and(|l| l.len() != self.architecture.shape.action_dim || l.iter().any(|v| !v.is_finite())) {
            return Err(LearnerError::Checkpoint("snapshot log_std must hold one finite number per action".into()));
        }
        let mut variables = self.vs.variables();
        for (name, target) in variables.iter_mut() {
            let source = named.iter().find(|(n, _)| n == name).map(|(_, t)| t).ok_or_else(|| LearnerError::Checkpoint(format!("snapshot lacks weights {name}")))?;
            if source.size() != target.size() {
                return Err(LearnerError::Checkpoint(format!("snapshot weights {name} have shape {:?}, expected {:?}", source.size(), target.size())));
            }
            if !bool::try_from(source.isfinite().all()).unwrap_or(false) {
                return Err(LearnerError::Checkpoint(format!("snapshot weights {name} hold non-finite numbers")));
            }
            tch::no_grad(|| target.copy_(source));
        }
        self.log_std = log_std;
        self.version = version;
        Ok(())
    }

    /// PPO's exploration standard deviations (normalized action units).
    pub fn exploration_std(&self) -> Option<Vec<f32>> {
        self.log_std.as_ref().map(|l| l.iter().map(|v| v.exp()).collect())
    }

    /// Normalized actions in [−1, 1] for rows of normalized observations.
    pub fn act_normalized(&self, obs: &[f32]) -> Vec<f32> {
        tch::no_grad(|| {
            let out = self.actor.forward(&batch(obs, self.architecture.shape.state_dim, tch::Device::Cpu));
            Vec::<f32>::try_from(out.flatten(0, -1)).unwrap_or_default()
        })
    }

    /// How this policy's normalized actions become `env`'s actions (around
    /// its base controller, if it has one).
    pub fn action_map(&self, env: &dyn Env) -> Result<ActionMap, LearnerError> {
        Ok(ActionMap::new(env.spec(), self.architecture.base.as_deref())?.with_residual_scale(self.architecture.residual_scale))
    }

    /// The full action for a raw environment state, in the environment's
    /// bounds, base controller included.
    pub fn act(&self, env: &dyn Env, state: &[f64]) -> Vec<f64> {
        let u = self.act_normalized(&crate::algo::agent::observe(env, state));
        match self.action_map(env) {
            Ok(map) => map.to_env(&u),
            // check_env and Architecture::validate refuse a base that does
            // not fit; the plain map is the only other meaning u has.
            Err(_) => ActionMap::plain(env.spec()).to_env(&u),
        }
    }

    /// Checks that the policy fits `env`.
    pub fn check_env(&self, env: &dyn Env) -> Result<(), LearnerError> {
        let (m, n) = (env.spec().state_dim(), env.spec().action_dim());
        let a = &self.architecture;
        if (m, n) != (a.shape.state_dim, a.shape.action_dim) {
            return Err(LearnerError::Mismatch(format!(
                "the policy was trained on {} ({} states, {} actions); {} has {m} states and {n} actions",
                a.shape.env, a.shape.state_dim, a.shape.action_dim, env.spec().name
            )));
        }
        self.action_map(env)?;
        Ok(())
    }
}

/// The folder of the policy `dir` means: `dir` itself when it is a
/// `checkpoints/epNNNNNN` or `selected` folder; for a run directory the
/// run's policy, the one validation selected (RUN/selected/) if the run has
/// one, else its newest checkpoint.
pub fn policy_dir(dir: &Path) -> Result<std::path::PathBuf, LearnerError> {
    let selected = crate::policy::checkpoint::selected_dir(dir);
    if dir.join("checkpoint.json").is_file() {
        Ok(dir.to_path_buf())
    } else if selected.join("checkpoint.json").is_file() {
        Ok(selected)
    } else {
        latest_checkpoint(dir).ok_or_else(|| LearnerError::Checkpoint(format!("{} holds no checkpoint (checkpoint.json)", dir.display())))
    }
}

/// Evaluates the deterministic policy of `snapshot` on `episodes` starts of
/// `env` from seed `first`, the episodes spread over the current rayon
/// pool. A libtorch network cannot be shared between threads, so every
/// thread builds its own copy from the snapshot's bytes; the copies act
/// alike, and the records are those of one thread (a test checks it).
/// `on_episode` sees each finished episode (progress).
pub fn evaluate_snapshot(
    env: &dyn Env,
    controller: &str,
    snapshot: &PolicySnapshot,
    episodes: usize,
    first: u64,
    on_episode: &(dyn Fn(&EpisodeRecord) + Sync),
) -> Result<(Summary, Vec<EpisodeRecord>), LearnerError> {
    // Checked once here: a bad snapshot fails with its own message, not
    // as a copy that failed on some thread.
    Policy::from_snapshot(&snapshot.architecture, &snapshot.weights, snapshot.version)?.check_env(env)?;
    let copy_error = |e: LearnerError| EnvError::Invalid { field: "policy".into(), message: e.to_string() };
    let make = || {
        let policy = Policy::from_snapshot(&snapshot.architecture, &snapshot.weights, snapshot.version).map_err(copy_error)?;
        let actions = policy.action_map(env).map_err(copy_error)?;
        let probe = env.fresh();
        Ok(move |state: &[f64]| actions.to_env(&policy.act_normalized(&crate::algo::agent::observe(probe.as_ref(), state))))
    };
    Ok(evaluate_parallel_with(env, controller, episodes, first, &make, on_episode)?)
}
