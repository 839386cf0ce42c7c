//! Steady states written as a map (`fixed_point_system!`): the fixed point
//! and its derivatives against an independent computation (Newton's method
//! on the residual `y − G(y)` with a direct solve), the three checks alone
//! and through a rollout, and a map without a fixed point is an error, not
//! a number.

use diffsim::check::{CheckParams, check_all};
use diffsim::implicit::{FixedPoint, FixedPointParams, FixedPointSystem, NewtonParams, NonlinearSolve, NonlinearSystem};
use diffsim::op::{Forward, Jvp, OperatorExt, Vjp};
use diffsim::rollout::{AtSteps, Checkpointing, Rollout, RolloutLoss, Wrt};

/// A relaxation on a periodic line, `G(y)_i = a·tanh((y_{i−1} + y_{i+1})/2)
/// + b·x_i`, `p = [a, b]`: a contraction for `|a| < 1`.
struct Relax {
    n: usize,
}

impl FixedPointSystem for Relax {
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

fn relax(s: &Relax, y: &[f64], x: &[f64], p: &[f64], out: &mut [f64]) {
    let n = s.n;
    for i in 0..n {
        let (l, r) = (y[(i + n - 1) % n], y[(i + 1) % n]);
        out[i] = p[0] * (0.5 * (l + r)).tanh() + p[1] * x[i];
    }
}

diffsim::fixed_point_system!(Relax => relax);

/// The same equations as a residual, `F(y) = y − G(y)`, for Newton.
struct RelaxResidual {
    n: usize,
}

impl NonlinearSystem for RelaxResidual {
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

fn relax_residual(s: &RelaxResidual, y: &[f64], x: &[f64], p: &[f64], r: &mut [f64]) {
    let n = s.n;
    for i in 0..n {
        let (l, rr) = (y[(i + n - 1) % n], y[(i + 1) % n]);
        r[i] = y[i] - p[0] * (0.5 * (l + rr)).tanh() - p[1] * x[i];
    }
}

diffsim::nonlinear_system!(RelaxResidual => relax_residual);

fn field(n: usize, a: f64) -> Vec<f64> {
    (0..n).map(|i| a * (0.9 * i as f64 + 0.3).sin()).collect()
}

#[test]
fn the_fixed_point_and_its_derivatives_equal_newton_s() {
    let n = 7;
    let op = FixedPoint::new(Relax { n }, FixedPointParams { tolerance: 1e-14, ..FixedPointParams::default() });
    let newton = NonlinearSolve::new(RelaxResidual { n }, NewtonParams { tolerance: 1e-14, ..NewtonParams::default() });
    let (x, p) = (field(n, 1.0), [0.8, 0.6]);
    let (y, y_newton) = (op.eval(&x, &p), newton.eval(&x, &p));
    for i in 0..n {
        assert!((y[i] - y_newton[i]).abs() < 1e-12, "y[{i}]: {} against Newton's {}", y[i], y_newton[i]);
    }
    // The VJP and the JVP by the fixed-point iterations against Newton's
    // implicit function theorem (a direct solve with the Jacobian).
    let w = field(n, 0.7);
    let (mut dx, mut dp) = (vec![0.0; n], vec![0.0; 2]);
    op.vjp(&x, &p, &mut w.clone(), &mut dx, &mut dp);
    let (mut dx_n, mut dp_n) = (vec![0.0; n], vec![0.0; 2]);
    newton.vjp(&x, &p, &mut w.clone(), &mut dx_n, &mut dp_n);
    for (a, b) in dx.iter().chain(&dp).zip(dx_n.iter().chain(&dp_n)) {
        assert!((a - b).abs() < 1e-11 * (1.0 + b.abs()), "VJP {a} against Newton's {b}");
    }
    let (tx, tp) = (field(n, -0.4), [0.3, -0.2]);
    let (mut y1, mut ty) = (vec![0.0; n], vec![0.0; n]);
    op.jvp(&x, &p, &tx, &tp, &mut y1, &mut ty);
    let (mut y2, mut ty_n) = (vec![0.0; n], vec![0.0; n]);
    newton.jvp(&x, &p, &tx, &tp, &mut y2, &mut ty_n);
    for (a, b) in ty.iter().zip(&ty_n) {
        assert!((a - b).abs() < 1e-11 * (1.0 + b.abs()), "JVP {a} against Newton's {b}");
    }
    assert!(op.info.forward.load(std::sync::atomic::Ordering::Relaxed) > 0);
}

#[test]
fn a_fixed_point_passes_the_checks_alone_and_through_a_rollout() {
    let n = 6;
    let op = FixedPoint::new(Relax { n }, FixedPointParams { relaxation: 0.8, ..FixedPointParams::default() });
    let (x, p) = (field(n, 1.0), [0.7, 0.9]);
    let r = check_all(&op, &x, &p, &CheckParams::default());
    assert!(r.passed(), "{r}");
    // Six steady states in a row, the loss on the last: for x0 and p.
    let loss = AtSteps {
        steps: vec![6],
        f: |_t: usize, s: &[f64], g: &mut [f64]| -> f64 {
            g.copy_from_slice(s);
            0.5 * s.iter().map(|v| v * v).sum::<f64>()
        },
    };
    let as_op = RolloutLoss::new(Rollout::new(&op, &p, 6).unwrap(), &x, &loss, Checkpointing::Store, Wrt::Both).unwrap();
    let (x0, p0) = as_op.point();
    let r = check_all(&as_op, x0, p0, &CheckParams::default());
    assert!(r.passed(), "{r}");
}

/// `G(y) = 2·y + 1`: its fixed point −1 repels the iteration.
struct Doubling;

impl FixedPointSystem for Doubling {
    fn n(&self) -> usize {
        1
    }
    fn n_in(&self) -> usize {
        1
    }
}

fn doubling(_: &Doubling, y: &[f64], _x: &[f64], _p: &[f64], out: &mut [f64]) {
    out[0] = 2.0 * y[0] + 1.0;
}

diffsim::fixed_point_system!(Doubling => doubling);

#[test]
fn a_map_that_does_not_contract_is_an_error_and_leaves_no_number() {
    let op = FixedPoint::new(Doubling, FixedPointParams { max_iterations: 200, ..FixedPointParams::default() });
    let mut y = [0.0];
    op.forward(&[0.0], &[], &mut y);
    assert!(y[0].is_nan(), "{y:?}");
    let e = op.take_error().expect("an error").to_string();
    assert!(e.contains("did not converge"), "{e}");
    // Through a rollout: the error, with the step.
    let e = Rollout::new(&op, &[], 3).unwrap().final_state(&[0.0]).unwrap_err().to_string();
    assert!(e.contains("did not converge"), "{e}");
}

#[test]
#[should_panic(expected = "relaxation in (0, 1]")]
fn a_relaxation_above_one_is_refused() {
    FixedPoint::new(Relax { n: 2 }, FixedPointParams { relaxation: 1.5, ..FixedPointParams::default() });
}
