//! Fluid operators on the MAC grid of [`diffsim_solvers::smoke::MacGrid`]
//! in 2D and 3D (unit cells, staggered velocity, any
//! [`diffsim_solvers::boundary::Boundary`]): diffusion, explicit and
//! implicit; semi-Lagrangian, MacCormack and upwind advection; buoyancy,
//! forces and inflow regions; the projection ([`Project`]). Each wraps a
//! plain function of `diffsim-solvers`; explicit ones get their derivatives
//! from Enzyme, implicit diffusion is a [`LinearSolve`] of its product
//! (the implicit rule), the projection solves with the transposed matrix.

use std::cell::{Cell, RefCell};

use diffsim_solvers::diffusion::{self, Grid};
use diffsim_solvers::mac::fft::FftProjection;
use diffsim_solvers::smoke::{self, MacGrid, NoConvergence, Preconditioner, PressureSolver, ProjectScratch, Scheme};

use crate::implicit::{LinearSolve, LinearSystem, SolveMethod, SolveParams, Start};
use crate::op::{Forward, Jvp, OpError, Operator, Vjp, validate_forward, validate_jvp, validate_vjp};

/// The sizes of a fluid operator on packed states of any dimension `D`:
/// `self.cfg.n_state()` values in and out, and the parameters `|op| count`
/// (none by default).
macro_rules! state_sizes {
    ($ty:ident) => {
        state_sizes!($ty, |_op| 0);
    };
    ($ty:ident, |$op:ident| $params:expr) => {
        state_sizes!($ty, cfg, |$op| $params);
    };
    // `$grid`: the field holding the operator's `MacGrid` (`cfg`, or `0`
    // in a tuple struct).
    ($ty:ident, $grid:tt, |$op:ident| $params:expr) => {
        impl<const D: usize> $crate::op::Operator for $ty<D> {
            fn n_in(&self) -> usize {
                self.$grid.n_state()
            }
            fn n_out(&self) -> usize {
                self.$grid.n_state()
            }
            fn n_params(&self) -> usize {
                let $op = self;
                $params
            }
        }
    };
}
pub(crate) use state_sizes;

/// Explicit diffusion of a field on a lattice ([`Grid`]), `s' = s − κ·A·s`,
/// with the parameter `p = [κ]` (κ = ν·dt). Derivatives by Enzyme, with
/// respect to `s` and κ. A κ beyond the stability limit ([`Grid::explicit_limit`]) is reported
/// through [`Forward::take_error`] (the step is still computed).
#[derive(Debug)]
pub struct DiffuseExplicit {
    /// The lattice.
    pub grid: Grid,
    unstable: Cell<Option<f64>>,
}

impl DiffuseExplicit {
    /// Explicit diffusion of the cells of the closed `n × n` box.
    pub fn new(n: usize) -> Self {
        Self::on(Grid::square(n))
    }

    /// Explicit diffusion on the lattice `grid`.
    pub fn on(grid: Grid) -> Self {
        Self { grid, unstable: Cell::new(None) }
    }
}

impl Operator for DiffuseExplicit {
    fn n_in(&self) -> usize {
        self.grid.len()
    }
    fn n_out(&self) -> usize {
        self.grid.len()
    }
    fn n_params(&self) -> usize {
        1
    }
}

/// Plain data for Enzyme (the `Cell` of [`DiffuseExplicit`] stays outside).
#[derive(Clone, Copy, Debug)]
struct ExplicitMap {
    grid: Grid,
}

impl Operator for ExplicitMap {
    fn n_in(&self) -> usize {
        self.grid.len()
    }
    fn n_out(&self) -> usize {
        self.grid.len()
    }
    fn n_params(&self) -> usize {
        1
    }
}

fn diffuse_explicit(op: &ExplicitMap, x: &[f64], p: &[f64], y: &mut [f64]) {
    diffusion::explicit(&op.grid, p[0], x, y)
}

crate::differentiable!(ExplicitMap => diffuse_explicit);

impl Forward for DiffuseExplicit {
    fn forward(&self, x: &[f64], p: &[f64], y: &mut [f64]) {
        validate_forward(self, "DiffuseExplicit", x, p, y);
        if p[0] > self.grid.explicit_limit() && self.unstable.get().is_none() {
            self.unstable.set(Some(p[0]));
        }
        ExplicitMap { grid: self.grid }.forward(x, p, y)
    }

