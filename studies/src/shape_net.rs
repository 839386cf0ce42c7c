//! A network that proposes minimum-drag shapes: the Reynolds number ↦ the
//! free Fourier coefficients of a body of fixed area in the 2D-1 channel,
//! trained through the steady solver with the drag of its proposed shape as
//! the loss (the learning version of [`diffsim_solvers::flow::drag_shape`]).
//!
//! Per training Reynolds number, the loss is the proposed shape's `c_D`
//! over the cylinder's; its gradient with respect to the network's weights
//! is the adjoint gradient of the steady drag
//! ([`diffsim_solvers::flow::SteadyFlow::force_gradient`]), projected on
//! the constant-area surface, passed back through the network's VJP.
//! Adam updates; each Reynolds number keeps its last steady velocity as
//! Newton's next start.

use std::time::Instant;

use rand::SeedableRng;
use rand::rngs::StdRng;

use diffsim_solvers::flow::FlowError;
use diffsim_solvers::flow::ShapeError;
use diffsim_solvers::flow::cylinder::DIAMETER;
use diffsim_solvers::flow::drag_shape::{DragShapeParams, Stream, drag_coefficient, optimise, reduced_gradient, shape_at_area, steady_drag};

use diffsim::nn::{Activation, Init, Layer, Net};
use diffsim::op::{Forward, Vjp};
use std::cell::RefCell;
use std::ops::ControlFlow;

use diffsim::distributed::World;
use diffsim::train::{FnObjective, Optimizer, TrainError, Trainer, TrainerParams};

/// What to train.
#[derive(Clone, Debug, PartialEq)]
pub struct ShapeNetParams {
    /// Grid cells per diameter.
    pub cells_per_d: usize,
    /// Highest Fourier mode `K` (coefficients 2..=K, cosine and sine).
    pub modes: usize,
    /// Reynolds numbers trained on.
    pub train_re: Vec<f64>,
    /// Held-out Reynolds numbers, compared with shapes optimised one by one.
    pub test_re: Vec<f64>,
    /// Adam updates (each one steady solve per training Reynolds number).
    pub iterations: usize,
    /// Adam's learning rate.
    pub lr: f64,
    /// Seed of the initial weights.
    pub seed: u64,
}

/// One held-out Reynolds number.
#[derive(Clone, Debug, PartialEq, serde::Serialize, serde::Deserialize)]
pub struct HeldOut {
    /// Reynolds number.
    pub re: f64,
    /// The cylinder's drag coefficient.
    pub cd_cylinder: f64,
    /// The network's shape's drag coefficient.
    pub cd_network: f64,
    /// The shape optimised for this Reynolds number alone (L-BFGS).
    pub cd_optimised: f64,
    /// Seconds: the network's proposal and one steady solve.
    pub time_network_s: f64,
    /// Seconds: the optimisation one by one.
    pub time_optimised_s: f64,
}

/// How the training went.
#[derive(Clone, Debug, PartialEq, serde::Serialize, serde::Deserialize)]
pub struct ShapeNetReport {
    /// Mean `c_D/c_D,cylinder` over the training Reynolds numbers, per update
    /// (before it).
    pub losses: Vec<f64>,
    /// Training time.
    pub train_s: f64,
    /// The held-out comparison.
    pub held_out: Vec<HeldOut>,
}

/// Why training stopped.
#[derive(Debug, thiserror::Error)]
pub enum ShapeNetError {
    /// A steady solve failed.
    #[error("Re {re}: {source}")]
    Flow {
        /// The Reynolds number.
        re: f64,
        /// What the solver said.
        source: FlowError,
    },
    /// The network proposed a shape that is not a body in the domain.
    #[error("Re {re}: the network proposed a shape that is not a body in the channel: {source}")]
    Shape {
        /// The Reynolds number.
        re: f64,
        /// What is wrong with it.
        source: ShapeError,
    },
    /// Training stopped (a loss or gradient that is not finite).
    #[error("training: {0}")]
    Train(String),
}

/// Peak inflow of the channel for Reynolds number `re` (ν = 10⁻³, `Re =
/// (2/3)·u_max·D/ν`).
pub fn u_max_for(re: f64) -> f64 {
    1.5 * re * 1e-3 / DIAMETER
}

