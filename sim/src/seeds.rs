//! Which episode starts each purpose uses. An episode's start (and, on the
//! randomized presets, its parts) is a function of its seed, so a policy
//! tested on a seed it trained on, or was chosen on, is tested on its own
//! training data. Each purpose therefore has a range of its own:
//!
//! | purpose | seeds |
//! |---|---|
//! | evaluation (`lcrl sim --seed S`, `lcrl tune`'s evaluation, the bar) | S, S+1, … (user's choice; 0 by default) |
//! | `lcrl tune`'s candidates | 1 000 000, … ([`TUNING`]) |
//! | training episodes of run seed r | [`training`]: 2⁴⁰ + r·2²⁰ + episode |
//! | validation (choosing the run's policy) | [`validation`]: 2⁴¹ + r·2²⁰ + k |
//! | a run's own final evaluation | [`run_evaluation`]: 2⁴² + r·2²⁰ + k |
//! | confirming the choice at the end (many starts, few candidates) | [`confirmation`]: 2⁴³ + r·2²⁰ + k |
//!
//! For run seeds and episode counts below 2²⁰ (a million) the last four
//! never meet each other, the first 2⁴⁰ seeds, or tuning's range.

/// The first tuning start of `lcrl tune` (its candidates are scored there).
pub const TUNING: u64 = 1_000_000;

/// Episodes (and run seeds) below this never share a seed across purposes.
pub const PER_RUN: u64 = 1 << 20;

const TRAINING_BASE: u64 = 1 << 40;
const VALIDATION_BASE: u64 = 1 << 41;
const RUN_EVALUATION_BASE: u64 = 1 << 42;
const CONFIRMATION_BASE: u64 = 1 << 43;

fn in_range(base: u64, run_seed: u64, k: usize) -> u64 {
    base.wrapping_add(run_seed.wrapping_mul(PER_RUN)).wrapping_add(k as u64)
}

/// The seed of training episode `episode` of a run with seed `run_seed`.
pub fn training(run_seed: u64, episode: usize) -> u64 {
    in_range(TRAINING_BASE, run_seed, episode)
}

/// The seed of validation start `k` (the starts a run's policy is chosen on).
pub fn validation(run_seed: u64, k: usize) -> u64 {
    in_range(VALIDATION_BASE, run_seed, k)
}

/// The seed of start `k` of a run's own final evaluation (summary.json's
/// `eval_return`).
pub fn run_evaluation(run_seed: u64, k: usize) -> u64 {
    in_range(RUN_EVALUATION_BASE, run_seed, k)
}

/// The seed of confirmation start `k`: the starts on which a run's best
/// few validated policies are scored again before one is handed over
/// (learner/src/run/selection.rs).
pub fn confirmation(run_seed: u64, k: usize) -> u64 {
    in_range(CONFIRMATION_BASE, run_seed, k)
}

#[cfg(test)]
mod tests {
    use super::*;
    use std::collections::HashSet;

    /// Every purpose's seeds, for run seeds 0..8 and 300 episodes each,
    /// and the first 10 000 evaluation seeds: no seed serves two purposes.
    #[test]
    fn purposes_never_share_a_seed() {
        let mut seen: HashSet<u64> = (0..10_000).collect();
        seen.extend(TUNING..TUNING + 1000);
        let before = seen.len();
        let mut drawn = 0;
        for run in 0..8 {
            for k in 0..300 {
                for seed in [training(run, k), validation(run, k), run_evaluation(run, k), confirmation(run, k)] {
                    assert!(seen.insert(seed), "seed {seed} (run {run}, k {k}) serves two purposes");
                    drawn += 1;
                }
            }
        }
        assert_eq!(seen.len(), before + drawn);
        // The largest run seed and episode count the ranges promise stay apart.
        let last = PER_RUN - 1;
        assert!(training(last, last as usize) < validation(0, 0));
        assert!(validation(last, last as usize) < run_evaluation(0, 0));
        assert!(run_evaluation(last, last as usize) < confirmation(0, 0));
    }
}
