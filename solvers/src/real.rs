//! The floating-point types kernels run in: `f64` and `f32`.
//!
//! [`Real`] is [`num_traits::Float`] plus what the vectorised kernels need:
//! a SIMD vector of [`Real::LANES`] values (eight `f64` or sixteen `f32`,
//! 512 bits either way), conversions to and from `f64`, and a fast
//! vectorisable `tanh`. The type is sealed: the kernels are written and
//! tested for these two types only.

use std::fmt::Debug;
use std::iter::Sum;
use std::ops::{Add, AddAssign, DivAssign, Mul, MulAssign, SubAssign};
use std::simd::{f32x16, f64x8};

use crate::nn::{self, Taps, WeightGrad};

mod sealed {
    pub trait Sealed {}
    impl Sealed for f64 {}
    impl Sealed for f32 {}
}

/// A floating-point type the kernels run in: `f64` or `f32`.
pub trait Real:
    num_traits::Float + std::simd::SimdElement + Default + Debug + Send + Sync + 'static + AddAssign + SubAssign + MulAssign + DivAssign + Sum + sealed::Sealed
{
    /// [`Real::LANES`] values in one vector register.
    type V: Copy + Add<Output = Self::V> + Mul<Output = Self::V> + AddAssign;
    /// Values per vector: 8 for `f64`, 16 for `f32`.
    const LANES: usize;
    /// `"f64"` or `"f32"`.
    const NAME: &'static str;
    /// `x` rounded to this type.
    fn of(x: f64) -> Self;
    /// `self` as `f64` (exact).
    fn as_f64(self) -> f64;
    /// All lanes `x`.
    fn splat(x: Self) -> Self::V;
    /// The first [`Real::LANES`] values of `s`.
    fn load(s: &[Self]) -> Self::V;
    /// Writes the vector to the first [`Real::LANES`] values of `s`.
    fn store(v: Self::V, s: &mut [Self]);
    /// `tanh x` to within a few units in the last place, branch-free so
    /// that loops over it vectorise (a NaN stays NaN).
    fn tanh_fast(self) -> Self;
    /// `y[i] = x[i].tanh_fast()`, compiled for the widest vector
    /// instructions the CPU has ([`crate::nn::tanh_slice`]).
    #[doc(hidden)]
    fn tanh_slice(x: &[Self], y: &mut [Self]);
    /// The blocked correlation behind [`crate::nn::conv1d`] and its adjoint.
    #[doc(hidden)]
    #[allow(clippy::too_many_arguments)]
    fn correlate(n: usize, k: usize, nq: usize, nr: usize, w: &[Self], taps: Taps, bias: Option<&[Self]>, inp: &[Self], out: &mut [Self], add: bool);
    /// The weight gradient of [`crate::nn::conv1d_adjoint`].
    #[doc(hidden)]
    fn weight_gradient(s: &WeightGrad, gy: &[Self], xp: &[Self], gw: &mut [Self]);
    /// Whether every value of `v` is finite ([`all_finite`]).
    #[doc(hidden)]
    fn all_finite_slice(v: &[Self]) -> bool;
    /// The loop of [`crate::nn::dense_batch`].
    #[doc(hidden)]
    fn dense_batch_kernel(n_in: usize, w: &[Self], b: &[Self], xs: &[Self], ys: &mut [Self]);
    /// The loops of [`crate::nn::dense_batch_adjoint`].
    #[doc(hidden)]
    #[allow(clippy::too_many_arguments)]
    fn dense_batch_adjoint_kernel(n_in: usize, w: &[Self], xs: &[Self], gys: &[Self], gxs: &mut [Self], gw: &mut [Self], gb: &mut [Self]);
    /// The input gradients of [`crate::nn::dense_batch_adjoint`] (its split form).
    #[doc(hidden)]
    fn dense_input_gradient_kernel(n_in: usize, w: &[Self], gys: &[Self], gxs: &mut [Self]);
    /// The weight gradients of [`crate::nn::dense_batch_adjoint`] (its split form).
    #[doc(hidden)]
    #[allow(clippy::too_many_arguments)]
    fn dense_weight_gradient_kernel(n_in: usize, n_out: usize, first: usize, xs: &[Self], gys: &[Self], gw: &mut [Self], gb: &mut [Self]);
}

/// Whether every value of `v` is finite (no NaN, no infinity), in one
/// vectorised pass with the widest instructions the CPU has: `x·0` is 0 for
/// finite `x` and NaN otherwise, summed in independent vector accumulators.
/// Cheap enough to run after every step of a rollout.
#[inline]
pub fn all_finite<R: Real>(v: &[R]) -> bool {
    R::all_finite_slice(v)
}

