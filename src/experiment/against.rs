//! `lcrl experiment report DIR --against REF`: a study's runs seed for seed
//! against another study's on the same environment and algorithm
//! (docs/experiment.md, "Against a reference study").
//!
//! The reference it was made for is the base held still under the
//! learner's own exploration (experiments/research/peg-group2-bar-base-exploring.toml):
//! no learner that explores can keep its training curve nearer its base
//! than the base itself exploring does, so a training run is held to that
//! run's worst 10-episode window on the same seed (the same warm-up and the
//! same noise) minus a margin. Against any other study (one change of a
//! setting, on the same seeds) the same figures are a paired comparison.

use std::fmt::Write as _;
use std::path::Path;

use serde::Serialize;

use super::report::{num, CellRuns, Run, Study};
use super::safety::RunSafety;
use super::stats::{mean_ci, one_sample_t, Estimate};

/// One seed of a cell beside the same seed of the reference.
#[derive(Debug, Clone, PartialEq, Serialize)]
pub struct SeedAgainst {
    pub seed: u64,
    /// This run's training safety (worst window and the episode ending it,
    /// failed episodes, peak force) and the reference run's.
    pub safety: RunSafety,
    pub reference_safety: RunSafety,
    /// The two worst windows' difference, this run's minus the reference's.
    pub worst_difference: f64,
    pub eval_return: f64,
    /// None when the two runs were evaluated on different starts (their
    /// returns would not compare).
    pub reference_eval_return: Option<f64>,
    /// No failed training episode and a worst window no lower than the
    /// reference's minus the margin.
    pub passes: bool,
}

/// A cell against its reference cell, over the seeds both finished.
#[derive(Debug, Clone, Serialize)]
pub struct CellAgainst {
    pub env: String,
    pub algo: String,
    pub connection: String,
    pub reference_connection: String,
    pub per_seed: Vec<SeedAgainst>,
    /// Finished seeds of this cell the reference has not (not compared).
    pub unpaired_seeds: Vec<u64>,
    pub passing: usize,
    pub worst_difference: Option<Paired>,
    /// Over the seeds both evaluated on the same starts.
    pub eval_difference: Option<Paired>,
}

/// A mean of per-seed differences with its 95% interval and t statistic
/// (the paired t-test).
#[derive(Debug, Clone, PartialEq, Serialize)]
pub struct Paired {
    #[serde(flatten)]
    pub estimate: Estimate,
    pub t: Option<f64>,
}

impl Paired {
    fn of(differences: &[f64]) -> Option<Self> {
        Some(Paired { estimate: mean_ci(differences)?, t: one_sample_t(differences) })
    }
}

/// against-NAME.json: every cell of a study against a reference study.
#[derive(Debug, Clone, Serialize)]
pub struct Against {
    pub experiment: String,
    pub reference: String,
    pub reference_dir: String,
    pub margin: f64,
    pub rule: &'static str,
    pub cells: Vec<CellAgainst>,
}

const RULE: &str = "per seed, a run passes when none of its training episodes failed and its worst 10-episode mean \
                    return is at least the reference run's (the same environment, algorithm and seed) minus the margin; \
                    differences are this study's minus the reference's, with the paired t interval over seeds";

/// Pairs every cell of `study` with the reference's cell of the same
/// environment and algorithm: the one with the same connection, or else
/// the only one (a reference study with several and none the same is
/// ambiguous: an error).
pub fn compare(study: &Study, reference: &Study, reference_dir: &Path, margin: f64) -> anyhow::Result<Against> {
    anyhow::ensure!(margin.is_finite() && margin >= 0.0, "--margin must be a finite number ≥ 0, not {margin}");
    let mut cells = Vec::new();
    for c in &study.cells {
        cells.push(cell_against(c, reference_cell(c, reference, reference_dir)?, margin));
    }
    Ok(Against {
        experiment: study.experiment.file.name.clone(),
        reference: reference.experiment.file.name.clone(),
        reference_dir: reference_dir.display().to_string(),
        margin,
        rule: RULE,
        cells,
    })
}

