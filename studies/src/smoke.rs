//! Inverse smoke: SIP with the reverse-time inverse of P2's solver
//! against Adam on the differentiable-physics gradient.
//!
//! States `x*` are 2 to 4 round smoke blobs in the lower half of P2's
//! closed box (centres anywhere there, radii `N/16` to `N/8`, strengths 0.5
//! to 1, edges anti-aliased); the observation is `y* = P(x*)`, the smoke
//! after `T` steps of P2's solver from rest ([`SmokeRise`]): risen, spread
//! and curled by its own buoyancy. A U-Net `N(y*; θ)` (float32, the physics
//! in float64) learns to recover `x*`:
//!
//! - **SIP**: `x̃ = x + P⁻¹(y* − P(x); x)`, the reverse-time simulation of
//!   the miss along the predicted trajectory ([`LocalInverse`] of
//!   [`SmokeRise`]); Adam on `½‖N(y*) − x̃‖²`.
//! - **Adam**: Adam on the physics loss `½‖P(N(y*)) − y*‖²`, its gradient
//!   through every step (Enzyme for the explicit part, the implicit adjoint
//!   of the solves).
//!
//! Both start from the same weights (the last layer zero: `x = 0`), see the
//! same batches (drawn on the fly) and train for the same wall time. The
//! errors are measured on a fixed held-out set: of the reconstructed
//! initial smoke, and of the final smoke re-simulated from it, each the
//! mean absolute error per cell.

use rand::rngs::StdRng;
use rand::{Rng, SeedableRng};
use rayon::prelude::*;

use crate::oscillators::Curve;
use diffsim::nn::{Activation, Net, Padding, presets};
use diffsim::op::{Float32, Forward, LocalInverse, OperatorExt, PerThread, Refined, Vjp};
use diffsim::problems::smoke::SmokeRise;
use std::cell::{Cell, RefCell};
use std::ops::ControlFlow;

use diffsim::distributed::World;
use diffsim::train::pg::{InverseSample, PgError, physics_ok};
use diffsim::train::trainer::Row;
use diffsim::train::{AdamParams, InverseBatch, Optimizer, Sip, TrainError, Trainer, TrainerParams};

/// The comparison's settings.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct SmokeParams {
    /// Cells per side.
    pub n: usize,
    /// Solver steps `T` from the initial to the observed smoke.
    pub steps: usize,
    /// Samples per batch.
    pub batch: usize,
    /// U-Net filters per level.
    pub width: usize,
    /// U-Net levels (`n` divisible by `2^(levels−1)`).
    pub levels: usize,
    /// Adam's learning rate on the physics loss.
    pub adam_lr: f64,
    /// SIP: Adam's learning rate on the proxy loss.
    pub sip_lr: f64,
    /// SIP: the physics step size `η`.
    pub eta: f64,
    /// SIP: defect-correction sweeps after each reverse-time inverse step
    /// ([`Refined`]; 0 for the inverse as it is).
    pub refine: usize,
    /// Training seconds per method (evaluations excluded).
    pub seconds: f64,
    /// Held-out samples for the errors.
    pub test_samples: usize,
    /// Seed of data and weights.
    pub seed: u64,
}

impl SmokeParams {
    /// 32 × 32 cells, 16 steps, batch 16, a 3-level U-Net of 8 filters,
    /// Adam and SIP at lr 1e-3 (η = 1), 120 s each, 16 held-out samples.
    pub fn standard() -> Self {
        Self { n: 32, steps: 16, batch: 16, width: 8, levels: 3, adam_lr: 1e-3, sip_lr: 1e-3, eta: 1.0, refine: 0, seconds: 120.0, test_samples: 16, seed: 1 }
    }

    /// A quick look: 16 × 16 cells, 16 steps, batch 8, a 2-level U-Net of
    /// 4 filters, 10 s each, 8 held-out samples.
    pub fn quick() -> Self {
        Self { n: 16, batch: 8, width: 4, levels: 2, seconds: 10.0, test_samples: 8, ..Self::standard() }
    }
}

