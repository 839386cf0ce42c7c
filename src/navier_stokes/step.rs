//! [`NavierStokes`]: incompressible Navier–Stokes on a box with any sides
//! (periodic, free-slip, no-slip, inflow, outflow) and obstacles, in 2D and
//! 3D, as an operator with its gradient with respect to the velocity, the
//! viscosity, the time step, the inflow profile and a body force.
//!
//! One sub-step of `s = dt/k` is six maps, each with its own derivatives:
//!
//! | map | how | derivatives |
//! |---|---|---|
//! | advection of the velocity by itself over `s` | [`AdvectVelocity`] ([`smoke::advect_velocity`]) | Enzyme |
//! | the sides | walls set, periodic copies refreshed, inflow faces set to the profile | by hand (linear in the velocity and the profile) |
//! | viscosity `κ = ν·s/h²` | each component on its own faces: [`DiffuseExplicit`] or [`DiffuseImplicit`] | Enzyme / the implicit rule |
//! | body force | `u += s·f` (before the viscosity when it is implicit) | by hand (bilinear) |
//! | the sides | as above | by hand |
//! | projection | [`Project`] (CG, or FFT when every side is periodic) | the transposed solve |

use std::cell::Cell;
use std::fmt;

use diffsim_solvers::boundary::BoundaryError;
use diffsim_solvers::diffusion::Grid;
use diffsim_solvers::mac::periodic::{COURANT_LIMIT, refresh_periodic_copies, viscous_limit};
use diffsim_solvers::smoke::{self, InflowFace, MacGrid, Preconditioner, Scheme};

use super::MAX_SUBSTEPS;
use super::drag::{SurfaceDrag, add};
use crate::fluids::{DiffuseExplicit, DiffuseImplicit, Project};
use crate::op::{Forward, Jvp, OpError, OpMessage, Operator, Vjp, validate_forward, validate_jvp, validate_vjp};
use diffsim_solvers::cg::dot;

/// How [`NavierStokes`] steps the viscosity.
#[derive(Clone, Copy, Debug, PartialEq)]
pub enum Viscosity {
    /// Forward Euler: its stability limit `κ = ν·s/h² ≤ 0.9/(2D)` enters the
    /// choice of sub-steps.
    Explicit,
    /// Backward Euler: each component's `(I + κ·A)·u' = u` solved by
    /// conjugate gradients to the relative `tolerance` in at most
    /// `max_iterations` (its gradient by the implicit rule); no limit on `κ`.
    Implicit {
        /// Relative tolerance of each solve.
        tolerance: f64,
        /// More iterations than this is an error.
        max_iterations: usize,
    },
}

/// The advection of one sub-step on any box: the packed velocity advected
/// by itself over the time `p[0]` ([`smoke::advect_velocity`], the fluid
/// operators' advection; cells of size `h`), the periodic copies refreshed
/// (the other faces the sides set are left to the map that follows). Derivatives by Enzyme, with respect to the
/// velocity and the time step. On a box periodic on every axis below a
/// cell per call (every sub-step of [`NavierStokes`] is) and without
/// MacCormack's limiter, the traces shorter than a cell
/// ([`smoke::advect_velocity_near`]: the same values to rounding, several
/// times faster), differentiated by Enzyme as a function of their own;
/// [`smoke::advect_velocity_near_adjoint`] is its hand-written adjoint,
/// the reference in the tests.
#[derive(Clone, Copy, Debug)]
pub struct AdvectVelocity<const D: usize> {
    /// The box and its sides.
    pub grid: MacGrid<D>,
    /// Cell size (every axis).
    pub h: f64,
    /// Advection scheme.
    pub scheme: Scheme,
}

impl<const D: usize> AdvectVelocity<D> {
    /// Whether the call at `(x, p)` takes the traces shorter than a cell.
    fn near(&self, x: &[f64], p: &[f64]) -> bool {
        smoke::near_applies(&self.grid, self.scheme, p[0] / self.h, x)
    }
}

/// [`AdvectVelocity`] by the general traces.
#[derive(Clone, Copy, Debug)]
struct AdvectTraced<const D: usize>(AdvectVelocity<D>);

/// [`AdvectVelocity`] by the traces shorter than a cell.
#[derive(Clone, Copy, Debug)]
struct AdvectNear<const D: usize>(AdvectVelocity<D>);

macro_rules! advect_sizes {
    ($($ty:ident),*) => {$(
        impl<const D: usize> Operator for $ty<D> {
            fn n_in(&self) -> usize {
                self.0.n_in()
            }
            fn n_out(&self) -> usize {
                self.0.n_out()
            }
            fn n_params(&self) -> usize {
                1
            }
        }
    )*};
}
advect_sizes!(AdvectTraced, AdvectNear);

