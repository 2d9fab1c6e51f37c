//! Choosing eq. 7's threshold T from CS3 alone (docs/method.md §3, "Choosing
//! T"): no training run and no evaluation start takes part, so the T a
//! study trains with cannot have been picked for its returns.
//!
//! The rule (the above-average rule): T_rule = 1. Eq. 7 at T = 1 keeps
//! G_ij = 1 where action i moves state j at least as much as the average
//! action does. Two properties make it the rule, not one T among many:
//! - it is the largest T at which every state some action moves is still
//!   seen by at least one action, whatever CS3 measures: a column's largest
//!   value is at least its mean (at any T > 1 a state that every action
//!   moves equally has no edge at all);
//! - it is scale-free per state, as eq. 7 is.
//! It replaced the reproducibility rule (the largest T at which two CS3
//! seeds' graphs agree), which picked T = 0.1 on the peg presets, the graph
//! measured to buy nothing (docs/research/2026-12-05-graph-rule.md).
//!
//! `lcrl graph --choose-t` still measures phi with K CS3 seeds and prints,
//! at every T of a grid, the edges of each seed's graph and how often two
//! seeds' graphs disagree: how much the chosen graph would change under a
//! second measurement, and where denser or sparser graphs lie.

use serde::{Deserialize, Serialize};

use crate::graph::{connection_graph, Rule};
use crate::{cs3, Cs3Config, GraphError};

/// T of the above-average rule (eq. 7 at T = 1).
pub const RULE_THRESHOLD: f64 = 1.0;

/// Why T_rule is what it is, in one line (printed by `lcrl graph`, the main
/// job, and recorded in a run's config.toml).
pub const RULE_REASON: &str = "the above-average rule: an action sees the states it moves at least as much as the average action does \
     (eq. 7 at T = 1), the largest T at which every state some action moves keeps at least one action whatever CS3 measures \
     (a guarantee for every phi; a given task's table may keep every state further) (docs/method.md, \"Choosing T\")";

/// `graph_threshold` in a TOML config: a number (T of eq. 7) or "auto"
/// (T_rule, [`RULE_THRESHOLD`]); serde's `deserialize_with` for an f64
/// field. Anything else is refused with what is allowed.
pub fn deserialize_threshold<'de, D: serde::Deserializer<'de>>(d: D) -> Result<f64, D::Error> {
    #[derive(serde::Deserialize)]
    #[serde(untagged)]
    enum Given {
        Number(f64),
        Text(String),
    }
    match Given::deserialize(d)? {
        Given::Number(t) => Ok(t),
        Given::Text(text) if text == "auto" => Ok(RULE_THRESHOLD),
        Given::Text(text) => Err(serde::de::Error::custom(format!(
            "graph_threshold = {text:?}: give \"auto\" (T_rule = {RULE_THRESHOLD}, the above-average rule) or a number > 0 (T of eq. 7; the publication's is {})",
            crate::PAPER_THRESHOLD
        ))),
    }
}

/// Why a graph was cut at `threshold`, in one line: the rule's T, the
/// publication's, or one a user or study named.
pub fn threshold_reason(threshold: f64) -> String {
    if threshold == RULE_THRESHOLD {
        format!("T_rule, {RULE_REASON}")
    } else if threshold == crate::PAPER_THRESHOLD {
        format!("the publication's T (`lcrl graph`'s default without --threshold, or named: local@0.1, graph_threshold = 0.1); `connection = \"local\"` trains T_rule = {RULE_THRESHOLD} by default (`lcrl graph --choose-t` says why)")
    } else {
        format!("named by the user or study (local@T, --threshold, run.graph_threshold); the rule's T_rule = {RULE_THRESHOLD}")
    }
}

/// The grid: 0.1 (the publication's T) to 2.0 in steps of 0.1.
pub fn grid() -> Vec<f64> {
    (1..=20).map(|k| k as f64 / 10.0).collect()
}

