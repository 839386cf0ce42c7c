//! Physics inversion and scale-invariant physics training: the spectral
//! heat operator against exact Fourier modes, its damped inverse, the
//! generic Gauss-Newton local inverse against a direct solve, and the SIP
//! and physics-loss gradients against finite differences.

use diffsim::nn::{Activation, Init, Padding, presets};
use diffsim::op::{GaussNewton, LocalInverse, OperatorExt};
use diffsim::problems::heat::Heat;
use diffsim::problems::oscillators::Oscillators;
use diffsim::train::pg::{InverseSample, physics_loss_and_gradient, sip_gradient, state_error};
use diffsim_studies::heat::samples;
use rand::SeedableRng;
use rand::rngs::StdRng;

use crate::checks::{assert_passes, state};

/// `cos(kx·i + ky·j + φ)` on an `nx × ny` grid and its `|k|²`.
fn mode(nx: usize, ny: usize, mx: usize, my: usize, phase: f64) -> (Vec<f64>, f64) {
    let tau = std::f64::consts::TAU;
    let (kx, ky) = (tau * mx as f64 / nx as f64, tau * my as f64 / ny as f64);
    let v = (0..ny).flat_map(|j| (0..nx).map(move |i| (kx * i as f64 + ky * j as f64 + phase).cos())).collect();
    (v, kx * kx + ky * ky)
}

fn max_diff(a: &[f64], b: &[f64]) -> f64 {
    a.iter().zip(b).map(|(x, y)| (x - y).abs()).fold(0.0, f64::max)
}

#[test]
fn heat_decays_fourier_modes_exactly_and_passes_the_checks() {
    // A non-square grid, so the two axes cannot be mixed up.
    let heat = Heat::new(16, 8, 0.7, 1e-3);
    // (Mode numbers and phases in separate vectors: a by-value array of
    // integer–float tuples crashes Enzyme's type analysis; docs/pitfalls.md.)
    let (mxs, mys, phases) = (vec![0, 1, 0, 5, 8], vec![0, 0, 3, 2, 4], vec![0.0, 0.3, 1.1, -0.4, 0.0]);
    for k in 0..mxs.len() {
        let (mx, my) = (mxs[k], mys[k]);
        let (x, k2) = mode(16, 8, mx, my, phases[k]);
        let y = heat.eval(&x, &[]);
        let f = (-0.7 * k2).exp();
        let expected: Vec<f64> = x.iter().map(|v| f * v).collect();
        assert!(max_diff(&y, &expected) < 1e-12, "mode ({mx}, {my})");
        // The damped inverse scales the mode by f/(f² + ε²).
        let mut back = vec![0.0; x.len()];
        heat.local_inverse(&x, &[], &y, &mut back);
        let g = f * f / (f * f + 1e-6);
        let expected: Vec<f64> = x.iter().map(|v| g * v).collect();
        assert!(max_diff(&back, &expected) < 1e-9, "inverse of mode ({mx}, {my})");
    }
    assert_passes("Heat", &heat, &state(128, 5), &[]);
}

#[test]
fn bayesian_inverse_inverts_signal_keeps_the_undecided_and_damps_noise() {
    use diffsim::problems::heat::BayesianInverse;
    // The published inverse (tum-pbs/SIP heat/inv_diffuse.py), mode by
    // mode, on a 16 × 8 grid: a mode whose amplitude is what a signal has
    // after diffusion (nx·e^{−g}, far above the noise 1e-6·‖y‖) is
    // inverted exactly (×e^{g}); one far below both signal and noise is
    // left as it is (P(signal) ≈ ½, no action); one far above any signal
    // the diffusion could have left is noise and diffused further (×e^{−g}).
    let heat = Heat::new(16, 8, 0.7, 1e-3).with_bayesian_inverse(BayesianInverse::PUBLISHED);
    let n = 128.0;
    let (m1, k1) = mode(16, 8, 1, 0, 0.3);
    let (m2, _) = mode(16, 8, 5, 2, -0.4);
    let (m3, k3) = mode(16, 8, 8, 4, 0.0);
    let (g1, g3) = (0.7 * k1, 0.7 * k3);
    // m1 splits over two DFT bins of amplitude c·N/2 each.
    let c1 = 2.0 * 16.0 * (-g1).exp() / n;
    let y: Vec<f64> = (0..128).map(|k| c1 * m1[k] + 1e-9 * m2[k] + m3[k]).collect();
    let want: Vec<f64> = (0..128).map(|k| c1 * g1.exp() * m1[k] + 1e-9 * m2[k] + (-g3).exp() * m3[k]).collect();
    let mut x = vec![0.0; 128];
    heat.local_inverse(&y, &[], &y, &mut x);
    assert!(max_diff(&x, &want) < 1e-12, "{}", max_diff(&x, &want));
}

