//! Minimum-drag shapes of a given area in the steady channel flow of
//! Schäfer & Turek's case 2D-1 (Re 20 at the benchmark's inflow), by L-BFGS
//! (argmin) on the gradient of the steady drag ([`SteadyFlow::force_gradient`]).
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

use argmin::core::{CostFunction, Error, Executor, Gradient, State};
use argmin::solver::linesearch::BacktrackingLineSearch;
use argmin::solver::linesearch::condition::ArmijoCondition;
use argmin::solver::quasinewton::LBFGS;

use super::cylinder::{DIAMETER, coefficients, force_box, poiseuille, schafer_turek, steady_in_channel};
use super::{Flow2d, FlowError, NewtonOptions, Shape, SteadyFlow};

/// What to optimise.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct DragShapeOptions {
    /// Grid cells per cylinder diameter (a multiple of 10).
    pub cells_per_d: usize,
    /// Highest Fourier mode `K` (modes 2..=K, cosine and sine).
    pub modes: usize,
    /// Peak inflow speed (0.3 for Re 20; `Re = (2/3)·u_max·D/ν`).
    pub u_max: f64,
    /// L-BFGS iterations at most.
    pub max_iterations: usize,
    /// Stop when the projected gradient has shrunk by this factor.
    pub gradient_reduction: f64,
}

impl DragShapeOptions {
    /// The Reynolds number `Ū·D/ν` of the channel, `Ū = 2·u_max/3`.
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
    /// Drag coefficient of the cylinder.
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
    /// Why the optimiser stopped early, if it did (else it met the
    /// gradient tolerance or ran its iterations).
    pub stopped: Option<String>,
}

/// The steady drag of one shape in the channel: `(c_D, ∂c_D/∂params, the
/// state's velocity)`, Newton starting from `start`.
pub fn steady_drag(cfg: &Flow2d, shape: &Shape, u_max: f64, start: &[f64]) -> Result<(f64, Vec<f64>, Vec<f64>), FlowError> {
    let flow = SteadyFlow::new(*cfg, std::slice::from_ref(shape))?;
    let state = flow.solve(start, &NewtonOptions::default())?;
    let cells = force_box(cfg);
    let scale = coefficients([1.0, 0.0], u_max)[0];
    let cd = flow.force(&state, cells)[0] * scale;
    let grad = flow.force_gradient(&state, cells, [scale, 0.0]);
    Ok((cd, grad, state.x))
}

/// The steady drag coefficient of `shape` in the benchmark's channel at
/// `cells_per_d` cells per diameter and peak inflow `u_max` (Newton from
/// Poiseuille flow): for re-simulating an optimised shape on another grid.
pub fn drag_coefficient(cells_per_d: usize, shape: &Shape, u_max: f64) -> Result<f64, FlowError> {
    let (flow, state) = steady_in_channel(cells_per_d, shape, u_max)?;
    Ok(flow.force(&state, force_box(flow.config()))[0] * coefficients([1.0, 0.0], u_max)[0])
}

/// The Fourier body about the cylinder's centre `(0.2, 0.2)` with free
/// coefficients `q = (a₂…a_K, b₂…b_K)` (`K = modes`, `a₁ = b₁ = 0`) and
/// `r₀` chosen so that the area is `area`; `None` when no positive `r₀`
/// fits.
pub fn shape_at_area(area: f64, modes: usize, q: &[f64]) -> Option<Shape> {
    let m = modes - 1;
    assert_eq!(q.len(), 2 * m, "shape_at_area: coefficient count");
    let squares: f64 = q.iter().map(|c| c * c).sum();
    let r0sq = area / std::f64::consts::PI - 0.5 * squares;
    if r0sq <= 0.0 {
        return None;
    }
    let cos = std::iter::once(0.0).chain(q[..m].iter().copied()).collect();
    let sin = std::iter::once(0.0).chain(q[m..].iter().copied()).collect();
    Some(Shape::Fourier { center: [0.2, 0.2], r0: r0sq.sqrt(), cos, sin })
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
    cfg: Flow2d,
    u_max: f64,
    modes: usize,
    area: f64,
    scale: f64,
    /// Last evaluation: `(z, c_D, ∂c_D/∂z)`.
    cache: RefCell<Option<Evaluation>>,
    /// The last steady velocity (Newton's next start).
    start: RefCell<Vec<f64>>,
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
        shape_at_area(self.area, self.modes, q)
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
        let Some(shape) = self.shape(&q) else { return Ok(None) };
        let start = self.start.borrow().clone();
        let (cd, full, x) = match steady_drag(&self.cfg, &shape, self.u_max, &start) {
            Ok(v) => v,
            // Not a body in the domain (validated before any solve).
            Err(FlowError::Shape(_)) => return Ok(None),
            Err(e) => return Err(e),
        };
        *self.solves.borrow_mut() += 1;
        *self.start.borrow_mut() = x;
        let g: Vec<f64> = reduced_gradient(&full, &q, self.area, self.modes).iter().map(|v| v * self.scale).collect();
        *self.cache.borrow_mut() = Some((z.to_vec(), cd, g.clone()));
        Ok(Some((cd, g)))
    }
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

