//! Statistics over seeds: the mean with its 95% confidence interval,
//! Welch's t-test between two connections, and episodes to a reward
//! threshold with the runs that never reach it censored at the budget.
//!
//! Why Welch's t and not a permutation test: the report must give a
//! confidence interval of the difference, and Welch's test gives the
//! interval and the p-value from one model, so the two always agree (the
//! CI excludes 0 exactly when p < 0.05). It does not assume equal
//! variances, and LCRL and GCRL runs differ most in their spread across
//! seeds. With 5 seeds a permutation test has only 252 splits and no
//! interval. Welch's test assumes roughly normal means; one diverged seed
//! breaks that, which is why report.md prints every seed's return as well.

use serde::Serialize;
use statrs::distribution::{ContinuousCDF, StudentsT};

/// A mean over seeds with its two-sided 95% Student-t interval (None with
/// fewer than two values).
#[derive(Debug, Clone, PartialEq, Serialize)]
pub struct Estimate {
    pub mean: f64,
    pub ci95: Option<[f64; 2]>,
    pub n: usize,
}

/// The 97.5% quantile of Student's t with `df` degrees of freedom.
fn t_975(df: f64) -> f64 {
    StudentsT::new(0.0, 1.0, df).map_or(f64::NAN, |t| t.inverse_cdf(0.975))
}

fn mean(sample: &[f64]) -> f64 {
    sample.iter().sum::<f64>() / sample.len() as f64
}

/// Unbiased sample variance (n − 1).
fn variance(sample: &[f64]) -> f64 {
    let m = mean(sample);
    sample.iter().map(|x| (x - m).powi(2)).sum::<f64>() / (sample.len() as f64 - 1.0)
}

/// Mean and 95% CI: mean ± t(0.975, n−1) · s/√n.
pub fn mean_ci(sample: &[f64]) -> Option<Estimate> {
    if sample.is_empty() {
        return None;
    }
    let m = mean(sample);
    let n = sample.len();
    let ci95 = (n >= 2).then(|| {
        let half = t_975(n as f64 - 1.0) * (variance(sample) / n as f64).sqrt();
        [m - half, m + half]
    });
    Some(Estimate { mean: m, ci95, n })
}

/// The one-sample t statistic of mean(sample) against 0, mean/(s/√n): the
/// paired t-test when the sample is per-seed differences (None with fewer
/// than two values or no spread).
pub fn one_sample_t(sample: &[f64]) -> Option<f64> {
    let spread = (sample.len() >= 2).then(|| (variance(sample) / sample.len() as f64).sqrt()).filter(|s| *s > 0.0)?;
    Some(mean(sample) / spread)
}

/// Welch's two-sample t-test of mean(a) − mean(b).
#[derive(Debug, Clone, PartialEq, Serialize)]
pub struct Welch {
    pub difference: f64,
    /// Standard error of the difference (Welch's, unpooled).
    pub se: f64,
    pub ci95: [f64; 2],
    /// Two-sided.
    pub p_value: f64,
    pub t: f64,
    /// Welch–Satterthwaite degrees of freedom.
    pub df: f64,
}

/// None unless both groups have at least two values.
pub fn welch(a: &[f64], b: &[f64]) -> Option<Welch> {
    if a.len() < 2 || b.len() < 2 {
        return None;
    }
    let difference = mean(a) - mean(b);
    let (va, vb) = (variance(a) / a.len() as f64, variance(b) / b.len() as f64);
    let se = (va + vb).sqrt();
    if se == 0.0 {
        // Both groups constant: identical means are no evidence of a
        // difference, different ones are certain.
        let p_value = if difference == 0.0 { 1.0 } else { 0.0 };
        return Some(Welch { difference, se, ci95: [difference, difference], p_value, t: 0.0, df: f64::INFINITY });
    }
    let df = (va + vb).powi(2) / (va.powi(2) / (a.len() as f64 - 1.0) + vb.powi(2) / (b.len() as f64 - 1.0));
    let t = difference / se;
    let p_value = StudentsT::new(0.0, 1.0, df).map_or(f64::NAN, |dist| 2.0 * dist.cdf(-t.abs()));
    let half = t_975(df) * se;
    Some(Welch { difference, se, ci95: [difference - half, difference + half], p_value, t, df })
}

