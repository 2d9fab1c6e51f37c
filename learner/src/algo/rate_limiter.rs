//! The replay-ratio rate limiter of the distributed learner, with the
//! semantics of Reverb's `SampleToInsertRatio`: a target number of samples
//! per insert (SPI), a minimum number of inserts before the first sample,
//! and an error buffer around the target.
//!
//! Counting in transitions, with `inserts` stored and `samples` drawn by
//! updates, the limiter keeps
//!
//! ```text
//! diff = inserts · SPI − samples
//! ```
//!
//! inside [min_diff, max_diff], where min_diff = SPI · min_size − error and
//! max_diff = SPI · min_size + error:
//!
//! - an insert of k transitions may go ahead while inserts + k ≤ min_size
//!   (filling the buffer is free), or when (inserts + k) · SPI − samples ≤
//!   max_diff; otherwise the learner is behind, and the actors wait;
//! - a sample of k transitions may go ahead once inserts ≥ min_size and
//!   inserts · SPI − (samples + k) ≥ min_diff; otherwise the actors are
//!   behind, and the learner waits.
//!
//! So after warm-up, samples ≈ SPI · (inserts − min_size) within ± error:
//! Algorithm 2 (docs/method.md §5), one update of `batch_size` per
//! environment step after `warmup_steps`, is SPI = batch_size with
//! min_size = max(warmup_steps, batch_size).

use serde::{Deserialize, Serialize};

/// The most samples per insert a limiter takes: far above any useful
/// ratio (Algorithm 2's is one batch of 256 per step), short of values
/// whose products overflow the counters' arithmetic.
pub const MAX_SAMPLES_PER_INSERT: f64 = 1e6;

/// The limiter's settings and counters (saved in checkpoints, so a
/// restarted learner keeps the ratio instead of bursting updates).
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct RateLimiter {
    /// Target transitions sampled per transition inserted.
    pub samples_per_insert: f64,
    /// Inserts before the first sample.
    pub min_size_to_sample: u64,
    /// Allowed distance of diff from its centre, in sampled transitions.
    pub error_buffer: f64,
    /// Transitions inserted so far.
    pub inserts: u64,
    /// Transitions sampled so far.
    pub samples: u64,
}

impl Default for RateLimiter {
    fn default() -> Self {
        RateLimiter::unlimited()
    }
}

impl RateLimiter {
    /// A limiter at the start of a run. `samples_per_insert` and
    /// `error_buffer` must be finite and positive, and the buffer must let
    /// one insert of `largest_insert` transitions and one sample of
    /// `largest_sample` through, or the learner and its actors would wait
    /// on each other forever.
    pub fn new(samples_per_insert: f64, min_size_to_sample: u64, error_buffer: f64) -> Result<Self, String> {
        if !(samples_per_insert.is_finite() && samples_per_insert > 0.0 && samples_per_insert <= MAX_SAMPLES_PER_INSERT) {
            return Err(format!("samples per insert must be a number above 0 and at most {MAX_SAMPLES_PER_INSERT:e}, got {samples_per_insert}"));
        }
        if !(error_buffer.is_finite() && error_buffer > 0.0) {
            return Err(format!("the error buffer must be a finite number > 0, got {error_buffer}"));
        }
        Ok(RateLimiter { samples_per_insert, min_size_to_sample, error_buffer, inserts: 0, samples: 0 })
    }

    /// A limiter that limits nothing and only counts (PPO, and DDPG with
    /// `--replay-ratio unlimited`): every insert and sample may go ahead.
    pub fn unlimited() -> Self {
        RateLimiter { samples_per_insert: 0.0, min_size_to_sample: 0, error_buffer: 0.0, inserts: 0, samples: 0 }
    }

    /// False for [`RateLimiter::unlimited`].
    pub fn is_limited(&self) -> bool {
        self.samples_per_insert > 0.0
    }

    /// Checks that inserts of up to `largest_insert` and samples of up to
    /// `largest_sample` transitions can always make progress: the window
    /// [min_diff, max_diff] must be wider than either step.
    pub fn check_steps(&self, largest_insert: u64, largest_sample: u64) -> Result<(), String> {
        let width = 2.0 * self.error_buffer;
        let insert_step = largest_insert as f64 * self.samples_per_insert;
        if width < insert_step + largest_sample as f64 {
            return Err(format!(
                "the replay-ratio error buffer ({}) is too small: it must be at least half of one batch of {largest_insert} inserted transitions × {} samples per insert plus one sample of {largest_sample} ({})",
                self.error_buffer,
                self.samples_per_insert,
                (insert_step + largest_sample as f64) / 2.0
            ));
        }
        Ok(())
    }

    /// The diff the limiter steers to: SPI · min_size.
    pub fn centre(&self) -> f64 {
        self.samples_per_insert * self.min_size_to_sample as f64
    }

    pub fn min_diff(&self) -> f64 {
        self.centre() - self.error_buffer
    }

    pub fn max_diff(&self) -> f64 {
        self.centre() + self.error_buffer
    }

    /// inserts · SPI − samples.
    pub fn diff(&self) -> f64 {
        self.inserts as f64 * self.samples_per_insert - self.samples as f64
    }

    /// Whether `count` transitions may be inserted now.
    pub fn can_insert(&self, count: u64) -> bool {
        if !self.is_limited() || self.inserts + count <= self.min_size_to_sample {
            return true;
        }
        (self.inserts + count) as f64 * self.samples_per_insert - self.samples as f64 <= self.max_diff()
    }

