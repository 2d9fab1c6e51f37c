//! The bars a study's runs are measured against: the best constant
//! (best_constant/ENV/best_constant.json, `lcrl tune`) and the headroom
//! reference (best_policy/ENV/best_policy.json), as report.rs shows them
//! and safety.rs takes a run's base figures from them.

use std::path::Path;

use anyhow::Context;
use lcrl_learner::run::summary::RunSummary;
use serde::Serialize;

/// The figures of best_constant.json a report shows.
#[derive(Debug, Clone, Serialize)]
pub struct BestConstant {
    pub action: Vec<f64>,
    pub mean_return: f64,
    pub success_rate: Option<f64>,
    pub zero_action_return: f64,
    pub eval_episodes: usize,
    /// The first evaluation start (older files: absent).
    pub eval_seed: Option<u64>,
}

impl BestConstant {
    /// Whether a run was evaluated on exactly these starts, so their
    /// returns compare start for start.
    pub fn same_starts(&self, run: &RunSummary, eval_episodes: usize) -> bool {
        self.eval_seed.is_some() && run.evaluation.eval_seed == self.eval_seed && eval_episodes == self.eval_episodes
    }

    /// Reads a best_constant.json or best_policy.json (None when the file
    /// cannot be read; an error when it is not JSON).
    pub fn read(path: &Path) -> anyhow::Result<Option<BestConstant>> {
        let Ok(text) = std::fs::read_to_string(path) else { return Ok(None) };
        let v: serde_json::Value = serde_json::from_str(&text).with_context(|| format!("reading {}", path.display()))?;
        let action = v["action"].as_array().map(|a| a.iter().filter_map(|x| x.as_f64()).collect()).unwrap_or_default();
        Ok(Some(BestConstant {
            action,
            mean_return: v["mean_return"].as_f64().unwrap_or(f64::NAN),
            success_rate: v["success_rate"].as_f64(),
            zero_action_return: v["zero_action"]["eval"]["mean_return"].as_f64().unwrap_or(f64::NAN),
            eval_episodes: v["eval_episodes"].as_u64().unwrap_or(0) as usize,
            eval_seed: v["eval_seed"].as_u64(),
        }))
    }
}
