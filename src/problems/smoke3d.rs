//! 3D buoyant smoke (benchmark P4) as operators: the explicit part of the
//! step with Enzyme-generated derivatives and the hand-written adjoint
//! beside it, the projection with its implicit adjoint, the full step, and
//! P4 itself.

use std::cell::RefCell;

use diffsim_solvers::smoke::{self, MacGrid};
use diffsim_solvers::smoke::{Preconditioner, ProjectScratch};
use diffsim_solvers::smoke3d::{self, PressureSolver3};

use super::ranges::{split_ranges, vjp_over_ranges};
use super::smoke::step_radius;

use crate::fluids::SolveLog;
use crate::op::{Forward, Jvp, Operator, Vjp, validate_forward, validate_jvp, validate_vjp};

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
/// `[s, u, v, w]`, with Enzyme-generated VJP and JVP. The forward runs its
/// slabs in parallel; the VJP is Enzyme's adjoint of [`SmokeAdvect3Slabs`]
/// over fixed slab ranges in parallel, summed in a fixed order
/// ([`slab_ranges`]): the same result for any thread count.
#[derive(Clone, Copy, Debug)]
pub struct SmokeAdvect3(pub MacGrid<3>);

state_operator!(SmokeAdvect3, o => o.0);

impl Forward for SmokeAdvect3 {
    fn forward(&self, x: &[f64], p: &[f64], y: &mut [f64]) {
        validate_forward(self, "SmokeAdvect3", x, p, y);
        closed_only(&self.0);
        smoke::advect_buoyancy_parallel(&self.0, x, y);
    }

    fn smooth_radius(&self, x: &[f64], _p: &[f64], dx: &[f64], _dp: &[f64]) -> f64 {
        step_radius(&self.0, x, dx)
    }
}

impl Vjp for SmokeAdvect3 {
    fn vjp(&self, x: &[f64], p: &[f64], dy: &mut [f64], dx: &mut [f64], dp: &mut [f64]) {
        validate_vjp(self, "SmokeAdvect3", x, p, dy, dx, dp);
        closed_only(&self.0);
        let cfg = self.0;
        let ranges = slab_ranges(cfg.n[2]);
        if ranges.len() == 1 {
            return SmokeAdvect3Slabs::new(cfg, 0..cfg.n[2]).vjp(x, p, dy, dx, dp);
        }
        // Each field's slabs are contiguous in the packed state.
        let pieces = |ks: &std::ops::Range<usize>| cfg.slab_pieces(ks.clone());
        vjp_over_ranges(&ranges, |ks| SmokeAdvect3Slabs::new(cfg, ks), pieces, x, dy, dx);
    }
}

impl Jvp for SmokeAdvect3 {
    fn jvp(&self, x: &[f64], p: &[f64], tx: &[f64], tp: &[f64], y: &mut [f64], ty: &mut [f64]) {
        validate_jvp(self, "SmokeAdvect3", x, p, tx, tp, y, ty);
        closed_only(&self.0);
        SmokeAdvect3Slabs::new(self.0, 0..self.0.n[2]).jvp(x, p, tx, tp, y, ty);
    }
}

/// P4's step is the closed box's: checked before the generated code runs.
fn closed_only(cfg: &MacGrid<3>) {
    assert!(cfg.is_closed(), "SmokeAdvect3 is P4's step of the closed box; a box with other sides takes fluids::Advect");
}

/// The fixed slab ranges [`SmokeAdvect3`]'s VJP splits `nz` slabs into
/// ([`split_ranges`]).
pub fn slab_ranges(nz: usize) -> Vec<std::ops::Range<usize>> {
    split_ranges(nz)
}

/// Slabs `k0..k1` (along z) of [`SmokeAdvect3`]'s output, packed as
/// [`MacGrid<3>::slab_lens`] says, with Enzyme-generated VJP and JVP: the
/// piece of the step whose adjoints [`SmokeAdvect3`] runs in parallel.
/// Over `0..nz` it is [`SmokeAdvect3`].
#[derive(Clone, Copy, Debug)]
pub struct SmokeAdvect3Slabs {
    cfg: MacGrid<3>,
    k0: usize,
    k1: usize,
}

