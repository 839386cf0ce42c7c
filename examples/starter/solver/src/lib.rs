//! The physics: the Fisher–KPP equation `u_t = D·u_xx + r·u·(1 − u)` on a
//! periodic line, as plain functions on slices, and the operators that
//! diffsim differentiates.
//!
//! This crate is built with `-Zautodiff=Enable` (../Cargo.toml): keep it to
//! the differentiated functions and their operator types. Everything else
//! (checks, rollouts, training, printing) lives in the crate at ../src,
//! built without the flag, where Enzyme's type analysis never sees it.
#![feature(autodiff)]

use diffsim::op::{Forward, Jvp, Operator, Vjp};

// ANCHOR: step
/// The grid and time step. The parameters `p = [ν, r]` are inputs of the
/// step: `ν = D·dt/dx²` (the diffusion number, stable for `ν ≤ ½`) and the
/// growth rate `r`.
#[derive(Clone, Copy, Debug)]
pub struct Fkpp {
    /// Cells.
    pub n: usize,
    /// Time step.
    pub dt: f64,
}

impl Operator for Fkpp {
    fn n_in(&self) -> usize {
        self.n
    }
    fn n_out(&self) -> usize {
        self.n
    }
    fn n_params(&self) -> usize {
        2
    }
}

/// One explicit Euler step: a plain function on slices that overwrites `y`.
pub fn fkpp_step(op: &Fkpp, u: &[f64], p: &[f64], y: &mut [f64]) {
    let n = op.n;
    let (nu, r) = (p[0], p[1]);
    for i in 0..n {
        let (l, c, rt) = (u[(i + n - 1) % n], u[i], u[(i + 1) % n]);
        y[i] = c + nu * (l - 2.0 * c + rt) + op.dt * r * c * (1.0 - c);
    }
}

diffsim::differentiable!(Fkpp => fkpp_step); // Forward, Vjp and Jvp by Enzyme
// ANCHOR_END: step

// ANCHOR: stencil
/// The variants below wrap the Euler step's type and have its sizes.
macro_rules! sizes_of_the_euler_step {
    ($($variant:ty),*) => {$(
        impl Operator for $variant {
            fn n_in(&self) -> usize {
                self.0.n
            }
            fn n_out(&self) -> usize {
                self.0.n
            }
            fn n_params(&self) -> usize {
                2
            }
        }
    )*};
}

sizes_of_the_euler_step!(FkppStencil, FkppHeun, FkppHand);

/// The same step written as a pointwise map over shifted views (`l`, `c`,
/// `r` are the left, centre and right neighbours of every cell):
/// `stencil3!` differentiates the map and gathers the adjoint, which is
/// faster than differentiating the whole loop on large grids.
#[derive(Clone, Copy, Debug)]
pub struct FkppStencil(pub Fkpp);

fn fkpp_map(op: &FkppStencil, l: &[f64], c: &[f64], r: &[f64], p: &[f64], out: &mut [f64]) {
    for i in 0..out.len() {
        out[i] = c[i] + p[0] * (l[i] - 2.0 * c[i] + r[i]) + op.0.dt * p[1] * c[i] * (1.0 - c[i]);
    }
}

diffsim::stencil3!(FkppStencil => fkpp_map);
// ANCHOR_END: stencil

// ANCHOR: scratch
/// Heun's method (two Euler stages averaged): the predictor is an
/// intermediate field, kept in scratch memory that diffsim lends
/// (`scratch = len`), never allocated inside the differentiated function.
#[derive(Clone, Copy, Debug)]
pub struct FkppHeun(pub Fkpp);

fn heun_step(op: &FkppHeun, u: &[f64], p: &[f64], y: &mut [f64], predictor: &mut [f64]) {
    fkpp_step(&op.0, u, p, predictor);
    fkpp_step(&op.0, predictor, p, y);
    for i in 0..op.0.n {
        y[i] = 0.5 * (u[i] + y[i]);
    }
}

fn heun_scratch(op: &FkppHeun) -> usize {
    op.0.n
}

diffsim::differentiable!(FkppHeun => heun_step, scratch = heun_scratch);
// ANCHOR_END: scratch

// ANCHOR: hand
/// The Euler step with a hand-written adjoint: the reference Enzyme's is
/// compared with (for correctness and speed). It follows diffsim's
/// contract: the VJP *adds* into `du` and `dp` and consumes (zeroes) `dy`.
#[derive(Clone, Copy, Debug)]
pub struct FkppHand(pub Fkpp);

impl Forward for FkppHand {
    fn forward(&self, u: &[f64], p: &[f64], y: &mut [f64]) {
        fkpp_step(&self.0, u, p, y);
    }
}

impl Vjp for FkppHand {
    fn vjp(&self, u: &[f64], p: &[f64], dy: &mut [f64], du: &mut [f64], dp: &mut [f64]) {
        let (n, dt) = (self.0.n, self.0.dt);
        let (nu, r) = (p[0], p[1]);
        for i in 0..n {
            let (im, ip) = ((i + n - 1) % n, (i + 1) % n);
            let c = u[i];
            // ∂y_i/∂u_i = 1 − 2ν + dt·r·(1 − 2u_i), ∂y_{i±1}/∂u_i = ν.
            du[i] += dy[i] * (1.0 - 2.0 * nu + dt * r * (1.0 - 2.0 * c)) + nu * (dy[im] + dy[ip]);
            dp[0] += dy[i] * (u[im] - 2.0 * c + u[ip]);
            dp[1] += dy[i] * dt * c * (1.0 - c);
        }
        dy.fill(0.0);
    }
}

impl Jvp for FkppHand {
    fn jvp(&self, u: &[f64], p: &[f64], tu: &[f64], tp: &[f64], y: &mut [f64], ty: &mut [f64]) {
        let (n, dt) = (self.0.n, self.0.dt);
        let (nu, r) = (p[0], p[1]);
        fkpp_step(&self.0, u, p, y);
        for i in 0..n {
            let (im, ip) = ((i + n - 1) % n, (i + 1) % n);
            let c = u[i];
            ty[i] = tu[i] * (1.0 - 2.0 * nu + dt * r * (1.0 - 2.0 * c))
                + nu * (tu[im] + tu[ip])
                + tp[0] * (u[im] - 2.0 * c + u[ip])
                + tp[1] * dt * c * (1.0 - c);
        }
    }
}
// ANCHOR_END: hand
