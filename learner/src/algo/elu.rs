//! ELU (α = 1) on the CPU at the cost of an exponential, not of `expm1`.
//!
//! ```text
//! elu(x) = x        for x > 0
//!          eˣ − 1   for x ≤ 0
//! ```
//!
//! (the peg presets' activation, docs/peg.md).
//!
//! libtorch computes the x ≤ 0 branch with a vectorized `expm1`, which on
//! this project's CPUs costs about twice its `exp` and makes ELU the most
//! expensive pass over a layer's activations; the locally connected actor
//! has 2.25× the global one's hidden units, so it paid that twice over
//! (docs/scaling.md, "The sparse actor's cost"). Here eˣ comes from
//! `lcrl_kernels` (a vectorized polynomial) and eˣ − 1 is one
//! subtraction: values within 1.2e-7 of libtorch's, gradients within
//! 1e-6 (tested below).
//!
//! - **No gradient wanted** (target networks, acting, serving): the layer's
//!   output is rewritten in place.
//! - **A gradient wanted**: autograd must see the operation. With
//!   d = elu′(x) (1, or eˣ) and c = elu(x) − x·d, both computed here and
//!   constant to autograd, the output is c + x·d (`addcmul`): its value is
//!   elu(x) and its gradient with respect to x is d, what `elu_backward`
//!   gives. One recorded product replaces `elu_`'s kernel and its backward
//!   pass stays one product. (Below −87 the slope is 0 and the value −1,
//!   as libtorch's; at x = −∞ the value is NaN (−∞ · 0) where libtorch
//!   gives −1, and the learner's finite-weights check rewinds an update
//!   that produced one, docs/reliability.md, "Finite weights only".)
//!
//! Anything else runs libtorch's `elu_`: a CUDA tensor, another dtype, a
//! strided view, a forward pass being traced into TorchScript by `lcrl
//! export` (see [`traceable`]; a trace records only libtorch's ops), and
//! libtorch thread counts at which its parallel kernel is the faster
//! (more than 2 without gradient, more than 1 with).

use std::cell::Cell;

use lcrl_kernels::{elu_in_place, elu_slope_and_offset};
use tch::{Device, Kind, Tensor};

thread_local! {
    /// Set while a forward pass is traced: raw-memory writes would be
    /// invisible to the trace.
    static TRACING: Cell<bool> = const { Cell::new(false) };
}

/// Runs `f` with every ELU as libtorch's own op, so that tracing records
/// it (`lcrl export`). Nested calls are fine.
pub fn traceable<T>(f: impl FnOnce() -> T) -> T {
    /// Puts the flag back however `f` ends, a panic included.
    struct Restore(bool);
    impl Drop for Restore {
        fn drop(&mut self) {
            TRACING.with(|t| t.set(self.0));
        }
    }
    let _restore = Restore(TRACING.with(|t| t.replace(true)));
    f()
}

/// ELU of a layer's fresh output `x`: nothing else may hold it, since
/// without a gradient it is rewritten in place behind libtorch's back (no
/// version counter sees it). Hence crate-private, called only by
/// `nets::activate` on the output of a layer's product.
pub(crate) fn elu(mut x: Tensor) -> Tensor {
    if takes_kernels(&x, tch::get_num_threads()) { kernel_elu(x) } else { x.elu_() }
}

/// Whether `x` is computed by `lcrl_kernels` rather than libtorch's `elu_`.
/// The kernels run on the calling thread, while libtorch splits a layer's
/// activations over its threads. Measured (one layer of 64–256 rows ×
/// 256–576 units; docs/research/2026-12-06-sparse-actor-cost.md): without
/// gradient the kernels are faster at 1 and 2 threads, with gradient
/// only at 1.
fn takes_kernels(x: &Tensor, threads: i32) -> bool {
    let plain = x.device() == Device::Cpu && x.kind() == Kind::Float && x.is_contiguous() && !TRACING.with(Cell::get);
    plain && if x.requires_grad() { threads == 1 } else { threads <= 2 }
}

