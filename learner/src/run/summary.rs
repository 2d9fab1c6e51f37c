//! summary.json, the one record of what a run hands over, from every loop:
//! `lcrl train` (one process), `lcrl-learner` (the distributed service,
//! under `lcrl run`, compose or Kubernetes) and `lcrl run` (which adds the
//! actors and the wall time to its learner's). The evaluation of the
//! handed-over policy is made here too, once, for all of them.

use std::path::Path;

use lcrl_proto::v1::PolicySnapshot;
use lcrl_sim::evaluate::{references, Summary, ZERO_ACTION};
use lcrl_sim::tune::feedback::StoredPolicy;
use lcrl_sim::Env;
use serde::{Deserialize, Serialize};

use crate::config::{Algo, Connection};
use crate::policy::trained::evaluate_snapshot;
use crate::run::files::{write_atomically, SelectionRecord};
use crate::LearnerError;

/// What summary.json holds. The JSON is flat: the sections' keys sit at the
/// top level, and a section a loop does not have is absent.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct RunSummary {
    pub env: String,
    pub algo: Algo,
    pub connection: Connection,
    pub seed: u64,
    pub episodes: usize,
    /// Mean return of the last 10 training episodes (with exploration).
    pub final_return: f64,
    /// The handed-over policy on the evaluation starts, beside references.
    #[serde(flatten)]
    pub evaluation: Evaluation,
    /// Which policy validation chose, and every validation.
    #[serde(default)]
    pub selection: Option<SelectionRecord>,
    #[serde(default)]
    pub graph_seconds: f64,
    /// Which graph a local actor trained on, when it was given as a file
    /// (`--graph`: a study's draw or graph task): the file and what it
    /// says of its origin (a random-rows draw names its index and seed).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub graph: Option<GraphRecord>,
    /// Time spent in updates (`lcrl train`; 0 where the learner's updates
    /// overlap the actors' stepping and are not timed apart).
    #[serde(default)]
    pub optimization_seconds: f64,
    pub total_seconds: f64,
    pub env_steps: u64,
    /// Gradient steps of the actor (DDPG with `policy_delay` d: one in d
    /// updates of the critics).
    pub updates: u64,
    /// Gradient steps of the critics (absent: not known, e.g. `lcrl run`).
    #[serde(default, skip_serializing_if = "is_zero")]
    pub critic_updates: u64,
    /// Updates undone because they left a NaN or ∞ in the networks
    /// (learner/src/algo/ddpg: the weights before them stay).
    #[serde(default, skip_serializing_if = "is_zero")]
    pub skipped_updates: u64,
    /// Episodes ended because the environment diverged (a non-finite or
    /// out-of-bounds state or reward); `lcrl train` only: actors count
    /// theirs in `lcrl_actor_diverged_env`.
    #[serde(default, skip_serializing_if = "is_zero")]
    pub diverged_env: u64,
    /// Transitions drawn from the replay buffer (DDPG: batch_size per critic
    /// update); against env_steps, the replay ratio the run kept.
    #[serde(default)]
    pub samples_drawn: u64,
    #[serde(default)]
    pub actor_params: usize,
    #[serde(default)]
    pub critic_params: usize,
    /// The distributed service's figures (`lcrl-learner`, `lcrl run`).
    #[serde(flatten, default, skip_serializing_if = "Option::is_none")]
    pub service: Option<ServiceFigures>,
}

/// The graph file a run was given, and its recorded origin.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct GraphRecord {
    pub file: String,
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub origin: Option<String>,
}