#[inline(always)]
fn all_finite_body<R: Real>(v: &[R]) -> bool {
    let zero = R::splat(R::zero());
    let mut acc = [zero; 4];
    let mut chunks = v.chunks_exact(4 * R::LANES);
    for c in &mut chunks {
        for (k, a) in acc.iter_mut().enumerate() {
            *a += R::load(&c[k * R::LANES..]) * zero;
        }
    }
    let mut rest = R::zero();
    for &x in chunks.remainder() {
        rest += x * R::zero();
    }
    let mut lanes = [R::zero(); 64];
    let mut total = rest;
    for a in acc {
        R::store(a, &mut lanes);
        total += lanes[..R::LANES].iter().copied().sum::<R>();
    }
    total.is_finite()
}

crate::simd_dispatch! {
    fn all_finite_f64(v: &[f64]) -> bool => all_finite_body::<f64>
}
crate::simd_dispatch! {
    fn all_finite_f32(v: &[f32]) -> bool => all_finite_body::<f32>
}

/// The kernel hooks of [`Real`], forwarded to the instances compiled in
/// [`crate::nn`].
macro_rules! hooks {
    ($tanh:ident, $correlate:ident, $weight_gradient:ident, $finite:ident, $dense:ident, $dense_adjoint:ident, $dense_gx:ident, $dense_gw:ident) => {
        #[inline]
        fn dense_input_gradient_kernel(n_in: usize, w: &[Self], gys: &[Self], gxs: &mut [Self]) {
            nn::$dense_gx(n_in, w, gys, gxs)
        }
        #[inline]
        fn dense_weight_gradient_kernel(n_in: usize, n_out: usize, first: usize, xs: &[Self], gys: &[Self], gw: &mut [Self], gb: &mut [Self]) {
            nn::$dense_gw(n_in, n_out, first, xs, gys, gw, gb)
        }
        #[inline]
        fn dense_batch_kernel(n_in: usize, w: &[Self], b: &[Self], xs: &[Self], ys: &mut [Self]) {
            nn::$dense(n_in, w, b, xs, ys)
        }
        #[inline]
        fn dense_batch_adjoint_kernel(n_in: usize, w: &[Self], xs: &[Self], gys: &[Self], gxs: &mut [Self], gw: &mut [Self], gb: &mut [Self]) {
            nn::$dense_adjoint(n_in, w, xs, gys, gxs, gw, gb)
        }
        #[inline]
        fn all_finite_slice(v: &[Self]) -> bool {
            $finite(v)
        }
        #[inline]
        fn tanh_slice(x: &[Self], y: &mut [Self]) {
            nn::$tanh(x, y)
        }
        #[inline]
        fn correlate(n: usize, k: usize, nq: usize, nr: usize, w: &[Self], taps: Taps, bias: Option<&[Self]>, inp: &[Self], out: &mut [Self], add: bool) {
            nn::$correlate(n, k, nq, nr, w, taps, bias, inp, out, add)
        }
        #[inline]
        fn weight_gradient(s: &WeightGrad, gy: &[Self], xp: &[Self], gw: &mut [Self]) {
            nn::$weight_gradient(s, gy, xp, gw)
        }
    };
}

impl Real for f64 {
    type V = f64x8;
    const LANES: usize = 8;
    const NAME: &'static str = "f64";
    hooks!(tanh_slice_f64, correlate_f64, weight_gradient_f64, all_finite_f64, dense_batch_f64, dense_batch_adjoint_f64, dense_gx_f64, dense_gw_f64);
    #[inline(always)]
    fn of(x: f64) -> Self {
        x
    }
    #[inline(always)]
    fn as_f64(self) -> f64 {
        self
    }
    #[inline(always)]
    fn splat(x: Self) -> Self::V {
        f64x8::splat(x)
    }
    #[inline(always)]
    fn load(s: &[Self]) -> Self::V {
        f64x8::from_slice(s)
    }
    #[inline(always)]
    fn store(v: Self::V, s: &mut [Self]) {
        v.copy_to_slice(s)
    }
    #[inline(always)]
    fn tanh_fast(self) -> Self {
        // (A comparison, not `min`: `f64::min` would turn a NaN into 20.)
        let a = if self.abs() > 20.0 { 20.0 } else { self.abs() };
        let e = expm1_f64(2.0 * a);
        let t = e / (e + 2.0);
        if self < 0.0 { -t } else { t }
    }
}