    fn take_error(&self) -> Option<OpError> {
        self.unstable.take().map(|kappa| OpError::Unstable { value: kappa, limit: self.grid.explicit_limit() })
    }
}

impl Vjp for DiffuseExplicit {
    fn vjp(&self, x: &[f64], p: &[f64], dy: &mut [f64], dx: &mut [f64], dp: &mut [f64]) {
        ExplicitMap { grid: self.grid }.vjp(x, p, dy, dx, dp)
    }
}

impl Jvp for DiffuseExplicit {
    fn jvp(&self, x: &[f64], p: &[f64], tx: &[f64], tp: &[f64], y: &mut [f64], ty: &mut [f64]) {
        ExplicitMap { grid: self.grid }.jvp(x, p, tx, tp, y, ty)
    }
}

/// Implicit diffusion on a lattice ([`Grid`]), `(I + κ·A)·s' = s`,
/// parameter `p = [κ]`: a [`LinearSolve`] of [`DiffusionSystem`], solved by
/// conjugate gradients from `s` to a relative tolerance, its derivatives by
/// the implicit rule (the matrix is symmetric, so the VJP is the same
/// solve; `κ̄` from Enzyme's derivative of the product). A solve that does
/// not converge is reported through [`Forward::take_error`].
#[derive(Debug)]
pub struct DiffuseImplicit {
    grid: Grid,
    solve: LinearSolve<DiffusionSystem>,
}

/// The system of [`DiffuseImplicit`]: `(I + κ·A)·y = x` on a lattice, the
/// product the explicit step with `−κ`.
#[derive(Clone, Copy, Debug)]
pub struct DiffusionSystem {
    grid: Grid,
}

impl LinearSystem for DiffusionSystem {
    fn n(&self) -> usize {
        self.grid.len()
    }
    fn n_in(&self) -> usize {
        self.grid.len()
    }
    fn n_params(&self) -> usize {
        1
    }
}

/// `out = (I + κ·A)·v`, `p = [κ]`.
fn diffusion_product(s: &DiffusionSystem, v: &[f64], p: &[f64], out: &mut [f64]) {
    diffusion::explicit(&s.grid, -p[0], v, out);
}

/// `b = x`.
fn diffusion_rhs(_: &DiffusionSystem, x: &[f64], _p: &[f64], b: &mut [f64]) {
    b.copy_from_slice(x);
}

crate::linear_system!(DiffusionSystem => diffusion_product, diffusion_rhs);

impl DiffuseImplicit {
    /// Implicit diffusion of the cells of the closed `n × n` box, solves to
    /// relative `tolerance`, at most `max_iterations` iterations.
    pub fn new(n: usize, tolerance: f64, max_iterations: usize) -> Self {
        Self::on(Grid::square(n), tolerance, max_iterations)
    }

    /// Implicit diffusion on the lattice `grid`.
    ///
    /// # Panics
    /// If the tolerance is not a positive number or the iteration limit 0
    /// ([`LinearSolve::new`]).
    #[track_caller]
    pub fn on(grid: Grid, tolerance: f64, max_iterations: usize) -> Self {
        // From the right-hand side, as a time step's solve starts best.
        let params = SolveParams { method: SolveMethod::Cg, tolerance, max_iterations, start: Start::Rhs };
        Self { grid, solve: LinearSolve::new(DiffusionSystem { grid }, params) }
    }
}

impl Operator for DiffuseImplicit {
    fn n_in(&self) -> usize {
        self.grid.len()
    }
    fn n_out(&self) -> usize {
        self.grid.len()
    }
    fn n_params(&self) -> usize {
        1
    }
}

impl Forward for DiffuseImplicit {
    fn forward(&self, x: &[f64], p: &[f64], y: &mut [f64]) {
        crate::op::count::record("DiffuseImplicit", crate::op::count::Method::Forward);
        validate_forward(self, "DiffuseImplicit", x, p, y);
        self.solve.forward(x, p, y);
    }

    fn solve_tolerance(&self) -> f64 {
        self.solve.solve_tolerance()
    }

    fn take_error(&self) -> Option<OpError> {
        self.solve.take_error()
    }
}

