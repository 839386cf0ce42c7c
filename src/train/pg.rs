//! Physical-gradient updates: scale-invariant physics (SIP) training
//! (Holl, Koltun & Thuerey, "Scale-invariant Learning by Physics
//! Inversion", NeurIPS 2022; the Physics-based Deep Learning book,
//! chapter "Scale-invariant physics training").
//!
//! The setting is an inverse problem: observations `y* = P(x*)`, a network
//! `x = N(y*; θ)` that should recover `x*`, and the physics loss
//! `L = (1/B)·Σ_b ½‖P(N(y*_b; θ)) − y*_b‖²`.
//!
//! - **Plain gradients** ([`physics_loss_and_gradient`], for SGD or Adam):
//!   `∂L/∂θ` by the VJPs of `P` and `N` (differentiable-physics training).
//! - **SIP** ([`sip_gradient`]): per sample, `x = N(y*)`, `y = P(x)`, the
//!   physics' local inverse gives `Δx = P⁻¹(η·(y* − y); x)` and the proxy
//!   target `x̃ = x + Δx`; the network is trained (by Adam, say) on
//!   `L̃ = (1/B)·Σ_b ½‖N(y*_b; θ) − x̃_b‖²` with `x̃` held fixed. Only the
//!   network is differentiated: the physics enters through its inverse.
//!
//! Requires: `P` with a [`LocalInverse`] (an exact or regularised inverse,
//! e.g. [`crate::problems::heat::Heat`], or [`crate::op::GaussNewton`] for
//! any operator with a VJP and a JVP), and `N` with a VJP.

use rayon::prelude::*;

use crate::op::{LocalInverse, OpError, OperatorExt, Vjp};

/// One example of the inverse problem.
#[derive(Clone, Debug)]
pub struct InverseSample {
    /// The observation `y*` (the network's input).
    pub observed: Vec<f64>,
    /// The true state `x*` (used only to measure the error).
    pub truth: Vec<f64>,
}

/// A physical-gradient step that could not be made.
#[derive(Clone, Copy, Debug, PartialEq, thiserror::Error)]
pub enum PgError {
    /// A non-finite loss, target or gradient.
    #[error("non-finite {what} in sample {sample} of the batch")]
    NonFinite {
        /// Which quantity.
        what: &'static str,
        /// The sample's index in the batch.
        sample: usize,
    },
    /// The physics failed (e.g. a solve did not converge) in some sample of
    /// the batch.
    #[error("the physics failed in the batch: {0}")]
    Physics(OpError),
}

/// The physics' recorded failure, if any, after a batch.
pub fn physics_ok<P: crate::op::Forward + ?Sized>(physics: &P) -> Result<(), PgError> {
    physics.take_error().map_or(Ok(()), |e| Err(PgError::Physics(e)))
}

/// What a SIP step computed.
#[derive(Clone, Debug)]
pub struct SipGradient {
    /// The physics loss `L` at the current parameters.
    pub physics_loss: f64,
    /// The proxy loss `L̃`.
    pub proxy_loss: f64,
    /// `∂L̃/∂θ`.
    pub grad: Vec<f64>,
}

fn finite(v: &[f64], what: &'static str, sample: usize) -> Result<(), PgError> {
    if v.iter().all(|x| x.is_finite()) { Ok(()) } else { Err(PgError::NonFinite { what, sample }) }
}

/// `(x, y, ½‖y − y*‖²)` of sample `i`; a non-finite prediction is an
/// error before the physics sees it.
fn predict<P: Vjp, N: Vjp>(physics: &P, net: &N, theta: &[f64], s: &InverseSample, i: usize) -> Result<(Vec<f64>, Vec<f64>, f64), PgError> {
    let x = net.eval(&s.observed, theta);
    finite(&x, "network prediction", i)?;
    let mut y = vec![0.0; physics.n_out()];
    physics.forward(&x, &[], &mut y);
    let loss = 0.5 * y.iter().zip(&s.observed).map(|(a, b)| (a - b) * (a - b)).sum::<f64>();
    Ok((x, y, loss))
}

/// One sample's `(loss, proxy loss, gradient)`.
type Part = (f64, f64, Vec<f64>);

