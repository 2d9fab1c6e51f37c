//! Running whole episodes with a policy, recording traces, and summarizing
//! them: what `lcrl sim` reports, for any environment.

use std::time::Instant;

use serde::Serialize;

use crate::env::{Env, EnvError, EpisodeMetrics, ReturnColumns, ReturnTerms};

/// One control step of a recorded episode.
#[derive(Debug, Clone, PartialEq)]
pub struct TraceRow {
    pub step: usize,
    /// Time at the end of the step, seconds (step × control period).
    pub time_s: f64,
    /// State after the step.
    pub state: Vec<f64>,
    /// Action as given to the environment (before clipping).
    pub action: Vec<f64>,
    pub reward: f64,
}

/// One finished episode.
#[derive(Debug, Clone, PartialEq)]
pub struct EpisodeRecord {
    pub seed: u64,
    pub steps: usize,
    pub episode_return: f64,
    pub terminated: bool,
    pub metrics: EpisodeMetrics,
    /// The largest change of one applied action component between two
    /// consecutive control steps, as a share of that component's range
    /// (ub − lb): 1 is a switch from one edge of the box to the other.
    /// How bang-bang the policy acts
    /// (docs/research/2026-11-27-peg-rare-handover-failures.md); 0 for a
    /// one-step episode.
    pub max_action_jump: f64,
    /// Initial state and every step, when recording was asked for.
    pub initial_state: Vec<f64>,
    pub trace: Vec<TraceRow>,
    /// Why the episode ended early because the environment left its
    /// bounds (a non-finite or out-of-scale state or reward, crate::diverged):
    /// such a state is never handed to the policy.
    pub diverged: Option<String>,
}

/// Runs one episode from `reset(seed)` until it terminates or is truncated.
#[tracing::instrument(level = "debug", skip(env, policy))]
pub fn run_episode(
    env: &mut dyn Env,
    seed: u64,
    policy: &mut dyn FnMut(&[f64]) -> Vec<f64>,
    record: bool,
) -> Result<EpisodeRecord, EnvError> {
    let initial_state = env.reset(seed)?;
    let period = env.control_period_s();
    let mut state = initial_state.clone();
    let mut trace = Vec::new();
    let mut episode_return = 0.0;
    let mut steps = 0;
    // The action the environment applied last step (clipped to the box).
    let (mut previous, mut max_action_jump) = (Vec::new(), 0.0f64);
    let mut diverged = crate::state_out_of_bounds(env, &initial_state).map(|why| format!("its start: {why}"));
    loop {
        if let Some(why) = &diverged {
            // A served environment gone wrong ends this episode, not the run.
            tracing::warn!(seed, steps, "the environment left its bounds ({why}): the episode ends here, failed");
            return Ok(EpisodeRecord {
                seed,
                steps,
                episode_return,
                terminated: true,
                metrics: env.episode_metrics(),
                max_action_jump,
                initial_state: if record { initial_state } else { Vec::new() },
                trace,
                diverged,
            });
        }
        let action = policy(&state);
        let step = env.step(&action)?;
        diverged = crate::diverged(env, &step);
        if diverged.is_some() {
            continue;
        }
        let applied = env.spec().clip_action(&action);
        max_action_jump = max_action_jump.max(action_jump(env.spec(), &previous, &applied));
        previous = applied;
        steps += 1;
        episode_return += step.reward;
        if record {
            trace.push(TraceRow { step: steps, time_s: steps as f64 * period, state: step.state.clone(), action, reward: step.reward });
        }
        state = step.state;
        if step.terminated || step.truncated {
            return Ok(EpisodeRecord {
                seed,
                steps,
                episode_return,
                terminated: step.terminated,
                metrics: env.episode_metrics(),
                max_action_jump,
                initial_state: if record { initial_state } else { Vec::new() },
                trace,
                diverged: None,
            });
        }
    }
}

/// The largest |a_i − b_i| / (ub_i − lb_i) over the components of two
/// applied actions; 0 when `previous` is empty (the first step).
fn action_jump(spec: &crate::env::EnvSpec, previous: &[f64], applied: &[f64]) -> f64 {
    previous
        .iter()
        .zip(applied)
        .enumerate()
        .map(|(i, (&b, &a))| (a - b).abs() / (spec.action_high[i] - spec.action_low[i]))
        .fold(0.0, f64::max)
}

