//! 2D buoyant smoke (benchmark P2) as operators: the explicit part of the
//! step (advection, walls, buoyancy) with Enzyme-generated derivatives, the
//! full step with the pressure projection's implicit adjoint chained in
//! between and an approximate local inverse (reverse-time simulation), and
//! [`SmokeRise`], P2's solver as the forward map of an inverse problem
//! (initial smoke to the smoke `T` steps later).

use diffsim_solvers::smoke::{self, MacGrid, Preconditioner};

use crate::fluids::Project;

use crate::op::{Forward, Jvp, LocalInverse, OpError, Operator, Vjp, validate_forward, validate_jvp, validate_vjp};

/// Steps 1–4 of P2 (`D = 2`) and P4 (`D = 3`) — advection, walls, buoyancy
/// — on the packed state, with Enzyme-generated VJP and JVP, in any box in
/// 2D and in the closed box in 3D.
/// The forward runs each lattice's slabs in parallel (the same values for
/// any thread count). In a closed box of 16 slabs or more (rows in 2D) the
/// VJP is Enzyme's adjoint of [`SmokeAdvectSlabs`] over two fixed slab
/// ranges in parallel, summed in a fixed order ([`super::ranges`]): the
/// same result for any thread count; otherwise the adjoint of the whole
/// step.
#[derive(Clone, Copy, Debug)]
pub struct SmokeAdvect<const D: usize>(pub MacGrid<D>);

crate::fluids::state_sizes!(SmokeAdvect, 0, |_op| 0);

impl<const D: usize> Forward for SmokeAdvect<D> {
    fn forward(&self, x: &[f64], p: &[f64], y: &mut [f64]) {
        crate::op::count::record("SmokeAdvect", crate::op::count::Method::Forward);
        validate_forward(self, "SmokeAdvect", x, p, y);
        smoke::advect_buoyancy_parallel(&self.0, x, y);
    }

    fn smooth_radius(&self, x: &[f64], _p: &[f64], dx: &[f64], _dp: &[f64]) -> f64 {
        step_radius(&self.0, x, dx)
    }
}

impl<const D: usize> Vjp for SmokeAdvect<D>
where
    SmokeAdvectWhole<D>: Vjp,
    SmokeAdvectSlabs<D>: Vjp,
{
    fn vjp(&self, x: &[f64], p: &[f64], dy: &mut [f64], dx: &mut [f64], dp: &mut [f64]) {
        let cfg = self.0;
        closed_in_3d(&cfg);
        let ranges = super::ranges::split_ranges(cfg.n[D - 1]);
        if !cfg.is_closed() || ranges.len() == 1 {
            return SmokeAdvectWhole(cfg).vjp(x, p, dy, dx, dp);
        }
        validate_vjp(self, "SmokeAdvect", x, p, dy, dx, dp);
        // Each field's slabs are contiguous in the packed state.
        let pieces = |ks: &std::ops::Range<usize>| cfg.slab_pieces(ks.clone());
        super::ranges::vjp_over_ranges(&ranges, |ks| SmokeAdvectSlabs::new(cfg, ks), pieces, x, dy, dx);
    }
}

impl<const D: usize> Jvp for SmokeAdvect<D>
where
    SmokeAdvectWhole<D>: Jvp,
{
    fn jvp(&self, x: &[f64], p: &[f64], tx: &[f64], tp: &[f64], y: &mut [f64], ty: &mut [f64]) {
        closed_in_3d(&self.0);
        SmokeAdvectWhole(self.0).jvp(x, p, tx, tp, y, ty)
    }
}

/// P4's step's derivatives are the closed box's (checked before the
/// generated code runs); a 3D box with other sides takes
/// [`crate::fluids::Advect`] and [`crate::fluids::Buoyancy`].
fn closed_in_3d<const D: usize>(cfg: &MacGrid<D>) {
    assert!(D == 2 || cfg.is_closed(), "SmokeAdvect in 3D is P4's step of the closed box; a box with other sides takes fluids::Advect and fluids::Buoyancy");
}

