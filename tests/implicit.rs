//! Implicit steps written as the forward physics only (`linear_system!`):
//! their derivatives by the implicit rule through the three checks, alone
//! and through a rollout, for a symmetric system (CG: the library's
//! `problems::implicit_heat`) and a non-symmetric one written here
//! (BiCGStab); a rollout hands each step its solution; a solve that does
//! not converge is an error, not a number.

use diffsim::check::{CheckParams, check_all};
use diffsim::implicit::{LinearSolve, LinearSystem, SolveMethod, SolveParams, Start};
use diffsim::op::{Forward, OperatorExt};
use diffsim::problems::implicit_heat::{ImplicitHeat as Heat, heat_conductances, heat_matvec};
use diffsim::rollout::{AtSteps, Checkpointing, Rollout, RolloutLoss, Wrt};
use std::sync::atomic::Ordering;

/// Implicit advection–diffusion on a periodic line, `(I + dt·(ν·L + c·D))·y
/// = x + dt·s` with `L` the negative Laplacian, `D` the upwind difference
/// (not symmetric) and a source `s = p[2]` in every cell; `p = [ν, c, s]`.
struct Drift {
    n: usize,
    dt: f64,
}

impl LinearSystem for Drift {
    fn n(&self) -> usize {
        self.n
    }
    fn n_in(&self) -> usize {
        self.n
    }
    fn n_params(&self) -> usize {
        3
    }
}

fn drift_matvec(s: &Drift, v: &[f64], p: &[f64], out: &mut [f64]) {
    let n = s.n;
    for i in 0..n {
        let (l, r) = (v[(i + n - 1) % n], v[(i + 1) % n]);
        out[i] = v[i] + s.dt * (p[0] * (2.0 * v[i] - l - r) + p[1] * (v[i] - l));
    }
}

fn drift_rhs(s: &Drift, x: &[f64], p: &[f64], b: &mut [f64]) {
    for (b, x) in b.iter_mut().zip(x) {
        *b = x + s.dt * p[2];
    }
}

diffsim::linear_system!(Drift => drift_matvec, drift_rhs);

fn field(n: usize, a: f64) -> Vec<f64> {
    (0..n).map(|k| a * (0.7 * k as f64).sin() + 0.3 * (0.23 * k as f64).cos()).collect()
}

#[test]
fn a_users_symmetric_system_passes_the_checks_by_the_implicit_rule() {
    let n = 6;
    let op = LinearSolve::new(Heat { n, dt: 0.1 }, SolveParams::default());
    let (x, theta) = (field(n * n, 1.0), field(n * n, 0.4));
    let report = check_all(&op, &x, &theta, &CheckParams::default());
    assert!(report.passed(), "{report}");
    // The solution solves the system, and the adjoint is a solve with the
    // same matrix: its input gradient equals the solution of A·λ = w
    // (A symmetric, b = x), computed here by a second, independent solve.
    let y = op.eval(&x, &theta);
    let mut ay = vec![0.0; n * n];
    let mut c = vec![0.0; Heat { n, dt: 0.1 }.n_coefficients()];
    heat_conductances(&Heat { n, dt: 0.1 }, &theta, &mut c);
    heat_matvec(&Heat { n, dt: 0.1 }, &y, &c, &mut ay);
    assert!(ay.iter().zip(&x).all(|(a, b)| (a - b).abs() < 1e-8), "A·y ≠ x");
    let w = field(n * n, -0.8);
    let (dx, _) = op.vjp_new(&x, &theta, &w);
    let lambda = op.eval(&w, &theta);
    assert!(dx.iter().zip(&lambda).all(|(a, b)| (a - b).abs() < 1e-12), "the input gradient is not A⁻¹·w");
    assert!(op.info.forward.load(Ordering::Relaxed) > 0);
}

#[test]
fn a_users_nonsymmetric_system_passes_the_checks_with_bicgstab() {
    let params = SolveParams { method: SolveMethod::BiCgStab, ..SolveParams::default() };
    let op = LinearSolve::new(Drift { n: 20, dt: 0.2 }, params);
    let report = check_all(&op, &field(20, 1.0), &[0.3, 0.8, 0.5], &CheckParams::default());
    assert!(report.passed(), "{report}");
    assert!(op.info.adjoint.load(Ordering::Relaxed) > 0, "the VJP solved with the transpose");
}

