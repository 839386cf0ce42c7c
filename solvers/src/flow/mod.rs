//! 2D viscous incompressible flow (Navier–Stokes) on a MAC grid in physical
//! units: no-slip walls that may slide (a cavity's lid), inflow with a
//! profile, outflow; second-order central differences in divergence form for
//! advection (velocities interpolated by two or four points: [`Convection`])
//! and the five-point Laplacian for viscosity; explicit time steps
//! (forward Euler or SSP-RK3) each followed by the pressure projection of
//! [`crate::smoke`].
//!
//! Layout: `nx × ny` square cells of side `h`, velocity packed `[u, v]` as in
//! [`crate::smoke`] (`u[j][i]` at the x-face `(i·h, (j+½)·h)`, `Ny·(Nx+1)`
//! values; `v[j][i]` at the y-face `((i+½)·h, j·h)`, `(Ny+1)·Nx` values).
//! Density is 1. The sides' normal conditions and the pressure equation are
//! those of [`Boundary`] (`Closed` and `NoSlip` are walls); the tangential
//! condition is no-slip on both kinds of wall here (at the wall's sliding speed) and inflow sides, zero
//! normal gradient on outflow sides, imposed through ghost values (`2·U_wall −
//! u_inside`). Periodic sides are not supported here.
//!
//! The module in files: this one holds the configuration and the time step,
//! `momentum` the right-hand side (advection and viscosity), `cavity` the
//! lid-driven cavity of Ghia, Ghia & Shin (1982) with its reference values
//! and the centreline profiles.

use crate::boundary::{Boundary, BoundaryError, Side};
use crate::smoke::{MacGrid, NoConvergence, PressureSolver, ProjectScratch, enforce_boundary, project_velocity};
use momentum::{Pads, momentum};
use std::fmt;

pub mod body;
pub mod cavity;
pub mod cylinder;
pub mod drag_shape;
pub mod momentum;
pub mod steady;

// The types every user of the flow meets, here; the rest in their modules.
pub use body::{Cut, CutSensitivity, Shape, ShapeError};
pub use cavity::{GHIA, GhiaTable, cavity_extrema, centrelines, ghia};
pub use steady::{NewtonParams, SteadyFlow, SteadyState};

/// Tangential speed of each wall (used on `Closed` sides only): along `+y`
/// for the left and right sides, along `+x` for the bottom and top.
#[derive(Clone, Copy, Debug, Default, PartialEq)]
pub struct WallSpeed {
    /// `x = 0`.
    pub left: f64,
    /// `x = Nx·h`.
    pub right: f64,
    /// `y = 0`.
    pub bottom: f64,
    /// `y = Ny·h`.
    pub top: f64,
}

/// A viscous flow problem: the grid, the viscosity and the sides.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Flow2d {
    /// Cells along x.
    pub nx: usize,
    /// Cells along y.
    pub ny: usize,
    /// Cell side.
    pub h: f64,
    /// Kinematic viscosity.
    pub nu: f64,
    /// Normal conditions of the four sides (and the pressure's).
    pub boundary: Boundary,
    /// Sliding speeds of the walls.
    pub wall_speed: WallSpeed,
    /// How the advection term interpolates velocities to the flux points.
    pub convection: Convection,
}

/// The interpolation of the advection term `∇·(u⊗u)` on the MAC grid (its
/// flux differences are second order either way).
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq, serde::Serialize, serde::Deserialize)]
#[serde(rename_all = "lowercase")]
pub enum Convection {
    /// Two-point averages of the transported and transporting velocities:
    /// the classic second-order central scheme.
    #[default]
    Second,
    /// Four-point (fourth-order) interpolation `(9(a + b) − (c + d))/16` of
    /// the transported and the transporting velocities, two-point averages
    /// where the four points do not fit inside the sides. Less dispersive:
    /// the vortex street behind a cylinder keeps its strength on coarser
    /// grids (docs/cylinder.md). The stencil reaches two faces each way.
    Fourth,
}

impl Convection {
    /// `"second"` or `"fourth"`: the interpolation's order, as reports and
    /// the command line name it.
    pub fn name(self) -> &'static str {
        match self {
            Convection::Second => "second",
            Convection::Fourth => "fourth",
        }
    }
}

