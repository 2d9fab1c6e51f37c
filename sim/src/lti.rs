//! Linear time-invariant systems: s_{t+1} = E s_t + F a_t + w_t.
//!
//! These have a closed-form connection graph (docs/method.md §4, Lemma 1), which
//! makes them the ground truth for CS3. The reward is a quadratic cost,
//! r_t = −(s_tᵀ Q s_t + a_tᵀ R a_t), so the optimal (LQR) controller is
//! known too. w_t is optional Gaussian process noise, i.i.d. per component.

use nalgebra::{DMatrix, DVector};
use rand::{Rng, SeedableRng};
use rand_chacha::ChaCha8Rng;
use rand_distr::{Distribution, Normal};
use serde::Deserialize;

use crate::env::{Env, EnvError, EnvSpec, Step};

/// A linear system as written in its TOML file (`kind = "lti"`).
///
/// Matrices are lists of rows. Only `e` and `f` are required.
#[derive(Debug, Clone, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct LtiConfig {
    /// Always "lti" in a file; lets the registry tell file kinds apart.
    #[serde(default)]
    pub kind: Option<String>,
    /// State transition E (m × m).
    pub e: Vec<Vec<f64>>,
    /// Input matrix F (m × n).
    pub f: Vec<Vec<f64>>,
    /// Lower action bounds (length n); default −1 each.
    #[serde(default)]
    pub action_low: Option<Vec<f64>>,
    /// Upper action bounds (length n); default +1 each.
    #[serde(default)]
    pub action_high: Option<Vec<f64>>,
    /// Initial state drawn uniformly from [low, high] per component; default −1.
    #[serde(default)]
    pub initial_state_low: Option<Vec<f64>>,
    /// Default +1.
    #[serde(default)]
    pub initial_state_high: Option<Vec<f64>>,
    /// Standard deviation of the Gaussian process noise w_t; default 0.
    #[serde(default)]
    pub noise_std: f64,
    /// State cost Q (m × m); default identity.
    #[serde(default)]
    pub q: Option<Vec<Vec<f64>>>,
    /// Action cost R (n × n); default 0.1 · identity.
    #[serde(default)]
    pub r: Option<Vec<Vec<f64>>>,
    /// Episode length (truncation); default 50.
    #[serde(default = "default_episode_steps")]
    pub episode_steps: usize,
    /// Optional component names; default s1..sm and a1..an.
    #[serde(default)]
    pub state_names: Option<Vec<String>>,
    #[serde(default)]
    pub action_names: Option<Vec<String>>,
}

fn default_episode_steps() -> usize {
    50
}

impl LtiConfig {
    /// The example of docs/method.md eq. 10: E = [[−1,1,0],[0,1,0],[0,0,1]], F = I.
    pub fn paper_example() -> Self {
        LtiConfig {
            kind: Some("lti".into()),
            e: vec![vec![-1.0, 1.0, 0.0], vec![0.0, 1.0, 0.0], vec![0.0, 0.0, 1.0]],
            f: vec![vec![1.0, 0.0, 0.0], vec![0.0, 1.0, 0.0], vec![0.0, 0.0, 1.0]],
            action_low: None,
            action_high: None,
            initial_state_low: None,
            initial_state_high: None,
            noise_std: 0.0,
            q: None,
            r: None,
            episode_steps: default_episode_steps(),
            state_names: None,
            action_names: None,
        }
    }

    /// A system from matrices, with every other setting at its default.
    pub fn from_matrices(e: Vec<Vec<f64>>, f: Vec<Vec<f64>>) -> Self {
        LtiConfig { e, f, ..Self::paper_example() }
    }

