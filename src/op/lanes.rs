//! Samples side by side in vector lanes: the batch methods
//! [`Forward::forward_each`](super::Forward::forward_each) and
//! [`Vjp::vjp_each`](super::Vjp::vjp_each) of an operator declared with
//! `differentiable!(Op => f, lanes = g)`.
//!
//! A small system integrated per sample (four oscillator states through 96
//! RK4 steps) is scalar code: one sample's operations depend on each other,
//! so nothing vectorises. Run [`LANES`] samples at once instead, each
//! value stored as `LANES` consecutive numbers (lane `l` of component `c` at
//! `c·LANES + l`), and the loop over the lanes vectorises: the user writes
//! `g`, the per-sample step inside a `for l in 0..LANES` loop, Enzyme
//! differentiates `g` once, and the framework gathers groups of samples into
//! lanes, calls `g` (or its generated adjoint) compiled for the widest
//! vector instructions the CPU has (AVX-512, AVX2 or baseline x86-64, chosen
//! at run time), and scatters the results back. A last partial group fills
//! its spare lanes with a copy of its first sample and a zero seed; their
//! results are dropped.

use super::with_scratch;

/// Samples per call of a lane form: eight `f64`, one AVX-512 register.
pub const LANES: usize = 8;

/// Copies samples `first..first + k` of a batch with `n` values per sample
/// into lane layout (`dst[c·LANES + l]`); lanes `k..` get `pad`, or a copy
/// of the group's first sample when `pad` is `None`.
#[inline(always)]
fn gather(src: &[f64], n: usize, first: usize, k: usize, pad: Option<f64>, dst: &mut [f64]) {
    for (c, lanes) in dst.as_chunks_mut::<LANES>().0.iter_mut().enumerate().take(n) {
        for (l, v) in lanes.iter_mut().enumerate() {
            *v = if l < k { src[(first + l) * n + c] } else { pad.unwrap_or(src[first * n + c]) };
        }
    }
}

/// Writes (or adds, `ADD`) the first `k` lanes of `src` (lane layout, `n`
/// values per sample) to samples `first..first + k` of `dst`.
#[inline(always)]
fn scatter<const ADD: bool>(src: &[f64], n: usize, first: usize, k: usize, dst: &mut [f64]) {
    for (c, lanes) in src.as_chunks::<LANES>().0.iter().enumerate().take(n) {
        for (l, v) in lanes.iter().enumerate().take(k) {
            let d = &mut dst[(first + l) * n + c];
            *d = if ADD { *d + v } else { *v };
        }
    }
}

/// `forward_each` through the lane form `g(x, p, y)` on `count` samples of
/// `sizes = [n_in, n_params, n_out]` values (lengths checked by the caller).
#[doc(hidden)]
#[inline]
pub fn forward_each<G: Fn(&[f64], &[f64], &mut [f64])>(sizes: [usize; 3], count: usize, xs: &[f64], ps: &[f64], ys: &mut [f64], g: G) {
    dispatch_generic!(forward_each_body, [G: Fn(&[f64], &[f64], &mut [f64])], sizes: [usize; 3], count: usize, xs: &[f64], ps: &[f64], ys: &mut [f64], g: G)
}

#[inline(always)]
fn forward_each_body<G: Fn(&[f64], &[f64], &mut [f64])>(sizes: [usize; 3], count: usize, xs: &[f64], ps: &[f64], ys: &mut [f64], g: G) {
    let [n_in, n_p, n_out] = sizes;
    with_scratch((n_in + n_p + n_out) * LANES, |buf| {
        let (x, rest) = buf.split_at_mut(n_in * LANES);
        let (p, y) = rest.split_at_mut(n_p * LANES);
        for first in (0..count).step_by(LANES) {
            let k = LANES.min(count - first);
            gather(xs, n_in, first, k, None, x);
            gather(ps, n_p, first, k, None, p);
            g(x, p, y);
            scatter::<false>(y, n_out, first, k, ys);
        }
    })
}

/// The generated adjoint of a lane form: `g(x, dx, p, dp, y, dy)` adds into
/// `dx` and `dp` and consumes `dy` (Enzyme's `Duplicated` arguments).
#[doc(hidden)]
pub trait LanesVjp: Fn(&[f64], &mut [f64], &[f64], &mut [f64], &mut [f64], &mut [f64]) {}
impl<G: Fn(&[f64], &mut [f64], &[f64], &mut [f64], &mut [f64], &mut [f64])> LanesVjp for G {}

/// `vjp_each` through the generated adjoint `g` of a lane form (lengths
/// checked by the caller): adds into `dxs` and `dps`, consumes `dys`.
#[doc(hidden)]
#[inline]
#[allow(clippy::too_many_arguments)]
pub fn vjp_each<G: LanesVjp>(sizes: [usize; 3], count: usize, xs: &[f64], ps: &[f64], dys: &mut [f64], dxs: &mut [f64], dps: &mut [f64], g: G) {
    dispatch_generic!(vjp_each_body, [G: LanesVjp], sizes: [usize; 3], count: usize, xs: &[f64], ps: &[f64], dys: &mut [f64], dxs: &mut [f64], dps: &mut [f64], g: G)
}

#[inline(always)]
#[allow(clippy::too_many_arguments)]
fn vjp_each_body<G: LanesVjp>(sizes: [usize; 3], count: usize, xs: &[f64], ps: &[f64], dys: &mut [f64], dxs: &mut [f64], dps: &mut [f64], g: G) {
    let [n_in, n_p, n_out] = sizes;
    with_scratch(2 * (n_in + n_p + n_out) * LANES, |buf| {
        let (x, rest) = buf.split_at_mut(n_in * LANES);
        let (dx, rest) = rest.split_at_mut(n_in * LANES);
        let (p, rest) = rest.split_at_mut(n_p * LANES);
        let (dp, rest) = rest.split_at_mut(n_p * LANES);
        let (y, dy) = rest.split_at_mut(n_out * LANES);
        for first in (0..count).step_by(LANES) {
            let k = LANES.min(count - first);
            gather(xs, n_in, first, k, None, x);
            gather(ps, n_p, first, k, None, p);
            gather(dys, n_out, first, k, Some(0.0), dy);
            dx.fill(0.0);
            dp.fill(0.0);
            g(x, dx, p, dp, y, dy);
            scatter::<true>(dx, n_in, first, k, dxs);
            scatter::<true>(dp, n_p, first, k, dps);
        }
    });
    dys.fill(0.0);
}