/// One initial smoke field of 2 to 4 round blobs on `n × n` cells (values
/// `[j·n + i]`): centres in the lower half, away from the walls by the
/// radius; radii uniform in `[n/16, n/8]`; strengths uniform in `[0.5, 1]`;
/// the edge anti-aliased over one cell; overlapping blobs add up to at
/// most 1.
pub fn blobs(rng: &mut impl Rng, n: usize) -> Vec<f64> {
    let count = rng.random_range(2..=4);
    let l = n as f64;
    let mut s = vec![0.0; n * n];
    for _ in 0..count {
        let r = l / 16.0 + rng.random::<f64>() * l / 16.0;
        let cx = r + 1.0 + rng.random::<f64>() * (l - 2.0 * r - 2.0);
        let cy = r + 1.0 + rng.random::<f64>() * (0.5 * l - 2.0 * r - 1.0).max(0.0);
        let strength = 0.5 + 0.5 * rng.random::<f64>();
        for j in 0..n {
            for i in 0..n {
                let d = ((i as f64 + 0.5 - cx).powi(2) + (j as f64 + 0.5 - cy).powi(2)).sqrt();
                let cover = (r + 0.5 - d).clamp(0.0, 1.0);
                let c = j * n + i;
                s[c] = (s[c] + strength * cover).min(1.0);
            }
        }
    }
    s
}

/// The physics, one [`SmokeRise`] per worker thread.
pub type Physics = PerThread<SmokeRise>;

/// The physics of `cfg`.
pub fn physics(cfg: &SmokeParams) -> Physics {
    PerThread::new(|| SmokeRise::new(cfg.n, cfg.steps))
}

/// `count` samples `(P(x*), x*)`: the states drawn in order from `rng`,
/// the observations simulated in parallel.
pub fn samples(physics: &Physics, n: usize, rng: &mut impl Rng, count: usize) -> Result<Vec<InverseSample>, PgError> {
    let truths: Vec<Vec<f64>> = (0..count).map(|_| blobs(rng, n)).collect();
    let out = truths
        .into_par_iter()
        .map(|truth| {
            let mut observed = vec![0.0; truth.len()];
            physics.forward(&truth, &[], &mut observed);
            InverseSample { observed, truth }
        })
        .collect();
    physics_ok(physics)?;
    Ok(out)
}

/// The network: a U-Net of `levels` levels and `width` filters (ReLU,
/// zero padding), one channel in and out.
pub fn network(cfg: &SmokeParams) -> Net {
    presets::unet_2d_levels(cfg.n, cfg.n, 1, 1, cfg.width, cfg.levels, 3, Padding::Zero, Activation::Relu)
        .expect("the preset is well formed when n is divisible by 2^(levels-1)")
}

/// Which update a run makes.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum SmokeMethod {
    /// SIP: the reverse-time target, Adam on the proxy loss.
    Sip,
    /// Adam on the physics loss.
    Adam,
}

impl SmokeMethod {
    /// `sip` or `adam`.
    pub fn name(self) -> &'static str {
        match self {
            SmokeMethod::Sip => "sip",
            SmokeMethod::Adam => "adam",
        }
    }
}

/// One method's run: its curves and its reconstructions of the first
/// held-out samples.
#[derive(Clone, Debug, serde::Serialize, serde::Deserialize)]
pub struct SmokeRun {
    /// `points`: `(training seconds, MAE of the initial smoke)`;
    /// `second_points`: the MAE of the re-simulated final smoke.
    pub curve: Curve,
    /// The final network's reconstructions of the first held-out samples.
    pub shown: Vec<Vec<f64>>,
}

/// What [`compare`] measured.
#[derive(Clone, Debug)]
pub struct SmokeComparison {
    /// One run per method asked for, in that order.
    pub runs: Vec<SmokeRun>,
    /// The held-out samples (the pictures show the first few).
    pub test: Vec<InverseSample>,
}

