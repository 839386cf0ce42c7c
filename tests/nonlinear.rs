//! Nonlinear solves written as the residual only (`nonlinear_system!`):
//! Newton's method forward, the implicit function theorem backward,
//! compared with an independent solution and derivative, through the three
//! checks alone and through a rollout; a system without a root is an error.

use diffsim::check::{CheckParams, check_all};
use diffsim::implicit::{NewtonParams, NonlinearSolve, NonlinearSystem, SolveMethod, SolveParams};
use diffsim::op::{Forward, OperatorExt};
use diffsim::rollout::{Checkpointing, Rollout, RolloutLoss, Wrt};
use std::sync::atomic::Ordering;

/// Per cell `y + a·y³ = x` (a = p[0]) coupled along a line by a reaction
/// `b·(y_{i+1} − 2·y_i + y_{i−1})` (b = p[1], zero ends): a discrete
/// stationary reaction–diffusion equation.
struct Cubic {
    n: usize,
}

impl NonlinearSystem for Cubic {
    fn n(&self) -> usize {
        self.n
    }
    fn n_in(&self) -> usize {
        self.n
    }
    fn n_params(&self) -> usize {
        2
    }
}

fn cubic(s: &Cubic, y: &[f64], x: &[f64], p: &[f64], r: &mut [f64]) {
    let n = s.n;
    for i in 0..n {
        let l = if i > 0 { y[i - 1] } else { 0.0 };
        let rr = if i + 1 < n { y[i + 1] } else { 0.0 };
        r[i] = y[i] + p[0] * y[i] * y[i] * y[i] - p[1] * (rr - 2.0 * y[i] + l) - x[i];
    }
}

diffsim::nonlinear_system!(Cubic => cubic);

fn field(n: usize, a: f64) -> Vec<f64> {
    (0..n).map(|k| a * (0.7 * k as f64).sin() + 0.3 * (0.23 * k as f64).cos()).collect()
}

/// The uncoupled cubic `y + a·y³ = x` by bisection, and `dy/dx = 1/(1 + 3a·y²)`,
/// `dy/da = −y³/(1 + 3a·y²)`: an independent solution and derivative.
fn cubic_root(x: f64, a: f64) -> f64 {
    let (mut lo, mut hi) = (-x.abs() - 1.0, x.abs() + 1.0);
    for _ in 0..200 {
        let mid = 0.5 * (lo + hi);
        if mid + a * mid * mid * mid < x { lo = mid } else { hi = mid }
    }
    0.5 * (lo + hi)
}

#[test]
fn newton_solves_a_users_residual_and_the_implicit_rule_matches_the_calculus() {
    let n = 7;
    let op = NonlinearSolve::new(Cubic { n }, NewtonParams::default());
    let (x, p) = (field(n, 2.0), [0.8, 0.0]);
    let y = op.eval(&x, &p);
    let w = field(n, -0.6);
    let (dx, dp) = op.vjp_new(&x, &p, &w);
    let mut da = 0.0;
    for i in 0..n {
        let root = cubic_root(x[i], p[0]);
        assert!((y[i] - root).abs() < 1e-9, "cell {i}: Newton {} against bisection {root}", y[i]);
        let slope = 1.0 / (1.0 + 3.0 * p[0] * root * root);
        assert!((dx[i] - w[i] * slope).abs() < 1e-9, "cell {i}: dy/dx");
        da -= w[i] * root * root * root * slope;
    }
    assert!((dp[0] - da).abs() < 1e-9, "dy/da: {} against {da}", dp[0]);
    assert!(op.info.newton.load(Ordering::Relaxed) > 0);
}