impl<const D: usize> Operator for AdvectVelocity<D> {
    fn n_in(&self) -> usize {
        self.grid.n_vel()
    }
    fn n_out(&self) -> usize {
        self.grid.n_vel()
    }
    fn n_params(&self) -> usize {
        1
    }
}

fn advect_traced<const D: usize>(op: &AdvectTraced<D>, x: &[f64], p: &[f64], y: &mut [f64], scratch: &mut [f64]) {
    let op = &op.0;
    smoke::advect_velocity(&op.grid, op.scheme, p[0] / op.h, x, y, scratch);
    refresh_periodic_copies(&op.grid, y);
}

fn advect_traced_scratch<const D: usize>(op: &AdvectTraced<D>) -> usize {
    smoke::advect_velocity_scratch_len(&op.0.grid, op.0.scheme)
}

fn advect_near<const D: usize>(op: &AdvectNear<D>, x: &[f64], p: &[f64], y: &mut [f64], scratch: &mut [f64]) {
    let op = &op.0;
    smoke::advect_velocity_near(&op.grid, op.scheme, p[0] / op.h, x, y, scratch);
}

fn advect_near_scratch<const D: usize>(op: &AdvectNear<D>) -> usize {
    smoke::advect_velocity_near_scratch_len(&op.0.grid)
}

fn advect_velocity_radius<const D: usize>(op: &AdvectVelocity<D>, x: &[f64], p: &[f64], dx: &[f64], dp: &[f64]) -> f64 {
    smoke::advect_velocity_radius(&op.grid, op.scheme, p[0] / op.h, dp[0] / op.h, x, dx)
}

fn advect_traced_radius<const D: usize>(op: &AdvectTraced<D>, x: &[f64], p: &[f64], dx: &[f64], dp: &[f64]) -> f64 {
    advect_velocity_radius(&op.0, x, p, dx, dp)
}

fn advect_near_radius<const D: usize>(op: &AdvectNear<D>, x: &[f64], p: &[f64], dx: &[f64], dp: &[f64]) -> f64 {
    advect_velocity_radius(&op.0, x, p, dx, dp)
}

crate::differentiable!(AdvectTraced<2> => advect_traced::<2>, smooth_radius = advect_traced_radius::<2>, scratch = advect_traced_scratch::<2>);
crate::differentiable!(AdvectTraced<3> => advect_traced::<3>, smooth_radius = advect_traced_radius::<3>, scratch = advect_traced_scratch::<3>);
crate::differentiable!(AdvectNear<2> => advect_near::<2>, smooth_radius = advect_near_radius::<2>, scratch = advect_near_scratch::<2>);
crate::differentiable!(AdvectNear<3> => advect_near::<3>, smooth_radius = advect_near_radius::<3>, scratch = advect_near_scratch::<3>);

impl<const D: usize> Forward for AdvectVelocity<D>
where
    AdvectTraced<D>: Forward,
    AdvectNear<D>: Forward,
{
    fn forward(&self, x: &[f64], p: &[f64], y: &mut [f64]) {
        validate_forward(self, "AdvectVelocity", x, p, y);
        if self.near(x, p) {
            // The generated code's primal, compiled for wider vectors (the
            // same values bit for bit).
            crate::op::count::record("AdvectNear", crate::op::count::Method::Forward);
            let (dt, len) = (p[0] / self.h, smoke::advect_velocity_near_scratch_len(&self.grid));
            crate::op::with_scratch(len, |s| smoke::advect_velocity_near_widest(&self.grid, self.scheme, dt, x, y, s))
        } else {
            AdvectTraced(*self).forward(x, p, y)
        }
    }

    fn smooth_radius(&self, x: &[f64], p: &[f64], dx: &[f64], dp: &[f64]) -> f64 {
        advect_velocity_radius(self, x, p, dx, dp)
    }
}

impl<const D: usize> Vjp for AdvectVelocity<D>
where
    AdvectTraced<D>: Vjp,
    AdvectNear<D>: Vjp,
{
    fn vjp(&self, x: &[f64], p: &[f64], dy: &mut [f64], dx: &mut [f64], dp: &mut [f64]) {
        validate_vjp(self, "AdvectVelocity", x, p, dy, dx, dp);
        if self.near(x, p) { AdvectNear(*self).vjp(x, p, dy, dx, dp) } else { AdvectTraced(*self).vjp(x, p, dy, dx, dp) }
    }
}

