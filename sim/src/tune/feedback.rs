//! The headroom reference: the best state-feedback controller of a simple
//! family, found by direct search, as the best constant is (docs/peg.md,
//! "Headroom"). It is the peg task's counterpart of LQR on the linear
//! example: how much a controller that looks at the state can gain over
//! the best fixed one.
//!
//! Families, in u ∈ [−1, 1]ⁿ (the action box mapped linearly, as the
//! constant search) and the normalized state ŝ (`Env::normalize_state`):
//! - affine:          u = clip(u₀ + K ŝ)
//! - depth-switched:  u = clip(u₀ + K₁ ŝ) while the remaining depth is
//!   above L − `ENTRY_MM` (the chamfer and the first millimetres, where
//!   the force is made), clip(u₀ + K₂ ŝ) deeper in the hole.
//!
//! The search starts at the best constant (K = 0), so a constant is always
//! a candidate and the result is never worse than it on the tuning starts.

use std::time::Instant;

use serde::Serialize;

use super::{action_of, constant_return, u_of, ConstantResult, TuneError, TuneOptions};
use crate::env::{Env, EnvError, ReturnColumns};
use crate::evaluate::{evaluate, run_episode};

/// Millimetres below the hole entrance where the depth-switched family
/// changes gains: the peg's chamfer and its first millimetres in the hole.
pub const ENTRY_MM: f64 = 2.0;

/// The policy families `lcrl tune --policy` searches.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize)]
#[serde(rename_all = "kebab-case")]
pub enum Family {
    /// u = clip(u₀ + K ŝ).
    Affine,
    /// Two gain matrices, switched on insertion depth.
    DepthSwitched,
}

/// A state-feedback policy of one family.
#[derive(Debug, Clone, PartialEq, Serialize)]
pub struct FeedbackPolicy {
    pub family: Family,
    /// u₀, in the box mapped to [−1, 1].
    pub u0: Vec<f64>,
    /// K per phase (one for affine; entry, then deep for depth-switched),
    /// each n × m, on the normalized state.
    pub gains: Vec<Vec<Vec<f64>>>,
    /// Remaining depth (mm) below which the second gains apply
    /// (depth-switched only), and the state index of the depth.
    pub switch_depth_mm: Option<f64>,
}

/// Each gain parameter is scaled by this over √m: unit steps of CMA-ES
/// move u by about this much when every ŝ is about 1.
const GAIN_SCALE: f64 = 0.5;

impl FeedbackPolicy {
    fn phases(family: Family) -> usize {
        match family {
            Family::Affine => 1,
            Family::DepthSwitched => 2,
        }
    }

    /// Parameters: u₀ (n), then each phase's K row by row (n·m).
    fn from_params(family: Family, theta: &[f64], n: usize, m: usize, switch_depth_mm: Option<f64>) -> Self {
        let scale = GAIN_SCALE / (m as f64).sqrt();
        let gains = (0..Self::phases(family))
            .map(|p| (0..n).map(|i| (0..m).map(|j| scale * theta[n + p * n * m + i * m + j]).collect()).collect())
            .collect();
        FeedbackPolicy { family, u0: theta[..n].to_vec(), gains, switch_depth_mm }
    }

    /// The action for a raw state.
    pub fn act(&self, env: &dyn Env, state: &[f64]) -> Vec<f64> {
        let s = env.normalize_state(state);
        let phase = match self.switch_depth_mm {
            // State index 2 is the remaining depth on peg tasks.
            Some(depth) if state.get(2).is_some_and(|&z| z < depth) => 1,
            _ => 0,
        };
        let k = &self.gains[phase.min(self.gains.len() - 1)];
        let u: Vec<f64> = self.u0.iter().zip(k).map(|(u0, row)| u0 + row.iter().zip(&s).map(|(g, x)| g * x).sum::<f64>()).collect();
        action_of(env.spec(), &u)
    }
}

/// Mean return of a policy over `episodes` starts from `seed`.
fn policy_return(template: &dyn Env, policy: &FeedbackPolicy, episodes: usize, seed: u64) -> Result<f64, EnvError> {
    let mut env = template.fresh();
    let probe = template.fresh();
    let mut total = 0.0;
    for k in 0..episodes {
        let record = run_episode(env.as_mut(), seed.wrapping_add(k as u64), &mut |s| policy.act(probe.as_ref(), s), false)?;
        total += record.episode_return;
    }
    Ok(total / episodes as f64)
}

/// What `lcrl tune --policy` writes (best_policy.json): the fields of
/// best_constant.json, with the policy and the constant it started from.
#[derive(Debug, Clone, PartialEq, Serialize)]
pub struct PolicyReport {
    pub env: String,
    pub action_names: Vec<String>,
    pub state_names: Vec<String>,
    /// The policy's action at u₀ (its constant part).
    pub action: Vec<f64>,
    /// Its figures on the evaluation starts.
    pub mean_return: f64,
    pub success_rate: Option<f64>,
    pub mean_peak_force_n: Option<f64>,
    #[serde(flatten)]
    pub terms: ReturnColumns,
    pub policy: FeedbackPolicy,
    pub best: ConstantResult,
    /// The constant the search started from, on the same starts.
    pub start_constant: ConstantResult,
    /// The constant compliance controller (a = 0) on the same starts.
    pub zero_action: ConstantResult,
    pub tuning_episodes: usize,
    pub tuning_seed: u64,
    pub eval_episodes: usize,
    pub eval_seed: u64,
    pub evaluations: usize,
    pub method: String,
    pub elapsed_s: f64,
}

