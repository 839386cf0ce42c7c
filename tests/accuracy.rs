//! Exact references, observed orders of convergence and the Pareto front
//! (`diffsim_studies::accuracy`).

use std::f64::consts::PI;

use diffsim::op::OpError;
use diffsim_solvers::burgers::Advection1d;
use diffsim_solvers::exact::{ColeHopf, TaylorGreen};
use diffsim_solvers::smoke::Scheme;
use diffsim_studies::accuracy::burgers::{BurgersRun, BurgersScheme};
use diffsim_studies::accuracy::flow::{AbcRun, HeatRun, NavierStokesRun, ScalarScheme, TaylorGreenRun, TranslationRun};
use diffsim_studies::accuracy::pareto::{Measurement, mark_front};
use diffsim_studies::accuracy::{AccuracyError, Diffusion, observed_orders};

/// Modified Bessel function `I_k(a)·e^{−a}` by the trapezoidal rule on
/// `(1/π)∫₀^π e^{a(cos θ − 1)} cos(kθ) dθ` (periodic integrand: spectrally
/// accurate).
fn bessel_i_scaled(k: usize, a: f64) -> f64 {
    let m = 2000;
    let h = PI / m as f64;
    let mut s = 0.0;
    for j in 0..=m {
        let t = j as f64 * h;
        let w = if j == 0 || j == m { 0.5 } else { 1.0 };
        s += w * (a * (t.cos() - 1.0)).exp() * (k as f64 * t).cos();
    }
    s * h / PI
}

#[test]
fn cole_hopf_matches_the_fourier_series_solution() {
    // φ = I₀(a) + 2 Σ I_k(a) e^{−νk²t} cos(kx), a = 1/(2ν); u = −2ν φ_x/φ.
    // An independent route to the same solution (series, not the heat
    // kernel integral).
    let nu = 0.1;
    let a = 1.0 / (2.0 * nu);
    let coef: Vec<f64> = (0..60).map(|k| bessel_i_scaled(k, a)).collect();
    let exact = ColeHopf::new(nu);
    let mut worst: f64 = 0.0;
    for &t in &[0.0, 0.3, 1.0, 2.0] {
        for j in 0..16 {
            let x = 2.0 * PI * j as f64 / 16.0 + 0.1;
            let (mut phi, mut phix) = (coef[0], 0.0);
            for (k, c) in coef.iter().enumerate().skip(1) {
                let d = 2.0 * c * (-nu * (k * k) as f64 * t).exp();
                phi += d * (k as f64 * x).cos();
                phix -= d * k as f64 * (k as f64 * x).sin();
            }
            let series = -2.0 * nu * phix / phi;
            worst = worst.max((exact.at(x, t) - series).abs());
        }
    }
    assert!(worst < 1e-10, "Cole–Hopf integral vs Fourier series: {worst:.3e}");
}

#[test]
fn taylor_green_solves_navier_stokes() {
    // Residual of u_t + u·u_x + v·u_y + p_x − ν·Δu by central differences
    // of the exact fields, with the exact pressure.
    let tg = TaylorGreen { length: 2.0, amplitude: 0.7, nu: 0.03 };
    let k = PI; // 2π/L
    let p = |x: f64, y: f64, t: f64| 0.25 * 0.7f64.powi(2) * ((2.0 * k * x).cos() + (2.0 * k * y).cos()) * (-4.0 * 0.03 * k * k * t).exp();
    let h = 1e-4;
    for &(x, y, t) in &[(0.3, 0.7, 0.2), (1.1, 0.4, 1.0), (1.9, 1.3, 0.5)] {
        let u = |x, y, t| tg.velocity(x, y, t).0;
        let v = |x, y, t| tg.velocity(x, y, t).1;
        let (uc, vc) = tg.velocity(x, y, t);
        let ut = (u(x, y, t + h) - u(x, y, t - h)) / (2.0 * h);
        let ux = (u(x + h, y, t) - u(x - h, y, t)) / (2.0 * h);
        let uy = (u(x, y + h, t) - u(x, y - h, t)) / (2.0 * h);
        let lap = (u(x + h, y, t) + u(x - h, y, t) + u(x, y + h, t) + u(x, y - h, t) - 4.0 * uc) / (h * h);
        let px = (p(x + h, y, t) - p(x - h, y, t)) / (2.0 * h);
        let r = ut + uc * ux + vc * uy + px - 0.03 * lap;
        let div = ux + (v(x, y + h, t) - v(x, y - h, t)) / (2.0 * h);
        assert!(r.abs() < 1e-5 && div.abs() < 1e-8, "residual {r:.2e}, divergence {div:.2e} at ({x}, {y}, {t})");
    }
}

