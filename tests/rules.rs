//! `train::rule`: every update rule behind the one trait, each against an
//! independent computation — the exact least-squares solution, a known
//! conductivity field recovered through a rollout, and the HIG and SIP
//! steps of the functions the studies were built on.

use diffsim::nn::{Activation, Init, Padding, presets};
use diffsim::op::Operator;
use diffsim::problems::heat::Heat;
use diffsim::problems::oscillators::Oscillators;
use diffsim::rollout::{AtSteps, Checkpointing, Rollout};
use diffsim::train::hig::{ControlSample, Hig, hig_step};
use diffsim::train::pg::sip_gradient;
use diffsim::train::{
    Adam, AdamParams, ControlBatch, FnObjective, InverseBatch, Lbfgs, LbfgsParams, Objective, Optimizer, Sgd, SgdParams, Sip, TrainError, UpdateRule,
};
use diffsim_studies::heat::samples;
use rand::SeedableRng;
use rand::rngs::StdRng;

use crate::checks::state;

/// `½‖Aθ − b‖²` for a fixed 6 × 4 matrix and its gradient.
fn least_squares() -> (Vec<f64>, Vec<f64>) {
    let a: Vec<f64> = (0..24).map(|k| ((k * 7 % 11) as f64 - 5.0) / 3.0 + if k % 5 == 0 { 2.0 } else { 0.0 }).collect();
    let b: Vec<f64> = (0..6).map(|i| (i as f64 * 0.9).sin()).collect();
    (a, b)
}

fn ls_objective(a: &[f64], b: &[f64]) -> impl Objective {
    let (a, b) = (a.to_vec(), b.to_vec());
    FnObjective {
        n: 4,
        f: move |th: &[f64]| -> Result<(f64, Vec<f64>), TrainError> {
            let r: Vec<f64> = (0..6).map(|i| (0..4).map(|j| a[i * 4 + j] * th[j]).sum::<f64>() - b[i]).collect();
            let g = (0..4).map(|j| (0..6).map(|i| a[i * 4 + j] * r[i]).sum()).collect();
            Ok((0.5 * r.iter().map(|v| v * v).sum::<f64>(), g))
        },
    }
}

/// The least-squares solution by the normal equations, solved here by
/// Gaussian elimination (independent of every rule).
fn normal_equations(a: &[f64], b: &[f64]) -> Vec<f64> {
    let mut m = vec![vec![0.0; 5]; 4];
    for (j, row) in m.iter_mut().enumerate() {
        for k in 0..4 {
            row[k] = (0..6).map(|i| a[i * 4 + j] * a[i * 4 + k]).sum();
        }
        row[4] = (0..6).map(|i| a[i * 4 + j] * b[i]).sum();
    }
    for c in 0..4 {
        let p = (c..4).max_by(|&x, &y| m[x][c].abs().total_cmp(&m[y][c].abs())).unwrap();
        m.swap(c, p);
        for r in 0..4 {
            if r != c {
                let f = m[r][c] / m[c][c];
                for k in c..5 {
                    m[r][k] -= f * m[c][k];
                }
            }
        }
    }
    (0..4).map(|j| m[j][4] / m[j][j]).collect()
}

#[test]
fn every_gradient_rule_solves_least_squares() {
    let (a, b) = least_squares();
    let exact = normal_equations(&a, &b);
    let error = |th: &[f64]| th.iter().zip(&exact).map(|(x, y)| (x - y).abs()).fold(0.0, f64::max);
    // (One call per rule: an array of tuples by value aborts Enzyme's type
    // analysis in this flagged test crate; docs/pitfalls.md.)
    let solve = |rule: &mut dyn UpdateRule, steps: usize, tolerance: f64| {
        let mut theta = vec![0.0; 4];
        let mut objective = ls_objective(&a, &b);
        let first = objective.loss_and_gradient(&theta).unwrap().0;
        let mut last = first;
        for _ in 0..steps {
            last = rule.step(&mut objective, &mut theta).unwrap();
        }
        assert!(last < first, "{}: {first} → {last}", rule.name());
        assert!(error(&theta) < tolerance, "{}: θ {theta:?} against {exact:?}", rule.name());
    };
    solve(&mut Sgd::new(SgdParams { lr: 0.01, momentum: 0.9 }), 3000, 1e-6);
    // Adam at a constant rate ends in a neighbourhood of the minimum of
    // the rate's size (here about 1e-3, from 0.43 at the start).
    solve(&mut Adam::new(AdamParams { lr: 0.05, ..AdamParams::default() }), 3000, 5e-3);
    solve(&mut Optimizer::adam(0.05), 3000, 5e-3);
    solve(&mut Lbfgs::new(LbfgsParams::default()).unwrap(), 30, 1e-8);
}