/// The largest magnitude of each cosine coefficient `a₂…a_K` (`a₂` up to
/// 0.6 of the radius, `a₃` 0.12, the others 0.24): the network's last layer
/// is a `tanh` scaled by these, which keeps `r₀` real for `K ≤ 30` and its
/// proposals bodies for `K ≤ 4` (the steady solve validates them anyway).
fn bounds(modes: usize) -> Vec<f64> {
    (2..=modes)
        .map(|k| match k {
            2 => 0.03,
            3 => 0.006,
            _ => 0.012,
        })
        .collect()
}

/// The network: `[1, 16, 16, K−1]`, tanh between and after the layers. It
/// proposes the cosine coefficients only (bodies symmetric about the
/// channel's axis, as the one-by-one optima nearly are).
fn network(modes: usize) -> Net {
    let out = modes - 1;
    Net::new(vec![
        Layer::Dense { n_in: 1, n_out: 16 },
        Layer::Act { f: Activation::Tanh, n: 16 },
        Layer::Dense { n_in: 16, n_out: 16 },
        Layer::Act { f: Activation::Tanh, n: 16 },
        Layer::Dense { n_in: 16, n_out: out },
        Layer::Act { f: Activation::Tanh, n: out },
    ])
    .expect("the network is well formed")
}

/// The network's input: the Reynolds number scaled to about `[−1, 1]`.
fn input(re: f64) -> [f64; 1] {
    [(re - 25.0) / 15.0]
}

/// The free coefficients `q = (a₂…a_K, b₂…b_K)` the network proposes at
/// `re` (the sine ones 0).
fn propose(net: &Net, theta: &[f64], re: f64, bound: &[f64]) -> Vec<f64> {
    let mut o = vec![0.0; bound.len()];
    net.forward(&input(re), theta, &mut o);
    o.iter().zip(bound).map(|(v, b)| v * b).chain(std::iter::repeat_n(0.0, bound.len())).collect()
}

