//! The heat equation on a periodic 2D grid, diffused to `ν·t` exactly in
//! Fourier space ([`diffsim_solvers::spectral`]): the inverse-heat problem of
//! scale-invariant physics training (Holl, Koltun & Thuerey, NeurIPS 2022;
//! 64 × 64 cells of size 1, `ν·t = 8`).
//!
//! The map `y = P(x)` is linear and symmetric (a real, even multiplier on
//! each Fourier mode), so its VJP and JVP are `P` itself. Its
//! [`LocalInverse`] is the damped spectral inverse `f/(f² + ε²)` per mode
//! (`f = exp(−ν·t·|k|²)`): modes that diffusion has not drowned are
//! inverted, the rest are left out, and nothing is amplified beyond
//! `1/(2ε)`. Or, with [`Heat::with_bayesian_inverse`], the published
//! inverse: each mode inverted as far as the probability that it carries
//! signal rather than noise allows ([`BayesianInverse`]).

pub use diffsim_solvers::spectral::BayesianInverse;
use diffsim_solvers::spectral::{Heat2d, heat, heat_inverse, heat_inverse_bayesian};

use crate::op::{Forward, Jvp, LocalInverse, Operator, Vjp};

/// Exact periodic diffusion as an operator `x ↦ P(x)` (no parameters).
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Heat {
    /// Grid and amount of diffusion.
    pub grid: Heat2d,
    /// Regularisation `ε` of the Tikhonov inverse.
    pub epsilon: f64,
    /// When set, the local inverse is this Bayesian one instead.
    pub bayesian: Option<BayesianInverse>,
}

impl Heat {
    /// The published problem: 64 × 64 cells of size 1, `ν·t = 8`, with
    /// `ε = 10⁻³` (amplification at most 500).
    pub fn published() -> Self {
        Self::new(64, 64, 8.0, 1e-3)
    }

    /// `nx × ny` cells of size 1, diffusion `ν·t`, inverse damping `ε`.
    pub fn new(nx: usize, ny: usize, nu_t: f64, epsilon: f64) -> Self {
        Self { grid: Heat2d { nx, ny, dx: 1.0, nu_t }, epsilon, bayesian: None }
    }

    /// The same physics with the Bayesian local inverse.
    pub fn with_bayesian_inverse(self, settings: BayesianInverse) -> Self {
        Self { bayesian: Some(settings), ..self }
    }

    fn cells(&self) -> usize {
        self.grid.nx * self.grid.ny
    }
}

impl Operator for Heat {
    fn n_in(&self) -> usize {
        self.cells()
    }
    fn n_out(&self) -> usize {
        self.cells()
    }
}

impl Forward for Heat {
    fn forward(&self, x: &[f64], _p: &[f64], y: &mut [f64]) {
        heat(&self.grid, x, y);
    }
}

impl Vjp for Heat {
    fn vjp(&self, _x: &[f64], _p: &[f64], dy: &mut [f64], dx: &mut [f64], _dp: &mut [f64]) {
        let mut t = vec![0.0; self.cells()];
        heat(&self.grid, dy, &mut t);
        for (a, b) in dx.iter_mut().zip(&t) {
            *a += b;
        }
        dy.fill(0.0);
    }
}

impl Jvp for Heat {
    fn jvp(&self, x: &[f64], _p: &[f64], tx: &[f64], _tp: &[f64], y: &mut [f64], ty: &mut [f64]) {
        heat(&self.grid, x, y);
        heat(&self.grid, tx, ty);
    }
}

impl LocalInverse for Heat {
    fn local_inverse(&self, _x: &[f64], _p: &[f64], dy: &[f64], dx: &mut [f64]) {
        match &self.bayesian {
            Some(b) => heat_inverse_bayesian(&self.grid, b, dy, dx),
            None => heat_inverse(&self.grid, self.epsilon, dy, dx),
        }
    }
}
