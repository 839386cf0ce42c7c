//! Half-inverse gradients (HIG; Schnell, Holl & Thuerey, ICLR 2022) for a
//! network `N(·; θ)` whose output drives a physics operator `P`: per
//! sample `y = P(x₀, N(y*; θ))`, loss `L = (1/B)·Σ_b ‖y_b − y*_b‖²`.
//!
//! Requires: `P` and `N` with VJPs (the physics Jacobian rows come from one
//! VJP of `P` and one of `N` per output value). Each step stacks the
//! per-sample Jacobians `∂y_b/∂θ` into `J` (`B·n_out × n_θ`), takes its
//! SVD (faer, in `diffsim-solvers`), raises the singular values to `−½`
//! (those at or below `truncation · s_max` dropped: relative truncation, as
//! the published code's `rcond`), and updates `θ ← θ − η·J^{−½}·∂L/∂y`.
//! The same step with the power `−1` is Gauss-Newton (the published
//! comparison's third optimizer). The decomposition is the SVD or, where
//! as accurate and cheaper, the eigendecomposition of the smaller Gram
//! matrix (`linalg::PowerMethod::AUTO`); the Jacobian rows are computed in
//! parallel over the samples.

use rayon::prelude::*;

use crate::op::Vjp;

pub use diffsim_solvers::linalg::{Decomposition, PowerMethod};

/// HIG settings.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Hig {
    /// Step size η (the published runs use 1).
    pub lr: f64,
    /// Relative truncation of the singular values.
    pub truncation: f64,
    /// Largest Jacobian (bytes) the step may build.
    pub memory_budget: usize,
    /// The power of the pseudo-inverse: ½ for HIG, 1 for Gauss-Newton.
    pub power: f64,
    /// How `J` is decomposed; `None` is [`PowerMethod::AUTO`] (the Gram
    /// eigendecomposition where it resolves the kept spectrum, else the SVD).
    pub method: Option<PowerMethod>,
}

impl Hig {
    /// Half-inverse gradients with step size `lr` and relative truncation
    /// `truncation`, a 1 GiB Jacobian budget and the automatic method.
    pub fn half_inverse(lr: f64, truncation: f64) -> Self {
        Self { lr, truncation, memory_budget: 1 << 30, power: 0.5, method: None }
    }

    /// Gauss-Newton (the truncated pseudo-inverse) with the same defaults.
    pub fn gauss_newton(lr: f64, truncation: f64) -> Self {
        Self { power: 1.0, ..Self::half_inverse(lr, truncation) }
    }

    /// The decomposition this step uses.
    pub fn method(&self) -> PowerMethod {
        self.method.unwrap_or(PowerMethod::AUTO)
    }
}

/// A HIG step that cannot be taken.
#[derive(Clone, Copy, Debug, PartialEq, thiserror::Error)]
pub enum HigError {
    /// The Jacobian would exceed the memory budget.
    #[error("the batch Jacobian ({rows} × {cols} values, {bytes} bytes) exceeds the memory budget of {budget} bytes; use a smaller batch or raise the budget")]
    Budget {
        /// Rows (batch × outputs).
        rows: usize,
        /// Columns (parameters).
        cols: usize,
        /// Its size.
        bytes: usize,
        /// The budget.
        budget: usize,
    },
    /// The decomposition did not converge.
    #[error("the decomposition of the batch Jacobian did not converge")]
    Svd,
    /// A non-finite loss, Jacobian or update.
    #[error("non-finite values in the HIG step")]
    NonFinite,
}

/// One sample: the physics input and the target (also the network's input).
#[derive(Clone, Debug)]
pub struct ControlSample {
    /// The physics operator's state input `x₀`.
    pub x0: Vec<f64>,
    /// The target `y*`.
    pub target: Vec<f64>,
}

/// `(L, ∂L/∂θ)` over a batch by one VJP per sample (for gradient-based
/// optimizers such as Adam), reduced in sample order.
pub fn loss_and_gradient<P: Vjp + Sync, N: Vjp + Sync>(physics: &P, net: &N, theta: &[f64], batch: &[ControlSample]) -> (f64, Vec<f64>) {
    let b = batch.len() as f64;
    let parts: Vec<(f64, Vec<f64>)> = batch
        .par_iter()
        .map(|s| {
            let u = net_eval(net, &s.target, theta);
            let mut y = vec![0.0; physics.n_out()];
            physics.forward(&s.x0, &u, &mut y);
            let mut seed: Vec<f64> = y.iter().zip(&s.target).map(|(a, t)| 2.0 * (a - t) / b).collect();
            let loss: f64 = y.iter().zip(&s.target).map(|(a, t)| (a - t) * (a - t)).sum::<f64>() / b;
            (loss, chain_vjp(physics, net, theta, s, &u, &mut seed))
        })
        .collect();
    let mut g = vec![0.0; theta.len()];
    let mut loss = 0.0;
    for (l, d) in parts {
        loss += l;
        for (a, v) in g.iter_mut().zip(&d) {
            *a += v;
        }
    }
    (loss, g)
}