/// How many held-out reconstructions a run keeps.
pub const SHOWN: usize = 4;

/// Trains one network per method for `cfg.seconds` of training time each
/// (same start, same batch sequence) and records the held-out errors about
/// 30 times. `progress(method, trained seconds)` is called after each
/// update.
pub fn compare(cfg: &SmokeParams, methods: &[SmokeMethod], mut progress: impl FnMut(SmokeMethod, f64)) -> Result<SmokeComparison, TrainError> {
    let physics = physics(cfg);
    let refined = Refined { op: &physics, sweeps: cfg.refine };
    let net = Float32(network(cfg));
    let theta0 = crate::burgers::initial_params(&net.0, cfg.seed);
    let test = test_set(cfg, &physics)?;
    let every = cfg.seconds / 30.0;
    let mut runs = Vec::new();
    for &method in methods {
        let mut theta = theta0.clone();
        let data_rng = RefCell::new(StdRng::seed_from_u64(cfg.seed + 1));
        let (e1, e2) = errors(&physics, &net, &theta, &test)?;
        let (mut points, mut second_points) = (vec![(0.0, e1)], vec![(0.0, e2)]);
        let (mut trained, mut updates, mut next) = (0.0, 0, every);
        // Drawing a batch simulates the physics: timed apart, and not
        // counted as training.
        let drawing = Cell::new(0.0);
        let draw = || -> Result<Vec<InverseSample>, TrainError> {
            let t = std::time::Instant::now();
            let batch = samples(&physics, cfg.n, &mut data_rng.borrow_mut(), cfg.batch)?;
            drawing.set(t.elapsed().as_secs_f64());
            Ok(batch)
        };
        let mut failed = None;
        let mut observe = |row: &Row, theta: &[f64]| {
            trained += row.step_seconds - drawing.get();
            updates = row.iteration;
            progress(method, trained);
            if trained >= next || trained >= cfg.seconds {
                match errors(&physics, &net, theta, &test) {
                    Ok((e1, e2)) => {
                        points.push((trained, e1));
                        second_points.push((trained, e2));
                    }
                    Err(e) => {
                        failed = Some(e);
                        return ControlFlow::Break(());
                    }
                }
                next = trained + every;
            }
            if trained >= cfg.seconds { ControlFlow::Break(()) } else { ControlFlow::Continue(()) }
        };
        // Until the budget is spent: the count is only a bound.
        let iterations = if cfg.seconds > 0.0 { usize::MAX / 4 } else { 0 };
        let world = World::single();
        let trainer = Trainer::new(TrainerParams { iterations, ..TrainerParams::default() }, &world);
        // SIP takes its targets from the refined inverse; Adam sees the
        // plain physics loss.
        match method {
            SmokeMethod::Sip => {
                let mut rule = Sip::new(cfg.eta, AdamParams { lr: cfg.sip_lr, ..AdamParams::default() });
                trainer.run(&mut rule, &mut theta, |_| Ok(InverseBatch::new(&refined, &net, draw()?)), |row, th, _| observe(row, th))?;
            }
            SmokeMethod::Adam => {
                let mut rule = Optimizer::adam(cfg.adam_lr);
                trainer.run(&mut rule, &mut theta, |_| Ok(InverseBatch::new(&physics, &net, draw()?)), |row, th, _| observe(row, th))?;
            }
        }
        if let Some(e) = failed {
            return Err(e.into());
        }
        let shown = test.iter().take(SHOWN).map(|s| net.eval(&s.observed, &theta)).collect();
        let curve = Curve { name: method.name().to_string(), points, updates, seconds: trained, diverged_after: None, second_points };
        runs.push(SmokeRun { curve, shown });
    }
    Ok(SmokeComparison { runs, test })
}

