//! Backward-Euler heat conduction with a conductivity per cell: the
//! implicit step of issue 51, written as the forward physics only.
//!
//! On an `n × n` grid of unit cells with insulated sides, one step solves
//! `(I + dt·A(θ))·y = x` where `A(θ)` is the finite-volume conduction
//! operator with cell conductivities `exp(θ)` (a face takes the mean of its
//! two cells'): symmetric positive definite, so CG solves it and the
//! adjoint solve is the same solve ([`crate::implicit`]). The parameters `θ`
//! (one per cell) are what an inverse problem recovers from the state.
//!
//! The matrix reads the faces' conductances `dt·(exp θ_k + exp θ_m)/2`,
//! formed once per solve by [`heat_conductances`] (the system's
//! coefficients), not in every product of the iterations.

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
    /// The cells' conductivities (`n²`), then the faces' conductances:
    /// `n + 1` a row between columns (the two outer ones 0, insulated), and
    /// `n + 1` rows of `n` between rows (the outer rows 0).
    fn n_coefficients(&self) -> usize {
        self.n * self.n + 2 * self.n * (self.n + 1)
    }
}

/// The cells' conductivities `exp θ`, then the faces' conductances times
/// the time step, `dt·(exp θ_k + exp θ_m)/2`: row `j` of the faces between
/// columns holds the face west of each cell and the last cell's east face
/// (`n + 1` values, the outer two 0); row `j` of the faces between rows the
/// face south of each cell of row `j` (`n + 1` rows, the outer two 0). The
/// zeros let the product treat every cell alike.
pub fn heat_conductances(s: &ImplicitHeat, theta: &[f64], c: &mut [f64]) {
    let n = s.n;
    let (kappa, faces) = c.split_at_mut(n * n);
    for (k, t) in kappa.iter_mut().zip(theta) {
        *k = t.exp();
    }
    let (cx, cy) = faces.split_at_mut(n * (n + 1));
    for j in 0..n {
        cx[j * (n + 1)] = 0.0;
        cx[j * (n + 1) + n] = 0.0;
        for i in 1..n {
            cx[j * (n + 1) + i] = s.dt * 0.5 * (kappa[j * n + i - 1] + kappa[j * n + i]);
        }
    }
    for i in 0..n {
        cy[i] = 0.0;
        cy[n * n + i] = 0.0;
    }
    for j in 1..n {
        for i in 0..n {
            cy[j * n + i] = s.dt * 0.5 * (kappa[(j - 1) * n + i] + kappa[j * n + i]);
        }
    }
}

/// `out = (I + dt·A(θ))·v` from the conductances `c` of
/// [`heat_conductances`]: one pass over each row, every cell the same
/// five-point formula over slices of equal length, so that the compiler
/// vectorises it. An insulated side's conductance is 0, so a missing
/// neighbour may be any finite value: the row itself for the first and
/// last rows, and inside, the cells on either side of the row in memory
/// (the last of the row below for the first cell, the first of the row
/// above for the last), which keeps the inner rows' loops whole.
/// `#[inline(always)]`: the solve's products then run in the widest
/// vectors the processor has ([`crate::linear_system!`]).
#[inline(always)]
pub fn heat_matvec(s: &ImplicitHeat, v: &[f64], c: &[f64], out: &mut [f64]) {
    let n = s.n;
    let (cx, cy) = c[n * n..].split_at(n * (n + 1));
    for j in 0..n {
        let (jb, ja) = (j.saturating_sub(1), (j + 1).min(n - 1));
        let row = &v[j * n..(j + 1) * n];
        let (below, above) = (&v[jb * n..(jb + 1) * n], &v[ja * n..(ja + 1) * n]);
        let (south, north) = (&cy[j * n..(j + 1) * n], &cy[(j + 1) * n..(j + 2) * n]);
        let (cw, ce) = (&cx[j * (n + 1)..j * (n + 1) + n], &cx[j * (n + 1) + 1..(j + 1) * (n + 1)]);
        let o = &mut out[j * n..(j + 1) * n];
        if j > 0 && j + 1 < n {
            let (west, east) = (&v[j * n - 1..(j + 1) * n - 1], &v[j * n + 1..(j + 1) * n + 1]);
            for i in 0..n {
                o[i] = cell(row[i], below[i], above[i], south[i], north[i], cw[i], west[i], ce[i], east[i]);
            }
        } else {
            for i in 0..n {
                let (west, east) = (row[i.saturating_sub(1)], row[(i + 1).min(n - 1)]);
                o[i] = cell(row[i], below[i], above[i], south[i], north[i], cw[i], west, ce[i], east);
            }
        }
    }
}

