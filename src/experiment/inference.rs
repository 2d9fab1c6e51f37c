//! The tests a study file can name beyond a mean difference
//! (docs/experiment.md, "Statistics, and why these"):
//!
//! - [`tost`]: equivalence by two one-sided tests against a margin;
//! - [`factorial`]: a 2 × 2 design's two main effects and interaction, each
//!   a Welch contrast of the four cell means;
//! - [`log_rank`]: a time to an event censored at the budget (episodes
//!   until the training mean reaches the best constant), stratified;
//! - [`auc`] and [`episodes_to_bar`]: the two speed measures of a run.

use serde::Serialize;
use statrs::distribution::{ChiSquared, ContinuousCDF, Normal, StudentsT};

use super::stats::{episodes_to_threshold, AVERAGE_WINDOW};

/// The episodes the area under the learning curve covers.
pub const AUC_EPISODES: usize = 100;

/// The area under the learning curve: the mean return over the first
/// [`AUC_EPISODES`] episodes (fewer if the run has fewer), each return
/// floored at `floor` (a = 0's return), so that one wild episode cannot
/// carry the mean. None for a run without episodes.
pub fn auc(returns: &[f64], floor: f64) -> Option<f64> {
    let first = &returns[..returns.len().min(AUC_EPISODES)];
    (!first.is_empty()).then(|| first.iter().map(|r| r.max(floor)).sum::<f64>() / first.len() as f64)
}

/// A time to an event, or censored.
#[derive(Debug, Clone, Copy, PartialEq, Serialize)]
pub struct Time {
    pub episodes: usize,
    /// False: the run never got there; `episodes` is the budget.
    pub reached: bool,
}

/// Episodes until the 10-episode training mean reaches `bar` (the best
/// constant's return), censored at `budget`.
pub fn episodes_to_bar(returns: &[f64], bar: f64, budget: usize) -> Time {
    match episodes_to_threshold(returns, bar, AVERAGE_WINDOW) {
        Some(k) if k <= budget => Time { episodes: k, reached: true },
        _ => Time { episodes: budget, reached: false },
    }
}

/// The Kaplan–Meier median: the first time at which the estimated share
/// still not there falls to one half or below; None if it never does.
pub fn km_median(times: &[Time]) -> Option<usize> {
    let mut event_times: Vec<usize> = times.iter().filter(|t| t.reached).map(|t| t.episodes).collect();
    event_times.sort_unstable();
    event_times.dedup();
    let mut surviving = 1.0;
    for t in event_times {
        let at_risk = times.iter().filter(|x| x.episodes >= t).count() as f64;
        let events = times.iter().filter(|x| x.reached && x.episodes == t).count() as f64;
        surviving *= 1.0 - events / at_risk;
        if surviving <= 0.5 + 1e-12 {
            return Some(t);
        }
    }
    None
}

/// The (stratified) log-rank test of group a against group b.
#[derive(Debug, Clone, PartialEq, Serialize)]
pub struct LogRank {
    /// Σ over strata and event times of a's events − their expectation
    /// under no difference: positive when a gets there sooner.
    pub observed_minus_expected: f64,
    pub variance: f64,
    pub chi_square: f64,
    /// Two-sided (χ² with 1 degree of freedom).
    pub p_value: f64,
}

/// Mantel's log-rank statistic summed over strata: each stratum is (a's
/// times, b's times). None without any event or with no spread.
pub fn log_rank(strata: &[(Vec<Time>, Vec<Time>)]) -> Option<LogRank> {
    let (mut o_minus_e, mut variance) = (0.0, 0.0);
    for (a, b) in strata {
        let mut event_times: Vec<usize> = a.iter().chain(b).filter(|t| t.reached).map(|t| t.episodes).collect();
        event_times.sort_unstable();
        event_times.dedup();
        for t in event_times {
            let at_risk = |g: &[Time]| g.iter().filter(|x| x.episodes >= t).count() as f64;
            let events = |g: &[Time]| g.iter().filter(|x| x.reached && x.episodes == t).count() as f64;
            let (n_a, n) = (at_risk(a), at_risk(a) + at_risk(b));
            let (d_a, d) = (events(a), events(a) + events(b));
            o_minus_e += d_a - d * n_a / n;
            if n > 1.0 {
                variance += d * (n_a / n) * (1.0 - n_a / n) * (n - d) / (n - 1.0);
            }
        }
    }
    if variance.is_nan() || variance <= 0.0 {
        return None;
    }
    let chi_square = o_minus_e * o_minus_e / variance;
    let p_value = ChiSquared::new(1.0).map_or(f64::NAN, |c| 1.0 - c.cdf(chi_square));
    Some(LogRank { observed_minus_expected: o_minus_e, variance, chi_square, p_value })
}

