//! Inverse heat: SIP against Adam and plain gradient descent (the
//! published comparison of scale-invariant physics training).
//!
//! States `x*` are sums of 4 to 10 hot boxes on a 64 × 64 periodic grid
//! (as the published generator: centres in the middle 80 % of the domain,
//! half sizes uniform in [0, 10) cells per axis on 64 cells, scaled
//! with the grid, strengths uniform in [0, 1), box
//! edges anti-aliased by the covered fraction of each cell); the
//! observation is `y* = P(x*)`, diffusion to `ν·t = 8`. A small U-Net
//! `N(y*; θ)` learns to recover `x*`. All optimizers start from the same
//! weights and see the same batches (drawn on the fly from the generator);
//! the error is measured on a fixed held-out set.

use rand::rngs::StdRng;
use rand::{Rng, SeedableRng};
use rayon::prelude::*;

use crate::oscillators::Curve;
use diffsim::nn::{Activation, Net, Padding, presets};
use diffsim::op::{Float32, Forward, MeanMatched, OperatorExt, Vjp};
use diffsim::problems::heat::Heat;
use std::cell::{Cell, RefCell};
use std::ops::ControlFlow;

use crate::StudyError;
use diffsim::distributed::World;
use diffsim::train::checkpoint::Parts;
use diffsim::train::pg::{InverseSample, PgError};
use diffsim::train::{AdamParams, InverseBatch, Optimizer, Sip, TrainError, Trainer, TrainerParams, UpdateRule};

/// The comparison's settings.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct HeatParams {
    /// The physics (grid, `ν·t`, inverse damping).
    pub physics: Heat,
    /// Samples per batch.
    pub batch: usize,
    /// Updates per optimizer.
    pub iterations: usize,
    /// U-Net width (channels of its first level).
    pub width: usize,
    /// Adam's learning rate (on the physics loss).
    pub adam_lr: f64,
    /// Plain gradient descent's learning rate (on the physics loss).
    pub gd_lr: f64,
    /// SIP: Adam's learning rate on the proxy loss.
    pub sip_lr: f64,
    /// SIP: the physics step size `η`.
    pub eta: f64,
    /// Held-out samples for the error.
    pub test_samples: usize,
    /// Seed of data and weights.
    pub seed: u64,
    /// The published network instead of the small one: a 4-level U-Net
    /// of `width` filters (ReLU, zero padding, He initialisation) in
    /// float32, its prediction shifted to the observation's mean
    /// ([`diffsim::op::MeanMatched`]).
    pub published_network: bool,
}

impl HeatParams {
    /// The published setup (tum-pbs/SIP `heat/train_heat.py` and the book's
    /// notebook): the Bayesian inverse (signal prior 0.5, noise
    /// 1e-6·|y − y*|), the published network with 16 filters, batch 128,
    /// Adam and SIP at lr 1e-3; `iterations` updates each (the notebook
    /// compares after 50). Plain gradient descent at the published 2e-6 on
    /// the batch *sum*, i.e. 2.56e-4 on diffsim's batch mean.
    pub fn published(iterations: usize) -> Self {
        Self {
            physics: Heat::published().with_bayesian_inverse(diffsim::problems::heat::BayesianInverse::PUBLISHED),
            batch: 128,
            iterations,
            width: 16,
            gd_lr: 2e-6 * 128.0,
            published_network: true,
            ..Self::standard()
        }
    }

    /// The published problem (64 × 64, `ν·t = 8`), batch 16, 300 updates
    /// per optimizer, U-Net of width 8; Adam and SIP at lr 1e-3, plain
    /// gradient descent at 1e-4 (1e-2 and 1e-3 diverge).
    pub fn standard() -> Self {
        Self {
            physics: Heat::published(),
            batch: 16,
            iterations: 300,
            width: 8,
            adam_lr: 1e-3,
            gd_lr: 1e-4,
            sip_lr: 1e-3,
            eta: 1.0,
            test_samples: 32,
            seed: 1,
            published_network: false,
        }
    }
}