/// The reference's cell for `c`: the same environment and algorithm, with
/// the same connection, or else the only one.
fn reference_cell<'a>(c: &CellRuns, reference: &'a Study, reference_dir: &Path) -> anyhow::Result<&'a CellRuns> {
    let same_task: Vec<&CellRuns> = reference.cells.iter().filter(|r| r.cell.env == c.cell.env && r.cell.algo == c.cell.algo).collect();
    if let Some(same) = same_task.iter().find(|r| r.cell.connection == c.cell.connection) {
        return Ok(same);
    }
    let task = format!("{}/{}", c.cell.env, super::config::algo_name(c.cell.algo));
    match same_task.as_slice() {
        [only] => Ok(only),
        [] => anyhow::bail!(
            "the reference study {} has no {task} cell to compare {} with: give a study of the same environment and algorithm",
            reference_dir.display(),
            c.cell.label()
        ),
        _ => anyhow::bail!(
            "the reference study {} has several {task} cells and none with {}'s connection: give a study with one",
            reference_dir.display(),
            c.cell.label()
        ),
    }
}

fn cell_against(cell: &CellRuns, reference: &CellRuns, margin: f64) -> CellAgainst {
    let mut per_seed = Vec::new();
    let mut unpaired_seeds = Vec::new();
    for run in &cell.runs {
        match reference.runs.iter().find(|r| r.seed == run.seed).and_then(|r| seed_against(run, r, margin)) {
            Some(s) => per_seed.push(s),
            None => unpaired_seeds.push(run.seed),
        }
    }
    let differences = |f: fn(&SeedAgainst) -> Option<f64>| Paired::of(&per_seed.iter().filter_map(f).collect::<Vec<_>>());
    CellAgainst {
        env: cell.cell.env.clone(),
        algo: super::config::algo_name(cell.cell.algo).into(),
        connection: cell.cell.connection.label(),
        reference_connection: reference.cell.connection.label(),
        passing: per_seed.iter().filter(|s| s.passes).count(),
        worst_difference: differences(|s| Some(s.worst_difference)),
        eval_difference: differences(|s| Some(s.eval_return - s.reference_eval_return?)),
        per_seed,
        unpaired_seeds,
    }
}

/// Whether both runs were evaluated on the same starts.
fn same_starts(a: &Run, b: &Run) -> bool {
    let (a, b) = (&a.summary.evaluation, &b.summary.evaluation);
    a.eval_seed.is_some() && (a.eval_seed, a.eval_episodes) == (b.eval_seed, b.eval_episodes)
}

/// None when either run has no training episodes.
fn seed_against(run: &Run, reference: &Run, margin: f64) -> Option<SeedAgainst> {
    let (safety, reference_safety) = (run.safety?, reference.safety?);
    let worst_difference = safety.worst_mean_return - reference_safety.worst_mean_return;
    Some(SeedAgainst {
        seed: run.seed,
        passes: safety.failed_episodes == 0 && worst_difference >= -margin,
        safety,
        reference_safety,
        worst_difference,
        eval_return: run.summary.evaluation.eval_return,
        reference_eval_return: same_starts(run, reference).then_some(reference.summary.evaluation.eval_return),
    })
}

fn paired(e: &Option<Paired>) -> String {
    match e {
        Some(Paired { estimate: Estimate { mean, ci95: Some([lo, hi]), .. }, t }) => {
            format!("{} [{}, {}]{}", num(*mean), num(*lo), num(*hi), t.map_or(String::new(), |t| format!(", t {t:.2}")))
        }
        Some(p) => num(p.estimate.mean),
        None => "—".into(),
    }
}

fn force(f: Option<f64>) -> String {
    f.map_or("—".into(), |f| format!("{f:.1}"))
}

