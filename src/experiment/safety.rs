//! How safe a run's training was, beside the controller it acts around
//! (docs/experiment.md, "Training safety"): a real robot lives through
//! every training episode, not only the policy handed over at the end.
//!
//! Per run, from its metrics.csv: the training episodes that failed (did
//! not reach the depth within the limits), the worst 10-episode mean
//! return (the window of episodes to threshold), and the highest contact
//! force of any training episode. Per cell, the same over its seeds, with
//! the base controller's own figures on the evaluation starts: the best
//! constant for a residual run, a = 0 for a run from scratch.

use std::path::Path;

use lcrl_learner::run::files::EpisodeRow;
use serde::Serialize;

use super::bars::BestConstant;
use super::stats::{mean_ci, Estimate, AVERAGE_WINDOW};

/// One run's training safety.
#[derive(Debug, Clone, Copy, PartialEq, Serialize)]
pub struct RunSafety {
    /// Training episodes that did not succeed (peg tasks; 0 elsewhere).
    pub failed_episodes: usize,
    pub episodes: usize,
    /// The lowest mean return over 10 consecutive training episodes (over
    /// all of them when there are fewer).
    pub worst_mean_return: f64,
    /// The episode that ends that window (the first such window on a tie).
    pub worst_window_end: usize,
    /// The highest peak contact force of any training episode, N.
    pub peak_force_n: Option<f64>,
}

/// The safety figures of one run's episode rows (None without rows).
pub fn of_rows(rows: &[EpisodeRow]) -> Option<RunSafety> {
    if rows.is_empty() {
        return None;
    }
    let window = AVERAGE_WINDOW.min(rows.len());
    let (worst_window_end, worst_mean_return) = rows
        .windows(window)
        .map(|w| (w[w.len() - 1].episode, w.iter().map(|r| r.episode_return).sum::<f64>() / window as f64))
        .fold((0, f64::INFINITY), |worst, w| if w.1 < worst.1 { w } else { worst });
    let peak_force_n = rows.iter().filter_map(|r| r.peak_force_n).reduce(f64::max);
    Some(RunSafety {
        failed_episodes: rows.iter().filter(|r| r.success == Some(false)).count(),
        episodes: rows.len(),
        worst_mean_return,
        worst_window_end,
        peak_force_n,
    })
}

/// The controller a cell's runs act around, with its figures on the
/// evaluation starts (the study's best_constant.json).
#[derive(Debug, Clone, PartialEq, Serialize)]
pub struct BaseFigures {
    pub controller: String,
    pub mean_return: f64,
    pub success_rate: Option<f64>,
}

/// How far a recorded best constant may sit from the study's tuned one.
const RECORDED_ROUNDING: f64 = 0.005 + 1e-9;

/// The base of a run from its resolved config.toml (`[base] action`, a
/// list of numbers once resolved; `[controller] base` before the rename):
/// a = 0 (its return: the run's own `zero_action_return`, else the
/// study's) or the recorded best constant, with that controller's figures.
/// None without a base, or for a base that is neither.
pub fn base_of_run(run_dir: &Path, zero_action_return: Option<f64>, bar: Option<&BestConstant>) -> Option<BaseFigures> {
    let text = std::fs::read_to_string(run_dir.join("config.toml")).ok()?;
    let table: toml::Table = text.parse().ok()?;
    // `[base] action`, or `[controller] base` in runs written before the rename.
    let action = table.get("base").and_then(|b| b.get("action")).or_else(|| table.get("controller").and_then(|c| c.get("base")))?;
    let base: Vec<f64> = action.as_array()?.iter().map(|v| v.as_float().or_else(|| v.as_integer().map(|i| i as f64))).collect::<Option<_>>()?;
    if base.iter().all(|&b| b == 0.0) {
        let mean_return = zero_action_return.or(bar.map(|b| b.zero_action_return))?;
        return Some(BaseFigures { controller: "a = 0".into(), mean_return, success_rate: None });
    }
    let bar = bar?;
    // The presets' recorded best constants (`base = "best-constant"`,
    // lcrl_sim::peg::measured_best_constant) are `lcrl tune`'s, rounded to
    // two decimals, so the study's own tuning finds them to within 0.005.
    let same = base.len() == bar.action.len() && base.iter().zip(&bar.action).all(|(a, b)| (a - b).abs() <= RECORDED_ROUNDING);
    same.then(|| BaseFigures { controller: "best constant".into(), mean_return: bar.mean_return, success_rate: bar.success_rate })
}

/// A cell's training safety over its seeds.
#[derive(Debug, Clone, Serialize)]
pub struct CellSafety {
    pub failed_episodes: usize,
    pub episodes: usize,
    /// The worst 10-episode mean return: its mean over seeds, and the
    /// lowest of any seed.
    pub worst_mean_return: Option<Estimate>,
    pub lowest_mean_return: f64,
    /// The highest training contact force of any seed, N.
    pub peak_force_n: Option<f64>,
    /// The controller the runs act around, on the evaluation starts.
    pub base: Option<BaseFigures>,
    /// Seeds whose worst 10-episode mean fell below the base's return.
    pub below_base: Option<usize>,
}