/// Why a flow cannot be simulated or a simulation stopped.
#[derive(Clone, Copy, Debug, PartialEq)]
pub enum FlowError {
    /// The sides cannot be simulated together.
    Boundary(BoundaryError),
    /// A side kind the viscous solver does not support.
    Periodic,
    /// Fewer than two cells along an axis, or a non-positive or non-finite
    /// cell size or viscosity.
    Grid,
    /// The pressure matrix could not be factored (out of memory).
    Factor,
    /// The pressure solve failed at this step.
    Pressure {
        /// The step.
        step: usize,
        /// What the solver reported.
        cause: NoConvergence,
    },
    /// The velocity stopped being finite (the time step was unstable).
    NotFinite {
        /// The step.
        step: usize,
    },
    /// A body is not a proper shape inside the domain.
    Shape(ShapeError),
    /// An unsteady run did not settle into a periodic signal.
    NotPeriodic {
        /// Upward crossings of the mean found in the measured window.
        crossings: usize,
    },
    /// A march to a steady state ran out of steps.
    NotSteady {
        /// Steps taken.
        steps: usize,
        /// The last `max |Δu|/dt`.
        rate: f64,
        /// The tolerance asked for.
        tolerance: f64,
    },
}

impl fmt::Display for FlowError {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        match self {
            FlowError::Boundary(e) => e.fmt(f),
            FlowError::Periodic => f.write_str("flow: periodic sides are not supported by the viscous solver"),
            FlowError::Grid => f.write_str("flow: the grid needs at least 2 × 2 cells and a positive cell size and viscosity"),
            FlowError::Factor => f.write_str("flow: the sparse Cholesky factorisation of the pressure matrix failed (out of memory?)"),
            FlowError::Pressure { step, cause } => write!(f, "flow: step {step}: {cause}"),
            FlowError::NotFinite { step } => write!(f, "flow: the velocity is not finite after step {step} (unstable time step?)"),
            FlowError::Shape(e) => e.fmt(f),
            FlowError::NotPeriodic { crossings } => {
                write!(f, "flow: the lift did not oscillate in the measured window ({crossings} upward crossings of its mean; run longer)")
            }
            FlowError::NotSteady { steps, rate, tolerance } => {
                write!(
                    f,
                    "flow: no steady state after {steps} steps: max |du/dt| is {rate:.3e}, above the tolerance {tolerance:.1e} (more steps, a looser tolerance, or an unsteady flow)"
                )
            }
        }
    }
}

impl std::error::Error for FlowError {}

impl Flow2d {
    /// The MAC grid of the flow (the smoke solver's, for its projection and
    /// boundary rules).
    pub fn grid(&self) -> MacGrid<2> {
        MacGrid::new([self.nx, self.ny]).with_boundary(self.boundary)
    }

    /// Number of velocities `Ny·(Nx+1) + (Ny+1)·Nx`.
    pub fn n_vel(&self) -> usize {
        self.grid().n_vel()
    }

    /// Number of x-face velocities.
    pub fn n_u(&self) -> usize {
        self.grid().n_face(0)
    }

    /// Checks that the flow can be simulated.
    pub fn validate(&self) -> Result<(), FlowError> {
        if self.nx < 2 || self.ny < 2 || !(self.h > 0.0 && self.h.is_finite()) || !(self.nu > 0.0 && self.nu.is_finite()) {
            return Err(FlowError::Grid);
        }
        self.boundary.validate().map_err(FlowError::Boundary)?;
        if self.boundary.sides.iter().flatten().any(|&s| s == Side::Periodic) {
            return Err(FlowError::Periodic);
        }
        Ok(())
    }

    /// The fluid at rest with the boundary values set.
    pub fn rest(&self) -> Vec<f64> {
        let mut x = vec![0.0; self.n_vel()];
        enforce_boundary(&self.grid(), &mut x);
        x
    }
}

/// Time integrator of [`Stepper::step`].
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Integrator {
    /// Forward Euler, one projection per step (cheapest where viscosity
    /// limits the step).
    Euler,
    /// The three-stage strong-stability-preserving Runge–Kutta method of
    /// Shu and Osher, a projection after each stage (stable for central
    /// advection where Euler is not).
    Rk3,
}

impl Integrator {
    /// Stages (projections) per step.
    pub fn stages(self) -> usize {
        match self {
            Integrator::Euler => 1,
            Integrator::Rk3 => 3,
        }
    }

