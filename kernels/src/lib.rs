//! Numeric loops over plain `f32` slices, compiled at opt-level 3 in every
//! profile (the workspace's Cargo.toml) so that LLVM vectorizes them:
//! the learner's crate is built at opt-level 1, where it would not.
//!
//! Today one kernel: ELU (α = 1) and its slope, for the learner's CPU
//! activations (learner/src/algo/elu.rs says why and how they are used).
//!
//! ```text
//! elu(x)  = x   for x > 0,   eˣ − 1   for x ≤ 0
//! elu′(x) = 1   for x > 0,   eˣ       for x ≤ 0
//! ```
//!
//! eˣ for x ≤ 0 is Cephes' `expf`: x = n·ln 2 + r with |r| ≤ ln 2 / 2, eʳ
//! by a degree-7 polynomial, 2ⁿ put in the exponent bits; relative error
//! within 2.4e-7 (two machine epsilons, tested). Every step is a plain
//! add, multiply, compare or bit shift, branch-free per element, so each
//! loop below becomes 8-lane AVX2 code on the project's x86-64-v3 target
//! and 4-lane SSE2 code on a plain x86-64 build (no `mul_add` or
//! `round_ties_even`, which without FMA and SSE4.1 would be calls into
//! the C maths library, one per element). eˣ − 1 is then one
//! subtraction: absolute error within 1.2e-7, the relative accuracy
//! `expm1` keeps near 0 given up (elu(−3e-8) is 0; a hidden unit that
//! near 0 contributes nothing either way).

/// Below this, eˣ (< 1.7e-38) is taken as 0 for the value (elu = −1
/// exactly in f32 anyway) and for the slope, and the range reduction
/// keeps 2ⁿ a normal number (n ≥ −126).
const LOWEST: f32 = -87.0;

/// Adding and subtracting 1.5 · 2²³ rounds an f32 below 2²² in magnitude
/// to the nearest integer (ties to even) in the default rounding mode.
const ROUND: f32 = 12_582_912.0;

/// eˣ for x in [LOWEST, 0] (anything else is clamped into it first; NaN
/// gives a number, and callers keep NaN themselves).
#[inline(always)]
fn exp_nonpositive(x: f32) -> f32 {
    const LOG2_E: f32 = std::f32::consts::LOG2_E;
    // ln 2 in two parts: n·LN2_HI is exact for the n that occur here.
    const LN2_HI: f32 = 355.0 / 512.0;
    const LN2_LO: f32 = -2.121_944_4e-4;
    // max/min, not clamp: they keep no NaN, and the callers select x
    // itself for a NaN anyway.
    #[allow(clippy::manual_clamp)]
    let x = x.max(LOWEST).min(0.0);
    let n = (x * LOG2_E + ROUND) - ROUND;
    let r = (x - n * LN2_HI) - n * LN2_LO;
    let mut p = 1.987_569_1e-4_f32;
    p = p * r + 1.398_199_9e-3;
    p = p * r + 8.333_452e-3;
    p = p * r + 4.166_579_6e-2;
    p = p * r + 1.666_666_5e-1;
    p = p * r + 0.5;
    let er = (p * (r * r) + r) + 1.0;
    // 2ⁿ for n in [−126, 0]: n + 127 is the biased exponent. Adding 2²³
    // puts that integer in the mantissa's low bits, and the shift moves it
    // to the exponent's (no float-to-int cast, whose saturation would
    // keep the loop scalar).
    let two_n = f32::from_bits((n + (127.0 + 8_388_608.0)).to_bits() << 23);
    er * two_n
}

/// elu(x) in place. NaN stays NaN; −0.0 becomes +0.0 (e⁰ − 1).
pub fn elu_in_place(values: &mut [f32]) {
    for v in values.iter_mut() {
        let x = *v;
        let negative = exp_nonpositive(x) - 1.0;
        // `x <= 0` is false for NaN, which then stays.
        *v = if x <= 0.0 { negative } else { x };
    }
}