impl<const D: usize> Jvp for AdvectVelocity<D>
where
    AdvectTraced<D>: Jvp,
    AdvectNear<D>: Jvp,
{
    fn jvp(&self, x: &[f64], p: &[f64], tx: &[f64], tp: &[f64], y: &mut [f64], ty: &mut [f64]) {
        validate_jvp(self, "AdvectVelocity", x, p, tx, tp, y, ty);
        if self.near(x, p) { AdvectNear(*self).jvp(x, p, tx, tp, y, ty) } else { AdvectTraced(*self).jvp(x, p, tx, tp, y, ty) }
    }
}

/// One component's viscosity: an explicit or implicit diffusion operator on
/// its faces (`p = [κ]`).
trait ViscousPart: Forward + Vjp + Jvp + Send + fmt::Debug {}
impl<T: Forward + Vjp + Jvp + Send + fmt::Debug> ViscousPart for T {}

/// One step of incompressible Navier–Stokes on a box of `D` axes with any
/// sides and obstacles: `x` the packed velocity (each component on its
/// faces, a periodic axis's copies included), `p = [ν, dt, q…, f…]` with
/// `q` the inward speed on each face of the inflow sides (the order of
/// [`NavierStokes::inflow_faces`]; none without inflow) and, for a
/// [forced](NavierStokes::forced) step, `f` a body force per face (the
/// packed velocity's layout). [`NavierStokes::params`] gives the box's own
/// profile.
///
/// The sides, as [`diffsim_solvers::boundary::Side`] says: closed (free
/// slip: the viscosity sees no gradient of the tangential velocity across
/// the wall), no-slip (the tangential velocity zero on the wall), periodic,
/// inflow (the profile on the side's faces; the tangential velocity sees no
/// gradient across it) and outflow (zero gradient of the velocity across
/// it, zero pressure beyond). Obstacles ([`NavierStokes::with_obstacles`])
/// take no flow through their faces (the projection's mask); the
/// viscosity sees the zero velocity of the faces inside them.
///
/// A call takes `dt` in `k` equal sub-steps (the fewest that keep the
/// Courant number `max|u|·s/h` within 0.9 and, with explicit viscosity, `κ
/// = ν·s/h²` within `0.9/(2D)`), `k` chosen from `x` and `p` at the start
/// of the call. It refuses, leaving the velocity as it was and reporting
/// why ([`Forward::take_error`]): `ν` or `dt` negative or not finite, a
/// profile or force value not finite ([`OpError::Input`]), a velocity not
/// finite or needing more than [`MAX_SUBSTEPS`] sub-steps
/// ([`OpError::Unstable`]); a solve that does not converge is reported as
/// the solve's error.
#[derive(Debug)]
pub struct NavierStokes<const D: usize> {
    /// The box with its sides as declared (inflow with its profile).
    grid: MacGrid<D>,
    /// The same box with the inflow sides closed: the map of the sides
    /// before the profile is added.
    walls: MacGrid<D>,
    h: f64,
    scheme: Scheme,
    viscosity: Viscosity,
    /// Per component: its faces in the packed velocity and its viscosity.
    parts: Vec<(std::ops::Range<usize>, Box<dyn ViscousPart>)>,
    inflow: Vec<InflowFace>,
    forced: bool,
    projection: Project<D>,
    /// The solid cells, when there are obstacles.
    solid: Option<Vec<bool>>,
    /// The drag carried in the state ([`NavierStokes::with_drag`]).
    drag: Option<SurfaceDrag>,
    error: Cell<Option<OpError>>,
}

/// An input error of a call (short: [`OpMessage`] keeps 63 bytes).
fn input(text: String) -> OpError {
    OpError::Input(OpMessage::new(&format!("NavierStokes: {text}")))
}

/// Why a [`NavierStokes`] step cannot be built.
#[derive(Clone, Debug, PartialEq, thiserror::Error)]
pub enum NavierStokesError {
    /// The sides do not validate.
    #[error("NavierStokes: the box's sides: {0}")]
    Sides(BoundaryError),
    /// The cell size is not positive and finite.
    #[error("NavierStokes: the cell size must be positive and finite, got {0}")]
    CellSize(f64),
    /// An axis has fewer than 2 cells.
    #[error("NavierStokes: every axis needs at least 2 cells, got {0:?}")]
    TooFewCells(Vec<usize>),
    /// The obstacles' flags are not one per cell.
    #[error("NavierStokes: {given} solid flags for a box of {cells} cells")]
    SolidFlags {
        /// Flags given.
        given: usize,
        /// Cells of the box.
        cells: usize,
    },
    /// Every cell is solid.
    #[error("NavierStokes: every cell is solid")]
    AllSolid,
    /// The drag asked of a box without obstacles.
    #[error("NavierStokes: the drag needs obstacles (with_obstacles first)")]
    NoObstacles,
    /// An obstacle of the drag touches a closed side along x.
    #[error(
        "NavierStokes: the drag's pressure term needs the pressure's level in the fluid region of cell {cell} (an obstacle against a closed side along x?)"
    )]
    DragLevel {
        /// A cell of the region.
        cell: usize,
    },
}