/// The elements of a contiguous CPU f32 tensor with at least one element.
///
/// # Safety
/// No other slice of `t`'s elements may be alive while this one is, and
/// nothing may read `t` through libtorch meanwhile if the slice is written.
#[allow(clippy::mut_from_ref)]
unsafe fn elements(t: &Tensor) -> &mut [f32] {
    debug_assert!(t.device() == Device::Cpu && t.kind() == Kind::Float && t.is_contiguous() && t.numel() > 0);
    // SAFETY: the pointer is t's first element and t holds numel() f32s
    // contiguously (the caller's promise above).
    unsafe { std::slice::from_raw_parts_mut(t.data_ptr().cast::<f32>(), t.numel()) }
}

/// [`elu`] by the kernels: `x` is a contiguous CPU f32 tensor.
fn kernel_elu(x: Tensor) -> Tensor {
    if x.numel() == 0 {
        // An empty tensor's data pointer may be null, which no slice may hold.
        return x;
    }
    if !x.requires_grad() {
        // SAFETY: x is fresh from the layer's product; nothing else reads it.
        elu_in_place(unsafe { elements(&x) });
        return x;
    }
    // empty_like keeps x's contiguous layout.
    let slope = Tensor::empty_like(&x);
    let mut offset = Tensor::empty_like(&x);
    // SAFETY: three distinct tensors, x only read; slope and offset fresh.
    unsafe { elu_slope_and_offset(elements(&x), elements(&slope), elements(&offset)) };
    offset.addcmul_(&x, &slope)
}

#[cfg(test)]
mod tests {
    use super::*;

    /// Every regime: large and small of both signs, zero, the tails where
    /// eˣ underflows, and ±∞; 8k + 5 values so a vectorized loop's
    /// remainder runs too.
    fn inputs() -> Vec<f32> {
        let mut v: Vec<f32> = (0..4000).map(|i| -20.0 + 40.0 * i as f32 / 3999.0).collect();
        v.extend((0..3000).map(|i| -1e-3 + 2e-3 * i as f32 / 2999.0));
        v.extend([0.0, -0.0, -87.0, -103.9, -150.0, -1e30, 1e30, f32::INFINITY, f32::NEG_INFINITY, 1e-30, -1e-30, 0.5, -0.5]);
        v
    }

    /// The largest |a − b| over the finite inputs, and the input it was at
    /// (a NaN in `a` counts as infinitely far).
    fn max_abs_diff(a: &Tensor, b: &Tensor, x: &[f32]) -> (f64, f32) {
        let (a, b) = (Vec::<f32>::try_from(a).expect("f32"), Vec::<f32>::try_from(b).expect("f32"));
        let mut worst = (0.0, 0.0);
        for ((a, b), &x) in a.iter().zip(&b).zip(x).filter(|(_, x)| x.is_finite()) {
            let diff = if a.is_nan() { f64::INFINITY } else { f64::from((a - b).abs()) };
            if diff > worst.0 {
                worst = (diff, x);
            }
        }
        worst
    }

    #[test]
    fn without_gradient_equals_libtorch_elu_within_an_ulp_of_one() {
        let x = Tensor::from_slice(&inputs());
        let reference = x.elu();
        let ours = kernel_elu(x.copy());
        assert_eq!(ours.size(), reference.size());
        let (diff, at) = max_abs_diff(&ours, &reference, &inputs());
        assert!(diff <= 1.2e-7, "ELU off libtorch's by {diff} at x = {at}");
        // Exactly x above zero, NaN in NaN out.
        assert!(ours.eq_tensor(&reference).logical_or(&x.le(0.0)).all().int64_value(&[]) == 1, "x > 0 must pass through unchanged");
        let nan = kernel_elu(Tensor::from_slice(&[f32::NAN; 9]));
        assert!(nan.isnan().all().int64_value(&[]) == 1, "NaN must stay NaN: {nan}");
    }

