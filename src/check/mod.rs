//! Gradient checks, as library code: call them on your own operators.
//!
//! - [`finite_differences`]: the VJP against central differences of the
//!   forward, index by index, over a sweep of steps. The whole sweep is
//!   reported (error and worst index per step), not only the best step.
//! - [`taylor`]: the remainder `|φ(z + h·v) − φ(z) − h·∇φ·v|` of the
//!   first-order expansion of `φ = ⟨w, f⟩` must shrink as `h²` (rate ≈ 2
//!   when `h` halves).
//! - [`dot_product`]: `⟨J·v, w⟩ = ⟨v, Jᵀ·w⟩` between the JVP and the VJP,
//!   plus the VJP's buffer contract (it accumulates, and consumes its seed).
//! - [`local_inverse`]: a [`LocalInverse`](crate::op::LocalInverse) against
//!   its promise `f(x + dx) ≈ f(x) + dy`, the relative miss over a sweep of
//!   step sizes (what physical-gradient training relies on).
//!
//! Operators with inner iterative solves declare their tolerance
//! ([`Forward::solve_tolerance`], or [`CheckParams::solve_tolerance`]): the
//! checks then allow errors at that level instead of at rounding, and a
//! Taylor test with nothing left above it is [`Verdict::Tolerance`].
//!
//! Piecewise-smooth operators declare [`Forward::smooth_radius`]; the checks
//! keep their steps inside it, and when no usable step fits (the point sits
//! on or next to a kink) the verdict is [`Verdict::Kink`], never a blind pass
//! or fail.
//!
//! Every check draws its random directions from a seeded generator, so a
//! report is reproducible.

mod dot;
mod fd;
mod inverse;
mod taylor;

use std::fmt;

use rand::rngs::StdRng;
use rand::{Rng, SeedableRng};

use crate::op::Forward;

pub use dot::{DotReport, dot_product, dot_product_between};
pub use fd::{FdReport, FdStep, central_gradient, finite_differences, sweep_steps};
pub use inverse::{InverseReport, InverseStep, local_inverse, local_inverse_error, step_miss};
pub use taylor::{TaylorReport, taylor};

/// Outcome of a check.
#[derive(Clone, Debug, PartialEq)]
pub enum Verdict {
    /// Within tolerance.
    Pass,
    /// Outside tolerance; the string says by how much and where.
    Fail(String),
    /// A kink (switch of a piecewise-smooth operator) is too close to the
    /// point for the check to say anything; the string says how close.
    Kink(String),
    /// The operator's inner solves are accurate to a tolerance that leaves
    /// the check nothing to measure above it (every Taylor remainder at
    /// the solver's level); the string says which level.
    Tolerance(String),
}

impl Verdict {
    /// True for [`Verdict::Pass`].
    pub fn passed(&self) -> bool {
        matches!(self, Verdict::Pass)
    }
}

impl fmt::Display for Verdict {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        match self {
            Verdict::Pass => write!(f, "pass"),
            Verdict::Fail(s) => write!(f, "FAIL: {s}"),
            Verdict::Kink(s) => write!(f, "inconclusive (kink): {s}"),
            Verdict::Tolerance(s) => write!(f, "inconclusive (solver tolerance): {s}"),
        }
    }
}

/// Options shared by the checks.
#[derive(Clone, Debug)]
pub struct CheckParams {
    /// Seed of the random directions and weights.
    pub seed: u64,
    /// Tolerance: relative error for finite differences (against `‖g‖∞`)
    /// and for the dot-product test.
    pub tol: f64,
    /// At most this many input indices are differenced (all when the
    /// operator is smaller; otherwise a seeded random subset, always
    /// including the first and last index).
    pub max_indices: usize,
    /// The relative accuracy of the operator's inner solves; `None` takes
    /// the operator's own [`Forward::solve_tolerance`] (0 unless it
    /// declares one). With a tolerance `s > 0` the checks allow errors at
    /// that level: where the Taylor rates at rounding level fail, the test
    /// judges again on the remainders above `100·s·|φ|` (and when too few
    /// are left there, the verdict is [`Verdict::Tolerance`], not a
    /// failure); finite differences are held to at least `10·s^{2/3}` (the
    /// error of the best central difference of a map known to `s`) and the
    /// dot product to at least `10·s`.
    pub solve_tolerance: Option<f64>,
}