/// The held-out samples every curve and [`inverse_alone`] are measured on.
fn test_set(cfg: &SmokeParams, physics: &Physics) -> Result<Vec<InverseSample>, PgError> {
    samples(physics, cfg.n, &mut StdRng::seed_from_u64(cfg.seed + 1000), cfg.test_samples)
}

fn mae(a: &[f64], b: &[f64]) -> f64 {
    a.iter().zip(b).map(|(x, y)| (x - y).abs()).sum::<f64>() / a.len().max(1) as f64
}

/// `(MAE of x against x*, MAE of P(x) against y*)`, each averaged over
/// `data`, for the states `xs` (one per sample).
fn state_errors(physics: &Physics, data: &[InverseSample], xs: &[Vec<f64>]) -> Result<(f64, f64), PgError> {
    let per: Vec<(f64, f64)> = data
        .par_iter()
        .zip(xs)
        .map(|(s, x)| {
            let mut y = vec![0.0; x.len()];
            physics.forward(x, &[], &mut y);
            (mae(x, &s.truth), mae(&y, &s.observed))
        })
        .collect();
    physics_ok(physics)?;
    let n = data.len().max(1) as f64;
    let (a, b) = per.iter().fold((0.0, 0.0), |(a, b), (c, d)| (a + c, b + d));
    let (a, b) = (a / n, b / n);
    if !(a.is_finite() && b.is_finite()) {
        return Err(PgError::NonFinite { what: "held-out error", sample: 0 });
    }
    Ok((a, b))
}

/// The network's held-out errors.
fn errors<N: Vjp + Sync>(physics: &Physics, net: &N, theta: &[f64], data: &[InverseSample]) -> Result<(f64, f64), PgError> {
    let xs: Vec<Vec<f64>> = data.par_iter().map(|s| net.eval(&s.observed, theta)).collect();
    state_errors(physics, data, &xs)
}

/// What the inverse alone recovers per held-out sample, without a
/// network: `x_{k+1} = x_k + P⁻¹(y* − P(x_k); x_k)` from `x_0 = 0` (so
/// `x_1 = y*`: nothing moves without smoke). The errors (as [`compare`]'s)
/// after `0..=iterations` iterations.
pub fn inverse_alone(cfg: &SmokeParams, iterations: usize) -> Result<Vec<(f64, f64)>, PgError> {
    let physics = physics(cfg);
    let test = test_set(cfg, &physics)?;
    let mut xs: Vec<Vec<f64>> = vec![vec![0.0; cfg.n * cfg.n]; test.len()];
    let mut out = vec![state_errors(&physics, &test, &xs)?];
    for _ in 0..iterations {
        xs.par_iter_mut().zip(&test).for_each(|(x, s)| {
            let mut y = vec![0.0; x.len()];
            physics.forward(x, &[], &mut y);
            let dy: Vec<f64> = s.observed.iter().zip(&y).map(|(a, b)| a - b).collect();
            let mut dx = vec![0.0; x.len()];
            physics.local_inverse(x, &[], &dy, &mut dx);
            x.iter_mut().zip(&dx).for_each(|(a, d)| *a += d);
        });
        out.push(state_errors(&physics, &test, &xs)?);
    }
    Ok(out)
}

/// How well the reverse-time inverse keeps its promise on held-out
/// states, for one scale of the change asked for.
#[derive(Clone, Copy, Debug, PartialEq, serde::Serialize, serde::Deserialize)]
pub struct InverseMiss {
    /// `dy = scale · J·(x*_b − x*_a)`: toward another held-out state.
    pub scale: f64,
    /// Mean relative miss `‖P(x + dx) − P(x) − dy‖ / ‖dy‖` of the
    /// reverse-time inverse ([`diffsim::check::local_inverse_error`]).
    pub reverse_time: f64,
    /// The same with the configured correction sweeps ([`Refined`]).
    pub refined: f64,
    /// The same with `dx = dy` (as if nothing moved), for comparison.
    pub unmoved: f64,
}

