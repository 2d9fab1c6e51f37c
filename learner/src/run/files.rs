//! The records of a run directory that people and tools read: one
//! `metrics.csv` row per episode, the selection record, and the atomic
//! writer every run file goes through (summary.json: crate::run::summary). The
//! same files from `lcrl train` and from the distributed learner.

use std::path::Path;

use serde::{Deserialize, Serialize};

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
    /// The end's second look (`run.confirm_candidates`): the best few
    /// validated policies and the starting one scored on many more starts;
    /// when present, `episode` is the one it handed over.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub confirmation: Option<Confirmation>,
}

impl SelectionRecord {
    /// How the policy was chosen, in words for a log or a status line.
    pub fn how_chosen(&self) -> String {
        let validated = format!("{} validations on {} held-out starts", self.history.len(), self.starts);
        match &self.confirmation {
            Some(c) => {
                let score = c.candidates.iter().find(|k| k.episode == self.episode).map_or(f64::NAN, |k| k.mean_return);
                format!("best of {} candidates on {} confirmation starts ({score:.4}; {:.4} in its validation), from {validated}", c.candidates.len(), c.starts, self.validation_return)
            }
            None => format!("best of {validated} ({:.4})", self.validation_return),
        }
    }
}

/// The confirmation of a run's choice: each candidate's score on the
/// confirmation starts (`lcrl_sim::seeds::confirmation`), in the order
/// they were ranked by validation (the starting policy last unless it
/// ranked). The chosen one is the best score, the higher-ranked of equals.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct Confirmation {
    pub starts: usize,
    pub candidates: Vec<ConfirmedCandidate>,
}

/// One candidate of a confirmation.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
pub struct ConfirmedCandidate {
    /// The training episodes behind the policy (0: the starting one).
    pub episode: usize,
    pub validation_return: f64,
    pub mean_return: f64,
    pub success_rate: Option<f64>,
}

/// The rows of a metrics.csv through episode `through` (a resumed run's
/// history, `through` its checkpoint's episode), one per episode in order.
/// Reading stops there, so rows written after the checkpoint (and a last
/// row cut short by a kill) are never read. A row whose episode does not
/// follow the one before is one a learner before this fix wrote again
/// after a resume, and is skipped.
pub fn read_rows(path: &Path, through: usize) -> Result<Vec<EpisodeRow>, LearnerError> {
    let (rows, error) = rows_through(path, through);
    match error {
        Some(e) => Err(e),
        None => Ok(rows),
    }
}

/// [`read_rows`], with the rows before an unreadable one kept beside the
/// error.
fn rows_through(path: &Path, through: usize) -> (Vec<EpisodeRow>, Option<LearnerError>) {
    let bad = |e: csv::Error| LearnerError::Checkpoint(format!("{}: {e}", path.display()));
    let mut rows: Vec<EpisodeRow> = Vec::new();
    if through == 0 {
        return (rows, None);
    }
    let mut reader = match csv::Reader::from_path(path) {
        Ok(reader) => reader,
        Err(e) => return (rows, Some(bad(e))),
    };
    for row in reader.deserialize::<EpisodeRow>() {
        let row = match row {
            Ok(row) => row,
            Err(e) => return (rows, Some(bad(e))),
        };
        if row.episode > through {
            break;
        }
        if rows.last().is_some_and(|last| row.episode <= last.episode) {
            continue;
        }
        let done = row.episode == through;
        rows.push(row);
        if done {
            break;
        }
    }
    (rows, None)
}

/// metrics.csv, one flushed row per episode, so an interrupted run still
/// leaves a well-formed file.
///
/// Each row goes out in one write. One that fails (a full disk) is cut off
/// the file again, so no torn row is left between whole ones, and kept in
/// memory (up to [`MAX_PENDING_ROWS`]) to be written before the next row:
/// a disk that fills and frees again costs no row.
pub struct MetricsLog {
    path: std::path::PathBuf,
    file: std::fs::File,
    /// The file's length after its last whole row.
    written: u64,
    /// Encoded rows not yet on disk, oldest first.
    pending: std::collections::VecDeque<Vec<u8>>,
}

/// Rows kept in memory while the disk refuses them (about 200 bytes each):
/// beyond them the oldest is dropped, and the drop logged.
pub const MAX_PENDING_ROWS: usize = 100_000;