    /// The largest stable time step for velocities up to `speed` (the
    /// maximum of `|u| + |v|`), with a safety factor: Euler with central
    /// differences needs `dt ≤ h²/(4ν)` and `dt ≤ 2ν/speed²`; SSP-RK3 covers
    /// the imaginary axis to `√3` and the negative real axis to about 2.5.
    pub fn stable_dt(self, cfg: &Flow2d, speed: f64) -> f64 {
        let (h, nu) = (cfg.h, cfg.nu);
        let speed = speed.max(1e-12);
        match self {
            Integrator::Euler => 0.8 * (0.25 * h * h / nu).min(2.0 * nu / (speed * speed)),
            Integrator::Rk3 => 0.8 * (3f64.sqrt() * h / speed).min(2.5 * h * h / (8.0 * nu)),
        }
    }

    /// The integrator with the smaller cost per unit of simulated time
    /// (projections per step over the stable step) at this speed.
    pub fn cheaper(cfg: &Flow2d, speed: f64) -> Self {
        let cost = |i: Integrator| i.stages() as f64 / i.stable_dt(cfg, speed);
        if cost(Integrator::Euler) <= cost(Integrator::Rk3) { Integrator::Euler } else { Integrator::Rk3 }
    }
}

/// Largest `|u| + |v|` over the cells (face values averaged to the centres).
pub fn max_speed(cfg: &Flow2d, x: &[f64]) -> f64 {
    let (u, v) = x.split_at(cfg.n_u());
    let (nx, ny) = (cfg.nx, cfg.ny);
    let mut m = 0.0f64;
    for j in 0..ny {
        for i in 0..nx {
            let uc = 0.5 * (u[j * (nx + 1) + i] + u[j * (nx + 1) + i + 1]);
            let vc = 0.5 * (v[j * nx + i] + v[(j + 1) * nx + i]);
            m = m.max(uc.abs() + vc.abs());
        }
    }
    m
}

/// What one time step did.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct StepReport {
    /// Largest change of a velocity over the step divided by the step,
    /// `max |Δu|/dt` (zero at a steady state).
    pub rate: f64,
    /// Conjugate-gradient iterations of the step's projections.
    pub iterations: usize,
}

/// Time steps of one [`Flow2d`], with the pressure solver and the work
/// buffers kept between steps.
#[derive(Debug)]
pub struct Stepper {
    cfg: Flow2d,
    grid: MacGrid<2>,
    /// The projection without bodies.
    solver: Option<PressureSolver<2>>,
    scratch: ProjectScratch,
    pads: Pads,
    rhs: Vec<f64>,
    start: Vec<f64>,
    /// The bodies' cut of the grid, if there are bodies.
    cut: Option<Cut>,
    /// The state with the faces inside bodies zeroed (what the momentum
    /// operator reads when there are bodies).
    masked: Vec<f64>,
    /// Around bodies: projections per stage weight `b·dt` (the factor
    /// `M = 1/(1 + b·dt·ν·K/h²)` of the implicit no-slip term enters the
    /// pressure matrix), most recent last.
    cut_solvers: Vec<CutSolver>,
    tolerance: f64,
    steps: usize,
    /// `dt` times the last stage's weight: the time over which the last
    /// projection's pressure gradient acted.
    last_dt: f64,
}

/// The projection of one stage weight around bodies.
#[derive(Debug)]
struct CutSolver {
    weight: f64,
    solver: PressureSolver<2>,
    /// `M` per velocity (packed `[u, v]`).
    scale: Vec<f64>,
}

impl Stepper {
    /// A stepper for a validated configuration; the pressure solve to
    /// relative tolerance `tolerance`. The closed square box with a side of
    /// a power of two uses the multigrid-preconditioned solve, others a
    /// sparse Cholesky factor (faer) computed here.
    pub fn new(cfg: Flow2d, tolerance: f64) -> Result<Self, FlowError> {
        cfg.validate()?;
        let max_it = 20 * (cfg.nx * cfg.ny).max(100);
        let multigrid = cfg.boundary == Boundary::CLOSED && cfg.nx == cfg.ny && cfg.nx.is_power_of_two();
        let solver = if multigrid {
            PressureSolver::new(&cfg.grid(), tolerance, max_it, crate::smoke::Preconditioner::Multigrid)
        } else {
            PressureSolver::direct(&cfg.grid(), tolerance, max_it, None).map_err(|_| FlowError::Factor)?
        };
        Ok(Self::assemble(cfg, Some(solver), None, tolerance))
    }

