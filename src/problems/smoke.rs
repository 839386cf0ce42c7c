//! 2D buoyant smoke (benchmark P2) as operators: the explicit part of the
//! step (advection, walls, buoyancy) with Enzyme-generated derivatives, and
//! the full step with the pressure projection's implicit adjoint chained in
//! between.

use diffsim_solvers::smoke::{self, Preconditioner, Smoke2d};

use crate::fluids::Project;

use crate::op::{Forward, Jvp, OpError, Operator, Vjp, validate_forward, validate_jvp, validate_vjp};
use crate::rollout::{Checkpointing, Gradient, Rollout, RolloutError, Workspace};

/// Steps 1–4 of P2 (advection, walls, buoyancy) on the packed state
/// `[s, u, v]`, with Enzyme-generated VJP and JVP.
#[derive(Clone, Copy, Debug)]
pub struct SmokeAdvect(pub Smoke2d);

impl Operator for SmokeAdvect {
    fn n_in(&self) -> usize {
        self.0.n_state()
    }
    fn n_out(&self) -> usize {
        self.0.n_state()
    }
}

/// The thin wrapper Enzyme differentiates.
fn smoke_advect(op: &SmokeAdvect, x: &[f64], _p: &[f64], y: &mut [f64]) {
    smoke::advect_buoyancy(&op.0, x, y)
}

/// P2's step traces every field back by one unit of time: bilinear
/// samples kink where a traced point crosses a lattice line.
fn p2_radius(cfg: &Smoke2d, x: &[f64], dx: &[f64]) -> f64 {
    smoke::advect_radius(cfg, smoke::Scheme::SemiLagrangian, 1.0, true, true, x, dx)
}

fn smoke_advect_radius(op: &SmokeAdvect, x: &[f64], _p: &[f64], dx: &[f64], _dp: &[f64]) -> f64 {
    p2_radius(&op.0, x, dx)
}

crate::differentiable!(SmokeAdvect => smoke_advect, smooth_radius = smoke_advect_radius);

/// Steps 1–4 of P2 with the hand-written adjoint (the reference for
/// [`SmokeAdvect`]'s generated one).
#[derive(Clone, Copy, Debug)]
pub struct SmokeAdvectHand(pub Smoke2d);

impl Operator for SmokeAdvectHand {
    fn n_in(&self) -> usize {
        self.0.n_state()
    }
    fn n_out(&self) -> usize {
        self.0.n_state()
    }
}

impl Forward for SmokeAdvectHand {
    fn forward(&self, x: &[f64], p: &[f64], y: &mut [f64]) {
        validate_forward(self, "SmokeAdvectHand", x, p, y);
        smoke::advect_buoyancy(&self.0, x, y)
    }

    fn smooth_radius(&self, x: &[f64], _p: &[f64], dx: &[f64], _dp: &[f64]) -> f64 {
        p2_radius(&self.0, x, dx)
    }
}

impl Vjp for SmokeAdvectHand {
    fn vjp(&self, x: &[f64], p: &[f64], dy: &mut [f64], dx: &mut [f64], dp: &mut [f64]) {
        validate_vjp(self, "SmokeAdvectHand", x, p, dy, dx, dp);
        smoke::advect_buoyancy_adjoint(&self.0, x, dy, dx);
        dy.fill(0.0);
    }
}

/// One full P2 step: [`SmokeAdvect`], then the pressure projection
/// ([`Project`], with the obstacle mask when there are obstacles).
///
/// The VJP chains the projection's implicit adjoint (one solve with the
/// transposed matrix, to the same tolerance) with Enzyme's VJP of the
/// explicit part. A solve that does not converge is recorded and reported
/// through [`Forward::take_error`] (rollouts turn it into an error).
#[derive(Debug)]
pub struct SmokeStep {
    advect: SmokeAdvect,
    /// Use the hand-written adjoint of the explicit part instead of Enzyme's.
    hand: bool,
    /// The projection (owns the solver and its iteration counters).
    pub project: Project,
}

impl SmokeStep {
    /// A step of the P2 box `cfg` whose solves stop at relative tolerance
    /// `tolerance` (true residual), fail after `max_iterations`, and use
    /// `precond` (see [`Project::new`]).
    ///
    /// # Panics
    /// If `cfg.boundary` does not [validate](diffsim_solvers::boundary::Boundary::validate).
    pub fn new(cfg: Smoke2d, tolerance: f64, max_iterations: usize, precond: Preconditioner) -> Self {
        Self { advect: SmokeAdvect(cfg), hand: false, project: Project::new(cfg, tolerance, max_iterations, precond) }
    }

    /// The same step with the hand-written adjoint of the explicit part
    /// ([`SmokeAdvectHand`]) in place of Enzyme's.
    pub fn with_hand_adjoint(mut self) -> Self {
        self.hand = true;
        self
    }

