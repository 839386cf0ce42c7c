//! 3D buoyant smoke (benchmark P4) as operators: the explicit part of the
//! step with Enzyme-generated derivatives and the hand-written adjoint
//! beside it, the projection with its implicit adjoint, the full step, and
//! P4 itself.

use std::cell::RefCell;

use diffsim_solvers::smoke::{Preconditioner, ProjectScratch};
use diffsim_solvers::smoke3d::{self, PressureSolver3, Smoke3d};

use crate::fluids::SolveLog;
use crate::op::Operator;

/// The operator sizes of a packed 3D state `[s, u, v, w]` in and out.
macro_rules! state_operator {
    ($ty:ty, $cfg:ident => $e:expr) => {
        impl Operator for $ty {
            fn n_in(&self) -> usize {
                let $cfg = self;
                $e.n_state()
            }
            fn n_out(&self) -> usize {
                let $cfg = self;
                $e.n_state()
            }
        }
    };
}

/// Steps 1–4 of P4 (advection, walls, buoyancy) on the packed state
/// `[s, u, v, w]`, with Enzyme-generated VJP and JVP.
#[derive(Clone, Copy, Debug)]
pub struct SmokeAdvect3(pub Smoke3d);

state_operator!(SmokeAdvect3, o => o.0);

/// The thin wrapper Enzyme differentiates.
fn smoke_advect3(op: &SmokeAdvect3, x: &[f64], _p: &[f64], y: &mut [f64]) {
    smoke3d::advect_buoyancy(&op.0, x, y)
}

fn smoke_advect3_radius(op: &SmokeAdvect3, x: &[f64], _p: &[f64], dx: &[f64], _dp: &[f64]) -> f64 {
    smoke3d::advect_radius(&op.0, x, dx)
}

crate::differentiable!(SmokeAdvect3 => smoke_advect3, smooth_radius = smoke_advect3_radius);

/// Steps 1–4 of P4 with the hand-written adjoint (the reference for
/// [`SmokeAdvect3`]'s generated one).
#[derive(Clone, Copy, Debug)]
pub struct SmokeAdvect3Hand(pub Smoke3d);

crate::problems::smoke::hand_explicit_operator!(SmokeAdvect3Hand, smoke3d::advect_buoyancy, smoke3d::advect_buoyancy_adjoint, smoke3d::advect_radius);

/// The 3D pressure projection of a packed `[s, u, v, w]` state (linear):
/// `(u, v, w) −= G·A⁺·(−D·(u, v, w))` by preconditioned CG to a relative
/// tolerance on the true residual. The VJP is the implicit adjoint: one
/// solve with the transposed (same) matrix to the same tolerance. A solve
/// that does not converge is reported through [`Forward::take_error`].
#[derive(Debug)]
pub struct Project3 {
    cfg: Smoke3d,
    solver: RefCell<PressureSolver3>,
    scratch: RefCell<ProjectScratch>,
    /// The solves' iteration counts and first failure.
    pub log: SolveLog,
}

impl Project3 {
    /// The projection of the closed cube `cfg` (`nx = ny = nz`), solves to
    /// relative `tolerance` in at most `max_iterations` iterations,
    /// preconditioned by multigrid or nothing.
    ///
    /// # Panics
    /// If the box is not a cube or the preconditioner is not multigrid or none.
    pub fn new(cfg: Smoke3d, tolerance: f64, max_iterations: usize, precond: Preconditioner) -> Self {
        assert!(cfg.nx == cfg.ny && cfg.ny == cfg.nz, "3D projection: the box must be a cube (got {}×{}×{})", cfg.nx, cfg.ny, cfg.nz);
        Self {
            cfg,
            solver: RefCell::new(PressureSolver3::new(cfg.nx, tolerance, max_iterations, precond)),
            scratch: RefCell::new(ProjectScratch::new(cfg.n_s())),
            log: SolveLog::default(),
        }
    }

    /// The preconditioner of the solves.
    pub fn preconditioner(&self) -> Preconditioner {
        self.solver.borrow().preconditioner()
    }

    /// The map in place on a packed state (or tangent).
    pub fn apply(&self, y: &mut [f64]) {
        let r = smoke3d::project(&self.cfg, y, &mut self.solver.borrow_mut(), &mut self.scratch.borrow_mut());
        self.log.record(r, false);
    }

    /// The transposed map in place on an adjoint.
    pub fn apply_adjoint(&self, g: &mut [f64]) {
        let r = smoke3d::project_adjoint(&self.cfg, g, &mut self.solver.borrow_mut(), &mut self.scratch.borrow_mut());
        self.log.record(r, true);
    }
}

crate::fluids::linear_projection!(Project3, "Project3");

/// One full P4 step: [`SmokeAdvect3`] (or its hand-written adjoint), then
/// [`Project3`]. The VJP chains the projection's implicit adjoint with the
/// explicit part's VJP; the JVP applies the (linear) projection to the
/// explicit part's value and tangent.
#[derive(Debug)]
pub struct SmokeStep3 {
    advect: SmokeAdvect3,
    hand: bool,
    /// The projection (owns the solver and its iteration counters).
    pub project: Project3,
}

impl SmokeStep3 {
    /// A step of the closed cube `cfg` (see [`Project3::new`]).
    pub fn new(cfg: Smoke3d, tolerance: f64, max_iterations: usize, precond: Preconditioner) -> Self {
        Self { advect: SmokeAdvect3(cfg), hand: false, project: Project3::new(cfg, tolerance, max_iterations, precond) }
    }

    /// The same step with the hand-written adjoint of the explicit part.
    pub fn with_hand_adjoint(mut self) -> Self {
        self.hand = true;
        self
    }

    /// The grid.
    pub fn cfg(&self) -> &Smoke3d {
        &self.advect.0
    }
}

state_operator!(SmokeStep3, o => o.advect.0);

crate::problems::smoke::smoke_step_operator!(SmokeStep3, "SmokeStep3", SmokeAdvect3Hand, smoke3d::advect_buoyancy, smoke3d::advect_radius);

/// Benchmark P4 at `n³` cells and `steps` steps.
pub type P4 = crate::problems::SmokeBenchmark<SmokeStep3>;

impl P4 {
    /// The P4 problem with solves to relative tolerance 1e-8, at most 2000
    /// iterations, preconditioned by `precond` (multigrid or none).
    pub fn new(n: usize, steps: usize, precond: Preconditioner) -> Self {
        let cfg = Smoke3d::p4(n);
        Self { step: SmokeStep3::new(cfg, 1e-8, 2000, precond), steps, x0: smoke3d::p4_initial(&cfg), target: smoke3d::p4_target(&cfg) }
    }

    /// The same problem with the hand-written adjoint of the explicit part.
    pub fn with_hand_adjoint(self) -> Self {
        Self { step: self.step.with_hand_adjoint(), ..self }
    }
}
