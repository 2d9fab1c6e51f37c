//! How a training action u is sampled, in one place for both loops: the
//! agents of `lcrl train` ([`crate::algo::ddpg`], [`crate::algo::ppo`]) and the actors of
//! a distributed run sample with these functions, so the same policy, state
//! and random draws give the same u, and the same u is stored
//! (docs/architecture.md, "One transition, one meaning").
//!
//! - DDPG: uniform in [−1, 1]ⁿ while the replay buffer warms up, then
//!   μ(s) + N(0, σ²) clipped to
//!   [−1, 1] (σ from the noise schedule).
//! - PPO: u ~ N(μ(s), diag σ²), not clipped: the Gaussian's own sample, so
//!   that log π(u|s) is the density the ratio needs. The action map
//!   ([`crate::policy::action::ActionMap::to_env`]) clips when it makes the
//!   environment's action, and only there.

use rand::Rng;
use rand_distr::{Distribution, StandardNormal};

/// u = μ + σ ⊙ z with z ~ N(0, I), clipped to [−1, 1] when `clip` (DDPG's
/// exploration noise) and left as sampled otherwise (PPO's Gaussian).
/// `std` has one entry per component of `mean`.
pub fn gaussian(mean: &[f32], std: &[f64], clip: bool, rng: &mut impl Rng) -> Vec<f32> {
    mean.iter()
        .zip(std)
        .map(|(&m, &s)| {
            let z: f64 = StandardNormal.sample(rng);
            let u = f64::from(m) + s * z;
            (if clip { u.clamp(-1.0, 1.0) } else { u }) as f32
        })
        .collect()
}

/// Uniform in [−1, 1]ⁿ (DDPG's warm-up).
pub fn uniform(n: usize, rng: &mut impl Rng) -> Vec<f32> {
    (0..n).map(|_| rng.random_range(-1.0f32..=1.0)).collect()
}

/// log N(u; μ, diag σ²), summed over components: PPO's log π(u|s) for one
/// row, as [`crate::algo::ppo`] computes it on tensors.
pub fn gaussian_log_prob(mean: &[f32], std: &[f64], u: &[f32]) -> f32 {
    let half_log_two_pi = 0.5 * (2.0 * std::f64::consts::PI).ln();
    mean.iter()
        .zip(std)
        .zip(u)
        .map(|((&m, &s), &u)| {
            let z = (f64::from(u) - f64::from(m)) / s;
            -0.5 * z * z - s.ln() - half_log_two_pi
        })
        .sum::<f64>() as f32
}

#[cfg(test)]
mod tests {
    use super::*;
    use rand::SeedableRng;
    use rand_chacha::ChaCha8Rng;

    #[test]
    fn clipping_is_ddpgs_and_only_ddpgs() {
        let mean = [0.9f32, -0.9, 0.0];
        let std = [1.0; 3];
        let draws = |clip| {
            let mut rng = ChaCha8Rng::seed_from_u64(7);
            (0..500).flat_map(|_| gaussian(&mean, &std, clip, &mut rng)).collect::<Vec<_>>()
        };
        let (clipped, raw) = (draws(true), draws(false));
        assert!(clipped.iter().all(|u| (-1.0..=1.0).contains(u)));
        assert!(raw.iter().any(|u| u.abs() > 1.0), "a std of 1 around ±0.9 leaves the box often");
        // The same draws: clipping is the only difference.
        for (c, r) in clipped.iter().zip(&raw) {
            assert_eq!(*c, r.clamp(-1.0, 1.0));
        }
    }

    #[test]
    fn log_prob_is_the_gaussian_density() {
        // One component, σ = 2, at u = μ + σ: log N = −½ − ln 2 − ½ ln 2π.
        let expected = -0.5 - 2f64.ln() - 0.5 * (2.0 * std::f64::consts::PI).ln();
        assert!((f64::from(gaussian_log_prob(&[0.5], &[2.0], &[2.5])) - expected).abs() < 1e-6);
        // Components add.
        let two = gaussian_log_prob(&[0.5, 0.5], &[2.0, 2.0], &[2.5, 2.5]);
        assert!((f64::from(two) - 2.0 * expected).abs() < 1e-5);
    }

    #[test]
    fn sample_moments_match_mean_and_std() {
        let mut rng = ChaCha8Rng::seed_from_u64(11);
        let samples: Vec<f64> = (0..20_000).map(|_| f64::from(gaussian(&[0.3], &[0.2], false, &mut rng)[0])).collect();
        let mean = samples.iter().sum::<f64>() / samples.len() as f64;
        let var = samples.iter().map(|x| (x - mean).powi(2)).sum::<f64>() / (samples.len() - 1) as f64;
        // Standard errors: 0.2/√20000 ≈ 0.0014 for the mean; ≈ 0.0010 for the std.
        assert!((mean - 0.3).abs() < 0.006, "{mean}");
        assert!((var.sqrt() - 0.2).abs() < 0.005, "{}", var.sqrt());
    }
}
