//! Classical optimisers driven one iteration at a time by the caller's
//! loop, behind plain functions on `f64` slices: L-BFGS is argmin's
//! (`argmin::solver::quasinewton::LBFGS` with the More–Thuente line search,
//! Nocedal & Wright 2006, Algorithms 7.4 and 3.5/3.6), so a training loop
//! keeps its own policies (logging, checkpoints, Ctrl-C) and asks for one
//! iteration at a time. argmin's generic code is instantiated here, in a
//! crate built without the autodiff flag.

use std::cell::{Cell, RefCell};

use argmin::core::{CostFunction, Error, Gradient, IterState, Problem, Solver, State, TerminationStatus};
use argmin::solver::linesearch::MoreThuenteLineSearch;
use argmin::solver::quasinewton::LBFGS;

/// The loss and its gradient at a point, or why they could not be had.
pub type Objective<'a> = dyn FnMut(&[f64]) -> Result<(f64, Vec<f64>), String> + 'a;

/// Settings of [`Lbfgs`]; `Default` gives the usual values (Nocedal &
/// Wright: a history of 10 pairs is "often sufficient").
#[derive(Clone, Copy, Debug, PartialEq, serde::Serialize, serde::Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct LbfgsParams {
    /// Pairs `(s, y)` kept for the inverse-Hessian estimate.
    pub memory: usize,
    /// Converged when the gradient's norm falls below this.
    pub tolerance_grad: f64,
    /// Converged when the loss changes by less than this in an iteration.
    pub tolerance_loss: f64,
    /// Evaluations of the objective the line search may make in one
    /// iteration before the iteration is an error.
    pub max_evaluations: usize,
}

impl Default for LbfgsParams {
    fn default() -> Self {
        LbfgsParams { memory: 10, tolerance_grad: 1e-10, tolerance_loss: 0.0, max_evaluations: 40 }
    }
}

/// What one iteration of [`Lbfgs::step`] did.
#[derive(Clone, Debug, PartialEq)]
pub enum LbfgsStep {
    /// Moved to a point of lower loss.
    Moved {
        /// The loss at the point the iteration started from.
        loss_before: f64,
        /// The loss at the new point.
        loss_after: f64,
        /// Evaluations of the objective (loss and gradient together).
        evaluations: usize,
    },
    /// Did not move: the gradient or the loss's change is below its
    /// tolerance.
    Converged {
        /// The loss at the point.
        loss: f64,
    },
}

type Search = MoreThuenteLineSearch<Vec<f64>, Vec<f64>, f64>;
type Lbfgs_ = LBFGS<Search, Vec<f64>, Vec<f64>, f64>;
type Iterate = IterState<Vec<f64>, Vec<f64>, (), (), (), f64>;

/// L-BFGS over a deterministic objective (a full batch, or one fixed
/// batch): the history of steps and gradient changes is kept between calls
/// to [`Lbfgs::step`], and starts afresh when the point given is not the
/// one the last iteration reached (the caller changed the parameters).
pub struct Lbfgs {
    params: LbfgsParams,
    solver: Option<Lbfgs_>,
    state: Option<Iterate>,
}

impl std::fmt::Debug for Lbfgs {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("Lbfgs").field("params", &self.params).field("started", &self.state.is_some()).finish()
    }
}

/// A point, the loss there and its gradient.
type Evaluation = (Vec<f64>, f64, Vec<f64>);

/// The objective as argmin sees it: loss and gradient evaluated together
/// and cached for the last point (argmin asks for them separately).
struct Fun<'a, 'b> {
    f: RefCell<&'a mut Objective<'b>>,
    last: RefCell<Option<Evaluation>>,
    evaluations: Cell<usize>,
    max_evaluations: usize,
    /// The first failure, kept whole (argmin's error would reword it).
    failure: RefCell<Option<String>>,
}

impl Fun<'_, '_> {
    fn at(&self, x: &[f64]) -> Result<(f64, Vec<f64>), Error> {
        if let Some((p, l, g)) = self.last.borrow().as_ref()
            && p.as_slice() == x
        {
            return Ok((*l, g.clone()));
        }
        let fail = |m: String| {
            self.failure.borrow_mut().get_or_insert(m.clone());
            Error::msg(m)
        };
        if self.evaluations.get() >= self.max_evaluations {
            return Err(fail(format!("the line search found no acceptable step in {} evaluations", self.max_evaluations)));
        }
        self.evaluations.set(self.evaluations.get() + 1);
        let (l, g) = (self.f.borrow_mut())(x).map_err(fail)?;
        if g.len() != x.len() {
            return Err(fail(format!("the gradient has {} values for {} parameters", g.len(), x.len())));
        }
        if !l.is_finite() || g.iter().any(|v| !v.is_finite()) {
            return Err(fail(format!("the loss or its gradient is not finite at a trial point (loss {l})")));
        }
        *self.last.borrow_mut() = Some((x.to_vec(), l, g.clone()));
        Ok((l, g))
    }
}