impl<const D: usize> NavierStokes<D> {
    /// The step on the box `grid` (its cells and sides; its own `dt` and
    /// viscosity unused: they are parameters) with cells of size `h`,
    /// advecting by `scheme`, explicit viscosity, the projection by
    /// multigrid-preconditioned CG to a relative residual of `1e-10` (by FFT
    /// when every side is periodic).
    ///
    /// # Errors
    /// If the sides do not validate (a periodic side needs its opposite
    /// periodic; inflow needs an outflow side), `h` is not positive and
    /// finite, or an axis has fewer than 2 cells.
    pub fn new(grid: MacGrid<D>, h: f64, scheme: Scheme) -> Result<Self, NavierStokesError> {
        grid.boundary.validate().map_err(NavierStokesError::Sides)?;
        if !(h.is_finite() && h > 0.0) {
            return Err(NavierStokesError::CellSize(h));
        }
        if grid.min_cells() < 2 {
            return Err(NavierStokesError::TooFewCells(grid.n.to_vec()));
        }
        let walls = grid.with_boundary(grid.boundary.homogeneous());
        let mut op = Self {
            grid,
            walls,
            h,
            scheme,
            viscosity: Viscosity::Explicit,
            parts: Vec::new(),
            inflow: smoke::inflow_faces(&grid),
            forced: false,
            projection: Project::new(grid, 1e-10, 1000, Preconditioner::Multigrid),
            solid: None,
            drag: None,
            error: Cell::new(None),
        };
        op.set_viscosity(Viscosity::Explicit);
        Ok(op)
    }

    /// The step with its viscosity stepped as `viscosity` says.
    pub fn with_viscosity(mut self, viscosity: Viscosity) -> Self {
        self.set_viscosity(viscosity);
        self
    }

    fn set_viscosity(&mut self, viscosity: Viscosity) {
        let lattices = Grid::of_state(&self.grid);
        self.parts = (0..D)
            .map(|a| {
                let lattice = lattices[a + 1];
                let part: Box<dyn ViscousPart> = match viscosity {
                    Viscosity::Explicit => Box::new(DiffuseExplicit::on(lattice)),
                    Viscosity::Implicit { tolerance, max_iterations } => Box::new(DiffuseImplicit::on(lattice, tolerance, max_iterations)),
                };
                // The part's samples: the component's faces up to a copy
                // layer of a periodic last axis (refreshed by the sides).
                let start = self.grid.face_range(a).start;
                (start..start + part.n_in(), part)
            })
            .collect();
        self.viscosity = viscosity;
    }

    /// The step under a body force: `f`, one value per face in the packed
    /// velocity's layout, follows `[ν, dt, q…]` in the parameters; added over
    /// each sub-step on the viscous step's right-hand side (`u += s·f` after
    /// explicit viscosity, before the implicit solve; the faces the sides
    /// set keep their value). The gradient reaches `f` too.
    pub fn forced(self) -> Self {
        Self { forced: true, ..self }
    }

    /// The step with its projection solved to the relative `tolerance` in
    /// at most `max_iterations` CG iterations preconditioned by `precond`
    /// (unused by the FFT of a box periodic on every axis).
    pub fn with_projection(mut self, tolerance: f64, max_iterations: usize, precond: Preconditioner) -> Self {
        self.projection = Project::new(self.grid, tolerance, max_iterations, precond);
        self
    }

    /// The step with solid cells where `solid[c]` is true (one flag per
    /// cell, e.g. from [`smoke::solid_cells`]): no flow through their faces.
    ///
    /// # Errors
    /// If `solid` does not have one flag per cell or every cell is solid.
    pub fn with_obstacles(mut self, solid: &[bool]) -> Result<Self, NavierStokesError> {
        if solid.len() != self.grid.n_s() {
            return Err(NavierStokesError::SolidFlags { given: solid.len(), cells: self.grid.n_s() });
        }
        if solid.iter().all(|&s| s) {
            return Err(NavierStokesError::AllSolid);
        }
        // The projection's own settings, now with the solids.
        let (stop, precond) = (self.projection.stop(), self.projection.preconditioner());
        self.projection = Project::with_obstacles(self.grid, stop.tolerance, stop.max_iterations, precond, solid);
        self.solid = Some(solid.to_vec());
        if self.drag.is_some() {
            self.drag = Some(SurfaceDrag::new(&self.grid, self.h, solid)?);
        }
        Ok(self)
    }

