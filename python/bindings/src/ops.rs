//! The operators diffsim offers Python: a step of a solver
//! ([`StepOp`]: P1's Burgers, P2's smoke) and the benchmarks' losses
//! through whole rollouts ([`P1Loss`], [`SmokeLoss`]), with the functions
//! that make them.

use std::sync::Arc;

use numpy::PyArray1;
use pyo3::prelude::*;
use pyo3::types::PyDict;

use diffsim::check::{CheckParams, check_all};
use diffsim::navier_stokes::{CentralNavierStokes, Centred, PeriodicNavierStokes};
use diffsim::op::{Jvp, Vjp};
use diffsim::problems::burgers::{BurgersEnzyme, P1};
use diffsim::rollout::{Checkpointing, Loss, Repeat, Rollout, RolloutLoss, Wrt};

use super::{DiffsimError, Failure, Operator, PyOp, simulation};

/// `pass`, `fail`, or `inconclusive` (a check that met a kink and could
/// not decide: not a failure).
pub(crate) fn verdict(r: &diffsim::check::FullReport) -> &'static str {
    if r.passed() {
        "pass"
    } else if r.failed() {
        "fail"
    } else {
        "inconclusive"
    }
}

/// A diffsim step operator (no state of its own between calls).
struct StepOp<O>(O);

impl<O: Vjp + Jvp + Send + Sync> PyOp for StepOp<O> {
    fn sizes(&self) -> (usize, usize, usize) {
        (self.0.n_in(), self.0.n_out(), self.0.n_params())
    }
    fn forward(&self, x: &[f64], p: &[f64], y: &mut [f64]) -> Result<(), Failure> {
        self.0.forward(x, p, y);
        self.0.take_error().map_or(Ok(()), |e| Err(simulation(e)))
    }
    fn vjp(&self, x: &[f64], p: &[f64], dy: &[f64], dx: &mut [f64], dp: &mut [f64]) -> Result<(), Failure> {
        dx.fill(0.0);
        dp.fill(0.0);
        let mut dy = dy.to_vec();
        self.0.vjp(x, p, &mut dy, dx, dp);
        self.0.take_error().map_or(Ok(()), |e| Err(simulation(e)))
    }
    fn jvp(&self, x: &[f64], p: &[f64], tx: &[f64], tp: &[f64], y: &mut [f64], ty: &mut [f64]) -> Result<(), Failure> {
        self.0.jvp(x, p, tx, tp, y, ty);
        self.0.take_error().map_or(Ok(()), |e| Err(simulation(e)))
    }
    fn check(&self, x: &[f64], p: &[f64]) -> Result<(&'static str, String), Failure> {
        let r = check_all(&self.0, x, p, &CheckParams::default());
        Ok((verdict(&r), r.to_string()))
    }
    fn smooth_radius(&self, x: &[f64], p: &[f64], dx: &[f64], dp: &[f64]) -> f64 {
        self.0.smooth_radius(x, p, dx, dp)
    }
}

/// P1's loss `L(u_0) = ½·dx·Σ (u_T − u*)²` as an operator of `u_0` (one
/// output), through the whole rollout with the Enzyme-generated step VJPs
/// (periodic √T checkpointing).
struct P1Loss {
    problem: P1,
}

impl P1Loss {
    fn at(&self, x: &[f64]) -> P1 {
        P1 { u0: x.to_vec(), target: self.problem.target.clone(), ..self.problem }
    }
}

impl PyOp for P1Loss {
    fn heavy(&self) -> bool {
        true
    }
    fn sizes(&self) -> (usize, usize, usize) {
        (self.problem.cfg.n, 1, 0)
    }
    fn forward(&self, x: &[f64], _p: &[f64], y: &mut [f64]) -> Result<(), Failure> {
        y[0] = self.at(x).value().map_err(simulation)?;
        Ok(())
    }
    fn vjp(&self, x: &[f64], _p: &[f64], dy: &[f64], dx: &mut [f64], _dp: &mut [f64]) -> Result<(), Failure> {
        let g = self.at(x).grad_enzyme(Checkpointing::periodic_sqrt(self.problem.steps)).map_err(simulation)?;
        for (d, g) in dx.iter_mut().zip(&g.dx0) {
            *d = dy[0] * g;
        }
        Ok(())
    }
    fn jvp(&self, x: &[f64], p: &[f64], tx: &[f64], _tp: &[f64], y: &mut [f64], ty: &mut [f64]) -> Result<(), Failure> {
        // A rollout that fails is a simulation error, not the panic of
        // RolloutLoss's JVP.
        self.forward(x, p, y)?;
        let step = BurgersEnzyme(self.problem.cfg);
        rollout_loss_jvp(Rollout::new(&step, &[], self.problem.steps).map_err(simulation)?, &self.problem.loss(), x, tx, y, ty)
    }
    fn check(&self, x: &[f64], _p: &[f64]) -> Result<(&'static str, String), Failure> {
        let step = BurgersEnzyme(self.problem.cfg);
        rollout_loss_check(Rollout::new(&step, &[], self.problem.steps).map_err(simulation)?, &self.problem.loss(), x)
    }
}