/// One explicit step of 1D diffusion with a conductivity per cell,
/// `κ_i = exp(θ_i)` (the parameters), zero values beyond both ends:
/// `y_i = x_i + c·(κ_{i+½}(x_{i+1} − x_i) − κ_{i−½}(x_i − x_{i−1}))`,
/// `κ_{i+½}` the mean of the two cells' `κ`.
struct Conduction {
    n: usize,
    c: f64,
}

impl Operator for Conduction {
    fn n_in(&self) -> usize {
        self.n
    }
    fn n_out(&self) -> usize {
        self.n
    }
    fn n_params(&self) -> usize {
        self.n
    }
}

fn conduction(op: &Conduction, x: &[f64], p: &[f64], y: &mut [f64]) {
    let n = op.n;
    for i in 0..n {
        let k = p[i].exp();
        let (kl, xl) = if i == 0 { (k, 0.0) } else { (0.5 * (k + p[i - 1].exp()), x[i - 1]) };
        let (kr, xr) = if i == n - 1 { (k, 0.0) } else { (0.5 * (k + p[i + 1].exp()), x[i + 1]) };
        y[i] = x[i] + op.c * (kr * (xr - x[i]) - kl * (x[i] - xl));
    }
}

diffsim::differentiable!(Conduction => conduction);

#[test]
fn the_conduction_step_passes_the_three_checks() {
    // Enzyme's VJP and JVP of the step (state and conductivities) against
    // finite differences, the Taylor remainder and each other.
    let op = Conduction { n: 9, c: 0.2 };
    let x: Vec<f64> = (0..9).map(|i| (0.9 * i as f64).sin()).collect();
    let theta: Vec<f64> = (0..9).map(|i| 0.3 * (0.4 * i as f64).cos()).collect();
    let report = diffsim::check::check_all(&op, &x, &theta, &diffsim::check::CheckParams::default());
    assert!(report.passed(), "{report}");
}

#[test]
fn lbfgs_recovers_a_conductivity_field_through_a_rollout_where_adam_does_not() {
    // The issue's user's setting in 1D: recover θ (κ = e^θ per cell) from
    // the states of 20 explicit steps. Observations from the true field,
    // the same number of gradient evaluations for both rules.
    let (n, steps) = (24, 20);
    let op = Conduction { n, c: 0.2 };
    let truth: Vec<f64> = (0..n).map(|i| 0.5 * (0.4 * i as f64).sin()).collect();
    let x0: Vec<f64> = (0..n).map(|i| (0.9 * i as f64).sin() + 0.5 * (2.3 * i as f64).cos()).collect();
    let observed: Vec<Vec<f64>> = {
        let (mut x, mut y, mut all) = (x0.clone(), vec![0.0; n], vec![]);
        for _ in 0..steps {
            conduction(&op, &x, &truth, &mut y);
            std::mem::swap(&mut x, &mut y);
            all.push(x.clone());
        }
        all
    };
    let loss = AtSteps {
        steps: (1..=steps).collect(),
        f: |t: usize, x: &[f64], g: &mut [f64]| {
            let mut l = 0.0;
            for i in 0..x.len() {
                g[i] = x[i] - observed[t - 1][i];
                l += 0.5 * g[i] * g[i];
            }
            l
        },
    };
    let evaluations = std::cell::Cell::new(0);
    let objective = || FnObjective {
        n,
        f: |th: &[f64]| {
            evaluations.set(evaluations.get() + 1);
            let g = Rollout::new(&op, th, steps)?.value_and_grad(&x0, &loss, Checkpointing::Store)?;
            Ok((g.loss, g.dp))
        },
    };
    let error = |th: &[f64]| th.iter().zip(&truth).map(|(a, b)| (a - b).abs()).fold(0.0, f64::max);
    let budget = 150;
    let mut lbfgs = Lbfgs::new(LbfgsParams::default()).unwrap();
    let mut theta = vec![0.0; n];
    let mut obj = objective();
    while evaluations.get() < budget {
        if lbfgs.step(&mut obj, &mut theta).is_err() {
            break; // converged to round-off: the line search finds no decrease
        }
    }
    let lbfgs_error = error(&theta);
    evaluations.set(0);
    let mut best_adam = f64::INFINITY;
    for lr in [0.3, 0.1, 0.03] {
        let mut adam = Adam::new(AdamParams { lr, ..AdamParams::default() });
        let mut theta = vec![0.0; n];
        let mut obj = objective();
        for _ in 0..budget {
            adam.step(&mut obj, &mut theta).unwrap();
        }
        best_adam = best_adam.min(error(&theta));
    }
    assert!(lbfgs_error < 1e-4, "L-BFGS: max |θ − θ*| = {lbfgs_error:e}");
    assert!(best_adam > 10.0 * lbfgs_error, "Adam's best {best_adam:e} against L-BFGS {lbfgs_error:e}");
}

