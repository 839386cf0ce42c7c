//! Physics inversion as a capability: an operator that can say how its
//! input must change to move its output by a given amount.
//!
//! Physical-gradient (PG) and scale-invariant physics (SIP) updates (Holl,
//! Koltun & Thuerey, NeurIPS 2022) use it in place of the gradient: the
//! inverse step gives a network its target in input space
//! ([`crate::train::pg`]).

use super::{Forward, Jvp, Operator, Vjp};

/// A local inverse of `y = f(x, p)` in `x` (`p` held fixed).
pub trait LocalInverse: Forward {
    /// Writes a step `dx` (overwritten) such that
    /// `f(x + dx, p) ≈ f(x, p) + dy`, as well as the physics allows: an
    /// exact or regularised inverse for invertible physics, a Gauss-Newton
    /// step ([`GaussNewton`]) for any operator with a Jacobian.
    ///
    /// # Panics
    /// If a slice length does not match the operator's sizes.
    fn local_inverse(&self, x: &[f64], p: &[f64], dy: &[f64], dx: &mut [f64]);
}

/// The generic local inverse of any operator with a VJP and a JVP: one
/// damped Gauss-Newton step
///
/// ```text
/// dx = (J_xᵀ·J_x + λ·I)⁻¹ · J_xᵀ·dy
/// ```
///
/// solved matrix-free by conjugate gradients (one JVP and one VJP per
/// iteration; at most `iterations`, stopping at a relative residual of
/// `tolerance`). The damping `λ > 0` keeps the step finite where `J_x` is
/// singular; it is absolute (in the units of `J_xᵀ·J_x`).
#[derive(Clone, Copy, Debug)]
pub struct GaussNewton<'a, O> {
    /// The operator to invert.
    pub op: &'a O,
    /// Damping `λ`.
    pub damping: f64,
    /// Largest number of CG iterations.
    pub iterations: usize,
    /// Relative residual at which CG stops.
    pub tolerance: f64,
}

sizes_of_inner!(['a, O: Operator] GaussNewton<'a, O> => op);

impl<O: Forward> Forward for GaussNewton<'_, O> {
    fn forward(&self, x: &[f64], p: &[f64], y: &mut [f64]) {
        self.op.forward(x, p, y);
    }
}

impl<O: Vjp + Jvp> GaussNewton<'_, O> {
    /// `(J_xᵀ·J_x + λ·I)·v`.
    fn normal(&self, x: &[f64], p: &[f64], v: &[f64], out: &mut [f64]) {
        let (n, k) = (self.op.n_in(), self.op.n_out());
        let mut y = vec![0.0; k];
        let mut jv = vec![0.0; k];
        self.op.jvp(x, p, v, &vec![0.0; self.op.n_params()], &mut y, &mut jv);
        let mut dp = vec![0.0; self.op.n_params()];
        out.fill(0.0);
        self.op.vjp(x, p, &mut jv, out, &mut dp);
        for i in 0..n {
            out[i] += self.damping * v[i];
        }
    }
}

impl<O: Vjp + Jvp> LocalInverse for GaussNewton<'_, O> {
    fn local_inverse(&self, x: &[f64], p: &[f64], dy: &[f64], dx: &mut [f64]) {
        let n = self.op.n_in();
        assert!(x.len() == n && dx.len() == n && dy.len() == self.op.n_out(), "GaussNewton: slice lengths do not match the operator");
        // b = J_xᵀ·dy
        let mut b = vec![0.0; n];
        let mut seed = dy.to_vec();
        let mut dp = vec![0.0; self.op.n_params()];
        self.op.vjp(x, p, &mut seed, &mut b, &mut dp);
        dx.fill(0.0);
        let dot = |a: &[f64], b: &[f64]| a.iter().zip(b).map(|(u, v)| u * v).sum::<f64>();
        let b_norm = dot(&b, &b).sqrt();
        if b_norm == 0.0 {
            return;
        }
        let mut r = b.clone();
        let mut d = b;
        let mut ad = vec![0.0; n];
        let mut rr = dot(&r, &r);
        for _ in 0..self.iterations {
            self.normal(x, p, &d, &mut ad);
            let alpha = rr / dot(&d, &ad);
            for i in 0..n {
                dx[i] += alpha * d[i];
                r[i] -= alpha * ad[i];
            }
            let rr_new = dot(&r, &r);
            if rr_new.sqrt() <= self.tolerance * b_norm {
                break;
            }
            let beta = rr_new / rr;
            for i in 0..n {
                d[i] = r[i] + beta * d[i];
            }
            rr = rr_new;
        }
    }
}

/// An approximate local inverse sharpened by defect correction:
///
/// ```text
/// dx₀ = P⁻¹(dy; x),   dx_{k+1} = dx_k + P⁻¹(dy − (f(x + dx_k) − f(x)); x)
/// ```
///
/// for `sweeps` sweeps (one forward and one inverse each). Where the
/// approximate inverse misses by less than the change asked for
/// (`‖dy − (f(x + P⁻¹(dy)) − f(x))‖ < ‖dy‖`), each sweep shrinks the miss
/// by about that ratio, nonlinearity included; directions the inverse
/// cannot see (which it maps to nearly zero) keep their miss.
/// [`crate::check::local_inverse`] measures both.
#[derive(Clone, Copy, Debug)]
pub struct Refined<'a, O> {
    /// The operator and its approximate inverse.
    pub op: &'a O,
    /// Correction sweeps after the first inverse step (0: the inverse as it is).
    pub sweeps: usize,
}

sizes_of_inner!(['a, O: Operator] Refined<'a, O> => op);

impl<O: Forward> Forward for Refined<'_, O> {
    fn forward(&self, x: &[f64], p: &[f64], y: &mut [f64]) {
        self.op.forward(x, p, y);
    }
    fn take_error(&self) -> Option<super::OpError> {
        self.op.take_error()
    }
}

impl<O: Vjp> Vjp for Refined<'_, O> {
    fn vjp(&self, x: &[f64], p: &[f64], dy: &mut [f64], dx: &mut [f64], dp: &mut [f64]) {
        self.op.vjp(x, p, dy, dx, dp);
    }
}

impl<O: LocalInverse> LocalInverse for Refined<'_, O> {
    fn local_inverse(&self, x: &[f64], p: &[f64], dy: &[f64], dx: &mut [f64]) {
        self.op.local_inverse(x, p, dy, dx);
        if self.sweeps == 0 {
            return;
        }
        let (n, k) = (self.op.n_in(), self.op.n_out());
        let mut y0 = vec![0.0; k];
        self.op.forward(x, p, &mut y0);
        let (mut moved, mut y1, mut step) = (vec![0.0; n], vec![0.0; k], vec![0.0; n]);
        for _ in 0..self.sweeps {
            for i in 0..n {
                moved[i] = x[i] + dx[i];
            }
            self.op.forward(&moved, p, &mut y1);
            // The defect: what the step has not yet delivered.
            for i in 0..k {
                y1[i] = dy[i] - (y1[i] - y0[i]);
            }
            self.op.local_inverse(x, p, &y1, &mut step);
            for i in 0..n {
                dx[i] += step[i];
            }
        }
    }
}
