//! `lcrl experiment report`: gathers the finished runs of a study and
//! writes report.json (cells, comparisons) and report.md (the same as
//! tables), with the best constant controller beside every cell.

use std::collections::BTreeMap;
use std::fmt::Write as _;
use std::path::Path;

use serde::Serialize;

use super::bars::BestConstant;
use super::config::algo_name;
use super::safety::{self, CellSafety, RunSafety};
pub use super::study::{gather, CellRuns, Companion, Comparison, Run, Study};
use super::stats::{censored_estimate, episodes_to_threshold, format_p, holm, mean_ci, reading_adjusted, welch, Estimate, ThresholdEstimate, AVERAGE_WINDOW};
use crate::output::write_atomic;

/// report.json.
#[derive(Debug, Serialize)]
pub struct Report {
    pub experiment: String,
    pub methods: Methods,
    pub best_constant: BTreeMap<String, BestConstant>,
    pub best_policy: BTreeMap<String, BestConstant>,
    pub cells: Vec<CellReport>,
    pub comparisons: Vec<Comparison>,
    /// The study file's `[primary]` contrasts, tested on their own.
    pub primary: Option<super::primary::PrimaryResult>,
    /// The file's `[[equivalence]]` tests.
    #[serde(skip_serializing_if = "Vec::is_empty")]
    pub equivalence: Vec<super::named::EquivalenceResult>,
    /// The file's `[[factorial]]` designs.
    #[serde(skip_serializing_if = "Vec::is_empty")]
    pub factorials: Vec<super::named::FactorialResult>,
    /// Graph cells placed among a `+per-seed` random cell's draws.
    #[serde(skip_serializing_if = "Vec::is_empty")]
    pub random_draws: Vec<super::draws::Placement>,
    /// Runs not finished (yet): their cells report the seeds that are.
    pub missing_runs: Vec<String>,
    /// Companion studies whose cells this report holds (`--with`), with
    /// their folders and the settings in which they differ.
    #[serde(skip_serializing_if = "Vec::is_empty")]
    pub companions: Vec<Companion>,
}

#[derive(Debug, Serialize)]
pub struct Methods {
    pub confidence_interval: &'static str,
    pub test: &'static str,
    pub why_this_test: &'static str,
    pub final_return: &'static str,
    pub episodes_to_threshold: &'static str,
    pub times: &'static str,
    pub bars: &'static str,
    pub safety: &'static str,
}

const METHODS: Methods = Methods {
    confidence_interval: "two-sided 95% Student-t interval of the mean over seeds (n − 1 degrees of freedom)",
    test: "Welch's two-sample t-test, two-sided; difference = mean(a) − mean(b) with its Welch 95% interval",
    why_this_test: "it gives the p-value and the interval of the difference from one model, does not assume the two \
                    connections spread equally across seeds, and works with a handful of seeds; it assumes roughly \
                    normal means, so a single diverged seed (see per_seed) weakens it",
    final_return: "mean return of the last 10 training episodes; eval_return: the deterministic policy after training",
    episodes_to_threshold: "the first episode whose 10-episode mean return reaches the threshold; runs that never do are \
                            censored: they count as the budget, so with any censored run the mean is a lower bound",
    times: "graph_seconds: the cell's graph, built once and shared by its seeds (counted once, as Table II does); \
            optimization_seconds: network updates; total_seconds: graph + the run's wall time",
    bars: "beat_best_constant: runs whose eval return is above the best constant's on the same evaluation starts \
           (every run of a study is evaluated on the starts `lcrl tune` evaluates the best constant on); diverged: runs \
           whose eval return is below a = 0's on the same starts",
    safety: "over training episodes: failed_episodes did not reach the depth within the limits; worst_mean_return is \
             the lowest 10-episode mean return (mean over seeds, and the lowest seed); peak_force_n the highest contact \
             force of any training episode; base: the controller the runs act around (the best constant for residual \
             runs, a = 0 from scratch) on the evaluation starts; below_base: seeds whose worst 10-episode mean fell \
             below the base's return",
};

