//! The run room's test helpers: `lcrl train`'s loop on lti-paper, whole or
//! stopped early, and what it records without the clock.

use std::path::Path;

use crate::config::{Algo, Connection, TrainConfig};
use crate::run::files::EpisodeRow;
use crate::run::trainer::{train, TrainOutcome, TrainRequest};

/// A run of lti-paper in `dir` (continuing its checkpoint with `resume`).
pub(crate) fn run(algo: Algo, connection: Connection, cfg: TrainConfig, dir: &Path, resume: bool) -> TrainOutcome {
    run_until(algo, connection, cfg, dir, resume, None)
}

/// [`run`], stopped after `stop_after` episodes when given.
pub(crate) fn run_until(algo: Algo, connection: Connection, cfg: TrainConfig, dir: &Path, resume: bool, stop_after: Option<usize>) -> TrainOutcome {
    let request = TrainRequest {
        env: "lti-paper".into(),
        algo,
        connection,
        graph: None,
        config: cfg,
        settings_source: "test".into(),
        run_dir: dir.into(),
        resume,
        stop_after,
    };
    train(&request, &mut |_| {}).unwrap()
}

/// Rows without their wall-clock columns.
pub(crate) fn timeless(rows: &[EpisodeRow]) -> Vec<(usize, f64, usize)> {
    rows.iter().map(|r| (r.episode, r.episode_return, r.length)).collect()
}
