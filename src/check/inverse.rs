//! A local inverse against its promise, `f(x + dx) ≈ f(x) + dy`.

use super::Verdict;
use crate::op::{Forward, LocalInverse};

/// The relative error of one inverse step:
/// `‖f(x + dx) − f(x) − dy‖₂ / ‖dy‖₂` with `dx` from
/// [`LocalInverse::local_inverse`]. 0 for an exact inverse of a linear map;
/// 1 for `dx = 0`; above 1 for a step that makes matters worse.
///
/// # Panics
/// If `dy` is zero or a slice length does not match the operator.
pub fn local_inverse_error<O: LocalInverse + ?Sized>(op: &O, x: &[f64], p: &[f64], dy: &[f64]) -> f64 {
    let mut dx = vec![0.0; op.n_in()];
    op.local_inverse(x, p, dy, &mut dx);
    step_miss(op, x, p, &dx, dy)
}

/// `‖f(x + dx) − f(x) − dy‖₂ / ‖dy‖₂` for any step `dx`: how far `dx`
/// misses the change `dy` (for comparing an inverse with a baseline).
///
/// # Panics
/// If `dy` is zero or a slice length does not match the operator.
pub fn step_miss<O: Forward + ?Sized>(op: &O, x: &[f64], p: &[f64], dx: &[f64], dy: &[f64]) -> f64 {
    let norm = dy.iter().map(|v| v * v).sum::<f64>().sqrt();
    assert!(norm > 0.0, "step_miss: dy is zero");
    let (mut y0, mut y1) = (vec![0.0; op.n_out()], vec![0.0; op.n_out()]);
    op.forward(x, p, &mut y0);
    let moved: Vec<f64> = x.iter().zip(dx).map(|(a, b)| a + b).collect();
    op.forward(&moved, p, &mut y1);
    let miss = y1.iter().zip(&y0).zip(dy).map(|((a, b), d)| (a - b - d).powi(2)).sum::<f64>().sqrt();
    miss / norm
}

/// One scale of [`local_inverse`]'s sweep.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct InverseStep {
    /// `dy = scale · direction`.
    pub scale: f64,
    /// [`local_inverse_error`] at that `dy`.
    pub relative_error: f64,
}

/// What [`local_inverse`] measured.
#[derive(Clone, Debug, PartialEq)]
pub struct InverseReport {
    /// One entry per scale, in the order given.
    pub steps: Vec<InverseStep>,
    /// Pass when the smallest error is at most the tolerance.
    pub verdict: Verdict,
}

impl InverseReport {
    /// The smallest relative error over the sweep.
    pub fn best(&self) -> f64 {
        self.steps.iter().map(|s| s.relative_error).fold(f64::INFINITY, f64::min)
    }
}

/// Sweeps `dy = scale · direction` over `scales` and reports
/// [`local_inverse_error`] at each. The inverse of the linearisation gives
/// errors that fall in proportion to the scale (what remains is `f`'s
/// curvature); an approximate inverse levels off at its own error on
/// `direction` (that of `J·dx` against `dy`). Choose a `direction` the
/// operator can reach (`J·v` from a JVP, or `f(x + v) − f(x)`): the error of
/// an unreachable one measures the range of `f`, not the inverse.
///
/// # Panics
/// If `direction` is zero, `scales` is empty, or a slice length does not
/// match the operator.
pub fn local_inverse<O: LocalInverse + ?Sized>(op: &O, x: &[f64], p: &[f64], direction: &[f64], scales: &[f64], tol: f64) -> InverseReport {
    assert!(!scales.is_empty(), "local_inverse: no scales");
    let steps: Vec<InverseStep> = scales
        .iter()
        .map(|&scale| {
            let dy: Vec<f64> = direction.iter().map(|d| scale * d).collect();
            InverseStep { scale, relative_error: local_inverse_error(op, x, p, &dy) }
        })
        .collect();
    let mut report = InverseReport { steps, verdict: Verdict::Pass };
    let best = report.best();
    // A NaN miss fails too.
    if best.is_nan() || best > tol {
        report.verdict = Verdict::Fail(format!("smallest relative error {best:.3e} over the sweep, tolerance {tol:.1e}"));
    }
    report
}