#[test]
fn the_checks_pass_through_twenty_implicit_steps_for_the_state_and_the_conductivity() {
    let n = 5;
    let op = LinearSolve::new(Heat { n, dt: 0.05 }, SolveParams::default());
    let (x0, theta) = (field(n * n, 1.0), field(n * n, 0.3));
    let target = field(n * n, 0.2);
    let loss = AtSteps {
        steps: vec![20],
        f: |_t: usize, x: &[f64], g: &mut [f64]| -> f64 {
            let mut value = 0.0;
            for ((g, a), b) in g.iter_mut().zip(x).zip(&target) {
                *g = a - b;
                value += 0.5 * (a - b) * (a - b);
            }
            value
        },
    };
    let as_op = RolloutLoss::new(Rollout::new(&op, &theta, 20).unwrap(), &x0, &loss, Checkpointing::periodic_sqrt(20), Wrt::Both).unwrap();
    // The rollout declares 20 × the step's tolerance.
    assert_eq!(as_op.solve_tolerance(), 20.0 * 1e-10);
    let (x, p) = as_op.point();
    let report = check_all(&as_op, x, p, &CheckParams::default());
    assert!(report.passed(), "{report}");
}

#[test]
fn a_solve_that_does_not_converge_is_an_error_and_leaves_no_number() {
    let n = 6;
    let op = LinearSolve::new(Heat { n, dt: 10.0 }, SolveParams { max_iterations: 2, ..SolveParams::default() });
    let y = op.eval(&field(n * n, 1.0), &field(n * n, 0.4));
    assert!(y.iter().all(|v| v.is_nan()));
    let e = op.take_error().expect("the failed solve is kept");
    assert!(e.to_string().contains("did not converge"), "{e}");
    assert!(op.take_error().is_none(), "taken once");
}

#[test]
#[should_panic(expected = "LinearSolve: the tolerance must be a positive number")]
fn a_solve_without_a_tolerance_is_refused() {
    LinearSolve::new(Heat { n: 2, dt: 0.1 }, SolveParams { tolerance: 0.0, ..SolveParams::default() });
}

/// The rollout hands each step's VJP the step's solution (the next state)
/// wherever its schedule holds it: with stored states the backward pass
/// makes no forward solve at all, and every schedule gives the same
/// gradient bit for bit (a solve is deterministic).
#[test]
fn a_rollout_hands_each_implicit_step_its_solution() {
    let n = 5;
    let op = LinearSolve::new(Heat { n, dt: 0.05 }, SolveParams::default());
    let (x0, theta) = (field(n * n, 1.0), field(n * n, 0.3));
    let loss = |x: &[f64], g: &mut [f64]| -> f64 {
        g.copy_from_slice(x);
        0.5 * x.iter().map(|v| v * v).sum::<f64>()
    };
    let rollout = Rollout::new(&op, &theta, 12).unwrap();
    let forward = || op.info.forward.load(Ordering::Relaxed);
    let before = forward();
    rollout.loss(&x0, &loss).unwrap();
    let forward_only = forward() - before;
    let before = forward();
    let stored = rollout.value_and_grad(&x0, &loss, Checkpointing::Store).unwrap();
    assert_eq!(forward() - before, forward_only, "the backward pass solved forward systems again");
    for mode in [Checkpointing::Periodic { every: 4 }, Checkpointing::Binomial { snapshots: 2 }] {
        let g = rollout.value_and_grad(&x0, &loss, mode).unwrap();
        assert_eq!((&g.dx0, &g.dp), (&stored.dx0, &stored.dp), "{mode}");
    }
}

#[test]
fn a_rollout_applies_the_coefficients_vjp_once_with_the_same_gradient() {
    // With the same θ at every step the backward pass gathers the
    // coefficients' cotangent and applies (∂c/∂θ)ᵀ once
    // (`Vjp::vjp_deferred`); with θ given per step (T copies) each step's
    // VJP applies it itself. The sums over the steps must agree.
    let (n, steps) = (6, 9);
    let op = LinearSolve::new(Heat { n, dt: 0.07 }, SolveParams { tolerance: 1e-13, ..SolveParams::default() });
    let (x0, theta) = (field(n * n, 1.0), field(n * n, 0.4));
    let loss = |x: &[f64], g: &mut [f64]| -> f64 {
        g.copy_from_slice(x);
        0.5 * x.iter().map(|v| v * v).sum::<f64>()
    };
    let shared = Rollout::new(&op, &theta, steps).unwrap().value_and_grad(&x0, &loss, Checkpointing::Store).unwrap();
    let repeated: Vec<f64> = (0..steps).flat_map(|_| theta.iter().copied()).collect();
    let each = Rollout::per_step(&op, &repeated, steps).unwrap().value_and_grad(&x0, &loss, Checkpointing::Store).unwrap();
    assert_eq!(shared.dx0, each.dx0);
    let summed: Vec<f64> = (0..n * n).map(|k| (0..steps).map(|t| each.dp[t * n * n + k]).sum()).collect();
    let scale = summed.iter().fold(0.0f64, |m, v| m.max(v.abs()));
    assert!(scale > 1e-3, "the test needs a gradient that is not zero");
    for (k, (a, b)) in shared.dp.iter().zip(&summed).enumerate() {
        assert!((a - b).abs() <= 1e-12 * scale, "θ[{k}]: {a} gathered, {b} step by step");
    }
}

