//! The LQR reference for linear environments with quadratic cost: the
//! ceiling a learned policy is measured against.
//!
//! The episode is a finite horizon of T steps with cost Σ sᵀQs + aᵀRa and no
//! terminal cost, so the optimal controller is time-varying: backward
//! Riccati recursion P_T = 0,
//!   K_t = (R + FᵀP_{t+1}F)⁻¹ FᵀP_{t+1}E,
//!   P_t = Q + EᵀP_{t+1}(E − F K_t),
//! and a_t = −K_t s_t. Its return is measured by running it on the
//! environment itself (same initial-state distribution, same action
//! clipping, same noise), so saturation is accounted for honestly.

use lcrl_sim::evaluate::run_episode;
use lcrl_sim::lti::LtiEnv;
use nalgebra::{DMatrix, DVector};

/// The time-varying LQR gains K_0 … K_{T−1}.
pub fn lqr_gains(e: &DMatrix<f64>, f: &DMatrix<f64>, q: &DMatrix<f64>, r: &DMatrix<f64>, horizon: usize) -> Option<Vec<DMatrix<f64>>> {
    let mut p = DMatrix::zeros(e.nrows(), e.nrows());
    let mut gains = Vec::with_capacity(horizon);
    for _ in 0..horizon {
        let k = (r + f.transpose() * &p * f).try_inverse()? * f.transpose() * &p * e;
        p = q + e.transpose() * &p * (e - f * &k);
        gains.push(k);
    }
    gains.reverse();
    Some(gains)
}

/// Mean return of the LQR controller over `episodes` episodes seeded
/// `seed`, `seed + 1`, …; None when the Riccati recursion is singular.
pub fn lqr_return(env: &LtiEnv, episodes: usize, seed: u64) -> Option<f64> {
    let system = env.system();
    let gains = lqr_gains(&system.e, &system.f, &system.q, &system.r, system.episode_steps)?;
    let mut env = env.clone();
    let mut total = 0.0;
    for k in 0..episodes {
        let mut t = 0;
        let mut policy = |s: &[f64]| {
            let a = -&gains[t.min(gains.len() - 1)] * DVector::from_column_slice(s);
            t += 1;
            a.as_slice().to_vec()
        };
        total += run_episode(&mut env, seed.wrapping_add(k as u64), &mut policy, false).ok()?.episode_return;
    }
    Some(total / episodes.max(1) as f64)
}

/// One quadratic control problem: s' = E s + F a, cost sᵀQs + aᵀRa per
/// step over `horizon` steps, from s_0 with second moment `sigma0`.
struct Problem {
    e: DMatrix<f64>,
    f: DMatrix<f64>,
    q: DMatrix<f64>,
    r: DMatrix<f64>,
    sigma0: DMatrix<f64>,
    horizon: usize,
}

/// Expected cost Σ_t E[sᵀQs + aᵀRa] of the problem under a = −K s
/// (clipping ignored).
fn linear_policy_cost(p: &Problem, k: &DMatrix<f64>) -> f64 {
    let closed = &p.e - &p.f * k;
    let stage = &p.q + k.transpose() * &p.r * k;
    let mut sigma = p.sigma0.clone();
    let mut cost = 0.0;
    for _ in 0..p.horizon {
        cost += (&stage * &sigma).trace();
        sigma = &closed * sigma * closed.transpose();
    }
    cost
}

/// The best time-invariant linear controller a = −K s whose gain has the
/// sparsity of G (K_ij = 0 where G_ij = 0): the ceiling of a locally
/// connected actor, which cannot use states outside its row of G. Found by
/// gradient descent (finite differences) on the exact expected cost from
/// the initial-state distribution, starting from the masked LQR gain.
///
/// The cost is a sum over the system's independent parts (states and
/// actions that no entry of E, F, Q, R, G or the initial second moment
/// ties together, such as the pairs of `lti-blocks-N`), so each part is
/// solved alone: the same optimum, at the cost of the largest part rather
/// than the whole (a 64-state system would take hours whole).
pub fn masked_lqr_gain(env: &LtiEnv, mask: &[Vec<u8>]) -> Option<DMatrix<f64>> {
    let s = env.system();
    let m = s.e.nrows();
    let n = s.f.ncols();
    let sigma0 = DMatrix::from_fn(m, m, |i, j| {
        let (lo, hi) = (s.initial_low[i], s.initial_high[i]);
        let mean = |k: usize| (s.initial_low[k] + s.initial_high[k]) / 2.0;
        if i == j { (hi - lo).powi(2) / 12.0 + mean(i).powi(2) } else { mean(i) * mean(j) }
    });
    let mut k = DMatrix::zeros(n, m);
    for (states, actions) in independent_parts(s, mask, &sigma0) {
        let sub = |a: &DMatrix<f64>, rows: &[usize], cols: &[usize]| DMatrix::from_fn(rows.len(), cols.len(), |i, j| a[(rows[i], cols[j])]);
        let part_mask: Vec<Vec<u8>> = actions.iter().map(|&i| states.iter().map(|&j| mask[i][j]).collect()).collect();
        let problem = Problem {
            e: sub(&s.e, &states, &states),
            f: sub(&s.f, &states, &actions),
            q: sub(&s.q, &states, &states),
            r: sub(&s.r, &actions, &actions),
            sigma0: sub(&sigma0, &states, &states),
            horizon: s.episode_steps,
        };
        let part = masked_gain_of(&problem, &part_mask)?;
        for (a, &i) in actions.iter().enumerate() {
            for (b, &j) in states.iter().enumerate() {
                k[(i, j)] = part[(a, b)];
            }
        }
    }
    Some(k)
}

