//! Checks through whole rollouts with respect to the initial state, the
//! parameters or both (`RolloutLoss`), on a user-style operator with
//! parameters (a damped wave equation written here, not a shipped solver),
//! with loss terms at several steps; a wrong parameter adjoint is caught.

use diffsim::check::{CheckParams, Verdict, check_all, taylor};
use diffsim::op::{Forward, Jvp, Operator, OperatorExt, Vjp};
use diffsim::rollout::{AtSteps, Checkpointing, Rollout, RolloutLoss, Wrt};

/// A damped wave on a periodic line: state `[u; v]`, parameters
/// `p = [c², γ]`, one symplectic Euler step of `u_tt = c²·u_xx − γ·u_t`.
struct Wave {
    n: usize,
    dt: f64,
    dx: f64,
}

impl Operator for Wave {
    fn n_in(&self) -> usize {
        2 * self.n
    }
    fn n_out(&self) -> usize {
        2 * self.n
    }
    fn n_params(&self) -> usize {
        2
    }
}

fn wave_step(op: &Wave, x: &[f64], p: &[f64], y: &mut [f64]) {
    let n = op.n;
    let (u, v) = x.split_at(n);
    let k = op.dt / (op.dx * op.dx);
    for i in 0..n {
        let lap = u[(i + 1) % n] - 2.0 * u[i] + u[(i + n - 1) % n];
        let vn = v[i] + k * p[0] * lap - op.dt * p[1] * v[i];
        y[n + i] = vn;
        y[i] = u[i] + op.dt * vn;
    }
}

diffsim::differentiable!(Wave => wave_step);

fn wave() -> (Wave, Vec<f64>) {
    let op = Wave { n: 12, dt: 0.05, dx: 0.25 };
    let x0: Vec<f64> = (0..24).map(|i| if i < 12 { (0.6 * i as f64).sin() } else { 0.1 * (0.3 * i as f64).cos() }).collect();
    (op, x0)
}

/// `Σ_t ½‖u_t − target‖²` over the listed steps (velocities not in the loss).
fn misfit(steps: Vec<usize>) -> AtSteps<impl Fn(usize, &[f64], &mut [f64]) -> f64> {
    AtSteps {
        steps,
        f: |t: usize, x: &[f64], g: &mut [f64]| -> f64 {
            let n = x.len() / 2;
            let mut value = 0.0;
            g.fill(0.0);
            for i in 0..n {
                let d = x[i] - 0.3 * (0.05 * t as f64 + 0.4 * i as f64).cos();
                value += 0.5 * d * d;
                g[i] = d;
            }
            value
        },
    }
}

fn passes<O: Vjp + Jvp>(what: &str, op: &O, x: &[f64], p: &[f64]) {
    let report = check_all(op, x, p, &CheckParams::default());
    assert!(report.passed(), "{what}:\n{report}");
}

#[test]
fn loss_through_a_rollout_passes_the_checks_for_x0_p_and_both() {
    let (op, x0) = wave();
    let p = [1.3, 0.4];
    let loss = misfit(vec![7, 19, 40]);
    for mode in [Checkpointing::Store, Checkpointing::Periodic { every: 6 }, Checkpointing::Binomial { snapshots: 3 }] {
        for wrt in [Wrt::X0, Wrt::P, Wrt::Both] {
            let as_op = RolloutLoss::new(Rollout::new(&op, &p, 40).unwrap(), &x0, &loss, mode, wrt).unwrap();
            let (x, pp) = as_op.point();
            assert_eq!((x.len(), pp.len()), (if wrt == Wrt::P { 0 } else { 24 }, if wrt == Wrt::X0 { 0 } else { 2 }));
            passes(&format!("{wrt:?}, {mode}"), &as_op, x, pp);
        }
    }
}

#[test]
fn parameter_gradient_through_a_rollout_matches_central_differences_written_here() {
    // An independent computation: the loss evaluated by a plain loop over
    // the forward step, differenced by hand.
    let (op, x0) = wave();
    let loss = misfit(vec![5, 30]);
    let value = |p: &[f64]| -> f64 {
        let (mut x, mut y, mut g) = (x0.clone(), vec![0.0; 24], vec![0.0; 24]);
        let mut l = 0.0;
        for t in 1..=30 {
            op.forward(&x, p, &mut y);
            std::mem::swap(&mut x, &mut y);
            if [5, 30].contains(&t) {
                l += (loss.f)(t, &x, &mut g);
            }
        }
        l
    };
    let p = [0.9, 0.25];
    let g = Rollout::new(&op, &p, 30).unwrap().value_and_grad(&x0, &loss, Checkpointing::periodic_sqrt(30)).unwrap();
    assert!((g.loss - value(&p)).abs() <= 1e-13 * g.loss.abs());
    for j in 0..2 {
        let h = 1e-6;
        let (mut a, mut b) = (p, p);
        a[j] += h;
        b[j] -= h;
        let fd = (value(&a) - value(&b)) / (2.0 * h);
        assert!((fd - g.dp[j]).abs() <= 1e-7 * fd.abs().max(1.0), "p[{j}]: rollout {} vs central differences {fd}", g.dp[j]);
    }
}

