//! A learner process's incarnation: a random non-zero id drawn at each
//! start and carried by every policy it publishes. Policy versions are
//! ordered within one incarnation only (a restarted learner counts on from
//! its checkpoint, which may be behind what actors last saw), so actors
//! compare incarnations before versions, and an on-policy learner drops
//! the batches of another incarnation (docs/reliability.md).
//!
//! Each start is appended to `RUN/incarnations.csv`: the run's history of
//! learner processes, with the checkpoint each resumed from.

use std::io::Write;
use std::path::Path;

use crate::{io, LearnerError};

/// The run directory's history of learner starts.
pub const HISTORY_FILE: &str = "incarnations.csv";

/// Draws this process's incarnation and records its start in
/// `run_dir/incarnations.csv` (resumed at `episode` and `policy_version`).
pub fn begin(run_dir: &Path, episode: usize, policy_version: u64) -> Result<u64, LearnerError> {
    let incarnation = draw();
    let path = run_dir.join(HISTORY_FILE);
    std::fs::create_dir_all(run_dir).map_err(io(run_dir))?;
    let new = std::fs::metadata(&path).map_or(true, |m| m.len() == 0);
    let mut file = std::fs::OpenOptions::new().create(true).append(true).open(&path).map_err(io(&path))?;
    let started = std::time::SystemTime::now().duration_since(std::time::UNIX_EPOCH).map_or(0, |d| d.as_secs());
    let header = if new { "incarnation,started_unix_s,resumed_episode,resumed_policy_version\n" } else { "" };
    write!(file, "{header}{incarnation:016x},{started},{episode},{policy_version}\n").map_err(io(&path))?;
    file.sync_all().map_err(io(&path))?;
    Ok(incarnation)
}

/// A random non-zero id (0 means "not said" on the wire).
fn draw() -> u64 {
    loop {
        let id = rand::random::<u64>();
        if id != 0 {
            return id;
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// The incarnations recorded in `run_dir`, oldest first.
    pub fn history(run_dir: &Path) -> Result<Vec<u64>, LearnerError> {
        let path = run_dir.join(HISTORY_FILE);
        let text = std::fs::read_to_string(&path).map_err(io(&path))?;
        text.lines()
            .skip(1)
            .map(|line| {
                let id = line.split(',').next().unwrap_or_default();
                u64::from_str_radix(id, 16).map_err(|e| LearnerError::Checkpoint(format!("{}: {line:?}: {e}", path.display())))
            })
            .collect()
    }

    #[test]
    fn every_start_draws_a_new_incarnation_and_keeps_the_history() {
        let run = tempfile::tempdir().unwrap();
        let first = begin(run.path(), 0, 0).unwrap();
        let second = begin(run.path(), 420, 2010).unwrap();
        assert_ne!(first, 0);
        assert_ne!(first, second);
        assert_eq!(history(run.path()).unwrap(), vec![first, second]);
        let text = std::fs::read_to_string(run.path().join(HISTORY_FILE)).unwrap();
        assert!(text.lines().nth(2).unwrap().ends_with(",420,2010"), "{text}");
    }
}