/// [`InverseMiss`] at `scales`, averaged over the first [`SHOWN`] held-out
/// states (each asked to move toward the next one's).
pub fn inverse_misses(cfg: &SmokeParams, scales: &[f64]) -> Result<Vec<InverseMiss>, PgError> {
    use diffsim::op::Jvp;
    let physics = physics(cfg);
    let test = test_set(cfg, &physics)?;
    let k = test.len().min(SHOWN);
    if k < 2 {
        return Ok(Vec::new());
    }
    let refined = Refined { op: &physics, sweeps: cfg.refine };
    let per: Vec<Vec<[f64; 3]>> = (0..k)
        .into_par_iter()
        .map(|a| {
            let x = &test[a].truth;
            let toward: Vec<f64> = test[(a + 1) % k].truth.iter().zip(x).map(|(b, a)| b - a).collect();
            let (mut y, mut dir) = (vec![0.0; x.len()], vec![0.0; x.len()]);
            physics.jvp(x, &[], &toward, &[], &mut y, &mut dir);
            scales
                .iter()
                .map(|&s| {
                    let dy: Vec<f64> = dir.iter().map(|d| s * d).collect();
                    [
                        diffsim::check::local_inverse_error(&physics, x, &[], &dy),
                        diffsim::check::local_inverse_error(&refined, x, &[], &dy),
                        diffsim::check::step_miss(&physics, x, &[], &dy, &dy),
                    ]
                })
                .collect()
        })
        .collect();
    physics_ok(&physics)?;
    Ok(scales
        .iter()
        .enumerate()
        .map(|(i, &scale)| {
            let mean = |j: usize| per.iter().map(|v| v[i][j]).sum::<f64>() / k as f64;
            InverseMiss { scale, reverse_time: mean(0), refined: mean(1), unmoved: mean(2) }
        })
        .collect())
}

/// What the study found ([`run`]).
#[derive(Clone, Debug, serde::Serialize, serde::Deserialize)]
pub struct SmokeReport {
    /// The settings' grid cells per side.
    pub n: usize,
    /// Simulation steps from the initial to the observed smoke.
    pub steps: usize,
    /// Correction sweeps of the inverse.
    pub refine: usize,
    /// Training seconds per method.
    pub seconds: f64,
    /// SIP's run, then Adam's.
    pub runs: Vec<SmokeRun>,
    /// The first [`SHOWN`] held-out samples' initial smoke …
    pub truth: Vec<Vec<f64>>,
    /// … and their observed final smoke (the pictures' first columns).
    pub observed: Vec<Vec<f64>>,
    /// Iterations of the inverse alone.
    pub inverse_iterations: usize,
    /// The inverse alone after them: the initial and the re-simulated
    /// final smoke's errors.
    pub inverse: (f64, f64),
    /// How well the inverse keeps its promise at three scales.
    pub misses: Vec<InverseMiss>,
}

/// The study: SIP and Adam for `cfg.seconds` each ([`compare`]), the
/// inverse alone for `inverse_iterations` iterations ([`inverse_alone`]),
/// and the inverse's misses at scales 1, 0.1 and 0.01
/// ([`inverse_misses`]). `progress(method, trained seconds)` after each
/// update.
///
/// # Errors
/// A non-finite loss, gradient or state.
pub fn run(cfg: &SmokeParams, inverse_iterations: usize, progress: impl FnMut(SmokeMethod, f64)) -> Result<SmokeReport, crate::StudyError> {
    let pg = |e: PgError| crate::StudyError::Train(e.into());
    let result = compare(cfg, &[SmokeMethod::Sip, SmokeMethod::Adam], progress)?;
    let inverse = *inverse_alone(cfg, inverse_iterations).map_err(pg)?.last().expect("inverse_alone reports iteration 0");
    let misses = inverse_misses(cfg, &[1.0, 0.1, 0.01]).map_err(pg)?;
    let shown = result.test.len().min(SHOWN);
    Ok(SmokeReport {
        n: cfg.n,
        steps: cfg.steps,
        refine: cfg.refine,
        seconds: cfg.seconds,
        truth: result.test[..shown].iter().map(|s| s.truth.clone()).collect(),
        observed: result.test[..shown].iter().map(|s| s.observed.clone()).collect(),
        runs: result.runs,
        inverse_iterations,
        inverse,
        misses,
    })
}

