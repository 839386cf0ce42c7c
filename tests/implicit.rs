//! Implicit steps written as the forward physics only (`linear_system!`):
//! their derivatives by the implicit rule through the three checks, alone
//! and through a rollout, for a symmetric system (CG: the library's
//! `problems::implicit_heat`) and a non-symmetric one written here
//! (BiCGStab); a rollout hands each step its solution; a solve that does
//! not converge is an error, not a number; a preconditioner changes the
//! iteration count, not the solution or gradient; a singular system with
//! the constant null space is solved without its mean.

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

/// The largest difference of two vectors relative to the first's largest
/// entry.
fn relative_gap(a: &[f64], b: &[f64]) -> f64 {
    let scale = a.iter().fold(0.0f64, |m, v| m.max(v.abs())).max(1e-300);
    a.iter().zip(b).fold(0.0f64, |m, (u, v)| m.max((u - v).abs())) / scale
}

/// A preconditioner (`linear_system!(.., preconditioner = m)`, here Jacobi)
/// on a layered medium whose conductivity jumps by e⁸ between layers: CG
/// reaches the same solution and the same gradient (the implicit rule does
/// not depend on how the solve converged) in a third fewer iterations or
/// better, forward and adjoint, and the checks pass.
#[test]
fn a_preconditioned_solve_agrees_with_the_plain_one_in_fewer_iterations() {
    use diffsim::problems::implicit_heat::PreconditionedHeat;
    let (n, dt) = (12, 1.0);
    let layered: Vec<f64> = (0..n * n).map(|k| if (k / n / 2) % 2 == 0 { 4.0 } else { -4.0 }).collect();
    let x = field(n * n, 1.0);
    let tight = SolveParams { tolerance: 1e-12, ..SolveParams::default() };
    let plain = LinearSolve::new(Heat { n, dt }, tight);
    let jacobi = PreconditionedHeat::step(n, dt, tight);
    let (a, b) = (plain.eval(&x, &layered), jacobi.eval(&x, &layered));
    assert!(relative_gap(&a, &b) < 1e-9, "the solutions differ by {:e}", relative_gap(&a, &b));
    let w = field(n * n, -0.8);
    let ((dx_a, dp_a), (dx_b, dp_b)) = (plain.vjp_new(&x, &layered, &w), jacobi.vjp_new(&x, &layered, &w));
    assert!(relative_gap(&dx_a, &dx_b) < 1e-9 && relative_gap(&dp_a, &dp_b) < 1e-9, "the gradients differ");
    let count = |s: &diffsim::implicit::SolveInfo| (s.forward.load(Ordering::Relaxed), s.adjoint.load(Ordering::Relaxed));
    let ((fa, aa), (fb, ab)) = (count(&plain.info), count(&jacobi.info));
    println!("layered heat, CG iterations forward + adjoint: Jacobi {fb} + {ab}, plain {fa} + {aa}");
    assert!(3 * fb < 2 * fa && 3 * ab < 2 * aa, "Jacobi {fb} + {ab} iterations, plain {fa} + {aa}");
    let report = check_all(&jacobi, &x, &field(n * n, 0.4), &CheckParams::default());
    assert!(report.passed(), "{report}");
}

/// Upwind advection–diffusion on a periodic line with a reaction rate per
/// cell spanning e⁻³ … e³, `(I + dt·(ν·L + c·D + R))·y = x`, `p = [ν, c]`;
/// preconditioned by its diagonal when `jacobi`, else by the identity.
struct Reactive {
    n: usize,
    dt: f64,
    jacobi: bool,
}

