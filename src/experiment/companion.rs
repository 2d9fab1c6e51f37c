//! `lcrl experiment report DIR --with OTHER`: a companion study's cells in
//! this study's report (docs/experiment.md, "Companion studies").
//!
//! A companion is a study of the same design that changes one setting,
//! such as the global actor's learning rate
//! (experiments/lti-blocks-32-global-lr3e-4.toml beside lti-blocks.toml).
//! Its cells join the report labelled `CONNECTION [NAME]`; the report
//! compares each with this study's cells by the usual rules and with this
//! study's cell of the same connection, all in one Holm family, and
//! advantage.png draws them. The design must match so that the runs
//! compare: the environments and algorithms are this study's, with the
//! same episode budgets and evaluation episodes, and a seed's evaluation
//! starts are the same in both.

use std::collections::BTreeMap;

use anyhow::{bail, ensure};

use super::config::algo_name;
use super::report::Study;

/// Adds `companion`'s cells to `study`, each marked with its study's name.
pub fn join(study: &mut Study, companion: Study) -> anyhow::Result<()> {
    let (own, other) = (&study.experiment, &companion.experiment);
    let name = other.file.name.clone();
    ensure!(name != own.file.name, "--with names the study {name} itself");
    ensure!(!study.cells.iter().any(|c| c.from.as_deref() == Some(name.as_str())), "--with names the study {name} twice");
    let not_same = |what: String| anyhow::anyhow!("--with: the study {name} is not of the same design as {}: {what}", own.file.name);
    for env in &other.file.environments {
        if !own.file.environments.contains(env) {
            return Err(not_same(format!("it runs {env}, which {} does not", own.file.name)));
        }
    }
    for &algo in &other.file.algorithms {
        if !own.file.algorithms.contains(&algo) {
            return Err(not_same(format!("it runs {}, which {} does not", algo_name(algo), own.file.name)));
        }
        let (mine, theirs) = (own.episodes(algo), other.episodes(algo));
        if mine != theirs {
            return Err(not_same(format!("{} trains {theirs} episodes there, {mine} here", algo_name(algo))));
        }
    }
    if own.file.eval_episodes != other.file.eval_episodes {
        return Err(not_same(format!("it evaluates on {} episodes, this study on {}", other.file.eval_episodes, own.file.eval_episodes)));
    }
    // The same seed evaluates on the same starts in both (their returns
    // compare): every finished run's evaluation seed, by (env, algo, seed).
    let mut starts: BTreeMap<(String, String, u64), Option<u64>> = BTreeMap::new();
    for cell in &study.cells {
        for run in &cell.runs {
            starts.insert((cell.cell.env.clone(), algo_name(cell.cell.algo).into(), run.seed), run.summary.evaluation.eval_seed);
        }
    }
    for cell in &companion.cells {
        for run in &cell.runs {
            let key = (cell.cell.env.clone(), algo_name(cell.cell.algo).to_string(), run.seed);
            if let Some(mine) = starts.get(&key) {
                if *mine != run.summary.evaluation.eval_seed {
                    bail!(
                        "--with: {} seed {} of {name} was evaluated on other starts than this study's runs of seed {} ({:?} against {:?})",
                        cell.cell.label(),
                        run.seed,
                        run.seed,
                        run.summary.evaluation.eval_seed,
                        mine
                    );
                }
            }
        }
    }
    study.missing.extend(companion.missing.iter().map(|m| format!("{m} [{name}]")));
    for mut cell in companion.cells {
        cell.from = Some(name.clone());
        study.cells.push(cell);
    }
    Ok(())
}

#[cfg(test)]
mod tests {
    use std::path::Path;

    use super::*;
    use crate::experiment::config::Experiment;
    use crate::experiment::plan::{cells, run_dir};
    use crate::experiment::report::fixtures::write_run;
    use crate::experiment::report::gather;

    const STUDY: &str = "environments = [\"lti-paper\"]\nalgorithms = [\"ppo\"]\nseeds = 3\nepisodes = { ppo = 2 }\n";