/// Holm's step-down adjustment of `p` (any order), returned in the same
/// order: the k-th smallest p is multiplied by (m − k + 1), made
/// non-decreasing along the sorted order, and capped at 1. It controls the
/// family-wise error rate over all m comparisons without assuming they are
/// independent, and is never less powerful than Bonferroni.
pub fn holm(p: &[f64]) -> Vec<f64> {
    // A p that is not a number (no test) counts as 1: it never makes
    // another comparison look stronger, and it still counts in m.
    let p: Vec<f64> = p.iter().map(|&x| if x.is_nan() { 1.0 } else { x }).collect();
    let m = p.len();
    let mut order: Vec<usize> = (0..m).collect();
    order.sort_by(|&i, &j| p[i].total_cmp(&p[j]));
    let mut adjusted = vec![1.0; m];
    let mut running = 0.0f64;
    for (k, &i) in order.iter().enumerate() {
        running = running.max(((m - k) as f64 * p[i]).min(1.0));
        adjusted[i] = running;
    }
    adjusted
}

/// A p value as a report prints it: three decimals, "< 0.001" below that
/// (never "0.000"), "—" when there is none.
pub fn format_p(p: f64) -> String {
    if !p.is_finite() {
        "—".into()
    } else if p < 0.001 {
        "< 0.001".into()
    } else {
        format!("{p:.3}")
    }
}

/// What a 95% interval of a difference a − b says, in words: which side
/// is higher when the interval excludes 0, "not distinguishable" when it
/// holds 0 (which is not evidence that the two are equal).
pub fn reading(a: &str, b: &str, ci95: [f64; 2]) -> String {
    let interval = format!("CI [{:.3}, {:.3}]", ci95[0], ci95[1]);
    if ci95[0] > 0.0 {
        format!("{a} higher than {b}, {interval}")
    } else if ci95[1] < 0.0 {
        format!("{a} lower than {b}, {interval}")
    } else {
        format!("not distinguishable, {interval}")
    }
}

/// [`reading`] for one comparison of a family: a side is named higher or
/// lower only when Holm's adjusted p is below 0.05 too; an interval that
/// excludes 0 on its own but not after the adjustment says so.
pub fn reading_adjusted(a: &str, b: &str, ci95: [f64; 2], p_holm: f64) -> String {
    let own = reading(a, b, ci95);
    if own.starts_with("not distinguishable") || p_holm < 0.05 {
        own
    } else {
        format!("not distinguishable after Holm's adjustment (its own CI [{:.3}, {:.3}] excludes 0)", ci95[0], ci95[1])
    }
}

/// Differences of one contrast across strata (environments), combined.
#[derive(Debug, Clone, PartialEq, Serialize)]
pub struct Stratified {
    pub difference: f64,
    /// Standard error of the combined difference.
    pub se: f64,
    pub ci95: [f64; 2],
    /// Two-sided.
    pub p_value: f64,
    pub strata: usize,
}

/// Combines per-stratum differences with their standard errors, weighted
/// by inverse variance (a fixed-effect stratified test): the combined
/// difference Σ w·d / Σ w with standard error 1/√Σ w, w = 1/se², and a
/// normal two-sided p. Strata with no spread (se = 0) or non-finite values
/// are left out; None when none is left.
pub fn stratified(strata: &[(f64, f64)]) -> Option<Stratified> {
    let kept: Vec<(f64, f64)> = strata.iter().copied().filter(|(d, se)| d.is_finite() && se.is_finite() && *se > 0.0).collect();
    if kept.is_empty() {
        return None;
    }
    let weight: f64 = kept.iter().map(|(_, se)| 1.0 / (se * se)).sum();
    let difference = kept.iter().map(|(d, se)| d / (se * se)).sum::<f64>() / weight;
    let se = weight.sqrt().recip();
    let normal = statrs::distribution::Normal::new(0.0, 1.0).ok()?;
    let p_value = 2.0 * normal.cdf(-(difference / se).abs());
    let half = normal.inverse_cdf(0.975) * se;
    Some(Stratified { difference, se, ci95: [difference - half, difference + half], p_value, strata: kept.len() })
}

/// Episodes until the average return reaches a threshold, over seeds.
#[derive(Debug, Clone, PartialEq, Serialize)]
pub struct ThresholdEstimate {
    pub threshold: f64,
    /// Mean (and CI) of min(episodes to threshold, budget): runs that never
    /// reach it count as the budget, so with any censored run the mean is
    /// a lower bound of the true one.
    pub mean: f64,
    pub ci95: Option<[f64; 2]>,
    /// Runs that reached the threshold within the budget.
    pub reached: usize,
    /// Runs that did not (censored at the budget).
    pub censored: usize,
    pub budget: usize,
}

/// The window of the "average return": the same 10 episodes as the final
/// return (the mean of the last 10).
pub const AVERAGE_WINDOW: usize = 10;

