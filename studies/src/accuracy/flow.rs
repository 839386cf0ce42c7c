//! The 2D schemes of [`diffsim::fluids`] on the periodic box `[0, 2π)²`
//! against exact solutions: the Taylor–Green vortex (advection of the
//! velocity, viscosity, pressure projection), translation of a smooth
//! profile by a constant velocity (advection of a scalar) and a Fourier
//! mode of the heat equation (diffusion); and the Navier–Stokes operator
//! on the Taylor–Green vortex and, in 3D, on the Arnold–Beltrami–Childress
//! flow.
//!
//! The solver works on unit cells; a run converts: cell width
//! `h = 2π/n`, velocities in cells per unit time (`u/h`), diffusion number
//! `κ = ν·dt/h²`.

use std::f64::consts::PI;

use diffsim_solvers::boundary::{Boundary, Side};
use diffsim_solvers::exact::{Abc, HeatMode, TaylorGreen, Translation, on_faces};
use diffsim_solvers::smoke::{MacGrid, Preconditioner, Scheme};

use super::{AccuracyError, Diffusion, all_finite, positive, relative_l2, steps_to};
use diffsim::fluids::{Advect, AdvectUpwind, Diffuse, Project};
use diffsim::navier_stokes::{NavierStokes, Viscosity};
use diffsim::op::{Forward, OpError};

/// Side of the periodic box.
pub const LENGTH: f64 = 2.0 * PI;

/// The periodic `n × n` box without buoyancy.
pub fn periodic_box(n: usize) -> MacGrid<2> {
    MacGrid::new([n, n]).with_boundary(Boundary::all(Side::Periodic))
}

/// Name of an advection scheme in reports.
pub fn scheme_name(scheme: Scheme) -> &'static str {
    match scheme {
        Scheme::SemiLagrangian => "semi-lagrangian",
        Scheme::MacCormack { limiter: false } => "maccormack",
        Scheme::MacCormack { limiter: true } => "maccormack-limited",
    }
}

/// Diffusion of the chosen fields of a box, explicit or implicit
/// (parameter `p = [κ]`).
fn diffuser(cfg: MacGrid<2>, smoke: bool, velocity: bool, diffusion: Diffusion, max_iterations: usize) -> Box<dyn Forward> {
    match diffusion {
        Diffusion::Explicit => Box::new(Diffuse::explicit(cfg, smoke, velocity)),
        Diffusion::Implicit { tolerance } => Box::new(Diffuse::implicit(cfg, smoke, velocity, tolerance, max_iterations)),
    }
}

/// One diffusion step `y = D(x; κ)` and the error it recorded.
fn diffuse_step(d: &dyn Forward, x: &[f64], kappa: f64, y: &mut [f64]) -> Option<OpError> {
    d.forward(x, &[kappa], y);
    d.take_error()
}

/// Checks an operator's error and the state after a stage.
fn after(stage: &'static str, step: usize, error: Option<OpError>, state: &[f64]) -> Result<(), AccuracyError> {
    if let Some(error) = error {
        return Err(AccuracyError::Operator { stage, step, error });
    }
    if !all_finite(state) {
        return Err(AccuracyError::NonFinite { stage, step });
    }
    Ok(())
}

/// Relative L2 error of the velocity samples of a packed state against
/// `(u, v)` (a periodic axis's copy faces left out).
fn velocity_error(cfg: &MacGrid<2>, x: &[f64], u: &[f64], v: &[f64]) -> f64 {
    debug_assert!(cfg.is_cube(), "the periodic box is square");
    let n = cfg.n[0];
    let (_, [xu, xv]) = cfg.split(x);
    let (mut a, mut b) = (Vec::with_capacity(2 * n * n), Vec::with_capacity(2 * n * n));
    for j in 0..n {
        for i in 0..n {
            a.push(xu[j * (n + 1) + i]);
            b.push(u[j * (n + 1) + i]);
            a.push(xv[j * n + i]);
            b.push(v[j * n + i]);
        }
    }
    relative_l2(&a, &b)
}

