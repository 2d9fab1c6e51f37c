//! A study's finished runs as read from its folder: every cell with its
//! runs, the best constants and headroom references, the companions that
//! joined, and the comparison row every test of a report fills. The report
//! (crate::experiment::report) and the tests it prints (::primary,
//! ::named, ::speed) read this; it reads none of them.

use std::collections::BTreeMap;
use std::path::{Path, PathBuf};

use anyhow::Context;
use lcrl_learner::run::files::EpisodeRow;
use lcrl_learner::run::summary::RunSummary;
use serde::Serialize;

use super::bars::BestConstant;
use super::config::Experiment;
use super::plan::{best_constant_path, cell_graph, cells, finished_run, run_dir, Cell};
use super::safety::{self, RunSafety};

/// A finished training run.
pub struct Run {
    pub seed: u64,
    pub dir: PathBuf,
    pub summary: RunSummary,
    /// Episode returns in order (metrics.csv).
    pub returns: Vec<f64>,
    /// Training safety (metrics.csv).
    pub safety: Option<RunSafety>,
}

/// A cell with its finished runs.
pub struct CellRuns {
    pub cell: Cell,
    pub runs: Vec<Run>,
    pub graph_seconds: f64,
    /// The companion study the cell comes from (`report --with`); None for
    /// the study's own cells.
    pub from: Option<String>,
}

impl CellRuns {
    /// The connection's label, with the companion study's name after it
    /// (`global [lti-blocks-32-global-lr3e-4]`).
    pub fn label(&self) -> String {
        match &self.from {
            Some(study) => format!("{} [{study}]", self.cell.connection.label()),
            None => self.cell.connection.label(),
        }
    }

    /// The run whose evaluation return is the median (the lower one of the
    /// middle two for an even count), as the publication's traces show a
    /// typical agent.
    pub fn median_run(&self) -> Option<&Run> {
        let mut order: Vec<&Run> = self.runs.iter().collect();
        order.sort_by(|a, b| a.summary.evaluation.eval_return.total_cmp(&b.summary.evaluation.eval_return));
        order.get(order.len().saturating_sub(1) / 2).copied()
    }
}

/// A companion study in a report (`--with`, src/experiment/companion.rs):
/// its name, its folder, and every setting of its study file that is not
/// this study's (besides the cells it runs: name, environments,
/// algorithms, connections, seeds, primary), so that a reader sees what
/// changed.
#[derive(Debug, Clone, Serialize)]
pub struct Companion {
    pub name: String,
    pub dir: String,
    pub differs: Vec<String>,
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
    /// The companion studies whose cells joined (`--with`).
    pub companions: Vec<Companion>,
}

/// Reads every finished run, graph and best constant under `out`.
pub fn gather(e: &Experiment, out: &Path) -> anyhow::Result<Study> {
    let mut study =
        Study { experiment: e.clone(), cells: Vec::new(), best_constant: BTreeMap::new(), best_policy: BTreeMap::new(), missing: Vec::new(), companions: Vec::new() };
    for cell in cells(e) {
        // Measured graphs only: a given one cost no rollouts.
        // (per run, the mean over its seeds' own graphs with +per-seed)
        let graph_seconds = match cell.connection.threshold() {
            Some(_) => {
                let times = e.seeds_for(&cell.connection).iter().filter_map(|&seed| cell_graph(out, &cell, seed)).map(|p| graph_seconds(&p)).collect::<anyhow::Result<Vec<f64>>>()?;
                times.iter().sum::<f64>() / times.len().max(1) as f64
            }
            None => 0.0,
        };
        let mut runs = Vec::new();
        for seed in e.seeds_for(&cell.connection) {
            let dir = run_dir(out, &cell, seed);
            match finished_run(&dir) {
                Some(summary) => {
                    let rows = read_rows(&dir.join("metrics.csv"))?;
                    let returns = rows.iter().map(|r| r.episode_return).collect();
                    runs.push(Run { seed, dir, summary, returns, safety: safety::of_rows(&rows) });
                }
                None => study.missing.push(format!("{} seed {seed}", cell.label())),
            }
        }
        study.cells.push(CellRuns { cell, runs, graph_seconds, from: None });
    }
    for env in &e.file.environments {
        let policy_path = out.join("best_policy").join(super::config::env_slug(env)).join("best_policy.json");
        for (path, map) in [(best_constant_path(out, env), &mut study.best_constant), (policy_path, &mut study.best_policy)] {
            if let Some(bar) = BestConstant::read(&path)? {
                map.insert(env.clone(), bar);
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

fn read_rows(path: &Path) -> anyhow::Result<Vec<EpisodeRow>> {
    let mut reader = csv::Reader::from_path(path).with_context(|| format!("reading {}", path.display()))?;
    reader.deserialize::<EpisodeRow>().map(|row| row.with_context(|| format!("reading {}", path.display()))).collect()
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
    /// Holm-adjusted over every comparison of the report.
    pub p_holm: f64,
    /// The interval in words (stats::reading); for a log-rank row, the
    /// test's verdict in words (its interval is descriptive).
    pub reading: String,
    pub test: &'static str,
    /// Log-rank rows: a's events minus their expectation (positive: a
    /// gets there sooner).
    #[serde(skip_serializing_if = "Option::is_none")]
    pub observed_minus_expected: Option<f64>,
    /// A primary contrast's own pair and metric in one environment: shown
    /// for the record, left out of the secondary family (tested above).
    #[serde(skip_serializing_if = "std::ops::Not::not")]
    pub primary: bool,
}

/// Hand-made study folders for the tests of the report and its neighbours.
#[cfg(test)]
pub(super) mod fixtures {
    use std::path::Path;

    use serde_json::json;

    /// A best_constant.json of `env` under `out`: the best constant's and
    /// a = 0's mean returns on 100 evaluation starts from seed 0.
    pub fn write_best_constant(out: &Path, env: &str, mean_return: f64, zero: f64) {
        let bar = json!({ "action": [0.0], "mean_return": mean_return, "success_rate": null, "eval_episodes": 100, "eval_seed": 0,
                          "zero_action": { "eval": { "mean_return": zero } } });
        let path = crate::experiment::plan::best_constant_path(out, env);
        std::fs::create_dir_all(path.parent().unwrap()).unwrap();
        std::fs::write(&path, bar.to_string()).unwrap();
    }

    /// A finished run written by hand: summary.json and a two-row metrics.csv.
    pub fn write_run(dir: &Path, connection: &str, seed: u64, eval_return: f64, eval_seed: Option<u64>, zero: Option<f64>) {
        std::fs::create_dir_all(dir).unwrap();
        let summary = json!({
            "env": "lti-paper", "algo": "ppo", "connection": connection, "seed": seed, "episodes": 2,
            "final_return": eval_return, "eval_return": eval_return, "eval_seed": eval_seed,
            "zero_action_return": zero, "lqr_return": null, "masked_lqr_return": null,
            "graph_seconds": 0.0, "optimization_seconds": 1.0, "total_seconds": 2.0, "env_steps": 20, "updates": 2,
            "actor_params": 10, "critic_params": 10
        });
        std::fs::write(dir.join("summary.json"), summary.to_string()).unwrap();
        let csv = "episode,return,length,success,peak_force_n,peak_moment_nm,wall_s,optimization_s\n1,-9,10,,,,,\n2,-8,10,,,,,\n";
        std::fs::write(dir.join("metrics.csv"), csv).unwrap();
    }
}