/// The handed-over policy, evaluated deterministically on `eval_episodes`
/// starts from `eval_seed`, and every reference on the same starts.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct Evaluation {
    /// Mean return of the handed-over policy: the one validation selected
    /// (RUN/selected/), else the last.
    pub eval_return: f64,
    /// Starts of the evaluation (absent in runs written before it was recorded).
    #[serde(default)]
    pub eval_episodes: Option<usize>,
    /// The evaluation's first start (its episodes use this seed and the
    /// following ones).
    #[serde(default)]
    pub eval_seed: Option<u64>,
    /// The evaluation's success rate and mean peak force (peg tasks).
    #[serde(default)]
    pub eval_success_rate: Option<f64>,
    #[serde(default)]
    pub eval_peak_force_n: Option<f64>,
    /// The evaluation return split into its reward terms (peg tasks).
    #[serde(flatten)]
    pub eval_terms: lcrl_sim::ReturnColumns,
    /// The last policy's on the same starts, when selection handed over
    /// another one.
    #[serde(default)]
    pub last_eval_return: Option<f64>,
    /// The neutral constant action a = 0 on the same starts (on peg tasks
    /// the constant compliance controller): a reference line.
    #[serde(default)]
    pub zero_action_return: Option<f64>,
    /// Every reference controller on the same starts: a = 0, the best
    /// constant where one is recorded for the environment, and a headroom
    /// reference where the run names one.
    #[serde(default)]
    pub references: Vec<Summary>,
    /// The LQR controller's mean return (linear environments only).
    #[serde(default)]
    pub lqr_return: Option<f64>,
    /// The best controller with a local actor's connection pattern (a = −K s
    /// with K zero where the mask is): its ceiling, which may be below
    /// `lqr_return` when G hides states the optimum uses.
    #[serde(default)]
    pub masked_lqr_return: Option<f64>,
}

/// Replay, flow and serving figures of the distributed service.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct ServiceFigures {
    /// Transitions drawn by updates and transitions stored.
    pub sampled: u64,
    pub inserted: u64,
    /// sampled / inserted.
    pub replay_ratio: f64,
    /// The limiter's target (0: unlimited or PPO).
    pub replay_ratio_target: f64,
    pub policy_lag: PolicyLag,
    pub actors_waited_s: f64,
    pub learner_waited_s: f64,
    /// The newest policy version, and the one served once training ended
    /// (the selected one, or the newest without a selection).
    pub policy_version: u64,
    pub served_version: u64,
    /// PPO: steps that arrived marked `cut` (an actor's batch end
    /// mid-episode) and how many its advantages ran on across
    /// (docs/architecture.md, "One transition, one meaning").
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub cuts: Option<u64>,
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub cuts_joined: Option<u64>,
    /// PPO: transitions that arrived but were not trained on, being more
    /// policy versions behind than the lag bound allows (`stale`, and
    /// `stale_incarnation`: acted by a previous learner process).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub discarded_stale: Option<u64>,
    /// `lcrl run`: its actor processes and their transport.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub actors: Option<usize>,
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub transport: Option<String>,
    /// `lcrl run`: actor processes restarted after they died.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub actor_restarts: Option<u64>,
    /// `lcrl run`: why the run ended before its budget, if it did.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub ended_early: Option<String>,
}

/// Policy lag over the window of recently stored transitions.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
pub struct PolicyLag {
    pub min: u64,
    pub mean: f64,
    pub max: u64,
}

/// Where and against what a run's handed-over policy is evaluated.
pub struct EvaluationPlan<'a> {
    pub episodes: usize,
    pub first_seed: u64,
    /// A local actor's mask: its masked-LQR ceiling (linear systems only;
    /// with every state connected it is LQR again).
    pub local_mask: Option<&'a [Vec<u8>]>,
    pub headroom: Option<&'a StoredPolicy>,
}

/// Evaluates the handed-over policy: `selected` when validation chose a
/// policy other than the last, else `last`; the last too when they differ;
/// and the references, all on the same starts, every one's episodes on
/// every core of the current rayon pool.
pub fn evaluate_hand_over(env: &dyn Env, selected: Option<&PolicySnapshot>, last: &PolicySnapshot, plan: &EvaluationPlan) -> Result<Evaluation, LearnerError> {
    let (episodes, first) = (plan.episodes.max(1), plan.first_seed);
    let (last_summary, _) = evaluate_snapshot(env, "last policy", last, episodes, first, &|_| {})?;
    let (handed, last_eval_return) = match selected {
        Some(policy) => (evaluate_snapshot(env, "selected policy", policy, episodes, first, &|_| {})?.0, Some(last_summary.mean_return)),
        None => (last_summary, None),
    };
    let references = references(env, plan.headroom, episodes, first)?;
    let lti = lcrl_sim::lti::LtiEnv::of(env);
    Ok(Evaluation {
        eval_return: handed.mean_return,
        eval_episodes: Some(episodes),
        eval_seed: Some(first),
        eval_success_rate: handed.success_rate,
        eval_peak_force_n: handed.mean_peak_force_n,
        eval_terms: handed.terms,
        last_eval_return,
        zero_action_return: references.iter().find(|r| r.controller == ZERO_ACTION).map(|r| r.mean_return),
        references,
        lqr_return: lti.and_then(|lti| crate::algo::lqr::lqr_return(lti, episodes, first)),
        masked_lqr_return: lti.zip(plan.local_mask).and_then(|(lti, mask)| crate::algo::lqr::masked_lqr_return(lti, mask, episodes, first)),
    })
}

