//! What accuracy costs: schemes run against exact solutions.
//!
//! - [`burgers`]: viscous Burgers on a periodic line, P1's fused upwind
//!   scheme or an operator split (upwind / semi-Lagrangian / MacCormack
//!   advection, then explicit or implicit diffusion), against the Cole–Hopf
//!   solution ([`diffsim_solvers::exact::ColeHopf`]).
//! - [`flow`]: the 2D schemes of [`diffsim::fluids`] on a periodic box: the
//!   Taylor–Green vortex (advection, viscosity, pressure projection),
//!   translation of a smooth profile by a constant velocity, and a Fourier
//!   mode of the heat equation.
//! - [`observed_orders`]: the order of convergence a sequence of grids shows.
//! - [`pareto`]: measurements of error, time and memory, and the
//!   configurations on the front of error versus time (`diffsim pareto`).
//! - [`stability`]: the hard cases (stiff diffusion, shocks, long
//!   rollouts, ill-conditioned solves, near-singular Jacobians, NaN
//!   detection) that `diffsim stability` reports.
//!
//! Every run checks its state once per step and stops with
//! [`AccuracyError::NonFinite`] (the step and the stage) instead of passing
//! a NaN on.

pub mod burgers;
pub mod flow;
pub mod pareto;
pub mod stability;

use thiserror::Error;

use diffsim::op::OpError;

/// Diffusion in time: explicit (forward Euler, stable up to its limit) or
/// implicit (backward Euler, solved by conjugate gradients to a relative
/// tolerance).
#[derive(Clone, Copy, Debug, PartialEq)]
pub enum Diffusion {
    /// Forward Euler; the time step is limited to keep it stable.
    Explicit,
    /// Backward Euler with CG to this relative tolerance.
    Implicit {
        /// Relative residual at which CG stops.
        tolerance: f64,
    },
}

impl std::fmt::Display for Diffusion {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        match self {
            Diffusion::Explicit => f.write_str("explicit"),
            Diffusion::Implicit { .. } => f.write_str("implicit"),
        }
    }
}

/// Why a run did not produce a solution.
#[derive(Debug, Error, Clone, PartialEq)]
pub enum AccuracyError {
    /// A setting is out of its range.
    #[error("invalid {what}: {reason}")]
    Invalid {
        /// The setting.
        what: &'static str,
        /// What is wrong.
        reason: String,
    },
    /// An operator failed (a solve that did not converge, an explicit step
    /// beyond its stability limit).
    #[error("{stage} at step {step}: {error}")]
    Operator {
        /// The stage of the step (advection, diffusion, pressure).
        stage: &'static str,
        /// The step (0-based).
        step: usize,
        /// What failed.
        error: OpError,
    },
    /// A NaN or infinity appeared.
    #[error("non-finite value after the {stage} of step {step}")]
    NonFinite {
        /// The stage that produced it.
        stage: &'static str,
        /// The step (0-based).
        step: usize,
    },
    /// A viscous flow solve failed.
    #[error("{0}")]
    Flow(#[from] diffsim_solvers::flow::FlowError),
}

pub(crate) use diffsim::rollout::all_finite;

/// `‖a − b‖₂ / ‖b‖₂`.
pub fn relative_l2(a: &[f64], b: &[f64]) -> f64 {
    let (mut d, mut r) = (0.0, 0.0);
    for (x, y) in a.iter().zip(b) {
        d += (x - y) * (x - y);
        r += y * y;
    }
    (d / r).sqrt()
}

/// Observed orders of convergence between consecutive runs: for cell widths
/// `h` and errors `e`, `log(e_k/e_{k+1}) / log(h_k/h_{k+1})`.
pub fn observed_orders(h: &[f64], e: &[f64]) -> Vec<f64> {
    h.windows(2).zip(e.windows(2)).map(|(h, e)| (e[0] / e[1]).ln() / (h[0] / h[1]).ln()).collect()
}

/// Validates a positive finite setting.
pub(crate) fn positive(what: &'static str, v: f64) -> Result<(), AccuracyError> {
    if v.is_finite() && v > 0.0 { Ok(()) } else { Err(AccuracyError::Invalid { what, reason: format!("must be positive and finite, got {v}") }) }
}

/// Number of steps and the step that reach `t_end` exactly with steps of at
/// most `dt_max`.
pub(crate) fn steps_to(t_end: f64, dt_max: f64) -> (usize, f64) {
    let steps = (t_end / dt_max).ceil().max(1.0) as usize;
    (steps, t_end / steps as f64)
}