    /// Whether `count` transitions may be sampled now.
    pub fn can_sample(&self, count: u64) -> bool {
        if !self.is_limited() {
            return true;
        }
        if self.inserts < self.min_size_to_sample {
            return false;
        }
        self.diff() - count as f64 >= self.min_diff()
    }

    /// Samples owed at the end of a run: how far diff is above its centre,
    /// so a learner that was behind can take the updates its last inserts
    /// earned (as the single-process loop takes one per step to the end).
    pub fn owed(&self) -> f64 {
        if !self.is_limited() {
            return 0.0;
        }
        (self.diff() - self.centre()).max(0.0)
    }

    pub fn insert(&mut self, count: u64) {
        self.inserts += count;
    }

    pub fn sample(&mut self, count: u64) {
        self.samples += count;
    }

    /// Samples per insert achieved so far (0 before the first insert).
    pub fn achieved_ratio(&self) -> f64 {
        if self.inserts == 0 { 0.0 } else { self.samples as f64 / self.inserts as f64 }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// SPI 2, min size 3, error 4: centre 6, window [2, 10].
    fn limiter() -> RateLimiter {
        RateLimiter::new(2.0, 3, 4.0).unwrap()
    }

    /// Issue 71: `--replay-ratio 1e300` was accepted.
    #[test]
    fn absurd_ratios_are_refused_with_the_range() {
        for spi in [1e300, f64::INFINITY, 0.0, -1.0, f64::NAN] {
            let err = RateLimiter::new(spi, 3, 4.0).unwrap_err();
            assert!(err.contains("at most 1e6"), "{spi}: {err}");
        }
        assert!(RateLimiter::new(MAX_SAMPLES_PER_INSERT, 3, 4.0).is_ok());
    }

    #[test]
    fn window_follows_reverbs_definition() {
        let l = limiter();
        assert_eq!((l.min_diff(), l.max_diff()), (2.0, 10.0));
    }

    #[test]
    fn filling_to_min_size_is_free_and_sampling_waits_for_it() {
        let mut l = limiter();
        assert!(l.can_insert(3), "up to min size, inserts are free");
        assert!(!l.can_sample(1), "nothing to sample before min size");
        l.insert(2);
        assert!(!l.can_sample(1));
        l.insert(1);
        // inserts 3: diff = 6; a sample of 4 leaves 2 ≥ 2, of 5 leaves 1.
        assert!(l.can_sample(4) && !l.can_sample(5));
    }

    #[test]
    fn inserts_wait_for_samples_beyond_the_window() {
        let mut l = limiter();
        l.insert(3);
        // (3 + 2) · 2 − 0 = 10 ≤ 10: allowed; (3 + 3) · 2 = 12 > 10: refused.
        assert!(l.can_insert(2) && !l.can_insert(3));
        l.insert(2);
        assert!(!l.can_insert(1), "learner behind: actors wait");
        l.sample(2);
        // (5 + 1) · 2 − 2 = 10: allowed again.
        assert!(l.can_insert(1));
    }

    #[test]
    fn samples_wait_for_inserts_below_the_window() {
        let mut l = limiter();
        l.insert(3);
        l.sample(4); // diff 2
        assert!(!l.can_sample(1), "actors behind: the learner waits");
        l.insert(1); // diff 4
        assert!(l.can_sample(2) && !l.can_sample(3));
    }

    /// Alternating one insert and as many samples as allowed keeps
    /// samples = SPI · (inserts − min size) within the error buffer.
    #[test]
    fn long_run_holds_the_ratio() {
        let mut l = RateLimiter::new(256.0, 1000, 256.0 * 64.0).unwrap();
        for _ in 0..20_000 {
            if l.can_insert(64) {
                l.insert(64);
            }
            while l.can_sample(256) {
                l.sample(256);
            }
            let expected = 256.0 * (l.inserts as f64 - 1000.0).max(0.0);
            assert!((l.samples as f64 - expected).abs() <= l.error_buffer + 256.0 * 64.0, "{l:?}");
        }
        assert!(l.inserts > 1_000_000);
    }

    #[test]
    fn owed_samples_are_the_distance_above_the_centre() {
        let mut l = limiter();
        l.insert(5); // diff 10, centre 6
        assert_eq!(l.owed(), 4.0);
        l.sample(6);
        assert_eq!(l.owed(), 0.0);
    }

    #[test]
    fn bad_settings_are_refused_with_reasons() {
        assert!(RateLimiter::new(0.0, 1, 1.0).unwrap_err().contains("samples per insert"));
        assert!(RateLimiter::new(1.0, 1, f64::NAN).unwrap_err().contains("error buffer"));
        let tight = RateLimiter::new(256.0, 1000, 1000.0).unwrap();
        assert!(tight.check_steps(64, 256).unwrap_err().contains("too small"));
        assert!(RateLimiter::new(256.0, 1000, 256.0 * 40.0).unwrap().check_steps(64, 256).is_ok());
    }

    #[test]
    fn counters_round_trip_through_json() {
        let mut l = limiter();
        l.insert(7);
        l.sample(5);
        let back: RateLimiter = serde_json::from_str(&serde_json::to_string(&l).unwrap()).unwrap();
        assert_eq!(back, l);
    }

    #[test]
    fn an_unlimited_limiter_admits_everything_and_counts() {
        let mut l = RateLimiter::unlimited();
        assert!(!l.is_limited() && limiter().is_limited());
        assert!(l.can_insert(1_000_000) && l.can_sample(1_000_000));
        l.insert(10);
        l.sample(640);
        assert_eq!((l.inserts, l.samples, l.owed()), (10, 640, 0.0));
        assert_eq!(l.achieved_ratio(), 64.0);
    }
}