/// The JVP of a rollout's loss with respect to its initial state `x`
/// (forward mode through every step; the caller has run the rollout
/// forward, so a failing one is already its error).
pub(crate) fn rollout_loss_jvp<O: Jvp, L: Loss>(
    rollout: Rollout<'_, O>,
    loss: &L,
    x: &[f64],
    tx: &[f64],
    y: &mut [f64],
    ty: &mut [f64],
) -> Result<(), Failure> {
    let op = RolloutLoss::new(rollout, x, loss, Checkpointing::Store, Wrt::X0).map_err(simulation)?;
    op.jvp(x, &[], tx, &[], y, ty);
    Ok(())
}

/// The three checks of a rollout's loss with respect to its initial state
/// `x`, the VJP under periodic √T checkpointing.
pub(crate) fn rollout_loss_check<O: Vjp + Jvp, L: Loss>(rollout: Rollout<'_, O>, loss: &L, x: &[f64]) -> Result<(&'static str, String), Failure> {
    let mode = Checkpointing::periodic_sqrt(rollout.steps);
    let op = RolloutLoss::new(rollout, x, loss, mode, Wrt::X0).map_err(simulation)?;
    let r = check_all(&op, x, &[], &CheckParams::default());
    Ok((verdict(&r), r.to_string()))
}

/// A smoke benchmark's loss (P2, P4) as an operator of the packed initial
/// state (one output): the rollout forward, its VJP through Enzyme's step
/// adjoints and the implicit adjoint of the pressure solves. The problem
/// owns solver buffers: one call at a time.
struct SmokeLoss<S> {
    problem: std::sync::Mutex<diffsim::problems::SmokeBenchmark<S>>,
    n: usize,
}

impl<S: Vjp + Jvp + Send> PyOp for SmokeLoss<S> {
    fn heavy(&self) -> bool {
        true
    }
    fn sizes(&self) -> (usize, usize, usize) {
        (self.n, 1, 0)
    }
    fn forward(&self, x: &[f64], _p: &[f64], y: &mut [f64]) -> Result<(), Failure> {
        let mut b = self.problem.lock().unwrap_or_else(|e| e.into_inner());
        b.x0.copy_from_slice(x);
        y[0] = b.value().map_err(simulation)?;
        Ok(())
    }
    fn vjp(&self, x: &[f64], _p: &[f64], dy: &[f64], dx: &mut [f64], _dp: &mut [f64]) -> Result<(), Failure> {
        let mut b = self.problem.lock().unwrap_or_else(|e| e.into_inner());
        b.x0.copy_from_slice(x);
        let g = b.grad_in(&mut diffsim::rollout::Workspace::default(), Checkpointing::periodic_sqrt(b.steps)).map_err(simulation)?;
        for (d, g) in dx.iter_mut().zip(&g.dx0) {
            *d = dy[0] * g;
        }
        Ok(())
    }
    fn jvp(&self, x: &[f64], p: &[f64], tx: &[f64], _tp: &[f64], y: &mut [f64], ty: &mut [f64]) -> Result<(), Failure> {
        self.forward(x, p, y)?;
        let b = self.problem.lock().unwrap_or_else(|e| e.into_inner());
        rollout_loss_jvp(Rollout::new(&b.step, &[], b.steps).map_err(simulation)?, &b.loss(), x, tx, y, ty)
    }
    fn check(&self, x: &[f64], _p: &[f64]) -> Result<(&'static str, String), Failure> {
        let b = self.problem.lock().unwrap_or_else(|e| e.into_inner());
        rollout_loss_check(Rollout::new(&b.step, &[], b.steps).map_err(simulation)?, &b.loss(), x)
    }
}