impl Vjp for DiffuseImplicit {
    fn vjp(&self, x: &[f64], p: &[f64], dy: &mut [f64], dx: &mut [f64], dp: &mut [f64]) {
        crate::op::count::record("DiffuseImplicit", crate::op::count::Method::Vjp);
        validate_vjp(self, "DiffuseImplicit", x, p, dy, dx, dp);
        self.solve.vjp(x, p, dy, dx, dp);
    }

    fn vjp_overwrite_given(&self, x: &[f64], p: &[f64], y: &[f64], dy: &mut [f64], dx: &mut [f64], dp: &mut [f64]) {
        crate::op::count::record("DiffuseImplicit", crate::op::count::Method::Vjp);
        validate_vjp(self, "DiffuseImplicit", x, p, dy, dx, dp);
        self.solve.vjp_overwrite_given(x, p, y, dy, dx, dp);
    }
}

impl Jvp for DiffuseImplicit {
    fn jvp(&self, x: &[f64], p: &[f64], tx: &[f64], tp: &[f64], y: &mut [f64], ty: &mut [f64]) {
        crate::op::count::record("DiffuseImplicit", crate::op::count::Method::Jvp);
        validate_jvp(self, "DiffuseImplicit", x, p, tx, tp, y, ty);
        self.solve.jvp(x, p, tx, tp, y, ty);
    }
}

/// Diffusion of the chosen fields of a packed state, each on its own
/// lattice with one coefficient `p = [κ]`: smoke diffusion, viscosity, or
/// both. In a box (`[s, u, v]`, lattices of [`Grid::of_state`]) the velocity
/// boundary conditions are applied after; on a line (`[s, u]`, [`Diffuse::line`])
/// each field is one row. `D` is [`DiffuseExplicit`] or [`DiffuseImplicit`].
/// Fields not chosen pass through.
#[derive(Debug)]
pub struct Diffuse<D> {
    n: usize,
    /// `(start in the state, operator)` per diffused lattice.
    parts: Vec<(usize, D)>,
    /// The box whose velocity boundary conditions are applied after a
    /// velocity diffusion.
    velocity_box: Option<Box<dyn Walls>>,
}

/// The velocity boundary conditions re-applied after a velocity diffusion:
/// the sides of a box of any dimension ([`smoke::enforce_boundary`]), on
/// the velocity part of a packed state. Implemented by every
/// [`MacGrid<N>`].
pub trait Walls: std::fmt::Debug + Send + Sync {
    /// The boundary conditions in place on a state.
    fn apply(&self, y: &mut [f64]);
    /// Their linear part in place on a tangent.
    fn apply_linear(&self, t: &mut [f64]);
    /// Their adjoint in place on an adjoint.
    fn apply_adjoint(&self, g: &mut [f64]);
}

impl<const N: usize> Walls for MacGrid<N> {
    fn apply(&self, y: &mut [f64]) {
        smoke::enforce_boundary(self, &mut y[self.n_s()..]);
    }

    fn apply_linear(&self, t: &mut [f64]) {
        smoke::enforce_boundary_linear(self, &mut t[self.n_s()..]);
    }

    fn apply_adjoint(&self, g: &mut [f64]) {
        smoke::enforce_boundary_adjoint(self, &mut g[self.n_s()..]);
    }
}

impl<D: Operator> Diffuse<D> {
    /// The chosen fields of the box `cfg`, 2D or 3D (`[s, u₀, …]`, each
    /// velocity component on its own faces, the walls applied after), each
    /// lattice's operator made by `op`.
    pub fn in_box<const N: usize>(cfg: MacGrid<N>, smoke: bool, velocity: bool, op: impl Fn(Grid) -> D) -> Self {
        let mut parts = Vec::new();
        for (l, grid) in Grid::of_state(&cfg).into_iter().enumerate() {
            if l == 0 && smoke {
                parts.push((0, op(grid)));
            } else if l > 0 && velocity {
                parts.push((cfg.n_s() + cfg.face_range(l - 1).start, op(grid)));
            }
        }
        let velocity_box: Option<Box<dyn Walls>> = if velocity { Some(Box::new(cfg)) } else { None };
        Self { n: cfg.n_state(), parts, velocity_box }
    }