/// Searches `family` from the constant `start` (an action in the box).
pub fn tune_policy(template: &dyn Env, family: Family, start: &[f64], opts: &TuneOptions, on_candidate: &(dyn Fn(f64) + Sync)) -> Result<PolicyReport, TuneError> {
    opts.check()?;
    let started = Instant::now();
    let spec = template.spec().clone();
    let (n, m) = (spec.action_dim(), spec.state_dim());
    template.spec().check_action(start)?;
    let switch = match family {
        Family::Affine => None,
        Family::DepthSwitched => {
            let depth = template.depth_reference_mm().ok_or_else(|| {
                TuneError::Options(format!("--policy depth-switched needs an insertion depth; {} has none (use affine)", spec.name))
            })?;
            Some(depth - ENTRY_MM)
        }
    };
    let dim = n + FeedbackPolicy::phases(family) * n * m;
    let mut theta0 = vec![0.0; dim];
    theta0[..n].copy_from_slice(&u_of(&spec, start));
    let start_policy = FeedbackPolicy::from_params(family, &theta0, n, m, switch);
    let start_return = policy_return(template, &start_policy, opts.episodes, opts.seed)?;

    let objective = |theta: &[f64]| policy_return(template, &FeedbackPolicy::from_params(family, theta, n, m, switch), opts.episodes, opts.seed);
    let (found, evaluations) = super::search(theta0, start_return, opts, &objective, on_candidate)?;
    let (policy, best_return) = match found {
        Some((theta, r)) => (FeedbackPolicy::from_params(family, &theta, n, m, switch), r),
        None => (start_policy, start_return),
    };

    let mut env = template.fresh();
    let probe = template.fresh();
    let label = format!("{family:?} policy");
    let (eval, _) = evaluate(env.as_mut(), &label, opts.eval_episodes, opts.eval_seed, &mut |s| policy.act(probe.as_ref(), s), &mut |_| {})?;
    let action = action_of(&spec, &policy.u0);
    let best = ConstantResult { action: action.clone(), tuning_return: best_return, eval };
    let start_constant = super::evaluate_constant(template, start, constant_return(template, start, opts.episodes, opts.seed)?, opts)?;
    let zero = vec![0.0; n];
    let zero_action = super::evaluate_constant(template, &zero, constant_return(template, &zero, opts.episodes, opts.seed)?, opts)?;
    Ok(PolicyReport {
        env: spec.name.clone(),
        action_names: spec.action_names.clone(),
        state_names: spec.state_names.clone(),
        action,
        mean_return: best.eval.mean_return,
        success_rate: best.eval.success_rate,
        mean_peak_force_n: best.eval.mean_peak_force_n,
        terms: best.eval.terms,
        policy,
        best,
        start_constant,
        zero_action,
        tuning_episodes: opts.episodes,
        tuning_seed: opts.seed,
        eval_episodes: opts.eval_episodes,
        eval_seed: opts.eval_seed,
        evaluations,
        method: format!(
            "CMA-ES (cmaes crate) over u0 and the gains of the {family:?} family on the normalized state, start at the given constant with K = 0, \
             sigma {}, up to {} candidates of {} episodes each; the start kept if nothing beats it",
            opts.sigma, opts.evaluations, opts.episodes
        ),
        elapsed_s: started.elapsed().as_secs_f64(),
    })
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::lti::{LtiConfig, LtiEnv};

    /// A system where feedback matters and the best gain is known:
    /// s' = s + a on one state from s₀ ∈ [−1, 1], cost s² + 0.1a² per
    /// step over 3 steps. No constant can help both signs of s₀; the
    /// affine search must find a negative gain and beat the best constant.
    #[test]
    fn affine_search_finds_feedback_where_no_constant_helps() {
        let mut cfg = LtiConfig::from_matrices(vec![vec![1.0]], vec![vec![1.0]]);
        cfg.initial_state_low = Some(vec![-1.0]);
        cfg.initial_state_high = Some(vec![1.0]);
        cfg.episode_steps = 3;
        let env = LtiEnv::new("one", &cfg).unwrap();
        let opts = TuneOptions { episodes: 16, evaluations: 300, eval_episodes: 32, ..TuneOptions::default() };
        let report = tune_policy(&env, Family::Affine, &[0.0], &opts, &|_| {}).unwrap();
        let gain = report.policy.gains[0][0][0];
        assert!(gain < -0.1, "the gain on s must be negative, got {gain}");
        assert!(report.mean_return > report.start_constant.eval.mean_return + 0.1, "{} vs {}", report.mean_return, report.start_constant.eval.mean_return);
        // An environment without a depth has no depth-switched family.
        assert!(tune_policy(&env, Family::DepthSwitched, &[0.0], &opts, &|_| {}).is_err());
    }
}