#[test]
fn hig_and_gauss_newton_as_rules_take_the_studies_steps_bit_for_bit() {
    let physics = Oscillators { steps: 6, ..Oscillators::linear() };
    let net = presets::mlp(&[4, 8, 6], Activation::Tanh).unwrap();
    let theta0 = net.init(&mut StdRng::seed_from_u64(2), Init::Glorot);
    let data: Vec<ControlSample> = (0..8)
        .map(|k| {
            let s: Vec<f64> = state(4, 40 + k).iter().map(|v| v.abs()).collect();
            ControlSample { x0: s.clone(), target: s }
        })
        .collect();
    let same_steps = |mut rule: Hig| {
        let (mut by_rule, mut by_function) = (theta0.clone(), theta0.clone());
        let mut objective = ControlBatch::new(&physics, &net, &data);
        for _ in 0..3 {
            let a = rule.step(&mut objective, &mut by_rule).unwrap();
            let b = hig_step(&physics, &net, &mut by_function, &data, &rule).unwrap();
            assert_eq!(a, b, "{}", rule.name());
        }
        assert_eq!(by_rule, by_function, "{}", rule.name());
        assert_ne!(by_rule, theta0);
    };
    same_steps(Hig { memory_budget: 1 << 20, ..Hig::half_inverse(1.0, 1e-10) });
    same_steps(Hig::gauss_newton(0.5, 1e-10));
    // A closure objective has no Jacobian: HIG says what it needs.
    let (a, b) = least_squares();
    let e = Hig::half_inverse(1.0, 1e-10).step(&mut ls_objective(&a, &b), &mut [0.0; 4]).unwrap_err();
    assert!(matches!(e, TrainError::Unsupported { .. }) && e.to_string().contains("Jacobian"), "{e}");
}

#[test]
fn sip_as_a_rule_is_adam_on_the_proxy_gradient() {
    let heat = Heat::new(8, 8, 2.0, 1e-2);
    let net = presets::unet_2d(8, 8, 1, 1, 2, 3, Padding::Periodic, Activation::Tanh).unwrap();
    let theta0 = net.init(&mut StdRng::seed_from_u64(3), Init::He);
    let batch = samples(&heat, &mut StdRng::seed_from_u64(4), 3);
    let mut rule = Sip::new(0.5, AdamParams { lr: 1e-3, ..AdamParams::default() });
    let mut adam = Adam::new(AdamParams { lr: 1e-3, ..AdamParams::default() });
    let (mut by_rule, mut by_hand) = (theta0.clone(), theta0.clone());
    let mut objective = InverseBatch::new(&heat, &net, &batch[..]);
    for _ in 0..3 {
        let loss = rule.step(&mut objective, &mut by_rule).unwrap();
        let s = sip_gradient(&heat, &net, &by_hand, &batch, 0.5).unwrap();
        adam.update(&mut by_hand, &s.grad);
        assert_eq!(loss, s.physics_loss);
    }
    assert_eq!(by_rule, by_hand);
    // The same objective trains with plain gradients too.
    let first = Adam::new(AdamParams::default()).step(&mut objective, &mut by_rule.clone()).unwrap();
    assert!(first.is_finite());
}

#[test]
fn a_non_finite_loss_stops_a_rule_and_leaves_the_parameters() {
    let mut nan = FnObjective { n: 2, f: |_: &[f64]| Ok((f64::NAN, vec![0.0, 0.0])) };
    let mut theta = vec![1.0, 2.0];
    for rule in
        [&mut Sgd::new(SgdParams::default()) as &mut dyn UpdateRule, &mut Adam::new(AdamParams::default()), &mut Lbfgs::new(LbfgsParams::default()).unwrap()]
    {
        let e = rule.step(&mut nan, &mut theta).unwrap_err();
        assert!(e.to_string().contains("not finite"), "{}: {e}", rule.name());
        assert_eq!(theta, [1.0, 2.0], "{}", rule.name());
    }
    // The objective's own error reaches the caller whole.
    let mut failing = FnObjective { n: 2, f: |_: &[f64]| Err(TrainError::Objective("the solve did not converge".into())) };
    let e = Lbfgs::new(LbfgsParams::default()).unwrap().step(&mut failing, &mut theta).unwrap_err();
    assert_eq!(e, TrainError::Objective("the solve did not converge".into()));
    // The checkpoint format of the optimizer is unchanged by the types.
    let saved = r#"{"adam":{"lr":0.001,"beta1":0.9,"beta2":0.999,"eps":1e-8,"m":[0.5],"v":[0.25],"t":1}}"#;
    let o: Optimizer = serde_json::from_str(saved).unwrap();
    assert_eq!(o.state(), vec![0.001, 0.9, 0.999, 1e-8, 1.0, 0.5, 0.25]);
    assert_eq!(serde_json::to_string(&o).unwrap(), saved);
}
