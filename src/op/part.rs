//! Operators on part of a state: [`Part`] applies an operator to a range of
//! a longer state and passes the rest through; [`AddParams`] adds its
//! (scaled) parameters to a range, the simplest control.

use std::ops::Range;

use super::{Forward, Jvp, OpError, Operator, Vjp, validate_forward, validate_jvp, validate_vjp};

/// `op` applied to `x[range]` of a state of length `n`; the rest of the
/// state passes through unchanged. The parameters are `op`'s.
#[derive(Clone, Debug)]
pub struct Part<O> {
    /// The operator on the range (`n_in == n_out == range.len()`).
    pub op: O,
    /// Length of the whole state.
    pub n: usize,
    /// The part `op` acts on.
    pub range: Range<usize>,
}

impl<O: Operator> Part<O> {
    /// `op` on `range` of a state of length `n`.
    ///
    /// # Panics
    /// If `op` does not map `range.len()` values to as many, or `range`
    /// does not lie in `0..n` (a programming error, not a user input).
    pub fn new(op: O, n: usize, range: Range<usize>) -> Self {
        assert!(op.n_in() == range.len() && op.n_out() == range.len(), "Part: the operator must map the range to itself");
        assert!(range.end <= n, "Part: the range ends beyond the state");
        Self { op, n, range }
    }
}

impl<O: Operator> Operator for Part<O> {
    fn n_in(&self) -> usize {
        self.n
    }
    fn n_out(&self) -> usize {
        self.n
    }
    fn n_params(&self) -> usize {
        self.op.n_params()
    }
}

impl<O: Forward> Forward for Part<O> {
    fn forward(&self, x: &[f64], p: &[f64], y: &mut [f64]) {
        validate_forward(self, "Part", x, p, y);
        let r = self.range.clone();
        y[..r.start].copy_from_slice(&x[..r.start]);
        y[r.end..].copy_from_slice(&x[r.end..]);
        self.op.forward(&x[r.clone()], p, &mut y[r]);
    }

    fn solve_tolerance(&self) -> f64 {
        self.op.solve_tolerance()
    }

    fn smooth_radius(&self, x: &[f64], p: &[f64], dx: &[f64], dp: &[f64]) -> f64 {
        let r = self.range.clone();
        self.op.smooth_radius(&x[r.clone()], p, &dx[r], dp)
    }

    fn take_error(&self) -> Option<OpError> {
        self.op.take_error()
    }
}

impl<O: Vjp> Vjp for Part<O> {
    fn vjp(&self, x: &[f64], p: &[f64], dy: &mut [f64], dx: &mut [f64], dp: &mut [f64]) {
        validate_vjp(self, "Part", x, p, dy, dx, dp);
        let r = self.range.clone();
        for k in (0..r.start).chain(r.end..self.n) {
            dx[k] += dy[k];
            dy[k] = 0.0;
        }
        self.op.vjp(&x[r.clone()], p, &mut dy[r.clone()], &mut dx[r], dp);
    }
}

impl<O: Jvp> Jvp for Part<O> {
    fn jvp(&self, x: &[f64], p: &[f64], tx: &[f64], tp: &[f64], y: &mut [f64], ty: &mut [f64]) {
        validate_jvp(self, "Part", x, p, tx, tp, y, ty);
        let r = self.range.clone();
        y.copy_from_slice(x);
        ty.copy_from_slice(tx);
        self.op.jvp(&x[r.clone()], p, &tx[r.clone()], tp, &mut y[r.clone()], &mut ty[r]);
    }
}

/// `y = x`, then `y[range] += scale·p`: a force or source given per value
/// (`p` has `range.len()` values). Linear, derivatives by hand.
#[derive(Clone, Debug)]
pub struct AddParams {
    /// Length of the state.
    pub n: usize,
    /// Where the parameters are added.
    pub range: Range<usize>,
    /// Their factor (e.g. the time step, for an acceleration).
    pub scale: f64,
}

impl Operator for AddParams {
    fn n_in(&self) -> usize {
        self.n
    }
    fn n_out(&self) -> usize {
        self.n
    }
    fn n_params(&self) -> usize {
        self.range.len()
    }
}

impl Forward for AddParams {
    fn forward(&self, x: &[f64], p: &[f64], y: &mut [f64]) {
        validate_forward(self, "AddParams", x, p, y);
        super::count::record("AddParams", super::count::Method::Forward);
        self.apply(x, p, y);
    }
}

impl AddParams {
    /// `y = x`, `y[range] += scale·p`.
    fn apply(&self, x: &[f64], p: &[f64], y: &mut [f64]) {
        y.copy_from_slice(x);
        for (y, p) in y[self.range.clone()].iter_mut().zip(p) {
            *y += self.scale * p;
        }
    }
}

impl Vjp for AddParams {
    fn vjp(&self, x: &[f64], p: &[f64], dy: &mut [f64], dx: &mut [f64], dp: &mut [f64]) {
        validate_vjp(self, "AddParams", x, p, dy, dx, dp);
        super::count::record("AddParams", super::count::Method::Vjp);
        for (d, g) in dp.iter_mut().zip(&dy[self.range.clone()]) {
            *d += self.scale * g;
        }
        for (d, g) in dx.iter_mut().zip(dy.iter_mut()) {
            *d += *g;
            *g = 0.0;
        }
    }
}

impl Jvp for AddParams {
    fn jvp(&self, x: &[f64], p: &[f64], tx: &[f64], tp: &[f64], y: &mut [f64], ty: &mut [f64]) {
        validate_jvp(self, "AddParams", x, p, tx, tp, y, ty);
        super::count::record("AddParams", super::count::Method::Jvp);
        self.apply(x, p, y);
        ty.copy_from_slice(tx);
        for (t, v) in ty[self.range.clone()].iter_mut().zip(tp) {
            *t += self.scale * v;
        }
    }
}