/// The Taylor–Green vortex (amplitude 1, period 2π) on an `n × n` MAC grid:
/// per step the velocity advects itself, diffuses (if `nu > 0`) and is
/// projected to be divergence-free. Time step `cfl·h`, for explicit
/// diffusion at most `0.2·h²/ν` (the limit is 0.25).
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct TaylorGreenRun {
    /// Cells per side.
    pub n: usize,
    /// Viscosity ν (0: the steady inviscid vortex).
    pub nu: f64,
    /// Final time.
    pub t_end: f64,
    /// Courant number.
    pub cfl: f64,
    /// Advection of the velocity.
    pub scheme: Scheme,
    /// Viscosity in time.
    pub diffusion: Diffusion,
    /// Relative tolerance of the pressure solve.
    pub pressure_tolerance: f64,
}

impl TaylorGreenRun {
    /// The exact solution.
    pub fn exact_solution(&self) -> TaylorGreen {
        TaylorGreen { length: LENGTH, amplitude: 1.0, nu: self.nu }
    }

    /// The settings checked: at least 4 cells, `ν ≥ 0`, a positive final
    /// time, Courant number and pressure tolerance.
    fn validate(&self) -> Result<(), AccuracyError> {
        check_flow(self.n, self.nu, self.t_end, self.cfl)?;
        positive("pressure_tolerance", self.pressure_tolerance)
    }

    /// Number of steps and the time step.
    pub fn steps(&self) -> (usize, f64) {
        let h = LENGTH / self.n as f64;
        let mut dt = self.cfl * h;
        if self.diffusion == Diffusion::Explicit && self.nu > 0.0 {
            dt = dt.min(0.2 * h * h / self.nu);
        }
        steps_to(self.t_end, dt)
    }

    /// The packed state `[s, u, v]` at `t_end` (the smoke is zero).
    pub fn run(&self) -> Result<Vec<f64>, AccuracyError> {
        self.validate()?;
        let n = self.n;
        let cfg = periodic_box(n);
        let h = LENGTH / n as f64;
        let (steps, dt) = self.steps();
        let kappa = self.nu * dt / (h * h);
        let (u, v) = self.exact_solution().mac(n, 0.0);
        let mut x = vec![0.0; cfg.n_s()];
        x.extend(u);
        x.extend(v);
        let mut y = vec![0.0; x.len()];
        let advect = Advect { cfg, scheme: self.scheme, dt, smoke: false, velocity: true };
        let diffuse = (self.nu > 0.0).then(|| diffuser(cfg, false, true, self.diffusion, 100 * n));
        let project = Project::new(cfg, self.pressure_tolerance, 100 * n * n, Preconditioner::None);
        for step in 0..steps {
            advect.forward(&x, &[], &mut y);
            after("advection", step, None, &y)?;
            match &diffuse {
                Some(d) => {
                    let e = diffuse_step(d.as_ref(), &y, kappa, &mut x);
                    after("diffusion", step, e, &x)?;
                }
                None => std::mem::swap(&mut x, &mut y),
            }
            project.apply(&mut x);
            after("pressure projection", step, project.take_error(), &x)?;
        }
        Ok(x)
    }

    /// Relative L2 error of the velocity of `x` (a result of
    /// [`TaylorGreenRun::run`]) against the exact one at `t_end`.
    pub fn error_of(&self, x: &[f64]) -> f64 {
        let (u, v) = self.exact_solution().mac(self.n, self.t_end);
        velocity_error(&periodic_box(self.n), x, &u, &v)
    }

    /// Runs and returns the relative L2 error of the velocity at `t_end`.
    pub fn error(&self) -> Result<f64, AccuracyError> {
        Ok(self.error_of(&self.run()?))
    }
}

/// The Taylor–Green vortex by the Navier–Stokes operator
/// ([`NavierStokes`] on the periodic box: sub-steps, the projection by
/// FFT) in calls of `cfl·h` (each split into stable sub-steps by the
/// operator), the viscosity explicit or implicit.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct NavierStokesRun {
    /// Cells per side.
    pub n: usize,
    /// Viscosity ν.
    pub nu: f64,
    /// Final time.
    pub t_end: f64,
    /// Courant number of a call (its sub-steps keep theirs within 0.9).
    pub cfl: f64,
    /// Advection of the velocity.
    pub scheme: Scheme,
    /// Viscosity in time.
    pub viscosity: Diffusion,
}