/// Two one-sided tests of |difference| < margin.
#[derive(Debug, Clone, PartialEq, Serialize)]
pub struct Tost {
    pub difference: f64,
    pub margin: f64,
    /// The 90% interval: inside ±margin exactly when p < 0.05.
    pub ci90: [f64; 2],
    /// The larger of the two one-sided p values.
    pub p_value: f64,
}

/// TOST on a difference with its standard error: Student's t with `df`
/// degrees of freedom (one stratum, Welch's), or the normal (strata
/// combined, `df` None).
pub fn tost(difference: f64, se: f64, df: Option<f64>, margin: f64) -> Option<Tost> {
    if !(se > 0.0 && se.is_finite() && difference.is_finite() && margin > 0.0) {
        return None;
    }
    let cdf = |x: f64| match df {
        Some(df) => StudentsT::new(0.0, 1.0, df).map_or(f64::NAN, |t| t.cdf(x)),
        None => Normal::new(0.0, 1.0).map_or(f64::NAN, |n| n.cdf(x)),
    };
    let q95 = match df {
        Some(df) => StudentsT::new(0.0, 1.0, df).map_or(f64::NAN, |t| t.inverse_cdf(0.95)),
        None => Normal::new(0.0, 1.0).map_or(f64::NAN, |n| n.inverse_cdf(0.95)),
    };
    // H0: d ≤ −margin, rejected for large (d + margin)/se; H0: d ≥ margin,
    // rejected for small (d − margin)/se.
    let p_lower = 1.0 - cdf((difference + margin) / se);
    let p_upper = cdf((difference - margin) / se);
    Some(Tost { difference, margin, ci90: [difference - q95 * se, difference + q95 * se], p_value: p_lower.max(p_upper) })
}

/// One effect of a 2 × 2 design.
#[derive(Debug, Clone, PartialEq, Serialize)]
pub struct Effect {
    pub name: String,
    pub estimate: f64,
    pub se: f64,
    pub df: f64,
    pub ci95: [f64; 2],
    pub p_value: f64,
}

/// The 2 × 2 design on `cells[r][c]` (the runs' values): the first
/// factor's main effect (row 2 − row 1, averaged over columns), the
/// second's (column 2 − column 1, averaged over rows), and the interaction
/// (the second factor's effect in row 2 minus that in row 1). Each is a
/// contrast of cell means with Welch–Satterthwaite degrees of freedom, so
/// cells may differ in spread and size; with equal spreads and sizes it is
/// the two-way ANOVA's t (t² = F). None if a cell has fewer than two runs.
pub fn factorial(cells: &[[&[f64]; 2]; 2], factors: &[String; 2]) -> Option<[Effect; 3]> {
    let flat = [cells[0][0], cells[0][1], cells[1][0], cells[1][1]];
    if flat.iter().any(|c| c.len() < 2) {
        return None;
    }
    let stats: Vec<(f64, f64, f64)> = flat
        .iter()
        .map(|c| {
            let n = c.len() as f64;
            let m = c.iter().sum::<f64>() / n;
            let v = c.iter().map(|x| (x - m).powi(2)).sum::<f64>() / (n - 1.0);
            (m, v / n, n)
        })
        .collect();
    let effect = |name: String, w: [f64; 4]| {
        let estimate: f64 = w.iter().zip(&stats).map(|(w, s)| w * s.0).sum();
        let var: f64 = w.iter().zip(&stats).map(|(w, s)| w * w * s.1).sum();
        let df = var * var / w.iter().zip(&stats).map(|(w, s)| (w * w * s.1).powi(2) / (s.2 - 1.0)).sum::<f64>();
        let se = var.sqrt();
        let t = StudentsT::new(0.0, 1.0, df).ok();
        let p_value = if se > 0.0 {
            t.as_ref().map_or(f64::NAN, |t| 2.0 * t.cdf(-(estimate / se).abs()))
        } else if se == 0.0 && estimate.is_finite() {
            // No spread in any cell: equal means are no evidence, unequal certain.
            if estimate == 0.0 { 1.0 } else { 0.0 }
        } else {
            f64::NAN
        };
        let half = t.map_or(f64::NAN, |t| t.inverse_cdf(0.975)) * se;
        Effect { name, estimate, se, df, ci95: [estimate - half, estimate + half], p_value }
    };
    Some([
        effect(format!("{} (main effect)", factors[0]), [-0.5, -0.5, 0.5, 0.5]),
        effect(format!("{} (main effect)", factors[1]), [-0.5, 0.5, -0.5, 0.5]),
        effect(format!("{} × {} (interaction)", factors[0], factors[1]), [1.0, -1.0, -1.0, 1.0]),
    ])
}

