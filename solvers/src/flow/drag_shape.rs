//! Minimum-drag shapes of a given area in a steady flow, by L-BFGS (argmin)
//! on the gradient of the steady drag ([`SteadyFlow::force_gradient`]): in
//! the channel of Schäfer & Turek's case 2D-1 (Re 20 at the benchmark's
//! inflow) or in a free stream (a wide box, [`Stream::Free`]).
//!
//! The body is a Fourier shape about the cylinder's centre,
//! `r(θ) = r₀ + Σ_{k=2..K} aₖ cos kθ + bₖ sin kθ`. The modes `k = 1` are left
//! out (to first order they translate the body, whose position stays
//! fixed). The area `π r₀² + (π/2)·Σ(aₖ² + bₖ²)` is held exactly by
//! elimination: `r₀` follows from the other coefficients, so the optimiser
//! moves on the constraint surface and its gradient is the projected
//! gradient.

use std::cell::RefCell;
use std::rc::Rc;

use argmin::core::{CostFunction, Error, Executor, Gradient, State, TerminationReason};
use argmin::solver::linesearch::BacktrackingLineSearch;
use argmin::solver::linesearch::condition::ArmijoCondition;
use argmin::solver::quasinewton::LBFGS;

use super::cylinder::{DIAMETER, coefficients, force_box, poiseuille, schafer_turek};
use super::{Convection, Flow2d, FlowError, NewtonParams, Shape, ShapeError, SteadyFlow, WallSpeed};
use crate::boundary::{Boundary, Profile, Side};
use crate::nonsmooth::{SamplingParams, gradient_sampling};

/// The flow a body sits in.
#[derive(Clone, Copy, Debug, PartialEq)]
pub enum Stream {
    /// Schäfer & Turek's channel, 2.2 × 0.41 with the body at (0.2, 0.2)
    /// and a parabolic inflow of peak `u_max`: the cylinder blocks 24 % of
    /// its height.
    Channel,
    /// A square box `2·half_width` diameters wide with the body at its
    /// centre: a uniform inflow `Ū = 2·u_max/3` on the left, outflow on the
    /// right, the top and bottom no-slip walls sliding at `Ū` (so they
    /// carry the free stream and shed no boundary layer). An unbounded
    /// stream as far as the box reaches.
    Free {
        /// Distance from the body's centre to each side, in diameters.
        half_width: f64,
    },
}

/// A [`Stream`] on a grid: what a solve of the steady flow around a body
/// in it needs.
#[derive(Clone, Debug, PartialEq)]
pub struct Setting {
    /// The grid and sides.
    pub cfg: Flow2d,
    /// Where bodies are centred.
    pub center: [f64; 2],
    /// The cylinder of diameter [`DIAMETER`] there.
    pub cylinder: Shape,
    /// Peak inflow speed of the channel (the free stream's speed is
    /// `2·u_max/3`, so that `Re = Ū·D/ν` alike).
    pub u_max: f64,
    /// The flow without a body: Newton's start.
    pub start: Vec<f64>,
    /// The control volume of the force, cells `[i0, i1) × [j0, j1)`: one
    /// diameter around the cylinder's bounding box.
    pub cells: [usize; 4],
}

impl Stream {
    /// The stream at `cells_per_d` cells per diameter and peak inflow
    /// `u_max`. A free stream's box has `round(2·half_width·cells_per_d)`
    /// cells a side; it must reach beyond the force's control volume
    /// (`half_width ≥ 2`), else [`FlowError::Grid`].
    pub fn setting(self, cells_per_d: usize, u_max: f64) -> Result<Setting, FlowError> {
        match self {
            Stream::Channel => {
                let (cfg, cylinder) = schafer_turek(cells_per_d, u_max);
                let start = poiseuille(&cfg, u_max);
                Ok(Setting { cells: force_box(&cfg), cfg, center: [0.2, 0.2], cylinder, u_max, start })
            }
            Stream::Free { half_width } => {
                if !(half_width.is_finite() && half_width >= 2.0) {
                    return Err(FlowError::Grid);
                }
                let h = DIAMETER / cells_per_d as f64;
                // An even count puts the centre on a grid node, as in the channel.
                let n = 2 * (half_width * cells_per_d as f64).round() as usize;
                let ubar = 2.0 * u_max / 3.0;
                let cfg = Flow2d {
                    nx: n,
                    ny: n,
                    h,
                    nu: 1e-3,
                    boundary: Boundary { sides: [[Side::Inflow(Profile::Uniform(ubar)), Side::Outflow], [Side::Closed, Side::Closed]] },
                    wall_speed: WallSpeed { bottom: ubar, top: ubar, ..WallSpeed::default() },
                    convection: Convection::Second,
                };
                let c = 0.5 * n as f64 * h;
                let mut start = cfg.rest();
                start[..cfg.n_u()].fill(ubar);
                let reach = (1.5 * cells_per_d as f64).round() as usize;
                let cells = [n / 2 - reach, n / 2 + reach, n / 2 - reach, n / 2 + reach];
                Ok(Setting { cfg, center: [c, c], cylinder: Shape::Circle { center: [c, c], radius: 0.5 * DIAMETER }, u_max, start, cells })
            }
        }
    }
}