    /// `lti-blocks-N` (docs/lcrl-value.md): N actions and 2N states, each
    /// action driving its own two-state block, blocks weakly coupled in
    /// pairs (k and k XOR 1). Block k holds x_k (state 2k) and y_k (2k+1):
    ///
    ///   y_k' = 0.9 y_k + 0.5 a_k
    ///   x_k' = 0.9 x_k + 0.2 y_k + 0.1 x_{k XOR 1}
    ///
    /// so a_k moves y_k at once, x_k a step later and its partner's x one
    /// step after that, and nothing else: Lemma 1's G has exactly 3 edges
    /// per action (3N of 2N²), the rest of the state is irrelevant to it.
    /// Stable (eigenvalues 0.9 and 0.9 ± 0.1), so no controller diverges.
    /// N must be even, at least 2 and at most [`LtiConfig::MAX_BLOCKS`].
    pub fn blocks(n: usize) -> Option<Self> {
        if !(2..=Self::MAX_BLOCKS).contains(&n) || n % 2 == 1 {
            return None;
        }
        let m = 2 * n;
        let mut e = vec![vec![0.0; m]; m];
        let mut f = vec![vec![0.0; n]; m];
        for k in 0..n {
            let (x, y, partner_x) = (2 * k, 2 * k + 1, 2 * (k ^ 1));
            e[y][y] = 0.9;
            f[y][k] = 0.5;
            e[x][x] = 0.9;
            e[x][y] = 0.2;
            e[x][partner_x] = 0.1;
        }
        let state_names = Some((1..=n).flat_map(|k| [format!("x{k}"), format!("y{k}")]).collect());
        let action_names = Some((1..=n).map(|k| format!("a{k}")).collect());
        Some(LtiConfig { state_names, action_names, ..Self::from_matrices(e, f) })
    }

    /// The registered block sizes of `lti-blocks-N` (any even N from 2 to
    /// [`LtiConfig::MAX_BLOCKS`] works).
    pub const BLOCK_SIZES: [usize; 4] = [4, 8, 16, 32];

    /// The largest N of `lti-blocks-N`: 256 actions and 512 states (E alone
    /// is then 2 MB; a name is not a way to ask for any allocation).
    pub const MAX_BLOCKS: usize = 256;

    /// N of a name `lti-blocks-N`.
    pub fn blocks_size(name: &str) -> Option<usize> {
        name.strip_prefix("lti-blocks-")?.parse().ok()
    }

    /// A seeded random sparse system: each entry of E and F is non-zero with
    /// probability `density`, drawn from ±[0.2, 0.6] (a scale that keeps m
    /// steps of rollout well inside f64 range). F gets at least one entry
    /// per action so every action moves something.
    pub fn random_sparse(m: usize, n: usize, density: f64, seed: u64) -> Self {
        let mut rng = ChaCha8Rng::seed_from_u64(seed);
        let entry = |rng: &mut ChaCha8Rng| {
            if rng.random_bool(density) {
                let v: f64 = rng.random_range(0.2..0.6);
                if rng.random_bool(0.5) { v } else { -v }
            } else {
                0.0
            }
        };
        let e = (0..m).map(|_| (0..m).map(|_| entry(&mut rng)).collect()).collect();
        let mut f: Vec<Vec<f64>> = (0..m).map(|_| (0..n).map(|_| entry(&mut rng)).collect()).collect();
        for i in 0..n {
            if f.iter().all(|row| row[i] == 0.0) {
                f[rng.random_range(0..m)][i] = 0.5;
            }
        }
        Self::from_matrices(e, f)
    }
}

/// A validated linear system, ready to run.
#[derive(Debug, Clone)]
pub struct LtiSystem {
    pub e: DMatrix<f64>,
    pub f: DMatrix<f64>,
    pub q: DMatrix<f64>,
    pub r: DMatrix<f64>,
    pub initial_low: Vec<f64>,
    pub initial_high: Vec<f64>,
    pub noise_std: f64,
    pub episode_steps: usize,
}

