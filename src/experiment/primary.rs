//! A study's primary contrasts: the comparisons its file names before any
//! run (`[primary]`), so that the results it reports first were not picked
//! after seeing the data. Each is tested stratified by environment: a mean
//! difference by inverse-variance weighted Welch differences, a time to
//! the best constant by the stratified log-rank test. Several contrasts
//! are one family under the rule the file states (Holm or Bonferroni at
//! its α); every other comparison a report prints is secondary and carries
//! Holm's adjustment over all of them (docs/experiment.md).

use std::fmt::Write as _;

use serde::Serialize;

use super::config::{ConnectionSpec, Primary, PrimaryContrast};
use super::inference::{km_median, log_rank, LogRank};
use super::study::Study;
use super::stats::{format_p, holm, reading, stratified, welch, Stratified, Welch};

/// One primary contrast's result.
#[derive(Debug, Serialize)]
pub struct ContrastResult {
    pub contrast: PrimaryContrast,
    pub description: String,
    /// Mean differences: each environment's Welch difference. For the time
    /// to the best constant: the difference of mean episodes with censored
    /// runs counted as the budget (descriptive; the test is the log-rank).
    pub per_environment: Vec<(String, Welch)>,
    pub combined: Option<Stratified>,
    /// Time to the best constant: the stratified log-rank test, and each
    /// environment's Kaplan–Meier medians (a, b).
    #[serde(skip_serializing_if = "Option::is_none")]
    pub log_rank: Option<LogRank>,
    #[serde(skip_serializing_if = "Vec::is_empty")]
    pub medians: Vec<(String, Option<usize>, Option<usize>)>,
    /// The contrast's own two-sided p.
    pub p_value: f64,
    /// Adjusted by the family's rule (its own p for a single contrast).
    pub p_adjusted: f64,
    /// Whether the family's rule rejects "no difference" at its α.
    pub rejected: bool,
    pub reading: String,
}

/// The primary contrasts with their family-wise rule.
#[derive(Debug, Serialize)]
pub struct PrimaryResult {
    pub rule: String,
    pub alpha: f64,
    pub contrasts: Vec<ContrastResult>,
    /// The decision the file ties to these contrasts, in its own words.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub decision: Option<String>,
}

/// The file's primary contrasts on a study's finished runs.
pub fn evaluate(primary: &Primary, study: &Study) -> PrimaryResult {
    let (rule, alpha) = primary.rule();
    let mut contrasts: Vec<ContrastResult> = primary.contrasts().into_iter().map(|c| one(c, study)).collect();
    let p: Vec<f64> = contrasts.iter().map(|c| c.p_value).collect();
    let adjusted = match rule {
        "bonferroni" => p.iter().map(|x| (x * p.len() as f64).min(1.0)).collect(),
        "holm" => holm(&p),
        _ => p.clone(),
    };
    for (c, adjusted) in contrasts.iter_mut().zip(adjusted) {
        c.p_adjusted = adjusted;
        c.rejected = adjusted < alpha;
        let (a, b) = (label(&c.contrast.a), label(&c.contrast.b));
        c.reading = match (&c.log_rank, &c.combined) {
            (None, None) if c.contrast.metric == "episodes_to_best_constant" => "no result: too few finished runs, no run reached the best constant, or no best constant yet".into(),
            (None, None) => "no result: too few finished runs".into(),
            (Some(lr), _) if c.rejected => format!("{a} reaches the best constant {} than {b}", if lr.observed_minus_expected > 0.0 { "sooner" } else { "later" }),
            (Some(_), _) => format!("{a} and {b} not distinguishable in time to the best constant"),
            (None, Some(s)) if c.rejected || rule == "none" => reading(&a, &b, s.ci95),
            (None, Some(s)) => format!("not distinguishable after the family's {rule} rule (its own CI [{:.3}, {:.3}])", s.ci95[0], s.ci95[1]),
        };
    }
    PrimaryResult { rule: rule.to_string(), alpha, contrasts, decision: primary.decision().map(str::to_string) }
}

fn label(connection: &str) -> String {
    ConnectionSpec::parse(connection).map(|c| c.label()).unwrap_or_default()
}