    /// The step carrying the force on the obstacles along x in the state
    /// ([`SurfaceDrag`], Mosaic's surface sums): the input and output gain
    /// two numbers after the velocity, `[I, A]`, to which each call adds
    /// the time integral of the pressure force over `dt` and the shear sum
    /// `Σ σ·ū` of the velocity it returns. Over `m` steps of `dt` the mean
    /// drag is `ΔI/(m·dt) − ν·ΔA/m`. The gradient flows through both.
    ///
    /// # Errors
    /// Without obstacles, or if an obstacle touches a closed side along x
    /// ([`NavierStokesError::DragLevel`]).
    pub fn with_drag(mut self) -> Result<Self, NavierStokesError> {
        let solid = self.solid.as_deref().ok_or(NavierStokesError::NoObstacles)?;
        self.drag = Some(SurfaceDrag::new(&self.grid, self.h, solid)?);
        Ok(self)
    }

    /// The drag's weights, when the state carries it.
    pub fn drag(&self) -> Option<&SurfaceDrag> {
        self.drag.as_ref()
    }

    /// The box and its sides.
    pub fn grid(&self) -> &MacGrid<D> {
        &self.grid
    }

    /// The cell size.
    pub fn h(&self) -> f64 {
        self.h
    }

    /// The faces the inflow sides set, in the order of their speeds in the
    /// parameters.
    pub fn inflow_faces(&self) -> &[InflowFace] {
        &self.inflow
    }

    /// The parameters `[ν, dt, q…]` with `q` the inflow sides' own profiles
    /// (and, for a forced step, a zero force).
    pub fn params(&self, nu: f64, dt: f64) -> Vec<f64> {
        let mut p = vec![nu, dt];
        p.extend(self.inflow.iter().map(|f| f.speed));
        if self.forced {
            p.resize(p.len() + self.grid.n_vel(), 0.0);
        }
        p
    }

    /// The projection (its solves' iteration counts in [`Project::log`]).
    pub fn projection(&self) -> &Project<D> {
        &self.projection
    }