/// The system's independent parts: (states, actions) groups that no
/// non-zero entry links (union-find over states 0..m and actions m..m+n).
/// A part with no action needs no gain and is left out.
fn independent_parts(s: &lcrl_sim::lti::LtiSystem, mask: &[Vec<u8>], sigma0: &DMatrix<f64>) -> Vec<(Vec<usize>, Vec<usize>)> {
    let (m, n) = (s.e.nrows(), s.f.ncols());
    let mut parent: Vec<usize> = (0..m + n).collect();
    fn root(parent: &mut [usize], mut x: usize) -> usize {
        while parent[x] != x {
            parent[x] = parent[parent[x]];
            x = parent[x];
        }
        x
    }
    let mut join = |a: usize, b: usize| {
        let (ra, rb) = (root(&mut parent, a), root(&mut parent, b));
        parent[ra] = rb;
    };
    for i in 0..m {
        for j in 0..m {
            if s.e[(i, j)] != 0.0 || s.q[(i, j)] != 0.0 || sigma0[(i, j)] != 0.0 {
                join(i, j);
            }
        }
        for a in 0..n {
            if s.f[(i, a)] != 0.0 || mask[a][i] == 1 {
                join(i, m + a);
            }
        }
    }
    for a in 0..n {
        for b in 0..n {
            if s.r[(a, b)] != 0.0 {
                join(m + a, m + b);
            }
        }
    }
    let mut parts: std::collections::BTreeMap<usize, (Vec<usize>, Vec<usize>)> = Default::default();
    for x in 0..m + n {
        let part = parts.entry(root(&mut parent, x)).or_default();
        if x < m { part.0.push(x) } else { part.1.push(x - m) }
    }
    parts.into_values().filter(|(_, actions)| !actions.is_empty()).collect()
}

/// [`masked_lqr_gain`] of one part, from the masked LQR gain downhill.
fn masked_gain_of(p: &Problem, mask: &[Vec<u8>]) -> Option<DMatrix<f64>> {
    let m = p.e.nrows();
    let free: Vec<(usize, usize)> = (0..mask.len()).flat_map(|i| (0..m).map(move |j| (i, j))).filter(|&(i, j)| mask[i][j] == 1).collect();
    let mut k = lqr_gains(&p.e, &p.f, &p.q, &p.r, p.horizon)?.into_iter().next()?;
    for (i, row) in mask.iter().enumerate() {
        for (j, &g) in row.iter().enumerate() {
            if g == 0 {
                k[(i, j)] = 0.0;
            }
        }
    }
    let cost = |k: &DMatrix<f64>| linear_policy_cost(p, k);
    let mut step = 0.05;
    let mut best = cost(&k);
    for _ in 0..3000 {
        let h = 1e-6;
        let grad: Vec<f64> = free
            .iter()
            .map(|&(i, j)| {
                let mut kp = k.clone();
                kp[(i, j)] += h;
                (cost(&kp) - best) / h
            })
            .collect();
        let mut candidate = k.clone();
        for (&(i, j), g) in free.iter().zip(&grad) {
            candidate[(i, j)] -= step * g;
        }
        let c = cost(&candidate);
        if c.is_finite() && c < best {
            k = candidate;
            best = c;
            step *= 1.2;
        } else {
            step *= 0.5;
            if step < 1e-12 {
                break;
            }
        }
    }
    Some(k)
}

/// Mean return of the best G-structured linear controller, run on the
/// environment like [`lqr_return`].
pub fn masked_lqr_return(env: &LtiEnv, mask: &[Vec<u8>], episodes: usize, seed: u64) -> Option<f64> {
    let k = masked_lqr_gain(env, mask)?;
    let mut env = env.clone();
    let mut total = 0.0;
    for n in 0..episodes {
        let mut policy = |s: &[f64]| (-&k * DVector::from_column_slice(s)).as_slice().to_vec();
        total += run_episode(&mut env, seed.wrapping_add(n as u64), &mut policy, false).ok()?.episode_return;
    }
    Some(total / episodes.max(1) as f64)
}

#[cfg(test)]
mod tests {
    use super::*;
    use lcrl_sim::lti::LtiConfig;

    #[test]
    fn scalar_riccati_by_hand() {
        // s' = s + a, cost s² + a², one step before the end: P = 0 → K = 0;
        // two steps: P_1 = 1 → K_0 = 1/(1+1) = 0.5.
        let one = DMatrix::from_element(1, 1, 1.0);
        let gains = lqr_gains(&one, &one, &one, &one, 2).unwrap();
        assert_eq!(gains[1][(0, 0)], 0.0);
        assert!((gains[0][(0, 0)] - 0.5).abs() < 1e-12);
    }

