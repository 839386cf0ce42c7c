//! The nonlinear solve: a user's residual `F(y, x, p) = 0` as an operator
//! `(x, p) ↦ y`, solved by Newton's method, differentiated by the implicit
//! function theorem.
//!
//! The user writes the residual as a plain function on slices and declares
//! it with [`nonlinear_system!`](crate::nonlinear_system):
//!
//! ```ignore
//! fn residual(s: &Steady, y: &[f64], x: &[f64], p: &[f64], r: &mut [f64]) { /* r = F(y, x, p) */ }
//! diffsim::nonlinear_system!(Steady => residual);
//! let solve = NonlinearSolve::new(Steady { .. }, NewtonParams::default());
//! ```
//!
//! Newton's step `J·δ = −F` with `J = ∂F/∂y` solves directly (the Jacobian
//! assembled from `n` of Enzyme's Jacobian-vector products, factored by
//! faer) or matrix-free (CG or BiCGStab on those products: Newton–Krylov),
//! with a backtracking line search on `‖F‖₂`. The derivatives, at the
//! solution:
//!
//! ```text
//! VJP:  Jᵀ·λ = ȳ,   x̄ −= (∂F/∂x)ᵀ·λ,   p̄ −= (∂F/∂p)ᵀ·λ
//! JVP:  J·ẏ = −(∂F/∂x)·ẋ − (∂F/∂p)·ṗ
//! ```
//!
//! one linear solve each, the products from Enzyme's derivatives of the
//! residual; the Newton iterations are never differentiated.

use std::sync::Mutex;
use std::sync::atomic::{AtomicUsize, Ordering};

use super::linear::{Aids, SolveMethod, SolveParams, check_given, fail, singular, solve_system, take};
use crate::op::{Forward, Jvp, OpError, Operator, Vjp, validate_forward, validate_jvp, validate_vjp};

/// The sizes of a user's nonlinear system `F(y, x, p) = 0`, and Newton's
/// starting point.
pub trait NonlinearSystem {
    /// Unknowns `y` (the operator's outputs; as many equations).
    fn n(&self) -> usize;
    /// Inputs `x`.
    fn n_in(&self) -> usize;
    /// Parameters `p`.
    fn n_params(&self) -> usize {
        0
    }
    /// Newton's starting point for the inputs `x` and parameters `p`
    /// (default: zeros). Not differentiated: the solution does not depend on
    /// it.
    fn guess(&self, x: &[f64], p: &[f64], y: &mut [f64]) {
        let _ = (x, p);
        y.fill(0.0);
    }
}

/// A residual and its derivatives, implemented by
/// [`nonlinear_system!`](crate::nonlinear_system) with Enzyme; not written
/// by hand.
#[doc(hidden)]
pub trait ResidualFunctions: NonlinearSystem {
    /// `r = F(y, x, p)`.
    fn residual(&self, y: &[f64], x: &[f64], p: &[f64], r: &mut [f64]);
    /// `tr = (∂F/∂y)·ty` (and `r = F`).
    #[allow(clippy::too_many_arguments)]
    fn residual_jvp_y(&self, y: &[f64], x: &[f64], p: &[f64], ty: &[f64], r: &mut [f64], tr: &mut [f64]);
    /// `tr = (∂F/∂y)·ty + (∂F/∂x)·tx + (∂F/∂p)·tp` (and `r = F`).
    #[allow(clippy::too_many_arguments)]
    fn residual_jvp(&self, y: &[f64], x: &[f64], p: &[f64], ty: &[f64], tx: &[f64], tp: &[f64], r: &mut [f64], tr: &mut [f64]);
    /// `dy += (∂F/∂y)ᵀ·w`, `dx += (∂F/∂x)ᵀ·w`, `dp += (∂F/∂p)ᵀ·w`; consumes `w`.
    #[allow(clippy::too_many_arguments)]
    fn residual_vjp(&self, y: &[f64], x: &[f64], p: &[f64], w: &mut [f64], dy: &mut [f64], dx: &mut [f64], dp: &mut [f64]);
}