/// `(Σ losses, Σ gradients)` / B in sample order, or the first error.
fn reduce(parts: Vec<Result<Part, PgError>>, n_theta: usize) -> Result<Part, PgError> {
    let b = parts.len().max(1) as f64;
    let (mut l1, mut l2, mut g) = (0.0, 0.0, vec![0.0; n_theta]);
    for part in parts {
        let (a, c, d) = part?;
        l1 += a;
        l2 += c;
        for (s, v) in g.iter_mut().zip(&d) {
            *s += v;
        }
    }
    g.iter_mut().for_each(|v| *v /= b);
    Ok((l1 / b, l2 / b, g))
}

fn net_vjp<N: Vjp>(net: &N, input: &[f64], theta: &[f64], seed: &mut [f64]) -> Vec<f64> {
    let mut din = vec![0.0; net.n_in()];
    let mut dtheta = vec![0.0; theta.len()];
    net.vjp(input, theta, seed, &mut din, &mut dtheta);
    dtheta
}

/// The physics loss `L` and its gradient `∂L/∂θ` (plain differentiable
/// physics), samples in parallel and reduced in order.
pub fn physics_loss_and_gradient<P: Vjp + Sync, N: Vjp + Sync>(
    physics: &P,
    net: &N,
    theta: &[f64],
    batch: &[InverseSample],
) -> Result<(f64, Vec<f64>), PgError> {
    let parts = batch
        .par_iter()
        .enumerate()
        .map(|(i, s)| {
            let (x, y, loss) = predict(physics, net, theta, s, i)?;
            let mut seed: Vec<f64> = y.iter().zip(&s.observed).map(|(a, b)| a - b).collect();
            let mut dx = vec![0.0; x.len()];
            physics.vjp(&x, &[], &mut seed, &mut dx, &mut []);
            let g = net_vjp(net, &s.observed, theta, &mut dx);
            finite(&g, "gradient", i)?;
            Ok((loss, 0.0, g))
        })
        .collect();
    physics_ok(physics)?;
    let (loss, _, g) = reduce(parts, theta.len())?;
    if !loss.is_finite() {
        return Err(PgError::NonFinite { what: "physics loss", sample: 0 });
    }
    Ok((loss, g))
}

/// The SIP gradient `∂L̃/∂θ` with the physics step size `η`, samples in
/// parallel and reduced in order.
pub fn sip_gradient<P: LocalInverse + Vjp + Sync, N: Vjp + Sync>(
    physics: &P,
    net: &N,
    theta: &[f64],
    batch: &[InverseSample],
    eta: f64,
) -> Result<SipGradient, PgError> {
    let parts = batch
        .par_iter()
        .enumerate()
        .map(|(i, s)| {
            let (x, y, loss) = predict(physics, net, theta, s, i)?;
            let dy: Vec<f64> = s.observed.iter().zip(&y).map(|(t, a)| eta * (t - a)).collect();
            let mut step = vec![0.0; x.len()];
            physics.local_inverse(&x, &[], &dy, &mut step);
            finite(&step, "inverse-physics step", i)?;
            // x̃ = x + Δx, so ∂L̃/∂x = x − x̃ = −Δx.
            let proxy = 0.5 * step.iter().map(|d| d * d).sum::<f64>();
            let mut seed: Vec<f64> = step.iter().map(|d| -d).collect();
            let g = net_vjp(net, &s.observed, theta, &mut seed);
            finite(&g, "gradient", i)?;
            Ok((loss, proxy, g))
        })
        .collect();
    physics_ok(physics)?;
    let (physics_loss, proxy_loss, grad) = reduce(parts, theta.len())?;
    Ok(SipGradient { physics_loss, proxy_loss, grad })
}

/// The mean over samples of `‖N(y*) − x*‖₁` (summed over values): how far
/// the recovered states are from the true ones.
pub fn state_error<N: Vjp + Sync>(net: &N, theta: &[f64], data: &[InverseSample]) -> f64 {
    let errors: Vec<f64> = data
        .par_iter()
        .map(|s| {
            let x = net.eval(&s.observed, theta);
            x.iter().zip(&s.truth).map(|(a, b)| (a - b).abs()).sum::<f64>()
        })
        .collect();
    errors.iter().sum::<f64>() / data.len().max(1) as f64
}
