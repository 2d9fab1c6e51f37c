//! The best constant action: the bar any learned agent must clear.
//!
//! A constant action a is a controller of its own (on the peg tasks a = 0
//! is the constant compliance controller, docs/method.md §6). `tune`
//! searches the action box for the constant with the highest mean return
//! on a fixed set of episode starts, with CMA-ES (the `cmaes` crate), and
//! then evaluates the winner on a separate set of starts, the same ones
//! `lcrl sim --seed` uses, so its figures are comparable with any policy's.
//!
//! The search runs in u ∈ [−1, 1]ⁿ, the box mapped linearly onto
//! [lb, ub] (so every component has the same scale); CMA-ES samples outside
//! the box are clipped onto it. The start is a = 0, and a = 0 itself is
//! always a candidate, so the bar is never worse than the untrained
//! controller on the tuning starts.

pub mod feedback;
pub mod policy;

use std::time::Instant;

use cmaes::{CMAESOptions, DVector};
use serde::Serialize;

pub use crate::env::{action_of, u_of};
use crate::env::{Env, EnvError};
use crate::evaluate::{evaluate_parallel, run_episode, Summary};

/// How the search runs.
#[derive(Debug, Clone, PartialEq)]
pub struct TuneOptions {
    /// Episodes per candidate (the fixed tuning starts).
    pub episodes: usize,
    /// Seed of the first tuning start; starts are seed, seed+1, …
    pub seed: u64,
    /// Candidates CMA-ES may evaluate in total.
    pub evaluations: usize,
    /// Initial CMA-ES step size in u units (the box is 2 wide).
    pub sigma: f64,
    /// Episodes of the final evaluation of a = 0 and the winner.
    pub eval_episodes: usize,
    /// Seed of the first evaluation start (as `lcrl sim --seed`).
    pub eval_seed: u64,
}

impl Default for TuneOptions {
    fn default() -> Self {
        TuneOptions { episodes: 32, seed: crate::seeds::TUNING, evaluations: 300, sigma: 0.3, eval_episodes: 100, eval_seed: 0 }
    }
}

impl TuneOptions {
    fn check(&self) -> Result<(), TuneError> {
        if self.episodes == 0 || self.eval_episodes == 0 {
            return Err(TuneError::Options("episodes and eval episodes must be at least 1".into()));
        }
        if self.evaluations < 2 {
            return Err(TuneError::Options("--evaluations must be at least 2".into()));
        }
        if !(self.sigma.is_finite() && self.sigma > 0.0) {
            return Err(TuneError::Options(format!("sigma must be a finite number > 0, got {}", self.sigma)));
        }
        Ok(())
    }
}

/// A controller's figures on the evaluation starts, as best_constant.json
/// reports them.
#[derive(Debug, Clone, PartialEq, Serialize)]
pub struct ConstantResult {
    pub action: Vec<f64>,
    /// Mean return on the tuning starts.
    pub tuning_return: f64,
    /// Everything `lcrl sim` reports, on the evaluation starts.
    pub eval: Summary,
}

/// What `lcrl tune` writes (best_constant.json), and what its policy
/// search's file (best_policy.json, [`feedback::PolicyReport`]) holds
/// first: the action found, its figures on the evaluation starts, a = 0
/// beside it, and how the search ran.
#[derive(Debug, Clone, PartialEq, Serialize)]
pub struct TuneReport {
    pub env: String,
    pub action_names: Vec<String>,
    /// The best constant action found (a policy search: the policy's
    /// action at u₀, its constant part).
    pub action: Vec<f64>,
    /// Its figures on the evaluation starts (the bar).
    pub mean_return: f64,
    pub success_rate: Option<f64>,
    pub mean_peak_force_n: Option<f64>,
    #[serde(flatten)]
    pub terms: crate::env::ReturnColumns,
    pub best: ConstantResult,
    /// The constant compliance controller (a = 0) on the same starts.
    pub zero_action: ConstantResult,
    pub tuning_episodes: usize,
    pub tuning_seed: u64,
    pub eval_episodes: usize,
    pub eval_seed: u64,
    /// Candidates evaluated by CMA-ES.
    pub evaluations: usize,
    pub method: String,
    pub elapsed_s: f64,
}