/// against-NAME.md.
pub fn markdown(a: &Against) -> String {
    let mut md = String::new();
    let _ = writeln!(md, "# `{}` against `{}` ({}), seed for seed\n", a.experiment, a.reference, a.reference_dir);
    let _ = writeln!(md, "Margin {}: {}.\n", num(a.margin), a.rule);
    let _ = writeln!(md, "| cell | against | seeds paired | passing | worst-window difference [95% CI] | eval-return difference [95% CI] |");
    let _ = writeln!(md, "|---|---|---|---|---|---|");
    for c in &a.cells {
        let n = c.per_seed.len();
        let _ = writeln!(
            md,
            "| {}/{}/{} | {} | {n} | {} of {n} | {} | {} |",
            c.env,
            c.algo,
            c.connection,
            c.reference_connection,
            c.passing,
            paired(&c.worst_difference),
            paired(&c.eval_difference)
        );
    }
    for c in &a.cells {
        let _ = writeln!(md, "\n## {}/{}/{}\n", c.env, c.algo, c.connection);
        let _ = writeln!(md, "| seed | worst window (ending at episode) | reference's | difference | failed (reference's) | peak N (reference's) | eval return | reference's | passes |");
        let _ = writeln!(md, "|---|---|---|---|---|---|---|---|---|");
        for s in &c.per_seed {
            let _ = writeln!(
                md,
                "| {} | {} ({}) | {} ({}) | {} | {} ({}) | {} ({}) | {} | {} | {} |",
                s.seed,
                num(s.safety.worst_mean_return),
                s.safety.worst_window_end,
                num(s.reference_safety.worst_mean_return),
                s.reference_safety.worst_window_end,
                num(s.worst_difference),
                s.safety.failed_episodes,
                s.reference_safety.failed_episodes,
                force(s.safety.peak_force_n),
                force(s.reference_safety.peak_force_n),
                num(s.eval_return),
                s.reference_eval_return.map_or("— (other starts)".into(), num),
                if s.passes { "yes" } else { "no" }
            );
        }
        if !c.unpaired_seeds.is_empty() {
            let _ = writeln!(md, "\nNot in the reference (not compared): seeds {:?}", c.unpaired_seeds);
        }
    }
    md
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::experiment::config::Experiment;
    use crate::experiment::plan::{cells, run_dir};
    use crate::experiment::study::{fixtures::write_run, gather};

    /// A study of one cell; per run its seed, eval return, training returns
    /// (episode k at returns[k − 1]) and the episode that failed, if any.
    fn study(dir: &Path, name: &str, connection: &str, runs: &[(u64, f64, &[f64], Option<usize>)]) -> Study {
        let seeds: Vec<String> = runs.iter().map(|r| r.0.to_string()).collect();
        let text = format!(
            "name = \"{name}\"\nenvironments = [\"lti-paper\"]\nalgorithms = [\"ppo\"]\nconnections = [\"{connection}\"]\nseeds = [{}]\nepisodes = {{ ppo = 12 }}\n",
            seeds.join(", ")
        );
        let e = Experiment::parse(&text).unwrap();
        let cell = cells(&e)[0].clone();
        for &(seed, eval, returns, failed_at) in runs {
            let run = run_dir(dir, &cell, seed);
            write_run(&run, connection, seed, eval, Some(0), None);
            let mut csv = "episode,return,length,success,peak_force_n,peak_moment_nm,wall_s,optimization_s\n".to_string();
            for (k, r) in returns.iter().enumerate() {
                csv += &format!("{},{r},10,{},20,,,\n", k + 1, failed_at != Some(k + 1));
            }
            std::fs::write(run.join("metrics.csv"), csv).unwrap();
        }
        gather(&e, dir).unwrap()
    }

    /// Twelve episodes at `level` with one dip of ten at `dip` ending at 11.
    fn curve(level: f64, dip: f64) -> Vec<f64> {
        (1..=12).map(|k| if (2..=11).contains(&k) { dip } else { level }).collect()
    }

    /// The pass rule at its edges: a window exactly the margin below the
    /// reference's passes, one a hair lower does not, a failed episode
    /// fails the seed whatever its window; seeds the reference lacks are
    /// listed, not compared; the paired figures are the differences'.
    #[test]
    fn seeds_pass_by_the_reference_window_minus_the_margin() {
        let tmp = tempfile::tempdir().unwrap();
        let (a, b) = (tmp.path().join("a"), tmp.path().join("b"));
        let (r0, r1, r2) = (curve(-3.0, -5.0), curve(-3.0, -6.0), curve(-3.0, -5.5));
        let reference = study(&b, "base", "global", &[(0, -3.5, &r0, None), (1, -3.5, &r1, None), (2, -3.5, &r2, None)]);
        let (s0, s1, s2, s3) = (curve(-3.0, -6.0), curve(-3.0, -7.0 - 1e-9), curve(-3.0, -4.0), curve(-3.0, -4.0));
        let runs = study(&a, "trained", "local", &[(0, -3.3, &s0, None), (1, -3.4, &s1, None), (2, -3.0, &s2, Some(4)), (3, -3.0, &s3, None)]);
        let against = compare(&runs, &reference, &b, 1.0).unwrap();
        let c = &against.cells[0];
        assert_eq!((c.connection.as_str(), c.reference_connection.as_str()), ("local@1", "global"), "the only cell of that task (a plain local is T_rule)");
        let verdicts: Vec<(u64, bool, usize)> = c.per_seed.iter().map(|s| (s.seed, s.passes, s.safety.worst_window_end)).collect();
        assert_eq!(verdicts, [(0, true, 11), (1, false, 11), (2, false, 11)]);
        assert_eq!((c.passing, c.unpaired_seeds.as_slice()), (1, &[3][..]));
        assert_eq!(c.per_seed[2].safety.failed_episodes, 1);
        // Differences −1, −1 − 1e-9, +1.5: mean 0.5/3 − 1e-9/3.
        let worst = c.worst_difference.as_ref().unwrap();
        assert!((worst.estimate.mean - (-0.5 / 3.0 - 1e-9 / 3.0)).abs() < 1e-12 && worst.estimate.n == 3, "{worst:?}");
        let eval = c.eval_difference.as_ref().unwrap();
        assert!((eval.estimate.mean - 0.8 / 3.0).abs() < 1e-12, "eval differences +0.2, +0.1, +0.5: {eval:?}");
        let md = markdown(&against);
        assert!(md.contains("| 1 of 3 |") && md.contains("| 1 | -7.000 (11) | -6.000 (11) |"), "{md}");

        // A reference run evaluated on other starts keeps its safety
        // figures but leaves the eval difference.
        let seed1 = run_dir(&b, &cells(&reference.experiment)[0], 1);
        write_run(&seed1, "global", 1, -3.5, Some(7), None);
        std::fs::write(seed1.join("metrics.csv"), std::fs::read(run_dir(&b, &cells(&reference.experiment)[0], 0).join("metrics.csv")).unwrap()).unwrap();
        let against = compare(&runs, &gather(&reference.experiment, &b).unwrap(), &b, 1.0).unwrap();
        let c = &against.cells[0];
        assert_eq!(c.per_seed[1].reference_eval_return, None);
        assert_eq!(c.eval_difference.as_ref().map(|e| e.estimate.n), Some(2), "seeds 0 and 2 only");
        assert!(markdown(&against).contains("— (other starts)"));
    }

    #[test]
    fn a_reference_of_another_task_or_an_ambiguous_one_is_refused() {
        let tmp = tempfile::tempdir().unwrap();
        let ones = vec![-1.0; 12];
        let runs = study(&tmp.path().join("a"), "a", "local", &[(0, -1.0, &ones, None)]);
        let text = "name = \"two\"\nenvironments = [\"lti-paper\"]\nalgorithms = [\"ppo\", \"ddpg\"]\nconnections = [\"global\", \"full-subnets\"]\nseeds = 1\nepisodes = { ppo = 2, ddpg = 2 }\n";
        let two = gather(&Experiment::parse(text).unwrap(), &tmp.path().join("b")).unwrap();
        let err = compare(&runs, &two, Path::new("b"), 1.0).unwrap_err().to_string();
        assert!(err.contains("several lti-paper/ppo cells"), "{err}");
        let other = "name = \"o\"\nenvironments = [\"lti-paper\"]\nalgorithms = [\"ddpg\"]\nconnections = [\"global\"]\nseeds = 1\nepisodes = { ddpg = 2 }\n";
        let err = compare(&runs, &gather(&Experiment::parse(other).unwrap(), &tmp.path().join("c")).unwrap(), Path::new("c"), 1.0).unwrap_err().to_string();
        assert!(err.contains("has no lti-paper/ppo cell"), "{err}");
        assert!(compare(&runs, &runs, Path::new("a"), f64::NAN).is_err());
    }
}
