//! Operators in sequence: `y = f_k(… f_2(f_1(x, p_1), p_2) …, p_k)`, with
//! the parameters concatenated, `p = [p_1, …, p_k]`. A scene's step is the
//! chain of its declared effects; nothing else runs.

use std::cell::RefCell;
use std::fmt;

use super::{Forward, Jvp, OpError, OpName, Operator, Vjp, validate_forward, validate_jvp, validate_vjp};

/// An operator with all three capabilities, as a trait object.
pub trait Effect: Vjp + Jvp + fmt::Debug {}

impl<T: Vjp + Jvp + fmt::Debug> Effect for T {}

/// A chain of operators of matching sizes (each one's output is the next
/// one's input). The VJP recomputes the intermediate states from `x` (one
/// forward pass, `k − 1` states kept) and runs the VJPs backwards.
pub struct Chain {
    ops: Vec<Box<dyn Effect>>,
    /// Where each operator's parameters start in `p`.
    offsets: Vec<usize>,
    /// Intermediate states (forward, and the tangents of the JVP).
    scratch: RefCell<Vec<Vec<f64>>>,
    tangents: RefCell<Vec<Vec<f64>>>,
    /// The running adjoint of the VJP.
    adjoint: RefCell<(Vec<f64>, Vec<f64>)>,
}

impl fmt::Debug for Chain {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        f.debug_struct("Chain").field("ops", &self.ops).finish()
    }
}

impl Chain {
    /// The chain of `ops`, applied first to last.
    ///
    /// # Panics
    /// If `ops` is empty or one operator's output size is not the next one's
    /// input size.
    pub fn new(ops: Vec<Box<dyn Effect>>) -> Self {
        assert!(!ops.is_empty(), "a chain needs at least one operator");
        for w in ops.windows(2) {
            assert_eq!(w[0].n_out(), w[1].n_in(), "chain: {:?} outputs {} values, {:?} takes {}", w[0], w[0].n_out(), w[1], w[1].n_in());
        }
        let mut offsets = Vec::with_capacity(ops.len() + 1);
        let mut at = 0;
        for op in &ops {
            offsets.push(at);
            at += op.n_params();
        }
        offsets.push(at);
        let states: Vec<Vec<f64>> = ops[..ops.len() - 1].iter().map(|op| vec![0.0; op.n_out()]).collect();
        let widest = ops.iter().map(|op| op.n_in().max(op.n_out())).max().unwrap_or(0);
        Self {
            offsets,
            tangents: RefCell::new(states.clone()),
            scratch: RefCell::new(states),
            adjoint: RefCell::new((vec![0.0; widest], vec![0.0; widest])),
            ops,
        }
    }

    /// The operators, first to last.
    pub fn ops(&self) -> &[Box<dyn Effect>] {
        &self.ops
    }

    /// Where operator `k`'s parameters lie in `p`.
    pub fn param_range(&self, k: usize) -> std::ops::Range<usize> {
        self.offsets[k]..self.offsets[k + 1]
    }

    /// The chain's forward pass with a callback after each operator
    /// (`after(k, y_k)`), for profiling and inspection.
    pub fn forward_with(&self, x: &[f64], p: &[f64], y: &mut [f64], mut after: impl FnMut(usize)) {
        validate_forward(self, "Chain", x, p, y);
        let mut states = self.scratch.borrow_mut();
        let last = self.ops.len() - 1;
        for (k, op) in self.ops.iter().enumerate() {
            let pk = &p[self.param_range(k)];
            match (k == 0, k == last) {
                (true, true) => op.forward(x, pk, y),
                (true, false) => op.forward(x, pk, &mut states[0]),
                (false, true) => op.forward(&states[k - 1], pk, y),
                (false, false) => {
                    let (done, rest) = states.split_at_mut(k);
                    op.forward(&done[k - 1], pk, &mut rest[0]);
                }
            }
            after(k);
        }
    }
}

impl Operator for Chain {
    fn n_in(&self) -> usize {
        self.ops[0].n_in()
    }
    fn n_out(&self) -> usize {
        self.ops[self.ops.len() - 1].n_out()
    }
    fn n_params(&self) -> usize {
        self.offsets[self.ops.len()]
    }
}

impl Forward for Chain {
    fn forward(&self, x: &[f64], p: &[f64], y: &mut [f64]) {
        self.forward_with(x, p, y, |_| {});
    }

