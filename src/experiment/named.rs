//! The equivalence tests and 2 × 2 factorials a study file names
//! (`[[equivalence]]`, `[[factorial]]`), on its finished runs. Each is its
//! own Holm family: the equivalence tests together, each factorial's three
//! effects together, beside the report's family of secondary comparisons.

use std::fmt::Write as _;

use serde::Serialize;

use super::config::{ConnectionSpec, Equivalence, Factorial};
use super::hypotheses::split_cell;
use super::inference::{factorial, tost, Effect, Tost};
use super::study::Study;
use super::stats::{format_p, holm, stratified, welch, Welch};

#[derive(Debug, Serialize)]
pub struct EquivalenceResult {
    pub spec: Equivalence,
    pub per_environment: Vec<(String, Welch)>,
    pub tost: Option<Tost>,
    /// Holm over the study's equivalence tests.
    pub p_holm: f64,
    pub reading: String,
}

#[derive(Debug, Serialize)]
pub struct FactorialResult {
    pub spec: Factorial,
    /// Runs per cell, in the file's order.
    pub runs: [[usize; 2]; 2],
    /// Main effects and interaction; empty with a cell under two runs.
    pub effects: Vec<Effect>,
    /// Holm over the three effects.
    pub p_holm: Vec<f64>,
}

fn label(c: &str) -> String {
    ConnectionSpec::parse(c).map(|c| c.label()).unwrap_or_default()
}

pub fn equivalence(study: &Study) -> Vec<EquivalenceResult> {
    let e = &study.experiment;
    let mut out: Vec<EquivalenceResult> = e
        .file
        .equivalence
        .iter()
        .map(|spec| {
            let environments = if spec.environments.is_empty() { e.file.environments.clone() } else { spec.environments.clone() };
            let (a, b) = (label(&spec.a), label(&spec.b));
            let per_environment: Vec<(String, Welch)> = environments
                .iter()
                .filter_map(|env| Some((env.clone(), welch(&study.values(env, spec.algorithm, &a, &spec.metric), &study.values(env, spec.algorithm, &b, &spec.metric))?)))
                .collect();
            let tost = match per_environment.as_slice() {
                [(_, w)] => tost(w.difference, w.se, Some(w.df), spec.margin),
                strata => stratified(&strata.iter().map(|(_, w)| (w.difference, w.se)).collect::<Vec<_>>())
                    .and_then(|s| tost(s.difference, s.se, None, spec.margin)),
            };
            EquivalenceResult { spec: spec.clone(), per_environment, tost, p_holm: f64::NAN, reading: String::new() }
        })
        .collect();
    let adjusted = holm(&out.iter().map(|r| r.tost.as_ref().map_or(1.0, |t| t.p_value)).collect::<Vec<_>>());
    for (r, p) in out.iter_mut().zip(adjusted) {
        r.p_holm = p;
        r.reading = match &r.tost {
            None => "no result: too few finished runs, or no spread at all".into(),
            Some(t) if p < 0.05 => format!("equivalent within ±{} (Holm p < 0.05): 90% CI [{:.3}, {:.3}]", t.margin, t.ci90[0], t.ci90[1]),
            Some(t) => format!("not shown equivalent within ±{}: 90% CI [{:.3}, {:.3}]", t.margin, t.ci90[0], t.ci90[1]),
        };
    }
    out
}

pub fn factorials(study: &Study) -> Vec<FactorialResult> {
    study
        .experiment
        .file
        .factorial
        .iter()
        .map(|spec| {
            let values = |cell: &str| -> Vec<f64> {
                split_cell(cell).map(|(env, connection)| study.values(env, spec.algorithm, &label(connection), &spec.metric)).unwrap_or_default()
            };
            let v = [[values(&spec.cells[0][0]), values(&spec.cells[0][1])], [values(&spec.cells[1][0]), values(&spec.cells[1][1])]];
            let runs = [[v[0][0].len(), v[0][1].len()], [v[1][0].len(), v[1][1].len()]];
            let effects: Vec<Effect> = factorial(&[[&v[0][0], &v[0][1]], [&v[1][0], &v[1][1]]], &spec.factors).map(Vec::from).unwrap_or_default();
            let p_holm = holm(&effects.iter().map(|e| e.p_value).collect::<Vec<_>>());
            FactorialResult { spec: spec.clone(), runs, effects, p_holm }
        })
        .collect()
}