/// Errors on the grids `ns` and the observed orders between them.
fn orders(ns: &[usize], error: impl Fn(usize) -> Result<f64, AccuracyError>) -> (Vec<f64>, Vec<f64>) {
    let e: Vec<f64> = ns.iter().map(|&n| error(n).unwrap()).collect();
    let h: Vec<f64> = ns.iter().map(|&n| 1.0 / n as f64).collect();
    let o = observed_orders(&h, &e);
    (e, o)
}

fn sci(v: &[f64]) -> String {
    v.iter().map(|x| format!("{x:.3e}")).collect::<Vec<_>>().join(", ")
}

fn assert_order(what: &str, ns: &[usize], expected: (f64, f64), error: impl Fn(usize) -> Result<f64, AccuracyError>) -> f64 {
    let (e, o) = orders(ns, error);
    println!("{what}: errors {}, observed orders {o:.2?}", sci(&e));
    let last = *o.last().unwrap();
    assert!(last >= expected.0 && last <= expected.1, "{what}: observed order {last:.2} outside [{}, {}] (errors {})", expected.0, expected.1, sci(&e));
    last
}

#[test]
fn translation_orders_of_convergence() {
    let ns = [32, 64, 128];
    let run = |scheme| move |n| TranslationRun { n, t_end: 1.0, cfl: 0.5, scheme }.error();
    assert_order("translation, upwind", &ns, (0.8, 1.2), run(ScalarScheme::Upwind));
    assert_order("translation, semi-Lagrangian", &ns, (0.8, 1.3), run(ScalarScheme::Traced(Scheme::SemiLagrangian)));
    assert_order("translation, MacCormack", &ns, (1.8, 2.3), run(ScalarScheme::Traced(Scheme::MacCormack { limiter: false })));
    // The limiter clamps at extrema, where it lowers the order: reported,
    // and still at least first order.
    let limited = assert_order("translation, MacCormack with limiter", &ns, (0.9, 2.3), run(ScalarScheme::Traced(Scheme::MacCormack { limiter: true })));
    println!("limiter on: order {limited:.2} (off: second order)");
}

#[test]
fn heat_orders_of_convergence_and_the_explicit_limit() {
    let ns = [16, 32, 64];
    let run = |diffusion, dt_factor| move |n| HeatRun { n, nu: 0.1, t_end: 1.0, dt_factor, diffusion }.error();
    assert_order("heat, explicit", &ns, (1.8, 2.2), run(Diffusion::Explicit, 0.2));
    assert_order("heat, implicit", &ns, (1.8, 2.2), run(Diffusion::Implicit { tolerance: 1e-12 }, 0.2));
    // Beyond the explicit limit (κ ≈ 0.43 > 0.25): refused, not run.
    match run(Diffusion::Explicit, 0.5)(32) {
        Err(AccuracyError::Operator { stage: "diffusion", step: 0, error: OpError::Unstable { limit, .. } }) => assert_eq!(limit, 0.25),
        other => panic!("expected the explicit limit to be refused, got {other:?}"),
    }
}