/// Trains the network and compares it with one-by-one optimisations on the
/// held-out Reynolds numbers.
pub fn train(opts: &ShapeNetParams, mut progress: impl FnMut(usize, f64)) -> Result<ShapeNetReport, ShapeNetError> {
    let net = network(opts.modes);
    let bound = bounds(opts.modes);
    let mut theta = net.init(&mut StdRng::seed_from_u64(opts.seed), Init::Glorot);
    let area = std::f64::consts::PI * 0.25 * DIAMETER * DIAMETER;
    let per_d = opts.cells_per_d;
    let flow_err = |re: f64| {
        move |e: FlowError| match e {
            FlowError::Shape(source) => ShapeNetError::Shape { re, source },
            source => ShapeNetError::Flow { re, source },
        }
    };
    // Per training Re: the channel, the cylinder's drag, Newton's start.
    let mut samples = Vec::new();
    for &re in &opts.train_re {
        let setting = Stream::Channel.setting(per_d, u_max_for(re)).map_err(flow_err(re))?;
        let (cd_cylinder, _, x) = steady_drag(&setting, &setting.cylinder, &setting.start).map_err(flow_err(re))?;
        samples.push((re, setting, cd_cylinder, x));
    }
    // The objective: the mean over the training Re of c_D / c_D(cylinder)
    // at the network's shape, its gradient by the steady adjoint and the
    // network's VJP; each steady solve starts from the last state.
    let samples = RefCell::new(samples);
    let failure = RefCell::new(None);
    let n_params = theta.len();
    let objective = |_: usize| {
        Ok(FnObjective {
            n: n_params,
            f: |theta: &[f64]| {
                let mut grad = vec![0.0; theta.len()];
                let mut loss = 0.0;
                for (re, setting, cd_cylinder, x) in samples.borrow_mut().iter_mut() {
                    let q = propose(&net, theta, *re, &bound);
                    let shape = shape_at_area(area, opts.modes, setting.center, &q).expect("the output bounds keep ½Σq² below the area's r₀²");
                    // (Validated by the steady solve before any derivative runs.)
                    let (cd, full, state) = match steady_drag(setting, &shape, x) {
                        Ok(v) => v,
                        Err(e) => {
                            let e = flow_err(*re)(e);
                            let message = e.to_string();
                            *failure.borrow_mut() = Some(e);
                            return Err(TrainError::Objective(message));
                        }
                    };
                    *x = state;
                    let n = opts.train_re.len() as f64;
                    loss += cd / *cd_cylinder / n;
                    // dL/dq (its cosine part), then through the scaled tanh
                    // output into the weights.
                    let mut seed: Vec<f64> =
                        reduced_gradient(&full, &q, area, opts.modes).iter().zip(&bound).map(|(g, b)| g * b / (*cd_cylinder * n)).collect();
                    let mut dx = [0.0];
                    net.vjp(&input(*re), theta, &mut seed, &mut dx, &mut grad);
                }
                Ok((loss, grad))
            },
        })
    };
    let mut adam = Optimizer::adam(opts.lr);
    let mut losses = Vec::with_capacity(opts.iterations);
    let start = Instant::now();
    let world = World::single();
    let trainer = Trainer::new(TrainerParams { iterations: opts.iterations, ..TrainerParams::default() }, &world);
    let run = trainer.run(&mut adam, &mut theta, objective, |row, _, _| {
        losses.push(row.loss);
        progress(row.iteration - 1, row.loss);
        ControlFlow::Continue(())
    });
    if let Some(e) = failure.into_inner() {
        return Err(e);
    }
    run.map_err(|e| ShapeNetError::Train(e.to_string()))?;
    let train_s = start.elapsed().as_secs_f64();
    let mut held_out = Vec::new();
    for &re in &opts.test_re {
        let u = u_max_for(re);
        let setting = Stream::Channel.setting(per_d, u).map_err(flow_err(re))?;
        let cd_cylinder = drag_coefficient(&setting, &setting.cylinder).map_err(flow_err(re))?;
        let t = Instant::now();
        let q = propose(&net, &theta, re, &bound);
        let shape = shape_at_area(area, opts.modes, setting.center, &q).expect("the output bounds keep ½Σq² below the area's r₀²");
        let cd_network = drag_coefficient(&setting, &shape).map_err(flow_err(re))?;
        let time_network_s = t.elapsed().as_secs_f64();
        let t = Instant::now();
        let one = optimise(&DragShapeParams {
            stream: Stream::Channel,
            cells_per_d: per_d,
            modes: opts.modes,
            u_max: u,
            max_iterations: 60,
            gradient_reduction: 100.0,
            sampling_iterations: 0,
        })
        .map_err(flow_err(re))?;
        held_out.push(HeldOut { re, cd_cylinder, cd_network, cd_optimised: one.cd_end, time_network_s, time_optimised_s: t.elapsed().as_secs_f64() });
    }
    Ok(ShapeNetReport { losses, train_s, held_out })
}

impl ShapeNetReport {
    /// The one-line result: the training's first and last loss and
    /// seconds, and per held-out Reynolds number the three drag
    /// coefficients and the two times (`diffsim experiment drag-net
    /// --json` adds the settings and the wall time).
    pub fn json(&self) -> serde_json::Map<String, serde_json::Value> {
        let mut obj = serde_json::Map::new();
        obj.insert("loss_start".into(), self.losses.first().copied().into());
        obj.insert("loss_end".into(), self.losses.last().copied().into());
        obj.insert("train_s".into(), self.train_s.into());
        let held: Vec<serde_json::Value> = self
            .held_out
            .iter()
            .map(|h| serde_json::json!({"re": h.re, "cd_cylinder": h.cd_cylinder, "cd_network": h.cd_network, "cd_optimised": h.cd_optimised, "time_network_s": h.time_network_s, "time_optimised_s": h.time_optimised_s}))
            .collect();
        obj.insert("held_out".into(), held.into());
        obj
    }

    /// The Markdown table of the held-out comparison.
    pub fn table(&self) -> String {
        let mut t = String::from("| held-out Re | cylinder c_D | network c_D (time) | optimised one by one c_D (time) |\n|---|---|---|---|\n");
        for h in &self.held_out {
            t.push_str(&format!(
                "| {} | {:.4} | {:.4} ({:.1} s) | {:.4} ({:.1} s) |\n",
                h.re, h.cd_cylinder, h.cd_network, h.time_network_s, h.cd_optimised, h.time_optimised_s
            ));
        }
        t
    }
}
