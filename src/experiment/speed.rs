//! How fast a cell learns, in every report (docs/experiment.md, "Speed"):
//! the area under the first 100 episodes' learning curve (returns floored
//! at a = 0's) and the episodes until the 10-episode training mean reaches
//! the best constant, censored at the budget. Also every run's value of a
//! named metric, which the primary contrasts, equivalence tests and
//! factorials read.

use serde::Serialize;

use super::config::algo_name;
use super::inference::{auc, episodes_to_bar, km_median, log_rank, Time};
use super::study::{CellRuns, Comparison, Run, Study};
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

    /// The values of `metric` in that cell, one per unit: a run, or for a
    /// random-rows cell a draw (the mean of its runs), since runs of one
    /// draw share a graph.
    pub fn values(&self, env: &str, algo: lcrl_learner::Algo, label: &str, metric: &str) -> Vec<f64> {
        self.own_cell(env, algo, label).map_or_else(Vec::new, |c| self.unit_values(c, metric))
    }

    /// [`Study::values`] of a cell.
    pub fn unit_values(&self, c: &CellRuns, metric: &str) -> Vec<f64> {
        let of = |runs: &[&Run]| runs.iter().filter_map(|r| self.value(&c.cell.env, r, metric)).collect::<Vec<f64>>();
        match draws(c) {
            Some(draws) => draws.iter().filter_map(|runs| mean(&of(runs))).collect(),
            None => of(&c.runs.iter().collect::<Vec<_>>()),
        }
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
        out.extend(self.time_comparison(a, b));
        out
    }

    /// The episodes to the best constant of (a, b) by log-rank, one time
    /// per run (its difference is that of the mean episodes with censored
    /// runs counted as the budget, a lower bound of each mean).
    fn time_comparison(&self, a: &CellRuns, b: &CellRuns) -> Option<Comparison> {
        let env = &a.cell.env;
        let budget = self.experiment.episodes(a.cell.algo);
        let (ta, tb): (Vec<Time>, Vec<Time>) = (a.runs.iter().filter_map(|r| self.time(env, budget, r)).collect(), b.runs.iter().filter_map(|r| self.time(env, budget, r)).collect());
        let episodes = |t: &[Time]| t.iter().map(|t| t.episodes as f64).collect::<Vec<f64>>();
        let (lr, w) = (log_rank(&[(ta.clone(), tb.clone())])?, welch(&episodes(&ta), &episodes(&tb))?);
        let mut c = comparison(a, b, "episodes_to_best_constant", "log_rank", (ta.len(), tb.len()), (w.difference, w.ci95, lr.p_value));
        c.observed_minus_expected = Some(lr.observed_minus_expected);
        Some(c)
    }

    /// A pair with a random-rows cell, with the draw as that cell's unit
    /// (the means of its draws' runs; runs of one draw share a graph, so
    /// they are not independent evidence about graphs): final and eval
    /// return and the area under the curve, by Welch; and the log-rank of
    /// the episodes to the best constant only where every draw has one run
    /// (draw and run coincide, as edges-or-sparsity's design has it): a
    /// draw with several runs has no one time to the best constant.
    pub fn draw_comparisons(&self, a: &CellRuns, b: &CellRuns) -> Vec<Comparison> {
        let mut out = Vec::new();
        for metric in ["final_return", "eval_return", "auc_100"] {
            let (xa, xb) = (self.unit_values(a, metric), self.unit_values(b, metric));
            if let Some(w) = welch(&xa, &xb) {
                let mut c = comparison(a, b, metric, "welch_t_draw_means", (xa.len(), xb.len()), (w.difference, w.ci95, w.p_value));
                let side = |cell: &CellRuns| if draws(cell).is_some() { format!("{} (draw means)", cell.label()) } else { cell.label() };
                (c.a, c.b) = (side(a), side(b));
                out.push(c);
            }
        }
        let one_run_a_draw = |cell: &CellRuns| draws(cell).is_none_or(|groups| groups.iter().all(|runs| runs.len() == 1));
        if one_run_a_draw(a) && one_run_a_draw(b) {
            out.extend(self.time_comparison(a, b));
        }
        out
    }
}

fn mean(x: &[f64]) -> Option<f64> {
    (!x.is_empty()).then(|| x.iter().sum::<f64>() / x.len() as f64)
}