/// What to optimise.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct DragShapeParams {
    /// The flow around the body.
    pub stream: Stream,
    /// Grid cells per cylinder diameter (a multiple of 10).
    pub cells_per_d: usize,
    /// Highest Fourier mode `K` (modes 2..=K, cosine and sine).
    pub modes: usize,
    /// Peak inflow speed of the channel (0.3 for Re 20; `Re =
    /// (2/3)·u_max·D/ν`; a free stream flows at `2·u_max/3`).
    pub u_max: f64,
    /// L-BFGS iterations at most.
    pub max_iterations: usize,
    /// Stop when the projected gradient has shrunk by this factor.
    pub gradient_reduction: f64,
    /// Iterations of gradient sampling ([`crate::nonsmooth`]) after
    /// L-BFGS when it stopped short of `gradient_reduction` (at a kink of
    /// the discrete drag, where its line search stalls); 0 for none.
    pub sampling_iterations: usize,
}

/// The former name of [`DragShapeParams`].
#[deprecated(note = "renamed DragShapeParams")]
pub type DragShapeOptions = DragShapeParams;

impl Default for DragShapeParams {
    /// The channel of case 2D-1 (Re 20) at 20 cells per diameter, modes
    /// 2..=8, at most 60 L-BFGS iterations until the projected gradient
    /// shrank 100×, then at most 20 of gradient sampling (`diffsim
    /// experiment drag-shape`'s defaults).
    fn default() -> Self {
        DragShapeParams {
            stream: Stream::Channel,
            cells_per_d: 20,
            modes: 8,
            u_max: 0.3,
            max_iterations: 60,
            gradient_reduction: 100.0,
            sampling_iterations: 20,
        }
    }
}

impl DragShapeParams {
    /// The Reynolds number `Ū·D/ν`, `Ū = 2·u_max/3`.
    pub fn reynolds(&self) -> f64 {
        2.0 * self.u_max / 3.0 * DIAMETER / 1e-3
    }
}

/// One accepted iterate.
#[derive(Clone, Debug, PartialEq)]
pub struct DragIterate {
    /// Drag coefficient.
    pub cd: f64,
    /// Norm of the projected gradient of `c_D`.
    pub gradient_norm: f64,
    /// The shape.
    pub shape: Shape,
}

/// How an optimisation went.
#[derive(Clone, Debug, PartialEq)]
pub struct DragShapeResult {
    /// Drag coefficient of the start (the cylinder, unless
    /// [`optimise_from`] started elsewhere).
    pub cd_start: f64,
    /// Drag coefficient of the final shape.
    pub cd_end: f64,
    /// Exact area of the start and final shapes.
    pub area_start: f64,
    /// See `area_start`.
    pub area_end: f64,
    /// Solid area the grid's cut sees, start and end (`Cut::solid_area`).
    pub cut_area_start: f64,
    /// See `cut_area_start`.
    pub cut_area_end: f64,
    /// Projected gradient norms at the start and the end.
    pub gradient_start: f64,
    /// See `gradient_start`.
    pub gradient_end: f64,
    /// L-BFGS iterations.
    pub iterations: usize,
    /// Steady solves (cost evaluations).
    pub solves: usize,
    /// Every accepted iterate, the start first.
    pub history: Vec<DragIterate>,
    /// The final shape.
    pub shape: Shape,
    /// Why L-BFGS stopped early, if it did (else it met the gradient
    /// tolerance or ran its iterations).
    pub stopped: Option<String>,
    /// Gradient sampling after L-BFGS, if it ran: its iterations, and the
    /// smallest element of the hull of the projected gradients sampled
    /// around the final shape (the stationarity measure at a kink) with
    /// the radius of that sample (in the coefficients `q`).
    pub sampling: Option<SamplingSummary>,
}