#[test]
fn per_step_parameters_are_checked_through_the_rollout() {
    let (op, x0) = wave();
    let steps = 9;
    let p: Vec<f64> = (0..steps).flat_map(|t| [1.0 + 0.05 * t as f64, 0.3]).collect();
    let loss = misfit(vec![4, 9]);
    let as_op = RolloutLoss::new(Rollout::per_step(&op, &p, steps).unwrap(), &x0, &loss, Checkpointing::Store, Wrt::Both).unwrap();
    let (x, pp) = as_op.point();
    assert_eq!(pp.len(), 2 * steps);
    passes("per-step parameters", &as_op, x, pp);
}

/// `y = a·x` with a hand VJP whose parameter part is off by a factor ½.
struct WrongParamAdjoint;

impl Operator for WrongParamAdjoint {
    fn n_in(&self) -> usize {
        3
    }
    fn n_out(&self) -> usize {
        3
    }
    fn n_params(&self) -> usize {
        1
    }
}

impl Forward for WrongParamAdjoint {
    fn forward(&self, x: &[f64], p: &[f64], y: &mut [f64]) {
        y.iter_mut().zip(x).for_each(|(y, x)| *y = p[0] * x);
    }
}

impl Vjp for WrongParamAdjoint {
    fn vjp(&self, x: &[f64], p: &[f64], dy: &mut [f64], dx: &mut [f64], dp: &mut [f64]) {
        for i in 0..3 {
            dx[i] += p[0] * dy[i];
            dp[0] += 0.5 * x[i] * dy[i]; // wrong: should be x[i]·dy[i]
        }
        dy.fill(0.0);
    }
}

impl Jvp for WrongParamAdjoint {
    fn jvp(&self, x: &[f64], p: &[f64], tx: &[f64], tp: &[f64], y: &mut [f64], ty: &mut [f64]) {
        for i in 0..3 {
            y[i] = p[0] * x[i];
            ty[i] = p[0] * tx[i] + tp[0] * x[i];
        }
    }
}

#[test]
fn a_wrong_parameter_adjoint_is_caught_through_the_rollout_and_only_there() {
    let x0 = [0.5, -1.0, 2.0];
    let p = [0.9];
    let loss = |x: &[f64], g: &mut [f64]| -> f64 {
        g.copy_from_slice(x);
        0.5 * x.iter().map(|v| v * v).sum::<f64>()
    };
    let rollout = Rollout::new(&WrongParamAdjoint, &p, 6).unwrap();
    let wrt_x0 = RolloutLoss::new(rollout, &x0, &loss, Checkpointing::Store, Wrt::X0).unwrap();
    let (x, pp) = wrt_x0.point();
    passes("x0 only (the state adjoint is right)", &wrt_x0, x, pp);
    for wrt in [Wrt::P, Wrt::Both] {
        let as_op = RolloutLoss::new(rollout, &x0, &loss, Checkpointing::Store, wrt).unwrap();
        let (x, pp) = as_op.point();
        let r = check_all(&as_op, x, pp, &CheckParams::default());
        assert!(matches!(r.fd.verdict, Verdict::Fail(_)), "{wrt:?}: finite differences missed it:\n{r}");
        assert!(matches!(r.taylor.verdict, Verdict::Fail(_)), "{wrt:?}: Taylor missed it:\n{r}");
        assert!(matches!(r.dot.verdict, Verdict::Fail(_)), "{wrt:?}: the dot product missed it:\n{r}");
        assert!(r.fd.worst.starts_with("p["), "{wrt:?}: {}", r.fd.worst);
    }
}

#[test]
fn wrong_lengths_name_the_callers_line() {
    use std::sync::Mutex;
    static WHERE: Mutex<Option<String>> = Mutex::new(None);
    let me = std::thread::current().id();
    let previous = std::panic::take_hook();
    std::panic::set_hook(Box::new(move |info| {
        if std::thread::current().id() == me {
            *WHERE.lock().unwrap() = info.location().map(|l| l.file().to_string());
        }
    }));
    let (op, x0) = wave();
    let short_seed = std::panic::catch_unwind(|| op.vjp_new(&x0, &[1.0, 0.1], &[1.0; 3]));
    let vjp_site = WHERE.lock().unwrap().take();
    let short_x = std::panic::catch_unwind(|| check_all(&op, &x0[..5], &[1.0, 0.1], &CheckParams::default()));
    let check_site = WHERE.lock().unwrap().take();
    std::panic::set_hook(previous);
    assert!(short_seed.is_err() && short_x.is_err());
    assert_eq!(vjp_site.as_deref(), Some(file!()), "vjp_new's panic should point at this file");
    assert_eq!(check_site.as_deref(), Some(file!()), "check_all's panic should point at this file");
}

/// `y = A·x + B·p`: linear, so the Taylor remainder is at round-off.
struct Linear;

impl Operator for Linear {
    fn n_in(&self) -> usize {
        2
    }
    fn n_out(&self) -> usize {
        2
    }
    fn n_params(&self) -> usize {
        1
    }
}

fn linear(_: &Linear, x: &[f64], p: &[f64], y: &mut [f64]) {
    y[0] = 2.0 * x[0] - x[1] + p[0];
    y[1] = 0.5 * x[1] - 3.0 * p[0];
}

diffsim::differentiable!(Linear => linear);

#[test]
fn taylor_says_when_the_remainder_is_at_round_off() {
    let r = taylor(&Linear, &[0.3, -0.7], &[1.1], &CheckParams::default());
    assert!(r.verdict.passed(), "{r}");
    let note = r.note.as_deref().unwrap_or("");
    assert!(note.contains("round-off") && note.contains("linear"), "{r}");
    assert!(r.to_string().contains("(round-off)"), "{r}");
}