impl MetricsLog {
    /// Starts `path` afresh with `rows` (a resumed run's kept history).
    /// The rows go into `.NAME.partial` first, flushed to disk, which then
    /// replaces `path` (later rows are appended to it there): a kill while
    /// the history is rewritten leaves the old file, never a cut one.
    pub fn create(path: &Path, rows: &[EpisodeRow]) -> Result<Self, LearnerError> {
        let name = path.file_name().map(|n| n.to_string_lossy().into_owned()).unwrap_or_default();
        let partial = path.with_file_name(format!(".{name}.partial"));
        let file = std::fs::OpenOptions::new().create(true).truncate(true).write(true).open(&partial).map_err(io(&partial))?;
        let mut log = Self::over(&partial, file)?;
        for row in rows {
            log.push(row)?;
        }
        log.file.sync_all().map_err(io(&partial))?;
        std::fs::rename(&partial, path).map_err(io(path))?;
        let dir = lcrl_runtime::files::folder_of(path);
        lcrl_runtime::files::sync_dir(dir).map_err(io(dir))?;
        log.path = path.to_path_buf();
        Ok(log)
    }

    /// Continues `path` from episode `through` (the distributed learner's
    /// checkpoint; 0 for a new run): the rows after it are dropped, as the
    /// episodes they record are trained again and written anew, so no
    /// episode appears twice. An unreadable row ends the history kept
    /// (logged): what follows it cannot be trusted either.
    pub fn resume(path: &Path, through: usize) -> Result<Self, LearnerError> {
        let rows = if path.exists() {
            let (rows, error) = rows_through(path, through);
            if let Some(e) = error {
                tracing::warn!("metrics.csv kept through episode {}: {e}", rows.last().map_or(0, |r| r.episode));
            }
            rows
        } else {
            Vec::new()
        };
        Self::create(path, &rows)
    }

    /// A log over a new, empty `file`, starting with the header.
    fn over(path: &Path, file: std::fs::File) -> Result<Self, LearnerError> {
        let mut log = MetricsLog { path: path.to_path_buf(), file, written: 0, pending: Default::default() };
        // The header is written by hand, now (serde's automatic header
        // waits for a first row).
        let mut header = csv::WriterBuilder::new().has_headers(false).from_writer(Vec::new());
        header.write_record(METRICS_COLUMNS).map_err(|e| LearnerError::Checkpoint(e.to_string()))?;
        log.pending.push_back(header.into_inner().map_err(|e| LearnerError::Checkpoint(e.to_string()))?);
        log.write_pending()?;
        Ok(log)
    }

    /// Appends `row`; an error leaves it (and any earlier refused ones)
    /// pending for the next call.
    pub fn push(&mut self, row: &EpisodeRow) -> Result<(), LearnerError> {
        let mut line = csv::WriterBuilder::new().has_headers(false).from_writer(Vec::new());
        line.serialize((row, &row.terms)).map_err(|e| LearnerError::Checkpoint(format!("{}: {e}", self.path.display())))?;
        self.pending.push_back(line.into_inner().map_err(|e| LearnerError::Checkpoint(e.to_string()))?);
        if self.pending.len() > MAX_PENDING_ROWS {
            self.pending.pop_front();
            tracing::warn!("{}: more than {MAX_PENDING_ROWS} rows the disk refused; dropping the oldest", self.path.display());
        }
        self.write_pending()
    }

    /// Writes the pending rows, each whole or not at all.
    fn write_pending(&mut self) -> Result<(), LearnerError> {
        use std::io::{Seek, Write};
        while let Some(line) = self.pending.front() {
            let wrote = self.file.seek(std::io::SeekFrom::Start(self.written)).and_then(|_| self.file.write_all(line));
            if let Err(e) = wrote {
                // Part of the row may be on disk: cut it off again.
                let _ = self.file.set_len(self.written);
                return Err(LearnerError::Io { path: self.path.clone(), source: e });
            }
            self.written += line.len() as u64;
            self.pending.pop_front();
        }
        Ok(())
    }

    /// Rows waiting for the disk.
    pub fn pending(&self) -> usize {
        self.pending.len()
    }
}