/// Makes `Sys` (a [`NonlinearSystem`], plain data) the system of a
/// [`NonlinearSolve`] from its residual `fn(&Sys, y, x, p, r)`, a plain
/// function that writes every element of `r`. Enzyme generates the
/// Jacobian products Newton's method and the implicit function theorem
/// need. The crate that invokes it needs what
/// [`differentiable!`](crate::differentiable) needs.
#[macro_export]
macro_rules! nonlinear_system {
    ($ty:ty => $residual:path) => {
        #[allow(clippy::too_many_arguments)]
        const _: () = {
            #[::std::autodiff::autodiff_reverse(diffsim_residual_vjp, Const, Duplicated, Duplicated, Duplicated, Duplicated)]
            fn diffsim_residual_reverse(s: &$ty, y: &[f64], x: &[f64], p: &[f64], r: &mut [f64]) {
                $residual(s, y, x, p, r)
            }
            #[::std::autodiff::autodiff_forward(diffsim_residual_jvp, Const, Dual, Dual, Dual, Dual)]
            fn diffsim_residual_forward(s: &$ty, y: &[f64], x: &[f64], p: &[f64], r: &mut [f64]) {
                $residual(s, y, x, p, r)
            }
            #[::std::autodiff::autodiff_forward(diffsim_residual_jvp_y, Const, Dual, Const, Const, Dual)]
            fn diffsim_residual_forward_y(s: &$ty, y: &[f64], x: &[f64], p: &[f64], r: &mut [f64]) {
                $residual(s, y, x, p, r)
            }

            impl $crate::implicit::ResidualFunctions for $ty {
                fn residual(&self, y: &[f64], x: &[f64], p: &[f64], r: &mut [f64]) {
                    $residual(self, y, x, p, r)
                }
                #[inline(never)]
                fn residual_jvp_y(&self, y: &[f64], x: &[f64], p: &[f64], ty: &[f64], r: &mut [f64], tr: &mut [f64]) {
                    diffsim_residual_jvp_y(self, y, ty, x, p, r, tr)
                }
                #[inline(never)]
                fn residual_jvp(&self, y: &[f64], x: &[f64], p: &[f64], ty: &[f64], tx: &[f64], tp: &[f64], r: &mut [f64], tr: &mut [f64]) {
                    diffsim_residual_jvp(self, y, ty, x, tx, p, tp, r, tr)
                }
                #[inline(never)]
                fn residual_vjp(&self, y: &[f64], x: &[f64], p: &[f64], w: &mut [f64], dy: &mut [f64], dx: &mut [f64], dp: &mut [f64]) {
                    let n = $crate::implicit::NonlinearSystem::n(self);
                    $crate::op::with_scratch(n, |r| diffsim_residual_vjp(self, y, dy, x, dx, p, dp, r, w));
                }
            }
        };
    };
}

/// Settings of Newton's method. `Default`: a direct linear solve, the
/// residual lowered by 1e-10 relative to the starting point's, at most 50
/// iterations, line search on.
#[derive(Clone, Copy, Debug, PartialEq, serde::Serialize, serde::Deserialize)]
pub struct NewtonParams {
    /// The linear solves with the Jacobian (Newton's steps and the adjoint):
    /// [`SolveMethod::Direct`] assembles it from `n` Jacobian-vector
    /// products (small systems); CG or BiCGStab solve matrix-free
    /// (Newton–Krylov) to its tolerance.
    pub linear: SolveParams,
    /// Converged when `‖F(y)‖₂ ≤ tolerance·‖F(y₀)‖₂`, `y₀` the guess.
    pub tolerance: f64,
    /// ... or when `‖F(y)‖₂ ≤ abs_tolerance`.
    pub abs_tolerance: f64,
    /// More Newton iterations than this is an error.
    pub max_iterations: usize,
    /// Backtracking (halving, Armijo's condition on `‖F‖₂`) when a full
    /// step does not lower the residual enough; off, every full step is
    /// taken and only a non-finite residual is refused.
    pub line_search: bool,
}

