//! `lcrl experiment report`: gathers the finished runs of a study and
//! writes report.json (cells, comparisons) and report.md (the same as
//! tables), with the best constant controller beside every cell.

use std::collections::BTreeMap;
use std::fmt::Write as _;
use std::path::{Path, PathBuf};

use anyhow::Context;
use lcrl_learner::run_files::{EpisodeRow, TrainSummary};
use serde::Serialize;

use super::config::{algo_name, Experiment};
use super::plan::{best_constant_path, cells, finished_run, graph_path, run_dir, Cell};
use super::stats::{censored_estimate, episodes_to_threshold, mean_ci, welch, Estimate, ThresholdEstimate, AVERAGE_WINDOW};
use crate::output::write_atomic;

/// A finished training run.
pub struct Run {
    pub seed: u64,
    pub dir: PathBuf,
    pub summary: TrainSummary,
    /// Episode returns in order (metrics.csv).
    pub returns: Vec<f64>,
}

/// A cell with its finished runs.
pub struct CellRuns {
    pub cell: Cell,
    pub runs: Vec<Run>,
    pub graph_seconds: f64,
}

impl CellRuns {
    /// The run whose evaluation return is the median (the lower one of the
    /// middle two for an even count), as the publication's traces show a
    /// typical agent.
    pub fn median_run(&self) -> Option<&Run> {
        let mut order: Vec<&Run> = self.runs.iter().collect();
        order.sort_by(|a, b| a.summary.eval_return.total_cmp(&b.summary.eval_return));
        order.get(order.len().saturating_sub(1) / 2).copied()
    }
}

/// The figures of best_constant.json a report shows.
#[derive(Debug, Clone, Serialize)]
pub struct BestConstant {
    pub action: Vec<f64>,
    pub mean_return: f64,
    pub success_rate: Option<f64>,
    pub zero_action_return: f64,
    pub eval_episodes: usize,
}

/// Everything a report and its figures are drawn from.
pub struct Study {
    pub experiment: Experiment,
    pub cells: Vec<CellRuns>,
    pub best_constant: BTreeMap<String, BestConstant>,
    /// The headroom reference per environment: best_policy/ENV/best_policy.json
    /// (`lcrl tune --policy affine --out OUT/best_policy/ENV`), where present.
    pub best_policy: BTreeMap<String, BestConstant>,
    pub missing: Vec<String>,
}

/// Reads every finished run, graph and best constant under `out`.
pub fn gather(e: &Experiment, out: &Path) -> anyhow::Result<Study> {
    let mut study = Study { experiment: e.clone(), cells: Vec::new(), best_constant: BTreeMap::new(), best_policy: BTreeMap::new(), missing: Vec::new() };
    for cell in cells(e) {
        let graph_seconds = match cell.connection.threshold() {
            Some(t) => graph_seconds(&graph_path(out, &cell.env, t))?,
            None => 0.0,
        };
        let mut runs = Vec::new();
        for &seed in &e.seeds {
            let dir = run_dir(out, &cell, seed);
            match finished_run(&dir) {
                Some(summary) => {
                    let returns = read_returns(&dir.join("metrics.csv"))?;
                    runs.push(Run { seed, dir, summary, returns });
                }
                None => study.missing.push(format!("{} seed {seed}", cell.label())),
            }
        }
        study.cells.push(CellRuns { cell, runs, graph_seconds });
    }
    for env in &e.file.environments {
        let policy_path = out.join("best_policy").join(super::config::env_slug(env)).join("best_policy.json");
        for (path, map) in [(best_constant_path(out, env), &mut study.best_constant), (policy_path, &mut study.best_policy)] {
            if let Ok(text) = std::fs::read_to_string(&path) {
                let v: serde_json::Value = serde_json::from_str(&text).with_context(|| format!("reading {}", path.display()))?;
                let action = v["action"].as_array().map(|a| a.iter().filter_map(|x| x.as_f64()).collect()).unwrap_or_default();
                map.insert(env.clone(), BestConstant {
                    action,
                    mean_return: v["mean_return"].as_f64().unwrap_or(f64::NAN),
                    success_rate: v["success_rate"].as_f64(),
                    zero_action_return: v["zero_action"]["eval"]["mean_return"].as_f64().unwrap_or(f64::NAN),
                    eval_episodes: v["eval_episodes"].as_u64().unwrap_or(0) as usize,
                });
            }
        }
    }
    Ok(study)
}