    /// The inflow speeds `q` and the force `f` in the parameters.
    fn split_params<'a>(&self, p: &'a [f64]) -> (&'a [f64], &'a [f64]) {
        p[2..].split_at(self.inflow.len())
    }

    /// The sub-steps of a call at `(x, p)`, or the error that refuses it
    /// (checked before any generated code runs).
    fn substeps(&self, x: &[f64], p: &[f64]) -> Result<usize, OpError> {
        // One test per parameter: an array of (name, value) pairs iterated
        // by value trips Enzyme's type analysis (docs/pitfalls.md).
        if !(p[0].is_finite() && p[0] >= 0.0) {
            return Err(input(format!("viscosity p[0] = {} not finite, ≥ 0", p[0])));
        }
        if !(p[1].is_finite() && p[1] >= 0.0) {
            return Err(input(format!("time step p[1] = {} not finite, ≥ 0", p[1])));
        }
        if let Some(i) = p[2..].iter().position(|v| !v.is_finite()) {
            let what = if i < self.inflow.len() { "inflow speed" } else { "force" };
            return Err(input(format!("{what} p[{}] = {}", i + 2, p[2 + i])));
        }
        let (q, _) = self.split_params(p);
        let speed = x[..self.grid.n_vel()].iter().chain(q).fold(0.0f64, |m, v| m.max(v.abs()));
        let (courant, kappa) = (speed * p[1] / self.h, p[0] * p[1] / (self.h * self.h));
        let viscous = if self.viscosity == Viscosity::Explicit { kappa / viscous_limit(D) } else { 0.0 };
        let k = viscous.max(courant / COURANT_LIMIT).ceil();
        if k.is_nan() || k > MAX_SUBSTEPS as f64 || x.iter().any(|v| !v.is_finite()) {
            let (value, limit) = if courant.is_nan() || courant / COURANT_LIMIT >= viscous {
                (courant, COURANT_LIMIT * MAX_SUBSTEPS as f64)
            } else {
                (kappa, viscous_limit(D) * MAX_SUBSTEPS as f64)
            };
            return Err(OpError::Unstable { value, limit });
        }
        Ok((k as usize).max(1))
    }

    fn advect(&self) -> AdvectVelocity<D> {
        AdvectVelocity { grid: self.grid, h: self.h, scheme: self.scheme }
    }

    /// The viscous number of a sub-step `s`.
    fn kappa(&self, nu: f64, s: f64) -> f64 {
        nu * s / (self.h * self.h)
    }

    /// The sides in place on a velocity (or a tangent, with the profile's
    /// tangent `q`): walls and inflow faces set, periodic copies refreshed.
    fn sides(&self, q: &[f64], v: &mut [f64]) {
        smoke::enforce_boundary(&self.walls, v);
        for (f, &q) in self.inflow.iter().zip(q) {
            v[f.index] = f.sign * q;
        }
    }

    /// The adjoint of [`Self::sides`]: the profile's adjoint into `gq`, the
    /// velocity's in place.
    fn sides_adjoint(&self, g: &mut [f64], gq: &mut [f64]) {
        for (f, gq) in self.inflow.iter().zip(gq) {
            *gq += f.sign * g[f.index];
        }
        smoke::enforce_boundary_adjoint(&self.walls, g);
    }

    /// The projection in place on a velocity (or a tangent).
    fn project(&self, v: &mut [f64]) {
        self.projection.apply_velocity(v);
    }

    /// The projection's adjoint in place on a velocity adjoint.
    fn project_adjoint(&self, g: &mut [f64]) {
        self.projection.apply_adjoint_velocity(g);
    }

    /// Whether the force is added before the viscosity (implicit: `(I +
    /// κA)·u' = u + s·f`) rather than after it (explicit: `u' = u − κA·u +
    /// s·f`): either way the force is on the right-hand side of the viscous
    /// step, so that a steady state balances it exactly (the Poiseuille
    /// test; the other order leaves an error of order `κ` at the walls).
    fn force_first(&self) -> bool {
        self.viscosity != Viscosity::Explicit
    }

    /// One sub-step of `s` from `x`: the viscosity's input (the advected
    /// velocity, the force if first, the sides) into `advected`, the result
    /// into `y`.
    fn substep(&self, x: &[f64], p: &[f64], s: f64, advected: &mut [f64], y: &mut [f64], impulse: &mut f64)
    where
        AdvectVelocity<D>: Forward,
    {
        let (q, f) = self.split_params(p);
        self.advect().forward(x, &[s], advected);
        if self.force_first() {
            add_scaled(s, f, advected);
        }
        self.sides(q, advected);
        let kappa = [self.kappa(p[0], s)];
        for (r, part) in &self.parts {
            part.forward(&advected[r.clone()], &kappa, &mut y[r.clone()]);
        }
        if !self.force_first() {
            add_scaled(s, f, y);
        }
        self.sides(q, y);
        self.project_counting(y, impulse);
    }

    /// The projection in place on a velocity (or a tangent), its change
    /// weighted by the drag's impulse weights added to `impulse`.
    fn project_counting(&self, y: &mut [f64], impulse: &mut f64) {
        match &self.drag {
            Some(d) => {
                *impulse -= dot(&d.impulse, y);
                self.project(y);
                *impulse += dot(&d.impulse, y);
            }
            None => self.project(y),
        }
    }

    /// The numbers the state carries after the velocity: 2 with the drag.
    fn carried(&self) -> usize {
        if self.drag.is_some() { 2 } else { 0 }
    }

    /// The carried drag sums `[I, A]` of `y` from those of `x`, the
    /// impulse of the call and the velocity of `y`.
    fn carry(&self, x: &[f64], impulse: f64, y: &mut [f64]) {
        if let Some(d) = &self.drag {
            let nv = self.grid.n_vel();
            let shear = dot(&d.shear, &y[..nv]);
            y[nv] = x[nv] + impulse;
            y[nv + 1] = x[nv + 1] + shear;
        }
    }
}

/// `v += s·f` (nothing when `f` is empty: no force).
fn add_scaled(s: f64, f: &[f64], v: &mut [f64]) {
    for (v, &f) in v.iter_mut().zip(f) {
        *v += s * f;
    }
}

/// The adjoint of [`add_scaled`] at `(s, f)` from the adjoint `g` of `v`:
/// `gf += s·g`, returns `∂/∂s = f·g`.
fn add_scaled_adjoint(s: f64, f: &[f64], g: &[f64], gf: &mut [f64]) -> f64 {
    let mut gs = 0.0;
    for ((gf, &g), &f) in gf.iter_mut().zip(g).zip(f) {
        *gf += s * g;
        gs += f * g;
    }
    gs
}