/// A smoke benchmark's loss as an `Operator` named `name`.
fn smoke_loss<S: Vjp + Jvp + Send + 'static>(b: diffsim::problems::SmokeBenchmark<S>, name: String) -> Operator {
    let n = b.x0.len();
    Operator::new(Arc::new(SmokeLoss { problem: std::sync::Mutex::new(b), n }), name)
}

/// A smoke benchmark's data as a dict: `{"x0", "target", "steps"}`.
fn smoke_problem<'py, S>(py: Python<'py>, b: &diffsim::problems::SmokeBenchmark<S>) -> PyResult<Bound<'py, PyDict>> {
    let d = PyDict::new(py);
    d.set_item("x0", PyArray1::from_vec(py, b.x0.clone()))?;
    d.set_item("target", PyArray1::from_vec(py, b.target.clone()))?;
    d.set_item("steps", b.steps)?;
    Ok(d)
}

fn smoke_sizes(what: &str, n: usize, steps: usize, max: usize) -> PyResult<()> {
    if !(4..=max).contains(&n) || steps < 1 {
        return Err(DiffsimError::new_err(format!("{what} needs 4 ≤ n ≤ {max} and steps ≥ 1, got n = {n}, steps = {steps}")));
    }
    Ok(())
}

fn p2(n: usize, steps: usize) -> PyResult<diffsim::problems::smoke::P2> {
    smoke_sizes("P2", n, steps, 1024)?;
    Ok(diffsim::problems::smoke::P2::new(n, steps, diffsim_solvers::smoke::Preconditioner::Multigrid))
}

fn p4(n: usize, steps: usize) -> PyResult<diffsim::problems::smoke::P4> {
    smoke_sizes("P4", n, steps, 256)?;
    Ok(diffsim::problems::smoke::P4::new(n, steps, diffsim_solvers::smoke::Preconditioner::Multigrid))
}

/// P2 of the shared benchmarks (2D smoke, `n × n`, `steps` steps):
/// `{"x0": packed initial state, "target": target smoke, "steps"}`.
#[pyfunction]
pub(crate) fn p2_problem<'py>(py: Python<'py>, n: usize, steps: usize) -> PyResult<Bound<'py, PyDict>> {
    smoke_problem(py, &p2(n, steps)?)
}

/// P2's loss `½·Σ (s_T − s*)²` as an operator of the packed initial state.
#[pyfunction]
pub(crate) fn p2_loss(n: usize, steps: usize) -> PyResult<Operator> {
    Ok(smoke_loss(p2(n, steps)?, format!("p2_loss(n={n}, steps={steps})")))
}

/// P4 of the shared benchmarks (3D smoke, `n³`, `steps` steps), as
/// `p2_problem`.
#[pyfunction]
pub(crate) fn p4_problem<'py>(py: Python<'py>, n: usize, steps: usize) -> PyResult<Bound<'py, PyDict>> {
    smoke_problem(py, &p4(n, steps)?)
}

/// P4's loss as an operator of the packed initial state.
#[pyfunction]
pub(crate) fn p4_loss(n: usize, steps: usize) -> PyResult<Operator> {
    Ok(smoke_loss(p4(n, steps)?, format!("p4_loss(n={n}, steps={steps})")))
}

/// One step of P1's Burgers scheme (upwind advection, explicit diffusion) on
/// a periodic line of `n` cells and length `length`: `u ↦ u_next`, no
/// parameters, Enzyme's VJP.
#[pyfunction]
#[pyo3(signature = (n, dt, nu, length = std::f64::consts::TAU))]
pub(crate) fn burgers_step(n: usize, dt: f64, nu: f64, length: f64) -> PyResult<Operator> {
    if n < 3 {
        return Err(DiffsimError::new_err(format!("n = {n}: need at least 3 cells")));
    }
    for (name, v) in [("dt", dt), ("length", length)] {
        if !(v.is_finite() && v > 0.0) {
            return Err(DiffsimError::new_err(format!("{name} = {v}: must be positive")));
        }
    }
    if !(nu.is_finite() && nu >= 0.0) {
        return Err(DiffsimError::new_err(format!("nu = {nu}: must be zero or positive")));
    }
    let dx = length / n as f64;
    if nu > 0.0 && dt > 0.5 * dx * dx / nu {
        return Err(DiffsimError::new_err(format!("dt = {dt} is unstable for the explicit diffusion: need dt ≤ dx²/(2ν) = {}", 0.5 * dx * dx / nu)));
    }
    let cfg = diffsim_solvers::burgers::Burgers1d { n, dx, dt, nu };
    Ok(Operator::new(Arc::new(StepOp(BurgersEnzyme(cfg))), format!("burgers_step(n={n}, dt={dt}, nu={nu})")))
}