/// Writes `summary` as pretty JSON to `run_dir/summary.json`, atomically:
/// a summary.json marks a finished run (`lcrl experiment` skips it), so it
/// must never be half a file.
pub fn write_summary(run_dir: &Path, summary: &RunSummary) -> Result<(), LearnerError> {
    let text = serde_json::to_string_pretty(summary).map_err(|e| LearnerError::Checkpoint(e.to_string()))?;
    write_atomically(&run_dir.join("summary.json"), (text + "\n").as_bytes())
}

/// Reads a run's summary.json, whichever loop wrote it.
pub fn read_summary(path: &Path) -> Result<RunSummary, LearnerError> {
    let text = std::fs::read_to_string(path).map_err(crate::io(path))?;
    serde_json::from_str(&text).map_err(|e| LearnerError::Checkpoint(format!("{}: {e}", path.display())))
}

fn is_zero(n: &u64) -> bool {
    *n == 0
}

#[cfg(test)]
mod tests {
    use super::*;

    fn summary(service: Option<ServiceFigures>) -> RunSummary {
        RunSummary {
            env: "lti-paper".into(),
            algo: Algo::Ddpg,
            connection: Connection::Local,
            seed: 3,
            episodes: 5,
            final_return: -2.5,
            evaluation: Evaluation {
                eval_return: -1.25,
                eval_episodes: Some(10),
                eval_seed: Some(1_000_000),
                eval_success_rate: None,
                eval_peak_force_n: None,
                eval_terms: lcrl_sim::ReturnColumns::default(),
                last_eval_return: Some(-1.5),
                zero_action_return: Some(-9.0),
                references: Vec::new(),
                lqr_return: Some(-1.0),
                masked_lqr_return: None,
            },
            selection: None,
            graph_seconds: 0.5,
            graph: Some(GraphRecord { file: "g.json".into(), origin: Some("draw 3, random rows".into()) }),
            optimization_seconds: 1.0,
            total_seconds: 2.0,
            env_steps: 250,
            updates: 200,
            critic_updates: 400,
            skipped_updates: 0,
            diverged_env: 0,
            samples_drawn: 51_200,
            actor_params: 40,
            critic_params: 90,
            service,
        }
    }

    /// Both loops' summaries round-trip through one type, flat, and the
    /// service's keys appear only where there is a service.
    #[test]
    fn summaries_of_every_loop_round_trip_flat() {
        let plain = summary(None);
        let text = serde_json::to_string(&plain).unwrap();
        let json: serde_json::Value = serde_json::from_str(&text).unwrap();
        assert_eq!(json["eval_return"], -1.25);
        assert!(json.get("replay_ratio").is_none() && json.get("evaluation").is_none(), "{json}");
        assert_eq!(serde_json::from_str::<RunSummary>(&text).unwrap(), plain);

        let service = ServiceFigures {
            sampled: 512,
            inserted: 256,
            replay_ratio: 2.0,
            replay_ratio_target: 2.0,
            policy_lag: PolicyLag { min: 0, mean: 1.5, max: 4 },
            actors_waited_s: 0.25,
            learner_waited_s: 0.75,
            policy_version: 12,
            served_version: 9,
            cuts: None,
            cuts_joined: None,
            discarded_stale: None,
            actors: Some(2),
            transport: Some("shm".into()),
            actor_restarts: None,
            ended_early: None,
        };
        let distributed = summary(Some(service));
        let text = serde_json::to_string(&distributed).unwrap();
        let json: serde_json::Value = serde_json::from_str(&text).unwrap();
        assert_eq!((json["replay_ratio"].as_f64(), json["served_version"].as_u64(), json["actors"].as_u64()), (Some(2.0), Some(9), Some(2)));
        assert_eq!(serde_json::from_str::<RunSummary>(&text).unwrap(), distributed);
    }
}