/// One cell of [`heat_matvec`]: `x` exchanging with the cells below, above,
/// west and east through their faces' conductances.
#[inline(always)]
#[allow(clippy::too_many_arguments)]
fn cell(x: f64, below: f64, above: f64, cs: f64, cn: f64, cw: f64, west: f64, ce: f64, east: f64) -> f64 {
    x + cs * (x - below) + cn * (x - above) + cw * (x - west) + ce * (x - east)
}

/// `b = x` (the previous state).
pub fn heat_rhs(_: &ImplicitHeat, x: &[f64], _theta: &[f64], b: &mut [f64]) {
    b.copy_from_slice(x);
}

crate::linear_system!(ImplicitHeat => heat_matvec, heat_rhs, coefficients = heat_conductances);

/// `z = D⁻¹·r` with `D` the diagonal of `I + dt·A(θ)` (`1` plus the
/// cell's four face conductances, from the coefficients `c` of
/// [`heat_conductances`]): the Jacobi preconditioner, symmetric positive
/// definite as CG needs. It pays where the conductivity varies over orders
/// of magnitude (a layered medium: a third fewer iterations); with `θ` of
/// order one, as in `diffsim bench implicit-heat`, it costs iterations
/// instead (260 against 183 over 20 steps, docs/implicit.md).
#[inline(always)]
pub fn heat_jacobi(s: &ImplicitHeat, c: &[f64], r: &[f64], z: &mut [f64]) {
    let n = s.n;
    let (cx, cy) = c[n * n..].split_at(n * (n + 1));
    for j in 0..n {
        let (south, north) = (&cy[j * n..(j + 1) * n], &cy[(j + 1) * n..(j + 2) * n]);
        let (west, east) = (&cx[j * (n + 1)..j * (n + 1) + n], &cx[j * (n + 1) + 1..(j + 1) * (n + 1)]);
        let (r, z) = (&r[j * n..(j + 1) * n], &mut z[j * n..(j + 1) * n]);
        for i in 0..n {
            z[i] = r[i] / (1.0 + south[i] + north[i] + west[i] + east[i]);
        }
    }
}

/// [`ImplicitHeat`] solved by CG preconditioned with [`heat_jacobi`]: the
/// same step, matrix and gradient, named with a preconditioner
/// ([`crate::linear_system!`]`(.., preconditioner = heat_jacobi)`).
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct PreconditionedHeat(pub ImplicitHeat);

impl PreconditionedHeat {
    /// The step as an operator `(x, θ) ↦ y`, solved with `params`.
    pub fn step(n: usize, dt: f64, params: SolveParams) -> LinearSolve<PreconditionedHeat> {
        LinearSolve::new(PreconditionedHeat(ImplicitHeat { n, dt }), params)
    }
}

impl LinearSystem for PreconditionedHeat {
    fn n(&self) -> usize {
        self.0.n()
    }
    fn n_in(&self) -> usize {
        self.0.n_in()
    }
    fn n_params(&self) -> usize {
        self.0.n_params()
    }
    fn n_coefficients(&self) -> usize {
        self.0.n_coefficients()
    }
}

fn preconditioned_conductances(s: &PreconditionedHeat, theta: &[f64], c: &mut [f64]) {
    heat_conductances(&s.0, theta, c)
}

#[inline(always)]
fn preconditioned_matvec(s: &PreconditionedHeat, v: &[f64], c: &[f64], out: &mut [f64]) {
    heat_matvec(&s.0, v, c, out)
}

fn preconditioned_rhs(s: &PreconditionedHeat, x: &[f64], theta: &[f64], b: &mut [f64]) {
    heat_rhs(&s.0, x, theta, b)
}

#[inline(always)]
fn preconditioned_jacobi(s: &PreconditionedHeat, c: &[f64], r: &[f64], z: &mut [f64]) {
    heat_jacobi(&s.0, c, r, z)
}

crate::linear_system!(
    PreconditionedHeat => preconditioned_matvec, preconditioned_rhs,
    coefficients = preconditioned_conductances, preconditioner = preconditioned_jacobi
);

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

/// One step by plain CG from zero: the conductances, `r`, `d`, `q` in
/// lent scratch.
fn heat_through_cg(op: &HeatThroughCg, x: &[f64], p: &[f64], y: &mut [f64], s: &mut [f64]) {
    let m = op.n * op.n;
    let sys = ImplicitHeat { n: op.n, dt: op.dt };
    let (c, rest) = s.split_at_mut(sys.n_coefficients());
    heat_conductances(&sys, p, c);
    let (r, rest) = rest.split_at_mut(m);
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
        heat_matvec(&sys, d, c, q);
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
    3 * op.n * op.n + ImplicitHeat { n: op.n, dt: op.dt }.n_coefficients()
}

crate::differentiable!(HeatThroughCg => heat_through_cg, scratch = heat_through_cg_scratch);