/// The runs of a random-rows cell grouped by draw (run seed mod draws);
/// None for any other cell.
fn draws(rows: &CellRuns) -> Option<Vec<Vec<&Run>>> {
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
        observed_minus_expected: None,
        primary: false,
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

#[cfg(test)]
mod tests {
    use super::super::config::Experiment;
    use super::super::plan::{cells, run_dir, Cell};
    use super::super::report::markdown;
    use super::super::study::fixtures::{write_best_constant, write_run};
    use super::super::study::gather;

    /// A study folder of `connections` on lti-paper (PPO, 20 episodes,
    /// seeds 0–3) whose best constant returns −5 and a = 0 −8.
    fn study(connections: &str) -> (Experiment, tempfile::TempDir) {
        let text = format!("name = \"s\"\nenvironments = [\"lti-paper\"]\nalgorithms = [\"ppo\"]\nconnections = [{connections}]\nseeds = [0, 1, 2, 3]\nepisodes = {{ ppo = 20 }}\n");
        let tmp = tempfile::tempdir().unwrap();
        write_best_constant(tmp.path(), "lti-paper", -5.0, -8.0);
        (Experiment::parse(&text).unwrap(), tmp)
    }

    /// One run of `cell` at `seed`: its summary (eval return `eval`) and
    /// its training returns.
    fn write_run_with_returns(out: &std::path::Path, cell: &Cell, seed: u64, eval: f64, returns: &[f64]) {
        let dir = run_dir(out, cell, seed);
        write_run(&dir, "local", seed, eval, Some(0), Some(-8.0));
        write_returns(&dir, returns);
    }

    /// A run's metrics.csv with these episode returns.
    fn write_returns(dir: &std::path::Path, returns: &[f64]) {
        let mut csv = String::from("episode,return,length,success,peak_force_n,peak_moment_nm,wall_s,optimization_s\n");
        for (k, r) in returns.iter().enumerate() {
            csv.push_str(&format!("{},{r},10,,,,,\n", k + 1));
        }
        std::fs::write(dir.join("metrics.csv"), csv).unwrap();
    }

    /// local gets to the best constant (−5) by episode 10 in every run,
    /// global never does; random rows run two draws on two seeds each and
    /// meet local@0.5 with the draw as the unit.
    #[test]
    fn speed_and_draw_level_comparisons_on_a_hand_made_study() {
        let (e, tmp) = study("\"local@0.5\", \"global\", \"random-rows@local@0.5+draws=2\"");
        let out = tmp.path();
        let [local, global, rows] = [0, 1, 2].map(|i| cells(&e)[i].clone());
        let local_eval = [-3.0, -3.2, -2.8, -3.1];
        // Draw 0 (seeds 0, 2) ends at −4 and −4.2, draw 1 (seeds 1, 3) at −5 and −5.4.
        let rows_eval = [-4.0, -5.0, -4.2, -5.4];
        for seed in 0..4u64 {
            let s = seed as usize;
            for (cell, eval, returns) in [
                (&local, local_eval[s], [-4.0; 20].to_vec()),
                (&global, -6.0 - 0.1 * seed as f64, [vec![-20.0; 5], vec![-7.0; 15]].concat()),
                (&rows, rows_eval[s], [-6.0; 20].to_vec()),
            ] {
                write_run_with_returns(out, cell, seed, eval, &returns);
            }
        }
        let report = gather(&e, out).unwrap().report();
        let speed = |i: usize| report.cells[i].speed.clone();
        assert_eq!((speed(0).median_to_best_constant, speed(0).reached_best_constant), (Some(10), 4));
        assert_eq!((speed(1).median_to_best_constant, speed(1).censored), (None, 4));
        // global's first 100 (here 20) floored at a = 0's −8: 5 × −8 + 15 × −7.
        assert!((speed(1).auc_100.unwrap().mean - (5.0 * -8.0 + 15.0 * -7.0) / 20.0).abs() < 1e-12);
        let find = |a: &str, b: &str, metric: &str| report.comparisons.iter().find(|c| c.a == a && c.b == b && c.metric == metric).unwrap_or_else(|| panic!("no {a} − {b} on {metric}"));
        let timed = find("local@0.5", "global", "episodes_to_best_constant");
        assert_eq!((timed.test, timed.difference), ("log_rank", 10.0 - 20.0));
        assert!(timed.p_value < 0.01, "{}", timed.p_value);
        assert_eq!(find("local@0.5", "global", "auc_100").test, "welch_t");
        // Draw level: two draw means (−4.1, −5.2) against four local runs.
        let draws = find("local@0.5", "random-rows@local@0.5+draws=2 (draw means)", "eval_return");
        assert_eq!((draws.test, draws.n_a, draws.n_b), ("welch_t_draw_means", 4, 2));
        assert!((draws.difference - (-3.025 - -4.65)).abs() < 1e-12, "{}", draws.difference);
        // Random rows are not compared with their graph run by run, nor
        // timed: each draw here has two runs.
        assert!(!report.comparisons.iter().any(|c| c.a == "local@0.5" && c.b == "random-rows@local@0.5+draws=2"));
        assert!(!report.comparisons.iter().any(|c| c.metric == "episodes_to_best_constant" && c.b.starts_with("random-rows")));
        let md = markdown(&report);
        assert!(md.contains("| 10 (4 of 4 reached) |") && md.contains("| not reached (0 of 4 reached) |"), "{md}");
        assert!(md.contains("welch_t_draw_means") && md.contains("log_rank"), "{md}");
    }

    /// With one run a draw (draw and run coincide) the random rows get a
    /// log-rank of their own; with two runs a draw (above) they do not.
    #[test]
    fn random_rows_with_one_run_a_draw_get_a_log_rank() {
        let (e, tmp) = study("\"local@0.5\", \"random-rows@local@0.5+draws=4\"");
        let out = tmp.path();
        let [local, rows] = [0, 1].map(|i| cells(&e)[i].clone());
        for seed in 0..4u64 {
            // local reaches −5 at episode 10 in every run, the rows never do.
            for (cell, returns) in [(&local, [-4.0; 20]), (&rows, [-6.0; 20])] {
                write_run_with_returns(out, cell, seed, -4.0, &returns);
            }
        }
        let report = gather(&e, out).unwrap().report();
        let timed = report.comparisons.iter().find(|c| c.metric == "episodes_to_best_constant").expect("a log-rank of local@0.5 against its random rows");
        assert_eq!((timed.a.as_str(), timed.b.as_str(), timed.test, timed.n_a, timed.n_b), ("local@0.5", "random-rows@local@0.5+draws=4", "log_rank", 4, 4));
        assert_eq!(timed.difference, 10.0 - 20.0);
        assert!(timed.p_value < 0.01, "{}", timed.p_value);
    }
}