    #[test]
    fn masked_controller_respects_g_and_pays_for_it() {
        let env = LtiEnv::new("lti-paper", &LtiConfig::paper_example()).unwrap();
        let g = vec![vec![1, 0, 0], vec![1, 1, 0], vec![0, 0, 1]];
        let k = masked_lqr_gain(&env, &g).unwrap();
        assert_eq!((k[(0, 1)], k[(0, 2)], k[(1, 2)], k[(2, 0)], k[(2, 1)]), (0.0, 0.0, 0.0, 0.0, 0.0));
        let full = lqr_return(&env, 200, 0).unwrap();
        let local = masked_lqr_return(&env, &g, 200, 0).unwrap();
        // a1 cannot see s2, which pushes s1 (s1' = −s1 + s2 + a1): the local
        // ceiling is strictly lower, by about E[s2²] = 1/3 at the first step.
        assert!(local < full - 0.15 && local > full - 0.6, "local {local} vs full {full}");
        // With every state connected the masked optimum is the LQR optimum.
        let everything = masked_lqr_return(&env, &vec![vec![1; 3]; 3], 200, 0).unwrap();
        assert!((everything - full).abs() < 0.05 * full.abs(), "{everything} vs {full}");
    }

    /// lti-blocks-N: the masked optimum is found part by part (the pairs);
    /// it is stable, beats a = 0 by far, and with the exact G it gives up
    /// little against full LQR (a_k misses only its partner's y).
    #[test]
    fn masked_lqr_on_lti_blocks_is_stable_and_beats_a_zero() {
        for n in [4, 32] {
            let env = LtiEnv::new("lti-blocks", &LtiConfig::blocks(n).unwrap()).unwrap();
            let s = env.system();
            let g = lcrl_graph_builder::lemma1::lemma1_graph(&s.e, &s.f);
            let k = masked_lqr_gain(&env, &g).unwrap();
            let closed = &s.e - &s.f * &k;
            let radius = closed.complex_eigenvalues().iter().map(|v| v.norm()).fold(0.0, f64::max);
            assert!(radius < 1.0, "N = {n}: closed-loop spectral radius {radius}");
            let masked = masked_lqr_return(&env, &g, 100, 0).unwrap();
            let full = lqr_return(&env, 100, 0).unwrap();
            let mut idle = env.clone();
            let zero: f64 = (0..100u64).map(|k| run_episode(&mut idle, k, &mut |_| vec![0.0; n], false).unwrap().episode_return).sum::<f64>() / 100.0;
            assert!(masked > 0.8 * zero, "N = {n}: masked LQR {masked} vs a = 0 {zero}");
            assert!(masked <= full + 0.01 * full.abs() && masked > full * 1.05, "N = {n}: masked {masked} vs LQR {full}");
            // The same gain as one 2N-state problem would give, part by
            // part: each pair's gain sees only its own pair's states.
            for i in 0..n {
                for j in 0..2 * n {
                    if j / 4 != i / 2 {
                        assert_eq!(k[(i, j)], 0.0, "N = {n}: a{} uses state {j} outside its pair", i + 1);
                    }
                }
            }
        }
    }

    #[test]
    fn lqr_beats_doing_nothing_on_the_paper_example() {
        let env = LtiEnv::new("lti-paper", &LtiConfig::paper_example()).unwrap();
        let lqr = lqr_return(&env, 50, 0).unwrap();
        let mut idle = env.clone();
        let zero: f64 = (0..50u64).map(|k| run_episode(&mut idle, k, &mut |_| vec![0.0; 3], false).unwrap().episode_return).sum::<f64>() / 50.0;
        assert!(lqr > 0.5 * zero, "LQR {lqr} vs zero action {zero}");
        assert!(lqr < 0.0);
    }

    /// The headroom search has a known answer on a linear system: the
    /// affine family contains the LQR controller (up to the box's clip and
    /// the finite horizon's time-varying gain), so `lcrl tune --policy
    /// affine` must come within 10% of LQR on the same evaluation starts.
    #[test]
    fn affine_search_on_the_paper_example_comes_within_10_percent_of_lqr() {
        use lcrl_sim::tune::feedback::{tune_policy, Family};
        use lcrl_sim::tune::TuneOptions;
        let env = LtiEnv::new("lti-paper", &LtiConfig::paper_example()).unwrap();
        let opts = TuneOptions { evaluations: 1500, sigma: 0.1, ..TuneOptions::default() };
        let report = tune_policy(&env, Family::Affine, &[0.0; 3], &opts, &|_| {}).unwrap();
        let lqr = lqr_return(&env, opts.eval_episodes, opts.eval_seed).unwrap();
        let zero = report.record.zero_action.eval.mean_return;
        assert!((report.record.mean_return - lqr).abs() <= 0.10 * lqr.abs(), "affine {} vs LQR {lqr} (a = 0: {zero})", report.record.mean_return);
        // And it is a real gain: a = 0 is far from both.
        assert!(zero < lqr - 0.5 * lqr.abs(), "a = 0 {zero} vs LQR {lqr}");
    }
}