/// One state of 4 to 10 anti-aliased boxes on an `nx × ny` grid of unit
/// cells (values `[j·nx + i]`).
pub fn boxes(rng: &mut impl Rng, nx: usize, ny: usize) -> Vec<f64> {
    let count = 4 + (7.0 * rng.random::<f64>()) as usize;
    let mut x = vec![0.0; nx * ny];
    let size = |n: usize| n as f64;
    for _ in 0..count {
        let (lx, ly) = (size(nx), size(ny));
        let mut cx = (rng.random::<f64>() - 0.5) * 0.8 * lx + 0.5 * lx;
        let mut cy = (rng.random::<f64>() - 0.5) * 0.8 * ly + 0.5 * ly;
        // Half sizes up to 10 cells on 64 (scaled with the grid, so boxes fit).
        let (hx, hy) = (10.0 / 64.0 * lx * rng.random::<f64>(), 10.0 / 64.0 * ly * rng.random::<f64>());
        let strength = rng.random::<f64>();
        cx = cx.clamp(hx, lx - hx);
        cy = cy.clamp(hy, ly - hy);
        // The covered fraction of cell [i, i+1] along one axis.
        let cover = |i: usize, c: f64, h: f64| ((i as f64 + 1.0).min(c + h) - (i as f64).max(c - h)).max(0.0);
        for j in 0..ny {
            let fy = cover(j, cy, hy);
            if fy == 0.0 {
                continue;
            }
            for i in 0..nx {
                x[j * nx + i] += strength * fy * cover(i, cx, hx);
            }
        }
    }
    x
}

/// `count` samples `(P(x*), x*)`.
pub fn samples(physics: &Heat, rng: &mut impl Rng, count: usize) -> Vec<InverseSample> {
    (0..count)
        .map(|_| {
            let truth = boxes(rng, physics.grid.nx, physics.grid.ny);
            let mut observed = vec![0.0; truth.len()];
            physics.forward(&truth, &[], &mut observed);
            InverseSample { observed, truth }
        })
        .collect()
}

/// The network: a one-level U-Net with periodic padding and tanh, or with
/// `published_network` PhiFlow's `u_net(1, 1)` shape (4 levels of `width`
/// filters, ReLU, zero padding; the caller adds float32 and the mean
/// correction).
pub fn network(cfg: &HeatParams) -> Net {
    let (nx, ny) = (cfg.physics.grid.nx, cfg.physics.grid.ny);
    if cfg.published_network {
        presets::unet_2d_levels(nx, ny, 1, 1, cfg.width, 4, 3, Padding::Zero, Activation::Relu)
            .expect("the preset is well formed for grid sizes divisible by 8")
    } else {
        presets::unet_2d(nx, ny, 1, 1, cfg.width, 3, Padding::Periodic, Activation::Tanh).expect("the preset is well formed for even grid sizes")
    }
}

/// Which update an optimizer makes.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Method {
    /// SIP: the inverse-physics target, Adam on the proxy loss.
    Sip,
    /// Adam on the physics loss.
    Adam,
    /// Plain gradient descent on the physics loss.
    Gd,
}

impl Method {
    /// `sip`, `adam` or `gd`.
    pub fn name(self) -> &'static str {
        match self {
            Method::Sip => "sip",
            Method::Adam => "adam",
            Method::Gd => "gd",
        }
    }
}

/// What the study found ([`run`]).
#[derive(Clone, Debug, serde::Serialize, serde::Deserialize)]
pub struct HeatReport {
    /// One curve per optimizer, in [`Method::ALL`]'s order: the held-out
    /// mean L1 state error against training seconds, the x-L2 error as the
    /// second measure.
    pub curves: Vec<Curve>,
    /// The local inverse alone, `x = P⁻¹(y*)`: its mean L1 error.
    pub inverse_l1: f64,
    /// … and its x-L2 error.
    pub inverse_l2: f64,
}

impl Method {
    /// The study's optimizers, in the report's order.
    pub const ALL: [Method; 3] = [Method::Sip, Method::Adam, Method::Gd];
}

/// The study: SIP, Adam and gradient descent, each from the same network
/// on the same batches ([`compare`]), and the inverse alone. With `parts`
/// each optimizer's finished curve is saved there and read back when an
/// interrupted run is resumed. `progress(method, update)` after each
/// update.
///
/// # Errors
/// A loss, gradient or state error that is not finite, or a part that
/// cannot be read or saved.
pub fn run(cfg: &HeatParams, parts: Option<&Parts>, mut progress: impl FnMut(Method, usize)) -> Result<HeatReport, StudyError> {
    let mut curves = Vec::new();
    for m in Method::ALL {
        curves.push(crate::part(&World::single(), parts, m.name(), || -> Result<Curve, StudyError> { Ok(compare(cfg, &[m], &mut progress)?.remove(0)) })?);
    }
    let (inverse_l1, inverse_l2) = inverse_errors(cfg);
    Ok(HeatReport { curves, inverse_l1, inverse_l2 })
}

