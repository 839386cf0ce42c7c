//! Time integrators from a right-hand side only (`ode_system!`): each
//! scheme against its stability function and its order of accuracy
//! (independent closed forms), the three checks on single steps and
//! through rollouts, Robertson's stiff kinetics against ODEPACK's published
//! solution, and its rate constants recovered from the states.

use diffsim::check::{CheckParams, check_all};
use diffsim::implicit::{Integrator, IntegratorParams, OdeSystem, Scheme};
use diffsim::op::{Forward, Operator, OperatorExt};
use diffsim::problems::robertson::{LSODE_STATES, LSODE_TIMES, Robertson, START, log_rates};
use diffsim::rollout::{AtSteps, Checkpointing, Rollout, RolloutLoss, Wrt};
use diffsim::train::{FnObjective, Lbfgs, LbfgsParams, LbfgsStep};
use std::sync::atomic::Ordering;

/// `du/dt = −k·u` on two components, `k = p[0]`.
struct Decay;

impl OdeSystem for Decay {
    fn n(&self) -> usize {
        2
    }
    fn n_params(&self) -> usize {
        1
    }
}

fn decay(_: &Decay, u: &[f64], p: &[f64], du: &mut [f64]) {
    du[0] = -p[0] * u[0];
    du[1] = -p[0] * u[1];
}

diffsim::ode_system!(Decay => decay);

/// Each scheme's stability function `R(z)`, `u_{n+1} = R(h·λ)·u_n` for
/// `du/dt = λ·u`, in closed form.
fn stability(scheme: Scheme, z: f64) -> Option<f64> {
    let g = 1.0 - std::f64::consts::FRAC_1_SQRT_2;
    match scheme {
        Scheme::SspRk3 => Some(1.0 + z + z * z / 2.0 + z * z * z / 6.0),
        Scheme::Rk4 => Some(1.0 + z + z * z / 2.0 + z * z * z / 6.0 + z * z * z * z / 24.0),
        Scheme::BackwardEuler => Some(1.0 / (1.0 - z)),
        Scheme::CrankNicolson => Some((1.0 + z / 2.0) / (1.0 - z / 2.0)),
        // 2 stages, γ = 1 − 1/√2: (1 + (1 − 2γ)·z + (γ² − 2γ + ½)·z²)/(1 − γz)², the z² term 0.
        Scheme::Sdirk2 => Some((1.0 + (1.0 - 2.0 * g) * z) / ((1.0 - g * z) * (1.0 - g * z))),
        Scheme::Sdirk3 | Scheme::Bdf2 => None,
    }
}

/// The start `[u, u]` of a two-level scheme, `u` for the others.
fn state(scheme: Scheme, u: &[f64]) -> Vec<f64> {
    u.repeat(scheme.levels())
}

#[test]
fn every_scheme_steps_linear_decay_by_its_stability_function() {
    let (u, k, dt) = ([1.0, -0.5], 3.0, 0.1);
    for scheme in Scheme::ALL {
        let op = Integrator::new(Decay, IntegratorParams::new(scheme, dt));
        let y = op.eval(&state(scheme, &u), &[k]);
        let z = -k * dt;
        if scheme == Scheme::Bdf2 {
            // From [u_n, u_{n−1}]: u_{n+1} = (4·u_n − u_{n−1})/(3 − 2z), and u_n moves down.
            let (un, older) = ([0.7, 0.2], [1.0, -0.5]);
            let y = op.eval(&[un[0], un[1], older[0], older[1]], &[k]);
            for i in 0..2 {
                assert!((y[i] - (4.0 * un[i] - older[i]) / (3.0 - 2.0 * z)).abs() < 1e-12, "Bdf2: {y:?}");
                assert_eq!(y[2 + i], un[i], "Bdf2 keeps u_n as the older level");
            }
        }
        if let Some(r) = stability(scheme, z) {
            assert!((y[0] - r * u[0]).abs() < 1e-12 && (y[1] - r * u[1]).abs() < 1e-12, "{scheme:?}: {y:?} against R = {r}");
            // dR/dk by central differences of the closed form.
            let e = 1e-6;
            let slope = (stability(scheme, -(k + e) * dt).unwrap() - stability(scheme, -(k - e) * dt).unwrap()) / (2.0 * e);
            let (_, dp) = op.vjp_new(&u, &[k], &[1.0, 1.0]);
            assert!((dp[0] - slope * (u[0] + u[1])).abs() < 1e-8, "{scheme:?}: d/dk {} against {}", dp[0], slope * (u[0] + u[1]));
        }
        // A stiff mode: L-stable schemes damp it, Crank–Nicolson keeps it
        // ringing, the explicit ones blow up (and say nothing: they are
        // explicit).
        let stiff = op.eval(&state(scheme, &u), &[1e4])[0] / u[0];
        match scheme {
            Scheme::BackwardEuler | Scheme::Sdirk2 | Scheme::Sdirk3 | Scheme::Bdf2 => assert!(stiff.abs() < 1e-2, "{scheme:?}: {stiff}"),
            Scheme::CrankNicolson => assert!((stiff + 1.0).abs() < 1e-2, "{scheme:?}: {stiff}"),
            Scheme::SspRk3 | Scheme::Rk4 => assert!(stiff.abs() > 1e3, "{scheme:?}: {stiff}"),
        }
    }
}

