//! `lcrl experiment report DIR --with OTHER`: a companion study's cells in
//! this study's report (docs/experiment.md, "Companion studies").
//!
//! A companion is a study of the same design that changes one setting,
//! such as the global actor's learning rate
//! (experiments/research/lti-blocks-32-global-lr3e-4.toml beside experiments/lti-blocks.toml).
//! Its cells join the report labelled `CONNECTION [NAME]`; the report
//! compares each with this study's cells by the usual rules and with this
//! study's cell of the same connection, all in one Holm family, and
//! advantage.png draws them. The design must match so that the runs
//! compare: the environments and algorithms are this study's, with the
//! same episode budgets and evaluation episodes, and a seed's evaluation
//! starts are the same in both.

use std::collections::BTreeMap;
use std::path::Path;

use anyhow::{bail, ensure};
use serde_json::Value;

use super::config::algo_name;
use super::report::{Companion, Study};

/// Adds `companion`'s cells (its study read from `dir`) to `study`, each
/// marked with its study's name.
pub fn join(study: &mut Study, companion: Study, dir: &Path) -> anyhow::Result<()> {
    let (own, other) = (&study.experiment, &companion.experiment);
    let name = other.file.name.clone();
    ensure!(name != own.file.name, "--with names the study {name} itself");
    ensure!(!study.companions.iter().any(|c| c.name == name), "--with names two studies called {name}: a report tells companions apart by name");
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
    check_starts(study, &companion, &name)?;
    // Thresholds of environments the companion does not run say nothing
    // about its cells.
    let unrun: Vec<String> = own.file.environments.iter().filter(|e| !other.file.environments.contains(e)).map(|e| format!("reward_threshold.{e}.")).collect();
    let differs = differences(&serde_json::to_value(&own.file)?, &serde_json::to_value(&other.file)?).into_iter().filter(|d| !unrun.iter().any(|u| d.starts_with(u.as_str()))).collect();
    study.companions.push(Companion { name: name.clone(), dir: dir.display().to_string(), differs });
    // "ENV/ALGO/CONNECTION seed K" → "ENV/ALGO/CONNECTION [NAME] seed K".
    study.missing.extend(companion.missing.iter().map(|m| match m.rsplit_once(" seed ") {
        Some((cell, seed)) => format!("{cell} [{name}] seed {seed}"),
        None => format!("{m} [{name}]"),
    }));
    for mut cell in companion.cells {
        cell.from = Some(name.clone());
        study.cells.push(cell);
    }
    Ok(())
}

/// The companion's runs were evaluated on the starts this study's runs of
/// the same environment, algorithm and seed were (their returns compare):
/// every run's evaluation seed is known, and at least one seed is shared,
/// so that the check says something.
fn check_starts(study: &Study, companion: &Study, name: &str) -> anyhow::Result<()> {
    let key = |cell: &super::plan::Cell, seed: u64| (cell.env.clone(), algo_name(cell.algo).to_string(), seed);
    let mut starts = BTreeMap::new();
    for cell in study.cells.iter().filter(|c| c.from.is_none()) {
        for run in &cell.runs {
            starts.insert(key(&cell.cell, run.seed), run.summary.evaluation.eval_seed);
        }
    }
    let mut shared = 0;
    for cell in &companion.cells {
        for run in &cell.runs {
            let Some(theirs) = run.summary.evaluation.eval_seed else {
                bail!("--with: {} seed {} of {name} does not record its evaluation starts (eval_seed): its returns cannot be shown to compare", cell.cell.label(), run.seed);
            };
            if let Some(mine) = starts.get(&key(&cell.cell, run.seed)) {
                if *mine != Some(theirs) {
                    bail!(
                        "--with: {} seed {} of {name} was evaluated on other starts than this study's runs of seed {} (eval_seed {theirs} against {})",
                        cell.cell.label(),
                        run.seed,
                        run.seed,
                        mine.map_or("none".into(), |s| s.to_string())
                    );
                }
                shared += 1;
            }
        }
    }
    let runs: usize = companion.cells.iter().map(|c| c.runs.len()).sum();
    ensure!(runs == 0 || shared > 0, "--with: no finished run of {name} has a seed this study finished on its environment and algorithm, so nothing shows the two were evaluated on the same starts");
    Ok(())
}

/// The settings in which two study files differ, as `key: here X, there
/// Y`, leaving out what says which cells a study runs.
fn differences(own: &Value, other: &Value) -> Vec<String> {
    const CELLS: [&str; 9] = ["name", "environments", "algorithms", "connections", "seeds", "seeds_of", "primary", "equivalence", "factorial"];
    let (mut mine, mut theirs) = (BTreeMap::new(), BTreeMap::new());
    flatten("", own, &mut mine);
    flatten("", other, &mut theirs);
    let keys: std::collections::BTreeSet<&String> = mine.keys().chain(theirs.keys()).collect();
    keys.into_iter()
        .filter(|k| !CELLS.iter().any(|c| k.as_str() == *c || k.starts_with(&format!("{c}."))))
        .filter(|k| mine.get(*k) != theirs.get(*k))
        .map(|k| format!("{k}: here {}, there {}", mine.get(k).map_or("unset", String::as_str), theirs.get(k).map_or("unset", String::as_str)))
        .collect()
}