/// What `summary.json` holds. Task figures are null where the environment
/// has no such notion (linear systems have no forces).
#[derive(Debug, Clone, PartialEq, Serialize, serde::Deserialize)]
pub struct Summary {
    pub env: String,
    pub controller: String,
    pub episodes: usize,
    pub seed: u64,
    pub success_rate: Option<f64>,
    /// Mean episode length of the successful episodes.
    pub mean_steps_to_insert: Option<f64>,
    pub mean_steps: f64,
    pub mean_peak_force_n: Option<f64>,
    pub max_peak_force_n: Option<f64>,
    pub mean_peak_moment_nm: Option<f64>,
    pub max_penetration_mm: Option<f64>,
    pub mean_return: f64,
    pub min_return: f64,
    pub max_return: f64,
    /// The mean return split into its reward terms (peg tasks; docs/peg.md).
    #[serde(flatten)]
    pub terms: ReturnColumns,
    /// Control steps per second of wall time, one thread, all physics
    /// substeps included.
    pub control_steps_per_sec: f64,
    pub elapsed_s: f64,
    /// Episodes ended because the environment left its bounds (a served
    /// environment gone wrong): their returns count only the sound steps.
    #[serde(default, skip_serializing_if = "is_zero")]
    pub diverged_episodes: usize,
}

fn is_zero(n: &usize) -> bool {
    *n == 0
}

/// The one field of a summary that readers of other files need.
#[derive(Debug, Clone, PartialEq, serde::Deserialize)]
pub struct SummaryReturn {
    pub mean_return: f64,
}

/// Runs `episodes` episodes with seeds seed, seed+1, …; records the first.
pub fn evaluate(
    env: &mut dyn Env,
    controller: &str,
    episodes: usize,
    seed: u64,
    policy: &mut dyn FnMut(&[f64]) -> Vec<f64>,
    on_episode: &mut dyn FnMut(&EpisodeRecord),
) -> Result<(Summary, Vec<EpisodeRecord>), EnvError> {
    let started = Instant::now();
    let mut records = Vec::with_capacity(episodes);
    for k in 0..episodes {
        let record = run_episode(env, seed.wrapping_add(k as u64), policy, k == 0)?;
        on_episode(&record);
        records.push(record);
    }
    let elapsed = started.elapsed().as_secs_f64();
    Ok((summarize(env.spec().name.clone(), controller, seed, &records, elapsed), records))
}

/// [`evaluate`] with the episodes run in parallel on the current rayon
/// pool, each in a fresh copy of `env`; the records, and so the summary
/// (but for its timing), are those of [`evaluate`]: an episode depends only
/// on its seed and the policy, which here must be a plain function of the
/// state (`Fn + Sync`), not one that learns or keeps state between calls.
pub fn evaluate_parallel(
    env: &dyn Env,
    controller: &str,
    episodes: usize,
    seed: u64,
    policy: &(dyn Fn(&[f64]) -> Vec<f64> + Sync),
) -> Result<(Summary, Vec<EpisodeRecord>), EnvError> {
    evaluate_parallel_with(env, controller, episodes, seed, &|| Ok(|s: &[f64]| policy(s)), &|_| {})
}

