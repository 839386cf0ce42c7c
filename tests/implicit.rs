//! Implicit steps written as the forward physics only (`linear_system!`):
//! their derivatives by the implicit rule through the three checks, alone
//! and through a rollout, for a symmetric system (CG) and a non-symmetric
//! one (BiCGStab); a solve that does not converge is an error, not a
//! number.

use diffsim::check::{CheckParams, check_all};
use diffsim::implicit::{LinearSolve, LinearSystem, SolveMethod, SolveParams};
use diffsim::op::{Forward, OperatorExt};
use diffsim::rollout::{AtSteps, Checkpointing, Rollout, RolloutLoss, Wrt};

/// Backward Euler for heat conduction on an `n × n` grid with a
/// conductivity `exp(θ)` per cell (faces take the mean of their two
/// cells), insulated sides: `(I + dt·A(θ))·y = x`, the user's problem in
/// issue 51.
struct Heat {
    n: usize,
    dt: f64,
}

impl LinearSystem for Heat {
    fn n(&self) -> usize {
        self.n * self.n
    }
    fn n_in(&self) -> usize {
        self.n * self.n
    }
    fn n_params(&self) -> usize {
        self.n * self.n
    }
}

fn heat_matvec(s: &Heat, v: &[f64], theta: &[f64], out: &mut [f64]) {
    let n = s.n;
    for j in 0..n {
        for i in 0..n {
            let k = j * n + i;
            let mut acc = v[k];
            let mut face = |m: usize| acc += s.dt * 0.5 * (theta[k].exp() + theta[m].exp()) * (v[k] - v[m]);
            if i + 1 < n {
                face(k + 1);
            }
            if i > 0 {
                face(k - 1);
            }
            if j + 1 < n {
                face(k + n);
            }
            if j > 0 {
                face(k - n);
            }
            out[k] = acc;
        }
    }
}

fn heat_rhs(_: &Heat, x: &[f64], _theta: &[f64], b: &mut [f64]) {
    b.copy_from_slice(x);
}

diffsim::linear_system!(Heat => heat_matvec, heat_rhs);

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
    heat_matvec(&Heat { n, dt: 0.1 }, &y, &theta, &mut ay);
    assert!(ay.iter().zip(&x).all(|(a, b)| (a - b).abs() < 1e-8), "A·y ≠ x");
    let w = field(n * n, -0.8);
    let (dx, _) = op.vjp_new(&x, &theta, &w);
    let lambda = op.eval(&w, &theta);
    assert!(dx.iter().zip(&lambda).all(|(a, b)| (a - b).abs() < 1e-12), "the input gradient is not A⁻¹·w");
    assert!(op.info.forward.load(std::sync::atomic::Ordering::Relaxed) > 0);
}

#[test]
fn a_users_nonsymmetric_system_passes_the_checks_with_bicgstab() {
    let params = SolveParams { method: SolveMethod::BiCgStab, ..SolveParams::default() };
    let op = LinearSolve::new(Drift { n: 20, dt: 0.2 }, params);
    let report = check_all(&op, &field(20, 1.0), &[0.3, 0.8, 0.5], &CheckParams::default());
    assert!(report.passed(), "{report}");
    assert!(op.info.adjoint.load(std::sync::atomic::Ordering::Relaxed) > 0, "the VJP solved with the transpose");
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
