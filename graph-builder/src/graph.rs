//! From phi to the connection graph G (docs/method.md §3, eqs. 6–7), and how
//! stable each entry of G is under resampling.

use rand::{Rng, SeedableRng};
use rand_chacha::ChaCha8Rng;

use rayon::prelude::*;

use crate::cs3::{sample_seed, Cs3Samples};

/// Which rule turns phi into G.
#[derive(Debug, Clone, Copy, PartialEq)]
pub enum Rule {
    /// Eq. 7: G_ij = 1 iff phi(i,j) ≥ T · (1/n) Σ_k phi(k,j).
    Threshold(f64),
    /// Eq. 6: G_ij = 1 iff phi(i,j) ≠ 0, read as phi(i,j) > tolerance ·
    /// max phi, so floating-point dust does not count as an effect.
    Exact { tolerance: f64 },
}

/// T of eq. 7, the publication's threshold (docs/method.md §3): an action
/// connects to a state whose normalized CS3 value is at least T.
pub const PAPER_THRESHOLD: f64 = 0.1;

/// Bootstrap resamples for each entry's stability, where nobody asks for
/// another count.
pub const DEFAULT_BOOTSTRAP: usize = 200;

/// The default relative tolerance of [`Rule::Exact`].
pub const EXACT_TOLERANCE: f64 = 1e-9;

/// G (n × m, entries 0/1) and the state columns no action moves.
#[derive(Debug, Clone, PartialEq)]
pub struct ConnectionGraph {
    pub g: Vec<Vec<u8>>,
    /// Columns j with phi(·, j) = 0 for every action. Decision (docs/method.md §3):
    /// such a column is all zeros, although eq. 7 read literally gives ones.
    pub unmoved_states: Vec<usize>,
}

/// Applies `rule` to phi (n × m).
pub fn connection_graph(phi: &[Vec<f64>], rule: Rule) -> ConnectionGraph {
    let n = phi.len();
    let m = phi.first().map_or(0, Vec::len);
    let column = |j: usize| phi.iter().map(move |row| row[j]);
    let max_phi = phi.iter().flatten().fold(0.0_f64, |a, &b| a.max(b));
    let mut g = vec![vec![0u8; m]; n];
    let mut unmoved_states = Vec::new();
    for j in 0..m {
        let unmoved = match rule {
            Rule::Threshold(_) => column(j).all(|v| v == 0.0),
            Rule::Exact { tolerance } => column(j).all(|v| v <= tolerance * max_phi),
        };
        if unmoved {
            unmoved_states.push(j);
            continue;
        }
        let cut = match rule {
            Rule::Threshold(t) => t * column(j).sum::<f64>() / n as f64,
            Rule::Exact { tolerance } => tolerance * max_phi,
        };
        // At T ≤ 1 a column's largest value is at least its cut; the mean,
        // rounded, can come out above equal entries (six 0.7s: 0.70000…01),
        // so the largest is kept as the arithmetic says.
        let column_max = column(j).fold(0.0_f64, f64::max);
        for i in 0..n {
            let keep = match rule {
                Rule::Threshold(t) => phi[i][j] >= cut || (t <= 1.0 && phi[i][j] == column_max),
                Rule::Exact { .. } => phi[i][j] > cut,
            };
            g[i][j] = u8::from(keep);
        }
    }
    ConnectionGraph { g, unmoved_states }
}

/// Each entry's margin under eq. 7 with threshold T: phi(i, j) divided by
/// its cut T · (1/n) Σ_k phi(k, j). G_ij = 1 exactly when the margin is ≥ 1;
/// a margin of 5 means the edge survives thresholds up to 5·T. Columns no
/// action moves get 0.
pub fn margins(phi: &[Vec<f64>], threshold: f64) -> Vec<Vec<f64>> {
    let n = phi.len();
    let m = phi.first().map_or(0, Vec::len);
    let cuts: Vec<f64> = (0..m).map(|j| threshold * phi.iter().map(|row| row[j]).sum::<f64>() / n as f64).collect();
    phi.iter()
        .map(|row| row.iter().zip(&cuts).map(|(v, cut)| if *cut > 0.0 { v / cut } else { 0.0 }).collect())
        .collect()
}

