//! 2D fluid operators: gradient checks (parameters included), stability of
//! implicit diffusion far beyond the explicit limit, refusal of an unstable
//! explicit step, conservation of the upwind scheme.

use diffsim::check::{CheckOptions, check_all};
use diffsim::fluids::{AdvectUpwind, DiffuseExplicit, DiffuseImplicit};
use diffsim::op::{OpError, OperatorExt};
use diffsim::rollout::{Pass, Rollout, RolloutError};
use diffsim_solvers::smoke::Smoke2d;

fn field(n: usize, seed: u64) -> Vec<f64> {
    (0..n).map(|k| (((k as f64 + 1.0) * 0.6180339887 * (seed as f64 + 0.7)).fract() - 0.5) * 2.0).collect()
}

#[test]
fn diffusion_operators_pass_all_checks() {
    for n in [4, 7] {
        let x = field(n * n, n as u64);
        let r = check_all(&DiffuseExplicit::new(n), &x, &[0.15], &CheckOptions::default());
        assert!(r.passed(), "explicit n = {n}:\n{r}");
        let r = check_all(&DiffuseImplicit::new(n, 1e-13, 500), &x, &[0.7], &CheckOptions::default());
        assert!(r.passed(), "implicit n = {n}:\n{r}");
    }
}

#[test]
fn upwind_advection_passes_all_checks_and_conserves_mass() {
    for n in [4, 7] {
        let cfg = Smoke2d::p2(n);
        let op = AdvectUpwind { cfg, dt: 0.4 };
        // Smoke in [0, 2], velocities bounded away from the switch at 0.
        let x: Vec<f64> = field(cfg.n_state(), 3 + n as u64)
            .iter()
            .enumerate()
            .map(|(k, v)| if k < cfg.n_s() { 1.0 + v } else { v.signum() * (0.1 + 0.3 * v.abs()) })
            .collect();
        let r = check_all(&op, &x, &[], &CheckOptions::default());
        assert!(r.passed(), "upwind n = {n}:\n{r}");
        let y = op.eval(&x, &[]);
        let mass = |v: &[f64]| v[..cfg.n_s()].iter().sum::<f64>();
        assert!((mass(&y) - mass(&x)).abs() < 1e-12 * mass(&x), "closed box: mass {} → {}", mass(&x), mass(&y));
    }
}

#[test]
fn implicit_diffusion_is_stable_at_100x_the_explicit_limit() {
    let n = 16;
    let op = DiffuseImplicit::new(n, 1e-10, 1000);
    let x0 = field(n * n, 9);
    let kappa = [100.0 * diffsim_solvers::diffusion::EXPLICIT_LIMIT];
    let r = Rollout::new(&op, &kappa, 50).unwrap();
    let x = r.final_state(&x0).unwrap();
    let (max0, max) = (x0.iter().fold(0.0f64, |m, v| m.max(v.abs())), x.iter().fold(0.0f64, |m, v| m.max(v.abs())));
    assert!(max <= max0, "maximum principle: {max} > {max0}");
    // Mass is conserved (closed box) and the field tends to its mean.
    let mean0 = x0.iter().sum::<f64>() / x0.len() as f64;
    let mean = x.iter().sum::<f64>() / x.len() as f64;
    assert!((mean - mean0).abs() < 1e-9, "{mean} vs {mean0}");
    assert!(x.iter().all(|v| (v - mean).abs() < 0.05), "not yet smooth");
}

#[test]
fn an_unstable_explicit_step_is_an_error() {
    let n = 8;
    let op = DiffuseExplicit::new(n);
    let r = Rollout::new(&op, &[0.3], 5).unwrap();
    assert_eq!(
        r.final_state(&field(n * n, 2)).unwrap_err(),
        RolloutError::Operator { pass: Pass::Forward, error: OpError::Unstable { value: 0.3, limit: 0.25 } }
    );
}
