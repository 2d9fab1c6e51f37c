//! CS3, the continuous space serialized Shapley value (docs/method.md §2, eq. 5),
//! measured by Algorithm 1.
//!
//! For action i and sample k: draw s_0 and a random subspace L of the other
//! actions; run two branches from the same s_0 for m steps (m = state
//! dimension); at every step draw a fresh a1_t in L and a fresh a2_t in A_i;
//! the plain branch applies a1_t, the primed branch a1_t + a2_t; accumulate
//! |s'_{t+1,j} − s_{t+1,j}| for every state j. phi(i, j) is the mean over k.
//!
//! Every sample draws from its own RNG, seeded from (seed, i, k) alone, and
//! samples are reduced in a fixed order, so the result is bit-identical
//! whatever the number of threads.

use lcrl_sim::{Env, EnvError};
use rand::{Rng, SeedableRng};
use rand_chacha::ChaCha8Rng;
use rayon::prelude::*;

/// Where the paired branches of a CS3 sample start (docs/method.md §2).
#[derive(Debug, Clone, Copy, PartialEq, Eq, serde::Serialize, serde::Deserialize, clap::ValueEnum)]
#[serde(rename_all = "kebab-case")]
pub enum Start {
    /// s_0 is an episode start: `reset(seed)`.
    Reset,
    /// s_0 is the state of an episode of the neutral controller (a = 0) at
    /// a step drawn uniformly from the episode, so on contact tasks it is
    /// often in contact and mid-insertion (eq. 5 draws s_0 from the whole
    /// state space, not only from episode starts).
    Trajectory,
}

impl Start {
    /// The start an environment gets when none is asked for.
    pub fn default_for(env: &dyn Env) -> Start {
        if env.prefers_trajectory_starts() { Start::Trajectory } else { Start::Reset }
    }

    pub fn name(&self) -> &'static str {
        match self {
            Start::Reset => "reset",
            Start::Trajectory => "trajectory",
        }
    }
}

/// How CS3 samples.
#[derive(Debug, Clone, PartialEq)]
pub struct Cs3Config {
    /// ST: samples per action component.
    pub samples: usize,
    /// Seed of all CS3 randomness.
    pub seed: u64,
    /// Worker threads for the rollouts; 0 means one per core.
    pub threads: usize,
    /// Where s_0 comes from; None: the environment's default
    /// ([`Start::default_for`]).
    pub start: Option<Start>,
}

impl Default for Cs3Config {
    fn default() -> Self {
        Cs3Config { samples: 256, seed: 0, threads: 0, start: None }
    }
}

/// The per-sample CS3 sums: for action i, sample k and state j,
/// sum_{t=0}^{m−1} |s'_{t+1,j} − s_{t+1,j}| (the bracket of eq. 5).
#[derive(Debug, Clone, PartialEq)]
pub struct Cs3Samples {
    pub actions: usize,
    pub states: usize,
    pub samples: usize,
    /// Flattened [i][k][j].
    values: Vec<f64>,
}

impl Cs3Samples {
    /// The sum of sample k of action i, one value per state j.
    pub fn sample(&self, i: usize, k: usize) -> &[f64] {
        let start = (i * self.samples + k) * self.states;
        &self.values[start..start + self.states]
    }

    /// phi (n × m): the mean over all samples (eq. 5).
    pub fn phi(&self) -> Vec<Vec<f64>> {
        let all: Vec<usize> = (0..self.samples).collect();
        self.phi_of(|_| &all)
    }

    /// The standard error of each phi(i, j): the sample standard deviation
    /// of the ST per-sample sums over √ST.
    pub fn phi_stderr(&self) -> Vec<Vec<f64>> {
        let phi = self.phi();
        let st = self.samples as f64;
        (0..self.actions)
            .map(|i| {
                (0..self.states)
                    .map(|j| {
                        if self.samples < 2 {
                            return 0.0;
                        }
                        let ss: f64 = (0..self.samples).map(|k| (self.sample(i, k)[j] - phi[i][j]).powi(2)).sum();
                        (ss / (st - 1.0)).sqrt() / st.sqrt()
                    })
                    .collect()
            })
            .collect()
    }