#[test]
fn burgers_orders_of_convergence() {
    let ns = [64, 128, 256];
    let run = |cfl, scheme| move |n| BurgersRun::new(n, 0.1, 0.5, cfl, scheme).error();
    assert_order("Burgers, P1 fused upwind", &ns, (0.8, 1.2), run(0.25, BurgersScheme::Fused));
    assert_order("Burgers, semi-Lagrangian", &ns, (0.8, 1.3), run(0.5, BurgersScheme::Split(Advection1d::SemiLagrangian, Diffusion::Explicit)));
    // With explicit diffusion the step is diffusion-limited (dt ∝ h²), so
    // the splitting error is second order too.
    assert_order("Burgers, MacCormack", &ns, (1.8, 2.3), run(1.0, BurgersScheme::Split(Advection1d::MacCormack, Diffusion::Explicit)));
}

#[test]
fn taylor_green_orders_of_convergence() {
    let ns = [16, 32, 64];
    let run = |scheme, nu| {
        move |n| TaylorGreenRun { n, nu, t_end: 1.0, cfl: 0.5, scheme, diffusion: Diffusion::Implicit { tolerance: 1e-12 }, pressure_tolerance: 1e-12 }.error()
    };
    // At a fixed Courant number both are first order: the velocity that
    // carries the trace is frozen at the start of the step and the
    // projection follows the advection (splitting), both O(dt). MacCormack's
    // second order in space (shown on translation) makes it about 3× more
    // accurate at the same grid and step.
    assert_order("Taylor–Green, semi-Lagrangian", &ns, (0.8, 1.3), run(Scheme::SemiLagrangian, 0.01));
    assert_order("Taylor–Green, MacCormack", &ns, (0.8, 1.3), run(Scheme::MacCormack { limiter: false }, 0.01));
    let (sl, mc) = (run(Scheme::SemiLagrangian, 0.01)(64).unwrap(), run(Scheme::MacCormack { limiter: false }, 0.01)(64).unwrap());
    assert!(mc < 0.5 * sl, "MacCormack {mc:.3e} vs semi-Lagrangian {sl:.3e} at 64²");
}

#[test]
fn the_navier_stokes_operator_converges_on_taylor_green_at_any_call_length() {
    // The operator's own sub-steps: calls of Courant number 0.8 take one
    // each, first order as the composed scheme.
    let ns = [16, 32, 64];
    let run = |cfl| {
        move |n| NavierStokesRun { n, nu: 0.01, t_end: 1.0, cfl, scheme: Scheme::MacCormack { limiter: false }, viscosity: Diffusion::Explicit }.run_error()
    };
    assert_order("Taylor–Green, the operator, calls of Courant number 0.8", &ns, (0.7, 1.5), run(0.8));
    // Calls five times longer: split into sub-steps within the Courant limit
    // (how many depends on the rounding of the calls to the final time),
    // stable and converging alike (measured 0.84, 0.93).
    assert_order("Taylor–Green, the operator, calls of Courant number 4", &ns, (0.5, 1.5), run(4.0));
    // The same settings composed from the fluid operators (explicit
    // viscosity, MacCormack, FFT projection): the same error.
    let composed = TaylorGreenRun {
        n: 32,
        nu: 0.01,
        t_end: 1.0,
        cfl: 0.8,
        scheme: Scheme::MacCormack { limiter: false },
        diffusion: Diffusion::Explicit,
        pressure_tolerance: 1e-8,
    }
    .error()
    .unwrap();
    let operator = run(0.8)(32).unwrap();
    assert!((operator / composed - 1.0).abs() < 0.01, "operator {operator:.4e} against the composed scheme {composed:.4e} at 32²");
}