    /// A study folder of `connections` whose runs return `base` − seed/2.
    fn study(out: &Path, name: &str, connections: &str, base: f64, eval_seed: Option<u64>) -> Study {
        let e = Experiment::parse(&format!("name = \"{name}\"\nconnections = [{connections}]\n{STUDY}")).unwrap();
        for cell in cells(&e) {
            for seed in 0..3 {
                let connection = if cell.connection.has_graph() { "local" } else { "global" };
                write_run(&run_dir(out, &cell, seed), connection, seed, base - seed as f64 * 0.5, eval_seed, None);
            }
        }
        gather(&e, out).unwrap()
    }

    /// A companion's global cell meets the study's local cell (a graph
    /// against global) and the study's global (the one setting changed),
    /// in the report's one Holm family; its label names its study.
    #[test]
    fn a_companions_cells_are_compared_with_the_study_in_one_family() {
        let tmp = tempfile::tempdir().unwrap();
        let mut main = study(&tmp.path().join("main"), "main", "\"local\", \"global\"", -4.0, Some(0));
        let other = study(&tmp.path().join("lr"), "lr", "\"global\"", -6.0, Some(0));
        join(&mut main, other).unwrap();
        let report = main.report();
        let labels: Vec<&str> = report.cells.iter().map(|c| c.connection.as_str()).collect();
        assert_eq!(labels, ["local@0.1", "global", "global [lr]"]);
        let mut pairs: Vec<(String, String)> = report.comparisons.iter().filter(|c| c.metric == "eval_return").map(|c| (c.a.clone(), c.b.clone())).collect();
        pairs.sort();
        let expected = [("global", "global [lr]"), ("local@0.1", "global"), ("local@0.1", "global [lr]")];
        assert_eq!(pairs, expected.map(|(a, b)| (a.to_string(), b.to_string())));
        // global − global [lr]: −4 − (−6) = 2 on every seed.
        let changed = report.comparisons.iter().find(|c| c.metric == "eval_return" && c.a == "global").unwrap();
        assert!((changed.difference - 2.0).abs() < 1e-12, "{}", changed.difference);
        // Holm over all six (two metrics): the adjusted p is the family's.
        let raw: Vec<f64> = report.comparisons.iter().map(|c| c.p_value).collect();
        let adjusted = crate::experiment::stats::holm(&raw);
        assert_eq!(report.comparisons.iter().map(|c| c.p_holm).collect::<Vec<_>>(), adjusted);
        assert_eq!(report.comparisons.len(), 6);
    }

    /// What does not fit is refused with the reason: another environment,
    /// another budget, other evaluation starts, the study itself.
    #[test]
    fn a_companion_of_another_design_is_refused() {
        let tmp = tempfile::tempdir().unwrap();
        let main = || study(&tmp.path().join("main"), "main", "\"local\", \"global\"", -4.0, Some(0));
        let err = |other: Study| join(&mut main(), other).unwrap_err().to_string();
        let e = Experiment::parse("name = \"far\"\nconnections = [\"global\"]\nenvironments = [\"lti-blocks-4\"]\nalgorithms = [\"ppo\"]\nseeds = 1\nepisodes = { ppo = 2 }\n").unwrap();
        assert!(err(gather(&e, &tmp.path().join("far")).unwrap()).contains("it runs lti-blocks-4"));
        let e = Experiment::parse(&format!("name = \"long\"\nconnections = [\"global\"]\n{}", STUDY.replace("ppo = 2", "ppo = 3"))).unwrap();
        assert!(err(gather(&e, &tmp.path().join("long")).unwrap()).contains("ppo trains 3 episodes there, 2 here"));
        assert!(err(study(&tmp.path().join("starts"), "starts", "\"global\"", -6.0, Some(7))).contains("other starts"));
        assert!(err(study(&tmp.path().join("self"), "main", "\"global\"", -6.0, Some(0))).contains("itself"));
    }
}
