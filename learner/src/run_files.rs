//! The records of a run directory that people and tools read: one
//! `metrics.csv` row per episode and `summary.json` at the end, the same
//! files from `lcrl train` and from the distributed learner.

use std::path::Path;

use serde::{Deserialize, Serialize};

use crate::config::{Algo, Connection};
use crate::{io, LearnerError};


/// One row of metrics.csv.
#[derive(Debug, Clone, Default, PartialEq, Serialize, Deserialize)]
pub struct EpisodeRow {
    pub episode: usize,
    #[serde(rename = "return")]
    pub episode_return: f64,
    pub length: usize,
    pub success: Option<bool>,
    pub peak_force_n: Option<f64>,
    pub peak_moment_nm: Option<f64>,
    /// Wall time of the episode and the part of it spent in updates
    /// (`lcrl train`; empty where actors ran the episode elsewhere).
    pub wall_s: Option<f64>,
    pub optimization_s: Option<f64>,
    /// The return split into its reward terms (peg tasks; docs/peg.md):
    /// the last five columns. Read by name; written after the row's own
    /// fields ([`MetricsLog::push`]), since the csv crate writes no
    /// flattened struct.
    #[serde(flatten, skip_serializing)]
    pub terms: lcrl_sim::ReturnColumns,
}

/// The columns of metrics.csv, in EpisodeRow's order.
pub const METRICS_COLUMNS: [&str; 13] = [
    "episode",
    "return",
    "length",
    "success",
    "peak_force_n",
    "peak_moment_nm",
    "wall_s",
    "optimization_s",
    "return_depth",
    "return_force",
    "return_moment",
    "return_bonus",
    "return_failure",
];

impl EpisodeRow {
    /// Fills the return-term columns from the episode's metrics.
    pub fn with_terms(self, terms: Option<lcrl_sim::ReturnTerms>) -> Self {
        EpisodeRow { terms: terms.into(), ..self }
    }
}

/// One validation of the policy after `episode` training episodes.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
pub struct Validation {
    pub episode: usize,
    pub mean_return: f64,
    pub success_rate: Option<f64>,
}

/// selection.json: which policy was chosen, on how many starts, and every
/// validation that chose it.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct SelectionRecord {
    /// The training episodes behind the chosen policy (0: the starting one).
    pub episode: usize,
    pub validation_return: f64,
    pub validation_success_rate: Option<f64>,
    /// Validation starts per validation.
    pub starts: usize,
    pub history: Vec<Validation>,
}

/// What summary.json holds.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct TrainSummary {
    pub env: String,
    pub algo: Algo,
    pub connection: Connection,
    pub seed: u64,
    pub episodes: usize,
    /// Mean return of the last 10 training episodes (with exploration).
    pub final_return: f64,
    /// Mean return of the deterministic policy over `eval_episodes` episodes.
    pub eval_return: f64,
    /// The evaluation's first start (its episodes use this seed and the
    /// following ones); absent in runs written before it was recorded.
    #[serde(default)]
    pub eval_seed: Option<u64>,
    /// The evaluation's success rate and mean peak force (peg tasks).
    #[serde(default)]
    pub eval_success_rate: Option<f64>,
    #[serde(default)]
    pub eval_peak_force_n: Option<f64>,
    /// The evaluation return split into its reward terms (peg tasks).
    #[serde(flatten)]
    pub eval_terms: lcrl_sim::ReturnColumns,
    /// With validation on (run.validation_episodes > 0), `eval_return` is
    /// the selected policy's, and this is the last policy's on the same
    /// episodes.
    #[serde(default)]
    pub last_eval_return: Option<f64>,
    /// Which policy validation chose, and every validation.
    #[serde(default)]
    pub selection: Option<SelectionRecord>,
    /// The neutral constant action a = 0 on the same evaluation episodes
    /// (on peg tasks the constant compliance controller): a reference line.
    #[serde(default)]
    pub zero_action_return: Option<f64>,
    /// Every reference controller on the same evaluation episodes (a = 0,
    /// and the best constant where one is recorded for the environment):
    /// the evaluator `lcrl run` uses too.
    #[serde(default)]
    pub references: Vec<lcrl_sim::evaluate::Summary>,
    /// The LQR controller's mean return on the same evaluation episodes
    /// (linear environments only).
    pub lqr_return: Option<f64>,
    /// The best controller with the actor's connection pattern (a = −K s
    /// with K zero where the mask is): the ceiling of a local actor, which
    /// may be below `lqr_return` when G hides states the optimum uses.
    pub masked_lqr_return: Option<f64>,
    pub graph_seconds: f64,
    pub optimization_seconds: f64,
    pub total_seconds: f64,
    pub env_steps: u64,
    pub updates: u64,
    /// Transitions drawn from the replay buffer (DDPG: batch_size per critic
    /// update); against env_steps, the replay ratio the run kept.
    #[serde(default)]
    pub samples_drawn: u64,
    pub actor_params: usize,
    pub critic_params: usize,
}