    fn assemble(cfg: Flow2d, solver: Option<PressureSolver<2>>, cut: Option<Cut>, tolerance: f64) -> Self {
        let n = cfg.n_vel();
        Self {
            cfg,
            grid: cfg.grid(),
            solver,
            scratch: ProjectScratch::new(cfg.nx * cfg.ny),
            pads: Pads::new(&cfg),
            rhs: vec![0.0; n],
            start: vec![0.0; n],
            masked: if cut.is_some() { vec![0.0; n] } else { Vec::new() },
            cut,
            cut_solvers: Vec::new(),
            tolerance,
            steps: 0,
            last_dt: 0.0,
        }
    }

    /// A stepper for a flow around fixed bodies (cut cells, [`Cut`]): faces
    /// whose centre lies inside a body hold velocity 0; the viscous stencil
    /// of a fluid face next to a body takes the no-slip value at the
    /// boundary's distance `θ·h` (Gibou et al. 2002), its stiff part
    /// `−ν·(1/θ − 1)/h²·u` implicit face by face, with factor
    /// `M = 1/(1 + b·dt·ν·(1/θ − 1)/h²)` for a stage of weight `b`; the
    /// projection is `y − M·G·p` with `D_a·M·G·p = D_a·y` (`D_a` the
    /// divergence weighted by the faces' open fractions; `M = 0` inside
    /// bodies), so that the discrete steady equations hold exactly whatever
    /// the step, and every weight varies continuously with the shape. One
    /// sparse Cholesky factorisation per stage weight, kept.
    pub fn with_bodies(cfg: Flow2d, tolerance: f64, shapes: &[Shape]) -> Result<Self, FlowError> {
        cfg.validate()?;
        let cut = Cut::new(&cfg, shapes);
        Ok(Self::assemble(cfg, None, Some(cut), tolerance))
    }

    /// The index in `cut_solvers` of the projection for stage weight
    /// `weight` (built and factored when new; at most six kept).
    fn cut_solver(&mut self, weight: f64) -> Result<usize, FlowError> {
        if let Some(k) = self.cut_solvers.iter().position(|c| c.weight == weight) {
            return Ok(k);
        }
        let cut = self.cut.as_ref().expect("a stepper with bodies");
        let cfg = &self.cfg;
        let stiff = weight * cfg.nu / (cfg.h * cfg.h);
        // Faces inside a body take no pressure gradient (their velocity is
        // the body's): as a fluid face nears the boundary its no-slip factor
        // tends to 0 too, so the weights change continuously.
        let scale: Vec<f64> = cut.wall.iter().zip(&cut.fluid).map(|(&k, &w)| w / (1.0 + stiff * k)).collect();
        let n_u = cfg.n_u();
        let au: Vec<f64> = cut.aperture_u.iter().zip(&scale[..n_u]).map(|(a, m)| a * m).collect();
        let av: Vec<f64> = cut.aperture_v.iter().zip(&scale[n_u..]).map(|(a, m)| a * m).collect();
        let max_it = 20 * (cfg.nx * cfg.ny).max(100);
        let solver = PressureSolver::with_apertures(&cfg.grid(), self.tolerance, max_it, [&au, &av]).map_err(|_| FlowError::Factor)?;
        if self.cut_solvers.len() == 6 {
            self.cut_solvers.remove(0);
        }
        self.cut_solvers.push(CutSolver { weight, solver, scale });
        Ok(self.cut_solvers.len() - 1)
    }

    /// The bodies' cut of the grid, if there are bodies.
    pub fn cut(&self) -> Option<&Cut> {
        self.cut.as_ref()
    }

