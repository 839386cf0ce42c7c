//! Finite-difference derivatives of any [`Forward`] operator: the third,
//! independent implementation of [`Vjp`] and [`Jvp`].

use super::{Forward, Jvp, Operator, Vjp, validate_jvp, validate_vjp};

/// Central finite differences of an operator.
///
/// The step for a perturbation direction `v` at the point `z = (x, p)` is
/// `h = rel_step · max(1, ‖z‖∞) / ‖v‖∞`; the default `rel_step` is
/// `ε^{1/3} ≈ 6.1e-6`, which balances the `O(h²)` truncation error of central
/// differences against the `O(ε/h)` rounding error.
///
/// The VJP is built column by column (`2·(n + m)` forward evaluations), so
/// this is for checking small operators, not for training.
#[derive(Clone, Debug)]
pub struct FiniteDiff<O> {
    /// The operator differentiated.
    pub op: O,
    /// Relative step, see the type's documentation.
    pub rel_step: f64,
}

impl<O> FiniteDiff<O> {
    /// Central differences with the default step `ε^{1/3}`.
    pub fn new(op: O) -> Self {
        Self { op, rel_step: f64::EPSILON.cbrt() }
    }

    /// Central differences with relative step `rel_step`.
    pub fn with_step(op: O, rel_step: f64) -> Self {
        Self { op, rel_step }
    }
}

fn max_abs(v: &[f64]) -> f64 {
    v.iter().fold(0.0, |m, &a| m.max(a.abs()))
}

impl<O: Forward> FiniteDiff<O> {
    /// `(f(z + h·t) − f(z − h·t)) / 2h` into `out` (overwrites), with `t = (tx, tp)`.
    fn central(&self, x: &[f64], p: &[f64], tx: &[f64], tp: &[f64], out: &mut [f64]) {
        let tnorm = max_abs(tx).max(max_abs(tp));
        if tnorm == 0.0 {
            out.fill(0.0);
            return;
        }
        let znorm = max_abs(x).max(max_abs(p)).max(1.0);
        let h = self.rel_step * znorm / tnorm;
        let shift = |s: f64, a: &[f64], t: &[f64]| -> Vec<f64> { a.iter().zip(t).map(|(a, t)| a + s * t).collect() };
        let mut plus = vec![0.0; self.op.n_out()];
        let mut minus = vec![0.0; self.op.n_out()];
        self.op.forward(&shift(h, x, tx), &shift(h, p, tp), &mut plus);
        self.op.forward(&shift(-h, x, tx), &shift(-h, p, tp), &mut minus);
        for ((o, a), b) in out.iter_mut().zip(&plus).zip(&minus) {
            *o = (a - b) / (2.0 * h);
        }
    }
}

sizes_of_inner!([O: Operator] FiniteDiff<O> => op);

impl<O: Forward> Forward for FiniteDiff<O> {
    fn forward(&self, x: &[f64], p: &[f64], y: &mut [f64]) {
        self.op.forward(x, p, y)
    }

    fn smooth_radius(&self, x: &[f64], p: &[f64], dx: &[f64], dp: &[f64]) -> f64 {
        self.op.smooth_radius(x, p, dx, dp)
    }
}

impl<O: Forward> Jvp for FiniteDiff<O> {
    fn jvp(&self, x: &[f64], p: &[f64], tx: &[f64], tp: &[f64], y: &mut [f64], ty: &mut [f64]) {
        validate_jvp(self, "FiniteDiff", x, p, tx, tp, y, ty);
        self.op.forward(x, p, y);
        self.central(x, p, tx, tp, ty);
    }
}

impl<O: Forward> Vjp for FiniteDiff<O> {
    fn vjp(&self, x: &[f64], p: &[f64], dy: &mut [f64], dx: &mut [f64], dp: &mut [f64]) {
        validate_vjp(self, "FiniteDiff", x, p, dy, dx, dp);
        let (n, m) = (self.n_in(), self.n_params());
        let mut tx = vec![0.0; n];
        let mut tp = vec![0.0; m];
        let mut col = vec![0.0; self.n_out()];
        let dot = |a: &[f64], b: &[f64]| a.iter().zip(b).map(|(a, b)| a * b).sum::<f64>();
        for j in 0..n + m {
            if j < n {
                tx[j] = 1.0
            } else {
                tp[j - n] = 1.0
            }
            self.central(x, p, &tx, &tp, &mut col);
            if j < n {
                tx[j] = 0.0;
                dx[j] += dot(&col, dy);
            } else {
                tp[j - n] = 0.0;
                dp[j - n] += dot(&col, dy);
            }
        }
        dy.fill(0.0);
    }
}