/// [`evaluate_parallel`] for a policy that threads cannot share (a libtorch
/// network is `Send` but not `Sync`): every worker thread builds its own
/// copy with `make`, once per run of episodes rayon hands it. The copies
/// must act alike (the same weights), and then the records are those of
/// [`evaluate`] with one of them, whatever the number of threads.
/// `on_episode` sees each finished episode, in the order they finish.
pub fn evaluate_parallel_with<P: FnMut(&[f64]) -> Vec<f64>>(
    env: &dyn Env,
    controller: &str,
    episodes: usize,
    seed: u64,
    make: &(dyn Fn() -> Result<P, EnvError> + Sync),
    on_episode: &(dyn Fn(&EpisodeRecord) + Sync),
) -> Result<(Summary, Vec<EpisodeRecord>), EnvError> {
    use rayon::prelude::*;
    let started = Instant::now();
    let records = (0..episodes)
        .into_par_iter()
        .map_init(
            || make().map(|policy| (policy, env.fresh())),
            |copy, k| match copy {
                Ok((policy, own)) => run_episode(own.as_mut(), seed.wrapping_add(k as u64), policy, k == 0).inspect(on_episode),
                Err(e) => Err(EnvError::Invalid { field: "policy".into(), message: format!("cannot copy the policy onto an evaluation thread: {e}") }),
            },
        )
        .collect::<Result<Vec<_>, _>>()?;
    let elapsed = started.elapsed().as_secs_f64();
    Ok((summarize(env.spec().name.clone(), controller, seed, &records, elapsed), records))
}

/// The label of a = 0 among [`references`].
pub const ZERO_ACTION: &str = "a = 0";
/// The label of the recorded best constant among [`references`].
pub const BEST_CONSTANT: &str = "best constant";

/// The reference controllers of `env` on `episodes` starts from `first`,
/// the one evaluator of references of `lcrl train` and `lcrl run`: a = 0,
/// the recorded best constant (docs/peg.md, "The bar") where `env` has one,
/// and a headroom policy when one is given. Episodes run on every core.
pub fn references(env: &dyn Env, headroom: Option<&crate::tune::policy::StoredPolicy>, episodes: usize, first: u64) -> Result<Vec<Summary>, EnvError> {
    let n = env.spec().action_dim();
    let mut out = vec![evaluate_parallel(env, ZERO_ACTION, episodes, first, &|_| vec![0.0; n])?.0];
    if let Some(best) = crate::peg::measured_best_constant(&env.spec().name) {
        out.push(evaluate_parallel(env, BEST_CONSTANT, episodes, first, &|_| best.to_vec())?.0);
    }
    if let Some(stored) = headroom {
        let probe = env.fresh();
        let label = format!("headroom: {} feedback", stored.policy.family.name());
        out.push(evaluate_parallel(env, &label, episodes, first, &|s| stored.policy.act(probe.as_ref(), s))?.0);
    }
    Ok(out)
}

fn mean(values: impl Iterator<Item = f64>) -> Option<f64> {
    let (sum, count) = values.fold((0.0, 0usize), |(s, c), v| (s + v, c + 1));
    (count > 0).then(|| sum / count as f64)
}