fn one(contrast: &PrimaryContrast, study: &Study) -> ContrastResult {
    let environments = if contrast.environments.is_empty() { study.experiment.file.environments.clone() } else { contrast.environments.clone() };
    let (a, b) = (label(&contrast.a), label(&contrast.b));
    let algo = contrast.algorithm;
    let timed = contrast.metric == "episodes_to_best_constant";
    let per_environment: Vec<(String, Welch)> = environments
        .iter()
        .filter_map(|env| {
            let (xa, xb) = if timed {
                let episodes = |label: &str| study.times(env, algo, label).iter().map(|t| t.episodes as f64).collect::<Vec<_>>();
                (episodes(&a), episodes(&b))
            } else {
                (study.values(env, algo, &a, &contrast.metric), study.values(env, algo, &b, &contrast.metric))
            };
            Some((env.clone(), welch(&xa, &xb)?))
        })
        .collect();
    // One stratum: its own Welch test (t, not the normal approximation).
    let combined = match per_environment.as_slice() {
        [(_, w)] => Some(Stratified { difference: w.difference, se: w.se, ci95: w.ci95, p_value: w.p_value, strata: 1 }),
        _ => stratified(&per_environment.iter().map(|(_, w)| (w.difference, w.se)).collect::<Vec<_>>()),
    };
    let (log_rank, medians) = if timed {
        let strata: Vec<_> = environments.iter().map(|env| (study.times(env, algo, &a), study.times(env, algo, &b))).collect();
        let medians = environments.iter().zip(&strata).map(|(env, (ta, tb))| (env.clone(), km_median(ta), km_median(tb))).collect();
        (log_rank(&strata), medians)
    } else {
        (None, Vec::new())
    };
    let p_value = match &log_rank {
        Some(lr) => lr.p_value,
        None if timed => f64::NAN,
        None => combined.as_ref().map_or(f64::NAN, |c| c.p_value),
    };
    ContrastResult {
        description: contrast.describe(&environments),
        contrast: contrast.clone(),
        per_environment,
        combined: if timed && log_rank.is_none() { None } else { combined },
        log_rank,
        medians,
        p_value,
        p_adjusted: f64::NAN,
        rejected: false,
        reading: String::new(),
    }
}

/// The section report.md opens with.
pub fn markdown(p: &PrimaryResult) -> String {
    let num = |x: f64| format!("{x:.3}");
    let mut md = String::new();
    let _ = writeln!(md, "## Primary contrast{}\n", if p.contrasts.len() > 1 { "s" } else { "" });
    if p.contrasts.len() > 1 {
        let _ = writeln!(md, "Named in the study file before any run, {} contrasts under {}'s rule at α = {} (family-wise); every comparison further below is secondary.\n", p.contrasts.len(), p.rule, p.alpha);
    }
    for c in &p.contrasts {
        let _ = writeln!(md, "Named in the study file before any run: {}.\n", c.description);
        let test = if c.log_rank.is_some() {
            "stratified log-rank test, runs that never reach the best constant censored at the budget; the difference is of mean episodes with censored runs counted as the budget".to_string()
        } else {
            format!("{} environment(s); inverse-variance weighted Welch differences, normal approximation across environments", c.combined.as_ref().map_or(0, |s| s.strata))
        };
        let adjusted = if p.contrasts.len() > 1 { format!(", adjusted p ({}) {}", p.rule, format_p(c.p_adjusted)) } else { String::new() };
        match &c.combined {
            Some(s) => {
                let _ = writeln!(md, "**{}**: difference {} [{}, {}], p {}{adjusted} ({test}).\n", c.reading, num(s.difference), num(s.ci95[0]), num(s.ci95[1]), format_p(c.p_value));
            }
            None => {
                let _ = writeln!(md, "{}.\n", c.reading);
            }
        }
        for (env, w) in &c.per_environment {
            let _ = writeln!(md, "- {env}: {} [{}, {}], p {} (Welch, this environment alone: raw, descriptive)", num(w.difference), num(w.ci95[0]), num(w.ci95[1]), format_p(w.p_value));
        }
        for (env, ma, mb) in &c.medians {
            let m = |x: &Option<usize>| x.map_or("not reached".into(), |k| k.to_string());
            let _ = writeln!(md, "- {env}: Kaplan–Meier median episodes to the best constant {} (a) and {} (b)", m(ma), m(mb));
        }
        let _ = writeln!(md);
    }
    if let Some(decision) = &p.decision {
        let _ = writeln!(md, "Decision rule, named in the study file before any run (`primary.decision`): {}\n", decision.trim());
    }
    md
}

#[cfg(test)]
mod tests {
    use super::super::config::Experiment;
    use super::super::plan::{cells, run_dir};
    use super::super::report::markdown;
    use super::super::study::fixtures::write_run;
    use super::super::study::gather;
    use super::super::stats::{holm, welch};

