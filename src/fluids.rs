//! 2D fluid operators on the P2 grid conventions (unit cells, MAC velocity,
//! any [`Boundary`](diffsim_solvers::boundary::Boundary); see
//! [`diffsim_solvers::smoke`]): diffusion, explicit and implicit (closed
//! box); semi-Lagrangian, MacCormack and upwind advection; forces and
//! inflow regions. Each wraps a
//! plain function of `diffsim-solvers`; explicit ones get their derivatives
//! from Enzyme, implicit ones from the solve with the transposed matrix.

use std::cell::{Cell, RefCell};

use diffsim_solvers::diffusion::{self, EXPLICIT_LIMIT, ImplicitSolver};
use diffsim_solvers::smoke::{self, NoConvergence, Scheme, Smoke2d, apply_pressure_matrix};

use crate::op::{Forward, Jvp, OpError, Operator, Vjp, validate_forward, validate_jvp, validate_vjp};

/// Explicit diffusion of a cell-centred scalar, `s' = s − κ·A·s`, with the
/// parameter `p = [κ]` (κ = ν·dt). Derivatives by Enzyme, with respect to
/// `s` and κ. A κ beyond the stability limit 1/4 is reported through
/// [`Forward::take_error`] (the step is still computed).
#[derive(Debug)]
pub struct DiffuseExplicit {
    /// Cells per side.
    pub n: usize,
    unstable: Cell<Option<f64>>,
}

impl DiffuseExplicit {
    /// Explicit diffusion on an `n × n` box.
    pub fn new(n: usize) -> Self {
        Self { n, unstable: Cell::new(None) }
    }
}

impl Operator for DiffuseExplicit {
    fn n_in(&self) -> usize {
        self.n * self.n
    }
    fn n_out(&self) -> usize {
        self.n * self.n
    }
    fn n_params(&self) -> usize {
        1
    }
}

/// Plain data for Enzyme (the `Cell` of [`DiffuseExplicit`] stays outside).
#[derive(Clone, Copy, Debug)]
struct ExplicitMap {
    n: usize,
}

impl Operator for ExplicitMap {
    fn n_in(&self) -> usize {
        self.n * self.n
    }
    fn n_out(&self) -> usize {
        self.n * self.n
    }
    fn n_params(&self) -> usize {
        1
    }
}

fn diffuse_explicit(op: &ExplicitMap, x: &[f64], p: &[f64], y: &mut [f64]) {
    diffusion::explicit(op.n, p[0], x, y)
}

crate::differentiable!(ExplicitMap => diffuse_explicit);

impl Forward for DiffuseExplicit {
    fn forward(&self, x: &[f64], p: &[f64], y: &mut [f64]) {
        validate_forward(self, "DiffuseExplicit", x, p, y);
        if p[0] > EXPLICIT_LIMIT && self.unstable.get().is_none() {
            self.unstable.set(Some(p[0]));
        }
        ExplicitMap { n: self.n }.forward(x, p, y)
    }

    fn take_error(&self) -> Option<OpError> {
        self.unstable.take().map(|kappa| OpError::Unstable { value: kappa, limit: EXPLICIT_LIMIT })
    }
}

impl Vjp for DiffuseExplicit {
    fn vjp(&self, x: &[f64], p: &[f64], dy: &mut [f64], dx: &mut [f64], dp: &mut [f64]) {
        ExplicitMap { n: self.n }.vjp(x, p, dy, dx, dp)
    }
}

impl Jvp for DiffuseExplicit {
    fn jvp(&self, x: &[f64], p: &[f64], tx: &[f64], tp: &[f64], y: &mut [f64], ty: &mut [f64]) {
        ExplicitMap { n: self.n }.jvp(x, p, tx, tp, y, ty)
    }
}