#[test]
fn mean_matched_keeps_the_input_mean_and_passes_the_checks() {
    use diffsim::op::{Forward, MeanMatched};
    let net = MeanMatched(presets::mlp(&[6, 5, 6], Activation::Tanh).unwrap());
    let theta = net.0.init(&mut StdRng::seed_from_u64(4), Init::Glorot);
    let x = state(6, 7);
    let mut y = vec![0.0; 6];
    net.forward(&x, &theta, &mut y);
    let mean = |v: &[f64]| v.iter().sum::<f64>() / v.len() as f64;
    assert!((mean(&y) - mean(&x)).abs() < 1e-15);
    assert_passes("MeanMatched(mlp)", &net, &x, &theta);
}

/// Solves `a·x = b` (`n × n`, row-major) by Gaussian elimination with
/// partial pivoting.
fn solve(n: usize, mut a: Vec<f64>, mut b: Vec<f64>) -> Vec<f64> {
    for c in 0..n {
        let p = (c..n).max_by(|&i, &j| a[i * n + c].abs().total_cmp(&a[j * n + c].abs())).unwrap();
        for k in 0..n {
            a.swap(c * n + k, p * n + k);
        }
        b.swap(c, p);
        for r in c + 1..n {
            let f = a[r * n + c] / a[c * n + c];
            for k in c..n {
                a[r * n + k] -= f * a[c * n + k];
            }
            b[r] -= f * b[c];
        }
    }
    let mut x = vec![0.0; n];
    for r in (0..n).rev() {
        let s: f64 = (r + 1..n).map(|k| a[r * n + k] * x[k]).sum();
        x[r] = (b[r] - s) / a[r * n + r];
    }
    x
}

#[test]
fn gauss_newton_equals_the_damped_normal_equations_and_inverts_nonlinear_physics() {
    // Linear: the Jacobian of a 4 × 4 heat operator column by column, then
    // (JᵀJ + λI)·dx = Jᵀ·dy by elimination.
    let heat = Heat::new(4, 4, 0.3, 1e-3);
    let n = 16;
    let cols: Vec<Vec<f64>> = (0..n)
        .map(|c| {
            let mut e = vec![0.0; n];
            e[c] = 1.0;
            heat.eval(&e, &[])
        })
        .collect();
    let lambda = 1e-2;
    let dy = state(n, 9);
    let mut normal = vec![0.0; n * n];
    let mut rhs = vec![0.0; n];
    for i in 0..n {
        rhs[i] = (0..n).map(|r| cols[i][r] * dy[r]).sum();
        for j in 0..n {
            normal[i * n + j] = (0..n).map(|r| cols[i][r] * cols[j][r]).sum::<f64>() + if i == j { lambda } else { 0.0 };
        }
    }
    let direct = solve(n, normal, rhs);
    let gn = GaussNewton { op: &heat, damping: lambda, iterations: 200, tolerance: 1e-14 };
    let mut dx = vec![0.0; n];
    gn.local_inverse(&vec![0.0; n], &[], &dy, &mut dx);
    assert!(max_diff(&dx, &direct) < 1e-9 * direct.iter().map(|v| v.abs()).fold(0.0, f64::max), "{dx:?} vs {direct:?}");

    // Nonlinear: repeated Gauss-Newton steps find the start state of the
    // cubic oscillators that reaches a given end state.
    let osc = Oscillators { steps: 8, ..Oscillators::nonlinear() };
    let u = state(8, 11);
    let truth = vec![0.4, -0.2, 0.1, 0.3];
    let target = osc.eval(&truth, &u);
    let gn = GaussNewton { op: &osc, damping: 1e-10, iterations: 50, tolerance: 1e-14 };
    let mut x = vec![0.0; 4];
    for _ in 0..8 {
        let y = osc.eval(&x, &u);
        let dy: Vec<f64> = target.iter().zip(&y).map(|(t, a)| t - a).collect();
        let mut step = vec![0.0; 4];
        gn.local_inverse(&x, &u, &dy, &mut step);
        x.iter_mut().zip(&step).for_each(|(a, d)| *a += d);
    }
    assert!(max_diff(&x, &truth) < 1e-8, "{x:?} vs {truth:?}");
}

