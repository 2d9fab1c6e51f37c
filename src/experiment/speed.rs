//! How fast a cell learns, in every report (docs/experiment.md, "Speed"):
//! the area under the first 100 episodes' learning curve (returns floored
//! at a = 0's) and the episodes until the 10-episode training mean reaches
//! the best constant, censored at the budget. Also every run's value of a
//! named metric, which the primary contrasts, equivalence tests and
//! factorials read.

use serde::Serialize;

use super::config::algo_name;
use super::inference::{auc, episodes_to_bar, km_median, log_rank, Time};
use super::report::{CellRuns, Comparison, Run, Study};
use super::stats::{mean_ci, welch, Estimate};

/// A cell's two speed measures.
#[derive(Debug, Clone, Serialize)]
pub struct CellSpeed {
    /// Mean return over the first 100 episodes, each floored at a = 0's.
    pub auc_100: Option<Estimate>,
    /// Kaplan–Meier median episodes until the 10-episode mean reaches the
    /// best constant (None: fewer than half got there).
    pub median_to_best_constant: Option<usize>,
    pub reached_best_constant: usize,
    pub censored: usize,
}

impl Study {
    /// a = 0's return on `env`: the floor of the area under the curve. The
    /// best constant's file where the study has one, else the run's own.
    fn floor(&self, env: &str, run: &Run) -> Option<f64> {
        self.best_constant.get(env).map(|b| b.zero_action_return).or(run.summary.evaluation.zero_action_return)
    }

    /// A run's value of a mean-difference metric (hypotheses::WELCH_METRICS).
    pub fn value(&self, env: &str, run: &Run, metric: &str) -> Option<f64> {
        match metric {
            "eval_return" => Some(run.summary.evaluation.eval_return),
            "final_return" => Some(run.summary.final_return),
            "auc_100" => auc(&run.returns, self.floor(env, run)?),
            _ => None,
        }
    }

    /// A run's episodes to the best constant of `env` (None: no best constant).
    pub fn time(&self, env: &str, budget: usize, run: &Run) -> Option<Time> {
        Some(episodes_to_bar(&run.returns, self.best_constant.get(env)?.mean_return, budget))
    }

    /// The study's own cell (not a companion's) of env, algorithm and label.
    pub fn own_cell(&self, env: &str, algo: lcrl_learner::Algo, label: &str) -> Option<&CellRuns> {
        self.cells.iter().find(|c| c.from.is_none() && c.cell.env == env && c.cell.algo == algo && c.cell.connection.label() == label)
    }

    /// Every finished run's value of `metric` in that cell.
    pub fn values(&self, env: &str, algo: lcrl_learner::Algo, label: &str, metric: &str) -> Vec<f64> {
        self.own_cell(env, algo, label).map_or_else(Vec::new, |c| c.runs.iter().filter_map(|r| self.value(env, r, metric)).collect())
    }

    /// Every finished run's time to the best constant in that cell.
    pub fn times(&self, env: &str, algo: lcrl_learner::Algo, label: &str) -> Vec<Time> {
        let budget = self.experiment.episodes(algo);
        self.own_cell(env, algo, label).map_or_else(Vec::new, |c| c.runs.iter().filter_map(|r| self.time(env, budget, r)).collect())
    }

    pub fn cell_speed(&self, c: &CellRuns) -> CellSpeed {
        let budget = self.experiment.episodes(c.cell.algo);
        let times: Vec<Time> = c.runs.iter().filter_map(|r| self.time(&c.cell.env, budget, r)).collect();
        let reached = times.iter().filter(|t| t.reached).count();
        CellSpeed {
            auc_100: mean_ci(&c.runs.iter().filter_map(|r| self.value(&c.cell.env, r, "auc_100")).collect::<Vec<_>>()),
            median_to_best_constant: km_median(&times),
            reached_best_constant: reached,
            censored: times.len() - reached,
        }
    }