impl HeatReport {
    /// The first or last x-L2 error of a curve.
    fn x_l2(c: &Curve, last: bool) -> f64 {
        let p = if last { c.second_points.last() } else { c.second_points.first() };
        p.map_or(f64::NAN, |p| p.1)
    }

    /// The Markdown table: updates, training seconds, start and final
    /// errors per optimizer, and the inverse alone.
    pub fn table(&self) -> String {
        let mut table =
            String::from("| optimizer | updates | training s | start error | final error | start x-L2 | final x-L2 |\n|---|---|---|---|---|---|---|\n");
        for c in &self.curves {
            let seconds = c.points.last().map_or(0.0, |p| p.0);
            table.push_str(&format!(
                "| {} | {} | {seconds:.1} | {:.1} | {:.1} | {:.1} | {:.1} |\n",
                c.name,
                c.updates,
                c.points.first().map_or(f64::NAN, |p| p.1),
                c.final_loss(),
                Self::x_l2(c, false),
                Self::x_l2(c, true)
            ));
        }
        table.push_str(&format!("| the inverse alone, x = P⁻¹(y*) | – | – | – | {:.1} | – | {:.1} |\n", self.inverse_l1, self.inverse_l2));
        table
    }

    /// `optimizer,seconds,error,x_l2`, one row per recorded point.
    pub fn csv(&self) -> String {
        let mut csv = String::from("optimizer,seconds,error,x_l2\n");
        for c in &self.curves {
            for (i, (t, e)) in c.points.iter().enumerate() {
                let x2 = c.second_points.get(i).map_or(f64::NAN, |p| p.1);
                csv.push_str(&format!("{},{t:.4},{e:.6e},{x2:.6e}\n", c.name));
            }
        }
        csv
    }

    /// The one-line result: each optimizer's final error (`sip`, `adam`,
    /// `gd`), training seconds (`…_s`) and final x-L2 (`…_x_l2`), and the
    /// inverse's (`inverse`, `inverse_x_l2`).
    pub fn json(&self) -> serde_json::Map<String, serde_json::Value> {
        let mut obj = serde_json::Map::new();
        for c in &self.curves {
            obj.insert(c.name.clone(), c.final_loss().into());
            obj.insert(format!("{}_s", c.name), c.seconds.into());
            obj.insert(format!("{}_x_l2", c.name), Self::x_l2(c, true).into());
        }
        obj.insert("inverse".into(), self.inverse_l1.into());
        obj.insert("inverse_x_l2".into(), self.inverse_l2.into());
        obj
    }
}

/// Trains one network per method (same start, same batches) and records
/// the held-out state error about 30 times, against training seconds.
/// `progress(method, update)` is called after each update.
pub fn compare(cfg: &HeatParams, methods: &[Method], progress: impl FnMut(Method, usize)) -> Result<Vec<Curve>, TrainError> {
    let net = network(cfg);
    if cfg.published_network {
        let theta0 = net.init(&mut StdRng::seed_from_u64(cfg.seed), diffsim::nn::Init::He);
        train_each(cfg, &MeanMatched(Float32(net)), &theta0, methods, progress)
    } else {
        // The last layer starts at zero: every method starts from x = 0.
        let theta0 = crate::burgers::initial_params(&net, cfg.seed);
        train_each(cfg, &net, &theta0, methods, progress)
    }
}