impl LinearSystem for Reactive {
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

fn reaction(i: usize) -> f64 {
    (3.0 * (0.9 * i as f64).sin()).exp()
}

fn reactive_matvec(s: &Reactive, v: &[f64], p: &[f64], out: &mut [f64]) {
    let n = s.n;
    for i in 0..n {
        let (l, r) = (v[(i + n - 1) % n], v[(i + 1) % n]);
        out[i] = v[i] + s.dt * (p[0] * (2.0 * v[i] - l - r) + p[1] * (v[i] - l) + reaction(i) * v[i]);
    }
}

fn reactive_rhs(_: &Reactive, x: &[f64], _p: &[f64], b: &mut [f64]) {
    b.copy_from_slice(x);
}

fn reactive_diagonal(s: &Reactive, p: &[f64], r: &[f64], z: &mut [f64]) {
    for i in 0..s.n {
        z[i] = if s.jacobi { r[i] / (1.0 + s.dt * (2.0 * p[0] + p[1] + reaction(i))) } else { r[i] };
    }
}

diffsim::linear_system!(Reactive => reactive_matvec, reactive_rhs, preconditioner = reactive_diagonal);

/// BiCGStab preconditioned on the right: the solution and gradient of the
/// direct solve (which ignores the preconditioner), in fewer matrix
/// products than with the identity, forward and transposed; the checks
/// pass.
#[test]
fn bicgstab_preconditioned_on_the_right_agrees_with_the_direct_solve() {
    let (n, dt) = (40, 2.0);
    let params = SolveParams { method: SolveMethod::BiCgStab, tolerance: 1e-12, ..SolveParams::default() };
    let direct = LinearSolve::new(Reactive { n, dt, jacobi: true }, SolveParams { method: SolveMethod::Direct, ..params });
    let identity = LinearSolve::new(Reactive { n, dt, jacobi: false }, params);
    let jacobi = LinearSolve::new(Reactive { n, dt, jacobi: true }, params);
    let (x, p, w) = (field(n, 1.0), [0.3, 0.8], field(n, -0.6));
    let exact = direct.eval(&x, &p);
    let (dx, dp) = direct.vjp_new(&x, &p, &w);
    for op in [&identity, &jacobi] {
        assert!(relative_gap(&exact, &op.eval(&x, &p)) < 1e-9, "the solution differs");
        let (gx, gp) = op.vjp_new(&x, &p, &w);
        assert!(relative_gap(&dx, &gx) < 1e-9 && relative_gap(&dp, &gp) < 1e-9, "the gradient differs: {dp:?} {gp:?}");
    }
    let products = |s: &diffsim::implicit::SolveInfo| s.forward.load(Ordering::Relaxed) + s.adjoint.load(Ordering::Relaxed);
    let (k_identity, k_jacobi) = (products(&identity.info), products(&jacobi.info));
    println!("reactive drift, BiCGStab products forward + adjoint: Jacobi {k_jacobi}, identity {k_identity}");
    assert!(k_jacobi < k_identity, "Jacobi {k_jacobi} products, identity {k_identity}");
    let report = check_all(&jacobi, &x, &p, &CheckParams::default());
    assert!(report.passed(), "{report}");
}

/// Conduction on a line of insulated cells, `A(p)·v` with the face
/// conductances `exp p` (`n − 1` inner faces) and nothing else: singular,
/// the constant vector its null space.
struct Insulated {
    n: usize,
}

impl LinearSystem for Insulated {
    fn n(&self) -> usize {
        self.n
    }
    fn n_in(&self) -> usize {
        self.n
    }
    fn n_params(&self) -> usize {
        self.n - 1
    }
    fn constant_null_space(&self) -> bool {
        true
    }
}

fn insulated_matvec(s: &Insulated, v: &[f64], p: &[f64], out: &mut [f64]) {
    out.fill(0.0);
    for f in 0..s.n - 1 {
        let flux = p[f].exp() * (v[f] - v[f + 1]);
        out[f] += flux;
        out[f + 1] -= flux;
    }
}

fn insulated_rhs(_: &Insulated, x: &[f64], _p: &[f64], b: &mut [f64]) {
    b.copy_from_slice(x);
}

diffsim::linear_system!(Insulated => insulated_matvec, insulated_rhs);

/// A singular system with the constant null space (`constant_null_space`):
/// CG solves for the right-hand side without its mean and returns the
/// solution of zero mean; on a line that solution is known in closed form
/// (the flux through face `f` is the sum of the sources left of it), and
/// the checks pass for the sources and the conductances. Any other method
/// is refused.
#[test]
fn a_system_with_a_constant_null_space_is_solved_without_its_mean() {
    let n = 16;
    let op = LinearSolve::new(Insulated { n }, SolveParams { tolerance: 1e-12, ..SolveParams::default() });
    let (x, p) = (field(n, 1.0), field(n - 1, 0.5));
    let y = op.eval(&x, &p);
    assert!(op.take_error().is_none());
    let mean_x = x.iter().sum::<f64>() / n as f64;
    // Closed form: flux_f = Σ_{i ≤ f} (x_i − x̄) = exp(p_f)·(y_f − y_{f+1}).
    let mut exact = vec![0.0; n];
    let mut flux = 0.0;
    for f in 0..n - 1 {
        flux += x[f] - mean_x;
        exact[f + 1] = exact[f] - flux / p[f].exp();
    }
    let shift = exact.iter().sum::<f64>() / n as f64;
    exact.iter_mut().for_each(|v| *v -= shift);
    assert!(relative_gap(&exact, &y) < 1e-9, "the solution differs from the closed form by {:e}", relative_gap(&exact, &y));
    assert!(y.iter().sum::<f64>().abs() < 1e-10, "the solution's mean is not zero");
    let report = check_all(&op, &x, &p, &CheckParams::default());
    assert!(report.passed(), "{report}");
}

#[test]
#[should_panic(expected = "a system with a constant null space is solved by SolveMethod::Cg")]
fn a_constant_null_space_needs_cg() {
    LinearSolve::new(Insulated { n: 4 }, SolveParams { method: SolveMethod::BiCgStab, ..SolveParams::default() });
}