    /// The chosen fields of a line of `n` cells (state `[s, u]`, unit
    /// spacing: κ = ν·dt/dx²), periodic or closed.
    pub fn line(n: usize, periodic: bool, smoke: bool, velocity: bool, op: impl Fn(Grid) -> D) -> Self {
        let grid = Grid::line(n, periodic);
        let parts = [(smoke, 0), (velocity, n)].into_iter().filter(|(on, _)| *on).map(|(_, start)| (start, op(grid))).collect();
        Self { n: 2 * n, parts, velocity_box: None }
    }
}

impl Diffuse<DiffuseExplicit> {
    /// Explicit diffusion of the smoke and/or the velocity of a box.
    pub fn explicit<const N: usize>(cfg: MacGrid<N>, smoke: bool, velocity: bool) -> Self {
        Self::in_box(cfg, smoke, velocity, DiffuseExplicit::on)
    }
}

impl Diffuse<DiffuseImplicit> {
    /// Implicit diffusion of the smoke and/or the velocity of a box, each
    /// solve to relative `tolerance` in at most `max_iterations` iterations.
    pub fn implicit<const N: usize>(cfg: MacGrid<N>, smoke: bool, velocity: bool, tolerance: f64, max_iterations: usize) -> Self {
        Self::in_box(cfg, smoke, velocity, |g| DiffuseImplicit::on(g, tolerance, max_iterations))
    }
}

impl<D> Diffuse<D> {
    /// The fields with their place in the state: `(start, operator)`.
    fn parts(&self) -> impl Iterator<Item = (usize, &D)> {
        self.parts.iter().map(|(s, d)| (*s, d))
    }
}

impl<D> Operator for Diffuse<D> {
    fn n_in(&self) -> usize {
        self.n
    }
    fn n_out(&self) -> usize {
        self.n
    }
    fn n_params(&self) -> usize {
        1
    }
}

impl<D: Forward> Forward for Diffuse<D> {
    fn forward(&self, x: &[f64], p: &[f64], y: &mut [f64]) {
        validate_forward(self, "Diffuse", x, p, y);
        y.copy_from_slice(x);
        for (start, op) in self.parts() {
            let r = start..start + op.n_in();
            op.forward(&x[r.clone()], p, &mut y[r]);
        }
        if let Some(walls) = &self.velocity_box {
            walls.apply(y);
        }
    }

    fn solve_tolerance(&self) -> f64 {
        self.parts().map(|(_, op)| op.solve_tolerance()).fold(0.0, f64::max)
    }

    fn take_error(&self) -> Option<OpError> {
        self.parts().filter_map(|(_, op)| op.take_error()).next()
    }
}

impl<D: Vjp> Vjp for Diffuse<D> {
    fn vjp(&self, x: &[f64], p: &[f64], dy: &mut [f64], dx: &mut [f64], dp: &mut [f64]) {
        validate_vjp(self, "Diffuse", x, p, dy, dx, dp);
        if let Some(walls) = &self.velocity_box {
            walls.apply_adjoint(dy);
        }
        for (start, op) in self.parts() {
            let r = start..start + op.n_in();
            op.vjp(&x[r.clone()], p, &mut dy[r.clone()], &mut dx[r.clone()], dp);
            dy[r].fill(0.0);
        }
        // What was not diffused passes through.
        for (d, g) in dx.iter_mut().zip(dy.iter_mut()) {
            *d += *g;
            *g = 0.0;
        }
    }
}

impl<D: Jvp> Jvp for Diffuse<D> {
    fn jvp(&self, x: &[f64], p: &[f64], tx: &[f64], tp: &[f64], y: &mut [f64], ty: &mut [f64]) {
        validate_jvp(self, "Diffuse", x, p, tx, tp, y, ty);
        y.copy_from_slice(x);
        ty.copy_from_slice(tx);
        for (start, op) in self.parts() {
            let r = start..start + op.n_in();
            op.jvp(&x[r.clone()], p, &tx[r.clone()], tp, &mut y[r.clone()], &mut ty[r]);
        }
        if let Some(walls) = &self.velocity_box {
            walls.apply(y);
            walls.apply_linear(ty);
        }
    }
}

/// First-order upwind advection of the smoke in a packed state over a time
/// step `dt` ([`smoke::advect_upwind`]; the velocity passes through), in 2D
/// and 3D. Derivatives by Enzyme; the upwind switch is declared through
/// [`Forward::smooth_radius`].
#[derive(Clone, Copy, Debug)]
pub struct AdvectUpwind<const D: usize> {
    /// The grid.
    pub cfg: MacGrid<D>,
    /// Time step.
    pub dt: f64,
}