    /// The force of the fluid on whatever lies inside the box of cells
    /// `[i0, i1) × [j0, j1)` (per unit depth, density 1), by the discrete
    /// momentum balance of that control volume: the momentum operator at
    /// `x` and the gradient of the last step's pressure summed over every
    /// face inside the box (they telescope to the fluxes through its sides,
    /// so only the bodies' terms remain), less the rate of change of the
    /// momentum inside (`dudt`, per velocity; `None` at a steady state).
    /// After an SSP-RK3 step the last pressure belongs to the middle of the
    /// step, so pass the mean of the states before and after as `x` and
    /// their difference over `dt` as `dudt` (second order in time). The box
    /// must lie inside the domain and contain the bodies whole.
    pub fn force_in_box(&mut self, x: &[f64], dudt: Option<&[f64]>, cells: [usize; 4]) -> [f64; 2] {
        let [i0, i1, j0, j1] = cells;
        let (nx, h) = (self.cfg.nx, self.cfg.h);
        let n_u = self.cfg.n_u();
        let mask = |k: usize, v: f64| self.cut.as_ref().map_or(v, |c| v * c.fluid[k]);
        let masked: Vec<f64> = x.iter().enumerate().map(|(k, &v)| mask(k, v)).collect();
        momentum(&self.cfg, &masked, &mut self.pads, &mut self.rhs);
        let p = self.pressure();
        let mut f = [0.0; 2];
        // x-momentum: u-faces strictly inside the box (columns i0+1 .. i1-1).
        for j in j0..j1 {
            for i in i0 + 1..i1 {
                let k = j * (nx + 1) + i;
                let ddt = dudt.map_or(0.0, |d| mask(k, d[k]));
                let gp = (p[j * nx + i] - p[j * nx + i - 1]) / h;
                f[0] += self.rhs[k] - gp - ddt;
            }
        }
        for j in j0 + 1..j1 {
            for i in i0..i1 {
                let k = n_u + j * nx + i;
                let ddt = dudt.map_or(0.0, |d| mask(k, d[k]));
                let gp = (p[j * nx + i] - p[(j - 1) * nx + i]) / h;
                f[1] += self.rhs[k] - gp - ddt;
            }
        }
        [f[0] * h * h, f[1] * h * h]
    }

    /// The configuration.
    pub fn config(&self) -> &Flow2d {
        &self.cfg
    }

    /// Steps taken so far.
    pub fn steps(&self) -> usize {
        self.steps
    }

    /// The kinematic pressure after the last step, per cell (in a closed box
    /// defined up to a constant): the projection's potential rescaled by
    /// `h` over the time its gradient acted.
    pub fn pressure(&self) -> Vec<f64> {
        let scale = if self.last_dt > 0.0 { self.cfg.h / self.last_dt } else { 0.0 };
        self.scratch.pressure().iter().map(|p| p * scale).collect()
    }

    /// One time step of `dt` in place on the packed velocity `x`, which
    /// must hold the boundary values (as [`Flow2d::rest`] does). Each stage
    /// is `x ← a·x⁰ + b·(x + dt·F(x))`, then the boundary values and the
    /// projection; the projection starts from the previous one's pressure,
    /// rescaled to the stage's weight.
    pub fn step(&mut self, x: &mut [f64], dt: f64, integrator: Integrator) -> Result<StepReport, FlowError> {
        assert_eq!(x.len(), self.cfg.n_vel(), "flow state length");
        const EULER: [(f64, f64); 1] = [(0.0, 1.0)];
        const RK3: [(f64, f64); 3] = [(0.0, 1.0), (0.75, 0.25), (1.0 / 3.0, 2.0 / 3.0)];
        let stages: &[(f64, f64)] = match integrator {
            Integrator::Euler => &EULER,
            Integrator::Rk3 => &RK3,
        };
        self.start.copy_from_slice(x);
        let mut iterations = 0;
        for &(a, b) in stages {
            match &self.cut {
                None => {
                    momentum(&self.cfg, x, &mut self.pads, &mut self.rhs);
                    for ((y, &x0), &f) in x.iter_mut().zip(&self.start).zip(&self.rhs) {
                        *y = a * x0 + b * (*y + dt * f);
                    }
                }
                Some(cut) => {
                    for ((m, &xv), &w) in self.masked.iter_mut().zip(x.iter()).zip(&cut.fluid) {
                        *m = xv * w;
                    }
                    momentum(&self.cfg, &self.masked, &mut self.pads, &mut self.rhs);
                    let stiff = b * dt * self.cfg.nu / (self.cfg.h * self.cfg.h);
                    for (((y, &x0), &f), (&w, &k)) in x.iter_mut().zip(&self.start).zip(&self.rhs).zip(cut.fluid.iter().zip(&cut.wall)) {
                        *y = w * (a * x0 + b * (*y + dt * f)) / (1.0 + stiff * k);
                    }
                }
            }
            enforce_boundary(&self.grid, x);
            let (u, v) = x.split_at_mut(self.cfg.n_u());
            let weight = b * dt;
            if self.last_dt > 0.0 {
                let r = weight / self.last_dt;
                self.scratch.scale_pressure(r);
            }
            let warm = self.last_dt > 0.0;
            let projected = match &self.cut {
                None => project_velocity(&self.grid, [u, v], None, None, self.solver.as_mut().expect("the projection without bodies"), &mut self.scratch, warm),
                Some(_) => {
                    let k = self.cut_solver(weight)?;
                    let cut = self.cut.as_ref().expect("bodies");
                    let CutSolver { solver, scale, .. } = &mut self.cut_solvers[k];
                    project_velocity(&self.grid, [u, v], Some([&cut.aperture_u, &cut.aperture_v]), Some(scale), solver, &mut self.scratch, warm)
                }
            };
            iterations += projected.map_err(|cause| FlowError::Pressure { step: self.steps, cause })?;
            self.last_dt = weight;
        }
        self.steps += 1;
        let mut change = 0.0f64;
        for (y, x0) in x.iter().zip(&self.start) {
            change = change.max((y - x0).abs());
        }
        if !change.is_finite() || x.iter().any(|v| !v.is_finite()) {
            return Err(FlowError::NotFinite { step: self.steps });
        }
        Ok(StepReport { rate: change / dt, iterations })
    }
}