    #[test]
    fn with_gradient_value_and_gradient_equal_libtorch_elu() {
        let values = inputs();
        let ours_x = Tensor::from_slice(&values).set_requires_grad(true);
        let ref_x = Tensor::from_slice(&values).set_requires_grad(true);
        // A non-uniform upstream gradient, so the slope is checked per element.
        let weight = Tensor::from_slice(&values.iter().enumerate().map(|(i, _)| 0.5 + (i % 7) as f32).collect::<Vec<_>>());
        // The fresh layer output `elu` expects: x · 1 is a new tensor.
        let ours = kernel_elu(&ours_x * 1.0);
        let reference = (&ref_x * 1.0).elu();
        let (diff, at) = max_abs_diff(&ours.detach(), &reference.detach(), &values);
        assert!(diff <= 1.2e-7, "ELU with gradient off libtorch's by {diff} at x = {at}");
        (&ours * &weight).sum(Kind::Float).backward();
        (&reference * &weight).sum(Kind::Float).backward();
        let (g, g_ref) = (ours_x.grad(), ref_x.grad());
        // Every gradient, the infinite inputs' included (slope 0 below −87, 1 at ∞).
        let (diff, at) = max_abs_diff(&g, &g_ref, &values);
        assert!(diff <= 1e-6, "ELU's gradient off libtorch's by {diff} at x = {at}");
        // The infinite inputs' values: elu(∞) = ∞, and NaN for −∞ (c + x·d
        // is −1 + (−∞)·0), where libtorch gives −1 (the module's note).
        let at = |v: f32| ours.masked_select(&Tensor::from_slice(&values).eq(f64::from(v))).double_value(&[0]);
        assert_eq!(at(f32::INFINITY), f64::INFINITY);
        assert!(at(f32::NEG_INFINITY).is_nan());
        // NaN in, NaN out, here too.
        let nan = kernel_elu(Tensor::from_slice(&[f32::NAN; 9]).set_requires_grad(true) * 1.0);
        assert!(nan.isnan().all().int64_value(&[]) == 1, "NaN must stay NaN: {nan}");
    }

    #[test]
    fn which_inputs_take_the_kernels() {
        let x = Tensor::from_slice(&inputs());
        let with_grad = Tensor::from_slice(&inputs()).set_requires_grad(true) * 1.0;
        // By libtorch thread count: without gradient at 1 and 2, with it at 1.
        assert!(takes_kernels(&x, 1) && takes_kernels(&x, 2) && !takes_kernels(&x, 4));
        assert!(takes_kernels(&with_grad, 1) && !takes_kernels(&with_grad, 2));
        // Never while tracing, nor for a strided view or another dtype.
        assert!(!traceable(|| takes_kernels(&x, 1)));
        assert!(!TRACING.with(Cell::get), "traceable restores the flag");
        let strided = Tensor::from_slice(&inputs()[..7000]).view([70, 100]).transpose(0, 1);
        assert!(!strided.is_contiguous() && !takes_kernels(&strided, 1));
        assert!(!takes_kernels(&x.to_kind(Kind::Double), 1));
        // And what libtorch then computes is its elu_ bit for bit.
        let reference = x.elu();
        let traced = traceable(|| elu(x.copy()));
        assert!(traced.eq_tensor(&reference).all().int64_value(&[]) == 1);
    }

    #[test]
    fn an_empty_batch_passes_with_and_without_gradient() {
        assert_eq!(kernel_elu(Tensor::zeros([0, 4], (Kind::Float, Device::Cpu))).size(), [0, 4]);
        let empty = Tensor::zeros([0, 4], (Kind::Float, Device::Cpu)).set_requires_grad(true);
        assert_eq!(kernel_elu(&empty * 1.0).size(), [0, 4]);
    }
}