    /// The largest of the operators' solve tolerances.
    fn solve_tolerance(&self) -> f64 {
        self.ops.iter().map(|op| op.solve_tolerance()).fold(0.0, f64::max)
    }

    /// The smallest radius of the operators, each at its own input along
    /// the tangent carried to it by the JVPs.
    fn smooth_radius(&self, x: &[f64], p: &[f64], dx: &[f64], dp: &[f64]) -> f64 {
        let mut r = f64::INFINITY;
        let (mut xs, mut ts) = (x.to_vec(), dx.to_vec());
        for (k, op) in self.ops.iter().enumerate() {
            let range = self.param_range(k);
            r = r.min(op.smooth_radius(&xs, &p[range.clone()], &ts, &dp[range.clone()]));
            let (mut y, mut ty) = (vec![0.0; op.n_out()], vec![0.0; op.n_out()]);
            op.jvp(&xs, &p[range.clone()], &ts, &dp[range], &mut y, &mut ty);
            (xs, ts) = (y, ty);
        }
        r
    }

    /// The first error any operator recorded (all are taken).
    fn take_error(&self) -> Option<OpError> {
        self.ops.iter().map(|op| op.take_error()).fold(None, |first, e| first.or(e))
    }

    /// The first operator whose output is not finite (e.g. the effect of a
    /// scene that blew up).
    fn locate_non_finite(&self, x: &[f64], p: &[f64]) -> OpName {
        let mut xs = x.to_vec();
        for (k, op) in self.ops.iter().enumerate() {
            let mut y = vec![0.0; op.n_out()];
            op.forward(&xs, &p[self.param_range(k)], &mut y);
            if !super::all_finite(&y) {
                return op.locate_non_finite(&xs, &p[self.param_range(k)]);
            }
            xs = y;
        }
        self.name()
    }
}

impl Vjp for Chain {
    fn vjp(&self, x: &[f64], p: &[f64], dy: &mut [f64], dx: &mut [f64], dp: &mut [f64]) {
        validate_vjp(self, "Chain", x, p, dy, dx, dp);
        let k_ops = self.ops.len();
        if k_ops == 1 {
            return self.ops[0].vjp(x, p, dy, dx, dp);
        }
        // The inputs of every operator after the first.
        let mut y_last = vec![0.0; self.n_out()];
        self.forward(x, p, &mut y_last);
        let states = self.scratch.borrow();
        let mut adj = self.adjoint.borrow_mut();
        let (a, b) = &mut *adj;
        // The last operator's VJP from dy into a (its input adjoint).
        let last = k_ops - 1;
        let n = self.ops[last].n_in();
        self.ops[last].vjp_overwrite(&states[last - 1], &p[self.param_range(last)], dy, &mut a[..n], &mut dp[self.param_range(last)]);
        dy.fill(0.0);
        for k in (1..last).rev() {
            let (n_in, n_out) = (self.ops[k].n_in(), self.ops[k].n_out());
            self.ops[k].vjp_overwrite(&states[k - 1], &p[self.param_range(k)], &mut a[..n_out], &mut b[..n_in], &mut dp[self.param_range(k)]);
            std::mem::swap(a, b);
        }
        let n_out = self.ops[0].n_out();
        self.ops[0].vjp(x, &p[self.param_range(0)], &mut a[..n_out], dx, &mut dp[self.param_range(0)]);
    }
}

impl Jvp for Chain {
    fn jvp(&self, x: &[f64], p: &[f64], tx: &[f64], tp: &[f64], y: &mut [f64], ty: &mut [f64]) {
        validate_jvp(self, "Chain", x, p, tx, tp, y, ty);
        let mut states = self.scratch.borrow_mut();
        let mut tangents = self.tangents.borrow_mut();
        let last = self.ops.len() - 1;
        for (k, op) in self.ops.iter().enumerate() {
            let r = self.param_range(k);
            let (pk, tpk) = (&p[r.clone()], &tp[r]);
            match (k == 0, k == last) {
                (true, true) => op.jvp(x, pk, tx, tpk, y, ty),
                (true, false) => op.jvp(x, pk, tx, tpk, &mut states[0], &mut tangents[0]),
                (false, true) => op.jvp(&states[k - 1], pk, &tangents[k - 1], tpk, y, ty),
                (false, false) => {
                    let (sd, sr) = states.split_at_mut(k);
                    let (td, tr) = tangents.split_at_mut(k);
                    op.jvp(&sd[k - 1], pk, &td[k - 1], tpk, &mut sr[0], &mut tr[0]);
                }
            }
        }
    }
}