fn flatten(prefix: &str, value: &Value, out: &mut BTreeMap<String, String>) {
    match value {
        Value::Object(map) => {
            for (k, v) in map {
                flatten(&if prefix.is_empty() { k.clone() } else { format!("{prefix}.{k}") }, v, out);
            }
        }
        Value::Null => {}
        other => {
            out.insert(prefix.to_string(), other.to_string());
        }
    }
}

#[cfg(test)]
mod tests {
    use std::path::Path;

    use super::*;
    use crate::experiment::config::Experiment;
    use crate::experiment::plan::{cells, run_dir};
    use crate::experiment::study::fixtures::write_run;
    use crate::experiment::study::gather;

    const STUDY: &str = "environments = [\"lti-paper\"]\nalgorithms = [\"ppo\"]\nseeds = 3\nepisodes = { ppo = 2 }\n";

    /// A study folder of `connections` (and `extra` settings) whose runs
    /// return `base` − seed/2, evaluated on `eval_seed`.
    fn study_with(out: &Path, name: &str, connections: &str, extra: &str, base: f64, eval_seed: Option<u64>) -> Study {
        let e = Experiment::parse(&format!("name = \"{name}\"\nconnections = [{connections}]\n{STUDY}{extra}")).unwrap();
        for cell in cells(&e) {
            for seed in 0..3 {
                let connection = if cell.connection.has_graph() { "local" } else { "global" };
                write_run(&run_dir(out, &cell, seed), connection, seed, base - seed as f64 * 0.5, eval_seed, None);
            }
        }
        gather(&e, out).unwrap()
    }

    fn study(out: &Path, name: &str, connections: &str, base: f64, eval_seed: Option<u64>) -> Study {
        study_with(out, name, connections, "", base, eval_seed)
    }

    fn eval_pairs(study: &Study) -> Vec<(String, String)> {
        let mut pairs: Vec<(String, String)> = study.report().comparisons.iter().filter(|c| c.metric == "eval_return").map(|c| (c.a.clone(), c.b.clone())).collect();
        pairs.sort();
        pairs
    }

    /// A companion's global cell meets the study's local cell (a graph
    /// against global) and the study's global (the one setting changed),
    /// in the report's one Holm family; its label names its study, and
    /// the report says where it came from and what differs.
    #[test]
    fn a_companions_cells_are_compared_with_the_study_in_one_family() {
        let tmp = tempfile::tempdir().unwrap();
        let mut main = study(&tmp.path().join("main"), "main", "\"local@0.1\", \"global\"", -4.0, Some(0));
        let other = study_with(&tmp.path().join("lr"), "lr", "\"global\"", "[train.ppo]\nactor_lr = 3e-4\n", -6.0, Some(0));
        join(&mut main, other, Path::new("runs/lr")).unwrap();
        let report = main.report();
        let labels: Vec<&str> = report.cells.iter().map(|c| c.connection.as_str()).collect();
        assert_eq!(labels, ["local@0.1", "global", "global [lr]"]);
        assert_eq!(report.cells[2].from.as_deref(), Some("lr"));
        let expected = [("global", "global [lr]"), ("local@0.1", "global"), ("local@0.1", "global [lr]")];
        assert_eq!(eval_pairs(&main), expected.map(|(a, b)| (a.to_string(), b.to_string())));
        // global − global [lr]: −4 − (−6) = 2 on every seed.
        let changed = report.comparisons.iter().find(|c| c.metric == "eval_return" && c.a == "global").unwrap();
        assert!((changed.difference - 2.0).abs() < 1e-12, "{}", changed.difference);
        // Holm over all six (two metrics): the adjusted p is the family's.
        let raw: Vec<f64> = report.comparisons.iter().map(|c| c.p_value).collect();
        assert_eq!(report.comparisons.iter().map(|c| c.p_holm).collect::<Vec<_>>(), crate::experiment::stats::holm(&raw));
        assert_eq!(report.comparisons.len(), 6);
        assert_eq!(report.companions.len(), 1);
        assert_eq!((report.companions[0].dir.as_str(), report.companions[0].differs.as_slice()), ("runs/lr", ["train.ppo.actor_lr: here unset, there 0.0003".to_string()].as_slice()));
        assert!(super::super::report::markdown(&report).contains("- lr (runs/lr), differs in: train.ppo.actor_lr"));
    }