impl LtiSystem {
    /// Checks shapes and values, naming the offending field.
    pub fn from_config(name: &str, cfg: &LtiConfig) -> Result<(Self, EnvSpec), EnvError> {
        if let Some(kind) = &cfg.kind {
            if kind != "lti" {
                return Err(EnvError::invalid("kind", format!("expected \"lti\", found \"{kind}\"")));
            }
        }
        let m = cfg.e.len();
        if m == 0 {
            return Err(EnvError::invalid("e", "must have at least one row"));
        }
        let e = matrix("e", &cfg.e, m, m)?;
        if cfg.f.len() != m {
            return Err(EnvError::invalid(
                "f",
                format!("has {} rows, expected {m} (one per state, like e)", cfg.f.len()),
            ));
        }
        let n = cfg.f[0].len();
        if n == 0 {
            return Err(EnvError::invalid("f", "must have at least one column (one per action)"));
        }
        let f = matrix("f", &cfg.f, m, n)?;
        let q = match &cfg.q {
            Some(q) => matrix("q", q, m, m)?,
            None => DMatrix::identity(m, m),
        };
        let r = match &cfg.r {
            Some(r) => matrix("r", r, n, n)?,
            None => DMatrix::identity(n, n) * 0.1,
        };
        let action_low = vector("action_low", cfg.action_low.as_deref(), n, -1.0)?;
        let action_high = vector("action_high", cfg.action_high.as_deref(), n, 1.0)?;
        for k in 0..n {
            // CS3 sets an action component to 0 when it is outside the random
            // subspace L (docs/method.md §2), so 0 must be a valid action.
            if !(action_low[k] <= 0.0 && 0.0 <= action_high[k] && action_low[k] < action_high[k]) {
                return Err(EnvError::invalid(
                    "action_low/action_high",
                    format!(
                        "component {k}: need low < high with 0 inside, got [{}, {}]",
                        action_low[k], action_high[k]
                    ),
                ));
            }
        }
        let initial_low = vector("initial_state_low", cfg.initial_state_low.as_deref(), m, -1.0)?;
        let initial_high = vector("initial_state_high", cfg.initial_state_high.as_deref(), m, 1.0)?;
        if let Some(k) = (0..m).find(|&k| initial_low[k] > initial_high[k]) {
            return Err(EnvError::invalid(
                "initial_state_low/initial_state_high",
                format!("component {k}: low {} is above high {}", initial_low[k], initial_high[k]),
            ));
        }
        if !cfg.noise_std.is_finite() || cfg.noise_std < 0.0 {
            return Err(EnvError::invalid("noise_std", format!("must be finite and ≥ 0, got {}", cfg.noise_std)));
        }
        if cfg.episode_steps == 0 {
            return Err(EnvError::invalid("episode_steps", "must be at least 1"));
        }
        let state_names = names("state_names", cfg.state_names.as_ref(), m, "s")?;
        let action_names = names("action_names", cfg.action_names.as_ref(), n, "a")?;
        let spec = EnvSpec { name: name.to_string(), state_names, action_names, action_low, action_high };
        let system = LtiSystem {
            e,
            f,
            q,
            r,
            initial_low,
            initial_high,
            noise_std: cfg.noise_std,
            episode_steps: cfg.episode_steps,
        };
        Ok((system, spec))
    }
}

fn matrix(field: &str, rows: &[Vec<f64>], m: usize, n: usize) -> Result<DMatrix<f64>, EnvError> {
    if rows.len() != m {
        return Err(EnvError::invalid(field, format!("has {} rows, expected {m}", rows.len())));
    }
    for (i, row) in rows.iter().enumerate() {
        if row.len() != n {
            return Err(EnvError::invalid(
                field,
                format!("row {} has {} columns, expected {n}", i + 1, row.len()),
            ));
        }
        if let Some(j) = row.iter().position(|v| !v.is_finite()) {
            return Err(EnvError::invalid(
                field,
                format!("entry ({}, {}) is {}; entries must be finite", i + 1, j + 1, row[j]),
            ));
        }
    }
    Ok(DMatrix::from_fn(m, n, |i, j| rows[i][j]))
}

fn vector(field: &str, values: Option<&[f64]>, len: usize, default: f64) -> Result<Vec<f64>, EnvError> {
    let Some(values) = values else { return Ok(vec![default; len]) };
    if values.len() != len {
        return Err(EnvError::invalid(field, format!("has {} entries, expected {len}", values.len())));
    }
    if let Some(k) = values.iter().position(|v| !v.is_finite()) {
        return Err(EnvError::invalid(field, format!("entry {} is {}; entries must be finite", k + 1, values[k])));
    }
    Ok(values.to_vec())
}

fn names(field: &str, given: Option<&Vec<String>>, len: usize, prefix: &str) -> Result<Vec<String>, EnvError> {
    match given {
        Some(v) if v.len() != len => {
            Err(EnvError::invalid(field, format!("has {} names, expected {len}", v.len())))
        }
        Some(v) => Ok(v.clone()),
        None => Ok((1..=len).map(|k| format!("{prefix}{k}")).collect()),
    }
}

