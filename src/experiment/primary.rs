//! A study's primary contrast: the one comparison its file names before
//! any run (`[primary]`), so that the result it reports first was not
//! picked after seeing the data. It is tested on its own, stratified by
//! environment; every other comparison a report prints is secondary and
//! carries Holm's adjustment over all of them (docs/experiment.md).

use std::fmt::Write as _;

use serde::Serialize;

use super::config::{ConnectionSpec, PrimaryContrast};
use super::stats::{format_p, reading, stratified, welch, Stratified, Welch};

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

/// The contrast on a study's finished runs: `values(env, connection)`
/// gives the contrast's metric of each finished run of that cell (its
/// algorithm), and `study_environments` the study's environments.
pub fn evaluate(contrast: &PrimaryContrast, study_environments: &[String], values: impl Fn(&str, &str) -> Vec<f64>) -> PrimaryResult {
    let environments = if contrast.environments.is_empty() { study_environments.to_vec() } else { contrast.environments.clone() };
    let label = |c: &str| ConnectionSpec::parse(c).map(|c| c.label()).unwrap_or_default();
    let (a, b) = (label(&contrast.a), label(&contrast.b));
    let per_environment: Vec<(String, Welch)> = environments.iter().filter_map(|env| Some((env.clone(), welch(&values(env, &a), &values(env, &b))?))).collect();
    // One stratum: its own Welch test (t, not the normal approximation).
    let combined = match per_environment.as_slice() {
        [(_, w)] => Some(Stratified { difference: w.difference, ci95: w.ci95, p_value: w.p_value, strata: 1 }),
        _ => stratified(&per_environment.iter().map(|(_, w)| (w.difference, w.se)).collect::<Vec<_>>()),
    };
    let reading = combined.as_ref().map_or("no result: too few finished runs".into(), |c| reading(&a, &b, c.ci95));
    PrimaryResult { contrast: contrast.clone(), description: contrast.describe(&environments), per_environment, combined, reading }
}

/// The section report.md opens with.
pub fn markdown(p: &PrimaryResult) -> String {
    let num = |x: f64| format!("{x:.3}");
    let mut md = String::new();
    let _ = writeln!(md, "## Primary contrast\n");
    let _ = writeln!(md, "Named in the study file before any run: {}.\n", p.description);
    match &p.combined {
        Some(c) => {
            let _ = writeln!(
                md,
                "**{}**: difference {} [{}, {}], p {} ({} environment(s); inverse-variance weighted Welch differences, normal approximation across environments). Tested on its own: no adjustment; the comparisons below are secondary.\n",
                p.reading,
                num(c.difference),
                num(c.ci95[0]),
                num(c.ci95[1]),
                format_p(c.p_value),
                c.strata
            );
        }
        None => {
            let _ = writeln!(md, "{}.\n", p.reading);
        }
    }
    for (env, w) in &p.per_environment {
        let _ = writeln!(md, "- {env}: {} [{}, {}], p {} (Welch)", num(w.difference), num(w.ci95[0]), num(w.ci95[1]), format_p(w.p_value));
    }
    let _ = writeln!(md);
    md
}

#[cfg(test)]
mod tests {
    use super::super::config::Experiment;
    use super::super::plan::{cells, run_dir};
    use super::super::report::fixtures::write_run;
    use super::super::report::{gather, markdown};
    use super::super::stats::{holm, welch};

    /// The file's primary contrast is reported first, on its own (here one
    /// environment: its Welch test); every other comparison carries
    /// Holm's adjustment over all of them and its interval in words.
    #[test]
    fn the_primary_contrast_stands_alone_and_the_rest_are_holm_adjusted() {
        let text = "name = \"p\"\nenvironments = [\"lti-paper\"]\nalgorithms = [\"ppo\"]\nconnections = [\"local\", \"global\", \"full-subnets\"]\nseeds = 3\nepisodes = { ppo = 2 }\n\
                    [primary]\nmetric = \"eval_return\"\na = \"local\"\nb = \"global\"\nalgorithm = \"ppo\"\n";
        let e = Experiment::parse(text).unwrap();
        let tmp = tempfile::tempdir().unwrap();
        let out = tmp.path();
        let returns = [[-1.0, -1.1, -0.9], [-3.0, -3.2, -2.9], [-1.05, -1.0, -0.95]];
        for (cell, values) in cells(&e).iter().zip(returns) {
            for (seed, r) in values.iter().enumerate() {
                write_run(&run_dir(out, cell, seed as u64), "local", seed as u64, *r, Some(0), None);
            }
        }
        let report = gather(&e, out).unwrap().report();
        let primary = report.primary.as_ref().unwrap();
        let w = welch(&returns[0], &returns[1]).unwrap();
        let combined = primary.combined.as_ref().unwrap();
        assert_eq!((combined.difference, combined.p_value, combined.strata), (w.difference, w.p_value, 1));
        assert!(primary.reading.starts_with("local@0.1 higher than global"), "{}", primary.reading);
        // Secondary: local − global and local − full-subnets, on two metrics.
        assert_eq!(report.comparisons.len(), 4);
        let adjusted = holm(&report.comparisons.iter().map(|c| c.p_value).collect::<Vec<_>>());
        for (c, p) in report.comparisons.iter().zip(adjusted) {
            assert_eq!(c.p_holm, p);
            assert!(c.p_holm >= c.p_value);
        }
        let md = markdown(&report);
        assert!(md.contains("## Primary contrast") && md.contains("eval_return, local − global, PPO, stratified by environment over lti-paper"), "{md}");
        assert!(md.contains("p (Holm, 4 comparisons)") && md.contains("not distinguishable, CI ["), "{md}");
        assert!(w.p_value < 0.001 && md.contains(&format!("p < 0.001 (1 environment(s)")), "p values print as < 0.001, never 0.000:\n{md}");
        // Named before the runs: a contrast of connections the study lacks is refused.
        let wrong = text.replace("b = \"global\"", "b = \"random@3\"");
        let err = format!("{:#}", Experiment::parse(&wrong).unwrap_err());
        assert!(err.contains("`primary.b` \"random@3\" is not one of `connections`"), "{err}");
    }
}