/// Aggregates episode records.
pub fn summarize(env: String, controller: &str, seed: u64, records: &[EpisodeRecord], elapsed_s: f64) -> Summary {
    let n = records.len();
    let all = |f: fn(&EpisodeMetrics) -> Option<f64>| -> Option<Vec<f64>> { records.iter().map(|r| f(&r.metrics)).collect() };
    let successes: Option<Vec<bool>> = records.iter().map(|r| r.metrics.success).collect();
    let peaks = all(|m| m.peak_force_n);
    let total_steps: usize = records.iter().map(|r| r.steps).sum();
    let returns = records.iter().map(|r| r.episode_return);
    Summary {
        env,
        controller: controller.to_string(),
        episodes: n,
        seed,
        success_rate: successes.as_ref().and_then(|s| mean(s.iter().map(|&ok| f64::from(u8::from(ok))))),
        mean_steps_to_insert: successes
            .as_ref()
            .and_then(|s| mean(records.iter().zip(s).filter(|(_, &ok)| ok).map(|(r, _)| r.steps as f64))),
        mean_steps: mean(records.iter().map(|r| r.steps as f64)).unwrap_or(0.0),
        mean_peak_force_n: peaks.as_ref().and_then(|p| mean(p.iter().copied())),
        max_peak_force_n: peaks.as_ref().and_then(|p| p.iter().copied().reduce(f64::max)),
        mean_peak_moment_nm: all(|m| m.peak_moment_nm).and_then(|p| mean(p.into_iter())),
        max_penetration_mm: all(|m| m.max_penetration_mm).and_then(|p| p.into_iter().reduce(f64::max)),
        mean_return: mean(returns.clone()).unwrap_or(0.0),
        min_return: returns.clone().fold(f64::INFINITY, f64::min),
        max_return: returns.fold(f64::NEG_INFINITY, f64::max),
        terms: ReturnTerms::mean(records.iter().map(|r| r.metrics.return_terms.as_ref())).into(),
        control_steps_per_sec: if elapsed_s > 0.0 { total_steps as f64 / elapsed_s } else { 0.0 },
        elapsed_s,
        diverged_episodes: records.iter().filter(|r| r.diverged.is_some()).count(),
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::make_env;

    #[test]
    fn constant_controller_on_peg_group1_inserts_and_summary_adds_up() {
        let mut env = make_env("peg-group1").unwrap();
        let (summary, records) = evaluate(env.as_mut(), "constant", 3, 5, &mut |_| vec![0.0; 6], &mut |_| {}).unwrap();
        assert_eq!(summary.episodes, 3);
        assert_eq!(records[0].trace.len(), records[0].steps);
        assert!(records[1].trace.is_empty());
        let sum: f64 = records[0].trace.iter().map(|r| r.reward).sum();
        assert!((sum - records[0].episode_return).abs() < 1e-9);
        assert!(summary.success_rate.is_some() && summary.mean_peak_force_n.is_some());
        assert!((records[0].trace[0].time_s - 0.02).abs() < 1e-12);
    }

    /// Parallel evaluation gives the episodes of the sequential one, bit
    /// for bit, in order (peg-group1, a state feedback so that every
    /// episode differs).
    #[test]
    fn parallel_evaluation_equals_sequential() {
        let policy = |s: &[f64]| vec![0.5 * s[6].tanh(), -0.5 * s[7].tanh(), 0.1, 0.0, 0.0, 0.3];
        let mut env = make_env("peg-group1").unwrap();
        let (one, one_records) = evaluate(env.as_mut(), "feedback", 12, 40, &mut |s| policy(s), &mut |_| {}).unwrap();
        let pool = rayon::ThreadPoolBuilder::new().num_threads(3).build().unwrap();
        let (many, many_records) = pool.install(|| evaluate_parallel(env.as_ref(), "feedback", 12, 40, &policy)).unwrap();
        assert_eq!(one_records, many_records);
        let timeless = |s: Summary| Summary { control_steps_per_sec: 0.0, elapsed_s: 0.0, ..s };
        assert_eq!(timeless(one), timeless(many));
    }

    /// The action jump is measured on the applied (clipped) action, as a
    /// share of each component's range: a constant never jumps, a switch
    /// of dγ between its edges (−1 and 4) every step is 1, and a switch of
    /// dx between 0 and 5 (applied: 2, the edge; range 3) is 2/3.
    #[test]
    fn the_action_jump_is_the_largest_switch_of_the_applied_action() {
        let mut env = make_env("peg-group1").unwrap();
        let mut jump = |policy: &mut dyn FnMut(&[f64]) -> Vec<f64>| run_episode(env.as_mut(), 3, policy, false).unwrap().max_action_jump;
        assert_eq!(jump(&mut |_| vec![2.0, 2.0, 0.0, -0.5, 0.0, 1.0]), 0.0);
        let mut k = 0;
        let flip = |low: f64, high: f64, i: usize| {
            move |_: &[f64]| {
                k += 1;
                let mut a = vec![0.0; 6];
                a[i] = if k % 2 == 0 { low } else { high };
                a
            }
        };
        assert_eq!(jump(&mut flip(-1.0, 4.0, 5)), 1.0);
        assert!((jump(&mut flip(0.0, 5.0, 0)) - 2.0 / 3.0).abs() < 1e-12);
    }

    #[test]
    fn linear_systems_have_no_task_figures() {
        let mut env = make_env("lti-paper").unwrap();
        let (summary, _) = evaluate(env.as_mut(), "zero", 2, 0, &mut |_| vec![0.0; 3], &mut |_| {}).unwrap();
        assert_eq!((summary.success_rate, summary.mean_peak_force_n), (None, None));
        assert_eq!(summary.mean_steps, 50.0);
    }
}