#[cfg(test)]
mod tests {
    use super::*;

    fn close(a: f64, b: f64, tol: f64) -> bool {
        (a - b).abs() < tol
    }

    /// Normal TOST by hand: d = 0.1, se = 0.1, margin 0.3: p_lower =
    /// 1 − Φ(4) ≈ 3.2e-5, p_upper = Φ(−2) = 0.02275; 90% CI 0.1 ± 1.6449·0.1.
    /// With 10 degrees of freedom the upper p is the t table's 0.0367.
    #[test]
    fn tost_matches_worked_examples() {
        let t = tost(0.1, 0.1, None, 0.3).unwrap();
        assert!(close(t.p_value, 0.022750, 1e-6), "{t:?}");
        assert!(close(t.ci90[0], -0.064485, 1e-6) && close(t.ci90[1], 0.264485, 1e-6), "{t:?}");
        assert!(close(tost(0.1, 0.1, Some(10.0), 0.3).unwrap().p_value, 0.036694, 1e-5));
        // A difference outside the margin is not equivalent, whatever its precision.
        assert!(tost(0.5, 0.01, None, 0.3).unwrap().p_value > 0.99);
        assert!(tost(0.1, 0.0, None, 0.3).is_none());
    }

    /// Balanced cells with spread 1 (n = 3): cell means 2, 3 / 4, 7. Row
    /// effect ½[(4 + 7) − (2 + 3)] = 3, column effect 2, interaction
    /// (7 − 4) − (3 − 2) = 2. By hand, two-way ANOVA: SS_interaction =
    /// 3 · 4 · 0.5² = 3, MSE = 1, F(1, 8) = 3, p = 0.1215; the contrast's
    /// t² must be F and its df the ANOVA's 8.
    #[test]
    fn factorial_matches_the_two_way_anova_on_a_balanced_example() {
        let (a, b, c, d) = ([1.0, 2.0, 3.0], [2.0, 3.0, 4.0], [3.0, 4.0, 5.0], [6.0, 7.0, 8.0]);
        let cells: [[&[f64]; 2]; 2] = [[&a, &b], [&c, &d]];
        let [row, column, interaction] = factorial(&cells, &["preset".into(), "connection".into()]).unwrap();
        assert!(close(row.estimate, 3.0, 1e-12) && close(column.estimate, 2.0, 1e-12) && close(interaction.estimate, 2.0, 1e-12));
        assert!(close((interaction.estimate / interaction.se).powi(2), 3.0, 1e-9));
        assert!(close(interaction.df, 8.0, 1e-9));
        assert!(close(interaction.p_value, 0.1215, 1e-3), "{interaction:?}");
        assert!(close(row.se, (1.0f64 / 3.0).sqrt(), 1e-12));
        assert_eq!(interaction.name, "preset × connection (interaction)");
        assert!(factorial(&[[&a, &b], [&c, &[1.0]]], &["x".into(), "y".into()]).is_none());
    }