/// P1 of the shared benchmarks at `n` cells and `steps` steps:
/// `{"u0", "target", "dx", "dt", "nu"}`.
#[pyfunction]
pub(crate) fn p1_problem<'py>(py: Python<'py>, n: usize, steps: usize) -> PyResult<Bound<'py, PyDict>> {
    let p = p1(n, steps)?;
    let d = PyDict::new(py);
    d.set_item("u0", PyArray1::from_vec(py, p.u0.clone()))?;
    d.set_item("target", PyArray1::from_vec(py, p.target.clone()))?;
    d.set_item("dx", p.cfg.dx)?;
    d.set_item("dt", p.cfg.dt)?;
    d.set_item("nu", p.cfg.nu)?;
    d.set_item("steps", steps)?;
    Ok(d)
}

fn p1(n: usize, steps: usize) -> PyResult<P1> {
    if n < 3 || steps < 1 {
        return Err(DiffsimError::new_err(format!("P1 needs n ≥ 3 and steps ≥ 1, got n = {n}, steps = {steps}")));
    }
    Ok(P1::new(n, steps))
}

/// P1's loss as an operator of `u0` (`n_in = n`, one output, no
/// parameters): the whole rollout of `steps` steps in diffsim, its VJP
/// through Enzyme's step VJPs.
#[pyfunction]
pub(crate) fn p1_loss(n: usize, steps: usize) -> PyResult<Operator> {
    Ok(Operator::new(Arc::new(P1Loss { problem: p1(n, steps)? }), format!("p1_loss(n={n}, steps={steps})")))
}

/// One step of P2's smoke solver on `n × n` cells (semi-Lagrangian
/// advection, buoyancy, pressure projection by multigrid-preconditioned
/// CG): the packed state (smoke, then the face velocities) in and out.
#[pyfunction]
pub(crate) fn smoke_step(n: usize) -> PyResult<Operator> {
    if !(4..=1024).contains(&n) {
        return Err(DiffsimError::new_err(format!("n = {n}: need 4 ≤ n ≤ 1024")));
    }
    // One solver (with its work buffers) per thread of the batch.
    let step = diffsim::op::PerThread::new(|| diffsim::problems::smoke::P2::new(n, 1, diffsim_solvers::smoke::Preconditioner::Multigrid).step);
    Ok(Operator::new(Arc::new(StepOp(step)), format!("smoke_step(n={n})")))
}