pub fn markdown(equivalence: &[EquivalenceResult], factorials: &[FactorialResult]) -> String {
    let mut md = String::new();
    if !equivalence.is_empty() {
        let _ = writeln!(md, "## Equivalence (margins named in the study file)\n");
        let _ = writeln!(md, "Two one-sided tests: a test alone says equivalent when the 90% interval of the difference (stratified over environments as the primary contrast is, normal approximation across environments) lies inside ±margin; the reading says so only when Holm's p over the {} test(s) is below 0.05. This family is secondary: only the primary family is confirmatory at 5% family-wise.\n", equivalence.len());
        let _ = writeln!(md, "| a − b | metric | margin | difference | 90% CI | p (TOST) | p (Holm) | reading |\n|---|---|---|---|---|---|---|---|");
        for r in equivalence {
            let (d, ci, p) = r.tost.as_ref().map_or(("—".into(), "—".into(), "—".into()), |t| (format!("{:.3}", t.difference), format!("[{:.3}, {:.3}]", t.ci90[0], t.ci90[1]), format_p(t.p_value)));
            let _ = writeln!(md, "| {} − {} | {} | ±{} | {d} | {ci} | {p} | {} | {} |", label(&r.spec.a), label(&r.spec.b), r.spec.metric, r.spec.margin, format_p(r.p_holm), r.reading);
        }
        let _ = writeln!(md);
    }
    for f in factorials {
        let s = &f.spec;
        let _ = writeln!(md, "## Factorial: {} ({}, {})\n", s.name, s.metric, crate::preset::algo_name(s.algorithm).to_uppercase());
        let _ = writeln!(md, "Cells ({} by rows, {} by columns), runs: {} ({}), {} ({}) / {} ({}), {} ({}). Each effect is a contrast of the four cell means with Welch–Satterthwaite degrees of freedom; Holm over the three.\n",
            s.factors[0], s.factors[1], s.cells[0][0], f.runs[0][0], s.cells[0][1], f.runs[0][1], s.cells[1][0], f.runs[1][0], s.cells[1][1], f.runs[1][1]);
        if f.effects.is_empty() {
            let _ = writeln!(md, "No result: a cell has fewer than two finished runs.\n");
            continue;
        }
        let _ = writeln!(md, "| effect | estimate | 95% CI | df | p | p (Holm, 3) |\n|---|---|---|---|---|---|");
        for (e, p) in f.effects.iter().zip(&f.p_holm) {
            let _ = writeln!(md, "| {} | {:.3} | [{:.3}, {:.3}] | {:.1} | {} | {} |", e.name, e.estimate, e.ci95[0], e.ci95[1], e.df, format_p(e.p_value), format_p(*p));
        }
        let _ = writeln!(md);
    }
    md
}

#[cfg(test)]
mod tests {
    use super::super::config::Experiment;
    use super::super::inference::{factorial, tost};
    use super::super::plan::{cells, run_dir};
    use super::super::report::markdown;
    use super::super::study::fixtures::write_run;
    use super::super::study::gather;
    use super::super::stats::welch;

    /// A study naming one equivalence test and one 2 × 2: the report
    /// carries exactly what the inference functions give on its runs.
    #[test]
    fn named_tests_reach_the_report() {
        let text = "name = \"n\"\nenvironments = [\"lti-paper\"]\nalgorithms = [\"ppo\"]\n\
                    connections = [\"global\", \"full-subnets\", \"local@0.25\", \"local@0.1\"]\nseeds = 3\nepisodes = { ppo = 2 }\n\
                    [[equivalence]]\nmetric = \"eval_return\"\na = \"full-subnets\"\nb = \"global\"\nalgorithm = \"ppo\"\nmargin = 0.5\n\
                    [[factorial]]\nname = \"mask × T\"\nmetric = \"eval_return\"\nalgorithm = \"ppo\"\nfactors = [\"mask\", \"T\"]\n\
                    cells = [[\"lti-paper/global\", \"lti-paper/full-subnets\"], [\"lti-paper/local@0.25\", \"lti-paper/local@0.1\"]]\n";
        let e = Experiment::parse(text).unwrap();
        let tmp = tempfile::tempdir().unwrap();
        let out = tmp.path();
        let returns = [[-3.0, -3.1, -2.9], [-3.05, -2.95, -3.1], [-2.0, -2.2, -1.9], [-1.0, -1.3, -1.1]];
        for (cell, values) in cells(&e).iter().zip(returns) {
            for (seed, r) in values.iter().enumerate() {
                write_run(&run_dir(out, cell, seed as u64), "local", seed as u64, *r, Some(0), None);
            }
        }
        let report = gather(&e, out).unwrap().report();
        let eq = &report.equivalence[0];
        let w = welch(&returns[1], &returns[0]).unwrap();
        let expected = tost(w.difference, w.se, Some(w.df), 0.5).unwrap();
        assert_eq!(eq.tost.as_ref().unwrap(), &expected);
        assert!(eq.p_holm < 0.05 && eq.reading.starts_with("equivalent within ±0.5"), "{}", eq.reading);
        let f = &report.factorials[0];
        let expected = factorial(&[[&returns[0], &returns[1]], [&returns[2], &returns[3]]], &["mask".into(), "T".into()]).unwrap();
        assert_eq!(f.effects, expected.to_vec());
        assert_eq!(f.runs, [[3, 3], [3, 3]]);
        let md = markdown(&report);
        assert!(md.contains("## Equivalence (margins named in the study file)") && md.contains("## Factorial: mask × T (eval_return, PPO)"), "{md}");
        assert!(md.contains("| mask × T (interaction) |"), "{md}");
    }
}