/// Minimises the drag at fixed area from the cylinder of the benchmark.
/// Errors: a steady solve that fails (the first one, or one the optimiser
/// asks for).
pub fn optimise(opts: &DragShapeOptions) -> Result<DragShapeResult, FlowError> {
    let (cfg, circle) = schafer_turek(opts.cells_per_d, opts.u_max);
    let m = opts.modes.saturating_sub(1);
    if m == 0 {
        return Err(FlowError::Grid);
    }
    let area = circle.area();
    let start = poiseuille(&cfg, opts.u_max);
    // The start, and the scale that makes L-BFGS's first (unit) step move
    // the boundary by about a tenth of the radius.
    let q0 = vec![0.0; 2 * m];
    let probe = Problem {
        cfg,
        u_max: opts.u_max,
        modes: opts.modes,
        area,
        scale: 1.0,
        cache: RefCell::new(None),
        start: RefCell::new(start),
        error: Rc::new(RefCell::new(None)),
        history: Rc::new(RefCell::new(Vec::new())),
        solves: Rc::new(RefCell::new(0)),
        trials: RefCell::new(0),
    };
    let (cd_start, g0) = probe.evaluate(&q0)?.expect("the cylinder is a body in the domain");
    let g0_norm = g0.iter().map(|v| v * v).sum::<f64>().sqrt();
    let scale = (0.1 * 0.5 * DIAMETER / g0_norm.max(1e-12)).sqrt();
    // The start's evaluation carries over (z = 0 at any scale; ∂c_D/∂z = s·∂c_D/∂q).
    let cached = (q0.clone(), cd_start, g0.iter().map(|v| v * scale).collect());
    let problem = Problem { scale, cache: RefCell::new(Some(cached)), ..probe };
    let linesearch = BacktrackingLineSearch::new(ArmijoCondition::new(1e-4).expect("a valid Armijo constant")).rho(0.5).expect("a valid contraction");
    let solver = LBFGS::new(linesearch, 8)
        .with_tolerance_grad(g0_norm * scale / opts.gradient_reduction)
        .expect("a non-negative tolerance")
        .with_tolerance_cost(0.0)
        .expect("a non-negative tolerance");
    let (error, history, solves) = (problem.error.clone(), problem.history.clone(), problem.solves.clone());
    let run = Executor::new(problem, solver).configure(|s| s.param(q0.clone()).max_iters(opts.max_iterations as u64)).run();
    if let Some(e) = error.borrow_mut().take() {
        return Err(e);
    }
    // A run that stopped otherwise (a line search finding no decrease at a
    // kink of the discrete drag) ends where it was: its iterates stand.
    let (iterations, stopped) = match run {
        Ok(r) => (r.state().get_iter() as usize, None),
        Err(e) => (history.borrow().len().saturating_sub(1), Some(e.to_string())),
    };
    let history = history.borrow().clone();
    let last = history.last().cloned().expect("at least the start");
    let cut_area = |s: &Shape| super::Cut::new(&cfg, std::slice::from_ref(s)).solid_area(&cfg);
    Ok(DragShapeResult {
        cd_start,
        cd_end: last.cd,
        area_start: area,
        area_end: last.shape.area(),
        cut_area_start: cut_area(&circle),
        cut_area_end: cut_area(&last.shape),
        gradient_start: history[0].gradient_norm,
        gradient_end: last.gradient_norm,
        iterations,
        solves: *solves.borrow(),
        stopped,
        shape: last.shape.clone(),
        history,
    })
}