impl Default for NewtonParams {
    fn default() -> Self {
        NewtonParams {
            linear: SolveParams { method: SolveMethod::Direct, ..SolveParams::default() },
            tolerance: 1e-10,
            abs_tolerance: 0.0,
            max_iterations: 50,
            line_search: true,
        }
    }
}

impl NewtonParams {
    /// The settings' error, named, or `None`.
    pub(crate) fn invalid(&self) -> Option<String> {
        let l = &self.linear;
        if !(self.tolerance.is_finite() && self.tolerance > 0.0 && self.tolerance < 1.0) {
            Some(format!("the Newton tolerance must lie in (0, 1), got {}", self.tolerance))
        } else if !(self.abs_tolerance.is_finite() && self.abs_tolerance >= 0.0) {
            Some(format!("the absolute Newton tolerance must be a number ≥ 0, got {}", self.abs_tolerance))
        } else if self.max_iterations == 0 || l.max_iterations == 0 {
            Some("the iteration limits must be at least 1".into())
        } else if !(l.tolerance.is_finite() && l.tolerance > 0.0) {
            Some(format!("the linear tolerance must be a positive number, got {}", l.tolerance))
        } else {
            None
        }
    }

    /// The level below which the solution's derivatives are not resolved.
    pub(crate) fn solve_tolerance(&self) -> f64 {
        self.tolerance.max(self.linear.solve_tolerance())
    }
}

/// Iterations of a Newton solver's work so far.
#[derive(Debug, Default)]
pub struct NewtonInfo {
    /// Newton iterations (forward solves and JVPs).
    pub newton: AtomicUsize,
    /// Iterations of the linear solves inside them (0 for direct solves).
    pub linear: AtomicUsize,
    /// Linear solves with the transposed Jacobian (the adjoints).
    pub adjoint_solves: AtomicUsize,
    /// Iterations of those solves (0 for direct solves).
    pub adjoint: AtomicUsize,
}

/// A square system `G(y) = 0` as Newton's method sees it: the residual and
/// the Jacobian's products. Shared by [`NonlinearSolve`] and the implicit
/// integrators' stages.
pub(crate) trait Equations {
    fn residual(&self, y: &[f64], r: &mut [f64]);
    /// `out = J(y)·v`.
    fn jacobian_product(&self, y: &[f64], v: &[f64], out: &mut [f64]);
    /// `out = J(y)ᵀ·w`.
    fn jacobian_transpose_product(&self, y: &[f64], w: &[f64], out: &mut [f64]);
    /// `J(y)` into `m` (`n × n`, column by column) when the equations have
    /// it as a matrix (a user's Jacobian); `false` (nothing written) when
    /// it is only known by its products.
    fn jacobian_matrix(&self, y: &[f64], m: &mut [f64]) -> bool {
        let _ = (y, m);
        false
    }
}

fn norm(v: &[f64]) -> f64 {
    v.iter().map(|a| a * a).sum::<f64>().sqrt()
}

/// Newton's start at `y`: its residual into `r`, and the residual's size
/// and the size to reach; an error when either is not finite.
fn start(eq: &impl Equations, params: &NewtonParams, y: &[f64], r: &mut [f64]) -> Result<(f64, f64), OpError> {
    eq.residual(y, r);
    let size = norm(r);
    if !size.is_finite() || !y.iter().all(|v| v.is_finite()) {
        return Err(OpError::Input(crate::op::OpMessage::new("Newton's method: the starting point or its residual is not finite")));
    }
    Ok((size, (params.tolerance * size).max(params.abs_tolerance)))
}