/// [`lcrl_runtime::files::write_atomically`] (temp file, fsync, rename), the
/// one atomic writer of every file a run or a command writes.
pub fn write_atomically(path: &Path, bytes: &[u8]) -> Result<(), LearnerError> {
    lcrl_runtime::files::write_atomically(path, bytes).map_err(io(path))
}

#[cfg(test)]
mod tests {
    use super::*;

    /// A row the disk refuses is not left torn in the file and is written,
    /// in order, once the disk takes rows again. /dev/full refuses every
    /// write with ENOSPC, as a full disk does.
    #[test]
    fn rows_the_disk_refused_are_written_whole_once_it_takes_them() {
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join("metrics.csv");
        let mut log = MetricsLog::create(&path, &[]).unwrap();
        let row = |episode| EpisodeRow { episode, episode_return: -1.5, length: 50, ..Default::default() };
        log.push(&row(1)).unwrap();
        let good = std::mem::replace(&mut log.file, std::fs::OpenOptions::new().write(true).open("/dev/full").unwrap());
        let refused = log.push(&row(2)).unwrap_err();
        assert!(refused.to_string().contains("No space left"), "{refused}");
        assert!(log.push(&row(3)).is_err());
        assert_eq!(log.pending(), 2);
        log.file = good;
        log.push(&row(4)).unwrap();
        assert_eq!(log.pending(), 0);
        let episodes: Vec<usize> = read_rows(&path, 10).unwrap().iter().map(|r| r.episode).collect();
        assert_eq!(episodes, vec![1, 2, 3, 4]);
    }

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

    fn row(episode: usize) -> EpisodeRow {
        EpisodeRow { episode, episode_return: -(episode as f64), length: 10, ..Default::default() }
    }

    /// Finding 10: a distributed learner resumed from its checkpoint
    /// appended to metrics.csv, so the episodes it had recorded after the
    /// checkpoint appeared twice. Resuming cuts the file back to the
    /// checkpoint's episode, the row a kill cut short included.
    #[test]
    fn resuming_cuts_metrics_back_to_the_checkpoint() {
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join("metrics.csv");
        let mut log = MetricsLog::resume(&path, 0).unwrap();
        for episode in 1..=8 {
            log.push(&row(episode)).unwrap();
        }
        drop(log);
        // Killed while writing episode 9's row, after the checkpoint at 5.
        let mut text = std::fs::read_to_string(&path).unwrap();
        text.push_str("9,-9.0,1");
        std::fs::write(&path, text).unwrap();
        let mut log = MetricsLog::resume(&path, 5).unwrap();
        for episode in 6..=7 {
            log.push(&row(episode)).unwrap();
        }
        drop(log);
        assert_eq!(read_rows(&path, usize::MAX).unwrap(), (1..=7).map(row).collect::<Vec<_>>());
        let left: Vec<_> = std::fs::read_dir(dir.path()).unwrap().map(|e| e.unwrap().file_name()).collect();
        assert_eq!(left, vec![std::ffi::OsString::from("metrics.csv")]);
        // A new run (no checkpoint) starts with the header alone.
        drop(MetricsLog::resume(&path, 0).unwrap());
        assert_eq!(read_rows(&path, usize::MAX).unwrap(), vec![]);
    }

    /// `lcrl train` reads its history through the checkpoint's episode, as
    /// it read the first rows before; repeats an older learner wrote are
    /// read once, and a damaged row before the checkpoint is an error.
    #[test]
    fn the_history_is_read_through_the_checkpoint_once_per_episode() {
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join("metrics.csv");
        let mut log = MetricsLog::create(&path, &(1..=4).map(row).collect::<Vec<_>>()).unwrap();
        for episode in [3, 4, 5, 6] {
            log.push(&row(episode)).unwrap();
        }
        drop(log);
        assert_eq!(read_rows(&path, 5).unwrap(), (1..=5).map(row).collect::<Vec<_>>());
        assert_eq!(read_rows(&path, 0).unwrap(), vec![]);
        let mut text = std::fs::read_to_string(&path).unwrap();
        text.push_str("7,oops\n");
        std::fs::write(&path, text).unwrap();
        assert_eq!(read_rows(&path, 6).unwrap().len(), 6);
        assert!(read_rows(&path, 7).is_err());
    }
}