impl CostFunction for Fun<'_, '_> {
    type Param = Vec<f64>;
    type Output = f64;
    fn cost(&self, x: &Vec<f64>) -> Result<f64, Error> {
        self.at(x).map(|(l, _)| l)
    }
}

impl Gradient for Fun<'_, '_> {
    type Param = Vec<f64>;
    type Gradient = Vec<f64>;
    fn gradient(&self, x: &Vec<f64>) -> Result<Vec<f64>, Error> {
        self.at(x).map(|(_, g)| g)
    }
}

impl Lbfgs {
    /// A fresh L-BFGS with `params`.
    ///
    /// # Errors
    /// A setting out of range (no history, a negative or NaN tolerance, no
    /// evaluations), named.
    pub fn new(params: LbfgsParams) -> Result<Self, String> {
        if params.memory == 0 {
            return Err("memory must be at least 1 pair".into());
        }
        if !(params.tolerance_grad >= 0.0 && params.tolerance_loss >= 0.0) {
            return Err(format!("tolerances must be non-negative numbers (gradient {}, loss {})", params.tolerance_grad, params.tolerance_loss));
        }
        if params.max_evaluations < 2 {
            return Err("max_evaluations must be at least 2".into());
        }
        Ok(Lbfgs { params, solver: None, state: None })
    }

    /// The settings.
    pub fn params(&self) -> LbfgsParams {
        self.params
    }

    /// Forgets the history (the next step starts as steepest descent).
    pub fn reset(&mut self) {
        self.solver = None;
        self.state = None;
    }