/// One step of incompressible Navier–Stokes on a box of `n` cells per axis
/// (2 or 3 axes, the same cell size on each, the box `length` long along
/// x): the packed MAC velocity `[u, v(, w)]` (each component on its faces,
/// x fastest; on a periodic axis face `n` is the copy of face 0) in and
/// out, the parameters `p = [ν, dt, q…, f…]`. A step is split into stable
/// sub-steps (advection by `scheme`, `"maccormack"` or `"semi_lagrangian"`;
/// viscosity `"explicit"` or `"implicit"`; the projection by FFT on a
/// periodic box, by multigrid CG otherwise); the derivatives with respect
/// to the velocity and every parameter.
///
/// `boundary`: `None` (periodic on every axis) or one `[lower, upper]`
/// pair per axis of `"periodic"`, `"free_slip"`, `"no_slip"`, `"outflow"`
/// or `"inflow"`. Each inflow side adds its faces' inward speeds `q` to the
/// parameters (axis by axis, lower side first, the side's points x
/// fastest; an inflow needs an outflow side). With `forced`, a body force
/// follows: one value per face. With `centred` (periodic boxes only), the
/// velocity in and out is `D` values per cell (component after
/// component), moved to and from the faces by a spectral half-cell shift.
///
/// `solid`: one flag per cell (x fastest), true inside an obstacle (no
/// flow through its faces; the projection by CG). With `drag`, the state
/// carries two numbers after the velocity, `[I, A]`: each call adds the
/// time integral of the pressure force on the obstacles along x over `dt`
/// and the shear sum `Σ σ·ū` of the velocity it returns (Mosaic's surface
/// sums; the mean drag over `m` steps is `ΔI/(m·dt) − ν·ΔA/m`).
#[pyfunction]
#[pyo3(signature = (n, scheme = "maccormack", length = std::f64::consts::TAU, forced = false, centred = false, boundary = None, viscosity = "explicit", solid = None, drag = false))]
#[allow(clippy::too_many_arguments)]
pub(crate) fn navier_stokes_step(
    n: Vec<usize>,
    scheme: &str,
    length: f64,
    forced: bool,
    centred: bool,
    boundary: Option<Vec<[String; 2]>>,
    viscosity: &str,
    solid: Option<Vec<bool>>,
    drag: bool,
) -> PyResult<Operator> {
    use diffsim_solvers::mac::periodic::Periodic;
    use diffsim_solvers::smoke::Scheme;
    let central = scheme == "central";
    let scheme = match scheme {
        "maccormack" => Scheme::MacCormack { limiter: false },
        // The central step does not trace: the box's scheme is unused.
        "semi_lagrangian" | "central" => Scheme::SemiLagrangian,
        other => return Err(DiffsimError::new_err(format!("scheme = {other:?}: expected \"maccormack\", \"semi_lagrangian\" or \"central\""))),
    };
    let viscosity = match viscosity {
        "explicit" => diffsim::navier_stokes::Viscosity::Explicit,
        "implicit" => diffsim::navier_stokes::Viscosity::Implicit { tolerance: 1e-10, max_iterations: 2000 },
        other => return Err(DiffsimError::new_err(format!("viscosity = {other:?}: expected \"explicit\" or \"implicit\""))),
    };
    if !(length.is_finite() && length > 0.0) {
        return Err(DiffsimError::new_err(format!("length = {length}: must be positive")));
    }
    if n.iter().any(|&m| !(4..=512).contains(&m)) {
        return Err(DiffsimError::new_err(format!("n = {n:?}: need 4 ≤ n ≤ 512 cells on each axis")));
    }
    let h = length / n[0] as f64;
    let name = format!("navier_stokes_step(n={n:?})");
    let sides = match &boundary {
        None => None,
        Some(b) if b.len() != n.len() => return Err(DiffsimError::new_err(format!("boundary: {} axes for a box of {}", b.len(), n.len()))),
        Some(b) => Some(b.iter().enumerate().map(|(a, pair)| Ok([side(a, 0, &pair[0])?, side(a, 1, &pair[1])?])).collect::<PyResult<Vec<_>>>()?),
    };
    let periodic = sides.as_ref().is_none_or(|s| s.iter().flatten().all(|&s| s == Side::Periodic));
    if centred && (!periodic || solid.is_some()) {
        return Err(DiffsimError::new_err("centred = True needs a box periodic on every axis without obstacles (the spectral half-cell shift)"));
    }
    if drag && solid.is_none() {
        return Err(DiffsimError::new_err("drag = True needs obstacles (solid)"));
    }
    let cells: usize = n.iter().product();
    if let Some(s) = &solid
        && s.len() != cells
    {
        return Err(DiffsimError::new_err(format!("solid: {} flags for a box of {cells} cells (one per cell, x fastest)", s.len())));
    }
    let fft_box = periodic && solid.is_none() && viscosity == diffsim::navier_stokes::Viscosity::Explicit;
    if central && !(fft_box && !forced) {
        return Err(DiffsimError::new_err("scheme = \"central\" runs a box periodic on every axis without obstacles, explicit viscosity, no body force"));
    }
    if fft_box {
        return match n[..] {
            [nx, ny] => Ok(fft_step(Periodic::new([nx, ny], h, 0.0, scheme), central, forced, centred, name)),
            [nx, ny, nz] => Ok(fft_step(Periodic::new([nx, ny, nz], h, 0.0, scheme), central, forced, centred, name)),
            _ => Err(DiffsimError::new_err(format!("n = {n:?}: give 2 or 3 cell counts, one per axis"))),
        };
    }
    let walls = Walls { sides: sides.unwrap_or_else(|| vec![[Side::Periodic; 2]; n.len()]), solid, drag };
    match n[..] {
        [nx, ny] => box_step([nx, ny], walls, h, scheme, viscosity, forced, name),
        [nx, ny, nz] => box_step([nx, ny, nz], walls, h, scheme, viscosity, forced, name),
        _ => Err(DiffsimError::new_err(format!("n = {n:?}: give 2 or 3 cell counts, one per axis"))),
    }
}

