//! The command-line arguments shared by `lcrl graph` and
//! `lcrl-graph-builder`, and the build-and-save run behind both.

use std::path::{Path, PathBuf};

use tempfile::NamedTempFile;

use crate::{build_graph, plot, Cs3Config, GraphError, GraphOptions, GraphReport, Rule, EXACT_TOLERANCE};

/// Build the LCRL connection graph G with CS3 (docs/method.md Algorithm 1).
#[derive(Debug, Clone, clap::Args)]
pub struct GraphArgs {
    /// Environment: a registered name (lti-paper, peg-group1, ...), a path to a
    /// .toml file, or grpc://HOST:PORT for a served environment (any Gymnasium
    /// environment behind `python -m lcrl_env serve`; CS3 needs it to fork).
    #[arg(long)]
    pub env: String,
    /// ST: CS3 samples per action component; more samples, steadier phi
    /// (1 to 100000000).
    #[arg(long, default_value_t = 256, value_parser = lcrl_runtime::process::count_in::<1, MAX_SAMPLES>)]
    pub samples: usize,
    /// T of eq. 7: keep action i for state j when phi(i,j) ≥ T × the mean
    /// effect of all actions on j [default: 0.1, the publication's value].
    #[arg(long, conflicts_with_all = ["exact", "thresholds"], allow_hyphen_values = true)]
    pub threshold: Option<f64>,
    /// A threshold sweep: G at each T (eq. 7) with its edge count, the
    /// edges that flip between consecutive T, one heatmap panel per T; the
    /// first T is the graph's own (its `g` in the JSON).
    #[arg(long, value_delimiter = ',', conflicts_with = "exact", allow_hyphen_values = true, value_name = "T1,T2,…")]
    pub thresholds: Option<Vec<f64>>,
    /// Where CS3's start states s_0 come from: `trajectory` (a state along
    /// an episode of the a = 0 controller, so often in contact; the default
    /// for peg tasks) or `reset` (an episode start; the default elsewhere).
    #[arg(long, value_enum)]
    pub start: Option<crate::Start>,
    /// Use eq. 6 (G_ij = 1 iff phi ≠ 0) instead of eq. 7; only sensible for
    /// noise-free systems.
    #[arg(long)]
    pub exact: bool,
    /// With --exact: phi counts as 0 below this fraction of the largest phi.
    #[arg(long, default_value_t = EXACT_TOLERANCE, requires = "exact", allow_hyphen_values = true)]
    pub tolerance: f64,
    /// Seed of the CS3 sampling; the same seed gives the same graph.
    #[arg(long, default_value_t = 0)]
    pub seed: u64,
    /// Rollout threads (0: one per core, at most 1024); the result does
    /// not depend on it.
    #[arg(long, default_value_t = 0, value_parser = lcrl_runtime::process::count_in::<0, MAX_THREADS>)]
    pub threads: usize,
    /// Bootstrap resamples for each entry's stability (0 to skip, at most
    /// 100000).
    #[arg(long, default_value_t = crate::DEFAULT_BOOTSTRAP, value_parser = lcrl_runtime::process::count_in::<0, MAX_BOOTSTRAP>)]
    pub bootstrap: usize,
    /// Write the graph as JSON here (read back by `lcrl train --graph`).
    #[arg(long, value_name = "FILE.json")]
    pub out: Option<PathBuf>,
    /// Where phi(ACTION, STATE) comes from: the same paired rollouts split
    /// by the phase of their start (free motion, first contact, sliding,
    /// inserted on peg tasks), each phase's share of phi, the effect step
    /// by step, and the states the action moves first (its physical path).
    /// Names or 1-based indices, e.g. `--explain dx,alpha`.
    #[arg(long, value_name = "ACTION,STATE", conflicts_with_all = ["random", "thresholds", "exact"])]
    pub explain: Option<String>,
    /// Draw K edges at random instead of measuring G (uniform among the
    /// graphs with an edge for every action; --seed picks the draw): the
    /// control graph of `random@K` connections. No CS3 runs.
    #[arg(long, value_name = "K", conflicts_with_all = ["thresholds", "exact", "threshold"])]
    pub random: Option<usize>,
    /// One action's row under its own rule, from the same phi: `dz=0.1`
    /// (eq. 7 at T = 0.1 for dz's row) or `dz=none` (dz gets no inputs);
    /// repeatable. The claim study's dz control (docs/lcrl-value.md).
    #[arg(long = "row", value_name = "ACTION=T|none", value_parser = parse_row, conflicts_with_all = ["exact", "random", "explain"])]
    pub rows: Vec<crate::RowRule>,
    /// Choose T from CS3 alone (docs/method.md, "Choosing T"): print T_rule
    /// (the above-average rule, eq. 7 at T = 1) and why, with a table from
    /// --choose-seeds CS3 seeds (from --seed on): for T = 0.1 to 2.0 each
    /// seed's edges, how often two seeds' graphs differ and how many moved
    /// states no action sees. With --out, writes the choice as JSON. No
    /// training run takes part.
    #[arg(long, conflicts_with_all = ["threshold", "thresholds", "exact", "random", "random_rows", "explain", "rows", "plot"])]
    pub choose_t: bool,
    /// CS3 seeds of --choose-t (2 to 64).
    #[arg(long, default_value_t = 8, requires = "choose_t", value_parser = lcrl_runtime::process::count_in::<2, 64>)]
    pub choose_seeds: usize,
    /// Draw, for every action, as many states as this graph gives it (a
    /// row with none stays empty), uniformly; --seed picks the draw. The
    /// degree-matched control of `random-rows@CONNECTION`. No CS3 runs.
    #[arg(long, value_name = "GRAPH.json", conflicts_with_all = ["thresholds", "exact", "threshold", "random", "rows", "explain"])]
    pub random_rows: Option<PathBuf>,
    /// With --random-rows: the draw's index in its study, recorded in the
    /// graph's origin (and so in every run trained on it) beside its seed.
    #[arg(long, value_name = "K", requires = "random_rows")]
    pub draw: Option<u64>,
    /// Draw the normalized-CS3 heatmap with G marked here (PNG).
    #[arg(long, value_name = "FILE.png", value_parser = crate::plot::png_path)]
    pub plot: Option<PathBuf>,
}