state_sizes!(AdvectUpwind);

fn advect_upwind<const D: usize>(op: &AdvectUpwind<D>, x: &[f64], _p: &[f64], y: &mut [f64]) {
    smoke::advect_upwind(&op.cfg, op.dt, x, y)
}

fn upwind_radius<const D: usize>(op: &AdvectUpwind<D>, x: &[f64], _p: &[f64], dx: &[f64], _dp: &[f64]) -> f64 {
    smoke::upwind_radius(&op.cfg, x, dx)
}

crate::differentiable!(AdvectUpwind<2> => advect_upwind::<2>, smooth_radius = upwind_radius::<2>);
crate::differentiable!(AdvectUpwind<3> => advect_upwind::<3>, smooth_radius = upwind_radius::<3>);

/// Semi-Lagrangian or MacCormack advection over a time step `dt` of the
/// smoke and/or the velocity in a packed state, in 2D and 3D, any boundary
/// ([`smoke::advect`]): fields not advected pass through, an advected
/// velocity gets the boundary conditions. Derivatives by Enzyme; the
/// sampling kinks and the limiter's switches are declared through
/// [`Forward::smooth_radius`]. P2's and P4's own step is
/// [`crate::problems::smoke::SmokeAdvect`] (both fields, with buoyancy,
/// parallel, with a hand adjoint beside it).
#[derive(Clone, Copy, Debug)]
pub struct Advect<const D: usize> {
    /// The grid and its boundary.
    pub cfg: MacGrid<D>,
    /// The scheme.
    pub scheme: Scheme,
    /// Time step.
    pub dt: f64,
    /// Advect the smoke.
    pub smoke: bool,
    /// Advect the velocity (by itself).
    pub velocity: bool,
}

impl<const D: usize> Advect<D> {
    /// Both fields over the grid's time step.
    pub fn new(cfg: MacGrid<D>, scheme: Scheme) -> Self {
        Self { cfg, scheme, dt: cfg.dt, smoke: true, velocity: true }
    }
}

state_sizes!(Advect);

fn advect<const D: usize>(op: &Advect<D>, x: &[f64], _p: &[f64], y: &mut [f64], scratch: &mut [f64]) {
    smoke::advect(&op.cfg, op.scheme, op.dt, op.smoke, op.velocity, x, y, scratch)
}

/// MacCormack's intermediate fields.
fn advect_scratch<const D: usize>(op: &Advect<D>) -> usize {
    smoke::advect_scratch_len(&op.cfg, op.scheme)
}

/// Where the multilinear samples stay between lattice planes, and with
/// MacCormack's limiter also where its clamp switches.
fn advect_radius<const D: usize>(op: &Advect<D>, x: &[f64], _p: &[f64], dx: &[f64], _dp: &[f64]) -> f64 {
    let sampling = smoke::advect_radius(&op.cfg, op.scheme, op.dt, op.smoke, op.velocity, x, dx);
    match op.scheme {
        Scheme::MacCormack { limiter: true } => sampling.min(smoke::limiter_radius(&op.cfg, op.dt, op.smoke, op.velocity, x, dx)),
        _ => sampling,
    }
}

crate::differentiable!(Advect<2> => advect::<2>, smooth_radius = advect_radius::<2>, scratch = advect_scratch::<2>);
crate::differentiable!(Advect<3> => advect::<3>, smooth_radius = advect_radius::<3>, scratch = advect_scratch::<3>);

/// An external force field on the faces as the parameters, in 2D and 3D:
/// `vel ↦ vel + dt·p` with `p` given per face ([`MacGrid::n_vel`] values,
/// the velocity layout; the faces on closed, inflow and outflow sides are
/// not forced; [`smoke::apply_force`]). The parameter gradient is the
/// gradient with respect to the force, for control. Derivatives by Enzyme.
#[derive(Clone, Copy, Debug)]
pub struct Force<const D: usize> {
    /// The grid.
    pub cfg: MacGrid<D>,
    /// Time step.
    pub dt: f64,
}

state_sizes!(Force, |op| op.cfg.n_vel());