impl NavierStokesRun {
    /// The run of the same vortex as `tg` by the operator.
    pub fn of(tg: &TaylorGreenRun) -> Self {
        Self { n: tg.n, nu: tg.nu, t_end: tg.t_end, cfl: tg.cfl, scheme: tg.scheme, viscosity: tg.diffusion }
    }

    /// The Taylor–Green run with the same settings (its exact solution and
    /// error measure are this run's).
    fn vortex(&self) -> TaylorGreenRun {
        TaylorGreenRun { n: self.n, nu: self.nu, t_end: self.t_end, cfl: self.cfl, scheme: self.scheme, diffusion: self.viscosity, pressure_tolerance: 1e-8 }
    }

    /// Number of calls and the time of each.
    pub fn steps(&self) -> (usize, f64) {
        steps_to(self.t_end, self.cfl * LENGTH / self.n as f64)
    }

    /// The packed state `[s, u, v]` at `t_end` (the smoke is zero).
    pub fn run(&self) -> Result<Vec<f64>, AccuracyError> {
        self.vortex().validate()?;
        let (n, cfg) = (self.n, periodic_box(self.n));
        // Unit cells, as the fluid operators (velocities in cells per unit
        // time, the viscosity in cells² per unit time).
        let h = LENGTH / n as f64;
        let op = operator(cfg, 1.0, self.scheme, self.viscosity)?;
        let (steps, dt) = self.steps();
        let (u, v) = self.vortex().exact_solution().mac(n, 0.0);
        let x = calls(&op, u.into_iter().chain(v).collect(), [self.nu / (h * h), dt], steps)?;
        let mut state = vec![0.0; cfg.n_s()];
        state.extend(x);
        Ok(state)
    }

    /// Relative L2 error of the velocity of `x` (a result of
    /// [`NavierStokesRun::run`]) against the exact one at `t_end`.
    pub fn error_of(&self, x: &[f64]) -> f64 {
        self.vortex().error_of(x)
    }

    /// Runs and returns the relative L2 error of the velocity at `t_end`.
    pub fn run_error(&self) -> Result<f64, AccuracyError> {
        Ok(self.error_of(&self.run()?))
    }
}

/// The settings every flow run checks: at least 4 cells, `ν ≥ 0`, a
/// positive final time and Courant number.
fn check_flow(n: usize, nu: f64, t_end: f64, cfl: f64) -> Result<(), AccuracyError> {
    if n < 4 {
        return Err(AccuracyError::Invalid { what: "n", reason: format!("need at least 4 cells per side, got {n}") });
    }
    if !(nu >= 0.0 && nu.is_finite()) {
        return Err(AccuracyError::Invalid { what: "nu", reason: format!("must be ≥ 0 and finite, got {nu}") });
    }
    positive("t_end", t_end)?;
    positive("cfl", cfl)
}

/// The Navier–Stokes operator on `grid` (cells of size `h`) with `scheme`
/// and `viscosity` (an implicit solve allowed 100 iterations per cell
/// along x).
fn operator<const D: usize>(grid: MacGrid<D>, h: f64, scheme: Scheme, viscosity: Diffusion) -> Result<NavierStokes<D>, AccuracyError> {
    let viscosity = match viscosity {
        Diffusion::Explicit => Viscosity::Explicit,
        Diffusion::Implicit { tolerance } => Viscosity::Implicit { tolerance, max_iterations: 100 * grid.n[0] },
    };
    Ok(NavierStokes::new(grid, h, scheme).map_err(|e| AccuracyError::Invalid { what: "n", reason: e.to_string() })?.with_viscosity(viscosity))
}