fn graph_seconds(path: &Path) -> anyhow::Result<f64> {
    let Ok(text) = std::fs::read_to_string(path) else { return Ok(0.0) };
    let v: serde_json::Value = serde_json::from_str(&text).with_context(|| format!("reading {}", path.display()))?;
    Ok(v["elapsed_s"].as_f64().unwrap_or(0.0))
}

fn read_returns(path: &Path) -> anyhow::Result<Vec<f64>> {
    let mut reader = csv::Reader::from_path(path).with_context(|| format!("reading {}", path.display()))?;
    reader
        .deserialize::<EpisodeRow>()
        .map(|row| row.map(|r| r.episode_return).with_context(|| format!("reading {}", path.display())))
        .collect()
}

/// report.json.
#[derive(Debug, Serialize)]
pub struct Report {
    pub experiment: String,
    pub methods: Methods,
    pub best_constant: BTreeMap<String, BestConstant>,
    pub best_policy: BTreeMap<String, BestConstant>,
    pub cells: Vec<CellReport>,
    pub comparisons: Vec<Comparison>,
    /// Runs not finished (yet): their cells report the seeds that are.
    pub missing_runs: Vec<String>,
}

#[derive(Debug, Serialize)]
pub struct Methods {
    pub confidence_interval: &'static str,
    pub test: &'static str,
    pub why_this_test: &'static str,
    pub final_return: &'static str,
    pub episodes_to_threshold: &'static str,
    pub times: &'static str,
}

const METHODS: Methods = Methods {
    confidence_interval: "two-sided 95% Student-t interval of the mean over seeds (n − 1 degrees of freedom)",
    test: "Welch's two-sample t-test, two-sided; difference = mean(a) − mean(b) with its Welch 95% interval",
    why_this_test: "it gives the p-value and the interval of the difference from one model, does not assume the two \
                    connections spread equally across seeds, and works with a handful of seeds; it assumes roughly \
                    normal means, so a single diverged seed (see per_seed) weakens it",
    final_return: "mean return of the last 10 training episodes; eval_return: the deterministic policy after training",
    episodes_to_threshold: "the first episode whose 10-episode mean return reaches the threshold; runs that never do are \
                            censored: they count as the budget, so with any censored run the mean is a lower bound",
    times: "graph_seconds: the cell's graph, built once and shared by its seeds (counted once, as Table II does); \
            optimization_seconds: network updates; total_seconds: graph + the run's wall time",
};

#[derive(Debug, Serialize)]
pub struct CellReport {
    pub env: String,
    pub algo: String,
    pub connection: String,
    pub episodes: usize,
    pub seeds: Vec<u64>,
    pub final_return: Option<Estimate>,
    pub eval_return: Option<Estimate>,
    pub eval_success_rate: Option<f64>,
    pub episodes_to_threshold: Option<ThresholdEstimate>,
    pub graph_seconds: f64,
    pub optimization_seconds: Option<Estimate>,
    pub total_seconds: Option<Estimate>,
    pub per_seed: Vec<SeedFigures>,
}

#[derive(Debug, Serialize)]
pub struct SeedFigures {
    pub seed: u64,
    pub final_return: f64,
    pub eval_return: f64,
    pub episodes_to_threshold: Option<usize>,
}

#[derive(Debug, Serialize)]
pub struct Comparison {
    pub env: String,
    pub algo: String,
    pub a: String,
    pub b: String,
    pub metric: &'static str,
    pub n_a: usize,
    pub n_b: usize,
    pub difference: f64,
    pub ci95: [f64; 2],
    pub p_value: f64,
    pub test: &'static str,
}

