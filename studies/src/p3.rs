//! Benchmark P3 `sol1d` (`docs/benchmarks.md`): one training
//! iteration through a 16-step unrolled coarse Burgers solver with a 1D
//! conv network correcting each step, batch 32, Adam.
//!
//! Built from the framework's parts, as a user would: the solver step
//! [`BurgersEnzyme`] (P1's scheme, Enzyme-generated VJP), the network
//! [`presets::conv_stack_1d`], [`Coupled`] with [`Coupling::Add`]
//! (`u_next = v + N(v)`, `v = step(u)`), [`batch_gradient`] (samples in
//! parallel, fixed reduction order) and [`Optimizer::adam`]; in `f64`,
//! in `f32`, or mixed (the network in `f32` behind [`Float32`]).

use std::time::Instant;

use rand::rngs::StdRng;
use rand::{Rng, SeedableRng};

use diffsim_solvers::burgers::Burgers1d;
use diffsim_solvers::nn::Padding;

use diffsim::nn::{Activation, Init, Net, presets};
use diffsim::op::{Float32, Jvp, Real, Vjp};
use diffsim::problems::burgers::BurgersEnzyme;
use diffsim::rollout::{Checkpointing, RolloutError};
use diffsim::train::{Coupled, Coupling, Optimizer, Sample, TimeShares, batch_gradient};

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

/// The precision P3 runs in.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Dtype {
    /// Everything in `f64`.
    F64,
    /// Everything in `f32`: states, weights, solver, network, gradients
    /// (the Adam moments are kept in `f64`, see [`Optimizer::step`]).
    F32,
    /// The network in `f32` ([`Float32`]), the solver, the chaining and
    /// the master weights in `f64`.
    Mixed,
}

impl Dtype {
    /// `"f64"`, `"f32"` or `"mixed"`.
    pub fn name(self) -> &'static str {
        match self {
            Dtype::F64 => "f64",
            Dtype::F32 => "f32",
            Dtype::Mixed => "mixed",
        }
    }
}

impl std::str::FromStr for Dtype {
    type Err = String;
    fn from_str(s: &str) -> Result<Self, String> {
        match s {
            "f64" => Ok(Dtype::F64),
            "f32" => Ok(Dtype::F32),
            "mixed" => Ok(Dtype::Mixed),
            _ => Err(format!("expected f64, f32 or mixed, got {s:?}")),
        }
    }
}

/// The P3 problem: network, weights, the fixed batch and the optimizer.
#[derive(Debug)]
pub struct P3 {
    /// The solver step.
    pub step: BurgersEnzyme,
    /// `1 → 32 → 32 → 1` channels, kernel 5, periodic, tanh between.
    pub net: Net,
    /// The weights (normal·√(1/(c_in·K)), zero biases): the live ones in
    /// `f64` and mixed precision.
    pub theta: Vec<f64>,
    /// The live weights in `f32` (the same draw, rounded).
    pub theta32: Vec<f32>,
    /// 32 initial states, each with 16 reference states (scaled by 0.5).
    pub batch: Vec<Sample>,
    /// The batch rounded to `f32`.
    pub batch32: Vec<Sample<f32>>,
    /// Adam, lr 1e-3.
    pub adam: Optimizer,
    /// The precision of [`P3::iteration`].
    pub dtype: Dtype,
}

impl P3 {
    /// The problem with data and weights drawn from `seed`, run in `dtype`.
    pub fn new(seed: u64, dtype: Dtype) -> Self {
        let net = presets::conv_stack_1d(N, &[1, 32, 32, 1], 5, Padding::Periodic, Activation::Tanh).expect("the P3 network is well formed");
        let theta = net.init(&mut StdRng::seed_from_u64(seed), Init::LeCun);
        let mut rng = StdRng::seed_from_u64(seed + 1);
        let x0: Vec<Vec<f64>> = (0..BATCH).map(|_| sine_state(&mut rng)).collect();
        let batch: Vec<Sample> =
            x0.into_iter().map(|x0| Sample { x0, targets: (0..UNROLL).map(|_| sine_state(&mut rng).iter().map(|v| 0.5 * v).collect()).collect() }).collect();
        let round = |v: &[f64]| v.iter().map(|&a| a as f32).collect::<Vec<f32>>();
        let batch32 = batch.iter().map(|s| Sample { x0: round(&s.x0), targets: s.targets.iter().map(|t| round(t)).collect() }).collect();
        let theta32 = round(&theta);
        Self { step: BurgersEnzyme(solver()), net, theta, theta32, batch, batch32, adam: Optimizer::adam(1e-3), dtype }
    }

    /// Number of network parameters (5505).
    pub fn params(&self) -> usize {
        self.theta.len()
    }

    /// The current weights as `f64` (whichever precision is live).
    pub fn weights(&self) -> Vec<f64> {
        match self.dtype {
            Dtype::F32 => self.theta32.iter().map(|&a| a as f64).collect(),
            Dtype::F64 | Dtype::Mixed => self.theta.clone(),
        }
    }

    /// One iteration: the loss (mean over steps, batch and cells of
    /// `(u_t − ref_t)²`), its gradient through the 16 coupled steps of
    /// every sample, and one Adam update. Returns the loss before the
    /// update and where the time went.
    pub fn iteration(&mut self) -> Result<(f64, TimeShares), RolloutError> {
        match self.dtype {
            Dtype::F64 => iterate(&self.step, &self.net, &mut self.theta, &self.batch, &mut self.adam),
            Dtype::F32 => iterate(&self.step, &self.net, &mut self.theta32, &self.batch32, &mut self.adam),
            Dtype::Mixed => iterate(&self.step, &Float32(self.net.clone()), &mut self.theta, &self.batch, &mut self.adam),
        }
    }
}

/// One P3 iteration in precision `R` with the network `net`.
fn iterate<R: Real, N: Vjp<R> + Jvp<R> + Sync>(
    step: &BurgersEnzyme,
    net: &N,
    theta: &mut [R],
    batch: &[Sample<R>],
    adam: &mut Optimizer,
) -> Result<(f64, TimeShares), RolloutError>
where
    BurgersEnzyme: Vjp<R> + Jvp<R>,
{
    let start = Instant::now();
    let coupled = Coupled::new(step, &[], net, Coupling::Add).expect("the network fits the solver");
    let steps: Vec<usize> = (1..=UNROLL).collect();
    let (loss, grad) = batch_gradient(&coupled, theta, UNROLL, &steps, batch, Checkpointing::Store)?;
    let t = Instant::now();
    adam.step(theta, &grad);
    let mut shares = TimeShares { optimizer: t.elapsed().as_secs_f64(), ..Default::default() };
    shares.add_timers(&coupled.timers);
    shares.total = start.elapsed().as_secs_f64();
    Ok((loss, shares))
}
