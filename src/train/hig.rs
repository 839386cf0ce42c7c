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
//!
//! Over the ranks of a [`World`] ([`hig_step_over`],
//! [`loss_and_gradient_over`]) each rank computes the rows of its share of
//! the batch; rank 0 gathers them, decomposes the whole Jacobian once and
//! sends the update (or the failure) to every rank: the same step as one
//! process, bit for bit.

use rayon::prelude::*;

use crate::distributed::World;
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

/// Samples per parallel task of the physics in [`loss_and_gradient_over`]:
/// the batch split evenly over rayon's threads, in whole groups of
/// [`crate::op::LANES`] (each task wakes a thread: on the linear problem,
/// 0.7 ms an update, a third of the time went to waking and parking
/// threads when the batch was cut into 32-sample tasks).
fn physics_chunk(samples: usize) -> usize {
    let per_thread = samples.div_ceil(rayon::current_num_threads().max(1));
    per_thread.div_ceil(crate::op::LANES).max(1) * crate::op::LANES
}

/// `(L, ∂L/∂θ)` over a batch by one VJP per sample (for gradient-based
/// optimizers such as Adam), reduced in sample order.
pub fn loss_and_gradient<P: Vjp + Sync, N: Vjp + Sync>(physics: &P, net: &N, theta: &[f64], batch: &[ControlSample]) -> (f64, Vec<f64>) {
    loss_and_gradient_over(&World::single(), physics, net, theta, batch, batch.len())
}

/// [`loss_and_gradient`] of a batch of `batch_len` samples shared among
/// the ranks of `world`: this rank evaluates the network on `mine` (its
/// [`World::share`]) in one batched pass, runs the physics and its VJP on
/// each thread's share of the samples at once ([`crate::op::Forward::forward_each`],
/// [`Vjp::vjp_each`]), and every rank receives every sample's loss,
/// network input and control adjoint; then every rank takes the network's
/// VJP over the whole batch at once ([`Vjp::vjp_batch`]: the parameters'
/// gradient summed in sample order, no per-sample gradient formed). The
/// result is one process's, bit for bit, for any number of ranks.
pub fn loss_and_gradient_over<P: Vjp + Sync, N: Vjp + Sync>(
    world: &World,
    physics: &P,
    net: &N,
    theta: &[f64],
    mine: &[ControlSample],
    batch_len: usize,
) -> (f64, Vec<f64>) {
    let b = batch_len as f64;
    let (n_in, n_u, n_y) = (net.n_in(), net.n_out(), physics.n_out());
    let mut inputs = Vec::with_capacity(mine.len() * n_in);
    for s in mine {
        inputs.extend_from_slice(&s.target);
    }
    let mut us = vec![0.0; mine.len() * n_u];
    net.forward_batch(&inputs, theta, &mut us);
    // In parallel over chunks of samples: the physics of the chunk at once
    // (`forward_each`, `vjp_each`: an operator with a lane form runs
    // several samples side by side), each sample's loss and `∂L/∂u`.
    let n_x = physics.n_in();
    let mut x0s = Vec::with_capacity(mine.len() * n_x);
    for s in mine {
        x0s.extend_from_slice(&s.x0);
    }
    let mut losses = vec![0.0; mine.len()];
    let mut dus = vec![0.0; mine.len() * n_u];
    let chunk = physics_chunk(mine.len());
    let chunks = losses.par_chunks_mut(chunk).zip(dus.par_chunks_mut(chunk * n_u));
    chunks.zip(mine.par_chunks(chunk)).zip(x0s.par_chunks(chunk * n_x)).zip(us.par_chunks(chunk * n_u)).for_each(|((((loss, du), samples), x0), u)| {
        let mut y = vec![0.0; samples.len() * n_y];
        physics.forward_each(x0, u, &mut y);
        // `y` becomes the seed `∂L/∂y` in place.
        for ((l, s), y) in loss.iter_mut().zip(samples).zip(y.chunks_exact_mut(n_y.max(1))) {
            *l = y.iter().zip(&s.target).map(|(a, t)| (a - t) * (a - t)).sum::<f64>() / b;
            for (a, t) in y.iter_mut().zip(&s.target) {
                *a = 2.0 * (*a - t) / b;
            }
        }
        let mut dx = vec![0.0; x0.len()];
        physics.vjp_each(x0, u, &mut y, &mut dx, du);
    });
    if world.size() > 1 {
        // Every rank receives every sample's [loss, network input, ∂L/∂u].
        let width = 1 + n_in + n_u;
        let mut rows = Vec::with_capacity(mine.len() * width);
        for (k, loss) in losses.iter().enumerate() {
            rows.push(*loss);
            rows.extend_from_slice(&inputs[k * n_in..(k + 1) * n_in]);
            rows.extend_from_slice(&dus[k * n_u..(k + 1) * n_u]);
        }
        let all = world.all_gather(&rows);
        losses.clear();
        inputs.clear();
        dus.clear();
        for row in all.chunks_exact(width) {
            losses.push(row[0]);
            inputs.extend_from_slice(&row[1..1 + n_in]);
            dus.extend_from_slice(&row[1 + n_in..]);
        }
    }
    // The loss summed in sample order, as one process sums it.
    let loss = losses.iter().fold(0.0, |acc, l| acc + l);
    let mut dtheta = vec![0.0; theta.len()];
    let mut dxs = vec![0.0; inputs.len()];
    net.vjp_batch(&inputs, theta, &mut dus, &mut dxs, &mut dtheta);
    (loss, dtheta)
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
    let (rows, cols) = within_budget(physics.n_out(), batch.len(), theta.len(), memory_budget)?;
    let (jac, grad) = jacobian_rows(physics, net, theta, batch, batch.len());
    finish(rows, cols, jac, grad, batch.len())
}