#[derive(Debug, Serialize)]
pub struct CellReport {
    pub env: String,
    pub algo: String,
    /// The connection's label (with ` [NAME]` for a companion's cell).
    pub connection: String,
    /// The companion study the cell comes from (`--with`).
    #[serde(skip_serializing_if = "Option::is_none")]
    pub from: Option<String>,
    pub episodes: usize,
    pub seeds: Vec<u64>,
    pub final_return: Option<Estimate>,
    pub eval_return: Option<Estimate>,
    pub eval_success_rate: Option<f64>,
    /// Runs whose eval return is above the best constant's, on the same
    /// starts; absent when there is no best constant or some run was
    /// evaluated on other starts (then no count would be fair).
    pub beat_best_constant: Option<usize>,
    /// Runs whose eval return is below a = 0's on the same starts.
    pub diverged: usize,
    pub episodes_to_threshold: Option<ThresholdEstimate>,
    /// The speed measures: area under the first 100 episodes' curve and
    /// episodes to the best constant (crate::experiment::speed).
    pub speed: super::speed::CellSpeed,
    pub graph_seconds: f64,
    pub optimization_seconds: Option<Estimate>,
    pub total_seconds: Option<Estimate>,
    /// Training safety over the cell's seeds.
    pub safety: Option<CellSafety>,
    pub per_seed: Vec<SeedFigures>,
}

#[derive(Debug, Serialize)]
pub struct SeedFigures {
    pub seed: u64,
    pub final_return: f64,
    pub eval_return: f64,
    /// Above the best constant on the same starts (absent: no comparable
    /// best constant).
    pub beats_best_constant: Option<bool>,
    /// Below a = 0 on the same starts.
    pub diverged: bool,
    pub episodes_to_threshold: Option<usize>,
    pub safety: Option<RunSafety>,
}


impl Study {
    pub fn report(&self) -> Report {
        let e = &self.experiment;
        let mut cells = Vec::new();
        for c in &self.cells {
            let threshold = e.reward_threshold(&c.cell.env, c.cell.algo);
            let budget = e.episodes(c.cell.algo);
            let reached: Vec<Option<usize>> =
                c.runs.iter().map(|r| threshold.and_then(|t| episodes_to_threshold(&r.returns, t, AVERAGE_WINDOW))).collect();
            let of = |f: &dyn Fn(&Run) -> f64| mean_ci(&c.runs.iter().map(f).collect::<Vec<_>>());
            let success: Vec<f64> = c.runs.iter().filter_map(|r| r.summary.evaluation.eval_success_rate).collect();
            let bar = self.best_constant.get(&c.cell.env);
            let beats: Vec<Option<bool>> = c
                .runs
                .iter()
                .map(|r| bar.filter(|b| b.same_starts(&r.summary, e.file.eval_episodes)).map(|b| r.summary.evaluation.eval_return > b.mean_return))
                .collect();
            let diverged: Vec<bool> = c.runs.iter().map(|r| diverged(r, bar, e.file.eval_episodes)).collect();
            cells.push(CellReport {
                env: c.cell.env.clone(),
                algo: algo_name(c.cell.algo).into(),
                connection: c.label(),
                from: c.from.clone(),
                episodes: budget,
                seeds: c.runs.iter().map(|r| r.seed).collect(),
                final_return: of(&|r| r.summary.final_return),
                eval_return: of(&|r| r.summary.evaluation.eval_return),
                eval_success_rate: (!success.is_empty()).then(|| success.iter().sum::<f64>() / success.len() as f64),
                beat_best_constant: beats.iter().map(|b| b.map(usize::from)).sum(),
                diverged: diverged.iter().filter(|d| **d).count(),
                episodes_to_threshold: threshold.and_then(|t| censored_estimate(&reached, t, budget)),
                speed: self.cell_speed(c),
                graph_seconds: c.graph_seconds,
                optimization_seconds: of(&|r| r.summary.optimization_seconds),
                total_seconds: of(&|r| c.graph_seconds + r.summary.total_seconds),
                safety: safety::of_cell(
                    &c.runs.iter().filter_map(|r| r.safety).collect::<Vec<_>>(),
                    c.runs.first().and_then(|r| safety::base_of_run(&r.dir, r.summary.evaluation.zero_action_return, bar)),
                ),
                per_seed: c
                    .runs
                    .iter()
                    .zip(&reached)
                    .zip(beats.iter().zip(&diverged))
                    .map(|((r, k), (beats, diverged))| SeedFigures {
                        seed: r.seed,
                        final_return: r.summary.final_return,
                        eval_return: r.summary.evaluation.eval_return,
                        beats_best_constant: *beats,
                        diverged: *diverged,
                        episodes_to_threshold: *k,
                        safety: r.safety,
                    })
                    .collect(),
            });
        }
        Report {
            experiment: e.file.name.clone(),
            methods: METHODS,
            best_constant: self.best_constant.clone(),
            best_policy: self.best_policy.clone(),
            comparisons: self.comparisons(),
            primary: e.file.primary.as_ref().map(|p| super::primary::evaluate(p, self)),
            equivalence: super::named::equivalence(self),
            factorials: super::named::factorials(self),
            random_draws: super::draws::placements(&self.cells.iter().filter(|c| c.from.is_none()).map(|c| (&c.cell, c.runs.iter().map(|r| r.summary.evaluation.eval_return).collect())).collect::<Vec<_>>()),
            cells,
            missing_runs: self.missing.clone(),
            companions: self.companions.clone(),
        }
    }