/// What gradient sampling did after L-BFGS ([`DragShapeResult::sampling`]).
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct SamplingSummary {
    /// Iterations run.
    pub iterations: usize,
    /// Steps it accepted (added to the history).
    pub steps: usize,
    /// The smallest element of the sampled gradients' hull, final shape.
    pub min_norm: f64,
    /// The sampling ball's radius there (in `q`).
    pub radius: f64,
    /// `min_norm` within the tolerance at the smallest radius.
    pub converged: bool,
}

/// The steady flow around `shape` in `setting`, by Newton from `start`.
fn solve_in(setting: &Setting, shape: &Shape, start: &[f64]) -> Result<(SteadyFlow, super::SteadyState), FlowError> {
    let flow = SteadyFlow::new(setting.cfg, std::slice::from_ref(shape))?;
    let state = flow.solve(start, &NewtonParams::default())?;
    Ok((flow, state))
}

/// The steady drag of one shape in `setting`: `(c_D, ∂c_D/∂params, the
/// state's velocity)`, Newton starting from `start`.
pub fn steady_drag(setting: &Setting, shape: &Shape, start: &[f64]) -> Result<(f64, Vec<f64>, Vec<f64>), FlowError> {
    let (flow, state) = solve_in(setting, shape, start)?;
    let scale = coefficients([1.0, 0.0], setting.u_max)[0];
    let cd = flow.force(&state, setting.cells)[0] * scale;
    let grad = flow.force_gradient(&state, setting.cells, [scale, 0.0]);
    Ok((cd, grad, state.x))
}

/// The steady drag coefficient of `shape` in `setting` (Newton from the
/// flow without a body): for re-simulating an optimised shape on another
/// grid.
pub fn drag_coefficient(setting: &Setting, shape: &Shape) -> Result<f64, FlowError> {
    let (flow, state) = solve_in(setting, shape, &setting.start)?;
    Ok(flow.force(&state, setting.cells)[0] * coefficients([1.0, 0.0], setting.u_max)[0])
}

/// The Fourier body about `center` with free coefficients `q = (a₂…a_K,
/// b₂…b_K)` (`K = modes`, `a₁ = b₁ = 0`) and `r₀` chosen so that the area
/// is `area`; `None` when no positive `r₀` fits.
pub fn shape_at_area(area: f64, modes: usize, center: [f64; 2], q: &[f64]) -> Option<Shape> {
    let m = modes - 1;
    assert_eq!(q.len(), 2 * m, "shape_at_area: coefficient count");
    let squares: f64 = q.iter().map(|c| c * c).sum();
    let r0sq = area / std::f64::consts::PI - 0.5 * squares;
    if r0sq <= 0.0 {
        return None;
    }
    let cos = std::iter::once(0.0).chain(q[..m].iter().copied()).collect();
    let sin = std::iter::once(0.0).chain(q[m..].iter().copied()).collect();
    Some(Shape::Fourier { center, r0: r0sq.sqrt(), cos, sin })
}

/// The gradient with respect to the free coefficients `q` of
/// [`shape_at_area`] (at `area`) from the gradient `full` with respect to
/// the shape's parameters `[cx, cy, r₀, a₁…a_K, b₁…b_K]`: `∂r₀/∂q =
/// −q/(2·r₀)` (the projected gradient on the constant-area surface).
pub fn reduced_gradient(full: &[f64], q: &[f64], area: f64, modes: usize) -> Vec<f64> {
    let (m, k) = (modes - 1, modes);
    let r0 = (area / std::f64::consts::PI - 0.5 * q.iter().map(|c| c * c).sum::<f64>()).sqrt();
    (0..2 * m)
        .map(|i| {
            let direct = if i < m { full[3 + 1 + i] } else { full[3 + k + 1 + (i - m)] };
            direct - full[2] * q[i] / (2.0 * r0)
        })
        .collect()
}

