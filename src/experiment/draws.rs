//! Where each graph sits among random graphs. A `random@K+per-seed` cell
//! trains every run on its own random draw of K edges, so its runs' eval
//! returns are a sample of what a random graph of that size yields; every
//! other graph cell of the same environment and algorithm is placed in it
//! by its mean eval return (the share of draws it beats). Descriptive: a
//! placement, not a test (the tests are the report's comparisons).

use std::fmt::Write as _;

use serde::Serialize;

use super::plan::Cell;
use crate::connection::ConnectionSpec;

/// One random-draw cell and the graph cells placed among its runs.
#[derive(Debug, Serialize)]
pub struct Placement {
    pub env: String,
    pub algo: String,
    /// The random cell's label, e.g. random@23+per-seed.
    pub random: String,
    /// The draws' eval returns, one per finished run, ascending.
    pub draws: Vec<f64>,
    pub placed: Vec<Placed>,
}

#[derive(Debug, Serialize)]
pub struct Placed {
    pub connection: String,
    pub runs: usize,
    pub mean_eval_return: f64,
    /// Share of the draws whose eval return is below this cell's mean.
    pub share_of_draws_below: f64,
}

/// Every per-seed random cell with at least two finished runs, and the
/// graph cells (measured, given, or a shared draw) beside it; `cells`
/// holds each cell with its finished runs' eval returns.
pub fn placements(cells: &[(&Cell, Vec<f64>)]) -> Vec<Placement> {
    let mut out = Vec::new();
    for (random, values) in cells.iter().filter(|(c, v)| matches!(c.connection, ConnectionSpec::Random { per_seed: true, .. }) && v.len() >= 2) {
        let mut draws = values.clone();
        draws.sort_by(f64::total_cmp);
        let placed = cells
            .iter()
            .filter(|(c, v)| c.env == random.env && c.algo == random.algo && c.connection.has_graph() && c != random && !v.is_empty())
            .map(|(c, values)| {
                let mean = values.iter().sum::<f64>() / values.len() as f64;
                Placed {
                    connection: c.connection.label(),
                    runs: values.len(),
                    mean_eval_return: mean,
                    share_of_draws_below: draws.iter().filter(|&&d| d < mean).count() as f64 / draws.len() as f64,
                }
            })
            .collect();
        out.push(Placement { env: random.env.clone(), algo: super::config::algo_name(random.algo).into(), random: random.connection.label(), draws, placed });
    }
    out
}

/// The report.md section.
pub fn markdown(placements: &[Placement]) -> String {
    let mut md = String::new();
    if placements.is_empty() {
        return md;
    }
    let _ = writeln!(md, "## Graphs among random draws\n");
    let _ = writeln!(md, "Each run of a `+per-seed` random cell trains on its own draw. A graph cell's mean eval return is placed among the draws' eval returns: the share of draws below it. Descriptive; the tests are the comparisons.\n");
    for p in placements {
        let (lo, hi) = (p.draws.first().copied().unwrap_or(f64::NAN), p.draws.last().copied().unwrap_or(f64::NAN));
        let n = p.draws.len();
        let median = if n % 2 == 1 { p.draws[n / 2] } else { (p.draws[n / 2 - 1] + p.draws[n / 2]) / 2.0 };
        let _ = writeln!(md, "**{} / {}**, {} draws of {}: eval return from {lo:.3} to {hi:.3}, median {median:.3}.\n", p.env, p.algo, p.draws.len(), p.random);
        let _ = writeln!(md, "| graph | runs | mean eval return | share of draws below |\n|---|---|---|---|");
        for c in &p.placed {
            let _ = writeln!(md, "| {} | {} | {:.3} | {:.0}% |", c.connection, c.runs, c.mean_eval_return, 100.0 * c.share_of_draws_below);
        }
        let _ = writeln!(md);
    }
    md
}

#[cfg(test)]
mod tests {
    use super::*;

    /// Four draws at −8, −6, −4, −2; a measured graph whose runs average −5
    /// beats two of them (50 %), and the section says so.
    #[test]
    fn a_graph_is_placed_among_the_draws_by_its_mean() {
        let cell = |connection: &str| Cell { env: "lti-paper".into(), algo: lcrl_learner::Algo::Ppo, connection: ConnectionSpec::parse(connection).unwrap() };
        let (local, random, global, shared) = (cell("local@0.1"), cell("random@4+per-seed"), cell("global"), cell("random@4"));
        let cells = vec![(&local, vec![-4.0, -6.0]), (&random, vec![-2.0, -8.0, -4.0, -6.0]), (&global, vec![-1.0]), (&shared, vec![-9.0])];
        let placements = placements(&cells);
        assert_eq!(placements.len(), 1);
        let p = &placements[0];
        assert_eq!((p.random.as_str(), p.draws.clone()), ("random@4+per-seed", vec![-8.0, -6.0, -4.0, -2.0]));
        // global has no graph: not placed; the shared draw is a graph.
        let placed: Vec<(&str, usize, f64, f64)> = p.placed.iter().map(|c| (c.connection.as_str(), c.runs, c.mean_eval_return, c.share_of_draws_below)).collect();
        assert_eq!(placed, [("local@0.1", 2, -5.0, 0.5), ("random@4", 1, -9.0, 0.0)]);
        let md = markdown(&placements);
        assert!(md.contains("4 draws of random@4+per-seed: eval return from -8.000 to -2.000, median -5.000"), "{md}");
        assert!(md.contains("| local@0.1 | 2 | -5.000 | 50% |"), "{md}");
    }
}