/// The whole of [`SmokeAdvect`], as Enzyme differentiates it.
#[derive(Clone, Copy, Debug)]
pub struct SmokeAdvectWhole<const D: usize>(MacGrid<D>);

crate::fluids::state_sizes!(SmokeAdvectWhole, 0, |_op| 0);

/// The thin wrapper Enzyme differentiates in 2D (any box).
fn smoke_advect_2d(op: &SmokeAdvectWhole<2>, x: &[f64], _p: &[f64], y: &mut [f64]) {
    smoke::advect_buoyancy(&op.0, x, y)
}

/// In 3D (the closed box): the step as all its slabs, the function
/// [`SmokeAdvectSlabs`] differentiates. (Enzyme differentiating
/// `advect_buoyancy::<3>` beside the slabs' function and the 2D ones made
/// LLVM's GVN crash at the link, docs/pitfalls.md.)
fn smoke_advect_3d(op: &SmokeAdvectWhole<3>, x: &[f64], _p: &[f64], y: &mut [f64]) {
    smoke::advect_buoyancy_slabs(&op.0, x, 0..op.0.n[2], y)
}

/// P2's and P4's step traces every field back over `cfg.dt` (1):
/// multilinear samples kink where a traced point crosses a lattice plane.
pub(crate) fn step_radius<const D: usize>(cfg: &MacGrid<D>, x: &[f64], dx: &[f64]) -> f64 {
    smoke::advect_radius(cfg, smoke::Scheme::SemiLagrangian, cfg.dt, true, true, x, dx)
}

fn smoke_advect_radius<const D: usize>(op: &SmokeAdvectWhole<D>, x: &[f64], _p: &[f64], dx: &[f64], _dp: &[f64]) -> f64 {
    step_radius(&op.0, x, dx)
}

crate::differentiable!(SmokeAdvectWhole<2> => smoke_advect_2d, smooth_radius = smoke_advect_radius::<2>);
crate::differentiable!(SmokeAdvectWhole<3> => smoke_advect_3d, smooth_radius = smoke_advect_radius::<3>);

/// Slabs `k0..k1` (layers along the slowest axis: rows in 2D) of
/// [`SmokeAdvect`]'s output in the closed box, packed as
/// [`MacGrid::slab_lens`] says, with Enzyme-generated VJP and JVP: the
/// piece of the step whose adjoints [`SmokeAdvect`] runs in parallel. Over
/// all slabs it is [`SmokeAdvect`].
#[derive(Clone, Copy, Debug)]
pub struct SmokeAdvectSlabs<const D: usize> {
    cfg: MacGrid<D>,
    k0: usize,
    k1: usize,
}

impl<const D: usize> SmokeAdvectSlabs<D> {
    /// Slabs `ks` of the closed box `cfg`.
    ///
    /// # Panics
    /// If the box is not closed, or `ks` is empty or reaches past the last
    /// slab.
    pub fn new(cfg: MacGrid<D>, ks: std::ops::Range<usize>) -> Self {
        assert!(cfg.is_closed(), "SmokeAdvectSlabs: the closed box only");
        assert!(ks.start < ks.end && ks.end <= cfg.n[D - 1], "SmokeAdvectSlabs: slabs {ks:?} of {}", cfg.n[D - 1]);
        Self { cfg, k0: ks.start, k1: ks.end }
    }
}

impl<const D: usize> Operator for SmokeAdvectSlabs<D> {
    fn n_in(&self) -> usize {
        self.cfg.n_state()
    }
    fn n_out(&self) -> usize {
        self.cfg.slabs_len(self.k0..self.k1)
    }
}

/// The thin wrapper Enzyme differentiates.
fn smoke_advect_slabs<const D: usize>(op: &SmokeAdvectSlabs<D>, x: &[f64], _p: &[f64], y: &mut [f64]) {
    smoke::advect_buoyancy_slabs(&op.cfg, x, op.k0..op.k1, y)
}