/// A cached evaluation `(z, c_D, ∂c_D/∂z)`.
type Evaluation = (Vec<f64>, f64, Vec<f64>);

/// The optimisation problem in scaled free coefficients `z = q/s`.
struct Problem {
    setting: Setting,
    modes: usize,
    area: f64,
    scale: f64,
    /// Last evaluation: `(z, c_D, ∂c_D/∂z)`.
    cache: RefCell<Option<Evaluation>>,
    /// The last steady velocity (Newton's next start).
    start: Rc<RefCell<Vec<f64>>>,
    /// Shared with the caller, which reads them whatever way the run ends.
    error: Rc<RefCell<Option<FlowError>>>,
    history: Rc<RefCell<Vec<DragIterate>>>,
    solves: Rc<RefCell<usize>>,
    /// Cost evaluations since the last gradient (the line search's trials).
    trials: RefCell<usize>,
}

/// Line-search trials after which the search is given up: the step has
/// halved 40 times (argmin's backtracking search has no limit of its own,
/// and at a kink of the discrete drag no step may satisfy Armijo's rule).
const MAX_TRIALS: usize = 40;

impl Problem {
    fn shape(&self, q: &[f64]) -> Option<Shape> {
        shape_at_area(self.area, self.modes, self.setting.center, q)
    }

    /// `c_D` and its gradient in `z`, cached; `None` for a shape that is
    /// not a body in the domain.
    fn evaluate(&self, z: &[f64]) -> Result<Option<(f64, Vec<f64>)>, FlowError> {
        if let Some((zc, cd, g)) = self.cache.borrow().as_ref()
            && zc == z
        {
            return Ok(Some((*cd, g.clone())));
        }
        let q: Vec<f64> = z.iter().map(|v| v * self.scale).collect();
        let Some((cd, gq)) = drag_at(&self.setting, self.modes, &q, &self.start, &self.solves)? else { return Ok(None) };
        let g: Vec<f64> = gq.iter().map(|v| v * self.scale).collect();
        *self.cache.borrow_mut() = Some((z.to_vec(), cd, g.clone()));
        Ok(Some((cd, g)))
    }
}

/// `c_D` and its projected gradient in the free coefficients `q` of the
/// body [`shape_at_area`]`(the cylinder's area, modes, centre, q)` in
/// `setting`, Newton from `start` (which becomes the new state; `solves`
/// counts the solve); `None` for a shape that is not a body in the domain.
fn drag_at(setting: &Setting, modes: usize, q: &[f64], start: &RefCell<Vec<f64>>, solves: &RefCell<usize>) -> Result<Option<(f64, Vec<f64>)>, FlowError> {
    let area = setting.cylinder.area();
    let Some(shape) = shape_at_area(area, modes, setting.center, q) else { return Ok(None) };
    let from = start.borrow().clone();
    let (cd, full, x) = match steady_drag(setting, &shape, &from) {
        Ok(v) => v,
        // Not a body in the domain (validated before any solve).
        Err(FlowError::Shape(_)) => return Ok(None),
        Err(e) => return Err(e),
    };
    *solves.borrow_mut() += 1;
    *start.borrow_mut() = x;
    Ok(Some((cd, reduced_gradient(&full, q, area, modes))))
}

impl CostFunction for Problem {
    type Param = Vec<f64>;
    type Output = f64;

    fn cost(&self, z: &Vec<f64>) -> Result<f64, Error> {
        *self.trials.borrow_mut() += 1;
        if *self.trials.borrow() > MAX_TRIALS {
            return Err(Error::msg(format!(
                "the line search found no decrease of the drag in {MAX_TRIALS} halvings of the step (a kink of the discrete drag)"
            )));
        }
        match self.evaluate(z) {
            Ok(Some((cd, _))) => Ok(cd),
            // Not a body in the domain: a cost the line search backs away from.
            Ok(None) => Ok(1e6),
            Err(e) => {
                *self.error.borrow_mut() = Some(e);
                Err(Error::msg(e.to_string()))
            }
        }
    }
}

impl Gradient for Problem {
    type Param = Vec<f64>;
    type Gradient = Vec<f64>;

