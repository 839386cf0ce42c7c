//! The physics: heat conduction on a square of `n × n` unit cells with
//! insulated sides and a conductivity `exp θ` per cell, written as its
//! right-hand side `du/dt = f(u, θ)` only. diffsim's integrator takes the
//! implicit step (backward Euler: one linear solve a step) and its
//! derivatives by the implicit rule; nothing here is an adjoint.
//!
//! This crate is built with `-Zautodiff=Enable` (../Cargo.toml): keep it to
//! the differentiated functions and their types. Everything else (checks,
//! rollouts, training, printing) lives in the crate at ../src, built
//! without the flag.
#![feature(autodiff)]

use diffsim::implicit::{Integrator, IntegratorParams, NewtonParams, OdeSystem, Scheme, SolveMethod, SolveParams};

// ANCHOR: physics
/// The grid: `n × n` unit cells. The state `u` is the temperature per
/// cell, the parameters `θ` the log-conductivity per cell.
#[derive(Clone, Copy, Debug)]
pub struct Heat {
    /// Cells per side.
    pub n: usize,
}

impl OdeSystem for Heat {
    fn n(&self) -> usize {
        self.n * self.n
    }
    fn n_params(&self) -> usize {
        self.n * self.n
    }
}

/// `du/dt = −A(θ)·u`: the heat that flows through each face between two
/// cells, `κ·(u_b − u_a)` with `κ` the mean of the two cells' `exp θ`.
/// A plain function on slices that writes every element of `du`.
pub fn heat_rate(s: &Heat, u: &[f64], theta: &[f64], du: &mut [f64]) {
    let n = s.n;
    for d in du.iter_mut() {
        *d = 0.0;
    }
    let mut face = |a: usize, b: usize| {
        let flux = 0.5 * (theta[a].exp() + theta[b].exp()) * (u[b] - u[a]);
        du[a] += flux;
        du[b] -= flux;
    };
    for j in 0..n {
        for i in 0..n - 1 {
            face(j * n + i, j * n + i + 1);
        }
    }
    for j in 0..n - 1 {
        for i in 0..n {
            face(j * n + i, (j + 1) * n + i);
        }
    }
}

// Enzyme generates the derivatives the integrator needs: Jacobian products
// for Newton's method and its transposed solves, and `∂f/∂θ`.
diffsim::ode_system!(Heat => heat_rate);

/// One backward-Euler step of `dt`: `(I + dt·A(θ))·u_{n+1} = u_n`, solved
/// matrix-free by CG on Enzyme's Jacobian products (the matrix is
/// symmetric positive definite) to a relative residual of 10⁻¹².
pub fn step(n: usize, dt: f64) -> Integrator<Heat> {
    let linear = SolveParams { method: SolveMethod::Cg, tolerance: 1e-12, ..SolveParams::default() };
    let newton = NewtonParams { linear, ..NewtonParams::default() };
    Integrator::new(Heat { n }, IntegratorParams { scheme: Scheme::BackwardEuler, dt, newton })
}
// ANCHOR_END: physics
