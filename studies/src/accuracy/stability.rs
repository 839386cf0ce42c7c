//! Hard cases that must stay stable (`diffsim stability`): stiff diffusion,
//! shocks, long rollouts, ill-conditioned pressure solves, near-singular
//! Jacobians in half-inverse gradients, and NaN detection with the step.
//!
//! Each case returns whether it passed and the figures it measured. No
//! float32 solver exists yet, so there are no float32 variants of these
//! cases.

use rand::SeedableRng;
use rand::rngs::StdRng;
use serde_json::{Map, Value, json};

use diffsim_solvers::burgers::Burgers1d;
use diffsim_solvers::exact::HeatMode;
use diffsim_solvers::smoke::MacGrid;

use super::AccuracyError;
use super::Diffusion;
use super::flow::{HeatRun, LENGTH, periodic_box};
use diffsim::fluids::{Diffuse, Project};
use diffsim::nn::{Activation, Init, presets};
use diffsim::op::{Forward, OpError, Operator, Vjp};
use diffsim::problems::burgers::{BurgersEnzyme, BurgersHand, P1};
use diffsim::problems::oscillators::Oscillators;
use diffsim::rollout::{Checkpointing, Pass, Rollout, RolloutError, all_finite};
use diffsim::train::clip_by_norm;
use diffsim::train::hig::{ControlSample, Hig, HigError, hig_step};

/// The outcome of one case.
#[derive(Clone, Debug)]
pub struct Case {
    /// Its name.
    pub case: String,
    /// Whether the behaviour was the stable one.
    pub passed: bool,
    /// What it measured, by name.
    pub figures: Map<String, Value>,
    /// One line on what happened.
    pub summary: String,
}

impl Case {
    fn new(case: &str, passed: bool, figures: Map<String, Value>, summary: String) -> Self {
        Self { case: case.to_string(), passed, figures, summary }
    }

    /// `{"case", "passed", figures…}`.
    pub fn to_json(&self) -> Value {
        let mut m = Map::new();
        m.insert("case".into(), json!(self.case));
        m.insert("passed".into(), json!(self.passed));
        for (k, v) in &self.figures {
            m.insert(k.clone(), v.clone());
        }
        Value::Object(m)
    }
}

/// Every case, in order.
pub fn run_all() -> Vec<Case> {
    vec![
        stiff_explicit_refused(),
        stiff_implicit_stable(),
        burgers_shock(),
        long_rollout(),
        exploding_gradient_clipped(),
        ill_conditioned_pressure(),
        hig_near_singular(),
        nan_forward_detected(),
        nan_backward_detected(),
    ]
}

/// `‖v‖₂`.
fn norm(v: &[f64]) -> f64 {
    v.iter().map(|a| a * a).sum::<f64>().sqrt()
}

fn figures(pairs: Vec<(&str, Value)>) -> Map<String, Value> {
    pairs.into_iter().map(|(k, v)| (k.to_string(), v)).collect()
}

/// Explicit diffusion at twice its stability limit is refused before it
/// runs (the scene builder refuses it the same way).
pub fn stiff_explicit_refused() -> Case {
    let r = HeatRun { n: 32, nu: 0.1, t_end: 1.0, dt_factor: 0.5, diffusion: Diffusion::Explicit }.error();
    match r {
        Err(AccuracyError::Operator { error: OpError::Unstable { value, limit }, step: 0, .. }) => Case::new(
            "stiff-diffusion-explicit",
            true,
            figures(vec![("kappa", json!(value)), ("limit", json!(limit))]),
            format!("refused: κ = {value} beyond the explicit limit {limit}"),
        ),
        other => Case::new("stiff-diffusion-explicit", false, Map::new(), format!("not refused: {other:?}")),
    }
}

/// Implicit diffusion at 100× the explicit limit (κ = 25): ten steps, the
/// largest value never grows and the mode decays.
pub fn stiff_implicit_stable() -> Case {
    let n = 32;
    let cfg = periodic_box(n);
    let d = Diffuse::implicit(cfg, true, false, 1e-10, 10_000);
    let mut x = HeatMode { length: LENGTH, modes: (1.0, 2.0), phase: 0.3, nu: 1.0 }.cells(n, 0.0);
    x.resize(cfg.n_state(), 0.0);
    let mut y = vec![0.0; x.len()];
    let max = |v: &[f64]| v.iter().fold(0.0f64, |m, a| m.max(a.abs()));
    let start = max(&x);
    let (mut monotone, mut error) = (true, None);
    for _ in 0..10 {
        d.forward(&x, &[25.0], &mut y);
        error = error.or(d.take_error());
        monotone &= all_finite(&y) && max(&y) <= max(&x) * (1.0 + 1e-12);
        std::mem::swap(&mut x, &mut y);
    }
    let end = max(&x);
    let passed = monotone && error.is_none() && end < start;
    Case::new(
        "stiff-diffusion-implicit-100x",
        passed,
        figures(vec![("kappa", json!(25.0)), ("explicit_limit", json!(0.25)), ("max_start", json!(start)), ("max_end", json!(end))]),
        format!("κ = 25 (100× the explicit limit), 10 steps: max |s| {start:.3} → {end:.3e}{}", error.map_or(String::new(), |e| format!(", {e}"))),
    )
}