/// The Jacobian's shape, refused above the budget.
fn within_budget(n_out: usize, batch_len: usize, cols: usize, memory_budget: usize) -> Result<(usize, usize), HigError> {
    let rows = batch_len * n_out;
    let bytes = rows * cols * std::mem::size_of::<f64>();
    if bytes > memory_budget {
        return Err(HigError::Budget { rows, cols, bytes, budget: memory_budget });
    }
    Ok((rows, cols))
}

/// The Jacobian rows and `∂L/∂y` of the samples `mine` of a batch of
/// `batch_len`, sample after sample.
fn jacobian_rows<P: Vjp + Sync, N: Vjp + Sync>(physics: &P, net: &N, theta: &[f64], mine: &[ControlSample], batch_len: usize) -> (Vec<f64>, Vec<f64>) {
    let (n_out, cols) = (physics.n_out(), theta.len());
    let b = batch_len as f64;
    let mut jac = vec![0.0; mine.len() * n_out * cols];
    let mut grad = vec![0.0; mine.len() * n_out];
    // Each sample writes its own rows and gradient entries.
    jac.par_chunks_mut(n_out * cols).zip(grad.par_chunks_mut(n_out)).zip(mine.par_iter()).for_each(|((jrows, g), s)| {
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
    (jac, grad)
}

/// The whole batch's Jacobian with its loss, checked for finite values.
fn finish(rows: usize, cols: usize, jac: Vec<f64>, grad: Vec<f64>, batch_len: usize) -> Result<BatchJacobian, HigError> {
    let b = batch_len as f64;
    let loss = grad.iter().map(|g| (g * b / 2.0).powi(2)).sum::<f64>() / b;
    if !loss.is_finite() || jac.iter().any(|v| !v.is_finite()) {
        return Err(HigError::NonFinite);
    }
    Ok(BatchJacobian { rows, cols, jac, grad, loss })
}

/// The update `J^{−power}·∂L/∂y` of a batch Jacobian.
pub(crate) fn update_of(j: &BatchJacobian, h: &Hig) -> Result<Vec<f64>, HigError> {
    let update = diffsim_solvers::linalg::pseudo_inverse_power_apply_with(j.rows, j.cols, &j.jac, &j.grad, h.power, h.truncation, h.method())
        .map_err(|_| HigError::Svd)?;
    if update.iter().any(|v| !v.is_finite()) {
        return Err(HigError::NonFinite);
    }
    Ok(update)
}

/// One HIG (or Gauss-Newton) step on `theta` (in place); returns the batch
/// loss before it.
pub fn hig_step<P: Vjp + Sync, N: Vjp + Sync>(physics: &P, net: &N, theta: &mut [f64], batch: &[ControlSample], h: &Hig) -> Result<f64, HigError> {
    hig_step_over(&World::single(), physics, net, theta, batch, batch.len(), h)
}

/// [`hig_step`] on a batch of `batch_len` samples shared among the ranks
/// of `world`: this rank computes the Jacobian rows of `mine` (its
/// [`World::share`]); rank 0 gathers the rows in sample order, checks
/// them, decomposes the whole Jacobian (once, there) and sends the update,
/// or the failure, to every rank. Every rank takes the same step as one
/// process, or returns the same error.
#[allow(clippy::too_many_arguments)]
pub fn hig_step_over<P: Vjp + Sync, N: Vjp + Sync>(
    world: &World,
    physics: &P,
    net: &N,
    theta: &mut [f64],
    mine: &[ControlSample],
    batch_len: usize,
    h: &Hig,
) -> Result<f64, HigError> {
    let (loss, update) = update_over(world, physics, net, theta, mine, batch_len, h)?;
    for (t, d) in theta.iter_mut().zip(&update) {
        *t -= h.lr * d;
    }
    Ok(loss)
}

/// The batch loss and the update `J^{−power}·∂L/∂y` of [`hig_step_over`]
/// (before the step size), the same on every rank.
pub(crate) fn update_over<P: Vjp + Sync, N: Vjp + Sync>(
    world: &World,
    physics: &P,
    net: &N,
    theta: &[f64],
    mine: &[ControlSample],
    batch_len: usize,
    h: &Hig,
) -> Result<(f64, Vec<f64>), HigError> {
    let n_out = physics.n_out();
    let (rows, cols) = within_budget(n_out, batch_len, theta.len(), h.memory_budget)?;
    let (jac, grad) = jacobian_rows(physics, net, theta, mine, batch_len);
    // The loss and the update of the whole batch's Jacobian.
    let decompose = |jac, grad| finish(rows, cols, jac, grad, batch_len).and_then(|j| Ok((j.loss, update_of(&j, h)?)));
    if world.size() == 1 {
        decompose(jac, grad)
    } else {
        // Each rank's rows, then its gradient entries; on rank 0 the
        // blocks are put back in sample order.
        let block: Vec<f64> = jac.into_iter().chain(grad).collect();
        let on_root = world.gather(&block).map(|all| {
            let (mut jac, mut grad) = (Vec::with_capacity(rows * cols), Vec::with_capacity(rows));
            let mut at = 0;
            for r in 0..world.size() {
                let n = world.share_of(r, batch_len).len() * n_out;
                jac.extend_from_slice(&all[at..at + n * cols]);
                grad.extend_from_slice(&all[at + n * cols..at + n * cols + n]);
                at += n * cols + n;
            }
            decompose(jac, grad)
        });
        // [0, loss, update…] or [1] (the SVD failed) or [2] (non-finite).
        let message = match on_root {
            Some(Ok((loss, update))) => [0.0, loss].into_iter().chain(update).collect(),
            Some(Err(HigError::Svd)) => vec![1.0],
            Some(Err(_)) => vec![2.0],
            None => Vec::new(),
        };
        let message = world.broadcast(message);
        if message[0] == 0.0 {
            Ok((message[1], message[2..].to_vec()))
        } else if message[0] == 1.0 {
            Err(HigError::Svd)
        } else {
            Err(HigError::NonFinite)
        }
    }
}
