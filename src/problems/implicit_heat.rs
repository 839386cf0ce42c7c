//! Backward-Euler heat conduction with a conductivity per cell: the
//! implicit step of issue 51, written as the forward physics only.
//!
//! On an `n × n` grid of unit cells with insulated sides, one step solves
//! `(I + dt·A(θ))·y = x` where `A(θ)` is the finite-volume conduction
//! operator with cell conductivities `exp(θ)` (a face takes the mean of its
//! two cells'): symmetric positive definite, so CG solves it and the
//! adjoint solve is the same solve ([`crate::implicit`]). The parameters `θ`
//! (one per cell) are what an inverse problem recovers from the state.

use crate::implicit::{LinearSolve, LinearSystem, SolveParams};

/// The system of one step: grid size and time step.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct ImplicitHeat {
    /// Cells per side.
    pub n: usize,
    /// Time step.
    pub dt: f64,
}

impl ImplicitHeat {
    /// The step as an operator `(x, θ) ↦ y`, solved with `params`.
    pub fn step(n: usize, dt: f64, params: SolveParams) -> LinearSolve<ImplicitHeat> {
        LinearSolve::new(ImplicitHeat { n, dt }, params)
    }
}

impl LinearSystem for ImplicitHeat {
    fn n(&self) -> usize {
        self.n * self.n
    }
    fn n_in(&self) -> usize {
        self.n * self.n
    }
    fn n_params(&self) -> usize {
        self.n * self.n
    }
}

/// `out = (I + dt·A(θ))·v`.
pub fn heat_matvec(s: &ImplicitHeat, v: &[f64], theta: &[f64], out: &mut [f64]) {
    let n = s.n;
    for j in 0..n {
        for i in 0..n {
            let k = j * n + i;
            let mut acc = v[k];
            let mut face = |m: usize| acc += s.dt * 0.5 * (theta[k].exp() + theta[m].exp()) * (v[k] - v[m]);
            if i + 1 < n {
                face(k + 1);
            }
            if i > 0 {
                face(k - 1);
            }
            if j + 1 < n {
                face(k + n);
            }
            if j > 0 {
                face(k - n);
            }
            out[k] = acc;
        }
    }
}

/// `b = x` (the previous state).
pub fn heat_rhs(_: &ImplicitHeat, x: &[f64], _theta: &[f64], b: &mut [f64]) {
    b.copy_from_slice(x);
}

crate::linear_system!(ImplicitHeat => heat_matvec, heat_rhs);

/// The same step with its CG iterations written inside the function, so
/// that Enzyme differentiates the iterations themselves (the route a user
/// takes without [`crate::implicit`]): for comparison only. Its derivative
/// is the truncated iteration's, which lags the solution's; it costs a
/// taped pass through every iteration (`diffsim bench implicit-heat`,
/// docs/implicit.md).
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct HeatThroughCg {
    /// Cells per side.
    pub n: usize,
    /// Time step.
    pub dt: f64,
    /// Relative residual at which the iterations stop.
    pub tolerance: f64,
    /// Iterations at most.
    pub max_iterations: usize,
}

impl crate::op::Operator for HeatThroughCg {
    fn n_in(&self) -> usize {
        self.n * self.n
    }
    fn n_out(&self) -> usize {
        self.n * self.n
    }
    fn n_params(&self) -> usize {
        self.n * self.n
    }
}

fn dot(a: &[f64], b: &[f64]) -> f64 {
    let mut s = 0.0;
    for (x, y) in a.iter().zip(b) {
        s += x * y;
    }
    s
}

/// One step by plain CG from zero, `r`, `d`, `q` in lent scratch.
fn heat_through_cg(op: &HeatThroughCg, x: &[f64], p: &[f64], y: &mut [f64], s: &mut [f64]) {
    let m = op.n * op.n;
    let sys = ImplicitHeat { n: op.n, dt: op.dt };
    let (r, rest) = s.split_at_mut(m);
    let (d, q) = rest.split_at_mut(m);
    for i in 0..m {
        y[i] = 0.0;
        r[i] = x[i];
        d[i] = x[i];
    }
    let target = op.tolerance * dot(x, x).sqrt();
    let mut rr = dot(r, r);
    let mut it = 0;
    while rr.sqrt() > target && it < op.max_iterations {
        heat_matvec(&sys, d, p, q);
        let alpha = rr / dot(d, q);
        for i in 0..m {
            y[i] += alpha * d[i];
            r[i] -= alpha * q[i];
        }
        let rr_new = dot(r, r);
        let beta = rr_new / rr;
        rr = rr_new;
        for i in 0..m {
            d[i] = r[i] + beta * d[i];
        }
        it += 1;
    }
}

fn heat_through_cg_scratch(op: &HeatThroughCg) -> usize {
    3 * op.n * op.n
}

crate::differentiable!(HeatThroughCg => heat_through_cg, scratch = heat_through_cg_scratch);