/// Total variation of a periodic line.
fn total_variation(u: &[f64]) -> f64 {
    let n = u.len();
    (0..n).map(|i| (u[(i + 1) % n] - u[i]).abs()).sum()
}

/// Near-inviscid Burgers (ν = 1e-4, P1's scheme, 512 cells) from `sin x`
/// to `t = 3`, well past the shock at `t = 1`: bounded by the initial
/// maximum, total variation never increasing, and its gradient (Enzyme,
/// binomial checkpointing) finite.
pub fn burgers_shock() -> Case {
    let n = 512;
    let dx = 2.0 * std::f64::consts::PI / n as f64;
    let cfg = Burgers1d { n, dx, dt: 0.25 * dx, nu: 1e-4 };
    let steps = (3.0 / cfg.dt).ceil() as usize;
    let u0: Vec<f64> = (0..n).map(|i| (i as f64 * dx).sin()).collect();
    let (mut u, mut v) = (u0.clone(), vec![0.0; n]);
    let (tv0, mut tv_increase, mut max_u, mut finite) = (total_variation(&u0), 0.0f64, 0.0f64, true);
    let mut tv = tv0;
    let op = BurgersHand(cfg);
    for _ in 0..steps {
        op.forward(&u, &[], &mut v);
        finite &= all_finite(&v);
        let tv_next = total_variation(&v);
        tv_increase = tv_increase.max(tv_next - tv);
        tv = tv_next;
        max_u = v.iter().fold(max_u, |m, a| m.max(a.abs()));
        std::mem::swap(&mut u, &mut v);
    }
    let loss = |x: &[f64], g: &mut [f64]| {
        let mut s = 0.0;
        for (g, &a) in g.iter_mut().zip(x) {
            *g = dx * a;
            s += 0.5 * dx * a * a;
        }
        s
    };
    let enzyme = BurgersEnzyme(cfg);
    let grad = Rollout::new(&enzyme, &[], steps).and_then(|r| r.value_and_grad(&u0, &loss, Checkpointing::binomial_log(steps)));
    let grad_norm = grad.as_ref().map_or(f64::NAN, |g| norm(&g.dx0));
    let passed = finite && max_u <= 1.0 + 1e-12 && tv_increase <= 1e-12 * tv0 && grad_norm.is_finite();
    Case::new(
        "burgers-shock-nu-1e-4",
        passed,
        figures(vec![
            ("steps", json!(steps)),
            ("max_abs_u", json!(max_u)),
            ("tv_start", json!(tv0)),
            ("tv_end", json!(tv)),
            ("largest_tv_increase", json!(tv_increase)),
            ("grad_norm", json!(grad_norm)),
        ]),
        format!(
            "{steps} steps: max |u| {max_u:.6}, TV {tv0:.4} → {tv:.4} (largest increase in a step {tv_increase:.1e}), ‖∂L/∂u₀‖ {grad_norm:.3e}{}",
            grad.err().map_or(String::new(), |e| format!(" ({e})"))
        ),
    )
}

/// P1 (64 cells) gradients through 10, 100, 1000 and 10⁴ steps (Enzyme,
/// binomial checkpointing): all finite; the norm's growth per step reported.
pub fn long_rollout() -> Case {
    let mut norms = Vec::new();
    let mut error = None;
    for steps in [10, 100, 1000, 10_000] {
        match P1::new(64, steps).grad_enzyme(Checkpointing::binomial_log(steps)) {
            Ok(g) => norms.push(norm(&g.dx0)),
            Err(e) => {
                error = Some(e);
                norms.push(f64::NAN);
            }
        }
    }
    let growth = (norms[3] / norms[0]).powf(1.0 / 9990.0);
    let passed = error.is_none() && norms.iter().all(|g| g.is_finite());
    Case::new(
        "long-rollout-1e4-steps",
        passed,
        figures(vec![
            ("grad_norm_10", json!(norms[0])),
            ("grad_norm_100", json!(norms[1])),
            ("grad_norm_1000", json!(norms[2])),
            ("grad_norm_10000", json!(norms[3])),
            ("growth_per_step", json!(growth)),
        ]),
        format!("‖∂L/∂u₀‖ after 10/100/1000/10⁴ steps: {:.3e} / {:.3e} / {:.3e} / {:.3e} (×{growth:.6} per step)", norms[0], norms[1], norms[2], norms[3]),
    )
}

