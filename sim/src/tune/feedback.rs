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

pub use super::policy::{Family, FeedbackPolicy, StoredPolicy};
use super::{action_of, constant_return, u_of, ConstantResult, TuneError, TuneOptions};
use crate::env::{Env, EnvError};
use crate::evaluate::{evaluate, run_episode};

/// Millimetres below the hole entrance where the depth-switched family
/// changes gains: the peg's chamfer and its first millimetres in the hole.
pub const ENTRY_MM: f64 = 2.0;

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

/// What `lcrl tune --policy` writes (best_policy.json): best_constant.json's
/// record of the search ([`super::TuneReport`], its `action` the policy's
/// at u₀ and its figures the policy's), with the state names, the policy
/// and the constant it started from.
#[derive(Debug, Clone, PartialEq, Serialize)]
pub struct PolicyReport {
    #[serde(flatten)]
    pub record: super::TuneReport,
    pub state_names: Vec<String>,
    pub policy: FeedbackPolicy,
    /// The constant the search started from, on the same starts.
    pub start_constant: ConstantResult,
    /// On linear systems, LQR's mean return on the same evaluation starts
    /// (the known optimum the search is measured against); filled by the
    /// caller, which has the Riccati solver.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub lqr_return: Option<f64>,
}

impl StoredPolicy {
    /// Reads a best_policy.json of `lcrl tune --policy`, checking the
    /// policy's shape against the file's own claims.
    pub fn read(path: &std::path::Path) -> Result<StoredPolicy, TuneError> {
        let bad = |why: String| TuneError::Options(format!("{}: not a best_policy.json of `lcrl tune --policy`: {why}", path.display()));
        let text = std::fs::read_to_string(path).map_err(|e| bad(e.to_string()))?;
        let stored: StoredPolicy = serde_json::from_str(&text).map_err(|e| bad(e.to_string()))?;
        let p = &stored.policy;
        let n = p.u0.len();
        let phases = FeedbackPolicy::phases(p.family);
        let m = p.gains.first().and_then(|k| k.first()).map_or(0, Vec::len);
        if p.gains.len() != phases || p.gains.iter().any(|k| k.len() != n || k.iter().any(|row| row.len() != m)) || m == 0 {
            return Err(bad(format!("{:?} needs {phases} gain matrices of {n} rows of equal, non-zero length", p.family)));
        }
        if (p.family == Family::DepthSwitched) != p.switch_depth_mm.is_some() {
            return Err(bad("switch_depth_mm is set exactly for the depth-switched family".into()));
        }
        Ok(stored)
    }

    /// Checks the policy fits `env` (state and action sizes).
    pub fn check_env(&self, env: &dyn Env) -> Result<(), TuneError> {
        let spec = env.spec();
        let m = self.policy.gains[0][0].len();
        if self.policy.u0.len() != spec.action_dim() || m != spec.state_dim() {
            return Err(TuneError::Options(format!(
                "the stored policy of {} has {} actions and {m} states; {} has {} and {}",
                self.env,
                self.policy.u0.len(),
                spec.name,
                spec.action_dim(),
                spec.state_dim()
            )));
        }
        Ok(())
    }
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
    let method = format!(
        "CMA-ES (cmaes crate) over u0 and the gains of the {family:?} family on the normalized state, start at the given constant with K = 0, \
         sigma {}, up to {} candidates of {} episodes each; the start kept if nothing beats it",
        opts.sigma, opts.evaluations, opts.episodes
    );
    let record = super::TuneReport::of(&spec, (best, zero_action), opts, evaluations, method, started);
    Ok(PolicyReport { record, state_names: spec.state_names.clone(), policy, start_constant, lqr_return: None })
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
        assert!(report.record.mean_return > report.start_constant.eval.mean_return + 0.1, "{} vs {}", report.record.mean_return, report.start_constant.eval.mean_return);
        // An environment without a depth has no depth-switched family.
        assert!(tune_policy(&env, Family::DepthSwitched, &[0.0], &opts, &|_| {}).is_err());
    }

    /// The headroom references shipped in references/ (what `lcrl run`
    /// prints beside a trained policy) are recomputed here: the stored
    /// policy, a = 0 and the constant it started from, on the file's own
    /// evaluation starts, give the file's figures (the simulator is
    /// deterministic), and that constant is the bar the code records.
    #[test]
    fn shipped_headroom_references_recompute() {
        let dir = std::path::Path::new(env!("CARGO_MANIFEST_DIR")).join("../references");
        let mut checked = 0;
        for entry in std::fs::read_dir(&dir).unwrap() {
            let path = entry.unwrap().path().join("best_policy.json");
            // references/ holds other files too (the publication's graph).
            if !path.is_file() {
                continue;
            }
            let stored = StoredPolicy::read(&path).unwrap();
            let raw: serde_json::Value = serde_json::from_str(&std::fs::read_to_string(&path).unwrap()).unwrap();
            let template = crate::make_env(&stored.env).unwrap();
            stored.check_env(template.as_ref()).unwrap();
            let n = template.spec().action_dim();
            let close = |a: f64, b: f64| (a - b).abs() <= 1e-9 * b.abs().max(1.0);
            let policy_return = super::policy_return(template.as_ref(), &stored.policy, stored.eval_episodes, stored.eval_seed).unwrap();
            assert!(close(policy_return, stored.mean_return), "{}: {policy_return} vs stored {}", path.display(), stored.mean_return);
            let start: Vec<f64> = serde_json::from_value(raw["start_constant"]["action"].clone()).unwrap();
            let bar = crate::peg::measured_best_constant(&stored.env).unwrap();
            assert_eq!(start, bar.to_vec(), "{}: the search did not start from the recorded best constant", path.display());
            for (key, action) in [("start_constant", start), ("zero_action", vec![0.0; n])] {
                let recorded = raw[key]["eval"]["mean_return"].as_f64().unwrap();
                let got = constant_return(template.as_ref(), &action, stored.eval_episodes, stored.eval_seed).unwrap();
                assert!(close(got, recorded), "{}: {key} {got} vs stored {recorded}", path.display());
            }
            checked += 1;
        }
        assert!(checked > 0, "no references in {}", dir.display());
    }
}