fn train_each<N: Vjp + Sync>(
    cfg: &HeatParams,
    net: &N,
    theta0: &[f64],
    methods: &[Method],
    mut progress: impl FnMut(Method, usize),
) -> Result<Vec<Curve>, TrainError> {
    let test = test_set(cfg);
    let every = (cfg.iterations / 30).max(1);
    let mut curves = Vec::new();
    for &method in methods {
        let mut theta = theta0.to_vec();
        let data_rng = RefCell::new(StdRng::seed_from_u64(cfg.seed + 1));
        let mut rule: Box<dyn UpdateRule> = match method {
            Method::Sip => Box::new(Sip::new(cfg.eta, AdamParams { lr: cfg.sip_lr, ..AdamParams::default() })),
            Method::Adam => Box::new(Optimizer::adam(cfg.adam_lr)),
            Method::Gd => Box::new(Optimizer::sgd(cfg.gd_lr)),
        };
        let (e1, e2) = state_errors(net, &theta, &test);
        let (mut points, mut second_points) = (vec![(0.0, e1)], vec![(0.0, e2)]);
        let mut trained = 0.0;
        // Drawing a batch simulates the physics: timed apart, and not
        // counted as training.
        let drawing = Cell::new(0.0);
        let batch_at = |_: usize| {
            let t = std::time::Instant::now();
            let batch = samples(&cfg.physics, &mut data_rng.borrow_mut(), cfg.batch);
            drawing.set(t.elapsed().as_secs_f64());
            Ok(InverseBatch::new(&cfg.physics, net, batch))
        };
        let mut failed = None;
        let world = World::single();
        let trainer = Trainer::new(TrainerParams { iterations: cfg.iterations, ..TrainerParams::default() }, &world);
        trainer.run(rule.as_mut(), &mut theta, batch_at, |row, theta, _| {
            trained += row.step_seconds - drawing.get();
            progress(method, row.iteration);
            if row.iteration % every == 0 || row.iteration == cfg.iterations {
                let (e1, e2) = state_errors(net, theta, &test);
                if !(e1.is_finite() && e2.is_finite()) {
                    failed = Some(PgError::NonFinite { what: "state error", sample: 0 });
                    return ControlFlow::Break(());
                }
                points.push((trained, e1));
                second_points.push((trained, e2));
            }
            ControlFlow::Continue(())
        })?;
        if let Some(e) = failed {
            return Err(e.into());
        }
        curves.push(Curve { name: method.name().to_string(), points, updates: cfg.iterations, seconds: trained, diverged_after: None, second_points });
    }
    Ok(curves)
}

/// The held-out samples every curve and [`inverse_errors`] are measured on.
fn test_set(cfg: &HeatParams) -> Vec<InverseSample> {
    samples(&cfg.physics, &mut StdRng::seed_from_u64(cfg.seed + 1000), cfg.test_samples)
}

/// `(‖x − x*‖₁, ½‖x − x*‖₂²)` of one recovered state.
fn errors(x: &[f64], truth: &[f64]) -> (f64, f64) {
    x.iter().zip(truth).fold((0.0, 0.0), |(l1, l2), (a, b)| (l1 + (a - b).abs(), l2 + 0.5 * (a - b) * (a - b)))
}

/// The means over `data` of `recover(sample)`'s [`errors`], samples in
/// parallel and summed in order.
fn mean_errors(data: &[InverseSample], recover: impl Fn(&InverseSample) -> Vec<f64> + Sync) -> (f64, f64) {
    let per: Vec<(f64, f64)> = data.par_iter().map(|s| errors(&recover(s), &s.truth)).collect();
    let n = data.len().max(1) as f64;
    let (l1, l2) = per.iter().fold((0.0, 0.0), |(a, b), (c, d)| (a + c, b + d));
    (l1 / n, l2 / n)
}

/// The held-out errors `(L1, x-L2)` of the physics' local inverse applied
/// to each observation directly (`x = P⁻¹(y*)`, from `x = 0`): what the
/// inverse alone recovers, the level a network trained through it
/// approaches. The same held-out samples as [`compare`]'s curves.
pub fn inverse_errors(cfg: &HeatParams) -> (f64, f64) {
    use diffsim::op::LocalInverse;
    let zero = vec![0.0; cfg.physics.grid.nx * cfg.physics.grid.ny];
    mean_errors(&test_set(cfg), |s| {
        let mut x = vec![0.0; zero.len()];
        cfg.physics.local_inverse(&zero, &[], &s.observed, &mut x);
        x
    })
}

/// The held-out errors of the recovered states: the mean over samples of
/// `‖x − x*‖₁` (summed over cells; the published MAE is this over the cell
/// count) and of `½‖x − x*‖₂²` (the notebook's x-L2).
fn state_errors<N: Vjp + Sync>(net: &N, theta: &[f64], data: &[InverseSample]) -> (f64, f64) {
    mean_errors(data, |s| net.eval(&s.observed, theta))
}