/// Whether the step `delta` from `y` is at rounding level: the root as
/// close as it can be had.
fn at_rounding(delta: &[f64], y: &[f64]) -> bool {
    let scale = y.iter().fold(0.0f64, |m, v| m.max(v.abs()));
    delta.iter().fold(0.0f64, |m, v| m.max(v.abs())) <= 4.0 * f64::EPSILON * scale
}

/// Solves `J(y)·out = b` (`transposed`: `J(y)ᵀ·out = b`) by the settings'
/// linear method, counting its iterations.
pub(crate) fn jacobian_solve(
    eq: &impl Equations,
    params: &NewtonParams,
    info: &NewtonInfo,
    y: &[f64],
    b: &[f64],
    out: &mut [f64],
    transposed: bool,
) -> Result<(), OpError> {
    let result = solve_system(
        &params.linear,
        |v, o| eq.jacobian_product(y, v, o),
        |w, o| eq.jacobian_transpose_product(y, w, o),
        Aids::default(),
        b,
        out,
        transposed,
        None,
    );
    let counter = if transposed { &info.adjoint } else { &info.linear };
    if transposed {
        info.adjoint_solves.fetch_add(1, Ordering::Relaxed);
    }
    match result {
        Ok(it) => {
            counter.fetch_add(it, Ordering::Relaxed);
            Ok(())
        }
        Err(e) => {
            if let OpError::NoConvergence { iterations, .. } = e {
                counter.fetch_add(iterations, Ordering::Relaxed);
            }
            Err(e)
        }
    }
}

/// Newton's method from the guess in `y`; on success `y` is the root.
pub(crate) fn newton(eq: &impl Equations, params: &NewtonParams, info: &NewtonInfo, y: &mut [f64]) -> Result<(), OpError> {
    let n = y.len();
    let (mut r, mut minus_r, mut delta, mut trial, mut r_trial) = (vec![0.0; n], vec![0.0; n], vec![0.0; n], vec![0.0; n], vec![0.0; n]);
    let (mut size, target) = start(eq, params, y, &mut r)?;
    let mut iterations = 0;
    let result = loop {
        if size <= target {
            break Ok(());
        }
        if iterations == params.max_iterations {
            break Err(OpError::NoRoot { iterations, residual: size, target });
        }
        iterations += 1;
        for (m, r) in minus_r.iter_mut().zip(&r) {
            *m = -r;
        }
        delta.fill(0.0);
        match jacobian_solve(eq, params, info, y, &minus_r, &mut delta, false) {
            Ok(()) => {}
            // A singular Jacobian (or one not finite): no Newton step here.
            Err(OpError::Input(_)) => break Err(OpError::NoRoot { iterations, residual: size, target }),
            Err(e) => break Err(e),
        }
        let rounding = at_rounding(&delta, y);
        // Backtracking on ‖F‖₂ along the Newton direction.
        let mut alpha = 1.0;
        let accepted = loop {
            for ((t, y), d) in trial.iter_mut().zip(y.iter()).zip(&delta) {
                *t = y + alpha * d;
            }
            eq.residual(&trial, &mut r_trial);
            let s = norm(&r_trial);
            let enough = !params.line_search || rounding || s <= (1.0 - 1e-4 * alpha) * size;
            if s.is_finite() && enough {
                break Some(s);
            }
            alpha *= 0.5;
            if (!params.line_search && !s.is_finite()) || alpha < 1.0 / 1024.0 {
                break None;
            }
        };
        match accepted {
            Some(s) => {
                y.copy_from_slice(&trial);
                std::mem::swap(&mut r, &mut r_trial);
                size = s;
                if rounding {
                    break Ok(());
                }
            }
            None => break Err(OpError::NoRoot { iterations, residual: size, target }),
        }
    };
    info.newton.fetch_add(iterations, Ordering::Relaxed);
    result
}