/// A linear system as an [`Env`].
#[derive(Debug, Clone)]
pub struct LtiEnv {
    system: LtiSystem,
    spec: EnvSpec,
    state: DVector<f64>,
    state_vec: Vec<f64>,
    steps: usize,
    noise_rng: ChaCha8Rng,
}

impl LtiEnv {
    pub fn new(name: &str, cfg: &LtiConfig) -> Result<Self, EnvError> {
        let (system, spec) = LtiSystem::from_config(name, cfg)?;
        let m = spec.state_dim();
        Ok(LtiEnv {
            system,
            spec,
            state: DVector::zeros(m),
            state_vec: vec![0.0; m],
            steps: 0,
            noise_rng: ChaCha8Rng::seed_from_u64(0),
        })
    }

    pub fn system(&self) -> &LtiSystem {
        &self.system
    }

    /// Sets the state directly (tests, LQR evaluation).
    pub fn set_state(&mut self, state: &[f64]) {
        self.state = DVector::from_column_slice(state);
        self.state_vec = state.to_vec();
        self.steps = 0;
    }
}

impl LtiEnv {
    /// The linear system behind `env`, if it is one (for the LQR reference).
    pub fn of(env: &dyn Env) -> Option<&LtiEnv> {
        env.as_any().downcast_ref::<LtiEnv>()
    }
}

impl Env for LtiEnv {
    fn spec(&self) -> &EnvSpec {
        &self.spec
    }

    fn reset(&mut self, seed: u64) -> Result<Vec<f64>, EnvError> {
        let mut rng = ChaCha8Rng::seed_from_u64(seed);
        let s: Vec<f64> = (0..self.spec.state_dim())
            .map(|k| {
                let (lo, hi) = (self.system.initial_low[k], self.system.initial_high[k]);
                if lo < hi { rng.random_range(lo..=hi) } else { lo }
            })
            .collect();
        self.noise_rng = ChaCha8Rng::seed_from_u64(rng.random());
        self.set_state(&s);
        Ok(s)
    }

    fn state(&self) -> &[f64] {
        &self.state_vec
    }

    fn step(&mut self, action: &[f64]) -> Result<Step, EnvError> {
        self.spec.check_action(action)?;
        let a = DVector::from_vec(self.spec.clip_action(action));
        let s = &self.state;
        let reward = -(s.dot(&(&self.system.q * s)) + a.dot(&(&self.system.r * &a)));
        let mut next = &self.system.e * s + &self.system.f * &a;
        if self.system.noise_std > 0.0 {
            // Cannot fail: noise_std was checked finite and ≥ 0 on load.
            let normal = Normal::new(0.0, self.system.noise_std).expect("validated noise_std");
            for v in next.iter_mut() {
                *v += normal.sample(&mut self.noise_rng);
            }
        }
        self.state = next;
        self.state_vec.copy_from_slice(self.state.as_slice());
        self.steps += 1;
        Ok(Step {
            state: self.state_vec.clone(),
            reward,
            terminated: false,
            truncated: self.steps >= self.system.episode_steps,
        })
    }

    fn fresh(&self) -> Box<dyn Env> {
        Box::new(self.clone())
    }

    fn snapshot(&self) -> Result<Box<dyn Env>, EnvError> {
        Ok(Box::new(self.clone()))
    }

    fn reseed_noise(&mut self, seed: u64) {
        self.noise_rng = ChaCha8Rng::seed_from_u64(seed);
    }

    fn is_stochastic(&self) -> bool {
        self.system.noise_std > 0.0
    }

    fn as_any(&self) -> &dyn std::any::Any {
        self
    }