use diffsim_solvers::boundary::{Profile, Side};

/// One side of `navier_stokes_step`'s `boundary` (side `h` of axis `a`).
fn side(a: usize, h: usize, kind: &str) -> PyResult<Side> {
    Ok(match kind {
        "periodic" => Side::Periodic,
        "free_slip" | "closed" => Side::Closed,
        "no_slip" => Side::NoSlip,
        "outflow" => Side::Outflow,
        // The speeds are parameters; the profile only gives their defaults.
        "inflow" => Side::Inflow(Profile::Uniform(0.0)),
        other => {
            return Err(DiffsimError::new_err(format!(
                "boundary[{a}][{h}] = {other:?}: expected \"periodic\", \"free_slip\", \"no_slip\", \"outflow\" or \"inflow\""
            )));
        }
    })
}

/// What a box has besides its cells: the sides (one pair per axis), the
/// solid cells, whether the state carries the drag.
struct Walls {
    sides: Vec<[Side; 2]>,
    solid: Option<Vec<bool>>,
    drag: bool,
}

/// The step on a box with any sides as a Python operator (one per thread
/// of a batch).
fn box_step<const D: usize>(
    n: [usize; D],
    walls: Walls,
    h: f64,
    scheme: diffsim_solvers::smoke::Scheme,
    viscosity: diffsim::navier_stokes::Viscosity,
    forced: bool,
    name: String,
) -> PyResult<Operator>
where
    diffsim::navier_stokes::NavierStokes<D>: Vjp + Jvp,
{
    use diffsim::navier_stokes::NavierStokes;
    let sides: [[Side; 2]; D] = std::array::from_fn(|a| walls.sides[a]);
    let grid = diffsim_solvers::smoke::MacGrid::new(n).with_boundary(diffsim_solvers::boundary::Boundary { sides });
    let Walls { solid, drag, .. } = walls;
    let make = move || {
        let op = NavierStokes::new(grid, h, scheme)?.with_viscosity(viscosity);
        let op = if forced { op.forced() } else { op };
        let Some(solid) = &solid else { return Ok(op) };
        let op = op.with_obstacles(solid)?;
        if drag { op.with_drag() } else { Ok(op) }
    };
    // Checked once here: the same inputs build every thread's copy.
    make().map_err(|e| DiffsimError::new_err(e.to_string()))?;
    Ok(Operator::new(Arc::new(StepOp(diffsim::op::PerThread::new(move || make().expect("checked above")))), name))
}

type Periodic<const D: usize> = diffsim_solvers::mac::periodic::Periodic<D>;

/// The traced schemes' periodic step (forced or not).
fn face_step<const D: usize>(flow: Periodic<D>, forced: bool) -> PeriodicNavierStokes<D> {
    if forced { PeriodicNavierStokes::forced(flow) } else { PeriodicNavierStokes::new(flow) }
}

/// The central scheme's periodic step (never forced: refused before).
fn central_step<const D: usize>(flow: Periodic<D>, _forced: bool) -> CentralNavierStokes<D> {
    CentralNavierStokes::new(flow)
}

/// The step of a periodic box without obstacles, central or traced.
fn fft_step<const D: usize>(flow: Periodic<D>, central: bool, forced: bool, centred: bool, name: String) -> Operator
where
    PeriodicNavierStokes<D>: Vjp + Jvp,
    CentralNavierStokes<D>: Vjp + Jvp,
{
    if central { periodic_step(flow, forced, centred, name, central_step) } else { periodic_step(flow, forced, centred, name, face_step) }
}

/// The periodic step `make(flow, forced)` as a Python operator (one per
/// thread of a batch), on the faces or the centres.
fn periodic_step<const D: usize, O>(flow: Periodic<D>, forced: bool, centred: bool, name: String, make: fn(Periodic<D>, bool) -> O) -> Operator
where
    O: Vjp + Jvp + Send + 'static,
{
    if centred {
        let step = StepOp(diffsim::op::PerThread::new(move || Centred::around(flow, make(flow, forced))));
        Operator::new(Arc::new(CentredStep { flow, forced, make, step }), name)
    } else {
        Operator::new(Arc::new(StepOp(diffsim::op::PerThread::new(move || make(flow, forced)))), name)
    }
}