/// The first episode (1-based) whose mean return over the last `window`
/// episodes (a full window) is at least `threshold`; None if none is.
pub fn episodes_to_threshold(returns: &[f64], threshold: f64, window: usize) -> Option<usize> {
    let window = window.max(1);
    (window..=returns.len()).find(|&k| mean(&returns[k - window..k]) >= threshold)
}

/// Summarizes per-run episodes to threshold (None: never reached).
pub fn censored_estimate(runs: &[Option<usize>], threshold: f64, budget: usize) -> Option<ThresholdEstimate> {
    let values: Vec<f64> = runs.iter().map(|r| r.map_or(budget, |k| k.min(budget)) as f64).collect();
    let estimate = mean_ci(&values)?;
    let reached = runs.iter().filter(|r| r.is_some()).count();
    Some(ThresholdEstimate { threshold, mean: estimate.mean, ci95: estimate.ci95, reached, censored: runs.len() - reached, budget })
}

#[cfg(test)]
mod tests {
    use super::*;

    /// Holm by hand: sorted 0.005, 0.01, 0.03, 0.04 times 4, 3, 2, 1 are
    /// 0.02, 0.03, 0.06, 0.04, and the last is raised to 0.06 (step-down
    /// adjusted p never decrease along the sorted order).
    #[test]
    fn holm_adjusts_a_worked_example() {
        let close = |a: &[f64], b: &[f64]| a.iter().zip(b).all(|(x, y)| (x - y).abs() < 1e-12);
        assert!(close(&holm(&[0.01, 0.04, 0.03, 0.005]), &[0.03, 0.06, 0.06, 0.02]), "{:?}", holm(&[0.01, 0.04, 0.03, 0.005]));
        assert!(close(&holm(&[0.01, 0.02, 0.03, 0.04, 0.05]), &[0.05, 0.08, 0.09, 0.09, 0.09]));
        // Capped at 1, one p alone unchanged, none at all fine.
        assert_eq!(holm(&[0.6, 0.7]), vec![1.0, 1.0]);
        assert_eq!(holm(&[0.2]), vec![0.2]);
        assert!(holm(&[]).is_empty());
    }

    #[test]
    fn p_values_and_intervals_read_as_a_report_prints_them() {
        assert_eq!(format_p(0.0), "< 0.001");
        assert_eq!(format_p(0.0004), "< 0.001");
        assert_eq!(format_p(0.006), "0.006");
        assert_eq!(format_p(f64::NAN), "—");
        assert_eq!(reading("local@1", "global", [0.1, 0.5]), "local@1 higher than global, CI [0.100, 0.500]");
        assert_eq!(reading("local@1", "global", [-0.5, -0.1]), "local@1 lower than global, CI [-0.500, -0.100]");
        assert_eq!(reading("a", "b", [-1.4, 13.9]), "not distinguishable, CI [-1.400, 13.900]");
        // In a family: a side is named only when the adjusted p agrees.
        assert_eq!(reading_adjusted("a", "b", [0.1, 0.5], 0.01), "a higher than b, CI [0.100, 0.500]");
        assert_eq!(reading_adjusted("a", "b", [0.1, 0.5], 0.8), "not distinguishable after Holm's adjustment (its own CI [0.100, 0.500] excludes 0)");
        assert_eq!(reading_adjusted("a", "b", [-0.1, 0.5], 0.001), "not distinguishable, CI [-0.100, 0.500]");
    }

    /// Two strata of equal weight: the mean difference, with the standard
    /// error of their average (0.5/√2) and a normal p.
    #[test]
    fn strata_combine_by_inverse_variance() {
        let s = stratified(&[(1.0, 0.5), (2.0, 0.5)]).unwrap();
        assert!((s.difference - 1.5).abs() < 1e-12);
        let se = 0.5 / 2f64.sqrt();
        assert!((s.ci95[1] - s.ci95[0] - 2.0 * 1.959_963_984_540_054 * se).abs() < 1e-9);
        // z = 1.5 / 0.35355 = 4.2426: p = 2.2090e-5 (scipy.stats.norm.sf).
        assert!((s.p_value - 2.209e-5).abs() < 1e-8, "{}", s.p_value);
        // The more precise stratum weighs more; a stratum without spread is left out.
        let weighted = stratified(&[(1.0, 0.1), (3.0, 1.0), (9.0, 0.0)]).unwrap();
        assert!((weighted.difference - (100.0 + 3.0) / 101.0).abs() < 1e-12);
        assert_eq!(weighted.strata, 2);
        assert_eq!(stratified(&[(1.0, 0.0)]), None);
    }