#[test]
fn a_coupled_residual_passes_the_checks_with_each_linear_method() {
    let n = 12;
    let (x, p) = (field(n, 2.0), [0.8, 0.5]);
    let mut solutions = Vec::new();
    for method in [SolveMethod::Direct, SolveMethod::Cg, SolveMethod::BiCgStab] {
        // The Jacobian I + 3a·diag(y²) + b·L is symmetric positive definite.
        let params = NewtonParams { linear: SolveParams { method, tolerance: 1e-12, ..SolveParams::default() }, ..NewtonParams::default() };
        let op = NonlinearSolve::new(Cubic { n }, params);
        let report = check_all(&op, &x, &p, &CheckParams::default());
        assert!(report.passed(), "{method:?}: {report}");
        let y = op.eval(&x, &p);
        let mut r = vec![0.0; n];
        cubic(&Cubic { n }, &y, &x, &p, &mut r);
        assert!(r.iter().all(|v| v.abs() < 1e-9), "{method:?}: the residual at the solution is {r:?}");
        solutions.push(y);
    }
    assert!(solutions.windows(2).all(|w| w[0].iter().zip(&w[1]).all(|(a, b)| (a - b).abs() < 1e-9)));
}

#[test]
fn the_checks_pass_through_a_rollout_of_nonlinear_steps() {
    // y_{t+1} solves y + a·y³ − b·Δy = y_t: a nonlinear implicit relaxation.
    let n = 6;
    let op = NonlinearSolve::new(Cubic { n }, NewtonParams::default());
    let (x0, p) = (field(n, 1.5), vec![0.6, 0.3]);
    let loss = |x: &[f64], g: &mut [f64]| -> f64 {
        let mut value = 0.0;
        for (k, (g, v)) in g.iter_mut().zip(x).enumerate() {
            let target = 0.1 * k as f64;
            *g = v - target;
            value += 0.5 * (v - target) * (v - target);
        }
        value
    };
    let as_op = RolloutLoss::new(Rollout::new(&op, &p, 8).unwrap(), &x0, &loss, Checkpointing::Store, Wrt::Both).unwrap();
    let (x, p) = as_op.point();
    let report = check_all(&as_op, x, p, &CheckParams::default());
    assert!(report.passed(), "{report}");
}

/// `y² + c = x` with c = p[0] > x: no real root.
struct NoRoot;

impl NonlinearSystem for NoRoot {
    fn n(&self) -> usize {
        1
    }
    fn n_in(&self) -> usize {
        1
    }
    fn n_params(&self) -> usize {
        1
    }
    fn guess(&self, _x: &[f64], _p: &[f64], y: &mut [f64]) {
        y[0] = 1.0;
    }
}

fn no_root(_: &NoRoot, y: &[f64], x: &[f64], p: &[f64], r: &mut [f64]) {
    r[0] = y[0] * y[0] + p[0] - x[0];
}

diffsim::nonlinear_system!(NoRoot => no_root);

#[test]
fn a_residual_without_a_root_is_an_error_not_a_number() {
    let op = NonlinearSolve::new(NoRoot, NewtonParams::default());
    assert!((op.eval(&[5.0], &[1.0])[0] - 2.0).abs() < 1e-10, "the root of y² = 4 from y = 1");
    assert!(op.take_error().is_none());
    let y = op.eval(&[1.0], &[2.0]);
    assert!(y[0].is_nan());
    let e = op.take_error().expect("the failure is kept");
    assert!(e.to_string().starts_with("Newton's method did not converge"), "{e}");
    // Through a rollout: the error, named with its step.
    let loss = |x: &[f64], g: &mut [f64]| -> f64 {
        g.copy_from_slice(x);
        0.5 * x[0] * x[0]
    };
    let rollout = Rollout::new(&op, &[2.0], 3).unwrap();
    let e = rollout.value_and_grad(&[1.0], &loss, Checkpointing::Store).unwrap_err();
    assert!(e.to_string().contains("Newton's method did not converge"), "{e}");
}

#[test]
#[should_panic(expected = "NonlinearSolve: the Newton tolerance must lie in (0, 1)")]
fn a_newton_solve_without_a_tolerance_is_refused() {
    NonlinearSolve::new(Cubic { n: 2 }, NewtonParams { tolerance: 0.0, ..NewtonParams::default() });
}