/// `x ↦ a·x` on `n` values, hand-written VJP: an unstable linear map whose
/// gradients grow as `a^T`.
#[derive(Clone, Copy, Debug)]
struct Amplify {
    n: usize,
    factor: f64,
}

impl Operator for Amplify {
    fn n_in(&self) -> usize {
        self.n
    }
    fn n_out(&self) -> usize {
        self.n
    }
}

impl Forward for Amplify {
    fn forward(&self, x: &[f64], _p: &[f64], y: &mut [f64]) {
        for (y, &a) in y.iter_mut().zip(x) {
            *y = self.factor * a;
        }
    }
}

impl Vjp for Amplify {
    fn vjp(&self, _x: &[f64], _p: &[f64], dy: &mut [f64], dx: &mut [f64], _dp: &mut [f64]) {
        for (d, g) in dx.iter_mut().zip(dy.iter_mut()) {
            *d += self.factor * *g;
            *g = 0.0;
        }
    }
}

/// An unstable map (×1.02 per step) through 10⁴ steps: the gradient is
/// finite but ~1e86 times the loss scale; clipping by norm bounds the
/// update a training step takes.
pub fn exploding_gradient_clipped() -> Case {
    let op = Amplify { n: 8, factor: 1.02 };
    let steps = 10_000;
    let x0 = vec![1e-80; 8];
    let loss = |x: &[f64], g: &mut [f64]| {
        g.copy_from_slice(x);
        0.5 * x.iter().map(|a| a * a).sum::<f64>()
    };
    let r = Rollout::new(&op, &[], steps).and_then(|r| r.value_and_grad(&x0, &loss, Checkpointing::Store));
    match r {
        Ok(g) => {
            let mut update = g.dx0.clone();
            let raw = clip_by_norm(&mut update, 1.0);
            let clipped = norm(&update);
            let passed = raw.is_finite() && clipped <= 1.0 + 1e-12;
            Case::new(
                "exploding-gradient-clipped",
                passed,
                figures(vec![("grad_norm", json!(raw)), ("growth_per_step", json!(op.factor * op.factor)), ("clipped_norm", json!(clipped))]),
                format!("×1.02 per step, 10⁴ steps: ‖∂L/∂x₀‖ {raw:.3e}, clipped to {clipped:.3}"),
            )
        }
        Err(e) => Case::new("exploding-gradient-clipped", false, Map::new(), format!("{e}")),
    }
}

/// A 96×96 closed box split by a one-cell wall with a one-cell gap: too
/// few CG iterations is reported as non-convergence with its residual;
/// enough converge, forward and adjoint.
pub fn ill_conditioned_pressure() -> Case {
    let n = 96;
    let cfg = MacGrid::p2(n);
    let mut solid = vec![false; n * n];
    for j in 0..n - 1 {
        solid[j * n + n / 2] = true;
    }
    let mut x = vec![0.0; cfg.n_state()];
    for (k, u) in x[cfg.n_s()..cfg.n_s() + cfg.n_face(0)].iter_mut().enumerate() {
        *u = ((k * 7919) % 101) as f64 / 101.0 - 0.5;
    }
    let short = Project::with_obstacles(cfg, 1e-10, 50, diffsim_solvers::smoke::Preconditioner::Mic0, &solid);
    let mut y = x.clone();
    short.apply(&mut y);
    let reported = short.take_error();
    let full = Project::with_obstacles(cfg, 1e-10, 100_000, diffsim_solvers::smoke::Preconditioner::Mic0, &solid);
    let mut y = x.clone();
    full.apply(&mut y);
    let forward = full.take_error();
    let mut g = x.clone();
    full.apply_adjoint(&mut g);
    let adjoint = full.take_error();
    let residual = match reported {
        Some(OpError::NoConvergence { relative_residual, .. }) => relative_residual,
        _ => f64::NAN,
    };
    let passed = residual.is_finite() && forward.is_none() && adjoint.is_none() && all_finite(&y) && all_finite(&g);
    Case::new(
        "ill-conditioned-pressure",
        passed,
        figures(vec![
            ("n", json!(n)),
            ("residual_after_50_iterations", json!(residual)),
            ("cg_forward_iterations", json!(full.log.cg_forward.get())),
            ("cg_adjoint_iterations", json!(full.log.cg_adjoint.get())),
        ]),
        format!(
            "thin wall: 50 iterations reported as {}; to 1e-10 in {} (forward) and {} (adjoint) iterations",
            reported.map_or("converged (not reported)".to_string(), |e| e.to_string()),
            full.log.cg_forward.get(),
            full.log.cg_adjoint.get()
        ),
    )
}