#[test]
fn sip_and_physics_gradients_match_finite_differences() {
    let heat = Heat::new(8, 8, 2.0, 1e-2);
    let net = presets::unet_2d(8, 8, 1, 1, 2, 3, Padding::Periodic, Activation::Tanh).unwrap();
    let theta = net.init(&mut StdRng::seed_from_u64(3), Init::He);
    let batch = samples(&heat, &mut StdRng::seed_from_u64(4), 3);
    let dir = state(theta.len(), 6);
    let along = |t: f64| -> Vec<f64> { theta.iter().zip(&dir).map(|(a, d)| a + t * d).collect() };
    let h = 1e-5;
    let dot = |g: &[f64]| g.iter().zip(&dir).map(|(a, b)| a * b).sum::<f64>();

    // Physics loss (1/B)·Σ ½‖P(N(y*)) − y*‖².
    let loss = |th: &[f64]| -> f64 {
        batch
            .iter()
            .map(|s| {
                let y = heat.eval(&net.eval(&s.observed, th), &[]);
                0.5 * y.iter().zip(&s.observed).map(|(a, b)| (a - b) * (a - b)).sum::<f64>()
            })
            .sum::<f64>()
            / 3.0
    };
    let (l, g) = physics_loss_and_gradient(&heat, &net, &theta, &batch).unwrap();
    assert!((l - loss(&theta)).abs() < 1e-12 * l);
    let fd = (loss(&along(h)) - loss(&along(-h))) / (2.0 * h);
    assert!((fd - dot(&g)).abs() < 1e-6 * fd.abs(), "physics: {fd} vs {}", dot(&g));

    // SIP: the proxy loss with the targets x̃ = x + P⁻¹(η·(y* − P(x))) frozen.
    let eta = 0.5;
    let targets: Vec<Vec<f64>> = batch
        .iter()
        .map(|s| {
            let x = net.eval(&s.observed, &theta);
            let y = heat.eval(&x, &[]);
            let dy: Vec<f64> = s.observed.iter().zip(&y).map(|(t, a)| eta * (t - a)).collect();
            let mut step = vec![0.0; x.len()];
            heat.local_inverse(&x, &[], &dy, &mut step);
            x.iter().zip(&step).map(|(a, d)| a + d).collect()
        })
        .collect();
    let proxy = |th: &[f64]| -> f64 {
        batch.iter().zip(&targets).map(|(s, t)| 0.5 * net.eval(&s.observed, th).iter().zip(t).map(|(a, b)| (a - b) * (a - b)).sum::<f64>()).sum::<f64>() / 3.0
    };
    let sip = sip_gradient(&heat, &net, &theta, &batch, eta).unwrap();
    assert!((sip.physics_loss - l).abs() < 1e-12 * l);
    assert!((sip.proxy_loss - proxy(&theta)).abs() < 1e-12 * sip.proxy_loss);
    let fd = (proxy(&along(h)) - proxy(&along(-h))) / (2.0 * h);
    assert!((fd - dot(&sip.grad)).abs() < 1e-6 * fd.abs(), "sip: {fd} vs {}", dot(&sip.grad));

    // A network that already inverts perfectly has zero error.
    let perfect: Vec<InverseSample> = batch.iter().map(|s| InverseSample { observed: s.truth.clone(), truth: s.truth.clone() }).collect();
    let identity = presets::mlp(&[64, 64], Activation::Tanh).unwrap();
    let mut eye = vec![0.0; 64 * 64 + 64];
    for i in 0..64 {
        eye[i * 64 + i] = 1.0;
    }
    assert!(state_error(&identity, &eye, &perfect) < 1e-14);
}

/// A smoke state of P2 on `n × n` cells after `warm` steps from 2 blobs:
/// smoke that moves, a velocity that is not zero.
fn moving_smoke(n: usize, warm: usize) -> (diffsim::problems::smoke::SmokeStep<2>, Vec<f64>) {
    use diffsim::op::Forward;
    use diffsim::problems::smoke::SmokeStep;
    use diffsim_solvers::smoke::{MacGrid, Preconditioner};
    let cfg = MacGrid::p2(n);
    let step = SmokeStep::new(cfg, 1e-12, 2000, Preconditioner::Mic0);
    let mut x = vec![0.0; cfg.n_state()];
    let s0 = diffsim_studies::smoke::blobs(&mut StdRng::seed_from_u64(3), n);
    x[..cfg.n_s()].copy_from_slice(&s0);
    for _ in 0..warm {
        let mut y = vec![0.0; x.len()];
        step.forward(&x, &[], &mut y);
        x = y;
    }
    (step, x)
}

/// A smooth smoke bump of height 1 and radius `r` cells around `(cx, cy)`.
fn bump(n: usize, cx: f64, cy: f64, r: f64) -> Vec<f64> {
    (0..n * n)
        .map(|c| {
            let (i, j) = ((c % n) as f64 + 0.5, (c / n) as f64 + 0.5);
            let d2 = ((i - cx).powi(2) + (j - cy).powi(2)) / (r * r);
            (-d2).exp()
        })
        .collect()
}