/// `du/dt = −u²`, `dv/dt = u·v`: from (1, 1), `u = 1/(1 + t)`, `v = 1 + t`.
struct Riccati;

impl OdeSystem for Riccati {
    fn n(&self) -> usize {
        2
    }
}

fn riccati(_: &Riccati, u: &[f64], _p: &[f64], du: &mut [f64]) {
    du[0] = -u[0] * u[0];
    du[1] = u[0] * u[1];
}

diffsim::ode_system!(Riccati => riccati);

fn error_at_one(scheme: Scheme, steps: usize) -> f64 {
    let params = IntegratorParams::new(scheme, 1.0 / steps as f64);
    let op = Integrator::new(Riccati, params);
    let mut u = vec![1.0, 1.0];
    let mut first = 0;
    if scheme == Scheme::Bdf2 {
        u = Integrator::bdf2_start(Riccati, params).eval(&u, &[]);
        first = 1;
    }
    for _ in first..steps {
        u = op.eval(&u, &[]);
    }
    (u[0] - 0.5).abs().max((u[1] - 2.0).abs())
}

#[test]
fn every_scheme_converges_at_its_order_on_a_nonlinear_system() {
    for scheme in Scheme::ALL {
        let (coarse, fine) = (error_at_one(scheme, 10), error_at_one(scheme, 20));
        let rate = (coarse / fine).log2();
        let order = scheme.order() as f64;
        assert!((rate - order).abs() < 0.3, "{scheme:?}: observed order {rate:.2}, expected {order} (errors {coarse:.2e}, {fine:.2e})");
    }
}

/// Lotka–Volterra, `p = [a, b, c, d]`: `du/dt = a·u − b·u·v`,
/// `dv/dt = c·u·v − d·v` (nonlinear, coupled, a non-symmetric Jacobian).
struct Predation;

impl OdeSystem for Predation {
    fn n(&self) -> usize {
        2
    }
    fn n_params(&self) -> usize {
        4
    }
}

fn predation(_: &Predation, u: &[f64], p: &[f64], du: &mut [f64]) {
    du[0] = p[0] * u[0] - p[1] * u[0] * u[1];
    du[1] = p[2] * u[0] * u[1] - p[3] * u[1];
}

diffsim::ode_system!(Predation => predation);

#[test]
fn every_scheme_passes_the_checks_for_the_state_and_the_parameters() {
    for scheme in Scheme::ALL {
        let op = Integrator::new(Predation, IntegratorParams::new(scheme, 0.2));
        let u = [1.0, 0.5, 0.9, 0.6];
        let report = check_all(&op, &u[..op.n_in()], &[1.1, 0.4, 0.4, 0.1], &CheckParams::default());
        assert!(report.passed(), "{scheme:?}: {report}");
    }
}

