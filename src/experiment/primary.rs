//! A study's primary contrast: the one comparison its file names before
//! any run (`[primary]`), so that the result it reports first was not
//! picked after seeing the data. It is tested on its own, stratified by
//! environment; every other comparison a report prints is secondary and
//! carries Holm's adjustment over all of them (docs/experiment.md).

use anyhow::bail;
use lcrl_learner::Algo;
use serde::{Deserialize, Serialize};

use super::config::{algo_name, ConnectionSpec, ExperimentFile};
use super::report::Study;
use super::stats::{reading, stratified, welch, Stratified, Welch};

/// `[primary]` of an experiment file, e.g.
/// `metric = "eval_return"`, `a = "local@1"`, `b = "global"`,
/// `algorithm = "ddpg"` (strata: every environment, or `environments`).
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct PrimaryContrast {
    /// `eval_return` or `final_return`.
    pub metric: String,
    /// The connections compared, a − b, as `connections` writes them.
    pub a: String,
    pub b: String,
    pub algorithm: Algo,
    /// The strata; every environment of the study when left out.
    #[serde(default)]
    pub environments: Vec<String>,
}

/// The metrics a contrast may name.
const METRICS: [&str; 2] = ["eval_return", "final_return"];

impl PrimaryContrast {
    /// Checked with the file, before a single run.
    pub fn check(&self, file: &ExperimentFile) -> anyhow::Result<()> {
        if !METRICS.contains(&self.metric.as_str()) {
            bail!("`primary.metric` \"{}\" must be one of {}", self.metric, METRICS.join(", "));
        }
        let labels: Vec<String> = file.connections.iter().filter_map(|c| ConnectionSpec::parse(c).ok()).map(|c| c.label()).collect();
        for (key, connection) in [("a", &self.a), ("b", &self.b)] {
            let label = ConnectionSpec::parse(connection)?.label();
            if !labels.contains(&label) {
                bail!("`primary.{key}` \"{connection}\" is not one of `connections` ({})", labels.join(", "));
            }
        }
        if self.a == self.b {
            bail!("`primary.a` and `primary.b` are the same connection");
        }
        if !file.algorithms.contains(&self.algorithm) {
            bail!("`primary.algorithm` {} is not one of `algorithms`", algo_name(self.algorithm));
        }
        if let Some(env) = self.environments.iter().find(|e| !file.environments.contains(e)) {
            bail!("`primary.environments`: {env} is not one of `environments`");
        }
        Ok(())
    }

    /// In words, as a report's heading gives it.
    pub fn describe(&self, environments: &[String]) -> String {
        format!("{}, {} − {}, {}, stratified by environment over {}", self.metric, self.a, self.b, algo_name(self.algorithm).to_uppercase(), environments.join(", "))
    }
}

/// The primary contrast's result: each environment's Welch difference and
/// their inverse-variance combination.
#[derive(Debug, Serialize)]
pub struct PrimaryResult {
    pub contrast: PrimaryContrast,
    pub description: String,
    pub per_environment: Vec<(String, Welch)>,
    pub combined: Option<Stratified>,
    /// The combined interval in words.
    pub reading: String,
}

/// The contrast on the study's finished runs.
pub fn evaluate(study: &Study, contrast: &PrimaryContrast) -> PrimaryResult {
    let file = &study.experiment.file;
    let environments = if contrast.environments.is_empty() { file.environments.clone() } else { contrast.environments.clone() };
    let label = |c: &str| ConnectionSpec::parse(c).map(|c| c.label()).unwrap_or_default();
    let (a, b) = (label(&contrast.a), label(&contrast.b));
    let values = |env: &str, connection: &str| -> Vec<f64> {
        study
            .cells
            .iter()
            .filter(|c| c.cell.env == env && c.cell.algo == contrast.algorithm && c.cell.connection.label() == connection)
            .flat_map(|c| &c.runs)
            .map(|r| if contrast.metric == "final_return" { r.summary.final_return } else { r.summary.evaluation.eval_return })
            .collect()
    };
    let per_environment: Vec<(String, Welch)> = environments.iter().filter_map(|env| Some((env.clone(), welch(&values(env, &a), &values(env, &b))?))).collect();
    // One stratum: its own Welch test (t, not the normal approximation).
    let combined = match per_environment.as_slice() {
        [(_, w)] => Some(Stratified { difference: w.difference, ci95: w.ci95, p_value: w.p_value, strata: 1 }),
        _ => stratified(&per_environment.iter().map(|(_, w)| (w.difference, w.se)).collect::<Vec<_>>()),
    };
    let reading = combined.as_ref().map_or("no result: too few finished runs".into(), |c| reading(&a, &b, c.ci95));
    PrimaryResult { contrast: contrast.clone(), description: contrast.describe(&environments), per_environment, combined, reading }
}