    /// The file's primary contrast is reported first, on its own (here one
    /// environment: its Welch test); every other comparison carries
    /// Holm's adjustment over all of them and its interval in words.
    #[test]
    fn the_primary_contrast_stands_alone_and_the_rest_are_holm_adjusted() {
        let text = "name = \"p\"\nenvironments = [\"lti-paper\"]\nalgorithms = [\"ppo\"]\nconnections = [\"local@0.1\", \"global\", \"full-subnets\"]\nseeds = 3\nepisodes = { ppo = 2 }\n\
                    [primary]\nmetric = \"eval_return\"\na = \"local@0.1\"\nb = \"global\"\nalgorithm = \"ppo\"\n";
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
        let primary = &report.primary.as_ref().unwrap().contrasts[0];
        let w = welch(&returns[0], &returns[1]).unwrap();
        let combined = primary.combined.as_ref().unwrap();
        assert_eq!((combined.difference, combined.p_value, combined.strata), (w.difference, w.p_value, 1));
        assert!(primary.rejected && primary.p_adjusted == primary.p_value);
        assert!(primary.reading.starts_with("local@0.1 higher than global"), "{}", primary.reading);
        // local − global and local − full-subnets, on two metrics (no best
        // constant here, so no speed comparison; the AUC needs a = 0's
        // return: absent too). local − global's eval return is the primary
        // contrast's own row: shown, but outside the secondary family.
        assert_eq!(report.comparisons.len(), 4);
        let (primary_rows, secondary): (Vec<_>, Vec<_>) = report.comparisons.iter().partition(|c| c.primary);
        assert_eq!(primary_rows.len(), 1);
        assert_eq!((primary_rows[0].a.as_str(), primary_rows[0].b.as_str(), primary_rows[0].metric), ("local@0.1", "global", "eval_return"));
        assert!(primary_rows[0].p_holm.is_nan() && primary_rows[0].reading.starts_with("primary contrast"));
        let adjusted = holm(&secondary.iter().map(|c| c.p_value).collect::<Vec<_>>());
        for (c, p) in secondary.iter().zip(adjusted) {
            assert_eq!(c.p_holm, p);
            assert!(c.p_holm >= c.p_value);
        }
        let md = markdown(&report);
        assert!(md.contains("## Primary contrast") && md.contains("eval_return, local@0.1 − global, PPO, stratified by environment over lti-paper"), "{md}");
        assert!(md.contains("p (Holm, 3 comparisons)") && md.contains("not distinguishable, CI ["), "{md}");
        assert!(w.p_value < 0.001 && md.contains(&format!("p < 0.001 (1 environment(s)")), "p values print as < 0.001, never 0.000:\n{md}");
        // Named before the runs: a contrast of connections the study lacks is refused.
        let wrong = text.replace("b = \"global\"", "b = \"random@3\"");
        let err = format!("{:#}", Experiment::parse(&wrong).unwrap_err());
        assert!(err.contains("`primary.b` \"random@3\" is not one of `connections`"), "{err}");
    }

    /// A family of two: eval return clearly apart, final return not; Holm's
    /// rule adjusts both, and only the first is called.
    #[test]
    fn a_primary_family_is_adjusted_by_its_rule() {
        let text = "name = \"p\"\nenvironments = [\"lti-paper\"]\nalgorithms = [\"ppo\"]\nconnections = [\"local@0.1\", \"global\"]\nseeds = 3\nepisodes = { ppo = 2 }\n\
                    [primary]\nfamily = \"holm\"\nalpha = 0.05\ndecision = \"ship local if the first is higher\"\n\
                    [[primary.contrasts]]\nmetric = \"eval_return\"\na = \"local@0.1\"\nb = \"global\"\nalgorithm = \"ppo\"\n\
                    [[primary.contrasts]]\nmetric = \"auc_100\"\na = \"local@0.1\"\nb = \"global\"\nalgorithm = \"ppo\"\n";
        let e = Experiment::parse(text).unwrap();
        let tmp = tempfile::tempdir().unwrap();
        let out = tmp.path();
        for (cell, values) in cells(&e).iter().zip([[-1.0, -1.1, -0.9], [-3.0, -3.2, -2.9]]) {
            for (seed, r) in values.iter().enumerate() {
                write_run(&run_dir(out, cell, seed as u64), "local", seed as u64, *r, Some(0), Some(-8.5));
            }
        }
        let report = gather(&e, out).unwrap().report();
        let p = report.primary.as_ref().unwrap();
        assert_eq!((p.rule.as_str(), p.contrasts.len()), ("holm", 2));
        let raw: Vec<f64> = p.contrasts.iter().map(|c| c.p_value).collect();
        // The fixture's curves are the same for every run: AUC equal, p = 1.
        assert_eq!(raw[1], 1.0);
        let adjusted = holm(&raw);
        assert_eq!(p.contrasts.iter().map(|c| c.p_adjusted).collect::<Vec<_>>(), adjusted);
        assert!(p.contrasts[0].rejected && !p.contrasts[1].rejected);
        let md = markdown(&report);
        assert!(md.contains("2 contrasts under holm's rule at α = 0.05"), "{md}");
        assert!(md.contains("Decision rule, named in the study file before any run (`primary.decision`): ship local if the first is higher"), "{md}");
    }
}