/// A stiff step checked for the rates (the fit's parameters). Its state
/// has a species at 3·10⁻⁵: the checks' state perturbations, of the order
/// of their steps, would drive it negative, where the stage equations'
/// roots change branch; the state derivative is checked on the system
/// above and through the rollouts below.
#[test]
fn every_scheme_passes_the_checks_on_a_stiff_step_for_the_rates() {
    let u = [0.98, 3.3e-5, 0.0199];
    let start = [u, [0.981, 3.2e-5, 0.0189]].concat();
    for scheme in Scheme::ALL {
        // Crank–Nicolson is not a stiff solver: its stage starts from an
        // explicit half step and needs a small one here.
        let dt = match scheme {
            Scheme::CrankNicolson => 1e-4,
            _ if scheme.is_implicit() => 0.05,
            _ => 1e-5,
        };
        let op = Integrator::new(Robertson, IntegratorParams::new(scheme, dt));
        let loss = AtSteps { steps: vec![1], f: |_t: usize, x: &[f64], g: &mut [f64]| misfit(x, &[0.97, 3.0e-5, 0.03], g) };
        let p0 = log_rates();
        let as_op = RolloutLoss::new(Rollout::new(&op, &p0, 1).unwrap(), &start[..op.n_in()], &loss, Checkpointing::Store, Wrt::P).unwrap();
        let (x, p) = as_op.point();
        let report = check_all(&as_op, x, p, &CheckParams::default());
        assert!(report.passed(), "{scheme:?}: {report}");
    }
}

/// The loss of the fit below: the scaled species at every tenth step.
fn observations(target: &[Vec<f64>]) -> AtSteps<impl Fn(usize, &[f64], &mut [f64]) -> f64 + '_> {
    AtSteps { steps: (1..=target.len()).map(|k| 10 * k).collect(), f: move |t: usize, x: &[f64], g: &mut [f64]| -> f64 { misfit(x, &target[t / 10 - 1], g) } }
}

/// `½·Σ (s_i·(x_i − want_i))²` with the second species scaled by 10⁴, and
/// its gradient (zero beyond the three species).
fn misfit(x: &[f64], want: &[f64], g: &mut [f64]) -> f64 {
    let scale = [1.0, 1e4, 1.0];
    g.fill(0.0);
    let mut value = 0.0;
    for i in 0..3 {
        let d = scale[i] * (x[i] - want[i]);
        g[i] = scale[i] * d;
        value += 0.5 * d * d;
    }
    value
}

fn trajectory(op: &impl Forward, scheme: Scheme, p: &[f64], steps: usize) -> Vec<Vec<f64>> {
    let mut u = state(scheme, &START);
    let mut kept = Vec::new();
    for t in 1..=steps {
        u = op.eval(&u, p);
        if t % 10 == 0 {
            kept.push(u[..3].to_vec());
        }
    }
    kept
}

#[test]
fn the_checks_pass_through_a_stiff_rollout_for_the_rates() {
    for scheme in [Scheme::BackwardEuler, Scheme::Sdirk2, Scheme::Bdf2] {
        let op = Integrator::new(Robertson, IntegratorParams::new(scheme, 0.02));
        let target = trajectory(&op, scheme, &[-3.0, 17.0, 9.0], 30);
        let loss = observations(&target);
        let p0 = log_rates();
        let start = state(scheme, &START);
        let as_op = RolloutLoss::new(Rollout::new(&op, &p0, 30).unwrap(), &start, &loss, Checkpointing::periodic_sqrt(30), Wrt::P).unwrap();
        let (x, p) = as_op.point();
        let report = check_all(&as_op, x, p, &CheckParams::default());
        assert!(report.passed(), "{scheme:?}: {report}");
    }
}

/// Robertson to t = 40 on fixed steps (finer at the start, where the fast
/// transient is), against the solution ODEPACK's LSODE documentation
/// prints (its tolerance 10⁻⁴ relative): an external reference.
#[test]
fn robertson_matches_odepack_s_published_solution() {
    let p = log_rates();
    let mut u = START.to_vec();
    let mut t0 = 0.0;
    for (t, want) in LSODE_TIMES.iter().zip(&LSODE_STATES) {
        let steps = 200;
        let op = Integrator::new(Robertson, IntegratorParams::new(Scheme::Sdirk3, (t - t0) / steps as f64));
        for _ in 0..steps {
            u = op.eval(&u, &p);
        }
        t0 = *t;
        for i in 0..3 {
            let rel = (u[i] - want[i]).abs() / want[i];
            assert!(rel < 2e-4, "t = {t}, species {}: {} against LSODE's {} (relative {rel:.1e})", i + 1, u[i], want[i]);
        }
        // Mass is conserved by every Runge–Kutta scheme (a linear invariant).
        assert!((u.iter().sum::<f64>() - 1.0).abs() < 1e-12, "t = {t}: Σu = {}", u.iter().sum::<f64>());
    }
}