/// The tangent of [`add_scaled`]: `v += s·f`, `tv += ts·f + s·tf`.
fn add_scaled_tangent(s: f64, ts: f64, f: &[f64], tf: &[f64], v: &mut [f64], tv: &mut [f64]) {
    for (((v, tv), &f), &tf) in v.iter_mut().zip(tv.iter_mut()).zip(f).zip(tf) {
        *v += s * f;
        *tv += ts * f + s * tf;
    }
}

impl<const D: usize> Operator for NavierStokes<D> {
    fn n_in(&self) -> usize {
        self.grid.n_vel() + self.carried()
    }
    fn n_out(&self) -> usize {
        self.grid.n_vel() + self.carried()
    }
    fn n_params(&self) -> usize {
        2 + self.inflow.len() + if self.forced { self.grid.n_vel() } else { 0 }
    }
}

impl<const D: usize> Forward for NavierStokes<D>
where
    AdvectVelocity<D>: Jvp,
{
    fn forward(&self, x: &[f64], p: &[f64], y: &mut [f64]) {
        validate_forward(self, "NavierStokes", x, p, y);
        let Some(k) = super::substeps_or_refuse(self.substeps(x, p), x, y, &self.error) else { return };
        let (s, nv) = (p[1] / k as f64, self.grid.n_vel());
        let (mut cur, mut advected, mut impulse) = (x[..nv].to_vec(), vec![0.0; nv], 0.0);
        for _ in 0..k {
            self.substep(&cur, p, s, &mut advected, &mut y[..nv], &mut impulse);
            cur.copy_from_slice(&y[..nv]);
        }
        self.carry(x, impulse, y);
    }

    /// The smallest of the sub-steps' advection radii, each at the state the
    /// sub-step starts from with the perturbation carried there to first
    /// order (a JVP through the call): later sub-steps' traces cross
    /// lattice planes too.
    fn smooth_radius(&self, x: &[f64], p: &[f64], dx: &[f64], dp: &[f64]) -> f64 {
        let Ok(k) = self.substeps(x, p) else { return 0.0 };
        let advect = self.advect();
        let mut r = f64::INFINITY;
        let (mut y, mut ty) = (vec![0.0; x.len()], vec![0.0; x.len()]);
        self.tangent_substeps(k, x, p, dx, dp, &mut y, &mut ty, |state, s, tangent, ts| {
            r = r.min(advect.smooth_radius(state, &[s], tangent, &[ts]));
        });
        r
    }

    fn solve_tolerance(&self) -> f64 {
        self.parts.iter().map(|(_, part)| part.solve_tolerance()).fold(self.projection.solve_tolerance(), f64::max)
    }

    fn take_error(&self) -> Option<OpError> {
        let parts = self.parts.iter().filter_map(|(_, part)| part.take_error()).next();
        self.error.take().or(self.projection.take_error()).or(parts)
    }
}

impl<const D: usize> Vjp for NavierStokes<D>
where
    AdvectVelocity<D>: Vjp + Jvp,
{
    fn vjp(&self, x: &[f64], p: &[f64], dy: &mut [f64], dx: &mut [f64], dp: &mut [f64]) {
        validate_vjp(self, "NavierStokes", x, p, dy, dx, dp);
        let Ok(k) = self.substeps(x, p) else {
            // The forward left the velocity as it was (and reported why).
            return super::refused_vjp(dy, dx);
        };
        let (s, nu, n) = (p[1] / k as f64, p[0], self.grid.n_vel());
        let (_, f) = self.split_params(p);
        // Each sub-step's starting state and advected velocity.
        let mut states = vec![x[..n].to_vec()];
        let mut advected = Vec::with_capacity(k);
        for i in 0..k {
            let (mut a, mut next) = (vec![0.0; n], vec![0.0; n]);
            self.substep(&states[i], p, s, &mut a, &mut next, &mut 0.0);
            advected.push(a);
            if i + 1 < k {
                states.push(next);
            }
        }
        let (advect, kappa, h2) = (self.advect(), [self.kappa(nu, s)], self.h * self.h);
        let (mut gq, mut gf) = (vec![0.0; self.inflow.len()], vec![0.0; f.len()]);
        let (mut g_nu, mut g_s) = (0.0, 0.0);
        let mut g = dy[..n].to_vec();
        // The carried sums pass through; the impulse's adjoint enters at
        // every projection, the shear sum's at the velocity returned.
        let g_impulse = match &self.drag {
            Some(d) => {
                let (gi, ga) = (dy[n], dy[n + 1]);
                add(ga, &d.shear, &mut g);
                dx[n] += gi;
                dx[n + 1] += ga;
                gi
            }
            None => 0.0,
        };
        dy.fill(0.0);
        let mut ga = vec![0.0; n];
        for (state, a) in states.iter().zip(&advected).rev() {
            match &self.drag {
                Some(d) => {
                    add(g_impulse, &d.impulse, &mut g);
                    self.project_adjoint(&mut g);
                    add(-g_impulse, &d.impulse, &mut g);
                }
                None => self.project_adjoint(&mut g),
            }
            self.sides_adjoint(&mut g, &mut gq);
            if !self.force_first() {
                g_s += add_scaled_adjoint(s, f, &g, &mut gf);
            }
            ga.fill(0.0);
            let mut g_kappa = [0.0];
            for (r, part) in &self.parts {
                part.vjp(&a[r.clone()], &kappa, &mut g[r.clone()], &mut ga[r.clone()], &mut g_kappa);
            }
            g_nu += g_kappa[0] * s / h2;
            g_s += g_kappa[0] * nu / h2;
            self.sides_adjoint(&mut ga, &mut gq);
            if self.force_first() {
                g_s += add_scaled_adjoint(s, f, &ga, &mut gf);
            }
            let (mut gx, mut gt) = (vec![0.0; n], [0.0]);
            advect.vjp(state, &[s], &mut ga, &mut gx, &mut gt);
            g_s += gt[0];
            g = gx;
        }
        dp[0] += g_nu;
        dp[1] += g_s / k as f64;
        for (d, g) in dp[2..].iter_mut().zip(gq.iter().chain(&gf)) {
            *d += g;
        }
        for (d, g) in dx[..n].iter_mut().zip(&g) {
            *d += g;
        }
    }
}

