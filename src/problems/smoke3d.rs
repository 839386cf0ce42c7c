//! 3D buoyant smoke (benchmark P4) as operators: the explicit part of the
//! step with Enzyme-generated derivatives and the hand-written adjoint
//! beside it, the projection with its implicit adjoint, the full step, and
//! P4 itself.

use std::cell::RefCell;

use diffsim_solvers::smoke::{self, MacGrid};
use diffsim_solvers::smoke::{Preconditioner, ProjectScratch};
use diffsim_solvers::smoke3d::{self, PressureSolver3};

use super::smoke::{SmokeAdvect, SmokeAdvectHand, step_radius};

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

/// The 3D pressure projection of a packed `[s, u, v, w]` state (linear):
/// `(u, v, w) −= G·A⁺·(−D·(u, v, w))` by preconditioned CG to a relative
/// tolerance on the true residual. With obstacles
/// ([`Project3::with_obstacles`]) the obstacle mask comes first and last
/// (no smoke in solid cells, no flow through their faces) and the solve
/// couples fluid cells only. The VJP is the implicit adjoint: one solve
/// with the transposed (same) matrix to the same tolerance. A solve that
/// does not converge is reported through [`Forward::take_error`].
#[derive(Debug)]
pub struct Project3 {
    cfg: MacGrid<3>,
    /// Each axis's open faces, when there are obstacles (the fluid mask is
    /// the solver's).
    open: Option<Vec<f64>>,
    solver: RefCell<PressureSolver3>,
    scratch: RefCell<ProjectScratch>,
    /// The solves' iteration counts and first failure.
    pub log: SolveLog,
}

impl Project3 {
    /// The projection of the box `cfg` (any sides), solves to relative
    /// `tolerance` in at most `max_iterations` iterations, preconditioned by
    /// multigrid (the geometric V-cycle in a closed box with two equal
    /// sides, the aggregation V-cycle in any other box), MIC(0) or nothing.
    ///
    /// # Panics
    /// For the Cholesky preconditioner (2D only).
    pub fn new(cfg: MacGrid<3>, tolerance: f64, max_iterations: usize, precond: Preconditioner) -> Self {
        Self::with_solver(cfg, None, PressureSolver3::new(&cfg, tolerance, max_iterations, precond))
    }

    /// The projection with `solver` (and the open faces when it has obstacles).
    fn with_solver(cfg: MacGrid<3>, open: Option<Vec<f64>>, solver: PressureSolver3) -> Self {
        Self { cfg, open, solver: RefCell::new(solver), scratch: RefCell::new(ProjectScratch::new(cfg.n_s())), log: SolveLog::default() }
    }

    /// The projection of the closed box `cfg` with solid cells where
    /// `solid[c]` is true (e.g. [`smoke::solid_cells`]): the obstacle mask
    /// ([`smoke::apply_obstacle_mask`]), the solve coupling fluid cells
    /// only ([`PressureSolver3::with_obstacles`]), the mask again. The
    /// result is divergence-free in every fluid cell with no flow through
    /// a solid's faces.
    ///
    /// # Panics
    /// As [`Project3::new`], if `solid` does not have a value per cell, or
    /// if every cell is solid.
    pub fn with_obstacles(cfg: MacGrid<3>, tolerance: f64, max_iterations: usize, precond: Preconditioner, solid: &[bool]) -> Self {
        assert_eq!(solid.len(), cfg.n_s(), "3D projection: one solid flag per cell");
        assert!(solid.iter().any(|&s| !s), "3D projection: every cell is solid");
        let fluid = smoke::fluid_of(solid);
        let open = smoke::open_faces(&cfg, &fluid);
        Self::with_solver(cfg, Some(open), PressureSolver3::with_obstacles(&cfg, tolerance, max_iterations, precond, fluid))
    }

    /// The obstacle mask in place (nothing without obstacles): linear and
    /// its own transpose.
    fn mask(&self, y: &mut [f64]) {
        if let (Some(open), Some(fluid)) = (&self.open, self.solver.borrow().fluid()) {
            smoke::apply_obstacle_mask(&self.cfg, fluid, open, y);
        }
    }

    /// The preconditioner of the solves.
    pub fn preconditioner(&self) -> Preconditioner {
        self.solver.borrow().preconditioner()
    }

    /// The map in place on a packed state (or tangent).
    pub fn apply(&self, y: &mut [f64]) {
        self.mask(y);
        let r = smoke3d::project(&self.cfg, y, &mut self.solver.borrow_mut(), &mut self.scratch.borrow_mut());
        self.log.record(r, false);
        self.mask(y);
    }

    /// The transposed map in place on an adjoint.
    pub fn apply_adjoint(&self, g: &mut [f64]) {
        self.mask(g);
        let r = smoke3d::project_adjoint(&self.cfg, g, &mut self.solver.borrow_mut(), &mut self.scratch.borrow_mut());
        self.log.record(r, true);
        self.mask(g);
    }
}

crate::fluids::linear_projection!(Project3, "Project3");

/// One full P4 step: [`SmokeAdvect`] (or its hand-written adjoint), then
/// [`Project3`]. The VJP chains the projection's implicit adjoint with the
/// explicit part's VJP; the JVP applies the (linear) projection to the
/// explicit part's value and tangent.
#[derive(Debug)]
pub struct SmokeStep3 {
    advect: SmokeAdvect<3>,
    hand: bool,
    /// The projection (owns the solver and its iteration counters).
    pub project: Project3,
}

impl SmokeStep3 {
    /// A step of the closed box `cfg` (see [`Project3::new`]).
    pub fn new(cfg: MacGrid<3>, tolerance: f64, max_iterations: usize, precond: Preconditioner) -> Self {
        Self { advect: SmokeAdvect(cfg), hand: false, project: Project3::new(cfg, tolerance, max_iterations, precond) }
    }

    /// The same step with the hand-written adjoint of the explicit part.
    pub fn with_hand_adjoint(mut self) -> Self {
        self.hand = true;
        self
    }

    /// The same step with solid cells where `solid[c]` is true (see
    /// [`Project3::with_obstacles`]; the solves keep this step's settings).
    ///
    /// # Panics
    /// As [`Project3::with_obstacles`].
    pub fn with_obstacles(mut self, solid: &[bool]) -> Self {
        let (stop, precond) = (self.project.solver.borrow().stop, self.project.preconditioner());
        self.project = Project3::with_obstacles(*self.cfg(), stop.tolerance, stop.max_iterations, precond, solid);
        self
    }

    /// The grid.
    pub fn cfg(&self) -> &MacGrid<3> {
        &self.advect.0
    }
}

state_operator!(SmokeStep3, o => o.advect.0);

crate::problems::smoke::smoke_step_operator!(SmokeStep3, "SmokeStep3", SmokeAdvectHand, smoke::advect_buoyancy_parallel, step_radius);

/// Benchmark P4 at `n³` cells and `steps` steps.
pub type P4 = crate::problems::SmokeBenchmark<SmokeStep3>;

impl P4 {
    /// The P4 problem with solves to relative tolerance 1e-8, at most 2000
    /// iterations, preconditioned by `precond` (multigrid or none).
    pub fn new(n: usize, steps: usize, precond: Preconditioner) -> Self {
        let cfg = MacGrid::p4(n);
        Self { step: SmokeStep3::new(cfg, 1e-8, 2000, precond), steps, x0: smoke::initial(&cfg), target: smoke::target(&cfg) }
    }

    /// The same problem with the hand-written adjoint of the explicit part.
    pub fn with_hand_adjoint(self) -> Self {
        Self { step: self.step.with_hand_adjoint(), ..self }
    }
}