/// The first `keep` rows of a metrics.csv (a resumed run's history).
pub fn read_rows(path: &Path, keep: usize) -> Result<Vec<EpisodeRow>, LearnerError> {
    let mut reader = csv::Reader::from_path(path).map_err(|e| LearnerError::Checkpoint(format!("{}: {e}", path.display())))?;
    let rows: Result<Vec<EpisodeRow>, _> = reader.deserialize().take(keep).collect();
    rows.map_err(|e| LearnerError::Checkpoint(format!("{}: {e}", path.display())))
}

/// metrics.csv, one flushed row per episode, so an interrupted run still
/// leaves a well-formed file.
pub struct MetricsLog {
    path: std::path::PathBuf,
    writer: csv::Writer<std::fs::File>,
}

impl MetricsLog {
    /// Starts `path` afresh with `rows` (a resumed run's kept history).
    pub fn create(path: &Path, rows: &[EpisodeRow]) -> Result<Self, LearnerError> {
        let file = std::fs::File::create(path).map_err(io(path))?;
        let mut log = Self::over(path, file, true)?;
        for row in rows {
            log.push(row)?;
        }
        Ok(log)
    }

    /// Appends to `path` (the distributed learner, resumed or not),
    /// starting it with the header when it is new.
    pub fn append(path: &Path) -> Result<Self, LearnerError> {
        let new = std::fs::metadata(path).map_or(true, |m| m.len() == 0);
        let file = std::fs::OpenOptions::new().create(true).append(true).open(path).map_err(io(path))?;
        Self::over(path, file, new)
    }

    fn over(path: &Path, file: std::fs::File, header: bool) -> Result<Self, LearnerError> {
        // The header is written by hand, now (serde's automatic header
        // waits for a first row).
        let mut writer = csv::WriterBuilder::new().has_headers(false).from_writer(file);
        if header {
            writer.write_record(METRICS_COLUMNS).map_err(|e| LearnerError::Checkpoint(e.to_string()))?;
            writer.flush().map_err(io(path))?;
        }
        Ok(MetricsLog { path: path.to_path_buf(), writer })
    }

    pub fn push(&mut self, row: &EpisodeRow) -> Result<(), LearnerError> {
        self.writer.serialize((row, &row.terms)).map_err(|e| LearnerError::Checkpoint(format!("{}: {e}", self.path.display())))?;
        self.writer.flush().map_err(io(&self.path))
    }
}

/// Writes `value` as pretty JSON to `run_dir/summary.json`: whole, then
/// renamed, because a summary.json marks a finished run (`lcrl experiment`
/// skips it), so it must never be half a file.
pub fn write_summary<T: Serialize>(run_dir: &Path, value: &T) -> Result<(), LearnerError> {
    let text = serde_json::to_string_pretty(value).map_err(|e| LearnerError::Checkpoint(e.to_string()))?;
    write_atomically(&run_dir.join("summary.json"), (text + "\n").as_bytes())
}

/// Writes `bytes` to `path` whole or not at all, the one atomic writer of
/// every file a run or a command writes: into `.NAME.PID.partial` beside
/// it (the folder is created if needed), flushed to disk (fsync), then
/// renamed over it. A crash leaves the old file or the new one, never half
/// of one.
pub fn write_atomically(path: &Path, bytes: &[u8]) -> Result<(), LearnerError> {
    use std::io::Write as _;
    let dir = path.parent().filter(|p| !p.as_os_str().is_empty()).unwrap_or(Path::new("."));
    std::fs::create_dir_all(dir).map_err(io(dir))?;
    let name = path.file_name().map(|n| n.to_string_lossy().into_owned()).unwrap_or_default();
    let partial = dir.join(format!(".{name}.{}.partial", std::process::id()));
    let mut file = std::fs::File::create(&partial).map_err(io(&partial))?;
    file.write_all(bytes).and_then(|()| file.sync_all()).map_err(io(&partial))?;
    drop(file);
    std::fs::rename(&partial, path).map_err(io(path))
}

#[cfg(test)]
mod tests {
    use super::*;

    /// Rows with return terms (peg) and without (linear systems: blank
    /// columns) come back from metrics.csv as they went in, under the
    /// header METRICS_COLUMNS names, 13 fields a row.
    #[test]
    fn metrics_rows_round_trip_with_and_without_terms() {
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join("metrics.csv");
        let terms = lcrl_sim::ReturnTerms { depth: -0.78, force: -4.11, moment: -0.48, bonus: 2.0, failure: 0.0 };
        let peg = EpisodeRow { episode: 1, episode_return: terms.total(), length: 52, success: Some(true), peak_force_n: Some(12.97), wall_s: Some(0.1), ..Default::default() }.with_terms(Some(terms));
        let lti = EpisodeRow { episode: 2, episode_return: -41.5, length: 50, optimization_s: Some(0.02), ..Default::default() };
        assert_eq!(peg.terms.return_force, Some(-4.11));
        let mut log = MetricsLog::create(&path, &[peg.clone()]).unwrap();
        log.push(&lti).unwrap();
        drop(log);
        let text = std::fs::read_to_string(&path).unwrap();
        let lines: Vec<&str> = text.lines().collect();
        assert_eq!(lines[0], METRICS_COLUMNS.join(","));
        assert!(lines.iter().all(|l| l.split(',').count() == METRICS_COLUMNS.len()), "{text}");
        assert_eq!(read_rows(&path, 10).unwrap(), vec![peg, lti]);
    }
}