/// The stiff example of docs/implicit.md: the three rate constants (eight
/// orders of magnitude apart) recovered from the states at ten times by
/// L-BFGS on the log-rates, the gradient through 100 SDIRK2 steps by the
/// implicit rule.
#[test]
fn robertson_s_rate_constants_are_recovered_from_its_states() {
    let op = Integrator::new(Robertson, IntegratorParams::new(Scheme::Sdirk2, 0.04));
    let truth = log_rates();
    let target = trajectory(&op, Scheme::Sdirk2, &truth, 100);
    let loss = observations(&target);
    let mut objective = FnObjective {
        n: 3,
        f: |p: &[f64]| {
            let g = Rollout::new(&op, p, 100)
                .unwrap()
                .value_and_grad(&START, &loss, Checkpointing::Store)
                .map_err(|e| diffsim::train::TrainError::Rollout(e.to_string()))?;
            Ok((g.loss, g.dp))
        },
    };
    let mut p = vec![truth[0] + 0.3, truth[1] - 0.4, truth[2] + 0.3];
    let mut rule = Lbfgs::new(LbfgsParams { tolerance_grad: 1e-12, ..LbfgsParams::default() }).unwrap();
    let mut iterations = 0;
    while iterations < 200 {
        iterations += 1;
        if let LbfgsStep::Converged { .. } = rule.iterate(&mut objective, &mut p).unwrap() {
            break;
        }
    }
    for i in 0..3 {
        assert!((p[i] - truth[i]).abs() < 1e-5, "ln k{} = {} after {iterations} iterations, truth {}", i + 1, p[i], truth[i]);
    }
    assert!(op.info.adjoint_solves.load(Ordering::Relaxed) > 0);
}

/// BDF2 from its start: the rollout's gradient with respect to `[u_1, u_0]`
/// carried back through `bdf2_start`'s VJP gives `dL/du_0` and `dL/dk`,
/// compared with central differences of the whole computation.
#[test]
fn bdf2_from_its_start_gives_the_gradient_of_the_whole_computation() {
    let params = IntegratorParams::new(Scheme::Bdf2, 0.1);
    let (start, step) = (Integrator::bdf2_start(Riccati, params), Integrator::new(Riccati, params));
    let loss = |x: &[f64], g: &mut [f64]| -> f64 {
        g.fill(0.0);
        g[0] = x[0];
        g[1] = 2.0 * x[1];
        0.5 * x[0] * x[0] + x[1] * x[1]
    };
    let total = |u0: &[f64]| -> f64 { Rollout::new(&step, &[], 9).unwrap().loss(&start.eval(u0, &[]), &loss).unwrap() };
    let u0 = [0.9, 1.2];
    let x1 = start.eval(&u0, &[]);
    let g = Rollout::new(&step, &[], 9).unwrap().value_and_grad(&x1, &loss, Checkpointing::Store).unwrap();
    let (du0, _) = start.vjp_new(&u0, &[], &g.dx0);
    for i in 0..2 {
        let e = 1e-6;
        let (mut up, mut down) = (u0, u0);
        up[i] += e;
        down[i] -= e;
        let fd = (total(&up) - total(&down)) / (2.0 * e);
        assert!((du0[i] - fd).abs() < 1e-7 * fd.abs().max(1.0), "dL/du0[{i}]: {} against {fd}", du0[i]);
    }
    let report = check_all(&start, &u0, &[], &CheckParams::default());
    assert!(report.passed(), "{report}");
}

/// Asserts that two VJPs `(dx, dp)` agree entry by entry within `tol`
/// times the first one's largest entry.
fn assert_same_gradient(a: (&[f64], &[f64]), b: (&[f64], &[f64]), tol: f64, what: &str) {
    let scale = a.0.iter().chain(a.1).fold(0.0f64, |m, g| m.max(g.abs()));
    for (g, h) in a.0.iter().chain(a.1).zip(b.0.iter().chain(b.1)) {
        assert!((g - h).abs() <= tol * scale, "{what}: gradient {g} against {h}");
    }
}