impl SmokeAdvect3Slabs {
    /// Slabs `ks` of the grid `cfg`.
    ///
    /// # Panics
    /// If `ks` is empty or reaches past `nz`.
    pub fn new(cfg: MacGrid<3>, ks: std::ops::Range<usize>) -> Self {
        assert!(ks.start < ks.end && ks.end <= cfg.n[2], "SmokeAdvect3Slabs: slabs {ks:?} of {}", cfg.n[2]);
        Self { cfg, k0: ks.start, k1: ks.end }
    }
}

impl Operator for SmokeAdvect3Slabs {
    fn n_in(&self) -> usize {
        self.cfg.n_state()
    }
    fn n_out(&self) -> usize {
        self.cfg.slabs_len(self.k0..self.k1)
    }
}

/// The thin wrapper Enzyme differentiates.
fn smoke_advect3_slabs(op: &SmokeAdvect3Slabs, x: &[f64], _p: &[f64], y: &mut [f64]) {
    smoke::advect_buoyancy_slabs(&op.cfg, x, op.k0..op.k1, y)
}

fn smoke_advect3_slabs_radius(op: &SmokeAdvect3Slabs, x: &[f64], _p: &[f64], dx: &[f64], _dp: &[f64]) -> f64 {
    step_radius(&op.cfg, x, dx)
}

crate::differentiable!(SmokeAdvect3Slabs => smoke_advect3_slabs, smooth_radius = smoke_advect3_slabs_radius);

/// Steps 1–4 of P4 with the hand-written adjoint (the reference for
/// [`SmokeAdvect3`]'s generated one).
#[derive(Clone, Copy, Debug)]
pub struct SmokeAdvect3Hand(pub MacGrid<3>);

crate::problems::smoke::hand_explicit_operator!(SmokeAdvect3Hand, smoke::advect_buoyancy, smoke::advect_buoyancy_adjoint, step_radius);

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
    open: Option<[Vec<f64>; 3]>,
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
    fn with_solver(cfg: MacGrid<3>, open: Option<[Vec<f64>; 3]>, solver: PressureSolver3) -> Self {
        Self { cfg, open, solver: RefCell::new(solver), scratch: RefCell::new(ProjectScratch::new(cfg.n_s())), log: SolveLog::default() }
    }

    /// The projection of the closed box `cfg` with solid cells where
    /// `solid[c]` is true (e.g. [`smoke3d::solid_cells`]): the obstacle mask
    /// ([`smoke3d::apply_obstacle_mask3`]), the solve coupling fluid cells
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
        let fluid: Vec<f64> = solid.iter().map(|&s| if s { 0.0 } else { 1.0 }).collect();
        let open = smoke3d::open_faces(&cfg, &fluid);
        Self::with_solver(cfg, Some(open), PressureSolver3::with_obstacles(&cfg, tolerance, max_iterations, precond, fluid))
    }

    /// The obstacle mask in place (nothing without obstacles): linear and
    /// its own transpose.
    fn mask(&self, y: &mut [f64]) {
        if let (Some(open), Some(fluid)) = (&self.open, self.solver.borrow().fluid()) {
            smoke3d::apply_obstacle_mask3(&self.cfg, fluid, open, y);
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
    /// A step of the closed box `cfg` (see [`Project3::new`]).
    pub fn new(cfg: MacGrid<3>, tolerance: f64, max_iterations: usize, precond: Preconditioner) -> Self {
        Self { advect: SmokeAdvect3(cfg), hand: false, project: Project3::new(cfg, tolerance, max_iterations, precond) }
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

crate::problems::smoke::smoke_step_operator!(SmokeStep3, "SmokeStep3", SmokeAdvect3Hand, smoke::advect_buoyancy_parallel, step_radius);

/// Benchmark P4 at `n³` cells and `steps` steps.
pub type P4 = crate::problems::SmokeBenchmark<SmokeStep3>;

impl P4 {
    /// The P4 problem with solves to relative tolerance 1e-8, at most 2000
    /// iterations, preconditioned by `precond` (multigrid or none).
    pub fn new(n: usize, steps: usize, precond: Preconditioner) -> Self {
        let cfg = MacGrid::p4(n);
        Self { step: SmokeStep3::new(cfg, 1e-8, 2000, precond), steps, x0: smoke3d::p4_initial(&cfg), target: smoke3d::p4_target(&cfg) }
    }

    /// The same problem with the hand-written adjoint of the explicit part.
    pub fn with_hand_adjoint(self) -> Self {
        Self { step: self.step.with_hand_adjoint(), ..self }
    }
}