fn force<const D: usize>(op: &Force<D>, x: &[f64], p: &[f64], y: &mut [f64]) {
    smoke::apply_force(&op.cfg, op.dt, x, p, y)
}

crate::differentiable!(Force<2> => force::<2>);
crate::differentiable!(Force<3> => force::<3>);

/// Inflow, in 2D and 3D: in the cells `region[a][0]..region[a][1]` along
/// each axis the smoke is set to `p[0]` and the velocity of the region's
/// faces to `(p[1], …, p[D])` every step ([`smoke::apply_inflow`]).
/// Derivatives by Enzyme (with respect to the inflow values too).
#[derive(Clone, Copy, Debug)]
pub struct Inflow<const D: usize> {
    /// The grid.
    pub cfg: MacGrid<D>,
    /// The cells per axis, half-open ranges `[start, end]`.
    pub region: [[usize; 2]; D],
}

state_sizes!(Inflow, |_op| D + 1);

fn inflow<const D: usize>(op: &Inflow<D>, x: &[f64], p: &[f64], y: &mut [f64]) {
    smoke::apply_inflow(&op.cfg, op.region, x, p, y)
}

crate::differentiable!(Inflow<2> => inflow::<2>);
crate::differentiable!(Inflow<3> => inflow::<3>);

/// The pressure projection of a packed `[s, u₀, …]` state as an operator
/// (linear), in 2D and 3D: with obstacles, the obstacle mask (smoke in
/// solids and velocity on faces touching them zeroed), then `vel −=
/// G·A⁻¹·(−D·vel)` by preconditioned CG to a relative tolerance on the true
/// residual ([`smoke::project`]). The VJP is the implicit adjoint: one
/// solve with the transposed (same) matrix to the same tolerance, never a
/// pass through the iterations. A solve that does not converge is recorded
/// and reported through [`Forward::take_error`].
///
/// On a box periodic on every axis and without obstacles the projection is
/// the FFT's ([`FftProjection`]: the same discrete divergence and gradient,
/// solved exactly, its own adjoint), 11× to 80× faster than the CG solve
/// (docs/fluids.md); the tolerance and preconditioner are then unused.
#[derive(Debug)]
pub struct Project<const D: usize> {
    cfg: MacGrid<D>,
    /// Fluid indicator per cell and open fraction per face when there are
    /// obstacles.
    mask: Option<(Vec<f64>, Vec<f64>)>,
    solve: RefCell<Solve<D>>,
    stop: diffsim_solvers::cg::Stop,
    precond: Preconditioner,
    /// The solves' iteration counts and first failure.
    pub log: SolveLog,
}

/// How a [`Project`] solves.
#[derive(Debug)]
enum Solve<const D: usize> {
    /// Conjugate gradients, with the divergence and pressure kept.
    Cg(Box<PressureSolver<D>>, ProjectScratch),
    /// The FFT of a fully periodic box.
    Fft(FftProjection<D>),
}

/// What a projection's solves did: CG iterations so far, forward and
/// adjoint, and the first solve that did not converge (reported, then
/// cleared, by [`SolveLog::take_error`]). Shared by the 2D and 3D
/// projections and implicit diffusion.
#[derive(Debug, Default)]
pub struct SolveLog {
    error: Cell<Option<NoConvergence>>,
    /// CG iterations of all forward (and JVP) solves so far.
    pub cg_forward: Cell<usize>,
    /// CG iterations of all adjoint solves so far.
    pub cg_adjoint: Cell<usize>,
}

impl SolveLog {
    /// Counts a forward (`adjoint = false`) or adjoint solve's iterations and
    /// keeps its failure if it is the first.
    pub fn record(&self, r: Result<usize, NoConvergence>, adjoint: bool) {
        let counter = if adjoint { &self.cg_adjoint } else { &self.cg_forward };
        match r {
            Ok(it) => counter.set(counter.get() + it),
            Err(e) => {
                counter.set(counter.get() + e.iterations);
                if self.error.get().is_none() {
                    self.error.set(Some(e));
                }
            }
        }
    }

    /// The first failure since the last call, as an operator error.
    pub fn take_error(&self) -> Option<OpError> {
        self.error.take().map(OpError::from)
    }
}