/// The most CS3 samples per action (`--samples`): far beyond any useful
/// precision (the graph service's tests keep a builder busy with 2
/// million), short of counts whose rollouts would never end.
pub const MAX_SAMPLES: usize = 100_000_000;
/// The most rollout threads (`--threads`).
pub const MAX_THREADS: usize = 1024;
/// The most bootstrap resamples (`--bootstrap`).
pub const MAX_BOOTSTRAP: usize = 100_000;


fn parse_row(text: &str) -> Result<crate::RowRule, String> {
    crate::RowRule::parse(text).map_err(|e| e.to_string())
}

impl GraphArgs {
    pub fn options(&self) -> GraphOptions {
        let rule = if self.exact {
            Rule::Exact { tolerance: self.tolerance }
        } else {
            let first = self.thresholds.as_ref().and_then(|t| t.first().copied());
            Rule::Threshold(self.threshold.or(first).unwrap_or(crate::PAPER_THRESHOLD))
        };
        GraphOptions {
            cs3: Cs3Config { samples: self.samples, seed: self.seed, threads: self.threads, start: self.start },
            rule,
            bootstrap: self.bootstrap,
        }
    }

    /// Checks everything that can be checked before the (possibly long)
    /// build, makes the environment, builds the graph with a progress bar,
    /// and writes the requested files (atomically: an old file is replaced
    /// only by a complete new one).
    pub fn run(&self) -> Result<GraphReport, GraphError> {
        let options = self.options();
        options.validate()?;
        let sweep = self.thresholds.clone().unwrap_or_default();
        if let Some(bad) = sweep.iter().find(|t| !(t.is_finite() && **t > 0.0)) {
            return Err(GraphError::Threshold(*bad));
        }
        let env = lcrl_sim::make_env(&self.env)?;
        if let Some(rule) = self.rows.iter().find(|r| !env.spec().action_names.contains(&r.action)) {
            return Err(crate::GraphError::Row(format!("--row {}: no action {} (actions: {})", rule.text(), rule.action, env.spec().action_names.join(", "))));
        }
        let json_out = self.out.as_deref().map(|p| PendingFile::new(p, ".json")).transpose()?;
        let plot_out = self.plot.as_deref().map(|p| PendingFile::new(p, ".png")).transpose()?;
        if let Some(of) = &self.random_rows {
            let source = of.display().to_string();
            let of = crate::given::load_measured_for(of, env.spec())?;
            let mut report = crate::given::random_rows(env.spec(), &of, self.seed)?;
            let draw = self.draw.map(|k| format!("draw {k}, ")).unwrap_or_default();
            report.origin = report.origin.map(|o| format!("{draw}{o}, of {source}"));
            if let Some(file) = json_out {
                report.write_json(file.temp.path())?;
                file.commit()?;
            }
            return Ok(report);
        }
        if let Some(edges) = self.random {
            let report = crate::given::random(env.spec(), edges, self.seed)?;
            if let Some(file) = json_out {
                report.write_json(file.temp.path())?;
                file.commit()?;
            }
            return Ok(report);
        }

        let total = env.spec().action_dim() * self.samples;
        let bar = crate::progress::bar(total as u64, "{msg} [{bar:30}] {pos}/{len} samples, {elapsed} (eta {eta})");
        bar.set_message("CS3 rollouts");
        let report = build_graph(env.as_ref(), &options, &|| bar.inc(1));
        bar.finish_and_clear();
        let report = report?.with_rows(&self.rows)?.with_sweep(&sweep);

        if let Some(file) = json_out {
            report.write_json(file.temp.path())?;
            file.commit()?;
        }
        if let Some(file) = plot_out {
            plot::heatmap(&report, file.temp.path())?;
            file.commit()?;
        }
        Ok(report)
    }
}