impl<const D: usize> Jvp for NavierStokes<D>
where
    AdvectVelocity<D>: Jvp,
{
    fn jvp(&self, x: &[f64], p: &[f64], tx: &[f64], tp: &[f64], y: &mut [f64], ty: &mut [f64]) {
        validate_jvp(self, "NavierStokes", x, p, tx, tp, y, ty);
        let Ok(k) = self.substeps(x, p) else { return super::refused_jvp(x, tx, y, ty) };
        self.tangent_substeps(k, x, p, tx, tp, y, ty, |_, _, _, _| {});
    }
}

impl<const D: usize> NavierStokes<D>
where
    AdvectVelocity<D>: Jvp,
{
    /// The `k` sub-steps from `x` with the tangent `(tx, tp)` carried along
    /// into `(y, ty)`; `visit(state, s, tangent, ts)` sees each sub-step's
    /// start (for the smooth radius of every sub-step).
    #[allow(clippy::too_many_arguments)]
    fn tangent_substeps(
        &self,
        k: usize,
        x: &[f64],
        p: &[f64],
        tx: &[f64],
        tp: &[f64],
        y: &mut [f64],
        ty: &mut [f64],
        mut visit: impl FnMut(&[f64], f64, &[f64], f64),
    ) {
        let (s, ts, n, h2) = (p[1] / k as f64, tp[1] / k as f64, self.grid.n_vel(), self.h * self.h);
        let ((q, f), (tq, tf)) = (self.split_params(p), self.split_params(tp));
        let (kappa, t_kappa) = ([self.kappa(p[0], s)], [(tp[0] * s + p[0] * ts) / h2]);
        let advect = self.advect();
        let (mut cur, mut tcur, mut a, mut ta) = (x[..n].to_vec(), tx[..n].to_vec(), vec![0.0; n], vec![0.0; n]);
        let (mut impulse, mut t_impulse) = (0.0, 0.0);
        let (y_all, ty_all) = (y, ty);
        for _ in 0..k {
            let (y, ty) = (&mut y_all[..n], &mut ty_all[..n]);
            visit(&cur, s, &tcur, ts);
            advect.jvp(&cur, &[s], &tcur, &[ts], &mut a, &mut ta);
            if self.force_first() {
                add_scaled_tangent(s, ts, f, tf, &mut a, &mut ta);
            }
            self.sides(q, &mut a);
            self.sides(tq, &mut ta);
            for (r, part) in &self.parts {
                part.jvp(&a[r.clone()], &kappa, &ta[r.clone()], &t_kappa, &mut y[r.clone()], &mut ty[r.clone()]);
            }
            if !self.force_first() {
                add_scaled_tangent(s, ts, f, tf, y, ty);
            }
            self.sides(q, y);
            self.sides(tq, ty);
            self.project_counting(y, &mut impulse);
            self.project_counting(ty, &mut t_impulse);
            cur.copy_from_slice(y);
            tcur.copy_from_slice(ty);
        }
        self.carry(x, impulse, y_all);
        self.carry(tx, t_impulse, ty_all);
    }
}