impl Real for f32 {
    type V = f32x16;
    const LANES: usize = 16;
    const NAME: &'static str = "f32";
    hooks!(tanh_slice_f32, correlate_f32, weight_gradient_f32, all_finite_f32, dense_batch_f32, dense_batch_adjoint_f32, dense_gx_f32, dense_gw_f32);
    #[inline(always)]
    fn of(x: f64) -> Self {
        x as f32
    }
    #[inline(always)]
    fn as_f64(self) -> f64 {
        self as f64
    }
    #[inline(always)]
    fn splat(x: Self) -> Self::V {
        f32x16::splat(x)
    }
    #[inline(always)]
    fn load(s: &[Self]) -> Self::V {
        f32x16::from_slice(s)
    }
    #[inline(always)]
    fn store(v: Self::V, s: &mut [Self]) {
        v.copy_to_slice(s)
    }
    #[inline(always)]
    fn tanh_fast(self) -> Self {
        // tanh 10 rounds to 1 in f32.
        let a = if self.abs() > 10.0 { 10.0 } else { self.abs() };
        let e = expm1_f32(2.0 * a);
        let t = e / (e + 2.0);
        if self < 0.0 { -t } else { t }
    }
}

/// `1/k!` for `k = 0..=13` (every `k!` here is exact in `f64`).
const INV_FACTORIAL: [f64; 14] = {
    let mut t = [1.0; 14];
    let mut f = 1.0;
    let mut k = 1;
    while k < 14 {
        f *= k as f64;
        t[k] = 1.0 / f;
        k += 1;
    }
    t
};

/// `e^z − 1` for `0 ≤ z ≤ 40`: `z = n·ln2 + r`, `|r| ≤ ln2/2`,
/// `e^r − 1 = r·q(r)` with `q` the Taylor polynomial of degree 12
/// (Estrin's scheme: a short dependency chain), then
/// `2^n·(e^r − 1) + (2^n − 1)` (`2^n` from the exponent bits; for `n = 0`
/// simply `e^r − 1`, accurate for tiny `z`).
#[inline(always)]
#[allow(clippy::excessive_precision)] // the split of ln 2 as published
fn expm1_f64(z: f64) -> f64 {
    const SHIFT: f64 = 6755399441055744.0; // 1.5·2^52: adding it rounds to an integer
    const LN2_HI: f64 = 0.693_147_180_369_123_816_49;
    const LN2_LO: f64 = 1.908_214_929_270_587_7e-10;
    let kd = z * std::f64::consts::LOG2_E + SHIFT;
    let ki = kd.to_bits();
    let n = kd - SHIFT;
    let r = (z - n * LN2_HI) - n * LN2_LO;
    // q(r) = Σ_{j=0}^{12} r^j/(j+1)!, c_j = INV_FACTORIAL[j + 1].
    let c = |j: usize| INV_FACTORIAL[j + 1];
    let (r2, r4) = (r * r, (r * r) * (r * r));
    let r8 = r4 * r4;
    let q03 = (c(0) + c(1) * r) + (c(2) + c(3) * r) * r2;
    let q47 = (c(4) + c(5) * r) + (c(6) + c(7) * r) * r2;
    let q812 = ((c(8) + c(9) * r) + (c(10) + c(11) * r) * r2) + c(12) * r4;
    let q = (q03 + q47 * r4) + q812 * r8;
    let scale = f64::from_bits((ki.wrapping_sub(SHIFT.to_bits()).wrapping_add(1023)) << 52);
    scale * (r * q) + (scale - 1.0)
}

/// [`expm1_f64`] in single precision for `0 ≤ z ≤ 20`: the same reduction
/// (`ln 2` split as in Cephes' `expf`) and the Taylor
/// polynomial of degree 7 (truncation `(ln2/2)^8/8! ≈ 4e-9`, below half an
/// ulp of `f32`).
#[inline(always)]
#[allow(clippy::excessive_precision)] // the split of ln 2 as published
fn expm1_f32(z: f32) -> f32 {
    const SHIFT: f32 = 12582912.0; // 1.5·2^23
    const LN2_HI: f32 = 0.693_359_375; // 355/512: n·LN2_HI is exact
    const LN2_LO: f32 = -2.121_944_4e-4;
    let kd = z * std::f32::consts::LOG2_E + SHIFT;
    let ki = kd.to_bits();
    let n = kd - SHIFT;
    let r = (z - n * LN2_HI) - n * LN2_LO;
    let c = |j: usize| INV_FACTORIAL[j + 1] as f32;
    let (r2, r4) = (r * r, (r * r) * (r * r));
    let q03 = (c(0) + c(1) * r) + (c(2) + c(3) * r) * r2;
    let q47 = (c(4) + c(5) * r) + (c(6) + c(7) * r) * r2;
    let q = q03 + q47 * r4;
    let scale = f32::from_bits((ki.wrapping_sub(SHIFT.to_bits()).wrapping_add(127)) << 23);
    scale * (r * q) + (scale - 1.0)
}