/// The stages' held Jacobian (simplified Newton, the direct default) finds
/// the same roots as Newton–Krylov, which forms nothing and takes a fresh
/// Jacobian's product at every iteration with line search: the same step
/// to the tolerances on stiff steps up to dt = 30 (where the first stage's
/// Jacobian is far from the last's), and the same gradient.
#[test]
fn the_stages_held_jacobian_finds_the_roots_of_newton_krylov() {
    use diffsim::implicit::{SolveMethod, SolveParams};
    let u = [0.98, 3.3e-5, 0.0199];
    let p = log_rates();
    for scheme in [Scheme::BackwardEuler, Scheme::Sdirk2, Scheme::Sdirk3] {
        for dt in [0.01, 1.0, 30.0] {
            let mut params = IntegratorParams::new(scheme, dt);
            params.newton.tolerance = 1e-13;
            let held = Integrator::new(Robertson, params);
            params.newton.linear = SolveParams { method: SolveMethod::BiCgStab, tolerance: 1e-14, ..SolveParams::default() };
            let krylov = Integrator::new(Robertson, params);
            let (a, b) = (held.eval(&u, &p), krylov.eval(&u, &p));
            assert!(held.take_error().is_none() && krylov.take_error().is_none(), "{scheme:?}, dt {dt}: a solve failed");
            for i in 0..3 {
                // Newton's tolerance is on the residual, whose size the
                // first species sets: about 1e-13 absolute.
                assert!((a[i] - b[i]).abs() <= 1e-11 * a[i].abs() + 1e-12, "{scheme:?}, dt {dt}, species {i}: {} against {}", a[i], b[i]);
            }
            // (At dt = 30 BiCGStab's transposed solve does not reach
            // 1e-14 on this Jacobian: the gradients are compared below it.)
            if dt > 1.0 {
                continue;
            }
            let w = [1.0, 1e4, -0.5];
            let ((dx_a, dp_a), (dx_b, dp_b)) = (held.vjp_new(&u, &p, &w), krylov.vjp_new(&u, &p, &w));
            assert_same_gradient((&dx_a, &dp_a), (&dx_b, &dp_b), 1e-8, &format!("{scheme:?}, dt {dt}"));
        }
    }
}

/// Robertson's kinetics with its Jacobian written by hand
/// (`ode_system!(.., jacobian = j)`); `error` scales one entry (`∂f₂/∂u₂`,
/// the stiff one) to make it wrong.
struct HandRobertson {
    error: f64,
}

impl OdeSystem for HandRobertson {
    fn n(&self) -> usize {
        3
    }
    fn n_params(&self) -> usize {
        3
    }
}

fn hand_rates(_: &HandRobertson, u: &[f64], p: &[f64], du: &mut [f64]) {
    diffsim::problems::robertson::robertson_rates(&Robertson, u, p, du)
}

/// `∂f/∂u` column by column.
fn hand_jacobian(s: &HandRobertson, u: &[f64], p: &[f64], jac: &mut [f64]) {
    let (k1, k2, k3) = (p[0].exp(), p[1].exp(), p[2].exp());
    let (b, c) = (u[1], u[2]);
    jac.copy_from_slice(&[-k1, k1, 0.0, k3 * c, (-k3 * c - 2.0 * k2 * b) * s.error, 2.0 * k2 * b, k3 * b, -k3 * b, 0.0]);
}

diffsim::ode_system!(HandRobertson => hand_rates, jacobian = hand_jacobian);

