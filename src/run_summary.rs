//! The end of `lcrl run`: the final policy evaluated (deterministic, as
//! `lcrl train` evaluates), beside its references, and summary.json with
//! the keys of `lcrl train`'s where they apply plus the distributed
//! figures (replay ratio, policy lag, waits).

use std::path::Path;

use anyhow::Context;
use lcrl_learner::policy::Policy;
use lcrl_learner::service::runtime::{LearnerSummary, PolicyLag};
use lcrl_learner::{Algo, Connection};
use lcrl_proto::v1::LearnerStatus;
use lcrl_sim::evaluate::{evaluate, Summary};
use serde::Serialize;

use crate::preset::Preset;

/// What `lcrl run` writes as summary.json.
#[derive(Debug, Clone, Serialize)]
pub struct RunSummary {
    pub env: String,
    pub algo: Algo,
    pub connection: Connection,
    pub seed: u64,
    pub episodes: u64,
    /// Mean return of the last 10 training episodes (with exploration).
    pub final_return: f64,
    /// Mean return of the run's policy (deterministic) over `eval_episodes`:
    /// the one validation selected on held-out starts (learner/selected/),
    /// else the last.
    pub eval_return: f64,
    /// The last policy's, on the same starts, when a selected one was
    /// evaluated instead (as in `lcrl train`'s summary).
    pub last_eval_return: Option<f64>,
    /// Which policy validation chose, with every validation.
    pub selection: Option<lcrl_learner::selection::SelectionRecord>,
    pub eval_episodes: usize,
    pub eval_success_rate: Option<f64>,
    pub eval_peak_force_n: Option<f64>,
    #[serde(flatten)]
    pub eval_terms: lcrl_sim::ReturnColumns,
    pub lqr_return: Option<f64>,
    pub masked_lqr_return: Option<f64>,
    pub zero_action_return: Option<f64>,
    /// Every reference controller on the policy's own evaluation starts:
    /// a = 0, the best constant (the bar) where one is recorded for the
    /// environment, and the preset's headroom reference (`job.headroom`).
    pub references: Vec<Summary>,
    pub graph_seconds: f64,
    pub total_seconds: f64,
    pub env_steps: u64,
    pub updates: u64,
    /// Transitions sampled by updates per transition inserted.
    pub replay_ratio: f64,
    /// The limiter's target (0: unlimited or PPO).
    pub replay_ratio_target: f64,
    pub policy_lag: PolicyLag,
    pub actors_waited_s: f64,
    pub learner_waited_s: f64,
    pub actors: usize,
    pub transport: String,
}

/// The labels of the references every run has, as `references` names them.
pub use lcrl_sim::evaluate::{BEST_CONSTANT, ZERO_ACTION};

/// Evaluates the run's policy (the learner's selected one, else its newest
/// checkpoint; the newest too when they differ) and writes summary.json
/// into `run_dir`.
pub fn evaluate_run(preset: &Preset, run_dir: &Path, status: &LearnerStatus, wall_seconds: f64, actors: usize, transport: &str) -> anyhow::Result<RunSummary> {
    let job = &preset.job;
    let learner_dir = run_dir.join("learner");
    let policy = Policy::load(&learner_dir).with_context(|| format!("loading the final policy from {}", learner_dir.display()))?;
    let mut env = lcrl_sim::make_env(&job.env)?;
    policy.check_env(env.as_ref())?;
    let seed = preset.train.run.seed;
    let episodes = preset.train.run.eval_episodes.max(1);
    let scales = env.fresh();
    let first = preset.train.run.first_eval_seed();
    let (eval, _) = evaluate(env.as_mut(), "policy", episodes, first, &mut |s: &[f64]| policy.act(scales.as_ref(), s), &mut |_| {})?;
    let selection = lcrl_learner::selection::read_record(&lcrl_learner::selection::selected_dir(&learner_dir))?;
    let last_eval_return = match (&selection, lcrl_learner::checkpoint::latest_checkpoint(&learner_dir)) {
        (Some(_), Some(last_dir)) => {
            let last = Policy::load(&last_dir).with_context(|| format!("loading the last policy from {}", last_dir.display()))?;
            Some(evaluate(env.as_mut(), "last policy", episodes, first, &mut |s: &[f64]| last.act(scales.as_ref(), s), &mut |_| {})?.0.mean_return)
        }
        _ => None,
    };
    let headroom = preset.headroom()?;
    let references = lcrl_sim::evaluate::references(env.as_ref(), headroom.as_ref(), episodes, first)?;
    let lqr = lcrl_sim::lti::LtiEnv::of(env.as_ref()).and_then(|lti| lcrl_learner::lqr::lqr_return(lti, episodes, first));
    // Only a locally connected actor has a G-structured optimum to show.
    let masked = lcrl_sim::lti::LtiEnv::of(env.as_ref())
        .filter(|_| policy.architecture.shape.connection == Connection::Local)
        .and_then(|lti| lcrl_learner::lqr::masked_lqr_return(lti, &policy.architecture.shape.mask, episodes, first));
    let learner: Option<LearnerSummary> = std::fs::read_to_string(learner_dir.join("summary.json")).ok().and_then(|t| serde_json::from_str(&t).ok());
    let graph_seconds = std::fs::read_to_string(run_dir.join("graph.json"))
        .ok()
        .and_then(|t| serde_json::from_str::<serde_json::Value>(&t).ok())
        .and_then(|v| v["elapsed_s"].as_f64())
        .unwrap_or(0.0);
    let ratio = if status.inserted > 0 { status.sampled as f64 / status.inserted as f64 } else { 0.0 };
    let summary = RunSummary {
        env: job.env.clone(),
        algo: job.algo,
        connection: job.connection,
        seed,
        episodes: status.episodes,
        final_return: learner.as_ref().map_or(status.recent_return, |l| l.final_return),
        eval_return: eval.mean_return,
        last_eval_return,
        selection,
        eval_episodes: episodes,
        eval_success_rate: eval.success_rate,
        eval_peak_force_n: eval.mean_peak_force_n,
        eval_terms: eval.terms,
        lqr_return: lqr,
        masked_lqr_return: if job.connection == Connection::Local { masked } else { None },
        zero_action_return: references.iter().find(|r| r.controller == ZERO_ACTION).map(|r| r.mean_return),
        references,
        graph_seconds,
        total_seconds: wall_seconds,
        env_steps: status.env_steps,
        updates: status.updates,
        replay_ratio: ratio,
        replay_ratio_target: status.replay_ratio_target,
        policy_lag: PolicyLag { min: status.policy_lag_min, mean: status.policy_lag_mean, max: status.policy_lag_max },
        actors_waited_s: status.actors_waited_s,
        learner_waited_s: status.learner_waited_s,
        actors,
        transport: transport.to_string(),
    };
    let path = run_dir.join("summary.json");
    lcrl_learner::run_files::write_atomically(&path, (serde_json::to_string_pretty(&summary)? + "\n").as_bytes()).with_context(|| format!("writing {}", path.display()))?;
    Ok(summary)
}