impl TuneReport {
    /// The record of a search begun at `started` whose result is `best`:
    /// its figures are `best`'s on the evaluation starts.
    fn of(spec: &crate::env::EnvSpec, (best, zero_action): (ConstantResult, ConstantResult), opts: &TuneOptions, evaluations: usize, method: String, started: Instant) -> Self {
        TuneReport {
            env: spec.name.clone(),
            action_names: spec.action_names.clone(),
            action: best.action.clone(),
            mean_return: best.eval.mean_return,
            success_rate: best.eval.success_rate,
            mean_peak_force_n: best.eval.mean_peak_force_n,
            terms: best.eval.terms,
            best,
            zero_action,
            tuning_episodes: opts.episodes,
            tuning_seed: opts.seed,
            eval_episodes: opts.eval_episodes,
            eval_seed: opts.eval_seed,
            evaluations,
            method,
            elapsed_s: started.elapsed().as_secs_f64(),
        }
    }
}

/// Mean return of a constant action over `episodes` starts from `seed`,
/// the episodes on the current rayon pool (the sum is taken in episode
/// order, so the mean does not depend on the thread count).
pub fn constant_return(template: &dyn Env, action: &[f64], episodes: usize, seed: u64) -> Result<f64, EnvError> {
    use rayon::prelude::*;
    template.spec().check_action(action)?;
    let returns = (0..episodes)
        .into_par_iter()
        .map_init(|| template.fresh(), |env, k| run_episode(env.as_mut(), seed.wrapping_add(k as u64), &mut |_| action.to_vec(), false).map(|r| r.episode_return))
        .collect::<Result<Vec<f64>, EnvError>>()?;
    Ok(returns.iter().sum::<f64>() / episodes as f64)
}

fn evaluate_constant(template: &dyn Env, action: &[f64], tuning_return: f64, opts: &TuneOptions) -> Result<ConstantResult, EnvError> {
    let label = format!("constant {action:?}");
    let (eval, _) = evaluate_parallel(template, &label, opts.eval_episodes, opts.eval_seed, &|_| action.to_vec())?;
    Ok(ConstantResult { action: action.to_vec(), tuning_return, eval })
}

/// CMA-ES from `start` (whose mean return is `start_return`), maximizing
/// `mean_return` over up to `opts.evaluations` candidates in parallel on
/// the current rayon pool. Returns the best point and its return if it
/// beats the start, and the candidates evaluated; the first episode error
/// (which cannot cross the objective's signature) ends it as an error.
fn search(
    start: Vec<f64>,
    start_return: f64,
    opts: &TuneOptions,
    mean_return: &(dyn Fn(&[f64]) -> Result<f64, EnvError> + Sync),
    on_candidate: &(dyn Fn(f64) + Sync),
) -> Result<(Option<(Vec<f64>, f64)>, usize), TuneError> {
    let failure: std::sync::Mutex<Option<EnvError>> = std::sync::Mutex::new(None);
    let best_so_far = std::sync::Mutex::new(start_return);
    let objective = |point: &DVector<f64>| -> f64 {
        match mean_return(point.as_slice()) {
            Ok(r) => {
                let best = {
                    let mut best = best_so_far.lock().unwrap_or_else(|p| p.into_inner());
                    *best = best.max(r);
                    *best
                };
                on_candidate(best);
                -r
            }
            Err(e) => {
                failure.lock().unwrap_or_else(|p| p.into_inner()).get_or_insert(e);
                f64::INFINITY
            }
        }
    };
    let mut state = CMAESOptions::new(start, opts.sigma)
        .max_function_evals(opts.evaluations)
        .seed(opts.seed)
        .build(objective)
        .map_err(|e| TuneError::Options(format!("{e:?}")))?;
    let data = state.run_parallel();
    let evaluations = state.function_evals();
    drop(state);
    if let Some(e) = failure.into_inner().unwrap_or_else(|p| p.into_inner()) {
        return Err(TuneError::Env(e));
    }
    let found = data.overall_best.filter(|ind| -ind.value > start_return).map(|ind| (ind.point.as_slice().to_vec(), -ind.value));
    Ok((found, evaluations))
}