    // The expected values below were computed independently with SciPy
    // 1.17 (scipy.stats.t.interval, scipy.stats.ttest_ind with
    // equal_var=False), not with this code.

    #[test]
    fn confidence_interval_of_a_known_sample() {
        let e = mean_ci(&[1.0, 2.0, 3.0, 4.0, 5.0]).unwrap();
        assert_eq!(e.mean, 3.0);
        let [lo, hi] = e.ci95.unwrap();
        assert!((lo - 1.0367568385224).abs() < 1e-9 && (hi - 4.9632431614776).abs() < 1e-9, "{lo} {hi}");
        let e = mean_ci(&[-3.2, -4.1, -2.7, -5.0]).unwrap();
        let [lo, hi] = e.ci95.unwrap();
        assert!((lo - (-5.3649151232026)).abs() < 1e-9 && (hi - (-2.1350848767974)).abs() < 1e-9, "{lo} {hi}");
        assert_eq!(mean_ci(&[7.0]).unwrap().ci95, None);
        assert_eq!(mean_ci(&[]), None);
    }

    /// Paired differences 1, 2, 3: mean 2, s = 1, t = 2/(1/√3) = 2√3.
    #[test]
    fn one_sample_t_of_a_known_sample() {
        assert!((one_sample_t(&[1.0, 2.0, 3.0]).unwrap() - 2.0 * 3f64.sqrt()).abs() < 1e-12);
        assert_eq!(one_sample_t(&[1.0]), None, "one value has no spread");
        assert_eq!(one_sample_t(&[2.0, 2.0]), None, "no spread, no t");
    }

    #[test]
    fn welch_on_identical_and_on_clearly_different_groups() {
        let same = welch(&[1.0, 2.0, 3.0, 4.0], &[1.0, 2.0, 3.0, 4.0]).unwrap();
        assert_eq!((same.difference, same.p_value), (0.0, 1.0));
        assert!(same.ci95[0] < 0.0 && same.ci95[1] > 0.0);

        let a = [10.1, 9.8, 10.3, 10.0, 9.9];
        let b = [5.2, 4.9, 5.1, 5.0, 4.8, 5.3];
        let w = welch(&a, &b).unwrap();
        assert!((w.difference - 4.97).abs() < 1e-9);
        assert!((w.t - 43.20378167047).abs() < 1e-8, "t {}", w.t);
        assert!((w.df - 8.544345657595).abs() < 1e-8, "df {}", w.df);
        assert!((w.p_value / 2.6398628318093e-11 - 1.0).abs() < 1e-6, "p {}", w.p_value);
        assert!((w.ci95[0] - 4.707639095670).abs() < 1e-8 && (w.ci95[1] - 5.232360904330).abs() < 1e-8, "{:?}", w.ci95);
        // Unequal spreads: the Welch df is well below na + nb − 2.
        let w = welch(&[0.0, 10.0, -10.0, 5.0], &[1.0, 1.1, 0.9, 1.0]).unwrap();
        assert!((w.p_value - 0.95699074541906).abs() < 1e-9, "p {}", w.p_value);
        assert!(w.df < 3.1, "df {}", w.df);
        assert_eq!(welch(&[1.0], &[1.0, 2.0]), None);
    }

    #[test]
    fn episodes_to_threshold_needs_a_full_window_and_censors_at_the_budget() {
        // Returns climb by 1 per episode from −20: the mean of episodes
        // k−2..k (window 3) is −22 + k, first ≥ −5 at k = 17.
        let climbing: Vec<f64> = (0..30).map(|k| -20.0 + k as f64).collect();
        assert_eq!(episodes_to_threshold(&climbing, -5.0, 3), Some(17));
        // One lucky episode does not count until its window is full.
        let lucky = [0.0, -9.0, -9.0, -9.0];
        assert_eq!(episodes_to_threshold(&lucky, -5.0, 3), None);
        assert_eq!(episodes_to_threshold(&lucky, -5.0, 1), Some(1));

        // Two runs reach it (40, 60), one never does within 200 episodes.
        let e = censored_estimate(&[Some(40), None, Some(60)], -5.0, 200).unwrap();
        assert_eq!((e.reached, e.censored, e.budget), (2, 1, 200));
        assert_eq!(e.mean, 100.0, "the censored run counts as the budget");
        let [lo, hi] = e.ci95.unwrap();
        assert!((lo - (-116.562104947161)).abs() < 1e-8 && (hi - 316.562104947161).abs() < 1e-8, "{lo} {hi}");
    }
}