#[test]
fn smoke_step_reverse_time_inverse_keeps_its_promise() {
    use diffsim::check::{local_inverse, step_miss};
    use diffsim::op::Jvp;
    let n = 24;
    let (step, x) = moving_smoke(n, 12);
    // A reachable change: the step's tangent for more smoke in a smooth
    // bump inside the plume, the velocity left as it is.
    let s = &x[..n * n];
    let (ci, _) = s.iter().enumerate().fold((0, f64::MIN), |(bi, bv), (i, &v)| if v > bv { (i, v) } else { (bi, bv) });
    let mut tx = vec![0.0; x.len()];
    tx[..n * n].copy_from_slice(&bump(n, (ci % n) as f64 + 0.5, (ci / n) as f64 + 0.5, 3.0));
    let (mut y, mut dy) = (vec![0.0; x.len()], vec![0.0; x.len()]);
    step.jvp(&x, &[], &tx, &[], &mut y, &mut dy);
    let report = local_inverse(&step, &x, &[], &dy, &[1e-1, 1e-2, 1e-3], 0.25);
    assert!(report.verdict.passed(), "{report:?}");
    // It levels off at its own error (the step is smooth at these scales):
    // the small steps agree.
    let (e2, e3) = (report.steps[1].relative_error, report.steps[2].relative_error);
    assert!((e2 - e3).abs() < 0.2 * e3, "{report:?}");
    // Ignoring the motion misses by several times more.
    let small: Vec<f64> = dy.iter().map(|v| 1e-3 * v).collect();
    let unmoved = step_miss(&step, &x, &[], &small, &small);
    assert!(unmoved > 3.0 * e3, "reverse time {e3:.3}, unmoved {unmoved:.3}");
    // Defect correction (two sweeps) shrinks the miss further.
    let refined = diffsim::check::local_inverse_error(&diffsim::op::Refined { op: &step, sweeps: 2 }, &x, &[], &small);
    assert!(refined < 0.6 * e3, "reverse time {e3:.3}, refined {refined:.3}");
    assert!(diffsim::op::Forward::take_error(&step).is_none());
}

#[test]
fn smoke_rise_passes_the_checks_and_its_inverse_recovers_initial_smoke() {
    use diffsim::check::local_inverse_error;
    use diffsim::op::PerThread;
    use diffsim::problems::smoke::{SmokeRise, SmokeStep};
    use diffsim_solvers::smoke::{MacGrid, Preconditioner};
    use diffsim_studies::smoke::{SmokeParams, inverse_alone};
    // The gradient checks through 4 steps (tight solves: the finite
    // differences see the exact map).
    let rise = SmokeRise { step: SmokeStep::new(MacGrid::p2(8), 1e-13, 2000, Preconditioner::Mic0), steps: 4 };
    let x: Vec<f64> = state(64, 21).iter().map(|v| v.abs()).collect();
    assert_passes("SmokeRise", &rise, &x, &[]);

    // The whole rollout's reverse-time inverse: from the smoke one would
    // see without motion, its step lands far closer to the observation.
    let cfg = SmokeParams { n: 16, steps: 10, ..SmokeParams::quick() };
    let rise = SmokeRise::new(cfg.n, cfg.steps);
    let truth = diffsim_studies::smoke::blobs(&mut StdRng::seed_from_u64(8), cfg.n);
    let observed = rise.eval(&truth, &[]);
    let guess = observed.clone();
    let dy: Vec<f64> = observed.iter().zip(rise.eval(&guess, &[])).map(|(a, b)| a - b).collect();
    let e = local_inverse_error(&rise, &guess, &[], &dy);
    assert!(e < 0.7, "one reverse-time step from the unmoved guess misses by {e:.3}");

    // Iterated per sample without a network, the inverse recovers the
    // initial smoke better than "nothing moved" (x = y*, iteration 1).
    let errors = inverse_alone(&cfg, 6).unwrap();
    let (unmoved, last) = (errors[1].0, errors[6].0);
    assert!(last < 0.6 * unmoved, "initial-smoke MAE: unmoved {unmoved:.4}, after 6 inverse steps {last:.4}: {errors:?}");
    assert!(errors[6].1 < 0.5 * errors[1].1, "re-simulated MAE: {errors:?}");

    // A solve that fails is an error of the batch, not a silent result.
    let physics = PerThread::new(|| SmokeRise { step: SmokeStep::new(MacGrid::p2(8), 1e-12, 1, Preconditioner::None), steps: 3 });
    let net = presets::mlp(&[64, 64], Activation::Tanh).unwrap();
    let theta = net.init(&mut StdRng::seed_from_u64(1), Init::Glorot);
    let batch = vec![InverseSample { observed: vec![0.5; 64], truth: vec![0.5; 64] }];
    let err = physics_loss_and_gradient(&physics, &net, &theta, &batch).unwrap_err();
    assert!(err.to_string().contains("did not converge"), "{err}");
    let err = sip_gradient(&physics, &net, &theta, &batch, 1.0).unwrap_err();
    assert!(err.to_string().contains("did not converge"), "{err}");
}