fn net_eval<N: Vjp>(net: &N, input: &[f64], theta: &[f64]) -> Vec<f64> {
    let mut u = vec![0.0; net.n_out()];
    net.forward(input, theta, &mut u);
    u
}

/// `(∂y/∂θ)ᵀ·seed` for one sample: the physics VJP into the controls, then
/// the network's into θ.
fn chain_vjp<P: Vjp, N: Vjp>(physics: &P, net: &N, theta: &[f64], s: &ControlSample, u: &[f64], seed: &mut [f64]) -> Vec<f64> {
    let mut dx = vec![0.0; physics.n_in()];
    let mut du = vec![0.0; u.len()];
    physics.vjp(&s.x0, u, seed, &mut dx, &mut du);
    let mut din = vec![0.0; net.n_in()];
    let mut dtheta = vec![0.0; theta.len()];
    net.vjp(&s.target, theta, &mut du, &mut din, &mut dtheta);
    dtheta
}

/// A batch's stacked Jacobian and loss gradient.
#[derive(Clone, Debug)]
pub struct BatchJacobian {
    /// Rows: batch × outputs.
    pub rows: usize,
    /// Columns: parameters.
    pub cols: usize,
    /// `∂y/∂θ`, row-major `rows × cols`, sample after sample.
    pub jac: Vec<f64>,
    /// `∂L/∂y`, `rows` values.
    pub grad: Vec<f64>,
    /// The batch loss.
    pub loss: f64,
}

/// The batch Jacobian `∂y/∂θ` (one physics and one network VJP per output
/// value, the samples in parallel) and `∂L/∂y`; refused above the memory
/// budget or when anything is not finite.
pub fn batch_jacobian<P: Vjp + Sync, N: Vjp + Sync>(
    physics: &P,
    net: &N,
    theta: &[f64],
    batch: &[ControlSample],
    memory_budget: usize,
) -> Result<BatchJacobian, HigError> {
    let n_out = physics.n_out();
    let (rows, cols) = (batch.len() * n_out, theta.len());
    let bytes = rows * cols * std::mem::size_of::<f64>();
    if bytes > memory_budget {
        return Err(HigError::Budget { rows, cols, bytes, budget: memory_budget });
    }
    let b = batch.len() as f64;
    let mut jac = vec![0.0; rows * cols];
    let mut grad = vec![0.0; rows];
    // Each sample writes its own rows and gradient entries.
    jac.par_chunks_mut(n_out * cols).zip(grad.par_chunks_mut(n_out)).zip(batch.par_iter()).for_each(|((jrows, g), s)| {
        let u = net_eval(net, &s.target, theta);
        let mut y = vec![0.0; n_out];
        physics.forward(&s.x0, &u, &mut y);
        for k in 0..n_out {
            g[k] = 2.0 * (y[k] - s.target[k]) / b;
        }
        let mut seed = vec![0.0; n_out];
        for k in 0..n_out {
            seed.fill(0.0);
            seed[k] = 1.0;
            jrows[k * cols..(k + 1) * cols].copy_from_slice(&chain_vjp(physics, net, theta, s, &u, &mut seed));
        }
    });
    let loss = grad.iter().map(|g| (g * b / 2.0).powi(2)).sum::<f64>() / b;
    if !loss.is_finite() || jac.iter().any(|v| !v.is_finite()) {
        return Err(HigError::NonFinite);
    }
    Ok(BatchJacobian { rows, cols, jac, grad, loss })
}

/// One HIG (or Gauss-Newton) step on `theta` (in place); returns the batch
/// loss before it.
pub fn hig_step<P: Vjp + Sync, N: Vjp + Sync>(physics: &P, net: &N, theta: &mut [f64], batch: &[ControlSample], h: &Hig) -> Result<f64, HigError> {
    let j = batch_jacobian(physics, net, theta, batch, h.memory_budget)?;
    let update = diffsim_solvers::linalg::pseudo_inverse_power_apply_with(j.rows, j.cols, &j.jac, &j.grad, h.power, h.truncation, h.method())
        .map_err(|_| HigError::Svd)?;
    if update.iter().any(|v| !v.is_finite()) {
        return Err(HigError::NonFinite);
    }
    for (t, d) in theta.iter_mut().zip(&update) {
        *t -= h.lr * d;
    }
    Ok(j.loss)
}