/// Runs the search (candidates in parallel on the current rayon pool);
/// `on_candidate` is called after every candidate with the best mean
/// return so far.
pub fn tune(template: &dyn Env, opts: &TuneOptions, on_candidate: &(dyn Fn(f64) + Sync)) -> Result<TuneReport, TuneError> {
    opts.check()?;
    let started = Instant::now();
    let spec = template.spec().clone();
    let n = spec.action_dim();
    let zero = vec![0.0; n];
    let zero_return = constant_return(template, &zero, opts.episodes, opts.seed)?;

    let (found, evaluations) = search(u_of(&spec, &zero), zero_return, opts, &|u| constant_return(template, &action_of(&spec, u), opts.episodes, opts.seed), on_candidate)?;
    let (best_action, best_return) = match found {
        Some((u, r)) => (action_of(&spec, &u), r),
        None => (zero.clone(), zero_return),
    };

    let best = evaluate_constant(template, &best_action, best_return, opts)?;
    let zero_action = evaluate_constant(template, &zero, zero_return, opts)?;
    let method = format!(
        "CMA-ES (cmaes crate) in the box mapped to [-1,1]^n, start a = 0, sigma {}, up to {} candidates of {} episodes each; a = 0 kept if nothing beats it",
        opts.sigma, opts.evaluations, opts.episodes
    );
    Ok(TuneReport::of(&spec, (best, zero_action), opts, evaluations, method, started))
}

#[derive(Debug, thiserror::Error)]
pub enum TuneError {
    #[error("tune: {0}")]
    Options(String),
    #[error(transparent)]
    Env(#[from] EnvError),
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::lti::{LtiConfig, LtiEnv};

    #[test]
    fn box_mapping_round_trips_and_clips() {
        let env = crate::make_env("peg-group1").unwrap();
        let spec = env.spec();
        let a = vec![0.0, 1.5, -1.0, 4.0, 0.25, -0.5];
        let back = action_of(spec, &u_of(spec, &a));
        assert!(a.iter().zip(&back).all(|(x, y)| (x - y).abs() < 1e-12), "{back:?}");
        assert_eq!(action_of(spec, &[9.0, -9.0, 0.0, 0.0, 0.0, 0.0])[..2], [2.0, -1.0]);
    }

    /// A system whose best constant is known: s' = s + a on one state from
    /// s_0 = 1, cost s_t² + 0.1 a² for t = 0, 1, 2. The return
    /// −[1 + (1+a)² + (1+2a)²] − 0.3 a² is a concave quadratic with its
    /// maximum at a = −6/10.6; the search must find it to 0.02.
    /// The search and its evaluations run on every core of the pool; the
    /// report (but for its timing) is that of one thread.
    #[test]
    fn tune_does_not_depend_on_thread_count() {
        // Starts in [0.5, 1.5]: a constant push towards 0 beats a = 0.
        let mut cfg = LtiConfig::from_matrices(vec![vec![1.0, 0.0], vec![0.0, 1.0]], vec![vec![1.0, 0.0], vec![0.0, 1.0]]);
        cfg.initial_state_low = Some(vec![0.5, 0.5]);
        cfg.initial_state_high = Some(vec![1.5, 1.5]);
        cfg.episode_steps = 3;
        let env = LtiEnv::new("two", &cfg).unwrap();
        let opts = TuneOptions { episodes: 6, evaluations: 40, eval_episodes: 10, ..TuneOptions::default() };
        let report = |threads: usize| {
            let pool = rayon::ThreadPoolBuilder::new().num_threads(threads).build().unwrap();
            let mut report = pool.install(|| tune(&env, &opts, &|_| {})).unwrap();
            report.elapsed_s = 0.0;
            for result in [&mut report.best, &mut report.zero_action] {
                result.eval.elapsed_s = 0.0;
                result.eval.control_steps_per_sec = 0.0;
            }
            (serde_json::to_string(&report).unwrap(), report.action)
        };
        let (one, action) = report(1);
        assert_eq!(one, report(3).0);
        assert_ne!(action, [0.0, 0.0], "the search found nothing: {one}");
    }

    #[test]
    fn finds_the_known_best_constant_of_a_linear_system() {
        let mut cfg = LtiConfig::from_matrices(vec![vec![1.0]], vec![vec![1.0]]);
        cfg.initial_state_low = Some(vec![1.0]);
        cfg.initial_state_high = Some(vec![1.0]);
        cfg.episode_steps = 3;
        let env = LtiEnv::new("one", &cfg).unwrap();
        let optimum = -6.0 / 10.6;
        let opts = TuneOptions { episodes: 1, evaluations: 200, eval_episodes: 1, ..TuneOptions::default() };
        let report = tune(&env, &opts, &|_| {}).unwrap();
        assert!((report.action[0] - optimum).abs() < 0.02, "{:?} vs {optimum}", report.action);
        assert!(report.mean_return > report.zero_action.eval.mean_return);
        assert_eq!(report.zero_action.action, vec![0.0]);
    }
}