/// slope = elu′(x) and offset = elu(x) − x·elu′(x), so that
/// elu(x) = offset + x·slope with slope the gradient: the learner's
/// differentiable ELU is one recorded product (learner/src/algo/elu.rs).
/// For x > 0 (and NaN): slope 1, offset 0. Below LOWEST: slope 0 and
/// offset −1, so every finite x gives elu(x) = −1 there exactly (and −∞
/// gives NaN: −∞ · 0).
///
/// # Panics
/// If the three slices differ in length.
pub fn elu_slope_and_offset(input: &[f32], slope: &mut [f32], offset: &mut [f32]) {
    assert!(input.len() == slope.len() && input.len() == offset.len(), "elu_slope_and_offset: slices of different lengths");
    for ((&x, d), c) in input.iter().zip(slope.iter_mut()).zip(offset.iter_mut()) {
        let e = exp_nonpositive(x);
        let (slope_x, offset_x) = if x > 0.0 || x.is_nan() {
            (1.0, 0.0)
        } else if x < LOWEST {
            (0.0, -1.0)
        } else {
            (e, (e - 1.0) - x * e)
        };
        *d = slope_x;
        *c = offset_x;
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// x from −90 to 0 in fine steps, −0.0, and the tiny values where
    /// eˣ − 1 ≈ x.
    fn nonpositive() -> Vec<f32> {
        let mut v: Vec<f32> = (0..=90_000).map(|i| -90.0 + i as f32 * 1e-3).filter(|x| *x <= 0.0).collect();
        v.extend((1..2000).map(|i| -(i as f32) * 1e-7));
        v.extend([0.0, -0.0, -1e-30, -f32::MIN_POSITIVE]);
        v
    }

    #[test]
    fn exp_is_within_two_machine_epsilons_of_f64s() {
        for x in nonpositive().into_iter().filter(|&x| x >= LOWEST) {
            let exact = f64::from(x).exp();
            let ours = f64::from(exp_nonpositive(x));
            assert!((ours - exact).abs() <= 2.0 * f64::from(f32::EPSILON) * exact, "e^{x}: {ours} against {exact}");
        }
    }

    #[test]
    fn elu_matches_f64_and_keeps_positive_and_nan_values() {
        let mut v = nonpositive();
        v.extend([1e-30, 0.5, 3.0, 1e30, f32::INFINITY, f32::NAN]);
        let mut out = v.clone();
        elu_in_place(&mut out);
        for (&x, &y) in v.iter().zip(&out) {
            if x.is_nan() {
                assert!(y.is_nan());
            } else if x > 0.0 {
                assert_eq!(y, x);
            } else {
                let exact = f64::from(x).exp_m1();
                assert!((f64::from(y) - exact).abs() <= 1.2e-7, "elu({x}) = {y}, exactly {exact}");
            }
        }
        // −∞ is the far tail: −1.
        let mut tail = [f32::NEG_INFINITY];
        elu_in_place(&mut tail);
        assert_eq!(tail, [-1.0]);
    }

    #[test]
    fn slope_and_offset_rebuild_elu_and_its_derivative() {
        let mut v = nonpositive();
        v.extend([0.25, 7.0, f32::NAN, -1e3, -6e37, -3e38, f32::MIN]);
        let (mut d, mut c) = (vec![0.0; v.len()], vec![0.0; v.len()]);
        elu_slope_and_offset(&v, &mut d, &mut c);
        for ((&x, &d), &c) in v.iter().zip(&d).zip(&c) {
            if x > 0.0 || x.is_nan() {
                assert_eq!((d, c), (1.0, 0.0));
                continue;
            }
            let value = c + x * d;
            if x < LOWEST {
                // The far tail: slope 0, and the value −1 for any finite x.
                assert_eq!((d, c, value), (0.0, -1.0, -1.0), "at {x}");
                continue;
            }
            let slope = f64::from(x).exp();
            assert!((f64::from(d) - slope).abs() <= 2.0 * f64::from(f32::EPSILON) * slope, "elu'({x}) = {d}, exactly {slope}");
            assert!((f64::from(value) - f64::from(x).exp_m1()).abs() <= 1.2e-7, "offset + x·slope at {x} = {value}");
        }
        // −∞ gives NaN (−∞ · 0), which the learner's finite checks catch.
        let (mut d, mut c) = ([0.0], [0.0]);
        elu_slope_and_offset(&[f32::NEG_INFINITY], &mut d, &mut c);
        assert!((c[0] + f32::NEG_INFINITY * d[0]).is_nan());
    }

    #[test]
    #[should_panic(expected = "different lengths")]
    fn slope_and_offset_refuse_mismatched_slices() {
        elu_slope_and_offset(&[0.0; 3], &mut [0.0; 3], &mut [0.0; 2]);
    }
}
