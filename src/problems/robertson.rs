//! Robertson's chemical kinetics (Robertson 1966), the classic stiff test
//! of implicit integrators: three species, rate constants eight orders of
//! magnitude apart,
//!
//! ```text
//! du₁/dt = −k₁·u₁ + k₃·u₂·u₃
//! du₂/dt =  k₁·u₁ − k₃·u₂·u₃ − k₂·u₂²
//! du₃/dt =  k₂·u₂²
//! ```
//!
//! with `k = (0.04, 3·10⁷, 10⁴)` and `u(0) = (1, 0, 0)`. The parameters are
//! the logarithms of the rates, `p = ln k`, so a fit moves them on one
//! scale. Written as the right-hand side only ([`crate::ode_system!`]); an
//! [`Integrator`](crate::implicit::Integrator) makes it a step.

use crate::implicit::OdeSystem;

/// The system (no data: three species, three log-rates).
#[derive(Clone, Copy, Debug, Default)]
pub struct Robertson;

impl OdeSystem for Robertson {
    fn n(&self) -> usize {
        3
    }
    fn n_params(&self) -> usize {
        3
    }
}

/// The published rate constants `k₁, k₂, k₃`.
pub const RATES: [f64; 3] = [0.04, 3.0e7, 1.0e4];

/// The initial state.
pub const START: [f64; 3] = [1.0, 0.0, 0.0];

/// `p = ln k` for the published rates.
pub fn log_rates() -> [f64; 3] {
    RATES.map(f64::ln)
}

/// `du = f(u, p)`, `p = ln k`.
pub fn robertson_rates(_: &Robertson, u: &[f64], p: &[f64], du: &mut [f64]) {
    let (k1, k2, k3) = (p[0].exp(), p[1].exp(), p[2].exp());
    let (a, b, c) = (u[0], u[1], u[2]);
    du[0] = -k1 * a + k3 * b * c;
    du[1] = k1 * a - k3 * b * c - k2 * b * b;
    du[2] = k2 * b * b;
}

crate::ode_system!(Robertson => robertson_rates);

/// The times at which ODEPACK's LSODE documentation (Hindmarsh 1983)
/// prints this problem's solution, [`LSODE_STATES`].
pub const LSODE_TIMES: [f64; 3] = [0.4, 4.0, 40.0];

/// The solution printed by ODEPACK's LSODE documentation at
/// [`LSODE_TIMES`] (relative tolerance 10⁻⁴, absolute 10⁻⁶, 10⁻¹⁰, 10⁻⁶,
/// single precision): an external reference for the integrators.
pub const LSODE_STATES: [[f64; 3]; 3] =
    [[9.851726e-01, 3.386406e-05, 1.479357e-02], [9.055142e-01, 2.240418e-05, 9.446344e-02], [7.158050e-01, 9.184616e-06, 2.841858e-01]];