    /// The speed comparisons of the pair (a, b) for the report's family:
    /// the area under the curve (Welch) and the episodes to the best
    /// constant (log-rank; its difference is that of the mean episodes with
    /// censored runs counted as the budget, a lower bound of each mean).
    pub fn speed_comparisons(&self, a: &CellRuns, b: &CellRuns) -> Vec<Comparison> {
        let env = &a.cell.env;
        let mut out = Vec::new();
        let (xa, xb): (Vec<f64>, Vec<f64>) = (a.runs.iter().filter_map(|r| self.value(env, r, "auc_100")).collect(), b.runs.iter().filter_map(|r| self.value(env, r, "auc_100")).collect());
        if let Some(w) = welch(&xa, &xb) {
            out.push(comparison(a, b, "auc_100", "welch_t", (xa.len(), xb.len()), (w.difference, w.ci95, w.p_value)));
        }
        let budget = self.experiment.episodes(a.cell.algo);
        let (ta, tb): (Vec<Time>, Vec<Time>) = (a.runs.iter().filter_map(|r| self.time(env, budget, r)).collect(), b.runs.iter().filter_map(|r| self.time(env, budget, r)).collect());
        let episodes = |t: &[Time]| t.iter().map(|t| t.episodes as f64).collect::<Vec<f64>>();
        if let (Some(lr), Some(w)) = (log_rank(&[(ta.clone(), tb.clone())]), welch(&episodes(&ta), &episodes(&tb))) {
            out.push(comparison(a, b, "episodes_to_best_constant", "log_rank", (ta.len(), tb.len()), (w.difference, w.ci95, lr.p_value)));
        }
        out
    }

    /// Random rows with the draw as the unit: a graph cell's runs against
    /// the means of the random-rows cell's draws (runs of one draw share
    /// its graph, so they are not independent evidence about graphs).
    pub fn draw_comparisons(&self, a: &CellRuns, rows: &CellRuns) -> Vec<Comparison> {
        let Some(draw_means) = draw_means(rows) else { return Vec::new() };
        let mut out = Vec::new();
        for metric in ["eval_return", "auc_100"] {
            let xa: Vec<f64> = a.runs.iter().filter_map(|r| self.value(&a.cell.env, r, metric)).collect();
            let xb: Vec<f64> = draw_means.iter().filter_map(|runs| mean(&runs.iter().filter_map(|r| self.value(&a.cell.env, r, metric)).collect::<Vec<_>>())).collect();
            if let Some(w) = welch(&xa, &xb) {
                let mut c = comparison(a, rows, metric, "welch_t_draw_means", (xa.len(), xb.len()), (w.difference, w.ci95, w.p_value));
                c.b = format!("{} (draw means)", rows.label());
                out.push(c);
            }
        }
        out
    }
}

fn mean(x: &[f64]) -> Option<f64> {
    (!x.is_empty()).then(|| x.iter().sum::<f64>() / x.len() as f64)
}

/// The runs of a random-rows cell grouped by draw (run seed mod draws).
fn draw_means(rows: &CellRuns) -> Option<Vec<Vec<&Run>>> {
    let crate::connection::ConnectionSpec::RandomRows { draws, .. } = &rows.cell.connection else { return None };
    let groups: Vec<Vec<&Run>> = (0..*draws).map(|d| rows.runs.iter().filter(|r| r.seed % draws == d).collect::<Vec<_>>()).filter(|g| !g.is_empty()).collect();
    Some(groups)
}

/// One comparison of the report's family; `estimate` is (difference, its
/// 95% CI, p), Holm's p filled in later.
fn comparison(a: &CellRuns, b: &CellRuns, metric: &'static str, test: &'static str, n: (usize, usize), estimate: (f64, [f64; 2], f64)) -> Comparison {
    let (difference, ci95, p_value) = estimate;
    Comparison {
        env: a.cell.env.clone(),
        algo: algo_name(a.cell.algo).into(),
        a: a.label(),
        b: b.label(),
        metric,
        n_a: n.0,
        n_b: n.1,
        difference,
        ci95,
        p_value,
        p_holm: f64::NAN,
        reading: String::new(),
        test,
    }
}

/// The report.md cell column: "AUC [CI]" and "median (k of n reached)".
pub fn columns(s: &CellSpeed) -> (String, String) {
    let auc = match &s.auc_100 {
        Some(Estimate { mean, ci95: Some([lo, hi]), .. }) => format!("{mean:.3} [{lo:.3}, {hi:.3}]"),
        Some(Estimate { mean, .. }) => format!("{mean:.3}"),
        None => "—".into(),
    };
    let n = s.reached_best_constant + s.censored;
    let to = if n == 0 {
        "—".into()
    } else {
        format!("{} ({} of {n} reached)", s.median_to_best_constant.map_or("not reached".into(), |m| m.to_string()), s.reached_best_constant)
    };
    (auc, to)
}