/// Implicit diffusion, `(I + κ·A)·s' = s`, parameter `p = [κ]`, solved by
/// conjugate gradients to a relative tolerance. The VJP is the same solve
/// (the matrix is symmetric): with `M·λ = ḡ`, `x̄ += λ` and
/// `κ̄ += −λᵀ·A·s'`. A solve that does not converge is reported through
/// [`Forward::take_error`].
#[derive(Debug)]
pub struct DiffuseImplicit {
    n: usize,
    solver: RefCell<ImplicitSolver>,
    scratch: RefCell<(Vec<f64>, Vec<f64>)>,
    error: Cell<Option<NoConvergence>>,
}

impl DiffuseImplicit {
    /// Implicit diffusion on an `n × n` box, solves to relative `tolerance`,
    /// at most `max_iterations` iterations.
    pub fn new(n: usize, tolerance: f64, max_iterations: usize) -> Self {
        Self {
            n,
            solver: RefCell::new(ImplicitSolver::new(n, tolerance, max_iterations)),
            scratch: RefCell::new((vec![0.0; n * n], vec![0.0; n * n])),
            error: Cell::new(None),
        }
    }

    fn solve(&self, kappa: f64, b: &[f64], x: &mut [f64]) {
        if let Err(e) = self.solver.borrow_mut().solve(kappa, b, x)
            && self.error.get().is_none()
        {
            self.error.set(Some(e));
        }
    }
}

impl Operator for DiffuseImplicit {
    fn n_in(&self) -> usize {
        self.n * self.n
    }
    fn n_out(&self) -> usize {
        self.n * self.n
    }
    fn n_params(&self) -> usize {
        1
    }
}

impl Forward for DiffuseImplicit {
    fn forward(&self, x: &[f64], p: &[f64], y: &mut [f64]) {
        validate_forward(self, "DiffuseImplicit", x, p, y);
        self.solve(p[0], x, y);
    }

    fn take_error(&self) -> Option<OpError> {
        self.error.take().map(OpError::from)
    }
}

impl Vjp for DiffuseImplicit {
    fn vjp(&self, x: &[f64], p: &[f64], dy: &mut [f64], dx: &mut [f64], dp: &mut [f64]) {
        validate_vjp(self, "DiffuseImplicit", x, p, dy, dx, dp);
        let mut guard = self.scratch.borrow_mut();
        let (lam, y) = &mut *guard;
        self.solve(p[0], dy, lam);
        for (d, &l) in dx.iter_mut().zip(lam.iter()) {
            *d += l;
        }
        // κ̄ = −λᵀ·A·y with y = M⁻¹·x (recomputed: the VJP gets only x).
        self.solve(p[0], x, y);
        apply_pressure_matrix(self.n, y, dy);
        dp[0] -= lam.iter().zip(dy.iter()).map(|(a, b)| a * b).sum::<f64>();
        dy.fill(0.0);
    }
}

impl Jvp for DiffuseImplicit {
    fn jvp(&self, x: &[f64], p: &[f64], tx: &[f64], tp: &[f64], y: &mut [f64], ty: &mut [f64]) {
        validate_jvp(self, "DiffuseImplicit", x, p, tx, tp, y, ty);
        self.solve(p[0], x, y);
        // M·ṫ = ẋ − κ̇·A·y.
        let mut guard = self.scratch.borrow_mut();
        let (rhs, _) = &mut *guard;
        apply_pressure_matrix(self.n, y, rhs);
        for (r, &t) in rhs.iter_mut().zip(tx) {
            *r = t - tp[0] * *r;
        }
        self.solve(p[0], rhs, ty);
    }
}

/// First-order upwind advection of the smoke in a packed `[s, u, v]` state
/// (P2 layout) over a time step `dt`: `[s, u, v] ↦ [s', u, v]`. Derivatives
/// by Enzyme; the upwind switch is declared through
/// [`Forward::smooth_radius`].
#[derive(Clone, Copy, Debug)]
pub struct AdvectUpwind {
    /// The grid.
    pub cfg: Smoke2d,
    /// Time step.
    pub dt: f64,
}

impl Operator for AdvectUpwind {
    fn n_in(&self) -> usize {
        self.cfg.n_state()
    }
    fn n_out(&self) -> usize {
        self.cfg.n_state()
    }
}