impl<const D: usize> Project<D> {
    /// The projection of the box `cfg` (any sides) with solves to relative
    /// `tolerance` in at most `max_iterations` iterations, preconditioned by
    /// `precond` ([`PressureSolver`]: multigrid is the geometric V-cycle in
    /// a closed box with two equal sides, the aggregation V-cycle in any
    /// other); by FFT on a box periodic on every axis.
    ///
    /// # Panics
    /// If `cfg.boundary` does not [validate](diffsim_solvers::boundary::Boundary::validate).
    pub fn new(cfg: MacGrid<D>, tolerance: f64, max_iterations: usize, precond: Preconditioner) -> Self {
        if let Err(e) = cfg.boundary.validate() {
            panic!("{e}");
        }
        let solve = if cfg.boundary.wraps().iter().all(|&w| w) {
            Solve::Fft(FftProjection::new(cfg.n))
        } else {
            Solve::Cg(Box::new(PressureSolver::new(&cfg, tolerance, max_iterations, precond)), ProjectScratch::new(cfg.n_s()))
        };
        Self::with_solve(cfg, None, solve, tolerance, max_iterations, precond)
    }

    fn with_solve(
        cfg: MacGrid<D>,
        mask: Option<(Vec<f64>, Vec<f64>)>,
        solve: Solve<D>,
        tolerance: f64,
        max_iterations: usize,
        precond: Preconditioner,
    ) -> Self {
        let stop = diffsim_solvers::cg::Stop { tolerance, max_iterations };
        Self { cfg, mask, solve: RefCell::new(solve), stop, precond, log: SolveLog::default() }
    }

    /// The projection with solid cells where `solid[c]` is true (e.g.
    /// [`smoke::solid_cells`]): the obstacle mask first, then a solve that
    /// couples fluid cells only ([`PressureSolver::with_obstacles`]). The
    /// result is divergence-free in every fluid cell with no flow through a
    /// solid's faces.
    ///
    /// # Panics
    /// As [`Project::new`], if `solid` does not have a value per cell, or
    /// if every cell is solid.
    pub fn with_obstacles(cfg: MacGrid<D>, tolerance: f64, max_iterations: usize, precond: Preconditioner, solid: &[bool]) -> Self {
        if let Err(e) = cfg.boundary.validate() {
            panic!("{e}");
        }
        assert_eq!(solid.len(), cfg.n_s(), "projection: one solid flag per cell");
        assert!(solid.iter().any(|&s| !s), "projection: every cell is solid");
        let fluid = smoke::fluid_of(solid);
        let mask = Some((fluid.clone(), smoke::open_faces(&cfg, &fluid)));
        let solver = PressureSolver::with_obstacles(&cfg, tolerance, max_iterations, precond, fluid);
        Self::with_solve(cfg, mask, Solve::Cg(Box::new(solver), ProjectScratch::new(cfg.n_s())), tolerance, max_iterations, precond)
    }

    /// The preconditioner of the solves (as asked for; unused by the FFT).
    pub fn preconditioner(&self) -> Preconditioner {
        self.precond
    }

    /// The stopping rule of the solves.
    pub fn stop(&self) -> diffsim_solvers::cg::Stop {
        self.stop
    }

    /// Whether it projects by FFT (a box periodic on every axis, no obstacles).
    pub fn by_fft(&self) -> bool {
        matches!(*self.solve.borrow(), Solve::Fft(_))
    }

    /// Records a velocity (or its adjoint) that is not finite as the FFT
    /// projection's error, as a CG solve's right-hand side holding one is
    /// recorded.
    fn refuse_non_finite(&self, vel: &[f64], adjoint: bool) {
        if vel.iter().any(|v| !v.is_finite()) {
            self.log.record(Err(NoConvergence { iterations: 0, relative_residual: f64::NAN, tolerance: 0.0 }), adjoint);
        }
    }

    /// The map in place on a packed state (or tangent).
    pub fn apply(&self, y: &mut [f64]) {
        let ns = self.cfg.n_s();
        if let Some((fluid, _)) = &self.mask {
            smoke::mask_cells(fluid, &mut y[..ns]);
        }
        self.apply_velocity(&mut y[ns..]);
    }

