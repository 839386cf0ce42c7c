//! 2D fluid operators: gradient checks (parameters included), stability of
//! implicit diffusion far beyond the explicit limit, refusal of an unstable
//! explicit step, conservation of the upwind scheme.

use diffsim::check::{CheckParams, check_all};
use diffsim::fluids::{AdvectUpwind, DiffuseExplicit, DiffuseImplicit};
use diffsim::op::{OpError, OperatorExt};
use diffsim::rollout::{Pass, Rollout, RolloutError};
use diffsim_solvers::smoke::MacGrid;

fn field(n: usize, seed: u64) -> Vec<f64> {
    (0..n).map(|k| (((k as f64 + 1.0) * 0.6180339887 * (seed as f64 + 0.7)).fract() - 0.5) * 2.0).collect()
}

#[test]
fn diffusion_operators_pass_all_checks() {
    for n in [4, 7] {
        let x = field(n * n, n as u64);
        let r = check_all(&DiffuseExplicit::new(n), &x, &[0.15], &CheckParams::default());
        assert!(r.passed(), "explicit n = {n}:\n{r}");
        let r = check_all(&DiffuseImplicit::new(n, 1e-13, 500), &x, &[0.7], &CheckParams::default());
        assert!(r.passed(), "implicit n = {n}:\n{r}");
    }
}

#[test]
fn upwind_advection_passes_all_checks_and_conserves_mass() {
    for n in [4, 7] {
        let cfg = MacGrid::p2(n);
        let op = AdvectUpwind { cfg, dt: 0.4 };
        // Smoke in [0, 2], velocities bounded away from the switch at 0.
        let x: Vec<f64> = field(cfg.n_state(), 3 + n as u64)
            .iter()
            .enumerate()
            .map(|(k, v)| if k < cfg.n_s() { 1.0 + v } else { v.signum() * (0.1 + 0.3 * v.abs()) })
            .collect();
        let r = check_all(&op, &x, &[], &CheckParams::default());
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

#[test]
fn maccormack_passes_the_checks_and_its_limiter_creates_no_extrema() {
    use diffsim::check::Verdict;
    use diffsim::fluids::Advect;
    use diffsim_solvers::smoke::Scheme;
    for n in [5, 8] {
        let cfg = MacGrid::p2(n);
        let x: Vec<f64> = field(cfg.n_state(), 11 + n as u64).iter().enumerate().map(|(k, v)| if k < cfg.n_s() { 1.0 + v } else { 0.3 * v }).collect();
        let mc = |limiter| Advect::new(cfg, Scheme::MacCormack { limiter });
        let r = check_all(&mc(false), &x, &[], &CheckParams::default());
        assert!(r.passed(), "MacCormack n = {n}:\n{r}");
        // With the limiter the map is piecewise smooth: the checks may report
        // a kink, but never a failure.
        let r = check_all(&mc(true), &x, &[], &CheckParams::default());
        for v in [&r.fd.verdict, &r.taylor.verdict, &r.dot.verdict] {
            assert!(!matches!(v, Verdict::Fail(_)), "limited MacCormack n = {n}:\n{r}");
        }
        let y = mc(true).eval(&x, &[]);
        let (lo, hi) = x[..cfg.n_s()].iter().fold((f64::INFINITY, f64::NEG_INFINITY), |(a, b), &v| (a.min(v), b.max(v)));
        assert!(y[..cfg.n_s()].iter().all(|&v| v >= lo - 1e-12 && v <= hi + 1e-12), "limiter let a new extremum through");
    }
}

#[test]
fn maccormack_is_more_accurate_than_semi_lagrangian_on_a_smooth_translation() {
    // A smooth bump translated by a constant velocity (0.3, 0.2) for 10
    // steps: compare each scheme with the exactly translated bump.
    use diffsim::fluids::Advect;
    use diffsim_solvers::smoke::Scheme;
    let n = 32;
    let cfg = MacGrid::p2(n);
    let bump = |x: f64, y: f64| (-((x - 12.0).powi(2) + (y - 12.0).powi(2)) / 18.0).exp();
    let mut x = vec![0.0; cfg.n_state()];
    for j in 0..n {
        for i in 0..n {
            x[j * n + i] = bump(i as f64 + 0.5, j as f64 + 0.5);
        }
    }
    let (us, vs) = (cfg.n_s(), cfg.n_s() + cfg.n_face(0));
    x[us..vs].fill(0.3);
    x[vs..].fill(0.2);
    let run = |scheme: Scheme| -> f64 {
        let op = Advect { velocity: false, ..Advect::new(cfg, scheme) };
        let mut s = x.clone();
        for _ in 0..10 {
            s = op.eval(&s, &[]);
        }
        let mut err = 0.0f64;
        for j in 0..n {
            for i in 0..n {
                err = err.max((s[j * n + i] - bump(i as f64 + 0.5 - 3.0, j as f64 + 0.5 - 2.0)).abs());
            }
        }
        err
    };
    let (sl, mc, mcl) = (run(Scheme::SemiLagrangian), run(Scheme::MacCormack { limiter: false }), run(Scheme::MacCormack { limiter: true }));
    eprintln!("max error after 10 steps: semi-Lagrangian {sl:.3e}, MacCormack {mc:.3e}, limited {mcl:.3e}");
    assert!(mc < 0.5 * sl, "MacCormack {mc} vs semi-Lagrangian {sl}");
    assert!(mcl <= sl, "limited MacCormack {mcl} vs semi-Lagrangian {sl}");
}

#[test]
fn force_and_inflow_pass_all_checks() {
    use diffsim::fluids::{Force, Inflow};
    for n in [4, 7] {
        let cfg = MacGrid::p2(n);
        let x = field(cfg.n_state(), 21 + n as u64);
        let f = field(cfg.n_vel(), 5);
        let r = check_all(&Force { cfg, dt: 0.5 }, &x, &f, &CheckParams::default());
        assert!(r.passed(), "force n = {n}:\n{r}");
        let op = Inflow { cfg, region: [[1, 3], [0, 2]] };
        let r = check_all(&op, &x, &[1.0, 0.2, 0.7], &CheckParams::default());
        assert!(r.passed(), "inflow n = {n}:\n{r}");
        // The inflow values are what the region holds afterwards.
        let y = op.eval(&x, &[1.0, 0.2, 0.7]);
        assert_eq!(y[n + 2], 1.0);
    }
}