/// `steps` calls of the Navier–Stokes operator `op` with `p` from the
/// velocity `x`; a refused call is the run's error.
fn calls<const D: usize>(op: &NavierStokes<D>, mut x: Vec<f64>, p: [f64; 2], steps: usize) -> Result<Vec<f64>, AccuracyError>
where
    NavierStokes<D>: Forward,
{
    let mut y = vec![0.0; x.len()];
    for step in 0..steps {
        op.forward(&x, &p, &mut y);
        after("Navier–Stokes step", step, op.take_error(), &y)?;
        std::mem::swap(&mut x, &mut y);
    }
    Ok(x)
}

/// The Arnold–Beltrami–Childress flow (`A = B = C = 1`: an exact steady
/// solution of the Euler equations that viscosity makes decay as
/// `e^{−νt}`) on the `n³` periodic box `[0, 2π)³` by the Navier–Stokes
/// operator ([`NavierStokes`] in 3D: sub-steps, the projection by FFT), in
/// calls of Courant number `cfl` on the flow's largest speed (2), each
/// split into stable sub-steps by the operator.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct AbcRun {
    /// Cells per side.
    pub n: usize,
    /// Viscosity ν.
    pub nu: f64,
    /// Final time.
    pub t_end: f64,
    /// Courant number of a call.
    pub cfl: f64,
    /// Advection of the velocity.
    pub scheme: Scheme,
    /// Viscosity in time.
    pub viscosity: Diffusion,
}

impl AbcRun {
    /// The exact solution.
    pub fn exact_solution(&self) -> Abc {
        Abc { coefficients: [1.0; 3], nu: self.nu }
    }

    /// The exact velocity at time `t` on the faces (with the copies).
    fn faces(&self, t: f64) -> Vec<f64> {
        let exact = self.exact_solution();
        on_faces([self.n; 3], LENGTH / self.n as f64, |a, p| exact.velocity(p, t)[a])
    }

    /// Number of calls and the time of each.
    pub fn steps(&self) -> (usize, f64) {
        steps_to(self.t_end, self.cfl * LENGTH / self.n as f64 / 2.0)
    }

    /// The packed velocity `[u, v, w]` at `t_end`.
    pub fn run(&self) -> Result<Vec<f64>, AccuracyError> {
        check_flow(self.n, self.nu, self.t_end, self.cfl)?;
        let n = self.n;
        let cfg = MacGrid::new([n; 3]).with_boundary(Boundary::all(Side::Periodic));
        let op = operator(cfg, LENGTH / n as f64, self.scheme, self.viscosity)?;
        let (steps, dt) = self.steps();
        calls(&op, self.faces(0.0), [self.nu, dt], steps)
    }

    /// Relative L2 error of the velocity `x` (a result of [`AbcRun::run`])
    /// against the exact one at `t_end`, over the faces that hold their own
    /// value (the periodic copies left out).
    pub fn error_of(&self, x: &[f64]) -> f64 {
        let exact = self.faces(self.t_end);
        if x.len() != exact.len() || !all_finite(x) {
            return f64::NAN;
        }
        let n = self.n;
        let (mut own_x, mut own_e) = (Vec::new(), Vec::new());
        let mut start = 0;
        for a in 0..3 {
            let len = |b: usize| n + usize::from(b == a);
            let stride: usize = (0..a).map(len).product();
            let total: usize = (0..3).map(len).product();
            for c in 0..total {
                if (c / stride) % len(a) < n {
                    own_x.push(x[start + c]);
                    own_e.push(exact[start + c]);
                }
            }
            start += total;
        }
        relative_l2(&own_x, &own_e)
    }
}

/// Advection of a scalar.
#[derive(Clone, Copy, Debug, PartialEq)]
pub enum ScalarScheme {
    /// Conservative first-order upwind fluxes ([`AdvectUpwind`]).
    Upwind,
    /// Semi-Lagrangian or MacCormack ([`Advect`]).
    Traced(Scheme),
}

impl ScalarScheme {
    /// Name in reports.
    pub fn name(&self) -> &'static str {
        match self {
            ScalarScheme::Upwind => "upwind",
            ScalarScheme::Traced(s) => scheme_name(*s),
        }
    }
}