/// One T of the grid.
#[derive(Debug, Clone, PartialEq, Serialize)]
pub struct Candidate {
    pub threshold: f64,
    /// Edges of each seed's graph, in seed order.
    pub edges: Vec<usize>,
    /// Mean over seed pairs of the share of entries in which their graphs differ.
    pub disagreement: f64,
    /// States some action moves that no action sees at this T (first seed).
    pub unseen_states: usize,
}

/// The rule's result.
#[derive(Debug, Clone, PartialEq, Serialize)]
pub struct Choice {
    pub seeds: Vec<u64>,
    pub candidates: Vec<Candidate>,
    /// T_rule.
    pub chosen: f64,
    pub reason: String,
    /// Inputs of each action at T_rule (first seed's graph), in action order.
    pub row_edges: Vec<usize>,
}

/// Applies the rule to K measurements of phi (each n × m, one per seed),
/// with the table over `grid`.
pub fn choose(phis: &[Vec<Vec<f64>>], seeds: &[u64], grid: &[f64]) -> Choice {
    let candidates = grid
        .iter()
        .map(|&t| {
            let graphs: Vec<Vec<Vec<u8>>> = phis.iter().map(|phi| connection_graph(phi, Rule::Threshold(t)).g).collect();
            let edges = graphs.iter().map(|g| g.iter().flatten().filter(|&&e| e == 1).count()).collect();
            let unseen_states = phis.first().map_or(0, |phi| unseen_states(phi, &graphs[0]));
            Candidate { threshold: t, edges, disagreement: mean_pairwise_disagreement(&graphs), unseen_states }
        })
        .collect();
    let row_edges = phis
        .first()
        .map(|phi| connection_graph(phi, Rule::Threshold(RULE_THRESHOLD)).g.iter().map(|row| row.iter().filter(|&&e| e == 1).count()).collect())
        .unwrap_or_default();
    Choice { seeds: seeds.to_vec(), candidates, chosen: RULE_THRESHOLD, reason: RULE_REASON.to_string(), row_edges }
}

/// Columns some action moves (phi > 0) in which `g` has no edge.
fn unseen_states(phi: &[Vec<f64>], g: &[Vec<u8>]) -> usize {
    let m = phi.first().map_or(0, Vec::len);
    (0..m).filter(|&j| phi.iter().any(|row| row[j] > 0.0) && g.iter().all(|row| row[j] == 0)).count()
}

