//! Your own solver step, differentiated by Enzyme and checked by diffsim.
#![feature(autodiff)]

use diffsim::check::{CheckOptions, check_all};
use diffsim::op::{Operator, OperatorExt};

/// A damped, driven chain of masses: state `x = [positions; velocities]`,
/// parameters `p = [stiffness, damping]`, one symplectic Euler step.
struct Chain {
    masses: usize,
    dt: f64,
}

impl Operator for Chain {
    fn n_in(&self) -> usize {
        2 * self.masses
    }
    fn n_out(&self) -> usize {
        2 * self.masses
    }
    fn n_params(&self) -> usize {
        2
    }
}

/// A plain function on slices: no framework types inside.
fn chain_step(op: &Chain, x: &[f64], p: &[f64], y: &mut [f64]) {
    let m = op.masses;
    let (k, c) = (p[0], p[1]);
    for i in 0..m {
        let left = if i > 0 { x[i - 1] } else { 0.0 };
        let right = if i + 1 < m { x[i + 1] } else { 0.0 };
        let force = k * (left - 2.0 * x[i] + right) - c * x[m + i] - 0.1 * x[i] * x[i] * x[i];
        y[m + i] = x[m + i] + op.dt * force;
        y[i] = x[i] + op.dt * y[m + i];
    }
}

diffsim::differentiable!(Chain => chain_step);

fn main() {
    let op = Chain { masses: 6, dt: 0.05 };
    let x: Vec<f64> = (0..12).map(|i| (0.9 * i as f64).sin()).collect();
    let p = [2.0, 0.3];
    let (dx, dp) = op.vjp_new(&x, &p, &vec![1.0; 12]);
    println!("∂Σy/∂x[0] = {:.6}, ∂Σy/∂p = {:?}", dx[0], dp);
    let report = check_all(&op, &x, &p, &CheckOptions::default());
    println!("{report}");
    if !report.passed() {
        eprintln!("gradient checks failed");
        std::process::exit(1);
    }
}