/// Sums a cell's runs (None when none has rows).
pub fn of_cell(runs: &[RunSafety], base: Option<BaseFigures>) -> Option<CellSafety> {
    if runs.is_empty() {
        return None;
    }
    let worst: Vec<f64> = runs.iter().map(|r| r.worst_mean_return).collect();
    Some(CellSafety {
        failed_episodes: runs.iter().map(|r| r.failed_episodes).sum(),
        episodes: runs.iter().map(|r| r.episodes).sum(),
        worst_mean_return: mean_ci(&worst),
        lowest_mean_return: worst.iter().copied().fold(f64::INFINITY, f64::min),
        peak_force_n: runs.iter().filter_map(|r| r.peak_force_n).reduce(f64::max),
        below_base: base.as_ref().map(|b| worst.iter().filter(|&&w| w < b.mean_return).count()),
        base,
    })
}

#[cfg(test)]
mod tests {
    use super::*;

    fn row(episode: usize, episode_return: f64, success: bool, peak: f64) -> EpisodeRow {
        EpisodeRow {
            episode,
            episode_return,
            length: 50,
            success: Some(success),
            peak_force_n: Some(peak),
            peak_moment_nm: None,
            wall_s: None,
            optimization_s: None,
            terms: Default::default(),
        }
    }

    /// A hand-made run folder: 30 episodes at −3 with a dip of ten at −8
    /// (two of them failed, one pushing 40 N), and a config whose base is
    /// the best constant.
    #[test]
    fn safety_figures_of_a_hand_made_run() {
        let dir = tempfile::tempdir().unwrap();
        let rows: Vec<EpisodeRow> = (1..=30)
            .map(|k| {
                let dip = (11..=20).contains(&k);
                row(k, if dip { -8.0 } else { -3.0 }, !(dip && k % 5 == 0), if k == 15 { 40.0 } else { 12.0 })
            })
            .collect();
        let mut log = lcrl_learner::run::files::MetricsLog::create(&dir.path().join("metrics.csv"), &[]).unwrap();
        for r in &rows {
            log.push(r).unwrap();
        }
        let read = lcrl_learner::run::files::read_rows(&dir.path().join("metrics.csv"), usize::MAX).unwrap();
        let safety = of_rows(&read).unwrap();
        assert_eq!(safety, RunSafety { failed_episodes: 2, episodes: 30, worst_mean_return: -8.0, worst_window_end: 20, peak_force_n: Some(40.0) });

        let bar = BestConstant { action: vec![2.0, 2.0, 0.22], mean_return: -3.5, success_rate: Some(1.0), zero_action_return: -8.7, eval_episodes: 100, eval_seed: Some(1) };
        std::fs::write(dir.path().join("config.toml"), "[base]\naction = [2.0, 2.0, 0.22]\n").unwrap();
        let base = base_of_run(dir.path(), Some(-8.1), Some(&bar)).unwrap();
        assert_eq!((base.controller.as_str(), base.mean_return), ("best constant", -3.5));
        // A preset's recorded constant: the tuned one rounded to 2 decimals.
        let tuned = BestConstant { action: vec![2.0, 1.996, 0.2249], ..bar.clone() };
        assert_eq!(base_of_run(dir.path(), None, Some(&tuned)).map(|b| b.controller), Some("best constant".into()));
        let other_constant = BestConstant { action: vec![2.0, 1.98, 0.22], ..bar.clone() };
        assert_eq!(base_of_run(dir.path(), None, Some(&other_constant)), None, "a different constant is not the base");
        std::fs::write(dir.path().join("config.toml"), "[controller]\nbase = [0.0, 0, 0.0]\n").unwrap();
        assert_eq!(base_of_run(dir.path(), Some(-8.1), Some(&bar)).unwrap().mean_return, -8.1, "the run's own a = 0");
        assert_eq!(base_of_run(dir.path(), None, Some(&bar)).unwrap().mean_return, -8.7, "the study's a = 0");
        std::fs::write(dir.path().join("config.toml"), "[run]\nseed = 1\n").unwrap();
        assert_eq!(base_of_run(dir.path(), Some(-8.1), Some(&bar)), None, "no base, no base figures");

        let other = RunSafety { failed_episodes: 0, episodes: 30, worst_mean_return: -3.2, worst_window_end: 10, peak_force_n: Some(13.0) };
        let cell = of_cell(&[safety, other], Some(base)).unwrap();
        assert_eq!((cell.failed_episodes, cell.episodes, cell.lowest_mean_return, cell.peak_force_n), (2, 60, -8.0, Some(40.0)));
        assert_eq!(cell.below_base, Some(1), "only the dipping seed fell below the best constant's −3.5");
        assert!((cell.worst_mean_return.unwrap().mean - (-5.6)).abs() < 1e-12);
    }

    #[test]
    fn short_runs_use_every_episode() {
        let rows = vec![row(1, -4.0, true, 1.0), row(2, -2.0, true, 1.0)];
        assert_eq!((of_rows(&rows).unwrap().worst_mean_return, of_rows(&rows).unwrap().worst_window_end), (-3.0, 2));
        assert_eq!(of_rows(&[]), None);
    }
}