/// Measures phi on `env` with each of `seeds` (the other CS3 settings from
/// `cs3`) and applies the rule on [`grid`].
pub fn measure_and_choose(env: &dyn lcrl_sim::Env, cs3: &Cs3Config, seeds: &[u64], on_sample: &(dyn Fn() + Sync)) -> Result<Choice, GraphError> {
    let pool = cs3::thread_pool(cs3.threads)?;
    let phis = pool.install(|| {
        seeds
            .iter()
            .map(|&seed| Ok(cs3::measure(env, &Cs3Config { seed, ..cs3.clone() }, on_sample)?.phi()))
            .collect::<Result<Vec<_>, GraphError>>()
    })?;
    Ok(choose(&phis, seeds, &grid()))
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
    /// The table `lcrl graph --choose-t` prints, and why T_rule is T_rule.
    pub fn text(&self, env: &str, samples: usize, action_names: &[String]) -> String {
        use std::fmt::Write as _;
        let mut out = String::new();
        let _ = writeln!(out, "Choosing T for {env}: CS3 with ST = {samples} on seeds {:?}; eq. 7 at each T.", self.seeds);
        let _ = writeln!(out, "\n{:>5}  {:>13}  {:>13}  {:>13}", "T", "edges (range)", "disagreement", "unseen states");
        for c in &self.candidates {
            let (lo, hi) = (c.edges.iter().min().copied().unwrap_or(0), c.edges.iter().max().copied().unwrap_or(0));
            let mark = if c.threshold == self.chosen { "  <- T_rule" } else { "" };
            let _ = writeln!(out, "{:>5}  {:>13}  {:>12.1}%  {:>13}{mark}", c.threshold, format!("{lo}–{hi}"), 100.0 * c.disagreement, c.unseen_states);
        }
        let rows: Vec<String> = action_names.iter().zip(&self.row_edges).map(|(a, k)| format!("{a} {k}")).collect();
        let _ = writeln!(out, "\nT_rule = {} (the publication's T = {}): {}.", self.chosen, crate::PAPER_THRESHOLD, self.reason);
        let _ = writeln!(out, "Inputs per action at T_rule (seed {}): {}.", self.seeds.first().copied().unwrap_or(0), rows.join(", "));
        let _ = writeln!(out, "Disagreement: the mean share of G's entries in which two seeds' graphs differ (information, not the rule).");
        out
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// Two actions, three states. Column 0 is [1.5, 0.5] (mean 1): at T = 1
    /// action 0 alone sees it. Column 1 is [1, 1]: both actions move it
    /// equally, so both keep it at T = 1 and neither at T = 1.1 (an unseen
    /// state). Column 2 is never moved. A second seed differs in column 0.
    #[test]
    fn the_rule_is_eq7_at_one_and_the_table_says_where_states_go_unseen() {
        let phis = vec![vec![vec![1.5, 1.0, 0.0], vec![0.5, 1.0, 0.0]], vec![vec![0.9, 1.0, 0.0], vec![1.1, 1.0, 0.0]]];
        let choice = choose(&phis, &[0, 1], &[0.5, 1.0, 1.1]);
        assert_eq!(choice.chosen, 1.0);
        assert_eq!(choice.row_edges, [2, 1]);
        let edges: Vec<Vec<usize>> = choice.candidates.iter().map(|c| c.edges.clone()).collect();
        assert_eq!(edges, [vec![4, 4], vec![3, 3], vec![1, 1]]);
        assert_eq!(choice.candidates.iter().map(|c| c.unseen_states).collect::<Vec<_>>(), [0, 0, 1]);
        // T = 1: seed 0 keeps (0, 0), seed 1 keeps (1, 0): 2 of 6 entries differ.
        assert!((choice.candidates[1].disagreement - 2.0 / 6.0).abs() < 1e-12);
        let text = choice.text("toy", 8, &["a".into(), "b".into()]);
        assert!(text.contains("T_rule = 1 (the publication's T = 0.1): the above-average rule"), "{text}");
        assert!(text.contains("Inputs per action at T_rule (seed 0): a 2, b 1."), "{text}");
        assert!(text.contains("33.3%"), "{text}");
    }

    /// Whatever phi is, T_rule leaves no moved state unseen: a column's
    /// largest value is at least its mean.
    #[test]
    fn no_moved_state_goes_unseen_at_t_rule() {
        use rand::{Rng, SeedableRng};
        let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(7);
        for _ in 0..200 {
            let (n, m) = (rng.random_range(1..8), rng.random_range(1..12));
            let phi: Vec<Vec<f64>> = (0..n).map(|_| (0..m).map(|_| if rng.random_bool(0.3) { 0.0 } else { rng.random::<f64>() }).collect()).collect();
            let g = connection_graph(&phi, Rule::Threshold(RULE_THRESHOLD)).g;
            assert_eq!(unseen_states(&phi, &g), 0, "{phi:?}");
        }
        // Ties: every action moves the state alike, and the rounded mean
        // (six 0.7s: 0.7000000000000001) lies above them.
        for (n, v) in [(6, 0.7), (32, 0.1), (3, 1.0 / 3.0)] {
            let phi = vec![vec![v]; n];
            let g = connection_graph(&phi, Rule::Threshold(RULE_THRESHOLD)).g;
            assert!(g.iter().all(|row| row[0] == 1), "{n} × {v}: {g:?}");
            assert_eq!(unseen_states(&phi, &g), 0);
        }
        assert_eq!(grid().first(), Some(&0.1));
        assert_eq!(grid().len(), 20);
    }
}