    /// phi from a chosen multiset of sample indices per action (bootstrap).
    pub fn phi_of<'a>(&self, picks: impl Fn(usize) -> &'a [usize]) -> Vec<Vec<f64>> {
        (0..self.actions)
            .map(|i| {
                let chosen = picks(i);
                let mut row = vec![0.0; self.states];
                for &k in chosen {
                    for (acc, v) in row.iter_mut().zip(self.sample(i, k)) {
                        *acc += v;
                    }
                }
                row.iter_mut().for_each(|v| *v /= chosen.len() as f64);
                row
            })
            .collect()
    }
}

/// Runs Algorithm 1's rollouts on snapshots of `env` (its own state is not
/// touched), on the current rayon pool (see [`thread_pool`]). `on_sample` is
/// called once per finished sample (progress).
pub fn measure(env: &dyn Env, cfg: &Cs3Config, on_sample: &(dyn Fn() + Sync)) -> Result<Cs3Samples, Cs3Error> {
    if cfg.samples == 0 {
        return Err(Cs3Error::NoSamples);
    }
    // Paired branches need exact copies: refuse at once, with the reason.
    env.check_snapshot()?;
    let n = env.spec().action_dim();
    let m = env.spec().state_dim();
    let start = cfg.start.unwrap_or_else(|| Start::default_for(env));
    let per_sample: Vec<Result<Vec<f64>, EnvError>> = (0..n * cfg.samples)
        .into_par_iter()
        .map(|index| {
            let (i, k) = (index / cfg.samples, index % cfg.samples);
            let result = paired_rollout(env, start, i, sample_seed(cfg.seed, i, k));
            on_sample();
            result
        })
        .collect();
    let mut values = Vec::with_capacity(n * cfg.samples * m);
    for sums in per_sample {
        values.extend(sums?);
    }
    Ok(Cs3Samples { actions: n, states: m, samples: cfg.samples, values })
}

/// One sample of eq. 5 for action i: two branches from one s_0, m steps.
fn paired_rollout(template: &dyn Env, start: Start, i: usize, seed: u64) -> Result<Vec<f64>, EnvError> {
    let trace = paired_trace(template, start, i, seed)?;
    let mut sums = vec![0.0; template.spec().state_dim()];
    for step in &trace.effects {
        for (acc, d) in sums.iter_mut().zip(step) {
            *acc += d;
        }
    }
    Ok(sums)
}

/// One CS3 sample step by step: its start state s_0 and, for every step t
/// it ran, |s'_{t+1,j} − s_{t+1,j}| for every state j (eq. 5's bracket
/// before the sum). `lcrl graph --explain` reads these.
#[derive(Debug, Clone, PartialEq)]
pub struct PairedTrace {
    pub start_state: Vec<f64>,
    pub effects: Vec<Vec<f64>>,
}