impl CheckParams {
    /// The solve tolerance the checks of `op` use: this one's, or the
    /// operator's.
    ///
    /// # Panics
    /// If the tolerance is negative or not finite.
    #[track_caller]
    pub fn solve_tolerance_of<O: Forward + ?Sized>(&self, op: &O) -> f64 {
        let s = self.solve_tolerance.unwrap_or_else(|| op.solve_tolerance());
        if !(s.is_finite() && s >= 0.0) {
            panic!(
                "CheckParams: the solve tolerance must be a finite number ≥ 0, got {s} (from {})",
                if self.solve_tolerance.is_some() { "CheckParams::solve_tolerance" } else { "the operator's solve_tolerance()" }
            );
        }
        s
    }
}

/// The former name of [`CheckParams`].
#[deprecated(note = "renamed CheckParams")]
pub type CheckOptions = CheckParams;

impl Default for CheckParams {
    fn default() -> Self {
        Self { seed: 0x5eed, tol: 1e-6, max_indices: 64, solve_tolerance: None }
    }
}

/// All three checks of one operator.
#[derive(Clone, Debug)]
pub struct FullReport {
    /// Finite differences.
    pub fd: FdReport,
    /// Taylor remainder.
    pub taylor: TaylorReport,
    /// Dot product.
    pub dot: DotReport,
}

impl FullReport {
    /// True when all three passed.
    pub fn passed(&self) -> bool {
        self.fd.verdict.passed() && self.taylor.verdict.passed() && self.dot.verdict.passed()
    }

    /// True when some check failed (an inconclusive one, at a kink, is not
    /// a failure).
    pub fn failed(&self) -> bool {
        [&self.fd.verdict, &self.taylor.verdict, &self.dot.verdict].iter().any(|v| matches!(v, Verdict::Fail(_)))
    }
}

impl fmt::Display for FullReport {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        write!(f, "{}\n{}\n{}", self.fd, self.taylor, self.dot)
    }
}

/// Runs the three checks on `op` at `(x, p)`.
///
/// # Panics
/// If `x` or `p` does not have the operator's length (at the caller's line).
#[track_caller]
pub fn check_all<O: crate::op::Vjp + crate::op::Jvp>(op: &O, x: &[f64], p: &[f64], opts: &CheckParams) -> FullReport {
    crate::op::check_lengths(op, "check_all", x, p, None);
    FullReport { fd: finite_differences(op, x, p, opts), taylor: taylor(op, x, p, opts), dot: dot_product(op, x, p, opts) }
}

/// A seeded vector with entries uniform in `[−1, 1)`.
pub fn random_vector(rng: &mut StdRng, n: usize) -> Vec<f64> {
    (0..n).map(|_| rng.random_range(-1.0..1.0)).collect()
}

fn rng(opts: &CheckParams, salt: u64) -> StdRng {
    StdRng::seed_from_u64(opts.seed ^ salt.wrapping_mul(0x9e37_79b9_7f4a_7c15))
}

fn dot(a: &[f64], b: &[f64]) -> f64 {
    a.iter().zip(b).map(|(a, b)| a * b).sum()
}

fn max_abs(v: &[f64]) -> f64 {
    v.iter().fold(0.0, |m, &a| m.max(a.abs()))
}

/// `φ(z) = ⟨w, f(x, p)⟩`.
fn functional<O: Forward + ?Sized>(op: &O, x: &[f64], p: &[f64], w: &[f64], y: &mut [f64]) -> f64 {
    op.forward(x, p, y);
    dot(w, y)
}

/// `a + t·b`.
fn axpy(a: &[f64], t: f64, b: &[f64]) -> Vec<f64> {
    a.iter().zip(b).map(|(a, b)| a + t * b).collect()
}