    /// The map in place on a packed velocity `[u₀, …]` alone (or its
    /// tangent): the faces that touch a solid zeroed, then the solve.
    pub fn apply_velocity(&self, vel: &mut [f64]) {
        if let Some((_, open)) = &self.mask {
            smoke::mask_faces(open, vel);
        }
        match &mut *self.solve.borrow_mut() {
            Solve::Cg(solver, scratch) => {
                self.log.record(smoke::project_velocity(&self.cfg, self.cfg.components_mut(vel), None, None, solver, scratch, false), false)
            }
            Solve::Fft(fft) => {
                self.refuse_non_finite(vel, false);
                fft.project(self.cfg.components_mut(vel));
            }
        }
    }

    /// The transposed map in place on an adjoint.
    pub fn apply_adjoint(&self, g: &mut [f64]) {
        let ns = self.cfg.n_s();
        self.apply_adjoint_velocity(&mut g[ns..]);
        if let Some((fluid, _)) = &self.mask {
            smoke::mask_cells(fluid, &mut g[..ns]);
        }
    }

    /// The transposed map in place on a packed velocity adjoint alone.
    pub fn apply_adjoint_velocity(&self, vel: &mut [f64]) {
        match &mut *self.solve.borrow_mut() {
            Solve::Cg(solver, scratch) => self.log.record(smoke::project_velocity_adjoint(&self.cfg, self.cfg.components_mut(vel), solver, scratch), true),
            Solve::Fft(fft) => {
                self.refuse_non_finite(vel, true);
                fft.project_adjoint(self.cfg.components_mut(vel));
            }
        }
        if let Some((_, open)) = &self.mask {
            smoke::mask_faces(open, vel);
        }
    }
}

// The operator traits of the projection: a linear map, its transpose the
// implicit adjoint.
state_sizes!(Project);

impl<const D: usize> crate::op::Forward for Project<D> {
    fn forward(&self, x: &[f64], p: &[f64], y: &mut [f64]) {
        crate::op::count::record("Project", crate::op::count::Method::Forward);
        crate::op::validate_forward(self, "Project", x, p, y);
        y.copy_from_slice(x);
        self.apply(y);
    }

    fn solve_tolerance(&self) -> f64 {
        if self.by_fft() { 0.0 } else { self.stop.tolerance }
    }

    fn take_error(&self) -> Option<crate::op::OpError> {
        self.log.take_error()
    }
}

impl<const D: usize> crate::op::Vjp for Project<D> {
    fn vjp(&self, x: &[f64], p: &[f64], dy: &mut [f64], dx: &mut [f64], dp: &mut [f64]) {
        crate::op::count::record("Project", crate::op::count::Method::Vjp);
        crate::op::validate_vjp(self, "Project", x, p, dy, dx, dp);
        self.apply_adjoint(dy);
        for (d, g) in dx.iter_mut().zip(dy.iter_mut()) {
            *d += *g;
            *g = 0.0;
        }
    }
}

impl<const D: usize> crate::op::Jvp for Project<D> {
    fn jvp(&self, x: &[f64], p: &[f64], tx: &[f64], tp: &[f64], y: &mut [f64], ty: &mut [f64]) {
        crate::op::count::record("Project", crate::op::count::Method::Jvp);
        crate::op::validate_jvp(self, "Project", x, p, tx, tp, y, ty);
        y.copy_from_slice(x);
        self.apply(y);
        ty.copy_from_slice(tx);
        self.apply(ty);
    }
}

/// Buoyancy over a time step `dt` along `axis` (0 x, 1 y, 2 z) with the
/// coefficient as the parameter `p = [b]`, in 2D and 3D: the component of
/// `axis` on its faces between two cells (interior, and across a periodic
/// side) gains `dt·b·(smoke averaged to the face)`
/// ([`smoke::apply_buoyancy`]). Derivatives by Enzyme, with respect to the
/// state and `b`.
#[derive(Clone, Copy, Debug)]
pub struct Buoyancy<const D: usize> {
    /// The grid.
    pub cfg: MacGrid<D>,
    /// Time step.
    pub dt: f64,
    /// The axis the force acts along (1: up).
    pub axis: usize,
}

state_sizes!(Buoyancy, |_op| 1);

fn buoyancy<const D: usize>(op: &Buoyancy<D>, x: &[f64], p: &[f64], y: &mut [f64]) {
    smoke::apply_buoyancy(&op.cfg, op.axis, op.dt * p[0], x, y)
}

crate::differentiable!(Buoyancy<2> => buoyancy::<2>);
crate::differentiable!(Buoyancy<3> => buoyancy::<3>);