/// When [`march_to_steady`] stops.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct SteadyParams {
    /// Stop when `max |Δu|/dt` falls below this.
    pub tolerance: f64,
    /// Give up after this many steps.
    pub max_steps: usize,
    /// Speed scale for the time step before the flow has developed (the
    /// step follows the larger of this and the flow's largest speed).
    pub reference_speed: f64,
}

/// The former name of [`SteadyParams`].
#[deprecated(note = "renamed SteadyParams")]
pub type SteadyOptions = SteadyParams;

/// How a march to a steady state ended.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct SteadyReport {
    /// Steps taken.
    pub steps: usize,
    /// Simulated (pseudo-)time.
    pub time: f64,
    /// The last `max |Δu|/dt` (below the tolerance).
    pub rate: f64,
    /// The integrator used.
    pub integrator: Integrator,
    /// Conjugate-gradient iterations, all projections together.
    pub iterations: usize,
}

/// Marches `x` in time until it stops changing (pseudo-time stepping to
/// the steady state of the discrete equations, which does not depend on
/// the time step): the integrator cheaper per unit of time at the reference
/// speed, each step the largest stable one for the current speed (around
/// bodies, from a ladder of sizes that repeat: each has its own pressure
/// factorisation).
/// `observe(step, time, rate)` is called after every step. Running out of
/// steps is [`FlowError::NotSteady`] (`x` holds the last state).
pub fn march_to_steady(stepper: &mut Stepper, x: &mut [f64], opts: &SteadyParams, mut observe: impl FnMut(usize, f64, f64)) -> Result<SteadyReport, FlowError> {
    let cfg = *stepper.config();
    let integrator = Integrator::cheaper(&cfg, opts.reference_speed);
    let (mut time, mut rate, mut iterations) = (0.0, f64::INFINITY, 0);
    let dt0 = integrator.stable_dt(&cfg, opts.reference_speed);
    let bodies = stepper.cut.is_some();
    for step in 0..opts.max_steps {
        let dt = integrator.stable_dt(&cfg, max_speed(&cfg, x).max(opts.reference_speed));
        // Around bodies each step size has its own pressure factorisation:
        // steps from a ladder, so that they repeat.
        let dt = if bodies { ladder(dt0, dt) } else { dt };
        let r = stepper.step(x, dt, integrator)?;
        time += dt;
        rate = r.rate;
        iterations += r.iterations;
        observe(step + 1, time, rate);
        if rate < opts.tolerance {
            return Ok(SteadyReport { steps: step + 1, time, rate, integrator, iterations });
        }
    }
    Err(FlowError::NotSteady { steps: opts.max_steps, rate, tolerance: opts.tolerance })
}

/// The largest `dt0·2^(−k/4)`, `k = 0, 1, …`, not above `dt`: step sizes
/// that repeat, for steppers whose projection depends on the step.
pub fn ladder(dt0: f64, dt: f64) -> f64 {
    if dt >= dt0 {
        return dt0;
    }
    let k = (4.0 * (dt0 / dt).log2()).ceil();
    dt0 * 2f64.powf(-k / 4.0)
}