/// A dense Jacobian's LU factors held over several Newton iterations
/// (simplified Newton), for small systems solved directly, with Newton's
/// vectors: the implicit stages of an integrator step share one.
/// Deterministic: what it holds depends only on the points it was formed
/// at, never on earlier calls.
#[derive(Debug)]
pub(crate) struct HeldJacobian {
    factors: JacobianFactors,
    /// Newton's vectors: the residual, the trial point and its residual.
    r: Vec<f64>,
    trial: Vec<f64>,
    r_trial: Vec<f64>,
}

/// The held Jacobian itself.
#[derive(Debug)]
struct JacobianFactors {
    lu: diffsim_solvers::linalg::DenseLu,
    matrix: Vec<f64>,
    unit: Vec<f64>,
    /// Whether `lu` holds factors (of the current equations' Jacobian).
    valid: bool,
}

impl JacobianFactors {
    /// Forms `J(y)` (the equations' matrix, else column by column from its
    /// products) and factors it; `false` when it is singular or not
    /// finite.
    fn refresh(&mut self, eq: &impl Equations, y: &[f64]) -> bool {
        let n = y.len();
        if !eq.jacobian_matrix(y, &mut self.matrix) {
            for (j, col) in self.matrix.chunks_exact_mut(n.max(1)).enumerate() {
                self.unit[j] = 1.0;
                eq.jacobian_product(y, &self.unit, col);
                self.unit[j] = 0.0;
            }
        }
        self.valid = self.matrix.iter().all(|v| v.is_finite()) && self.lu.factor(n, &self.matrix);
        self.valid
    }
}

impl HeldJacobian {
    /// Nothing held yet, for `n` unknowns; `None` when `n` is too large to
    /// hold dense or `params` do not solve directly.
    pub(crate) fn for_params(n: usize, params: &NewtonParams) -> Option<Self> {
        (params.linear.method == SolveMethod::Direct && n <= diffsim_solvers::linalg::DENSE_SOLVE_MAX).then(|| HeldJacobian {
            factors: JacobianFactors { lu: Default::default(), matrix: vec![0.0; n * n], unit: vec![0.0; n], valid: false },
            r: vec![0.0; n],
            trial: vec![0.0; n],
            r_trial: vec![0.0; n],
        })
    }

    /// Unknowns it is made for.
    pub(crate) fn n(&self) -> usize {
        self.r.len()
    }

    /// Solves `J(y)·out = b` (`transposed`: `J(y)ᵀ·out = b`) with a
    /// Jacobian formed at `y` (the exact one, for an adjoint); what it
    /// held before is replaced. An error when `J(y)` is singular.
    pub(crate) fn solve_at(&mut self, eq: &impl Equations, y: &[f64], b: &[f64], out: &mut [f64], transposed: bool) -> Result<(), OpError> {
        let formed = self.factors.refresh(eq, y);
        // Held for this point only: the next Newton solve forms its own.
        self.factors.valid = false;
        if !formed {
            return Err(singular());
        }
        out.copy_from_slice(b);
        self.factors.lu.solve(out, transposed);
        Ok(())
    }

    /// Forgets the factors (the equations' Jacobian changed form).
    pub(crate) fn invalidate(&mut self) {
        self.factors.valid = false;
    }
}