/// A user's Jacobian replaces Enzyme's products where the stages are
/// solved directly: the same steps and gradients as Enzyme's to the Newton
/// tolerance, and the checks pass through a stiff rollout; a wrong one
/// (one entry 10 % off) still lets Newton converge, so the step is right,
/// but its gradient is not, and the checks say so.
#[test]
fn a_users_jacobian_gives_enzymes_steps_and_gradients_and_a_wrong_one_fails_the_checks() {
    let u = [0.98, 3.3e-5, 0.0199];
    let p = log_rates();
    for scheme in [Scheme::BackwardEuler, Scheme::Sdirk2, Scheme::Sdirk3, Scheme::Bdf2] {
        let params = IntegratorParams::new(scheme, 0.05);
        let (enzyme, hand) = (Integrator::new(Robertson, params), Integrator::new(HandRobertson { error: 1.0 }, params));
        let x = [u, [0.981, 3.2e-5, 0.0189]].concat();
        let x = &x[..enzyme.n_in()];
        let (a, b) = (enzyme.eval(x, &p), hand.eval(x, &p));
        for (a, b) in a.iter().zip(&b) {
            assert!((a - b).abs() <= 1e-10 * a.abs() + 1e-12, "{scheme:?}: step {a} against {b}");
        }
        let w: Vec<f64> = [1.0, 1e4, -0.5, 0.3, -2.0, 1.0][..enzyme.n_out()].to_vec();
        let ((dx_a, dp_a), (dx_b, dp_b)) = (enzyme.vjp_new(x, &p, &w), hand.vjp_new(x, &p, &w));
        assert_same_gradient((&dx_a, &dp_a), (&dx_b, &dp_b), 1e-9, &format!("{scheme:?}"));
    }
    // Through 30 stiff SDIRK3 steps for the rates: right passes, wrong fails.
    let target = [0.97, 3.0e-5, 0.03];
    let loss = AtSteps { steps: vec![30], f: |_t: usize, x: &[f64], g: &mut [f64]| misfit(x, &target, g) };
    // (One call per case: an array of tuples iterated by value aborts
    // Enzyme's type analysis, docs/pitfalls.md.)
    let checks = |error: f64| {
        let op = Integrator::new(HandRobertson { error }, IntegratorParams::new(Scheme::Sdirk3, 0.05));
        let as_op = RolloutLoss::new(Rollout::new(&op, &p, 30).unwrap(), &u, &loss, Checkpointing::Store, Wrt::P).unwrap();
        let (x, q) = as_op.point();
        let report = check_all(&as_op, x, q, &CheckParams::default());
        (report.passed(), report.to_string())
    };
    let (right, report) = checks(1.0);
    assert!(right, "the right Jacobian: {report}");
    let (wrong, report) = checks(1.1);
    assert!(!wrong, "a Jacobian 10 % off passed the checks: {report}");
}

/// A forward step keeps its stages for its VJP: a rollout's backward pass
/// then solves nothing (no Newton iteration beyond the forward pass's),
/// and a step's VJP from kept stages equals the one that solves them again
/// (a fresh operator, nothing kept) to the Newton tolerance.
#[test]
fn a_rollout_s_backward_pass_reuses_the_forward_steps_stages() {
    let (u, p) = ([0.98, 3.3e-5, 0.0199], log_rates());
    let op = Integrator::new(Robertson, IntegratorParams::new(Scheme::Sdirk3, 0.05));
    let newton = |op: &Integrator<Robertson>| op.info.newton.load(Ordering::Relaxed);
    let loss = AtSteps { steps: vec![20], f: |_t: usize, x: &[f64], g: &mut [f64]| misfit(x, &[0.97, 3.0e-5, 0.03], g) };
    let rollout = Rollout::new(&op, &p, 20).unwrap();
    let before = newton(&op);
    rollout.loss(&u, &loss).unwrap();
    let forward = newton(&op) - before;
    let before = newton(&op);
    rollout.value_and_grad(&u, &loss, Checkpointing::Store).unwrap();
    assert!(forward > 0);
    assert_eq!(newton(&op) - before, forward, "the backward pass solved stages again");
    let w = [1.0, 1e4, -0.5];
    op.eval(&u, &p);
    let (kept_dx, kept_dp) = op.vjp_new(&u, &p, &w);
    let fresh = Integrator::new(Robertson, IntegratorParams::new(Scheme::Sdirk3, 0.05));
    let (dx, dp) = fresh.vjp_new(&u, &p, &w);
    assert_same_gradient((&dx, &dp), (&kept_dx, &kept_dp), 1e-9, "solved again against kept");
    assert!(newton(&fresh) > 0, "the fresh operator solved its stages");
}
