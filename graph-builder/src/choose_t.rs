//! Choosing eq. 7's threshold T from CS3 alone (docs/method.md §3, "Choosing
//! T"): no training run and no evaluation start takes part, so the T a
//! study trains with cannot have been picked for its returns.
//!
//! The rule: measure phi with K independent CS3 seeds at the study's ST.
//! At each T of a fixed grid, threshold every seed's phi (eq. 7) and count,
//! for every pair of seeds, the entries of G in which their graphs differ.
//! A T is *reproducible* when two measurements differ, on average, in at
//! most `max_disagreement` of G's entries. T* is the largest grid T such
//! that every grid T up to it is reproducible: the sparsest graph reached
//! from the publication's T = 0.1 by raising T without passing a graph that
//! a second measurement would not give again.

use serde::Serialize;

use crate::graph::{connection_graph, Rule};
use crate::{cs3, Cs3Config, GraphError};

/// The grid: 0.1 (the publication's T) to 2.0 in steps of 0.1.
pub fn grid() -> Vec<f64> {
    (1..=20).map(|k| k as f64 / 10.0).collect()
}

/// The default largest mean share of G's entries in which two CS3
/// measurements may differ (2%: 1.4 of the peg tasks' 72 entries).
pub const MAX_DISAGREEMENT: f64 = 0.02;

/// One T of the grid.
#[derive(Debug, Clone, PartialEq, Serialize)]
pub struct Candidate {
    pub threshold: f64,
    /// Edges of each seed's graph, in seed order.
    pub edges: Vec<usize>,
    /// Mean over seed pairs of the share of entries in which their graphs differ.
    pub disagreement: f64,
    pub reproducible: bool,
}

/// The rule's result.
#[derive(Debug, Clone, PartialEq, Serialize)]
pub struct Choice {
    pub seeds: Vec<u64>,
    pub max_disagreement: f64,
    pub candidates: Vec<Candidate>,
    /// None when not even the first grid T is reproducible.
    pub chosen: Option<f64>,
}

/// Applies the rule to K measurements of phi (each n × m, one per seed).
pub fn choose(phis: &[Vec<Vec<f64>>], seeds: &[u64], grid: &[f64], max_disagreement: f64) -> Choice {
    let mut candidates = Vec::new();
    let mut chosen = None;
    let mut still_reproducible = true;
    for &t in grid {
        let graphs: Vec<Vec<Vec<u8>>> = phis.iter().map(|phi| connection_graph(phi, Rule::Threshold(t)).g).collect();
        let edges = graphs.iter().map(|g| g.iter().flatten().filter(|&&e| e == 1).count()).collect();
        let disagreement = mean_pairwise_disagreement(&graphs);
        let reproducible = disagreement <= max_disagreement;
        still_reproducible &= reproducible;
        if still_reproducible {
            chosen = Some(t);
        }
        candidates.push(Candidate { threshold: t, edges, disagreement, reproducible });
    }
    Choice { seeds: seeds.to_vec(), max_disagreement, candidates, chosen }
}

/// Measures phi on `env` with each of `seeds` (the other CS3 settings from
/// `cs3`) and applies the rule on [`grid`].
pub fn measure_and_choose(env: &dyn lcrl_sim::Env, cs3: &Cs3Config, seeds: &[u64], max_disagreement: f64, on_sample: &(dyn Fn() + Sync)) -> Result<Choice, GraphError> {
    let pool = cs3::thread_pool(cs3.threads)?;
    let phis = pool.install(|| {
        seeds
            .iter()
            .map(|&seed| Ok(cs3::measure(env, &Cs3Config { seed, ..cs3.clone() }, on_sample)?.phi()))
            .collect::<Result<Vec<_>, GraphError>>()
    })?;
    Ok(choose(&phis, seeds, &grid(), max_disagreement))
}

/// Mean over pairs of graphs of the share of entries in which they differ
/// (0 for fewer than two graphs).
fn mean_pairwise_disagreement(graphs: &[Vec<Vec<u8>>]) -> f64 {
    let entries = graphs.first().map_or(0, |g| g.iter().map(Vec::len).sum::<usize>());
    let (mut total, mut pairs) = (0.0, 0usize);
    for (a, first) in graphs.iter().enumerate() {
        for second in &graphs[a + 1..] {
            let differ = first.iter().flatten().zip(second.iter().flatten()).filter(|(x, y)| x != y).count();
            total += differ as f64 / entries.max(1) as f64;
            pairs += 1;
        }
    }
    if pairs == 0 {
        0.0
    } else {
        total / pairs as f64
    }
}