    /// One iteration from `x` on the objective `f` (loss and gradient at a
    /// point), `x` updated in place.
    ///
    /// # Errors
    /// The objective's own error, a non-finite loss or gradient at a trial
    /// point, or a line search that found no acceptable step (at a kink,
    /// or when the gradient is wrong): the point is left where it was.
    pub fn step(&mut self, f: &mut Objective<'_>, x: &mut [f64]) -> Result<LbfgsStep, String> {
        let started_here = self.state.as_ref().and_then(|s| s.get_param()).is_some_and(|p| p.as_slice() == x);
        if !started_here {
            self.reset();
        }
        let fun = Fun {
            f: RefCell::new(f),
            last: RefCell::new(None),
            evaluations: Cell::new(0),
            max_evaluations: self.params.max_evaluations,
            failure: RefCell::new(None),
        };
        let mut problem = Problem::new(fun);
        // The failure our objective recorded is clearer than argmin's
        // rewording of it.
        let recorded = |problem: &Problem<Fun>| problem.problem.as_ref().and_then(|p| p.failure.borrow().clone());
        let why = |e: Error, problem: &Problem<Fun>| recorded(problem).unwrap_or_else(|| e.to_string());
        if self.solver.is_none() {
            let mut solver = LBFGS::new(Search::new(), self.params.memory)
                .with_tolerance_grad(self.params.tolerance_grad)
                .and_then(|s| s.with_tolerance_cost(self.params.tolerance_loss))
                .map_err(|e| e.to_string())?;
            let state = IterState::new().param(x.to_vec());
            let (mut state, _) = solver.init(&mut problem, state).map_err(|e| why(e, &problem))?;
            state.update();
            self.solver = Some(solver);
            self.state = Some(state);
        }
        let (solver, state) = (self.solver.as_mut().expect("initialised above"), self.state.take().expect("initialised above"));
        let loss_before = state.get_cost();
        if let TerminationStatus::Terminated(_) = <Lbfgs_ as Solver<Fun, Iterate>>::terminate(solver, &state) {
            self.state = Some(state);
            return Ok(LbfgsStep::Converged { loss: loss_before });
        }
        let (mut next, _) = match solver.next_iter(&mut problem, state) {
            Ok(v) => v,
            Err(e) => {
                let m = why(e, &problem);
                self.reset();
                return Err(m);
            }
        };
        let evaluations = problem.problem.as_ref().map_or(0, |p| p.evaluations.get());
        if next.terminated() {
            // argmin ends the run when the line search fails.
            let m = recorded(&problem).unwrap_or_else(|| format!("{:?}", next.get_termination_reason()));
            self.reset();
            return Err(m);
        }
        let loss_after = next.get_cost();
        if loss_after > loss_before || loss_after.is_nan() {
            // The search ended above its start: along the direction the
            // gradient gives, the loss does not fall (a wrong gradient, or
            // a kink); moving would undo progress.
            self.reset();
            return Err(format!("the line search found no decrease ({loss_before:e} → {loss_after:e} in {evaluations} evaluations): is the gradient right?"));
        }
        next.update();
        next.increment_iter();
        x.copy_from_slice(next.get_param().expect("L-BFGS keeps its point"));
        self.state = Some(next);
        Ok(LbfgsStep::Moved { loss_before, loss_after, evaluations })
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn rosenbrock(x: &[f64]) -> Result<(f64, Vec<f64>), String> {
        let (a, b) = (x[0], x[1]);
        let f = (1.0 - a).powi(2) + 100.0 * (b - a * a).powi(2);
        Ok((f, vec![-2.0 * (1.0 - a) - 400.0 * a * (b - a * a), 200.0 * (b - a * a)]))
    }

    #[test]
    fn lbfgs_reaches_rosenbrocks_minimum_one_iteration_at_a_time() {
        let mut opt = Lbfgs::new(LbfgsParams::default()).unwrap();
        let mut x = vec![-1.2, 1.0];
        let mut f = rosenbrock;
        let mut iterations = 0;
        let mut last = f64::INFINITY;
        while let LbfgsStep::Moved { loss_before, loss_after, .. } = opt.step(&mut f, &mut x).unwrap() {
            // Every iteration decreases the loss (the line search's
            // sufficient-decrease condition).
            assert!(loss_after < loss_before && loss_before <= last, "{loss_before} → {loss_after}");
            last = loss_after;
            iterations += 1;
            assert!(iterations < 200, "no convergence: x = {x:?}");
        }
        assert!((x[0] - 1.0).abs() < 1e-6 && (x[1] - 1.0).abs() < 1e-6, "{x:?} after {iterations}");
        // Gradient descent needs thousands of iterations here; L-BFGS tens.
        assert!(iterations < 60, "{iterations} iterations");
    }

    #[test]
    fn lbfgs_restarts_when_the_point_was_changed_and_refuses_bad_objectives() {
        let mut opt = Lbfgs::new(LbfgsParams::default()).unwrap();
        let mut x = vec![-1.2, 1.0];
        let mut f = rosenbrock;
        opt.step(&mut f, &mut x).unwrap();
        // The caller moves the point: the history no longer applies, and
        // the step starts over from there (no panic, a decrease).
        x = vec![0.5, 0.5];
        let LbfgsStep::Moved { loss_before, loss_after, .. } = opt.step(&mut f, &mut x).unwrap() else { panic!("converged at once") };
        assert_eq!(loss_before, rosenbrock(&[0.5, 0.5]).unwrap().0);
        assert!(loss_after < loss_before);
        // A wrong gradient (the sign flipped): no step along it decreases
        // the loss, and the iteration says so instead of moving.
        let mut wrong = |x: &[f64]| rosenbrock(x).map(|(f, g)| (f, g.iter().map(|v| -v).collect()));
        let mut fresh = Lbfgs::new(LbfgsParams::default()).unwrap();
        let mut y = vec![-1.2, 1.0];
        let r = fresh.step(&mut wrong, &mut y);
        assert!(r.is_err(), "{r:?} {y:?}");
        assert_eq!(y, [-1.2, 1.0], "the point is left where it was");
        // A loss that is NaN away from the start is an error, named.
        let mut nan = |x: &[f64]| if x[0] == -1.2 { rosenbrock(x) } else { Ok((f64::NAN, vec![0.0, 0.0])) };
        let e = Lbfgs::new(LbfgsParams::default()).unwrap().step(&mut nan, &mut [-1.2, 1.0]).unwrap_err();
        assert!(e.contains("not finite"), "{e}");
        assert!(Lbfgs::new(LbfgsParams { memory: 0, ..Default::default() }).is_err());
        assert!(Lbfgs::new(LbfgsParams { tolerance_grad: f64::NAN, ..Default::default() }).is_err());
    }
}
