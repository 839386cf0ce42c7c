//! A user's own plain function made differentiable with the macro, as the
//! README shows it: the three checks, parameters included, and validation
//! before the generated code.

use diffsim::check::{CheckOptions, check_all};
use diffsim::op::{Operator, OperatorExt};

/// A reaction–diffusion step with parameters `p = [ν, k]` on a periodic
/// grid: `y_i = x_i + ν·(x_{i+1} − 2x_i + x_{i−1}) − k·x_i³`.
pub struct ReactionDiffusion {
    pub n: usize,
}

impl Operator for ReactionDiffusion {
    fn n_in(&self) -> usize {
        self.n
    }
    fn n_out(&self) -> usize {
        self.n
    }
    fn n_params(&self) -> usize {
        2
    }
}

fn reaction_diffusion(op: &ReactionDiffusion, x: &[f64], p: &[f64], y: &mut [f64]) {
    let n = op.n;
    for i in 0..n {
        let (l, r) = (x[(i + n - 1) % n], x[(i + 1) % n]);
        y[i] = x[i] + p[0] * (r - 2.0 * x[i] + l) - p[1] * x[i] * x[i] * x[i];
    }
}

diffsim::differentiable!(ReactionDiffusion => reaction_diffusion);

#[test]
fn user_operator_with_parameters_passes_all_checks() {
    for n in [4, 13] {
        let op = ReactionDiffusion { n };
        let x: Vec<f64> = (0..n).map(|i| (0.7 * i as f64).sin()).collect();
        let report = check_all(&op, &x, &[0.2, 0.5], &CheckOptions::default());
        assert!(report.passed(), "n = {n}:\n{report}");
    }
}

#[test]
fn parameter_gradient_matches_closed_form() {
    let op = ReactionDiffusion { n: 5 };
    let x = [0.1, -0.4, 0.9, 0.3, -0.2];
    let w = [1.0, 2.0, -1.0, 0.5, 0.25];
    let (_, dp) = op.vjp_new(&x, &[0.2, 0.5], &w);
    let lap = |i: usize| x[(i + 1) % 5] - 2.0 * x[i] + x[(i + 4) % 5];
    let d_nu: f64 = (0..5).map(|i| w[i] * lap(i)).sum();
    let d_k: f64 = (0..5).map(|i| -w[i] * x[i].powi(3)).sum();
    assert!((dp[0] - d_nu).abs() < 1e-14 && (dp[1] - d_k).abs() < 1e-14, "{dp:?} vs [{d_nu}, {d_k}]");
}

#[test]
fn wrong_lengths_panic_before_the_generated_code() {
    let op = ReactionDiffusion { n: 4 };
    let res = std::panic::catch_unwind(|| op.vjp_new(&[0.0; 3], &[0.1, 0.1], &[1.0; 4]));
    let msg = res.unwrap_err();
    let msg = msg.downcast_ref::<String>().unwrap();
    assert!(msg.contains("`x` has length 3, the operator expects 4"), "{msg}");
}

/// Reads back what it wrote to its output: `y = A·x`, then `y = x − κ·y`.
/// Enzyme got `∂/∂κ` wrong for this shape when the output was declared
/// `DuplicatedOnly`; the macro declares it `Duplicated`, and this test keeps
/// it that way.
pub struct ReadsBackOutput {
    pub n: usize,
}

impl Operator for ReadsBackOutput {
    fn n_in(&self) -> usize {
        self.n
    }
    fn n_out(&self) -> usize {
        self.n
    }
    fn n_params(&self) -> usize {
        1
    }
}

fn reads_back_output(op: &ReadsBackOutput, x: &[f64], p: &[f64], y: &mut [f64]) {
    let n = op.n;
    for i in 0..n {
        y[i] = 2.0 * x[i] - x[(i + 1) % n] - x[(i + n - 1) % n];
    }
    for i in 0..n {
        y[i] = x[i] - p[0] * y[i];
    }
}

diffsim::differentiable!(ReadsBackOutput => reads_back_output);

#[test]
fn an_operator_that_reads_back_its_output_gets_the_right_gradient() {
    let op = ReadsBackOutput { n: 6 };
    let x: Vec<f64> = (0..6).map(|i| (1.3 * i as f64).cos()).collect();
    let report = check_all(&op, &x, &[0.2], &CheckOptions::default());
    assert!(report.passed(), "{report}");
}