fn advect_upwind(op: &AdvectUpwind, x: &[f64], _p: &[f64], y: &mut [f64]) {
    smoke::advect_upwind(&op.cfg, op.dt, x, y)
}

fn upwind_radius(op: &AdvectUpwind, x: &[f64], _p: &[f64], dx: &[f64], _dp: &[f64]) -> f64 {
    smoke::upwind_radius(&op.cfg, x, dx)
}

crate::differentiable!(AdvectUpwind => advect_upwind, smooth_radius = upwind_radius);

/// Semi-Lagrangian or MacCormack advection over a time step `dt` of the
/// smoke and/or the velocity in a packed `[s, u, v]` state (P2 layout, any
/// boundary; [`smoke::advect`]): fields not advected pass through, an
/// advected velocity gets the boundary conditions. Derivatives by Enzyme.
/// With MacCormack's limiter the map has kinks where the clamp engages; the
/// gradient checks report them when they spoil a rate.
#[derive(Clone, Copy, Debug)]
pub struct Advect {
    /// The grid and its boundary.
    pub cfg: Smoke2d,
    /// The scheme.
    pub scheme: Scheme,
    /// Time step.
    pub dt: f64,
    /// Advect the smoke.
    pub smoke: bool,
    /// Advect the velocity (by itself).
    pub velocity: bool,
}

impl Advect {
    /// Both fields, unit time step.
    pub fn new(cfg: Smoke2d, scheme: Scheme) -> Self {
        Self { cfg, scheme, dt: 1.0, smoke: true, velocity: true }
    }
}

impl Operator for Advect {
    fn n_in(&self) -> usize {
        self.cfg.n_state()
    }
    fn n_out(&self) -> usize {
        self.cfg.n_state()
    }
}

fn advect(op: &Advect, x: &[f64], _p: &[f64], y: &mut [f64]) {
    let mut scratch = vec![0.0; smoke::advect_scratch_len(&op.cfg, op.scheme)];
    smoke::advect(&op.cfg, op.scheme, op.dt, op.smoke, op.velocity, x, y, &mut scratch)
}

crate::differentiable!(Advect => advect);

/// An external force field on the faces as the parameters:
/// `[s, u, v] ↦ [s, u + dt·fu, v + dt·fv]`, `p = [fu, fv]` (`2·N·(N+1)`
/// values, the velocity layout; wall faces are not forced). The parameter
/// gradient is the gradient with respect to the force, for control.
/// Derivatives by Enzyme.
#[derive(Clone, Copy, Debug)]
pub struct Force {
    /// The grid.
    pub cfg: Smoke2d,
    /// Time step.
    pub dt: f64,
}

impl Operator for Force {
    fn n_in(&self) -> usize {
        self.cfg.n_state()
    }
    fn n_out(&self) -> usize {
        self.cfg.n_state()
    }
    fn n_params(&self) -> usize {
        2 * self.cfg.n_u()
    }
}

fn force(op: &Force, x: &[f64], p: &[f64], y: &mut [f64]) {
    smoke::apply_force(&op.cfg, op.dt, x, p, y)
}

crate::differentiable!(Force => force);

/// Inflow: in the cells `region = [i0, i1, j0, j1]` (half-open) the smoke is
/// set to `p[0]` and the velocity of the region's faces to `(p[1], p[2])`
/// every step. Derivatives by Enzyme (with respect to the inflow values too).
#[derive(Clone, Copy, Debug)]
pub struct Inflow {
    /// The grid.
    pub cfg: Smoke2d,
    /// Cells `[i0, i1, j0, j1]`, half-open ranges.
    pub region: [usize; 4],
}

impl Operator for Inflow {
    fn n_in(&self) -> usize {
        self.cfg.n_state()
    }
    fn n_out(&self) -> usize {
        self.cfg.n_state()
    }
    fn n_params(&self) -> usize {
        3
    }
}

fn inflow(op: &Inflow, x: &[f64], p: &[f64], y: &mut [f64]) {
    smoke::apply_inflow(&op.cfg, op.region, x, p, y)
}

crate::differentiable!(Inflow => inflow);