/// Newton's method with the Jacobian held (simplified Newton): each step
/// solves with the factors `held` has (formed at the first point that
/// needed them, perhaps by an earlier call), and forms them again at the
/// current point only when a step lowers `‖G‖₂` by less than a factor 4.
/// When even a fresh Jacobian's step does not, it falls back on
/// [`newton`] (fresh Jacobians and line search) from where it is. The
/// same convergence test as [`newton`]; the root is the same to the
/// tolerance.
pub(crate) fn newton_held(eq: &impl Equations, params: &NewtonParams, info: &NewtonInfo, held: &mut HeldJacobian, y: &mut [f64]) -> Result<(), OpError> {
    let HeldJacobian { factors, r, trial, r_trial } = held;
    let (mut size, target) = start(eq, params, y, r)?;
    let (mut iterations, mut fresh) = (0, false);
    let result = loop {
        if size <= target {
            break Some(Ok(()));
        }
        if iterations == params.max_iterations {
            break Some(Err(OpError::NoRoot { iterations, residual: size, target }));
        }
        if !factors.valid {
            if !factors.refresh(eq, y) {
                break None;
            }
            fresh = true;
        }
        iterations += 1;
        // trial = y − J⁻¹·r.
        for (t, r) in trial.iter_mut().zip(r.iter()) {
            *t = -r;
        }
        factors.lu.solve(trial, false);
        let rounding = at_rounding(trial, y);
        for (t, y) in trial.iter_mut().zip(y.iter()) {
            *t += y;
        }
        eq.residual(trial, r_trial);
        let s = norm(r_trial);
        if s.is_finite() && (rounding || s <= 0.25 * size) {
            y.copy_from_slice(trial);
            std::mem::swap(r, r_trial);
            size = s;
            fresh = false;
            if rounding {
                break Some(Ok(()));
            }
        } else if fresh {
            // A fresh Jacobian's full step did not contract: line search.
            break None;
        } else {
            factors.valid = false;
        }
    };
    info.newton.fetch_add(iterations, Ordering::Relaxed);
    match result {
        Some(done) => done,
        None => {
            factors.valid = false;
            newton(eq, params, info, y)
        }
    }
}

/// The operator `(x, p) ↦ y` with `F(y, x, p) = 0` for a user's system `S`
/// ([`nonlinear_system!`](crate::nonlinear_system)); Newton's method
/// forward, derivatives by the implicit function theorem (module docs).
/// A failed solve leaves the output NaN and its error in
/// [`Forward::take_error`].
#[derive(Debug)]
pub struct NonlinearSolve<S> {
    /// The user's system.
    pub system: S,
    /// How it is solved.
    pub params: NewtonParams,
    /// Work so far.
    pub info: NewtonInfo,
    error: Mutex<Option<OpError>>,
}

impl<S: NonlinearSystem> NonlinearSolve<S> {
    /// The solve of `system` with `params`.
    ///
    /// # Panics
    /// If a setting is out of range (named).
    #[track_caller]
    pub fn new(system: S, params: NewtonParams) -> Self {
        if let Some(e) = params.invalid() {
            panic!("NonlinearSolve: {e}");
        }
        NonlinearSolve { system, params, info: NewtonInfo::default(), error: Mutex::new(None) }
    }
}

/// The user's residual at fixed `x`, `p` as Newton's [`Equations`].
struct At<'a, S> {
    system: &'a S,
    x: &'a [f64],
    p: &'a [f64],
}

impl<S: ResidualFunctions> Equations for At<'_, S> {
    fn residual(&self, y: &[f64], r: &mut [f64]) {
        self.system.residual(y, self.x, self.p, r);
    }
    fn jacobian_product(&self, y: &[f64], v: &[f64], out: &mut [f64]) {
        // The residual itself is not needed: into the thread's scratch.
        crate::op::with_scratch(y.len(), |r| self.system.residual_jvp_y(y, self.x, self.p, v, r, out));
    }
    fn jacobian_transpose_product(&self, y: &[f64], w: &[f64], out: &mut [f64]) {
        let (mut seed, mut dx, mut dp) = (w.to_vec(), vec![0.0; self.x.len()], vec![0.0; self.p.len()]);
        out.fill(0.0);
        self.system.residual_vjp(y, self.x, self.p, &mut seed, out, &mut dx, &mut dp);
    }
}

