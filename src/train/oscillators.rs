//! HIG against Adam on the coupled oscillators, in equal wall-clock budgets
//! (the published comparison: 4096 samples from U[0, 1)⁴, the target is the
//! start state, network 4 → 20 → 20 → 20 → controls with tanh).

use rand::rngs::StdRng;
use rand::{Rng, SeedableRng};

use super::Optimizer;
use super::hig::{ControlSample, Hig, HigError, hig_step, loss_and_gradient};
use crate::nn::{Activation, Init, Net, presets};
use crate::op::Forward;
use crate::problems::oscillators::Oscillators;

/// One comparison's settings.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct OscConfig {
    /// The physics.
    pub problem: Oscillators,
    /// Training samples.
    pub samples: usize,
    /// HIG's batch, step size and truncation.
    pub hig_batch: usize,
    /// HIG's settings.
    pub hig: Hig,
    /// Adam's batch.
    pub adam_batch: usize,
    /// Adam's learning rate.
    pub adam_lr: f64,
    /// Training seconds per optimizer.
    pub budget_s: f64,
    /// Seed of data and weights.
    pub seed: u64,
}

impl OscConfig {
    /// The linear problem as published: HIG batch 32, η = 1, truncation
    /// 1e-10; Adam batch 256, lr 1e-3.
    pub fn linear(budget_s: f64) -> Self {
        Self {
            problem: Oscillators::linear(),
            samples: 4096,
            hig_batch: 32,
            hig: Hig { lr: 1.0, truncation: 1e-10, memory_budget: 1 << 30 },
            adam_batch: 256,
            adam_lr: 1e-3,
            budget_s,
            seed: 1,
        }
    }

    /// The nonlinear problem: HIG batch 128, η = 1, truncation 1e-6; Adam
    /// batch 512, lr 3e-4.
    pub fn nonlinear(budget_s: f64) -> Self {
        Self {
            problem: Oscillators::nonlinear(),
            hig_batch: 128,
            hig: Hig { lr: 1.0, truncation: 1e-6, memory_budget: 1 << 30 },
            adam_batch: 512,
            adam_lr: 3e-4,
            ..Self::linear(budget_s)
        }
    }
}

/// Loss versus training time of one optimizer.
#[derive(Clone, Debug, serde::Serialize, serde::Deserialize)]
pub struct Curve {
    /// `hig` or `adam`.
    pub name: String,
    /// `(training seconds, loss on the whole training set)`.
    pub points: Vec<(f64, f64)>,
    /// Updates taken.
    pub updates: usize,
}

impl Curve {
    /// The last loss.
    pub fn final_loss(&self) -> f64 {
        self.points.last().map_or(f64::NAN, |p| p.1)
    }
}

/// The mean over samples of `‖y − y*‖²`.
pub fn dataset_loss(physics: &Oscillators, net: &Net, theta: &[f64], data: &[ControlSample]) -> f64 {
    let mut u = vec![0.0; physics.steps];
    let mut y = [0.0; 4];
    let mut total = 0.0;
    for s in data {
        net.forward(&s.target, theta, &mut u);
        physics.forward(&s.x0, &u, &mut y);
        total += y.iter().zip(&s.target).map(|(a, t)| (a - t) * (a - t)).sum::<f64>();
    }
    total / data.len() as f64
}

/// Trains the same initial network with HIG and with Adam, each for
/// `budget_s` seconds of training (evaluation excluded), recording the
/// training-set loss about 40 times along the way.
pub fn compare(cfg: &OscConfig) -> Result<Vec<Curve>, HigError> {
    let mut rng = StdRng::seed_from_u64(cfg.seed);
    let data: Vec<ControlSample> = (0..cfg.samples)
        .map(|_| {
            let x: Vec<f64> = (0..4).map(|_| rng.random::<f64>()).collect();
            ControlSample { x0: x.clone(), target: x }
        })
        .collect();
    let net = presets::mlp(&[4, 20, 20, 20, cfg.problem.steps], Activation::Tanh).expect("the preset is well formed");
    let theta0 = net.init(&mut StdRng::seed_from_u64(cfg.seed + 1), Init::Glorot);
    let every = cfg.budget_s / 40.0;
    let mut curves = Vec::new();
    // (Two passes by flag: a by-value array of `&str` can crash Enzyme's
    // type analysis in this crate; docs/pitfalls.md.)
    for use_hig in [true, false] {
        let name = if use_hig { "hig" } else { "adam" };
        let mut theta = theta0.clone();
        let mut adam = Optimizer::adam(cfg.adam_lr);
        let batch = if use_hig { cfg.hig_batch } else { cfg.adam_batch };
        let mut points = vec![(0.0, dataset_loss(&cfg.problem, &net, &theta, &data))];
        let (mut trained, mut next, mut updates, mut at) = (0.0, every, 0, 0);
        while trained < cfg.budget_s {
            if at + batch > data.len() {
                at = 0;
            }
            let b = &data[at..at + batch];
            at += batch;
            let t = std::time::Instant::now();
            if use_hig {
                hig_step(&cfg.problem, &net, &mut theta, b, &cfg.hig)?;
            } else {
                let (_, g) = loss_and_gradient(&cfg.problem, &net, &theta, b);
                adam.step(&mut theta, &g);
            }
            trained += t.elapsed().as_secs_f64();
            updates += 1;
            if trained >= next || trained >= cfg.budget_s {
                let l = dataset_loss(&cfg.problem, &net, &theta, &data);
                if !l.is_finite() {
                    return Err(HigError::NonFinite);
                }
                points.push((trained, l));
                next += every;
            }
        }
        curves.push(Curve { name: name.to_string(), points, updates });
    }
    Ok(curves)
}