impl Choice {
    /// The table `lcrl graph --choose-t` prints, and why T* is T*.
    pub fn text(&self, env: &str, samples: usize) -> String {
        use std::fmt::Write as _;
        let mut out = String::new();
        let _ = writeln!(out, "Choosing T for {env}: CS3 with ST = {samples} on seeds {:?}; eq. 7 at each T.", self.seeds);
        let _ = writeln!(out, "\n{:>5}  {:>13}  {:>13}  reproducible", "T", "edges (range)", "disagreement");
        for c in &self.candidates {
            let (lo, hi) = (c.edges.iter().min().copied().unwrap_or(0), c.edges.iter().max().copied().unwrap_or(0));
            let mark = if Some(c.threshold) == self.chosen { "  <- T*" } else { "" };
            let _ = writeln!(
                out,
                "{:>5}  {:>13}  {:>12.1}%  {}{mark}",
                c.threshold,
                format!("{lo}–{hi}"),
                100.0 * c.disagreement,
                if c.reproducible { "yes" } else { "no" }
            );
        }
        let rule = format!(
            "the largest T such that at every grid T up to it two CS3 seeds' graphs differ in at most {:.1}% of G's entries on average",
            100.0 * self.max_disagreement
        );
        match self.chosen {
            Some(t) => {
                let _ = writeln!(out, "\nT* = {t} (the publication's T = {}): {rule}.", crate::PAPER_THRESHOLD);
            }
            None => {
                let _ = writeln!(out, "\nNo T*: not even T = {} is reproducible by the rule ({rule}); measure with more samples (--samples).", self.candidates.first().map_or(f64::NAN, |c| c.threshold));
            }
        }
        out
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// Two actions, two states, three seeds. Column 0 is [1.5, 0.5] for
    /// every seed (mean 1): entry (1, 0) is kept while T ≤ 0.5. Column 1 is
    /// [2 − w, w] (mean 1) with w = 0.6, 0.8, 0.9 by seed: entry (1, 1) is
    /// kept while T ≤ w, so the seeds part ways between T = 0.6 and 0.9.
    #[test]
    fn the_chosen_t_is_the_last_before_the_first_irreproducible_one() {
        let phi = |w: f64| vec![vec![1.5, 2.0 - w], vec![0.5, w]];
        let phis = vec![phi(0.6), phi(0.8), phi(0.9)];
        let grid = [0.2, 0.4, 0.55, 0.7, 0.85, 0.95];
        let choice = choose(&phis, &[0, 1, 2], &grid, 0.1);
        let disagreement: Vec<f64> = choice.candidates.iter().map(|c| c.disagreement).collect();
        // T = 0.7: seed 0 alone drops (1, 1): pairs (0, 1) and (0, 2) differ
        // in 1 of 4 entries, (1, 2) in none → (0.25 + 0.25 + 0) / 3.
        // T = 0.85: seeds 0 and 1 drop it → 1/6 again. T = 0.95: every seed
        // drops it → 0, reproducible again but after an irreproducible T.
        assert_eq!(disagreement, [0.0, 0.0, 0.0, 1.0 / 6.0, 1.0 / 6.0, 0.0]);
        assert_eq!(choice.candidates.iter().map(|c| c.reproducible).collect::<Vec<_>>(), [true, true, true, false, false, true]);
        assert_eq!(choice.chosen, Some(0.55));
        assert_eq!(choice.candidates[0].edges, [4, 4, 4]);
        assert_eq!(choice.candidates[2].edges, [3, 3, 3]);
        assert_eq!(choice.candidates[4].edges, [2, 2, 3]);
        // A looser rule reaches further.
        assert_eq!(choose(&phis, &[0, 1, 2], &grid, 0.2).chosen, Some(0.95));
        let text = choice.text("toy", 8);
        assert!(text.contains("T* = 0.55 (the publication's T = 0.1)"), "{text}");
        assert!(text.contains("16.7%"), "{text}");
    }

    #[test]
    fn no_reproducible_t_is_said_plainly() {
        let phis = vec![vec![vec![1.0, 1.0], vec![0.0, 1.0]], vec![vec![1.0, 1.0], vec![1.0, 1.0]]];
        let choice = choose(&phis, &[0, 1], &[0.1], 0.0);
        assert_eq!(choice.chosen, None);
        assert!(choice.text("toy", 4).contains("No T*"));
        assert_eq!(grid().first(), Some(&0.1));
        assert_eq!(grid().len(), 20);
    }
}