/// The periodic step on cell-centred values: a step as any other, and a
/// rollout of it ([`PyOp::repeat`]) converts to the faces once, repeats
/// the face step, and converts back once.
struct CentredStep<const D: usize, O> {
    flow: Periodic<D>,
    forced: bool,
    make: fn(Periodic<D>, bool) -> O,
    step: StepOp<diffsim::op::PerThread<Centred<D, O>>>,
}

impl<const D: usize, O> PyOp for CentredStep<D, O>
where
    O: Vjp + Jvp + Send + 'static,
{
    fn sizes(&self) -> (usize, usize, usize) {
        self.step.sizes()
    }
    fn forward(&self, x: &[f64], p: &[f64], y: &mut [f64]) -> Result<(), Failure> {
        self.step.forward(x, p, y)
    }
    fn vjp(&self, x: &[f64], p: &[f64], dy: &[f64], dx: &mut [f64], dp: &mut [f64]) -> Result<(), Failure> {
        self.step.vjp(x, p, dy, dx, dp)
    }
    fn jvp(&self, x: &[f64], p: &[f64], tx: &[f64], tp: &[f64], y: &mut [f64], ty: &mut [f64]) -> Result<(), Failure> {
        self.step.jvp(x, p, tx, tp, y, ty)
    }
    fn check(&self, x: &[f64], p: &[f64]) -> Result<(&'static str, String), Failure> {
        self.step.check(x, p)
    }
    fn smooth_radius(&self, x: &[f64], p: &[f64], dx: &[f64], dp: &[f64]) -> f64 {
        self.step.smooth_radius(x, p, dx, dp)
    }
    fn repeat(&self, steps: usize, mode: Option<Checkpointing>) -> Option<Result<Arc<dyn PyOp>, Failure>> {
        let (flow, forced, step) = (self.flow, self.forced, self.make);
        let make = move || {
            let rollout = Repeat::new(step(flow, forced), steps).expect("a step maps its velocity to itself; steps checked");
            Centred::around(flow, if let Some(m) = mode { rollout.with_checkpointing(m) } else { rollout })
        };
        Some(Ok(Arc::new(Rolled(StepOp(diffsim::op::PerThread::new(make))))))
    }
}

/// A whole rollout as one Python operator: worth a thread per element of a
/// batch, and interruptible.
struct Rolled<O>(StepOp<O>);

impl<O: Vjp + Jvp + Send + Sync> PyOp for Rolled<O> {
    fn sizes(&self) -> (usize, usize, usize) {
        self.0.sizes()
    }
    fn heavy(&self) -> bool {
        true
    }
    fn forward(&self, x: &[f64], p: &[f64], y: &mut [f64]) -> Result<(), Failure> {
        self.0.forward(x, p, y)
    }
    fn vjp(&self, x: &[f64], p: &[f64], dy: &[f64], dx: &mut [f64], dp: &mut [f64]) -> Result<(), Failure> {
        self.0.vjp(x, p, dy, dx, dp)
    }
    fn jvp(&self, x: &[f64], p: &[f64], tx: &[f64], tp: &[f64], y: &mut [f64], ty: &mut [f64]) -> Result<(), Failure> {
        self.0.jvp(x, p, tx, tp, y, ty)
    }
    fn check(&self, x: &[f64], p: &[f64]) -> Result<(&'static str, String), Failure> {
        self.0.check(x, p)
    }
    fn smooth_radius(&self, x: &[f64], p: &[f64], dx: &[f64], dp: &[f64]) -> f64 {
        self.0.smooth_radius(x, p, dx, dp)
    }
}

/// The coupled oscillators of the half-inverse-gradients problem
/// (`kind`: `"linear"`, 24 RK4 steps of 0.5, or `"nonlinear"`, 96 steps of
/// 0.125): the initial state `(x₁, x₂, v₁, v₂)` and one control per step
/// (the parameters `p`) in, the final state out; Enzyme's derivatives.
#[pyfunction]
pub(crate) fn oscillators(kind: &str) -> PyResult<Operator> {
    let op = match kind {
        "linear" => diffsim::problems::oscillators::Oscillators::linear(),
        "nonlinear" => diffsim::problems::oscillators::Oscillators::nonlinear(),
        _ => return Err(DiffsimError::new_err(format!("oscillators: kind {kind:?} is not \"linear\" or \"nonlinear\""))),
    };
    Ok(Operator::new(Arc::new(StepOp(op)), format!("oscillators({kind:?})")))
}