fn smoke_advect_slabs_radius<const D: usize>(op: &SmokeAdvectSlabs<D>, x: &[f64], _p: &[f64], dx: &[f64], _dp: &[f64]) -> f64 {
    step_radius(&op.cfg, x, dx)
}

crate::differentiable!(SmokeAdvectSlabs<2> => smoke_advect_slabs::<2>, smooth_radius = smoke_advect_slabs_radius::<2>);
crate::differentiable!(SmokeAdvectSlabs<3> => smoke_advect_slabs::<3>, smooth_radius = smoke_advect_slabs_radius::<3>);

/// Steps 1–4 of P2 and P4 with the hand-written adjoint (the reference for
/// [`SmokeAdvect`]'s generated one).
#[derive(Clone, Copy, Debug)]
pub struct SmokeAdvectHand<const D: usize>(pub MacGrid<D>);

crate::fluids::state_sizes!(SmokeAdvectHand, 0, |_op| 0);

impl<const D: usize> Forward for SmokeAdvectHand<D> {
    fn forward(&self, x: &[f64], p: &[f64], y: &mut [f64]) {
        validate_forward(self, "SmokeAdvectHand", x, p, y);
        smoke::advect_buoyancy(&self.0, x, y)
    }

    fn smooth_radius(&self, x: &[f64], _p: &[f64], dx: &[f64], _dp: &[f64]) -> f64 {
        step_radius(&self.0, x, dx)
    }
}

impl<const D: usize> Vjp for SmokeAdvectHand<D> {
    fn vjp(&self, x: &[f64], p: &[f64], dy: &mut [f64], dx: &mut [f64], dp: &mut [f64]) {
        validate_vjp(self, "SmokeAdvectHand", x, p, dy, dx, dp);
        smoke::advect_buoyancy_adjoint(&self.0, x, dy, dx);
        dy.fill(0.0);
    }
}

/// One full P2 or P4 step: [`SmokeAdvect`] (or its hand-written adjoint),
/// then the pressure projection ([`Project`], with the obstacle mask when
/// there are obstacles).
///
/// The VJP chains the projection's implicit adjoint (one solve with the
/// transposed matrix, to the same tolerance) with the explicit part's VJP
/// (Enzyme's, or [`SmokeAdvectHand`]); the JVP applies the (linear)
/// projection to the explicit part's value and tangent. A solve that does
/// not converge is recorded and reported through [`Forward::take_error`]
/// (rollouts turn it into an error).
#[derive(Debug)]
pub struct SmokeStep<const D: usize> {
    advect: SmokeAdvect<D>,
    /// Use the hand-written adjoint of the explicit part instead of Enzyme's.
    hand: bool,
    /// The projection (owns the solver and its iteration counters).
    pub project: Project<D>,
}

impl<const D: usize> SmokeStep<D> {
    /// A step of the box `cfg` whose solves stop at relative tolerance
    /// `tolerance` (true residual), fail after `max_iterations`, and use
    /// `precond` (see [`Project::new`]).
    ///
    /// # Panics
    /// If `cfg.boundary` does not [validate](diffsim_solvers::boundary::Boundary::validate).
    pub fn new(cfg: MacGrid<D>, tolerance: f64, max_iterations: usize, precond: Preconditioner) -> Self {
        Self { advect: SmokeAdvect(cfg), hand: false, project: Project::new(cfg, tolerance, max_iterations, precond) }
    }

    /// The same step with the hand-written adjoint of the explicit part
    /// ([`SmokeAdvectHand`]) in place of Enzyme's.
    pub fn with_hand_adjoint(mut self) -> Self {
        self.hand = true;
        self
    }

    /// The same step with solid cells where `solid[c]` is true (see
    /// [`Project::with_obstacles`]; the solves keep this step's settings).
    ///
    /// # Panics
    /// As [`Project::with_obstacles`].
    pub fn with_obstacles(mut self, solid: &[bool]) -> Self {
        let (stop, precond) = (self.project.stop(), self.project.preconditioner());
        self.project = Project::with_obstacles(*self.cfg(), stop.tolerance, stop.max_iterations, precond, solid);
        self
    }