impl Study {
    pub fn report(&self) -> Report {
        let e = &self.experiment;
        let mut cells = Vec::new();
        for c in &self.cells {
            let threshold = e.reward_threshold(&c.cell.env, c.cell.algo);
            let budget = e.episodes(c.cell.algo);
            let reached: Vec<Option<usize>> =
                c.runs.iter().map(|r| threshold.and_then(|t| episodes_to_threshold(&r.returns, t, AVERAGE_WINDOW))).collect();
            let of = |f: &dyn Fn(&Run) -> f64| mean_ci(&c.runs.iter().map(f).collect::<Vec<_>>());
            let success: Vec<f64> = c.runs.iter().filter_map(|r| r.summary.eval_success_rate).collect();
            cells.push(CellReport {
                env: c.cell.env.clone(),
                algo: algo_name(c.cell.algo).into(),
                connection: c.cell.connection.label(),
                episodes: budget,
                seeds: c.runs.iter().map(|r| r.seed).collect(),
                final_return: of(&|r| r.summary.final_return),
                eval_return: of(&|r| r.summary.eval_return),
                eval_success_rate: (!success.is_empty()).then(|| success.iter().sum::<f64>() / success.len() as f64),
                episodes_to_threshold: threshold.and_then(|t| censored_estimate(&reached, t, budget)),
                graph_seconds: c.graph_seconds,
                optimization_seconds: of(&|r| r.summary.optimization_seconds),
                total_seconds: of(&|r| c.graph_seconds + r.summary.total_seconds),
                per_seed: c
                    .runs
                    .iter()
                    .zip(&reached)
                    .map(|(r, k)| SeedFigures { seed: r.seed, final_return: r.summary.final_return, eval_return: r.summary.eval_return, episodes_to_threshold: *k })
                    .collect(),
            });
        }
        Report {
            experiment: e.file.name.clone(),
            methods: METHODS,
            best_constant: self.best_constant.clone(),
            best_policy: self.best_policy.clone(),
            comparisons: self.comparisons(),
            cells,
            missing_runs: self.missing.clone(),
        }
    }