/// Sample `seed` of action i as Algorithm 1 draws it (the same draws as
/// [`measure`]'s sample with that seed), step by step.
pub fn paired_trace(template: &dyn Env, start: Start, i: usize, seed: u64) -> Result<PairedTrace, EnvError> {
    let mut rng = ChaCha8Rng::seed_from_u64(seed);
    let spec = template.spec();
    let (n, m) = (spec.action_dim(), spec.state_dim());

    // s_0 ~ S, and s'_0 = s_0: the primed branch is an exact snapshot.
    let mut plain = draw_start(template, start, &mut rng)?;
    let start_state = plain.state().to_vec();
    let mut primed = plain.snapshot()?;
    if plain.is_stochastic() {
        // Process noise is part of the system, not of the action: the two
        // branches draw it independently, as two real runs would.
        plain.reseed_noise(rng.random());
        primed.reseed_noise(rng.random());
    }

    // L ⊆ A \ A_i: each other action component is in L with probability ½.
    let in_subspace: Vec<bool> = (0..n).map(|k| k != i && rng.random_bool(0.5)).collect();
    let draw = |rng: &mut ChaCha8Rng, k: usize| rng.random_range(spec.action_low[k]..=spec.action_high[k]);

    let mut effects = Vec::with_capacity(m);
    let mut a1 = vec![0.0; n];
    for _t in 0..m {
        // a1_t ∈ L (components outside L stay at the neutral 0); a2_t ∈ A_i.
        for k in 0..n {
            a1[k] = if in_subspace[k] { draw(&mut rng, k) } else { 0.0 };
        }
        let mut a1_plus_a2 = a1.clone();
        a1_plus_a2[i] = draw(&mut rng, i);
        let s = plain.step(&a1)?;
        let s_primed = primed.step(&a1_plus_a2)?;
        effects.push(s_primed.state.iter().zip(&s.state).map(|(sp, sj)| (sp - sj).abs()).collect());
        // After an episode ends its state means nothing more; stop the pair.
        if s.terminated || s.truncated || s_primed.terminated || s_primed.truncated {
            break;
        }
    }
    Ok(PairedTrace { start_state, effects })
}

/// A copy of `template` in a start state s_0 drawn as `start` says.
///
/// Trajectory starts run one episode of the neutral controller (a = 0) and
/// keep the state at a step drawn uniformly from it by reservoir sampling
/// (state t replaces the kept one with probability 1/(t+1)), so one pass
/// and a few snapshots suffice. The final, ended state is never kept: an
/// ended episode cannot be stepped. The copy is an exact snapshot, so both
/// branches continue from it bit-identically.
pub fn draw_start(template: &dyn Env, start: Start, rng: &mut ChaCha8Rng) -> Result<Box<dyn Env>, EnvError> {
    let mut env = template.fresh();
    env.reset(rng.random())?;
    if start == Start::Reset {
        return Ok(env);
    }
    let neutral = vec![0.0; env.spec().action_dim()];
    let mut kept = env.snapshot()?;
    for t in 1usize.. {
        let step = env.step(&neutral)?;
        if step.terminated || step.truncated {
            break;
        }
        if rng.random_range(0..=t) == 0 {
            kept = env.snapshot()?;
        }
    }
    Ok(kept)
}

/// The pool the rollouts run on: `threads` workers, or one per core for 0.
pub fn thread_pool(threads: usize) -> Result<rayon::ThreadPool, Cs3Error> {
    rayon::ThreadPoolBuilder::new()
        .num_threads(threads)
        .build()
        .map_err(|e| Cs3Error::ThreadPool(e.to_string()))
}

/// A well-mixed seed for sample k of action i (SplitMix64 finalizer), so
/// neighbouring samples get unrelated streams.
pub fn sample_seed(seed: u64, i: usize, k: usize) -> u64 {
    let mut z = seed
        .wrapping_add((i as u64).wrapping_mul(0x9E37_79B9_7F4A_7C15))
        .wrapping_add((k as u64).wrapping_mul(0xD1B5_4A32_D192_ED03));
    z = (z ^ (z >> 30)).wrapping_mul(0xBF58_476D_1CE4_E5B9);
    z = (z ^ (z >> 27)).wrapping_mul(0x94D0_49BB_1331_11EB);
    z ^ (z >> 31)
}

#[derive(Debug, thiserror::Error)]
pub enum Cs3Error {
    #[error("the number of CS3 samples (ST) must be at least 1")]
    NoSamples,
    #[error("cannot start the rollout threads: {0}")]
    ThreadPool(String),
    #[error("a CS3 rollout failed: {0}")]
    Env(#[from] EnvError),
}