    /// The grid.
    pub fn cfg(&self) -> &MacGrid<D> {
        &self.advect.0
    }

    /// The preconditioner of the solves.
    pub fn preconditioner(&self) -> Preconditioner {
        self.project.preconditioner()
    }
}

impl<const D: usize> Operator for SmokeStep<D> {
    fn n_in(&self) -> usize {
        self.advect.0.n_state()
    }
    fn n_out(&self) -> usize {
        self.advect.0.n_state()
    }
}

// The step's operator traits: the explicit part, then the projection; the
// VJP through the projection's implicit adjoint (in place on `dy`), then
// the explicit part's VJP; the JVP applies the (linear) projection to the
// explicit part's value and tangent alike; the smooth radius is the
// advection's (the projection after it is linear).
impl<const D: usize> Forward for SmokeStep<D> {
    fn forward(&self, x: &[f64], p: &[f64], y: &mut [f64]) {
        crate::op::validate_forward(self, "SmokeStep", x, p, y);
        smoke::advect_buoyancy_parallel(&self.advect.0, x, y);
        self.project.apply(y);
    }

    fn solve_tolerance(&self) -> f64 {
        Forward::solve_tolerance(&self.project)
    }

    fn smooth_radius(&self, x: &[f64], _p: &[f64], dx: &[f64], _dp: &[f64]) -> f64 {
        step_radius(&self.advect.0, x, dx)
    }

    fn take_error(&self) -> Option<crate::op::OpError> {
        self.project.log.take_error()
    }
}

impl<const D: usize> Vjp for SmokeStep<D>
where
    SmokeAdvect<D>: Vjp,
{
    fn vjp(&self, x: &[f64], p: &[f64], dy: &mut [f64], dx: &mut [f64], dp: &mut [f64]) {
        crate::op::validate_vjp(self, "SmokeStep", x, p, dy, dx, dp);
        self.project.apply_adjoint(dy);
        if self.hand {
            SmokeAdvectHand(self.advect.0).vjp(x, p, dy, dx, dp);
        } else {
            self.advect.vjp(x, p, dy, dx, dp);
        }
    }
}

impl<const D: usize> Jvp for SmokeStep<D>
where
    SmokeAdvect<D>: Jvp,
{
    fn jvp(&self, x: &[f64], p: &[f64], tx: &[f64], tp: &[f64], y: &mut [f64], ty: &mut [f64]) {
        crate::op::validate_jvp(self, "SmokeStep", x, p, tx, tp, y, ty);
        self.advect.jvp(x, p, tx, tp, y, ty);
        self.project.apply(y);
        self.project.apply(ty);
    }
}

impl<const D: usize> LocalInverse for SmokeStep<D> {
    /// The step run backwards in time on the perturbation, along the
    /// velocity of `x` (the one the forward step advected with): the
    /// buoyancy the step added to `dy`'s velocity taken back, every field of
    /// the perturbation carried back one unit of time
    /// ([`smoke::advect_along`] with `dt = −1`), the velocity projected so
    /// that `x + dx` stays divergence-free. Approximate: it ignores how
    /// `dx` changes the velocity that advects (the step's nonlinearity),
    /// and bilinear sampling back and forth smooths what it carries (a
    /// first-order error in the cell size);
    /// [`crate::check::local_inverse`] measures how well
    /// `f(x + dx) ≈ f(x) + dy` holds. A failed solve is recorded as in
    /// [`Forward::forward`].
    fn local_inverse(&self, x: &[f64], p: &[f64], dy: &[f64], dx: &mut [f64]) {
        validate_forward(self, "SmokeStep::local_inverse", x, p, dy);
        assert_eq!(dx.len(), self.n_in(), "SmokeStep::local_inverse: dx has the wrong length");
        let cfg = *self.cfg();
        let mut d = dy.to_vec();
        let (s, vel) = cfg.split_mut(&mut d);
        smoke::add_buoyancy(&cfg, 1, -cfg.buoyancy, s, &mut *vel[1]);
        smoke::advect_along(&cfg, -1.0, x, &d, dx);
        self.project.apply(dx);
    }
}