    /// Unbalanced cells with unequal spreads, against an independent
    /// computation (numpy and scipy): 11 = 1, 2, 4; 12 = 2, 3;
    /// 21 = 5, 5.5, 7, 8; 22 = 6, 9, 10.
    #[test]
    fn factorial_welch_contrasts_on_an_unbalanced_example() {
        let (a, b, c, d) = ([1.0, 2.0, 4.0], [2.0, 3.0], [5.0, 5.5, 7.0, 8.0], [6.0, 9.0, 10.0]);
        let [row, _, interaction] = factorial(&[[&a, &b], [&c, &d]], &["r".into(), "c".into()]).unwrap();
        assert!(close(row.estimate, 4.9375, 1e-12) && close(row.se, 0.858222, 1e-6), "{row:?}");
        assert!(close(row.df, 5.852759, 1e-6) && close(row.p_value, 0.0013088, 1e-6), "{row:?}");
        assert!(close(interaction.estimate, 1.791667, 1e-6) && close(interaction.p_value, 0.337750, 1e-6), "{interaction:?}");
        // Values that are not numbers give no verdict, never p = 0.
        let nan = [f64::NAN, 1.0];
        let [row, ..] = factorial(&[[&nan, &b], [&c, &d]], &["r".into(), "c".into()]).unwrap();
        assert!(row.p_value.is_nan(), "{row:?}");
    }

    /// By hand: a reaches at 1 and 2, b at 3 and is censored at 4. At t = 1:
    /// 2 of 4 at risk in a, 1 event: E = 0.5, V = 0.25. At t = 2: 1 of 3,
    /// E = 1/3, V = 2/9. At t = 3: a has none at risk: E = 0, V = 0. O − E =
    /// 2 − 5/6 = 7/6, V = 17/36, χ² = (49/36)/(17/36) = 49/17, p = 0.08956.
    #[test]
    fn log_rank_matches_a_worked_example_and_strata_add() {
        let t = |episodes, reached| Time { episodes, reached };
        let a = vec![t(1, true), t(2, true)];
        let b = vec![t(3, true), t(4, false)];
        let lr = log_rank(&[(a.clone(), b.clone())]).unwrap();
        assert!(close(lr.observed_minus_expected, 7.0 / 6.0, 1e-12) && close(lr.variance, 17.0 / 36.0, 1e-12));
        assert!(close(lr.chi_square, 49.0 / 17.0, 1e-12) && close(lr.p_value, 0.089555, 1e-5), "{lr:?}");
        // Two identical strata: O − E and V double, χ² doubles.
        let two = log_rank(&[(a.clone(), b.clone()), (a, b)]).unwrap();
        assert!(close(two.chi_square, 2.0 * 49.0 / 17.0, 1e-12));
        // Ties and censoring at an event time (checked against scipy's
        // logrank): a = 1, 1, 2, 3, 3+; b = 1, 2, 2, 3+, 3+.
        let a = vec![t(1, true), t(1, true), t(2, true), t(3, true), t(3, false)];
        let b = vec![t(1, true), t(2, true), t(2, true), t(3, false), t(3, false)];
        let tied = log_rank(&[(a, b)]).unwrap();
        assert!(close(tied.chi_square, 0.385604, 1e-6) && close(tied.p_value, 0.534619, 1e-6), "{tied:?}");
        // Nobody gets there: no test.
        assert!(log_rank(&[(vec![t(5, false)], vec![t(5, false)])]).is_none());
    }

    #[test]
    fn speed_measures_of_a_run() {
        // The 10-episode mean reaches −3 first at episode 18 (2 × −10 + 8 × −1).
        let mut returns = vec![-10.0; 10];
        returns.extend([-1.0; 10]);
        assert_eq!(episodes_to_bar(&returns, -3.0, 200), Time { episodes: 18, reached: true });
        assert_eq!(episodes_to_bar(&returns, 0.0, 200), Time { episodes: 200, reached: false });
        // Floored at −8: ten at −8 and ten at −1 → −4.5.
        assert!(close(auc(&returns, -8.0).unwrap(), -4.5, 1e-12));
        assert!(auc(&[], 0.0).is_none());
        let t = |episodes, reached| Time { episodes, reached };
        // KM: 4 runs, events at 10 and 20, one censored at 15: S(10) = 3/4,
        // S(20) = 3/4 · (1 − 1/2) = 3/8 ≤ 1/2 → median 20.
        assert_eq!(km_median(&[t(10, true), t(15, false), t(20, true), t(30, true)]), Some(20));
        assert_eq!(km_median(&[t(10, true), t(200, false), t(200, false)]), None);
    }
}
