//! The end of `lcrl run`: summary.json of the run, the learner's own
//! (which evaluated the handed-over policy as `lcrl train` does, beside the
//! references; lcrl_learner::run::summary) with the run's actors, transport and
//! wall time added. One type and one evaluation for every loop.

use std::path::Path;

use anyhow::Context;
use lcrl_learner::policy::trained::Policy;
use lcrl_learner::run::summary::{evaluate_hand_over, read_summary, write_summary, EvaluationPlan, PolicyLag, RunSummary, ServiceFigures};
use lcrl_learner::Connection;
use lcrl_proto::v1::LearnerStatus;

use crate::preset::Preset;

/// The labels of the references every run has, as `references` names them.
pub use lcrl_sim::evaluate::{BEST_CONSTANT, ZERO_ACTION};

/// Writes the run's summary.json into `run_dir` from its learner's, and
/// returns it. A run interrupted before its budget has no learner summary:
/// its policy (the selected one, else the newest checkpoint) is evaluated
/// here, with the same evaluation.
pub fn write_run_summary(preset: &Preset, run_dir: &Path, status: &LearnerStatus, wall_seconds: f64, end: &RunEnd) -> anyhow::Result<RunSummary> {
    let learner_dir = run_dir.join("learner");
    let learner_summary = learner_dir.join("summary.json");
    let mut summary = if learner_summary.is_file() {
        read_summary(&learner_summary)?
    } else {
        interrupted_run_summary(preset, &learner_dir, status)?
    };
    summary.graph_seconds = std::fs::read_to_string(run_dir.join("graph.json"))
        .ok()
        .and_then(|t| serde_json::from_str::<serde_json::Value>(&t).ok())
        .and_then(|v| v["elapsed_s"].as_f64())
        .unwrap_or(summary.graph_seconds);
    summary.total_seconds = wall_seconds;
    let service = summary.service.get_or_insert_with(|| service_figures(status));
    service.actors = Some(end.actors);
    service.transport = Some(end.transport.clone());
    service.actor_restarts = Some(end.actor_restarts);
    service.ended_early = end.ended_early.clone();
    write_summary(run_dir, &summary).with_context(|| format!("writing {}", run_dir.join("summary.json").display()))?;
    Ok(summary)
}

/// How a local run's processes ended, for summary.json.
#[derive(Debug, Clone, Default)]
pub struct RunEnd {
    pub actors: usize,
    pub transport: String,
    pub actor_restarts: u64,
    /// Why the run stopped before its budget (None: it spent it, or was
    /// interrupted).
    pub ended_early: Option<String>,
}

/// The service's figures as the learner last reported them.
fn service_figures(status: &LearnerStatus) -> ServiceFigures {
    ServiceFigures {
        sampled: status.sampled,
        inserted: status.inserted,
        replay_ratio: if status.inserted > 0 { status.sampled as f64 / status.inserted as f64 } else { 0.0 },
        replay_ratio_target: status.replay_ratio_target,
        policy_lag: PolicyLag { min: status.policy_lag_min, mean: status.policy_lag_mean, max: status.policy_lag_max },
        actors_waited_s: status.actors_waited_s,
        learner_waited_s: status.learner_waited_s,
        policy_version: status.policy_version,
        served_version: status.served_version,
        cuts: None,
        cuts_joined: None,
        discarded_stale: Some(lcrl_learner::service::ingest::discarded_stale(&status.rejected)),
        actors: None,
        transport: None,
        actor_restarts: None,
        ended_early: None,
    }
}

/// The summary of a run stopped before its budget: its policy evaluated
/// here, its counters as the learner last reported them.
fn interrupted_run_summary(preset: &Preset, learner_dir: &Path, status: &LearnerStatus) -> anyhow::Result<RunSummary> {
    let job = &preset.job;
    let snapshot = lcrl_learner::policy::trained::policy_dir(learner_dir)
        .and_then(|dir| lcrl_learner::policy::snapshot::read_snapshot(&dir))
        .with_context(|| format!("loading the policy from {}", learner_dir.display()))?;
    let policy = Policy::from_snapshot(&snapshot.architecture, &snapshot.weights, snapshot.version)?;
    let env = lcrl_sim::make_env(&job.env)?;
    policy.check_env(env.as_ref())?;
    let headroom = preset.headroom()?;
    let plan = EvaluationPlan {
        episodes: preset.train.run.eval_episodes,
        first_seed: preset.train.run.first_eval_seed(),
        local_mask: (job.connection == Connection::Local).then_some(policy.architecture.shape.mask.as_slice()),
        headroom: headroom.as_ref(),
    };
    let evaluation = evaluate_hand_over(env.as_ref(), None, &snapshot, &plan)?;
    Ok(RunSummary {
        env: job.env.clone(),
        algo: job.algo,
        connection: job.connection,
        seed: preset.train.run.seed,
        episodes: status.episodes as usize,
        final_return: status.recent_return,
        evaluation,
        selection: lcrl_learner::run::selection::read_record(&lcrl_learner::run::selection::selected_dir(learner_dir))?,
        graph_seconds: 0.0,
        graph: None,
        optimization_seconds: 0.0,
        total_seconds: 0.0,
        env_steps: status.env_steps,
        updates: status.updates,
        critic_updates: 0,
        skipped_updates: 0,
        diverged_env: 0,
        samples_drawn: status.sampled,
        actor_params: 0,
        critic_params: 0,
        service: Some(service_figures(status)),
    })
}

/// A run's reference lines: the LQR optimum and the best controller with
/// the actor's connection pattern (linear systems), and a = 0.
pub fn references(s: &RunSummary) -> Vec<(String, f64)> {
    let masked = if s.connection == lcrl_learner::Connection::Local { s.evaluation.masked_lqr_return } else { None };
    reference_lines(s.evaluation.lqr_return, masked, s.evaluation.zero_action_return)
}

/// Reference lines from their values, where a run has them.
pub fn reference_lines(lqr: Option<f64>, masked_lqr: Option<f64>, zero_action: Option<f64>) -> Vec<(String, f64)> {
    let mut lines = Vec::new();
    lines.extend(lqr.map(|v| ("LQR".to_string(), v)));
    lines.extend(masked_lqr.map(|v| ("masked LQR (best with G)".to_string(), v)));
    lines.extend(zero_action.map(|v| ("a = 0".to_string(), v)));
    lines
}
