//! Diffusion of a cell-centred scalar on an `n × n` closed box (no flux
//! through the walls), unit cells: explicit (forward Euler) and implicit
//! (backward Euler, solved by conjugate gradients).
//!
//! With `A` the closed-box matrix of [`crate::smoke::apply_pressure_matrix`]
//! (`A ≈ −Δ` on unit cells) and `κ = ν·dt`:
//! - explicit: `s' = s − κ·A·s`, stable for `κ ≤ 1/4` (the largest eigenvalue
//!   of `A` is below 8);
//! - implicit: `(I + κ·A)·s' = s`, stable for every `κ ≥ 0`. The matrix is
//!   symmetric positive definite, so its adjoint is the same solve.

use crate::smoke::{NoConvergence, apply_pressure_matrix};

/// Largest stable `κ = ν·dt` of the explicit scheme on unit cells.
pub const EXPLICIT_LIMIT: f64 = 0.25;

/// `out = s − κ·A·s` (overwrites `out`). It writes `A·s` into `out` and
/// rescales in place; Enzyme differentiates this correctly with the output
/// declared `Duplicated`, as diffsim's macros do (tests/user_op.rs keeps
/// that shape under the checks).
pub fn explicit(n: usize, kappa: f64, s: &[f64], out: &mut [f64]) {
    apply_pressure_matrix(n, s, out);
    for (o, &v) in out.iter_mut().zip(s) {
        *o = v - kappa * *o;
    }
}

/// Conjugate gradients for `(I + κ·A)·x = b` with reusable buffers.
#[derive(Clone, Debug)]
pub struct ImplicitSolver {
    n: usize,
    /// Relative tolerance on the true residual.
    pub tolerance: f64,
    /// More iterations than this is an error.
    pub max_iterations: usize,
    r: Vec<f64>,
    d: Vec<f64>,
    q: Vec<f64>,
}

impl ImplicitSolver {
    /// A solver for the `n × n` box.
    pub fn new(n: usize, tolerance: f64, max_iterations: usize) -> Self {
        let z = vec![0.0; n * n];
        Self { n, tolerance, max_iterations, r: z.clone(), d: z.clone(), q: z }
    }

    /// `out = (I + κ·A)·x`: the explicit step with `−κ`.
    fn apply(n: usize, kappa: f64, x: &[f64], out: &mut [f64]) {
        explicit(n, -kappa, x, out)
    }

    /// Solves `(I + κ·A)·x = b`, starting from `x = b` (a good guess for
    /// small `κ`), until `‖b − M·x‖ ≤ tol·‖b‖` on the true residual;
    /// overwrites `x`. Returns the iterations.
    pub fn solve(&mut self, kappa: f64, b: &[f64], x: &mut [f64]) -> Result<usize, NoConvergence> {
        let n = self.n;
        let dot = |a: &[f64], b: &[f64]| a.iter().zip(b).map(|(a, b)| a * b).sum::<f64>();
        let bnorm = dot(b, b).sqrt();
        x.copy_from_slice(b);
        if bnorm == 0.0 {
            return Ok(0);
        }
        let target = self.tolerance * bnorm;
        let residual = |x: &[f64], r: &mut [f64], q: &mut [f64]| {
            Self::apply(n, kappa, x, q);
            for ((r, &bv), &qv) in r.iter_mut().zip(b).zip(q.iter()) {
                *r = bv - qv;
            }
        };
        residual(x, &mut self.r, &mut self.q);
        self.d.copy_from_slice(&self.r);
        let mut rr = dot(&self.r, &self.r);
        let mut it = 0;
        loop {
            if rr.sqrt() <= target {
                residual(x, &mut self.r, &mut self.q);
                rr = dot(&self.r, &self.r);
                if rr.sqrt() <= target {
                    return Ok(it);
                }
                self.d.copy_from_slice(&self.r);
            }
            if it >= self.max_iterations || !rr.is_finite() {
                return Err(NoConvergence { iterations: it, relative_residual: rr.sqrt() / bnorm, tolerance: self.tolerance });
            }
            Self::apply(n, kappa, &self.d, &mut self.q);
            let alpha = rr / dot(&self.d, &self.q);
            for ((xv, &dv), (r, &qv)) in x.iter_mut().zip(&self.d).zip(self.r.iter_mut().zip(&self.q)) {
                *xv += alpha * dv;
                *r -= alpha * qv;
            }
            let rr_new = dot(&self.r, &self.r);
            let beta = rr_new / rr;
            rr = rr_new;
            for (dv, &rv) in self.d.iter_mut().zip(&self.r) {
                *dv = rv + beta * *dv;
            }
            it += 1;
        }
    }
}
