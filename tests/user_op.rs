//! A user's own plain function made differentiable with the macro, as the
//! README and docs/own-solver.md show it: the three checks, parameters included, and validation
//! before the generated code.

use diffsim::check::{CheckParams, check_all};
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
        let report = check_all(&op, &x, &[0.2, 0.5], &CheckParams::default());
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
    let report = check_all(&op, &x, &[0.2], &CheckParams::default());
    assert!(report.passed(), "{report}");
}

/// Two reaction–diffusion steps, the state between them kept in the
/// scratch the framework lends (`differentiable!(… , scratch = len)`).
pub struct TwoSteps {
    pub n: usize,
}

impl Operator for TwoSteps {
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

fn two_steps(op: &TwoSteps, x: &[f64], p: &[f64], y: &mut [f64], h: &mut [f64]) {
    let one = ReactionDiffusion { n: op.n };
    reaction_diffusion(&one, x, p, h);
    reaction_diffusion(&one, h, p, y);
}

fn two_steps_scratch(op: &TwoSteps) -> usize {
    op.n
}

diffsim::differentiable!(TwoSteps => two_steps, scratch = two_steps_scratch);

#[test]
fn a_function_with_lent_scratch_equals_its_steps_chained() {
    let n = 7;
    let (op, one) = (TwoSteps { n }, ReactionDiffusion { n });
    let x: Vec<f64> = (0..n).map(|i| (0.9 * i as f64).sin()).collect();
    let w: Vec<f64> = (0..n).map(|i| (0.4 * i as f64).cos()).collect();
    let p = [0.2, 0.5];
    // Leave non-zero values in this thread's scratch where the scratch's
    // shadow will lie: the shadow must be zeroed before each generated call.
    let big = ReadsBackOutput { n: 4 * n };
    let _ = big.vjp_new(&vec![1.0; 4 * n], &[0.3], &vec![1.0; 4 * n]);
    // Independent computation: the one-step operator twice.
    let h = one.eval(&x, &p);
    assert_eq!(op.eval(&x, &p), one.eval(&h, &p));
    let (dh, dp2) = one.vjp_new(&h, &p, &w);
    let (dx, dp1) = one.vjp_new(&x, &p, &dh);
    for _ in 0..2 {
        let (gx, gp) = op.vjp_new(&x, &p, &w);
        let close = |a: f64, b: f64| (a - b).abs() <= 1e-13 * (1.0 + b.abs());
        assert!(gx.iter().zip(&dx).all(|(&a, &b)| close(a, b)), "{gx:?} vs {dx:?}");
        assert!(close(gp[0], dp1[0] + dp2[0]) && close(gp[1], dp1[1] + dp2[1]), "{gp:?}");
    }
    let report = check_all(&op, &x, &p, &CheckParams::default());
    assert!(report.passed(), "{report}");
}

/// `y_i = |x_i|·|x_{i+1}|` (periodic), with `|x|` kept in lent scratch:
/// both options of the macro at once (a kink at every `x_i = 0`).
pub struct AbsProduct {
    pub n: usize,
}

impl Operator for AbsProduct {
    fn n_in(&self) -> usize {
        self.n
    }
    fn n_out(&self) -> usize {
        self.n
    }
}

fn abs_product(op: &AbsProduct, x: &[f64], _p: &[f64], y: &mut [f64], a: &mut [f64]) {
    let n = op.n;
    for i in 0..n {
        a[i] = if x[i] > 0.0 { x[i] } else { -x[i] };
    }
    for i in 0..n {
        y[i] = a[i] * a[(i + 1) % n];
    }
}

fn abs_product_scratch(op: &AbsProduct) -> usize {
    op.n
}

/// Distance along `dx` to the nearest sign change of `x`.
fn abs_product_radius(_: &AbsProduct, x: &[f64], _p: &[f64], dx: &[f64], _dp: &[f64]) -> f64 {
    x.iter().zip(dx).filter(|(_, d)| **d != 0.0).map(|(x, d)| (x / d).abs()).fold(f64::INFINITY, f64::min)
}

diffsim::differentiable!(AbsProduct => abs_product, smooth_radius = abs_product_radius, scratch = abs_product_scratch);

#[test]
fn a_kinked_function_with_lent_scratch_matches_its_closed_form() {
    let n = 6;
    let op = AbsProduct { n };
    let x = [0.7, -0.3, 1e-3, -1.2, 0.5, -2e-3];
    let w = [1.0, -0.5, 2.0, 0.25, -1.0, 0.75];
    // ∂/∂x_j of Σ_i w_i·|x_i|·|x_{i+1}|: rows j and j − 1.
    let sign = |v: f64| if v > 0.0 { 1.0 } else { -1.0 };
    let want: Vec<f64> = (0..n).map(|j| sign(x[j]) * (w[j] * x[(j + 1) % n].abs() + w[(j + n - 1) % n] * x[(j + n - 1) % n].abs())).collect();
    let (dx, _) = op.vjp_new(&x, &[], &w);
    assert!(dx.iter().zip(&want).all(|(a, b)| (a - b).abs() <= 1e-15), "{dx:?} vs {want:?}");
    // The kinks 1e-3 away are within reach of the larger steps: the checks
    // keep their steps inside the smooth radius and still pass.
    let report = check_all(&op, &x, &[], &CheckParams::default());
    assert!(report.passed(), "{report}");
}

/// The same reaction–diffusion step as a stencil *map* (with its
/// parameters) and as a *cell* function (parameters fixed in the type):
/// the two forms of `stencil3!`.
pub struct ReactionDiffusionMap {
    pub n: usize,
}

impl Operator for ReactionDiffusionMap {
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

fn reaction_diffusion_map(_: &ReactionDiffusionMap, l: &[f64], c: &[f64], r: &[f64], p: &[f64], out: &mut [f64]) {
    for i in 0..out.len() {
        out[i] = c[i] + p[0] * (r[i] - 2.0 * c[i] + l[i]) - p[1] * c[i] * c[i] * c[i];
    }
}

diffsim::stencil3!(ReactionDiffusionMap => reaction_diffusion_map);

pub struct ReactionDiffusionCell {
    pub n: usize,
    pub nu: f64,
    pub k: f64,
}

impl Operator for ReactionDiffusionCell {
    fn n_in(&self) -> usize {
        self.n
    }
    fn n_out(&self) -> usize {
        self.n
    }
}

fn reaction_diffusion_cell(op: &ReactionDiffusionCell, l: f64, c: f64, r: f64) -> f64 {
    c + op.nu * (r - 2.0 * c + l) - op.k * c * c * c
}

diffsim::stencil3!(cell: ReactionDiffusionCell => reaction_diffusion_cell, smooth_radius = diffsim::op::always_smooth);

#[test]
fn stencil_map_and_cell_forms_pass_all_checks_and_agree_with_the_whole_step() {
    use diffsim::check::dot_product_between;
    use diffsim::op::{Forward, Vjp};
    let p = [0.2, 0.5];
    // 3 and 1027: the smallest grid, and chunks of 512 that end in a two-cell chunk.
    for n in [3, 13, 1027] {
        let x: Vec<f64> = (0..n).map(|i| (0.7 * i as f64).sin()).collect();
        let map = ReactionDiffusionMap { n };
        let cell = ReactionDiffusionCell { n, nu: p[0], k: p[1] };
        let whole = ReactionDiffusion { n };
        let report = check_all(&map, &x, &p, &CheckParams::default());
        assert!(report.passed(), "map form, n = {n}:\n{report}");
        let report = check_all(&cell, &x, &[], &CheckParams::default());
        assert!(report.passed(), "cell form, n = {n}:\n{report}");
        // Same values and same adjoints as the whole-step operator.
        let (mut y1, mut y2) = (vec![0.0; n], vec![0.0; n]);
        cell.forward(&x, &[], &mut y1);
        whole.forward(&x, &p, &mut y2);
        assert!(y1.iter().zip(&y2).all(|(a, b)| (a - b).abs() < 1e-15));
        let w: Vec<f64> = (0..n).map(|i| (1.1 * i as f64).cos()).collect();
        let (mut d1, mut d2, mut dp) = (vec![0.0; n], vec![0.0; n], vec![0.0; 2]);
        Vjp::vjp(&cell, &x, &[], &mut w.clone(), &mut d1, &mut []);
        Vjp::vjp(&whole, &x, &p, &mut w.clone(), &mut d2, &mut dp);
        assert!(d1.iter().zip(&d2).all(|(a, b)| (a - b).abs() < 1e-14), "cell adjoint differs from the whole step's");
        let o = CheckParams { tol: 1e-12, ..Default::default() };
        assert!(dot_product_between(&map, &whole, &x, &p, &o).verdict.passed());
    }
}