    /// A step of the box `cfg` with solid cells where `solid[c]` is true
    /// (see [`Project::with_obstacles`]).
    pub fn with_obstacles(cfg: Smoke2d, tolerance: f64, max_iterations: usize, solid: &[bool]) -> Self {
        Self { advect: SmokeAdvect(cfg), hand: false, project: Project::with_obstacles(cfg, tolerance, max_iterations, solid) }
    }

    /// The grid.
    pub fn cfg(&self) -> &Smoke2d {
        &self.advect.0
    }

    /// The preconditioner of the solves.
    pub fn preconditioner(&self) -> Preconditioner {
        self.project.preconditioner()
    }
}

impl Operator for SmokeStep {
    fn n_in(&self) -> usize {
        self.advect.0.n_state()
    }
    fn n_out(&self) -> usize {
        self.advect.0.n_state()
    }
}

impl Forward for SmokeStep {
    fn forward(&self, x: &[f64], p: &[f64], y: &mut [f64]) {
        validate_forward(self, "SmokeStep", x, p, y);
        smoke::advect_buoyancy(&self.advect.0, x, y);
        self.project.apply(y);
    }

    /// The advection's (the projection after it is linear).
    fn smooth_radius(&self, x: &[f64], _p: &[f64], dx: &[f64], _dp: &[f64]) -> f64 {
        p2_radius(&self.advect.0, x, dx)
    }

    fn take_error(&self) -> Option<OpError> {
        self.project.take_error()
    }
}

impl Vjp for SmokeStep {
    fn vjp(&self, x: &[f64], p: &[f64], dy: &mut [f64], dx: &mut [f64], dp: &mut [f64]) {
        validate_vjp(self, "SmokeStep", x, p, dy, dx, dp);
        // Through the projection (in place on dy), then the explicit part.
        self.project.apply_adjoint(dy);
        if self.hand {
            SmokeAdvectHand(self.advect.0).vjp(x, p, dy, dx, dp);
        } else {
            self.advect.vjp(x, p, dy, dx, dp);
        }
    }
}

impl Jvp for SmokeStep {
    /// The explicit part's JVP, then the projection (a linear map) applied to
    /// the state and to the tangent alike.
    fn jvp(&self, x: &[f64], p: &[f64], tx: &[f64], tp: &[f64], y: &mut [f64], ty: &mut [f64]) {
        validate_jvp(self, "SmokeStep", x, p, tx, tp, y, ty);
        self.advect.jvp(x, p, tx, tp, y, ty);
        self.project.apply(y);
        self.project.apply(ty);
    }
}

/// Benchmark P2 at `n × n` cells and `steps` steps.
#[derive(Debug)]
pub struct P2 {
    /// The step operator (owns the solver and its iteration counters).
    pub step: SmokeStep,
    /// Number of steps `T`.
    pub steps: usize,
    /// Packed initial state `[s, u, v]`.
    pub x0: Vec<f64>,
    /// Target smoke.
    pub target: Vec<f64>,
}

impl P2 {
    /// The P2 problem with solves to relative tolerance 1e-8, at most 2000
    /// iterations, preconditioned by `precond`.
    pub fn new(n: usize, steps: usize, precond: Preconditioner) -> Self {
        let cfg = Smoke2d::p2(n);
        Self { step: SmokeStep::new(cfg, 1e-8, 2000, precond), steps, x0: smoke::p2_initial(&cfg), target: smoke::p2_target(&cfg) }
    }

    /// The same problem with the hand-written adjoint of the explicit part.
    pub fn with_hand_adjoint(self) -> Self {
        Self { step: self.step.with_hand_adjoint(), ..self }
    }

    /// The loss `L = ½·Σ (s_T − s*)²` and its gradient.
    pub fn loss(&self) -> impl Fn(&[f64], &mut [f64]) -> f64 + '_ {
        |x, g| smoke::p2_loss(self.step.cfg(), x, &self.target, g)
    }

    /// `L` by the forward rollout alone.
    pub fn value(&self) -> Result<f64, RolloutError> {
        Rollout::new(&self.step, &[], self.steps)?.loss(&self.x0, &self.loss())
    }

    /// `L` and its gradient with respect to the packed initial state
    /// (Enzyme for the explicit part, implicit adjoint for the solves).
    pub fn grad_in(&self, ws: &mut Workspace, mode: Checkpointing) -> Result<Gradient, RolloutError> {
        Rollout::new(&self.step, &[], self.steps)?.value_and_grad_in(ws, &self.x0, &self.loss(), mode)
    }

    /// The gradient with respect to the initial smoke only (`N²` values).
    pub fn smoke_gradient<'g>(&self, g: &'g Gradient) -> &'g [f64] {
        &g.dx0[..self.step.cfg().n_s()]
    }
}