impl<S: NonlinearSystem> Operator for NonlinearSolve<S> {
    fn n_in(&self) -> usize {
        self.system.n_in()
    }
    fn n_out(&self) -> usize {
        self.system.n()
    }
    fn n_params(&self) -> usize {
        self.system.n_params()
    }
}

impl<S: ResidualFunctions> NonlinearSolve<S> {
    fn solve(&self, x: &[f64], p: &[f64], y: &mut [f64]) {
        self.system.guess(x, p, y);
        if let Err(e) = newton(&At { system: &self.system, x, p }, &self.params, &self.info, y) {
            fail(&self.error, y, e);
        }
    }

    /// The implicit function theorem at the solution `y`: one solve with
    /// the transposed Jacobian, then the residual's VJP.
    fn vjp_from_solution(&self, x: &[f64], p: &[f64], y: &[f64], dy: &mut [f64], dx: &mut [f64], dp: &mut [f64]) {
        let n = self.system.n();
        let mut lambda = vec![0.0; n];
        if let Err(e) = jacobian_solve(&At { system: &self.system, x, p }, &self.params, &self.info, y, dy, &mut lambda, true) {
            fail(&self.error, &mut lambda, e);
        }
        for l in &mut lambda {
            *l = -*l;
        }
        let mut dy_unused = vec![0.0; n];
        self.system.residual_vjp(y, x, p, &mut lambda, &mut dy_unused, dx, dp);
        dy.fill(0.0);
    }
}

impl<S: ResidualFunctions> Forward for NonlinearSolve<S> {
    #[track_caller]
    fn forward(&self, x: &[f64], p: &[f64], y: &mut [f64]) {
        validate_forward(self, "NonlinearSolve", x, p, y);
        self.solve(x, p, y);
    }

    /// Newton's tolerance (or the linear solves', if looser).
    fn solve_tolerance(&self) -> f64 {
        self.params.solve_tolerance()
    }

    fn take_error(&self) -> Option<OpError> {
        take(&self.error)
    }
}

impl<S: ResidualFunctions> Vjp for NonlinearSolve<S> {
    #[track_caller]
    fn vjp(&self, x: &[f64], p: &[f64], dy: &mut [f64], dx: &mut [f64], dp: &mut [f64]) {
        validate_vjp(self, "NonlinearSolve", x, p, dy, dx, dp);
        let mut y = vec![0.0; self.system.n()];
        self.solve(x, p, &mut y);
        self.vjp_from_solution(x, p, &y, dy, dx, dp);
    }

    /// The solution is the rollout's next state: no Newton iterations.
    #[track_caller]
    fn vjp_overwrite_given(&self, x: &[f64], p: &[f64], y: &[f64], dy: &mut [f64], dx: &mut [f64], dp: &mut [f64]) {
        validate_vjp(self, "NonlinearSolve", x, p, dy, dx, dp);
        check_given("NonlinearSolve", y, self.system.n());
        dx.fill(0.0);
        self.vjp_from_solution(x, p, y, dy, dx, dp);
    }
}

impl<S: ResidualFunctions> Jvp for NonlinearSolve<S> {
    #[track_caller]
    fn jvp(&self, x: &[f64], p: &[f64], tx: &[f64], tp: &[f64], y: &mut [f64], ty: &mut [f64]) {
        validate_jvp(self, "NonlinearSolve", x, p, tx, tp, y, ty);
        let n = self.system.n();
        self.solve(x, p, y);
        // J·ẏ = −(∂F/∂x)·ẋ − (∂F/∂p)·ṗ.
        let (zero, mut r, mut tr) = (vec![0.0; n], vec![0.0; n], vec![0.0; n]);
        self.system.residual_jvp(y, x, p, &zero, tx, tp, &mut r, &mut tr);
        for t in &mut tr {
            *t = -*t;
        }
        if let Err(e) = jacobian_solve(&At { system: &self.system, x, p }, &self.params, &self.info, y, &tr, ty, false) {
            fail(&self.error, ty, e);
        }
    }
}