/// A matrix of rank one: `A·v = (Σ v)·1`, singular for n > 1.
struct RankOne {
    n: usize,
}

impl LinearSystem for RankOne {
    fn n(&self) -> usize {
        self.n
    }
    fn n_in(&self) -> usize {
        self.n
    }
}

fn rank_one_matvec(s: &RankOne, v: &[f64], _p: &[f64], out: &mut [f64]) {
    let sum: f64 = v.iter().sum();
    for o in out.iter_mut().take(s.n) {
        *o = sum;
    }
}

fn copy_rhs(_: &RankOne, x: &[f64], _p: &[f64], b: &mut [f64]) {
    b.copy_from_slice(x);
}

diffsim::linear_system!(RankOne => rank_one_matvec, copy_rhs);

#[test]
fn a_direct_solve_is_exact_and_refuses_a_singular_matrix() {
    let direct = LinearSolve::new(Drift { n: 20, dt: 0.2 }, SolveParams { method: SolveMethod::Direct, ..SolveParams::default() });
    let iterative = LinearSolve::new(Drift { n: 20, dt: 0.2 }, SolveParams { method: SolveMethod::BiCgStab, ..SolveParams::default() });
    let (x, p) = (field(20, 1.0), [0.3, 0.8, 0.5]);
    // Exact to rounding: no solve tolerance to declare, and the three
    // checks pass at their rounding-level settings.
    assert_eq!(direct.solve_tolerance(), 0.0);
    let report = check_all(&direct, &x, &p, &CheckParams::default());
    assert!(report.passed(), "{report}");
    let (a, b) = (direct.eval(&x, &p), iterative.eval(&x, &p));
    assert!(a.iter().zip(&b).all(|(u, v)| (u - v).abs() < 1e-8), "the direct and iterative solutions differ");
    let (da, _) = direct.vjp_new(&x, &p, &field(20, -0.5));
    let (db, _) = iterative.vjp_new(&x, &p, &field(20, -0.5));
    assert!(da.iter().zip(&db).all(|(u, v)| (u - v).abs() < 1e-8), "the direct and iterative adjoints differ");
    let singular = LinearSolve::new(RankOne { n: 4 }, SolveParams { method: SolveMethod::Direct, ..SolveParams::default() });
    assert!(singular.eval(&[1.0, 2.0, 3.0, 4.0], &[]).iter().all(|v| v.is_nan()));
    let e = singular.take_error().expect("a singular matrix is an error");
    assert!(e.to_string().contains("the matrix is singular"), "{e}");
}

/// Enzyme through the CG iterations (the comparison route of `bench
/// implicit-heat`): on a grid small enough for CG to terminate, at a tight
/// tolerance, its gradient agrees with central differences of its forward.
#[test]
fn enzyme_through_cg_agrees_with_finite_differences_at_a_tight_tolerance() {
    use diffsim::check::finite_differences;
    use diffsim::problems::implicit_heat::HeatThroughCg;
    let n = 4;
    let op = HeatThroughCg { n, dt: 0.1, tolerance: 1e-13, max_iterations: 1000 };
    let report = finite_differences(&op, &field(n * n, 1.0), &field(n * n, 0.4), &CheckParams { tol: 1e-5, ..CheckParams::default() });
    assert!(report.verdict.passed(), "{report}");
}

/// CG from the right-hand side (`Start::Rhs`, for time steps): the same
/// solution and gradient as from zero to the tolerance, in fewer
/// iterations, and the checks pass; the same solve twice gives the same
/// bits (the start depends on nothing solved before).
#[test]
fn a_solve_from_the_right_hand_side_agrees_in_fewer_iterations() {
    let n = 8;
    let (x, theta) = (field(n * n, 1.0), field(n * n, 0.3));
    let zero = LinearSolve::new(Heat { n, dt: 0.05 }, SolveParams::default());
    let rhs = LinearSolve::new(Heat { n, dt: 0.05 }, SolveParams { start: Start::Rhs, ..SolveParams::default() });
    let (a, b) = (zero.eval(&x, &theta), rhs.eval(&x, &theta));
    assert!(a.iter().zip(&b).all(|(u, v)| (u - v).abs() < 1e-8), "the two starts disagree");
    let (iz, ir) = (zero.info.forward.load(Ordering::Relaxed), rhs.info.forward.load(Ordering::Relaxed));
    assert!(ir < iz, "from the right-hand side {ir} iterations, from zero {iz}");
    assert_eq!(rhs.eval(&x, &theta), b, "the same solve, other bits");
    let report = check_all(&rhs, &x, &theta, &CheckParams::default());
    assert!(report.passed(), "{report}");
}