impl GraphArgs {
    /// `--choose-t`: T_rule (crate::choose_t) with the table beside it, and
    /// the choice written to --out as JSON; the action names for its text.
    pub fn run_choose_t(&self) -> Result<(crate::choose_t::Choice, Vec<String>), GraphError> {
        let options = self.options();
        options.validate()?;
        let env = lcrl_sim::make_env(&self.env)?;
        let json_out = self.out.as_deref().map(|p| PendingFile::new(p, ".json")).transpose()?;
        let seeds: Vec<u64> = (0..self.choose_seeds as u64).map(|k| self.seed.wrapping_add(k)).collect();
        let total = env.spec().action_dim() * self.samples * seeds.len();
        let bar = crate::progress::bar(total as u64, "{msg} [{bar:30}] {pos}/{len} samples, {elapsed} (eta {eta})");
        bar.set_message("CS3 rollouts");
        let choice = crate::choose_t::measure_and_choose(env.as_ref(), &options.cs3, &seeds, &|| bar.inc(1));
        bar.finish_and_clear();
        let choice = choice?;
        if let Some(file) = json_out {
            let text = serde_json::to_string_pretty(&choice).map_err(|e| GraphError::Json(e.to_string()))?;
            std::fs::write(file.temp.path(), text + "\n").map_err(|source| GraphError::Io { path: file.target.clone(), source })?;
            file.commit()?;
        }
        Ok((choice, env.spec().action_names.clone()))
    }

    /// `--explain ACTION,STATE`: phi(ACTION, STATE) split by phase, from
    /// the same samples (ST, seed, starts) the graph is built from.
    pub fn run_explain(&self, pair: &str) -> Result<crate::explain::Explanation, GraphError> {
        let options = self.options();
        options.validate()?;
        let env = lcrl_sim::make_env(&self.env)?;
        let (i, j) = crate::explain::parse_pair(env.as_ref(), pair).map_err(GraphError::Explain)?;
        let bar = crate::progress::bar(self.samples as u64, "{msg} [{bar:30}] {pos}/{len} samples, {elapsed} (eta {eta})");
        bar.set_message("paired rollouts");
        let explanation = crate::explain::explain(env.as_ref(), &options.cs3, i, j, &|| bar.inc(1));
        bar.finish_and_clear();
        explanation
    }
}

/// An output file reserved before the work starts: a temporary file next to
/// the target, renamed over it once complete. Creating it up front proves
/// the directory is writable before any rollout runs.
struct PendingFile {
    target: PathBuf,
    temp: NamedTempFile,
}

impl PendingFile {
    fn new(target: &Path, suffix: &str) -> Result<Self, GraphError> {
        let dir = match target.parent() {
            Some(d) if !d.as_os_str().is_empty() => d,
            _ => Path::new("."),
        };
        if target.is_dir() {
            return Err(GraphError::Output { path: target.into(), message: "is a directory; give a file name".into() });
        }
        let mut builder = tempfile::Builder::new();
        builder.prefix(".lcrl-").suffix(suffix);
        // tempfile's 0600 is for secrets; results are ordinary files (umask applies).
        #[cfg(unix)]
        builder.permissions(std::os::unix::fs::PermissionsExt::from_mode(0o666));
        let temp = builder
            .tempfile_in(dir)
            .map_err(|e| GraphError::Output { path: target.into(), message: e.to_string() })?;
        Ok(PendingFile { target: target.into(), temp })
    }

    fn commit(self) -> Result<(), GraphError> {
        let target = self.target;
        self.temp
            .persist(&target)
            .map(|_| ())
            .map_err(|e| GraphError::Output { path: target, message: e.error.to_string() })
    }
}