/// Translation of `exp(sin x)·cos y` by the constant velocity `(1, 0.5)`
/// on an `n × n` periodic grid, time step `cfl·h/1`.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct TranslationRun {
    /// Cells per side.
    pub n: usize,
    /// Final time.
    pub t_end: f64,
    /// Courant number along x.
    pub cfl: f64,
    /// The scheme.
    pub scheme: ScalarScheme,
}

impl TranslationRun {
    /// The exact solution.
    pub fn exact_solution(&self) -> Translation {
        Translation { length: LENGTH, velocity: (1.0, 0.5) }
    }

    /// Relative L2 error of the scalar at `t_end`.
    pub fn error(&self) -> Result<f64, AccuracyError> {
        if self.n < 4 {
            return Err(AccuracyError::Invalid { what: "n", reason: format!("need at least 4 cells per side, got {}", self.n) });
        }
        positive("t_end", self.t_end)?;
        positive("cfl", self.cfl)?;
        let (n, h) = (self.n, LENGTH / self.n as f64);
        let cfg = periodic_box(n);
        let exact = self.exact_solution();
        let (steps, dt) = steps_to(self.t_end, self.cfl * h);
        let mut x = exact.cells(n, 0.0);
        x.extend(std::iter::repeat_n(exact.velocity.0 / h, cfg.n_face(0)));
        x.extend(std::iter::repeat_n(exact.velocity.1 / h, cfg.n_face(1)));
        let mut y = vec![0.0; x.len()];
        for step in 0..steps {
            match self.scheme {
                ScalarScheme::Upwind => AdvectUpwind { cfg, dt }.forward(&x, &[], &mut y),
                ScalarScheme::Traced(scheme) => Advect { cfg, scheme, dt, smoke: true, velocity: false }.forward(&x, &[], &mut y),
            }
            after("advection", step, None, &y)?;
            std::mem::swap(&mut x, &mut y);
        }
        Ok(relative_l2(&x[..cfg.n_s()], &exact.cells(n, self.t_end)))
    }
}

/// The heat mode `sin(x + 0.3)·cos(2y)` diffusing with `nu` on an `n × n`
/// periodic grid, time step `dt_factor·h²/ν`.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct HeatRun {
    /// Cells per side.
    pub n: usize,
    /// Diffusivity ν.
    pub nu: f64,
    /// Final time.
    pub t_end: f64,
    /// The diffusion number `ν·dt/h²` (at most this; explicit: ≤ 0.25).
    pub dt_factor: f64,
    /// Explicit or implicit.
    pub diffusion: Diffusion,
}

impl HeatRun {
    /// The exact solution.
    pub fn exact_solution(&self) -> HeatMode {
        HeatMode { length: LENGTH, modes: (1.0, 2.0), phase: 0.3, nu: self.nu }
    }

    /// Relative L2 error at `t_end`. The explicit scheme beyond its limit is
    /// refused ([`AccuracyError::Operator`] with [`OpError::Unstable`]).
    pub fn error(&self) -> Result<f64, AccuracyError> {
        if self.n < 4 {
            return Err(AccuracyError::Invalid { what: "n", reason: format!("need at least 4 cells per side, got {}", self.n) });
        }
        positive("nu", self.nu)?;
        positive("t_end", self.t_end)?;
        positive("dt_factor", self.dt_factor)?;
        let (n, h) = (self.n, LENGTH / self.n as f64);
        let cfg = periodic_box(n);
        let (steps, dt) = steps_to(self.t_end, self.dt_factor * h * h / self.nu);
        let kappa = self.nu * dt / (h * h);
        let exact = self.exact_solution();
        let mut x = exact.cells(n, 0.0);
        x.resize(cfg.n_state(), 0.0);
        let mut y = vec![0.0; x.len()];
        let diffuse = diffuser(cfg, true, false, self.diffusion, 100 * n);
        for step in 0..steps {
            let e = diffuse_step(diffuse.as_ref(), &x, kappa, &mut y);
            after("diffusion", step, e, &y)?;
            std::mem::swap(&mut x, &mut y);
        }
        Ok(relative_l2(&x[..cfg.n_s()], &exact.cells(n, self.t_end)))
    }
}