    /// Per environment and algorithm: each local connection against global
    /// and against full-subnets, on final and evaluation return.
    fn comparisons(&self) -> Vec<Comparison> {
        let mut out = Vec::new();
        for a in self.cells.iter().filter(|c| c.cell.connection.threshold().is_some()) {
            for b in self.cells.iter().filter(|b| b.cell.env == a.cell.env && b.cell.algo == a.cell.algo && b.cell.connection.threshold().is_none()) {
                let metrics: [(&'static str, fn(&Run) -> f64); 2] = [("final_return", |r| r.summary.final_return), ("eval_return", |r| r.summary.eval_return)];
                for (metric, f) in metrics {
                    let (xa, xb): (Vec<f64>, Vec<f64>) = (a.runs.iter().map(f).collect(), b.runs.iter().map(f).collect());
                    if let Some(w) = welch(&xa, &xb) {
                        out.push(Comparison {
                            env: a.cell.env.clone(),
                            algo: algo_name(a.cell.algo).into(),
                            a: a.cell.connection.label(),
                            b: b.cell.connection.label(),
                            metric,
                            n_a: xa.len(),
                            n_b: xb.len(),
                            difference: w.difference,
                            ci95: w.ci95,
                            p_value: w.p_value,
                            test: "welch_t",
                        });
                    }
                }
            }
        }
        out
    }
}

/// Three decimals, as every number in report.md.
pub fn num(x: f64) -> String {
    format!("{x:.3}")
}

fn estimate(e: &Option<Estimate>) -> String {
    match e {
        Some(Estimate { mean, ci95: Some([lo, hi]), .. }) => format!("{} [{}, {}]", num(*mean), num(*lo), num(*hi)),
        Some(Estimate { mean, .. }) => num(*mean),
        None => "—".into(),
    }
}

/// report.md: one table per environment and algorithm, then comparisons.
pub fn markdown(report: &Report) -> String {
    let mut md = String::new();
    let _ = writeln!(md, "# Experiment `{}`\n", report.experiment);
    let m = &report.methods;
    let _ = writeln!(md, "Intervals: {}. Test: {} ({}).\n", m.confidence_interval, m.test, m.why_this_test);
    let _ = writeln!(md, "Final return: {}. Episodes to threshold: {}. Times: {}.\n", m.final_return, m.episodes_to_threshold, m.times);
    if !report.missing_runs.is_empty() {
        let _ = writeln!(md, "**Not finished ({}):** {}\n", report.missing_runs.len(), report.missing_runs.join(", "));
    }
    let mut groups: Vec<(&str, &str)> = Vec::new();
    for c in &report.cells {
        if !groups.contains(&(c.env.as_str(), c.algo.as_str())) {
            groups.push((&c.env, &c.algo));
        }
    }
    for (env, algo) in groups {
        let rows: Vec<&CellReport> = report.cells.iter().filter(|c| c.env == env && c.algo == algo).collect();
        let threshold = rows.iter().find_map(|c| c.episodes_to_threshold.as_ref().map(|t| t.threshold));
        let _ = writeln!(md, "## {env}, {} ({} episodes)\n", algo.to_uppercase(), rows[0].episodes);
        let to = threshold.map_or("episodes to threshold".to_string(), |t| format!("episodes to {}", num(t)));
        let _ = writeln!(md, "| connection | seeds | final return | eval return | success | {to} | graph s | optimization s | total s |");
        let _ = writeln!(md, "|---|---|---|---|---|---|---|---|---|");
        for c in &rows {
            let success = c.eval_success_rate.map_or("—".into(), |r| format!("{:.0}%", 100.0 * r));
            let reach = c.episodes_to_threshold.as_ref().map_or("—".into(), |t| {
                let ci = t.ci95.map_or(String::new(), |[lo, hi]| format!(" [{}, {}]", num(lo), num(hi)));
                format!("{}{ci} ({} of {} censored)", num(t.mean), t.censored, t.reached + t.censored)
            });
            let _ = writeln!(
                md,
                "| {} | {} | {} | {} | {success} | {reach} | {} | {} | {} |",
                c.connection,
                c.seeds.len(),
                estimate(&c.final_return),
                estimate(&c.eval_return),
                num(c.graph_seconds),
                estimate(&c.optimization_seconds),
                estimate(&c.total_seconds)
            );
        }
        if let Some(b) = report.best_constant.get(env) {
            let success = b.success_rate.map_or("—".into(), |r| format!("{:.0}%", 100.0 * r));
            let _ = writeln!(md, "| best constant | — | — | {} | {success} | — | — | — | — |", num(b.mean_return));
            let _ = writeln!(md, "| a = 0 | — | — | {} | — | — | — | — | — |", num(b.zero_action_return));
        }
        if let Some(p) = report.best_policy.get(env) {
            let success = p.success_rate.map_or("—".into(), |r| format!("{:.0}%", 100.0 * r));
            let _ = writeln!(md, "| best feedback policy (headroom) | — | — | {} | {success} | — | — | — | — |", num(p.mean_return));
        }
        let _ = writeln!(md);
        for c in &rows {
            let seeds: Vec<String> = c.per_seed.iter().map(|s| format!("{}: {} / {}", s.seed, num(s.final_return), num(s.eval_return))).collect();
            let _ = writeln!(md, "- {} per seed (final / eval): {}", c.connection, seeds.join("; "));
        }
        if let Some(b) = report.best_constant.get(env) {
            let _ = writeln!(md, "- best constant on {} evaluation episodes, action {:?}", b.eval_episodes, b.action.iter().map(|a| num(*a)).collect::<Vec<_>>());
        }
        let comparisons: Vec<&Comparison> = report.comparisons.iter().filter(|c| c.env == env && c.algo == algo).collect();
        if !comparisons.is_empty() {
            let _ = writeln!(md, "\n| comparison | metric | difference | 95% CI | p (Welch) |");
            let _ = writeln!(md, "|---|---|---|---|---|");
            for c in comparisons {
                let _ = writeln!(md, "| {} − {} | {} | {} | [{}, {}] | {:.4} |", c.a, c.b, c.metric, num(c.difference), num(c.ci95[0]), num(c.ci95[1]), c.p_value);
            }
        }
        let _ = writeln!(md);
    }
    md
}

/// Writes report.json and report.md into `out`.
pub fn write(report: &Report, out: &Path) -> anyhow::Result<()> {
    write_atomic(&out.join("report.json"), &(serde_json::to_string_pretty(report)? + "\n"))?;
    write_atomic(&out.join("report.md"), &markdown(report))
}
