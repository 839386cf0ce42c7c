//! Solver-in-the-loop on Burgers (Um et al., NeurIPS 2020): a network
//! corrects a coarse solver toward a downsampled fine reference (the study
//! itself, generic over the problem, is [`crate::sol`]).
//!
//! - Reference: P1's scheme on `N_f = 256` cells with P1's time step
//!   `dt_f`; every `4` fine steps it is downsampled to `N = 32` cells by
//!   averaging each 8 fine cells.
//! - Source: the same scheme on the coarse grid with `dt = 4·dt_f`.
//! - Corrected: `u_{t+1} = v + N(v; θ)`, `v = source(u_t)` ([`diffsim::train::Coupling::Add`]).
//! - Training variants (same network, same number of updates): PRE (one
//!   step, supervised on reference pairs), NOISE (PRE with Gaussian input
//!   noise), SOL-k (unrolled `k` corrected steps from a reference state,
//!   loss at every step, gradient through all of them).
//! - Evaluation: rollouts from held-out reference initial states, relative
//!   L2 error against the reference per step.

use std::f64::consts::TAU;

use rand::Rng;
use rand::rngs::StdRng;

use diffsim_solvers::burgers::Burgers1d;

use crate::sol::SolProblem;
pub use crate::sol::{
    EvalError, LogRow, Method, StudyError, StudyParams, TimeShares, TrainData, TrainParams, Trajectory, VariantResult, evaluate, initial_params, mean, study,
    train,
};
use diffsim::nn::{Activation, Net};
use diffsim::problems::burgers::BurgersEnzyme;

/// The grids and time steps of the study.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Setup {
    /// The reference grid.
    pub fine: Burgers1d,
    /// The coarse grid (the source solver).
    pub coarse: Burgers1d,
    /// Fine steps per coarse step.
    pub time_factor: usize,
    /// Sine modes in an initial state.
    pub modes: usize,
}

impl Setup {
    /// Coarse grid of `n` cells on `[0, 2π)`, the reference `factor` times
    /// finer, viscosity `nu`, `dt_f = min(0.25·dx_f, 0.25·dx_f²/ν)` (P1's
    /// formula), coarse `dt = time_factor·dt_f`.
    pub fn new(n: usize, factor: usize, time_factor: usize, nu: f64, modes: usize) -> Self {
        let nf = n * factor;
        let dxf = TAU / nf as f64;
        let dtf = (0.25 * dxf).min(0.25 * dxf * dxf / nu);
        let fine = Burgers1d { n: nf, dx: dxf, dt: dtf, nu };
        let coarse = Burgers1d { n, dx: TAU / n as f64, dt: time_factor as f64 * dtf, nu };
        Self { fine, coarse, time_factor, modes }
    }

    /// The study's setup: 32 coarse cells, 8× finer reference, 4 fine steps
    /// per coarse step, ν = 0.01, three sine modes.
    pub fn standard() -> Self {
        Self::new(32, 8, 4, 0.01, 3)
    }

    /// A random fine initial state `Σ_{k=1..modes} a_k·sin(k·x + φ_k)`,
    /// `a_k ∈ U[−1, 1]`, `φ_k ∈ U[0, 2π)`.
    pub fn initial(&self, rng: &mut impl Rng) -> Vec<f64> {
        let coeffs: Vec<(f64, f64)> = (0..self.modes).map(|_| (rng.random_range(-1.0..1.0), rng.random_range(0.0..TAU))).collect();
        (0..self.fine.n)
            .map(|i| {
                let x = i as f64 * self.fine.dx;
                coeffs.iter().enumerate().map(|(k, (a, phi))| a * ((k + 1) as f64 * x + phi).sin()).sum()
            })
            .collect()
    }

    /// The fine state averaged over each block of fine cells.
    pub fn downsample(&self, fine: &[f64]) -> Vec<f64> {
        let f = self.fine.n / self.coarse.n;
        fine.chunks_exact(f).map(|c| c.iter().sum::<f64>() / f as f64).collect()
    }