    fn gradient(&self, z: &Vec<f64>) -> Result<Vec<f64>, Error> {
        *self.trials.borrow_mut() = 0;
        match self.evaluate(z) {
            Ok(Some((cd, g))) => {
                let q: Vec<f64> = z.iter().map(|v| v * self.scale).collect();
                let shape = self.shape(&q).expect("an evaluated shape");
                let norm = g.iter().map(|v| v * v).sum::<f64>().sqrt() / self.scale;
                self.history.borrow_mut().push(DragIterate { cd, gradient_norm: norm, shape });
                Ok(g)
            }
            Ok(None) => Err(Error::msg("the gradient was asked at a shape outside the domain")),
            Err(e) => {
                *self.error.borrow_mut() = Some(e);
                Err(Error::msg(e.to_string()))
            }
        }
    }
}

/// Minimises the drag at fixed area from the cylinder of the stream.
/// Errors: a steady solve that fails (the first one, or one the optimiser
/// asks for).
pub fn optimise(opts: &DragShapeParams) -> Result<DragShapeResult, FlowError> {
    optimise_from(opts, &vec![0.0; 2 * opts.modes.saturating_sub(1)])
}

/// The body of [`shape_at_area`]`(the cylinder's area, modes, centre, q)`
/// in `setting`, checked: `q = (a₂…a_K, b₂…b_K)` of the right length,
/// leaving a positive `r₀`, a body inside the domain.
pub fn start_shape(setting: &Setting, modes: usize, q: &[f64]) -> Result<Shape, ShapeError> {
    let expected = 2 * modes.saturating_sub(1);
    if q.len() != expected {
        return Err(ShapeError::Parameters { expected, given: q.len() });
    }
    let area = setting.cylinder.area();
    let shape = shape_at_area(area, modes.max(1), setting.center, q).ok_or(ShapeError::NoRadiusForArea { area })?;
    shape.validate(&setting.cfg)?;
    Ok(shape)
}

/// [`optimise`] from the body [`start_shape`]`(setting, opts.modes, q0)`
/// instead of the cylinder: to continue an optimum of a coarser grid or
/// another stream. Errors: that body's ([`FlowError::Shape`]); then as
/// [`optimise`].
pub fn optimise_from(opts: &DragShapeParams, q0: &[f64]) -> Result<DragShapeResult, FlowError> {
    let setting = opts.stream.setting(opts.cells_per_d, opts.u_max)?;
    if opts.modes < 2 {
        return Err(FlowError::Grid);
    }
    let first = start_shape(&setting, opts.modes, q0).map_err(FlowError::Shape)?;
    let (cfg, area) = (setting.cfg, setting.cylinder.area());
    let start = Rc::new(RefCell::new(setting.start.clone()));
    let sampling_setting = setting.clone();
    // The start, and the scale that makes L-BFGS's first (unit) step move
    // the boundary by about a tenth of the radius.
    let probe = Problem {
        setting,
        modes: opts.modes,
        area,
        scale: 1.0,
        cache: RefCell::new(None),
        start: start.clone(),
        error: Rc::new(RefCell::new(None)),
        history: Rc::new(RefCell::new(Vec::new())),
        solves: Rc::new(RefCell::new(0)),
        trials: RefCell::new(0),
    };
    // (At scale 1, z = q.)
    let (cd_start, g0) = probe.evaluate(q0)?.expect("start_shape checked the body as the solve does");
    let g0_norm = g0.iter().map(|v| v * v).sum::<f64>().sqrt();
    let scale = (0.1 * 0.5 * DIAMETER / g0_norm.max(1e-12)).sqrt();
    // The start's evaluation carries over (z = q/s; ∂c_D/∂z = s·∂c_D/∂q).
    let z0: Vec<f64> = q0.iter().map(|q| q / scale).collect();
    let cached = (z0.clone(), cd_start, g0.iter().map(|v| v * scale).collect());
    let problem = Problem { scale, cache: RefCell::new(Some(cached)), ..probe };
    let linesearch = BacktrackingLineSearch::new(ArmijoCondition::new(1e-4).expect("a valid Armijo constant")).rho(0.5).expect("a valid contraction");
    let solver = LBFGS::new(linesearch, 8)
        .with_tolerance_grad(g0_norm * scale / opts.gradient_reduction)
        .expect("a non-negative tolerance")
        .with_tolerance_cost(0.0)
        .expect("a non-negative tolerance");
    let (error, history, solves) = (problem.error.clone(), problem.history.clone(), problem.solves.clone());
    let run = Executor::new(problem, solver).configure(|s| s.param(z0).max_iters(opts.max_iterations as u64)).run();
    if let Some(e) = error.borrow_mut().take() {
        return Err(e);
    }
    // A run that stopped otherwise (a line search finding no decrease at a
    // kink of the discrete drag: L-BFGS ends with the search's error as
    // its reason) ends where it was: its iterates stand.
    let (iterations, stopped) = match run {
        Ok(r) => {
            let why = match r.state().get_termination_reason() {
                Some(TerminationReason::SolverExit(why)) => Some(why.clone()),
                _ => None,
            };
            (r.state().get_iter() as usize, why)
        }
        Err(e) => (history.borrow().len().saturating_sub(1), Some(e.to_string())),
    };
    let mut history = history.borrow().clone();
    let sampling =
        if opts.sampling_iterations > 0 && history.last().expect("at least the start").gradient_norm > history[0].gradient_norm / opts.gradient_reduction {
            Some(sample_from(opts, &sampling_setting, &start, &solves, &mut history)?)
        } else {
            None
        };
    let last = history.last().cloned().expect("at least the start");
    let cut_area = |s: &Shape| super::Cut::new(&cfg, std::slice::from_ref(s)).solid_area(&cfg);
    Ok(DragShapeResult {
        cd_start,
        cd_end: last.cd,
        area_start: area,
        area_end: last.shape.area(),
        cut_area_start: cut_area(&first),
        cut_area_end: cut_area(&last.shape),
        gradient_start: history[0].gradient_norm,
        gradient_end: last.gradient_norm,
        iterations,
        solves: *solves.borrow(),
        stopped,
        sampling,
        shape: last.shape.clone(),
        history,
    })
}