    /// Per environment and algorithm: each connection with a graph against
    /// global and full-subnets, the matched cell against its matched
    /// global, and each given or measured graph
    /// (graph:PATH, local@T) against each random@K (does the structure
    /// matter, or only the number of inputs?), on final and evaluation
    /// return. A companion study's cell (`--with`) meets the study's own
    /// cells by the same rules, and the study's cell of its connection
    /// (what changing the companion's one setting did); companions' cells
    /// are not compared with each other.
    fn comparisons(&self) -> Vec<Comparison> {
        use crate::connection::ConnectionSpec as C;
        let pairs_with = |a: &C, b: &C| match (a, b) {
            (a, C::Global | C::FullSubnets) => a.has_graph(),
            // A matched global is sized to one local cell: compared with it.
            (a, C::MatchedGlobal { to }) => a == to.as_ref(),
            (C::Graph { .. } | C::Local { .. }, C::Random { .. }) => true,
            // Random rows meet their own measured graph draw by draw (below).
            (a, C::RandomRows { of, .. }) => a == of.as_ref(),
            _ => false,
        };
        // pairs_with(x, x) is false for every connection, so the same-
        // connection rule adds no pair the usual rules make.
        let paired = |a: &CellRuns, b: &CellRuns| match (&a.from, &b.from) {
            (None, Some(_)) => pairs_with(&a.cell.connection, &b.cell.connection) || a.cell.connection == b.cell.connection,
            (None, None) | (Some(_), None) => pairs_with(&a.cell.connection, &b.cell.connection),
            (Some(_), Some(_)) => false,
        };
        let mut out = Vec::new();
        for a in &self.cells {
            for b in self.cells.iter().filter(|b| b.cell.env == a.cell.env && b.cell.algo == a.cell.algo && paired(a, b)) {
                // A random-rows cell's unit is the draw (its runs of one
                // draw share a graph): every pair with it is tested on
                // draw means.
                if matches!(a.cell.connection, C::RandomRows { .. }) || matches!(b.cell.connection, C::RandomRows { .. }) {
                    out.extend(self.draw_comparisons(a, b));
                    continue;
                }
                let metrics: [(&'static str, fn(&Run) -> f64); 2] = [("final_return", |r| r.summary.final_return), ("eval_return", |r| r.summary.evaluation.eval_return)];
                for (metric, f) in metrics {
                    let (xa, xb): (Vec<f64>, Vec<f64>) = (a.runs.iter().map(f).collect(), b.runs.iter().map(f).collect());
                    if let Some(w) = welch(&xa, &xb) {
                        out.push(Comparison {
                            env: a.cell.env.clone(),
                            algo: algo_name(a.cell.algo).into(),
                            a: a.label(),
                            b: b.label(),
                            metric,
                            n_a: xa.len(),
                            n_b: xb.len(),
                            difference: w.difference,
                            ci95: w.ci95,
                            p_value: w.p_value,
                            p_holm: f64::NAN,
                            reading: String::new(),
                            test: "welch_t",
                            observed_minus_expected: None,
                            primary: false,
                        });
                    }
                }
                out.extend(self.speed_comparisons(a, b));
            }
        }
        // The primary contrasts' own rows (their pair and metric in each
        // stratum) are tested above, in the primary family: shown here
        // raw, outside the secondary family.
        for c in out.iter_mut() {
            c.primary = self.is_primary(c);
        }
        // One secondary family: every other comparison the report prints.
        let secondary: Vec<usize> = (0..out.len()).filter(|&i| !out[i].primary).collect();
        let adjusted = holm(&secondary.iter().map(|&i| out[i].p_value).collect::<Vec<_>>());
        for (&i, adjusted) in secondary.iter().zip(adjusted) {
            out[i].p_holm = adjusted;
        }
        for c in out.iter_mut() {
            c.reading = match (c.primary, c.observed_minus_expected) {
                (true, _) => "primary contrast, tested above in its family (this row: one environment, raw p)".into(),
                (false, Some(o_minus_e)) if c.p_holm < 0.05 => {
                    format!("{} reaches the best constant {} than {} (log-rank; the interval is descriptive)", c.a, if o_minus_e > 0.0 { "sooner" } else { "later" }, c.b)
                }
                (false, Some(_)) => "not distinguishable in time to the best constant (log-rank, Holm)".into(),
                (false, None) => reading_adjusted(&c.a, &c.b, c.ci95, c.p_holm),
            };
        }
        out
    }
}

impl Study {
    /// Whether a comparison row is a primary contrast's pair and metric in
    /// one of its strata.
    fn is_primary(&self, c: &Comparison) -> bool {
        let label = |text: &str| crate::connection::ConnectionSpec::parse(text).map(|c| c.label()).unwrap_or_default();
        let e = &self.experiment;
        e.file.primary.as_ref().is_some_and(|p| {
            p.contrasts().iter().any(|k| {
                let strata = if k.environments.is_empty() { &e.file.environments } else { &k.environments };
                // Either order, and a random-rows side by its draw means.
                let side = |s: &str| s.strip_suffix(" (draw means)").unwrap_or(s).to_string();
                let (a, b) = (side(&c.a), side(&c.b));
                let pair = (label(&k.a), label(&k.b));
                (pair == (a.clone(), b.clone()) || pair == (b, a)) && k.metric == c.metric && algo_name(k.algorithm) == c.algo && strata.contains(&c.env)
            })
        })
    }
}

/// A run diverged when its eval return is below a = 0's on the same starts:
/// the run's own a = 0 evaluation (summary.json), or else the best
/// constant's file when the run was evaluated on its starts.
fn diverged(run: &Run, bar: Option<&BestConstant>, eval_episodes: usize) -> bool {
    let zero = run.summary.evaluation.zero_action_return.or_else(|| bar.filter(|b| b.same_starts(&run.summary, eval_episodes)).map(|b| b.zero_action_return));
    zero.is_some_and(|zero| run.summary.evaluation.eval_return < zero)
}

/// Three decimals, as every number in report.md.
pub fn num(x: f64) -> String {
    format!("{x:.3}")
}

fn estimate(e: &Option<Estimate>) -> String {
    match e {
        Some(Estimate { mean, ci95: Some([lo, hi]), .. }) => format!("{} [{}, {}]", num(*mean), num(*lo), num(*hi)),
        Some(Estimate { mean, .. }) => num(*mean),
        None => "—".into(),
    }
}

/// report.md: one table per environment and algorithm, then comparisons.
pub fn markdown(report: &Report) -> String {
    let mut md = String::new();
    let _ = writeln!(md, "# Experiment `{}`\n", report.experiment);
    let m = &report.methods;
    let _ = writeln!(md, "Intervals: {}. Test: {} ({}).\n", m.confidence_interval, m.test, m.why_this_test);
    let _ = writeln!(md, "Final return: {}. Episodes to threshold: {}. Times: {}.\n", m.final_return, m.episodes_to_threshold, m.times);
    let _ = writeln!(md, "Bars: {}.\n", m.bars);
    let _ = writeln!(md, "Training safety: {}.\n", m.safety);
    if let Some(p) = &report.primary {
        md.push_str(&super::primary::markdown(p));
    }
    md.push_str(&super::named::markdown(&report.equivalence, &report.factorials));
    if !report.companions.is_empty() {
        let _ = writeln!(md, "**Companion studies** (`--with`; their cells are labelled `CONNECTION [NAME]`):\n");
        for c in &report.companions {
            let differs = if c.differs.is_empty() { "no setting".to_string() } else { c.differs.join("; ") };
            let _ = writeln!(md, "- {} ({}), differs in: {differs}", c.name, c.dir);
        }
        let _ = writeln!(md);
    }
    if !report.missing_runs.is_empty() {
        let _ = writeln!(md, "**Not finished ({}):** {}\n", report.missing_runs.len(), report.missing_runs.join(", "));
    }
    let mut groups: Vec<(&str, &str)> = Vec::new();
    for c in &report.cells {
        if !groups.contains(&(c.env.as_str(), c.algo.as_str())) {
            groups.push((&c.env, &c.algo));
        }
    }
    for (env, algo) in groups {
        let rows: Vec<&CellReport> = report.cells.iter().filter(|c| c.env == env && c.algo == algo).collect();
        results_table(&mut md, report, env, algo, &rows);
        let _ = writeln!(md);
        per_seed_lines(&mut md, report, env, &rows);
        safety_table(&mut md, &rows);
        comparisons_table(&mut md, report, env, algo);
        let _ = writeln!(md);
    }
    md.push_str(&super::draws::markdown(&report.random_draws));
    md
}

/// The table of one environment and algorithm: a row per connection, then
/// the best constant, a = 0 and the best feedback policy where known.
fn results_table(md: &mut String, report: &Report, env: &str, algo: &str, rows: &[&CellReport]) {
    let threshold = rows.iter().find_map(|c| c.episodes_to_threshold.as_ref().map(|t| t.threshold));
    let _ = writeln!(md, "## {env}, {} ({} episodes)\n", algo.to_uppercase(), rows[0].episodes);
    let to = threshold.map_or("episodes to threshold".to_string(), |t| format!("episodes to {}", num(t)));
    let _ = writeln!(md, "| connection | seeds | final return | eval return | success | beat best constant | diverged | {to} | AUC, first 100 | median episodes to best constant | graph s | optimization s | total s |");
    let _ = writeln!(md, "|---|---|---|---|---|---|---|---|---|---|---|---|---|");
    for c in rows {
        let success = c.eval_success_rate.map_or("—".into(), |r| format!("{:.0}%", 100.0 * r));
        let reach = c.episodes_to_threshold.as_ref().map_or("—".into(), |t| {
            let ci = t.ci95.map_or(String::new(), |[lo, hi]| format!(" [{}, {}]", num(lo), num(hi)));
            format!("{}{ci} ({} of {} censored)", num(t.mean), t.censored, t.reached + t.censored)
        });
        let n = c.seeds.len();
        let beat = c.beat_best_constant.map_or("—".into(), |k| format!("{k} of {n}"));
        let (auc, to_bar) = super::speed::columns(&c.speed);
        let _ = writeln!(
            md,
            "| {} | {n} | {} | {} | {success} | {beat} | {} of {n} | {reach} | {auc} | {to_bar} | {} | {} | {} |",
            c.connection,
            estimate(&c.final_return),
            estimate(&c.eval_return),
            c.diverged,
            num(c.graph_seconds),
            estimate(&c.optimization_seconds),
            estimate(&c.total_seconds)
        );
    }
    if let Some(b) = report.best_constant.get(env) {
        let success = b.success_rate.map_or("—".into(), |r| format!("{:.0}%", 100.0 * r));
        let _ = writeln!(md, "| best constant | — | — | {} | {success} | — | — | — | — | — | — | — | — |", num(b.mean_return));
        let _ = writeln!(md, "| a = 0 | — | — | {} | — | — | — | — | {} | — | — | — | — |", num(b.zero_action_return), num(b.zero_action_return));
    }
    if let Some(p) = report.best_policy.get(env) {
        let success = p.success_rate.map_or("—".into(), |r| format!("{:.0}%", 100.0 * r));
        let _ = writeln!(md, "| best feedback policy (headroom) | — | — | {} | {success} | — | — | — | — | — | — | — | — |", num(p.mean_return));
    }
}

/// Each connection's returns seed by seed, and the best constant's action.
fn per_seed_lines(md: &mut String, report: &Report, env: &str, rows: &[&CellReport]) {
    for c in rows {
        // A random-rows run names its draw: index (seed mod draws) and
        // the draw's seed, as its graph.json and summary.json record.
        let spec = crate::connection::ConnectionSpec::parse(&c.connection).ok();
        let draw = |seed: u64| match spec.as_ref().and_then(|spec| spec.draw_of(seed)) {
            Some(k) => format!(" (draw {k}, draw seed {})", lcrl_graph_builder::given::draw_seed(env, k)),
            None => String::new(),
        };
        let seeds: Vec<String> = c.per_seed.iter().map(|s| format!("{}{}: {} / {}", s.seed, draw(s.seed), num(s.final_return), num(s.eval_return))).collect();
        let _ = writeln!(md, "- {} per seed (final / eval): {}", c.connection, seeds.join("; "));
    }
    if let Some(b) = report.best_constant.get(env) {
        let _ = writeln!(md, "- best constant on {} evaluation episodes, action {:?}", b.eval_episodes, b.action.iter().map(|a| num(*a)).collect::<Vec<_>>());
    }
}

/// The training-safety table, when any connection has safety records.
fn safety_table(md: &mut String, rows: &[&CellReport]) {
    if rows.iter().any(|c| c.safety.is_some()) {
        let _ = writeln!(md, "\n| training safety | failed training episodes | worst 10-episode mean (mean [95% CI]) | lowest seed | below the base | peak force, N | base (eval starts) |");
        let _ = writeln!(md, "|---|---|---|---|---|---|---|");
        for c in rows {
            let Some(s) = &c.safety else { continue };
            let base = s.base.as_ref().map_or("—".into(), |b| format!("{} {}", b.controller, num(b.mean_return)));
            let below = s.below_base.map_or("—".into(), |k| format!("{k} of {}", c.seeds.len()));
            let peak = s.peak_force_n.map_or("—".into(), |f| format!("{f:.1}"));
            let _ = writeln!(
                md,
                "| {} | {} of {} | {} | {} | {below} | {peak} | {base} |",
                c.connection,
                s.failed_episodes,
                s.episodes,
                estimate(&s.worst_mean_return),
                num(s.lowest_mean_return)
            );
        }
    }
}

/// The comparisons of one environment and algorithm, with the family's
/// Holm-adjusted p values.
fn comparisons_table(md: &mut String, report: &Report, env: &str, algo: &str) {
    let comparisons: Vec<&Comparison> = report.comparisons.iter().filter(|c| c.env == env && c.algo == algo).collect();
    if !comparisons.is_empty() {
        let family = report.comparisons.iter().filter(|c| !c.primary).count();
        let _ = writeln!(md, "\n| comparison | metric | difference | 95% CI | test | p | p (Holm, {family} comparisons) | reading |");
        let _ = writeln!(md, "|---|---|---|---|---|---|---|---|");
        for c in comparisons {
            let _ = writeln!(
                md,
                "| {} − {} | {} | {} | [{}, {}] | {} | {} | {} | {} |",
                c.a,
                c.b,
                c.metric,
                num(c.difference),
                num(c.ci95[0]),
                num(c.ci95[1]),
                c.test,
                format_p(c.p_value),
                format_p(c.p_holm),
                c.reading
            );
        }
    }
}

/// Writes report.json and report.md into `out`.
pub fn write(report: &Report, out: &Path) -> anyhow::Result<()> {
    write_atomic(&out.join("report.json"), &(serde_json::to_string_pretty(report)? + "\n"))?;
    write_atomic(&out.join("report.md"), &markdown(report))
}

#[cfg(test)]
mod tests;