impl SmokeReport {
    /// The Markdown table: updates, seconds per update and the two errors
    /// per method and for the inverse alone, then the inverse's misses.
    pub fn table(&self) -> String {
        let mut table =
            format!("| method | updates in {:.0} s | s per update | initial smoke MAE | re-simulated final smoke MAE |\n|---|---|---|---|---|\n", self.seconds);
        for run in &self.runs {
            let c = &run.curve;
            let resim = c.second_points.last().map_or(f64::NAN, |p| p.1);
            table.push_str(&format!("| {} | {} | {:.3} | {:.4} | {resim:.4} |\n", c.name, c.updates, c.seconds_per_update(), c.final_loss()));
        }
        let (inv_x, inv_y) = self.inverse;
        table.push_str(&format!("| the inverse alone, {} iterations per sample | – | – | {inv_x:.4} | {inv_y:.4} |\n", self.inverse_iterations));
        table.push_str(&format!(
            "\nThe reverse-time inverse's promise, P(x + dx) ≈ P(x) + dy at held-out states (relative miss; dx = dy for comparison):\n\n| scale of dy | reverse time | with {} correction sweeps | dx = dy |\n|---|---|---|---|\n",
            self.refine
        ));
        for m in &self.misses {
            table.push_str(&format!("| {} | {:.3} | {:.3} | {:.3} |\n", m.scale, m.reverse_time, m.refined, m.unmoved));
        }
        table
    }

    /// `method,seconds,initial_mae,final_mae`, one row per recorded point.
    pub fn csv(&self) -> String {
        let mut csv = String::from("method,seconds,initial_mae,final_mae\n");
        for run in &self.runs {
            let c = &run.curve;
            for (i, (t, e)) in c.points.iter().enumerate() {
                let r = c.second_points.get(i).map_or(f64::NAN, |p| p.1);
                csv.push_str(&format!("{},{t:.4},{e:.6e},{r:.6e}\n", c.name));
            }
        }
        csv
    }

    /// The one-line result: per method its final errors, updates and
    /// seconds per update; the inverse alone's; the misses; the settings.
    pub fn json(&self) -> serde_json::Map<String, serde_json::Value> {
        let last = |c: &Curve| c.second_points.last().map_or(f64::NAN, |p| p.1);
        let mut obj = serde_json::Map::new();
        for run in &self.runs {
            let c = &run.curve;
            obj.insert(c.name.clone(), c.final_loss().into());
            obj.insert(format!("{}_resim", c.name), last(c).into());
            obj.insert(format!("{}_updates", c.name), c.updates.into());
            obj.insert(format!("{}_s_per_update", c.name), c.seconds_per_update().into());
        }
        obj.insert("time_s".into(), self.seconds.into());
        obj.insert("inverse".into(), self.inverse.0.into());
        obj.insert("inverse_resim".into(), self.inverse.1.into());
        obj.insert("inverse_iterations".into(), self.inverse_iterations.into());
        let misses: Vec<serde_json::Value> = self
            .misses
            .iter()
            .map(|m| serde_json::json!({"scale": m.scale, "reverse_time": m.reverse_time, "refined": m.refined, "unmoved": m.unmoved}))
            .collect();
        obj.insert("inverse_miss".into(), misses.into());
        obj.insert("n".into(), self.n.into());
        obj.insert("steps".into(), self.steps.into());
        obj.insert("refine".into(), self.refine.into());
        obj
    }
}