    /// A companion that changes the local actor's setting meets the
    /// study's baselines as the study's own local cell does, and the
    /// study's local cell; two companions never meet each other.
    #[test]
    fn a_companions_graph_cell_meets_the_studys_baselines() {
        let tmp = tempfile::tempdir().unwrap();
        let mut main = study(&tmp.path().join("main"), "main", "\"local@0.1\", \"global\", \"random@4\"", -4.0, Some(0));
        join(&mut main, study(&tmp.path().join("a"), "a", "\"local@0.1\"", -3.0, Some(0)), Path::new("a")).unwrap();
        join(&mut main, study(&tmp.path().join("b"), "b", "\"local@0.1\", \"global\"", -5.0, Some(0)), Path::new("b")).unwrap();
        let mut pairs: Vec<String> = eval_pairs(&main).into_iter().map(|(a, b)| format!("{a} − {b}")).collect();
        pairs.sort();
        let mut expected = vec![
            "local@0.1 − global",
            "local@0.1 − random@4",
            "random@4 − global",
            "random@4 − global [b]",
            "local@0.1 [a] − global",
            "local@0.1 [a] − random@4",
            "local@0.1 − local@0.1 [a]",
            "local@0.1 [b] − global",
            "local@0.1 [b] − random@4",
            "local@0.1 − local@0.1 [b]",
            "local@0.1 − global [b]",
            "global − global [b]",
        ];
        expected.sort();
        assert_eq!(pairs, expected);
    }

    /// Companions stay out of what the study names on its own: the primary
    /// contrast and the placements among random draws are those of the
    /// study without them.
    #[test]
    fn companions_leave_the_primary_contrast_and_the_draws_alone() {
        let tmp = tempfile::tempdir().unwrap();
        let primary = "[primary]\nmetric = \"eval_return\"\na = \"local@0.1\"\nb = \"global\"\nalgorithm = \"ppo\"\n";
        let connections = "\"local@0.1\", \"global\", \"random@4+per-seed\"";
        let alone = study_with(&tmp.path().join("main"), "main", connections, primary, -4.0, Some(0)).report();
        let mut main = study_with(&tmp.path().join("main"), "main", connections, primary, -4.0, Some(0));
        join(&mut main, study(&tmp.path().join("c"), "c", connections, -1.0, Some(0)), Path::new("c")).unwrap();
        let joined = main.report();
        assert!(joined.primary.is_some() && !joined.random_draws.is_empty());
        assert_eq!(serde_json::to_value(&joined.primary).unwrap(), serde_json::to_value(&alone.primary).unwrap());
        assert_eq!(serde_json::to_value(&joined.random_draws).unwrap(), serde_json::to_value(&alone.random_draws).unwrap());
    }

    /// What does not fit is refused with the reason: another environment,
    /// algorithm, budget or number of evaluation episodes, other or
    /// unknown evaluation starts, no seed in common, the study itself, a
    /// name twice.
    #[test]
    fn a_companion_of_another_design_is_refused() {
        let tmp = tempfile::tempdir().unwrap();
        let main = || study(&tmp.path().join("main"), "main", "\"local@0.1\", \"global\"", -4.0, Some(0));
        let err = |other: Study| join(&mut main(), other, Path::new("x")).unwrap_err().to_string();
        let parsed = |name: &str, text: String| gather(&Experiment::parse(&format!("name = \"{name}\"\nconnections = [\"global\"]\n{text}")).unwrap(), &tmp.path().join(name)).unwrap();
        assert!(err(parsed("far", STUDY.replace("lti-paper", "lti-blocks-4"))).contains("it runs lti-blocks-4"));
        assert!(err(parsed("off", STUDY.replace("\"ppo\"]", "\"ppo\", \"ddpg\"]").replace("ppo = 2", "ppo = 2, ddpg = 2"))).contains("it runs ddpg"));
        assert!(err(parsed("long", STUDY.replace("ppo = 2", "ppo = 3"))).contains("ppo trains 3 episodes there, 2 here"));
        assert!(err(parsed("wide", format!("{STUDY}eval_episodes = 7\n"))).contains("evaluates on 7 episodes"));
        assert!(err(study(&tmp.path().join("starts"), "starts", "\"global\"", -6.0, Some(7))).contains("other starts"));
        assert!(err(study(&tmp.path().join("unknown"), "unknown", "\"global\"", -6.0, None)).contains("does not record its evaluation starts"));
        let apart = Experiment::parse(&format!("name = \"apart\"\nconnections = [\"global\"]\n{}", STUDY.replace("seeds = 3", "seeds = 5"))).unwrap();
        let cell = &cells(&apart)[0];
        write_run(&run_dir(&tmp.path().join("apart"), cell, 4), "global", 4, -6.0, Some(0), None);
        assert!(err(gather(&apart, &tmp.path().join("apart")).unwrap()).contains("no finished run of apart has a seed"));
        assert!(err(study(&tmp.path().join("self"), "main", "\"global\"", -6.0, Some(0))).contains("itself"));
        let mut twice = main();
        join(&mut twice, study(&tmp.path().join("lr"), "lr", "\"global\"", -6.0, Some(0)), Path::new("lr")).unwrap();
        let again = join(&mut twice, study(&tmp.path().join("lr2"), "lr", "\"global\"", -6.0, Some(0)), Path::new("lr2")).unwrap_err().to_string();
        assert!(again.contains("two studies called lr"), "{again}");
    }
}