    fn as_any_mut(&mut self) -> &mut dyn std::any::Any {
        self
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn paper_example_follows_eq_10_by_hand() {
        let mut env = LtiEnv::new("lti-paper", &LtiConfig::paper_example()).unwrap();
        env.set_state(&[0.5, -0.25, 1.0]);
        let step = env.step(&[0.1, 0.2, -0.3]).unwrap();
        // s1' = −s1 + s2 + a1, s2' = s2 + a2, s3' = s3 + a3
        assert_eq!(step.state, vec![-0.5 - 0.25 + 0.1, -0.25 + 0.2, 1.0 - 0.3]);
        // r = −(sᵀ I s + 0.1 aᵀ a)
        let expected = -(0.25 + 0.0625 + 1.0 + 0.1 * (0.01 + 0.04 + 0.09));
        assert!((step.reward - expected).abs() < 1e-12);
    }

    #[test]
    fn actions_are_clipped_and_bad_actions_leave_state_unchanged() {
        let mut env = LtiEnv::new("lti-paper", &LtiConfig::paper_example()).unwrap();
        env.set_state(&[0.0, 0.0, 0.0]);
        let err = env.step(&[0.0, f64::NAN, 0.0]).unwrap_err();
        assert!(matches!(err, EnvError::NonFiniteAction { index: 1, .. }), "{err}");
        let err = env.step(&[0.0, 0.0]).unwrap_err();
        assert!(matches!(err, EnvError::ActionDim { expected: 3, got: 2 }), "{err}");
        assert_eq!(env.state(), &[0.0, 0.0, 0.0]);
        let step = env.step(&[5.0, -5.0, 0.5]).unwrap();
        assert_eq!(step.state, vec![1.0, -1.0, 0.5]);
    }

    #[test]
    fn truncates_at_episode_steps() {
        let cfg = LtiConfig { episode_steps: 3, ..LtiConfig::paper_example() };
        let mut env = LtiEnv::new("x", &cfg).unwrap();
        env.reset(1).unwrap();
        let flags: Vec<bool> = (0..3).map(|_| env.step(&[0.0; 3]).unwrap().truncated).collect();
        assert_eq!(flags, vec![false, false, true]);
    }

    #[test]
    fn snapshot_continues_bit_identically_with_noise() {
        let cfg = LtiConfig { noise_std: 0.3, ..LtiConfig::paper_example() };
        let mut env = LtiEnv::new("x", &cfg).unwrap();
        env.reset(7).unwrap();
        env.step(&[0.3, 0.1, -0.2]).unwrap();
        let mut copy = env.snapshot().unwrap();
        for k in 0..10 {
            let a = [0.1 * k as f64, -0.05, 0.2];
            assert_eq!(env.step(&a).unwrap(), copy.step(&a).unwrap());
        }
    }

    #[test]
    fn same_seed_same_initial_state_and_bounds_respected() {
        let cfg = LtiConfig {
            initial_state_low: Some(vec![-2.0, 0.0, 1.0]),
            initial_state_high: Some(vec![-1.0, 0.0, 3.0]),
            ..LtiConfig::paper_example()
        };
        let mut env = LtiEnv::new("x", &cfg).unwrap();
        let a = env.reset(11).unwrap();
        assert_eq!(a, env.reset(11).unwrap());
        assert_ne!(a, env.reset(12).unwrap());
        assert!((-2.0..=-1.0).contains(&a[0]) && a[1] == 0.0 && (1.0..=3.0).contains(&a[2]));
    }

    fn invalid_field(cfg: LtiConfig) -> String {
        match LtiEnv::new("x", &cfg) {
            Err(EnvError::Invalid { field, .. }) => field,
            other => panic!("expected an invalid-field error, got {other:?}"),
        }
    }

    #[test]
    fn malformed_systems_name_the_field() {
        let base = LtiConfig::paper_example;
        let mut cfg = base();
        cfg.e[1].pop();
        assert_eq!(invalid_field(cfg), "e");
        let mut cfg = base();
        cfg.f.pop();
        assert_eq!(invalid_field(cfg), "f");
        let mut cfg = base();
        cfg.f[2][0] = f64::INFINITY;
        assert_eq!(invalid_field(cfg), "f");
        assert_eq!(invalid_field(LtiConfig { noise_std: -1.0, ..base() }), "noise_std");
        assert_eq!(invalid_field(LtiConfig { action_high: Some(vec![1.0, 1.0]), ..base() }), "action_high");
        assert_eq!(
            invalid_field(LtiConfig { action_low: Some(vec![0.5, -1.0, -1.0]), ..base() }),
            "action_low/action_high"
        );
        assert_eq!(invalid_field(LtiConfig { q: Some(vec![vec![1.0]]), ..base() }), "q");
        assert_eq!(invalid_field(LtiConfig { kind: Some("peg".into()), ..base() }), "kind");
    }
}
