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

/// A damped pendulum integrated by 50 explicit Euler steps, its damping
/// and length per sample (`p = [damping, g/ℓ]`): an ensemble member with
/// its own parameters, declared with its lane form.
pub struct Pendulum {
    pub dt: f64,
}

impl Operator for Pendulum {
    fn n_in(&self) -> usize {
        2
    }
    fn n_out(&self) -> usize {
        2
    }
    fn n_params(&self) -> usize {
        2
    }
}

#[inline(always)]
fn pendulum_sample(op: &Pendulum, theta: f64, omega: f64, damping: f64, g: f64) -> (f64, f64) {
    let (mut t, mut w) = (theta, omega);
    for _ in 0..50 {
        let a = -g * t.sin() - damping * w;
        t += op.dt * w;
        w += op.dt * a;
    }
    (t, w)
}

fn pendulum(op: &Pendulum, x: &[f64], p: &[f64], y: &mut [f64]) {
    let (t, w) = pendulum_sample(op, x[0], x[1], p[0], p[1]);
    y[0] = t;
    y[1] = w;
}

/// [`pendulum`] on `LANES` samples side by side (value `c` of lane `l` at
/// `c·LANES + l`).
fn pendulum_lanes(op: &Pendulum, x: &[f64], p: &[f64], y: &mut [f64]) {
    use diffsim::op::LANES;
    for l in 0..LANES {
        let (t, w) = pendulum_sample(op, x[l], x[LANES + l], p[l], p[LANES + l]);
        y[l] = t;
        y[LANES + l] = w;
    }
}

diffsim::differentiable!(Pendulum => pendulum, lanes = pendulum_lanes);

/// `forward_each` equals `forward` per sample bit for bit, and `vjp_each`
/// (adding into its outputs, consuming its seeds) equals `vjp` per sample,
/// for batches of whole and partial lane groups.
fn lanes_agree_with_samples<O: diffsim::op::Vjp>(op: &O, count: usize, what: &str) {
    let (n_in, n_p, n_out) = (op.n_in(), op.n_params(), op.n_out());
    let wave = |n: usize, a: f64, b: f64| -> Vec<f64> { (0..n).map(|i| a + b * (0.37 * i as f64 + a).sin()).collect() };
    let (xs, ps, seeds) = (wave(count * n_in, 0.3, 0.4), wave(count * n_p, 0.5, 0.3), wave(count * n_out, 0.1, 1.0));
    let mut ys = vec![0.0; count * n_out];
    op.forward_each(&xs, &ps, &mut ys);
    let (mut dys, mut dxs, mut dps) = (seeds.clone(), vec![1.0; count * n_in], vec![-1.0; count * n_p]);
    op.vjp_each(&xs, &ps, &mut dys, &mut dxs, &mut dps);
    assert!(dys.iter().all(|&v| v == 0.0), "{what}: vjp_each leaves its seeds consumed");
    for s in 0..count {
        let (x, p) = (&xs[s * n_in..(s + 1) * n_in], &ps[s * n_p..(s + 1) * n_p]);
        let mut y = vec![0.0; n_out];
        op.forward(x, p, &mut y);
        assert_eq!(y, ys[s * n_out..(s + 1) * n_out], "{what}: forward_each, sample {s} of {count}");
        let (mut dx, mut dp) = (vec![1.0; n_in], vec![-1.0; n_p]);
        op.vjp(x, p, &mut seeds[s * n_out..(s + 1) * n_out].to_vec(), &mut dx, &mut dp);
        let close = |a: &[f64], b: &[f64]| a.iter().zip(b).all(|(u, v)| (u - v).abs() <= 1e-13 * (1.0 + v.abs()));
        assert!(close(&dxs[s * n_in..(s + 1) * n_in], &dx), "{what}: vjp_each's dx, sample {s} of {count}");
        assert!(close(&dps[s * n_p..(s + 1) * n_p], &dp), "{what}: vjp_each's dp, sample {s} of {count}");
    }
}

#[test]
fn lane_forms_match_their_per_sample_operator() {
    use diffsim::problems::oscillators::Oscillators;
    let pendulum = Pendulum { dt: 0.05 };
    let report = check_all(&pendulum, &[0.4, -0.2], &[0.3, 2.0], &CheckParams::default());
    assert!(report.passed(), "the pendulum:\n{report}");
    // One sample, one whole group, a partial group after a whole one, three groups.
    for count in [1, 8, 13, 24] {
        lanes_agree_with_samples(&pendulum, count, "pendulum");
        lanes_agree_with_samples(&Oscillators::nonlinear(), count, "nonlinear oscillators");
        lanes_agree_with_samples(&Oscillators { steps: 5, ..Oscillators::linear() }, count, "linear oscillators");
    }
}

#[test]
#[should_panic(expected = "vjp_each: slice 1 holds 5 values, 2 samples of 2 expected")]
fn lane_batches_of_partial_samples_panic_before_the_generated_code() {
    use diffsim::op::Vjp;
    let op = Pendulum { dt: 0.05 };
    let (mut dys, mut dxs, mut dps) = (vec![0.0; 4], vec![0.0; 4], vec![0.0; 5]);
    op.vjp_each(&[0.0; 4], &[0.0; 5], &mut dys, &mut dxs, &mut dps);
}