#[test]
fn the_navier_stokes_operator_converges_on_the_abc_flow_in_3d() {
    // `diffsim pareto abc`'s runs: calls of Courant number 0.8 and of 4
    // (split into sub-steps), MacCormack, explicit viscosity.
    let ns = [8, 16, 32];
    let error = |cfl, scheme| {
        move |n| {
            let r = AbcRun { n, nu: 0.05, t_end: 1.0, cfl, scheme, viscosity: Diffusion::Explicit };
            r.run().map(|x| r.error_of(&x))
        }
    };
    let mc = Scheme::MacCormack { limiter: false };
    assert_order("ABC, the operator, calls of Courant number 0.8", &ns, (0.7, 2.0), error(0.8, mc));
    assert_order("ABC, the operator, calls of Courant number 4", &ns, (0.5, 2.0), error(4.0, mc));
    // MacCormack well below semi-Lagrangian at 32³; implicit viscosity
    // (its solve to 1e-8) within 10% of explicit.
    let (sl, m) = (error(0.8, Scheme::SemiLagrangian)(32).unwrap(), error(0.8, mc)(32).unwrap());
    assert!(m < 0.5 * sl, "MacCormack {m:.3e} against semi-Lagrangian {sl:.3e} at 32³");
    let implicit = AbcRun { n: 32, nu: 0.05, t_end: 1.0, cfl: 0.8, scheme: mc, viscosity: Diffusion::Implicit { tolerance: 1e-8 } };
    let i = implicit.error_of(&implicit.run().unwrap());
    assert!((i / m - 1.0).abs() < 0.1, "implicit {i:.3e} against explicit {m:.3e} at 32³");
}

#[test]
fn unstable_runs_stop_with_the_step_instead_of_nans() {
    // Upwind at three times its Courant limit with next to no viscosity
    // blows up (the quadratic term overflows): reported with the step.
    let r = BurgersRun::new(64, 1e-6, 50.0, 3.0, BurgersScheme::Split(Advection1d::Upwind, Diffusion::Implicit { tolerance: 1e-8 }));
    match r.run() {
        Err(AccuracyError::NonFinite { stage, step }) => println!("non-finite after the {stage} of step {step}"),
        Err(AccuracyError::Operator { stage, step, error }) => println!("{stage} at step {step}: {error}"),
        other => panic!("expected a reported blow-up, got {:?}", other.map(|u| u[0])),
    }
    // Explicit diffusion beyond its limit is refused before the first step.
    let r = BurgersRun { diffusion_number: 0.6, ..BurgersRun::new(64, 0.5, 1.0, 0.5, BurgersScheme::Fused) };
    assert!(matches!(r.run(), Err(AccuracyError::Operator { stage: "diffusion", step: 0, error: OpError::Unstable { .. } })));
    let bad = BurgersRun::new(2, 0.05, 1.0, 0.5, BurgersScheme::Fused).run();
    assert!(matches!(bad, Err(AccuracyError::Invalid { what: "n", .. })), "{bad:?}");
}

#[test]
fn pareto_front_is_the_set_of_undominated_points() {
    let m = |error: f64, time_s: f64| Measurement { family: "f".into(), params: Default::default(), error, time_s, peak_rss_bytes: 0, pareto: false };
    let mut ms = vec![m(1.0, 1.0), m(0.5, 2.0), m(0.6, 3.0), m(0.1, 10.0), m(1.0, 1.0), m(f64::NAN, 0.1), m(2.0, 0.5)];
    mark_front(&mut ms);
    let front: Vec<bool> = ms.iter().map(|x| x.pareto).collect();
    assert_eq!(front, vec![true, true, false, true, true, false, true]);
}

#[test]
fn every_stability_case_passes() {
    let cases = diffsim_studies::accuracy::stability::run_all();
    for c in &cases {
        println!("{}: {} {}", c.case, c.passed, c.summary);
    }
    let failed: Vec<&str> = cases.iter().filter(|c| !c.passed).map(|c| c.case.as_str()).collect();
    assert!(failed.is_empty(), "stability cases not passed: {failed:?}");
    assert!(cases.len() >= 9);
}