/// "Normalized CS3": phi divided by its column sum (0 for an all-zero column).
pub fn normalized(phi: &[Vec<f64>]) -> Vec<Vec<f64>> {
    let m = phi.first().map_or(0, Vec::len);
    let sums: Vec<f64> = (0..m).map(|j| phi.iter().map(|row| row[j]).sum()).collect();
    phi.iter()
        .map(|row| row.iter().zip(&sums).map(|(v, s)| if *s > 0.0 { v / s } else { 0.0 }).collect())
        .collect()
}

/// For each entry, the share of `resamples` bootstrap resamples (the ST
/// samples of every action drawn again with replacement) whose graph has
/// the same G_ij as `reference`. 1.0 everywhere means a clear-cut graph;
/// values near 0.5 mark borderline edges.
pub fn stability(samples: &Cs3Samples, rule: Rule, reference: &ConnectionGraph, resamples: usize, seed: u64) -> Vec<Vec<f64>> {
    let (n, m, st) = (samples.actions, samples.states, samples.samples);
    if resamples == 0 {
        return vec![vec![f64::NAN; m]; n];
    }
    // Each resample has its own RNG (seeded from its index), so the result
    // does not depend on how rayon splits the work.
    let agree = (0..resamples)
        .into_par_iter()
        .map(|r| {
            let mut rng = ChaCha8Rng::seed_from_u64(sample_seed(seed ^ 0x5EED_B007_5742_0000, usize::MAX, r));
            let picks: Vec<Vec<usize>> = (0..n).map(|_| (0..st).map(|_| rng.random_range(0..st)).collect()).collect();
            let g = connection_graph(&samples.phi_of(|i| &picks[i]), rule).g;
            g.iter()
                .zip(&reference.g)
                .map(|(row, reference_row)| row.iter().zip(reference_row).map(|(a, b)| usize::from(a == b)).collect())
                .collect::<Vec<Vec<usize>>>()
        })
        .reduce(
            || vec![vec![0usize; m]; n],
            |mut total, part| {
                for (t, p) in total.iter_mut().flatten().zip(part.iter().flatten()) {
                    *t += p;
                }
                total
            },
        );
    agree.iter().map(|row| row.iter().map(|&c| c as f64 / resamples as f64).collect()).collect()
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn eq7_is_relative_to_the_column_mean() {
        // Column 0: mean 4/3, cut 0.4 · 4/3 ≈ 0.53 → 0.5 is dropped, 1.0 kept.
        // Column 1: all zero → unmoved, all zeros (the §3 decision).
        // Column 2: scale is irrelevant: 1e-6 ≥ 0.4 · mean(1e-6, 1e-6, 0).
        let phi = vec![vec![2.5, 0.0, 1e-6], vec![1.0, 0.0, 1e-6], vec![0.5, 0.0, 0.0]];
        let graph = connection_graph(&phi, Rule::Threshold(0.4));
        assert_eq!(graph.g, vec![vec![1, 0, 1], vec![1, 0, 1], vec![0, 0, 0]]);
        assert_eq!(graph.unmoved_states, vec![1]);
    }

    #[test]
    fn eq6_ignores_rounding_dust_but_keeps_small_real_effects() {
        let phi = vec![vec![1.0, 1e-18], vec![1e-6, 0.0]];
        let graph = connection_graph(&phi, Rule::Exact { tolerance: EXACT_TOLERANCE });
        assert_eq!(graph.g, vec![vec![1, 0], vec![1, 0]]);
        assert_eq!(graph.unmoved_states, vec![1]);
    }

    #[test]
    fn margins_are_phi_over_the_cut_and_agree_with_g() {
        let phi = vec![vec![2.5, 0.0, 1e-6], vec![1.0, 0.0, 1e-6], vec![0.5, 0.0, 0.0]];
        let margin = margins(&phi, 0.4);
        // Column 0: cut 0.4 · 4/3; 2.5 / (1.6/3) = 4.6875.
        assert!((margin[0][0] - 4.6875).abs() < 1e-12);
        assert_eq!(margin[0][1], 0.0);
        let g = connection_graph(&phi, Rule::Threshold(0.4)).g;
        for (i, row) in margin.iter().enumerate() {
            for (j, &v) in row.iter().enumerate() {
                assert_eq!(g[i][j] == 1, v >= 1.0, "({i}, {j}): margin {v}");
            }
        }
    }

    #[test]
    fn normalized_columns_sum_to_one() {
        let norm = normalized(&[vec![3.0, 0.0], vec![1.0, 0.0]]);
        assert_eq!(norm, vec![vec![0.75, 0.0], vec![0.25, 0.0]]);
    }
}