/// P2's solver as the forward map of an inverse problem: the initial
/// smoke (velocity at rest) to the smoke `steps` steps later,
/// `P: s_0 ↦ s_T`, both `N²` values. The smoke rises, drives the velocity
/// by its buoyancy and is carried by it: `P` is nonlinear.
///
/// - VJP: the steps' VJPs chained back over the stored trajectory
///   (Enzyme for the explicit part, the implicit adjoint of the solves).
/// - JVP: the steps' JVPs chained forward.
/// - [`LocalInverse`]: the steps' local inverses chained back over the
///   stored trajectory (reverse-time simulation of the perturbation `[dy,
///   0, 0]`), its smoke part.
///
/// A failed solve is recorded and reported by [`Forward::take_error`].
#[derive(Debug)]
pub struct SmokeRise {
    /// The step (owns the solver; not `Sync`: wrap in
    /// [`crate::op::PerThread`] for batches).
    pub step: SmokeStep<2>,
    /// Number of steps `T`.
    pub steps: usize,
}

impl SmokeRise {
    /// `steps` steps of P2 on `n × n` cells, solves to relative tolerance
    /// 1e-8 with a sparse Cholesky preconditioner (a direct solve).
    pub fn new(n: usize, steps: usize) -> Self {
        Self { step: SmokeStep::new(MacGrid::p2(n), 1e-8, 2000, Preconditioner::Cholesky), steps }
    }

    /// The packed states `x_0 = [s_0, 0, 0], …, x_T`.
    pub fn trajectory(&self, s0: &[f64]) -> Vec<Vec<f64>> {
        let cfg = self.step.cfg();
        let mut x = vec![0.0; cfg.n_state()];
        x[..cfg.n_s()].copy_from_slice(s0);
        let mut states = Vec::with_capacity(self.steps + 1);
        for _ in 0..self.steps {
            let mut y = vec![0.0; x.len()];
            self.step.forward(&x, &[], &mut y);
            states.push(std::mem::replace(&mut x, y));
        }
        states.push(x);
        states
    }

    /// The packed state `[s_0, 0, 0]` and tangent `[t_0, 0, 0]` carried
    /// through the steps by their JVPs; `visit(x_t, t_t)` sees each pair
    /// before its step. Returns `(x_T, t_T)`.
    fn carry(&self, s0: &[f64], t0: &[f64], mut visit: impl FnMut(&[f64], &[f64])) -> (Vec<f64>, Vec<f64>) {
        let n = self.step.cfg().n_state();
        let (mut xc, mut tc) = (vec![0.0; n], vec![0.0; n]);
        xc[..s0.len()].copy_from_slice(s0);
        tc[..t0.len()].copy_from_slice(t0);
        let (mut yn, mut tn) = (vec![0.0; n], vec![0.0; n]);
        for _ in 0..self.steps {
            visit(&xc, &tc);
            self.step.jvp(&xc, &[], &tc, &[], &mut yn, &mut tn);
            std::mem::swap(&mut xc, &mut yn);
            std::mem::swap(&mut tc, &mut tn);
        }
        (xc, tc)
    }
}

impl Operator for SmokeRise {
    fn n_in(&self) -> usize {
        self.step.cfg().n_s()
    }
    fn n_out(&self) -> usize {
        self.step.cfg().n_s()
    }
}

impl Forward for SmokeRise {
    fn forward(&self, x: &[f64], p: &[f64], y: &mut [f64]) {
        validate_forward(self, "SmokeRise", x, p, y);
        let states = self.trajectory(x);
        y.copy_from_slice(&states[self.steps][..y.len()]);
    }