/// The free coefficients `q = (a₂…a_K, b₂…b_K)` of a Fourier body.
fn free_coefficients(shape: &Shape, modes: usize) -> Vec<f64> {
    match shape {
        Shape::Fourier { cos, sin, .. } => cos[1..modes].iter().chain(&sin[1..modes]).copied().collect(),
        _ => unreachable!("the optimiser's bodies are Fourier bodies"),
    }
}

/// Gradient sampling from the last iterate of `history` (appending the
/// steps it accepts): balls of radius h/2 down to h/32 in the coefficients
/// `q`, as many samples as coefficients + 1, stationary when the sampled
/// hull's smallest gradient has shrunk `gradient_reduction` times from the
/// start's gradient.
fn sample_from(
    opts: &DragShapeParams,
    setting: &Setting,
    start: &Rc<RefCell<Vec<f64>>>,
    solves: &Rc<RefCell<usize>>,
    history: &mut Vec<DragIterate>,
) -> Result<SamplingSummary, FlowError> {
    let (area, modes, center) = (setting.cylinder.area(), opts.modes, setting.center);
    let last = history.last().cloned().expect("at least the start");
    let q0 = free_coefficients(&last.shape, modes);
    let evaluate = |q: &[f64]| drag_at(setting, modes, q, start, solves);
    let (cd0, g0) = evaluate(&q0)?.expect("an iterate is a body in the domain");
    let h = DIAMETER / opts.cells_per_d as f64;
    let sampling = SamplingParams {
        radius: 0.5 * h,
        min_radius: h / 32.0,
        samples: q0.len() + 1,
        max_iterations: opts.sampling_iterations,
        tolerance: history[0].gradient_norm / opts.gradient_reduction,
        seed: 1,
    };
    let out = gradient_sampling(evaluate, &q0, cd0, &g0, &sampling)?;
    let norm = |v: &[f64]| v.iter().map(|a| a * a).sum::<f64>().sqrt();
    for (q, cd, g) in &out.accepted {
        let shape = shape_at_area(area, modes, center, q).expect("an accepted point is a body");
        history.push(DragIterate { cd: *cd, gradient_norm: norm(g), shape });
    }
    Ok(SamplingSummary { iterations: out.iterations, steps: out.accepted.len(), min_norm: out.min_norm, radius: out.radius, converged: out.converged })
}
