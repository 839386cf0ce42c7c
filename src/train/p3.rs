//! Benchmark P3 `sol1d` (`../shared/benchmarks.md`): one training
//! iteration through a 16-step unrolled coarse Burgers solver with a 1D
//! conv network correcting each step, batch 32, Adam.
//!
//! Built from the framework's parts, as a user would: the solver step
//! [`BurgersEnzyme`] (P1's scheme, Enzyme-generated VJP), the network
//! [`presets::conv_stack_1d`], [`Coupled`] with [`Coupling::Add`]
//! (`u_next = v + N(v)`, `v = step(u)`), [`batch_gradient`] (samples in
//! parallel, fixed reduction order) and [`Optimizer::adam`].

use std::time::Instant;

use rand::rngs::StdRng;
use rand::{Rng, SeedableRng};

use diffsim_solvers::burgers::Burgers1d;
use diffsim_solvers::nn::Padding;

use super::{Coupled, Coupling, Optimizer, Sample, TimeShares, batch_gradient};
use crate::nn::{Activation, Init, Net, presets};
use crate::problems::burgers::BurgersEnzyme;
use crate::rollout::{Checkpointing, RolloutError};

/// Cells of the coarse grid.
pub const N: usize = 32;
/// Samples per batch.
pub const BATCH: usize = 32;
/// Unrolled steps.
pub const UNROLL: usize = 16;

/// The solver of P3: `N = 32`, `dx = 2π/32`, `ν = 0.01`, `dt = 0.05`.
pub fn solver() -> Burgers1d {
    Burgers1d { n: N, dx: 2.0 * std::f64::consts::PI / N as f64, dt: 0.05, nu: 0.01 }
}

/// `Σ_{k=1..3} a_k·sin(k·x + φ_k)`, `a_k ∈ [−1, 1]`, `φ_k ∈ [0, 2π)` uniform.
fn sine_state(rng: &mut StdRng) -> Vec<f64> {
    let a: Vec<f64> = (0..3).map(|_| rng.random_range(-1.0..1.0)).collect();
    let phi: Vec<f64> = (0..3).map(|_| rng.random_range(0.0..std::f64::consts::TAU)).collect();
    let dx = solver().dx;
    (0..N).map(|i| (0..3).map(|k| a[k] * ((k + 1) as f64 * i as f64 * dx + phi[k]).sin()).sum()).collect()
}

/// The P3 problem: network, weights, the fixed batch and the optimizer.
#[derive(Debug)]
pub struct P3 {
    /// The solver step.
    pub step: BurgersEnzyme,
    /// `1 → 32 → 32 → 1` channels, kernel 5, periodic, tanh between.
    pub net: Net,
    /// The weights (normal·√(1/(c_in·K)), zero biases).
    pub theta: Vec<f64>,
    /// 32 initial states, each with 16 reference states (scaled by 0.5).
    pub batch: Vec<Sample>,
    /// Adam, lr 1e-3.
    pub adam: Optimizer,
}

impl P3 {
    /// The problem with data and weights drawn from `seed`.
    pub fn new(seed: u64) -> Self {
        let net = presets::conv_stack_1d(N, &[1, 32, 32, 1], 5, Padding::Periodic, Activation::Tanh).expect("the P3 network is well formed");
        let theta = net.init(&mut StdRng::seed_from_u64(seed), Init::LeCun);
        let mut rng = StdRng::seed_from_u64(seed + 1);
        let x0: Vec<Vec<f64>> = (0..BATCH).map(|_| sine_state(&mut rng)).collect();
        let batch =
            x0.into_iter().map(|x0| Sample { x0, targets: (0..UNROLL).map(|_| sine_state(&mut rng).iter().map(|v| 0.5 * v).collect()).collect() }).collect();
        Self { step: BurgersEnzyme(solver()), net, theta, batch, adam: Optimizer::adam(1e-3) }
    }

    /// Number of network parameters (5505).
    pub fn params(&self) -> usize {
        self.theta.len()
    }

    /// One iteration: the loss (mean over steps, batch and cells of
    /// `(u_t − ref_t)²`), its gradient through the 16 coupled steps of
    /// every sample, and one Adam update. Returns the loss before the
    /// update and where the time went.
    pub fn iteration(&mut self) -> Result<(f64, TimeShares), RolloutError> {
        let start = Instant::now();
        let coupled = Coupled::new(&self.step, &[], &self.net, Coupling::Add).expect("the network fits the solver");
        let steps: Vec<usize> = (1..=UNROLL).collect();
        let (loss, grad) = batch_gradient(&coupled, &self.theta, UNROLL, &steps, &self.batch, Checkpointing::Store)?;
        let t = Instant::now();
        self.adam.step(&mut self.theta, &grad);
        let mut shares = TimeShares { optimizer: t.elapsed().as_secs_f64(), ..Default::default() };
        shares.add_timers(&coupled.timers);
        shares.total = start.elapsed().as_secs_f64();
        Ok((loss, shares))
    }
}
