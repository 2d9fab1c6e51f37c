//! The distributed learner's record of finished episodes: metrics.csv (the
//! same writer and columns as `lcrl train`) and TensorBoard scalars, with
//! the learner's flow figures beside them.

use std::sync::atomic::Ordering;

use crate::service::shared::Shared;

/// Where finished episodes are recorded: metrics.csv (episode, return,
/// length, success; what `lcrl compare` and the reward curve read) and
/// TensorBoard scalars beside it.
pub struct EpisodeLog {
    /// None when the file cannot be opened (warned once; training goes on).
    csv: Option<crate::run::files::MetricsLog>,
    tensorboard: Option<crate::run::tensorboard::EventWriter>,
}

impl EpisodeLog {
    /// Opens the records of a run that has `episodes` done (its
    /// checkpoint's; 0 for a new run). metrics.csv is cut back to them: a
    /// learner killed after its last checkpoint had written rows for
    /// episodes that are now trained again.
    pub fn open(run_dir: &std::path::Path, episodes: u64) -> EpisodeLog {
        let tensorboard = crate::run::tensorboard::EventWriter::create(run_dir)
            .map_err(|e| tracing::warn!("no TensorBoard events in {}: {e}", run_dir.display()))
            .ok();
        let csv = crate::run::files::MetricsLog::resume(&run_dir.join("metrics.csv"), episodes as usize).map_err(|e| tracing::warn!("no metrics.csv: {e}")).ok();
        EpisodeLog { csv, tensorboard }
    }

    pub fn append(&mut self, first: u64, episodes: &[lcrl_proto::v1::EpisodeSummary], shared: &Shared) -> std::io::Result<()> {
        // Every row is handed over even when the disk refuses one: the log
        // keeps refused rows and writes them once it can.
        let mut refused = None;
        if let Some(csv) = &mut self.csv {
            for (k, e) in episodes.iter().enumerate() {
                // The actors report what the environment measured; the
                // wall and update times are `lcrl train`'s own.
                let row = crate::run::files::EpisodeRow {
                    episode: (first + k as u64 + 1) as usize,
                    episode_return: e.episode_return,
                    length: e.length as usize,
                    success: e.success,
                    peak_force_n: e.peak_force_n,
                    peak_moment_nm: e.peak_moment_nm,
                    ..Default::default()
                }
                .with_terms(e.return_terms.as_ref().map(|t| lcrl_sim::ReturnTerms { depth: t.depth, force: t.force, moment: t.moment, bonus: t.bonus, failure: t.failure }));
                if let Err(e) = csv.push(&row) {
                    refused.get_or_insert(e);
                }
            }
        }
        if let Some(e) = refused {
            return Err(std::io::Error::other(e));
        }
        if let Some(tb) = &mut self.tensorboard {
            for (k, e) in episodes.iter().enumerate() {
                tb.scalars((first + k as u64 + 1) as i64, &[("episode/return", e.episode_return), ("episode/length", f64::from(e.length))])?;
            }
            let step = (first + episodes.len() as u64) as i64;
            // Read under the lock: no copy of the lag window per batch.
            let (ratio, (lag_min, lag_mean, lag_max), actors_waited, learner_waited) = {
                let f = shared.flow_mut();
                (f.achieved_ratio(), f.lag.stats(), f.actors_waited_s, f.learner_waited_s)
            };
            let learner = [
                ("learner/env_steps", shared.env_steps.load(Ordering::Relaxed) as f64),
                ("learner/updates", shared.updates.load(Ordering::Relaxed) as f64),
                ("learner/policy_version", shared.policy_version() as f64),
                ("learner/replay_ratio", ratio),
                ("learner/policy_lag_min", lag_min as f64),
                ("learner/policy_lag_mean", lag_mean),
                ("learner/policy_lag_max", lag_max as f64),
                ("learner/actors_waited_s", actors_waited),
                ("learner/learner_waited_s", learner_waited),
            ];
            tb.scalars(step, &learner)?;
            tb.flush()?;
        }
        Ok(())
    }
}