    /// The reference trajectory: coarse states `0..=steps` from a fine
    /// initial state.
    pub fn reference(&self, u0: &[f64], steps: usize) -> Vec<Vec<f64>> {
        let mut u = u0.to_vec();
        let mut tmp = vec![0.0; u.len()];
        let mut out = vec![self.downsample(&u)];
        for _ in 0..steps {
            for _ in 0..self.time_factor {
                diffsim_solvers::burgers::step(&self.fine, &u, &mut tmp);
                std::mem::swap(&mut u, &mut tmp);
            }
            out.push(self.downsample(&u));
        }
        out
    }

    /// `count` reference trajectories of `steps` coarse steps from random
    /// initial states.
    pub fn dataset(&self, count: usize, steps: usize, rng: &mut impl Rng) -> Vec<Vec<Vec<f64>>> {
        (0..count).map(|_| self.reference(&self.initial(rng), steps)).collect()
    }
}

impl SolProblem for Setup {
    type Solver = BurgersEnzyme;

    /// The source solver as an operator.
    fn source(&self) -> BurgersEnzyme {
        BurgersEnzyme(self.coarse)
    }

    fn dataset(&self, count: usize, steps: usize, rng: &mut StdRng) -> Vec<Trajectory> {
        Setup::dataset(self, count, steps, rng)
    }

    fn dataset_share(&self, count: usize, steps: usize, rng: &mut StdRng, share: std::ops::Range<usize>) -> Vec<Trajectory> {
        let initial: Vec<Vec<f64>> = (0..count).map(|_| self.initial(rng)).collect();
        initial[share].iter().map(|u0| self.reference(u0, steps)).collect()
    }

    fn with_viscosity(&self, nu: f64) -> Self {
        Setup::new(self.coarse.n, self.fine.n / self.coarse.n, self.time_factor, nu, self.modes)
    }
}

/// The activation of the study's network.
pub const STUDY_ACTIVATION: Activation = Activation::Relu;

impl StudyParams<Setup> {
    /// The study as specified: 64 training and 16 test trajectories,
    /// 128-step evaluation, PRE / NOISE / SOL-4 / SOL-16, 6000 updates of
    /// batch 16 with Adam, learning rate 1e-3 decaying to 1e-5 (cosine).
    /// `quick`: 1500 updates, 32 + 8 trajectories.
    pub fn standard(quick: bool) -> Self {
        let iterations = if quick { 1500 } else { 6000 };
        let setup = Setup::standard();
        let net = correction_net("conv-stack", setup.coarse.n, 32, STUDY_ACTIVATION).expect("the preset is well formed");
        Self {
            setup,
            train: if quick { 32 } else { 64 },
            train_base: if quick { 32 } else { 64 },
            test: if quick { 8 } else { 16 },
            train_steps: 128 + 16,
            eval_steps: 128,
            methods: Method::standard(),
            settings: TrainParams::adam(16, iterations),
            net,
        }
    }
}

/// A correction network for `n` cells by name: `conv-stack` (P3's shape
/// at width 32: 1 → `width` → `width` → 1 channels, kernel 5), `unet`
/// ([`presets::unet_1d`], kernel 5) or `resnet` ([`presets::resnet_1d`], 3
/// blocks, kernel 5); periodic padding throughout, activation `act`. A zero
/// width is refused by [`Net::new`].
///
/// [`presets::unet_1d`]: diffsim::nn::presets::unet_1d
/// [`presets::resnet_1d`]: diffsim::nn::presets::resnet_1d
pub fn correction_net(name: &str, n: usize, width: usize, act: Activation) -> Result<Net, String> {
    use diffsim::nn::{Padding::Periodic, presets};
    let net = match name {
        "conv-stack" => presets::conv_stack_1d(n, &[1, width, width, 1], 5, Periodic, act),
        "unet" => presets::unet_1d(n, 1, 1, width, 5, Periodic, act),
        "resnet" => presets::resnet_1d(n, 1, 1, width, 3, 5, Periodic, act),
        _ => return Err(format!("expected conv-stack, unet or resnet, got {name:?}")),
    };
    net.map_err(|e| e.to_string())
}