/// A HIG step whose batch Jacobian is exactly rank-deficient (eight copies
/// of one sample): with truncation the update is finite; without it the
/// step is refused (`HigError::NonFinite`) or finite, never NaN passed on.
pub fn hig_near_singular() -> Case {
    let physics = Oscillators::linear();
    let net = presets::mlp(&[4, 8, physics.steps], Activation::Tanh).expect("the preset is well formed");
    let theta0 = net.init(&mut StdRng::seed_from_u64(3), Init::Glorot);
    let s = ControlSample { x0: vec![0.3, -0.2, 0.5, 0.1], target: vec![0.3, -0.2, 0.5, 0.1] };
    let batch = vec![s; 8];
    let mut truncated = theta0.clone();
    let r1 = hig_step(&physics, &net, &mut truncated, &batch, &Hig { memory_budget: 1 << 26, ..Hig::half_inverse(1.0, 1e-10) });
    let mut raw = theta0.clone();
    let r2 = hig_step(&physics, &net, &mut raw, &batch, &Hig { memory_budget: 1 << 26, ..Hig::half_inverse(1.0, 0.0) });
    let step = |t: &[f64]| t.iter().zip(&theta0).map(|(a, b)| (a - b) * (a - b)).sum::<f64>().sqrt();
    let ok1 = r1.is_ok() && all_finite(&truncated);
    let ok2 = matches!(r2, Err(HigError::NonFinite)) || (r2.is_ok() && all_finite(&raw));
    Case::new(
        "hig-near-singular",
        ok1 && ok2,
        figures(vec![("update_norm_truncated", json!(step(&truncated))), ("untruncated_refused", json!(r2.is_err()))]),
        format!(
            "rank-deficient Jacobian: truncated step {:.3e}; untruncated {}",
            step(&truncated),
            match r2 {
                Ok(_) => format!("step {:.3e}", step(&raw)),
                Err(e) => format!("refused ({e})"),
            }
        ),
    )
}

/// P1's scheme at 2× its Courant limit blows up: the rollout stops with the
/// step whose output first held a non-finite value.
pub fn nan_forward_detected() -> Case {
    let mut p = P1::new(64, 2000);
    p.cfg.dt = 2.0 * p.cfg.dx;
    let hand = BurgersHand(p.cfg);
    let r = Rollout::new(&hand, &[], p.steps).and_then(|r| r.final_state(&p.u0));
    match r {
        Err(e @ RolloutError::NonFinite { pass: Pass::Forward, step, operator }) => Case::new(
            "nan-forward",
            step > 0 && operator.as_str() == "BurgersHand",
            figures(vec![("step", json!(step)), ("operator", json!(operator.as_str()))]),
            format!("reported: {e}"),
        ),
        other => Case::new("nan-forward", false, Map::new(), format!("not reported: {:?}", other.map(|x| x[0]))),
    }
}

/// A loss whose gradient is NaN at step 5 of 10 (its value finite): the
/// backward pass reports step 5.
pub fn nan_backward_detected() -> Case {
    let p = P1::new(64, 10);
    let hand = BurgersHand(p.cfg);
    let loss = diffsim::rollout::AtSteps {
        steps: vec![5, 10],
        f: |t: usize, x: &[f64], g: &mut [f64]| {
            for (g, &a) in g.iter_mut().zip(x) {
                *g = if t == 5 { f64::NAN } else { a };
            }
            0.0
        },
    };
    let r = Rollout::new(&hand, &[], p.steps).and_then(|r| r.value_and_grad(&p.u0, &loss, Checkpointing::Store));
    match r {
        Err(e @ RolloutError::NonFinite { pass: Pass::Backward, step, .. }) => {
            Case::new("nan-backward", step == 5, figures(vec![("step", json!(step))]), format!("reported: {e}"))
        }
        other => Case::new("nan-backward", false, Map::new(), format!("not reported: {:?}", other.map(|g| g.loss))),
    }
}