    fn smooth_radius(&self, x: &[f64], _p: &[f64], dx: &[f64], _dp: &[f64]) -> f64 {
        // The smallest radius of the steps along the tangent carried forward.
        let mut radius = f64::INFINITY;
        self.carry(x, dx, |xc, tc| radius = radius.min(self.step.smooth_radius(xc, &[], tc, &[])));
        radius
    }

    fn take_error(&self) -> Option<OpError> {
        self.step.take_error()
    }
}

impl Vjp for SmokeRise {
    fn vjp(&self, x: &[f64], p: &[f64], dy: &mut [f64], dx: &mut [f64], dp: &mut [f64]) {
        validate_vjp(self, "SmokeRise", x, p, dy, dx, dp);
        let states = self.trajectory(x);
        let n = self.step.cfg().n_state();
        let mut g = vec![0.0; n];
        g[..dy.len()].copy_from_slice(dy);
        for t in (0..self.steps).rev() {
            let mut gx = vec![0.0; n];
            self.step.vjp(&states[t], &[], &mut g, &mut gx, &mut []);
            g = gx;
        }
        for (d, v) in dx.iter_mut().zip(&g) {
            *d += v;
        }
        dy.fill(0.0);
    }
}

impl Jvp for SmokeRise {
    fn jvp(&self, x: &[f64], p: &[f64], tx: &[f64], tp: &[f64], y: &mut [f64], ty: &mut [f64]) {
        validate_jvp(self, "SmokeRise", x, p, tx, tp, y, ty);
        let (xc, tc) = self.carry(x, tx, |_, _| {});
        y.copy_from_slice(&xc[..y.len()]);
        ty.copy_from_slice(&tc[..ty.len()]);
    }
}

impl LocalInverse for SmokeRise {
    fn local_inverse(&self, x: &[f64], p: &[f64], dy: &[f64], dx: &mut [f64]) {
        validate_forward(self, "SmokeRise::local_inverse", x, p, dy);
        assert_eq!(dx.len(), self.n_in(), "SmokeRise::local_inverse: dx has the wrong length");
        let states = self.trajectory(x);
        let n = self.step.cfg().n_state();
        let mut d = vec![0.0; n];
        d[..dy.len()].copy_from_slice(dy);
        let mut back = vec![0.0; n];
        for t in (0..self.steps).rev() {
            self.step.local_inverse(&states[t], &[], &d, &mut back);
            std::mem::swap(&mut d, &mut back);
        }
        dx.copy_from_slice(&d[..dx.len()]);
    }
}

/// Benchmark P2 at `n × n` cells and `steps` steps.
pub type P2 = crate::problems::SmokeBenchmark<SmokeStep<2>>;

/// Benchmark P4 at `n³` cells and `steps` steps.
pub type P4 = crate::problems::SmokeBenchmark<SmokeStep<3>>;

impl<const D: usize> crate::problems::SmokeBenchmark<SmokeStep<D>> {
    /// The smoke benchmark on the box `cfg` (P2's or P4's): `steps` steps
    /// from [`smoke::initial`] towards [`smoke::target`], solves to relative
    /// tolerance 1e-8, at most 2000 iterations, preconditioned by `precond`.
    pub fn on(cfg: MacGrid<D>, steps: usize, precond: Preconditioner) -> Self {
        Self { step: SmokeStep::new(cfg, 1e-8, 2000, precond), steps, x0: smoke::initial(&cfg), target: smoke::target(&cfg) }
    }

    /// The same problem with the hand-written adjoint of the explicit part.
    pub fn with_hand_adjoint(self) -> Self {
        Self { step: self.step.with_hand_adjoint(), ..self }
    }
}

impl P2 {
    /// The P2 problem ([`MacGrid::p2`]).
    pub fn new(n: usize, steps: usize, precond: Preconditioner) -> Self {
        Self::on(MacGrid::p2(n), steps, precond)
    }
}

impl P4 {
    /// The P4 problem ([`MacGrid::p4`]).
    pub fn new(n: usize, steps: usize, precond: Preconditioner) -> Self {
        Self::on(MacGrid::p4(n), steps, precond)
    }
}
