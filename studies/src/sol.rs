//! Solver-in-the-loop studies (Um et al., NeurIPS 2020) for any problem
//! that supplies a coarse source solver and reference trajectories
//! ([`SolProblem`]): a network corrects the source solver after each step,
//! `u_{t+1} = v + N(v; θ)`, `v = source(u_t)` ([`Coupling::Add`]).
//!
//! - Training variants (same network, same number of updates): PRE (one
//!   step, supervised on reference pairs), NOISE (PRE with Gaussian input
//!   noise), SOL-k (unrolled `k` corrected steps from a reference state,
//!   loss at every step, gradient through all of them).
//! - Evaluation: rollouts from held-out reference initial states, relative
//!   L2 error against the reference per step.
//!
//! [`crate::burgers`] (1D Burgers) and [`crate::wake`] (2D flow past a
//! disc) are the two problems.

use rand::rngs::StdRng;
use rand::{Rng, SeedableRng};

pub use crate::StudyError;
use diffsim::distributed::World;
use diffsim::nn::Net;
use diffsim::op::{Forward, Jvp, Operator, Vjp};
use diffsim::rollout::Checkpointing;
pub use diffsim::train::TimeShares;
pub use diffsim::train::TrainError;
use diffsim::train::checkpoint::{CheckpointError, PartProgress, Parts};
use diffsim::train::observe::{CheckpointPolicy, Observer};
use diffsim::train::trainer::{Info, Row};
use diffsim::train::{Coupled, Coupling, Objective, Optimizer, Sample, Schedule, Trainer, TrainerParams, batch_gradient_over};

/// A reference trajectory: coarse states `0..=steps`.
pub type Trajectory = Vec<Vec<f64>>;

/// What a solver-in-the-loop study needs from a problem.
pub trait SolProblem: Sized + Sync {
    /// The coarse source solver (a state-to-state step without parameters).
    type Solver: Vjp + Jvp + Sync;

    /// The source solver.
    fn source(&self) -> Self::Solver;

    /// `count` reference trajectories of `steps` coarse steps from random
    /// initial states.
    fn dataset(&self, count: usize, steps: usize, rng: &mut StdRng) -> Vec<Trajectory>;

    /// The trajectories `share` of [`SolProblem::dataset`]`(count, steps,
    /// rng)`, the same values and the generator left in the same state,
    /// without simulating the others (a rank's share of a batch drawn
    /// afresh). The default simulates all and keeps the share.
    fn dataset_share(&self, count: usize, steps: usize, rng: &mut StdRng, share: std::ops::Range<usize>) -> Vec<Trajectory> {
        let mut all = self.dataset(count, steps, rng);
        all.truncate(share.end);
        all.drain(..share.start);
        all
    }

    /// The same problem with another viscosity (the physical parameter
    /// [`TrainData::Random`] draws per batch).
    fn with_viscosity(&self, nu: f64) -> Self;
}

/// A training variant.
#[derive(Clone, Copy, Debug, PartialEq)]
pub enum Method {
    /// One step, supervised on reference pairs.
    Pre,
    /// [`Method::Pre`] with Gaussian noise of this standard deviation added
    /// to the inputs.
    Noise(f64),
    /// Unrolled through this many corrected solver steps.
    Sol(usize),
}

impl Method {
    /// The unroll length.
    pub fn unroll(self) -> usize {
        match self {
            Method::Pre | Method::Noise(_) => 1,
            Method::Sol(k) => k,
        }
    }

    /// A short name: `pre`, `noise`, `sol4` …
    pub fn name(self) -> String {
        match self {
            Method::Pre => "pre".into(),
            Method::Noise(_) => "noise".into(),
            Method::Sol(k) => format!("sol{k}"),
        }
    }
}

/// Training settings.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct TrainParams {
    /// The variant.
    pub method: Method,
    /// Samples per mini-batch.
    pub batch: usize,
    /// Gradient updates (in this call).
    pub iterations: usize,
    /// The learning rate at the start.
    pub lr: f64,
    /// The learning rate at the end of the schedule: cosine decay from `lr`
    /// over iterations `1..=decay_over`, `lr_end` after (equal to `lr`:
    /// constant).
    pub lr_end: f64,
    /// Iterations the decay spans.
    pub decay_over: usize,
    /// Gradient clipping by norm (∞: none).
    pub clip: f64,
    /// Seed of the batch sampling and the noise.
    pub seed: u64,
    /// The number of the first iteration (1, or one past a saved
    /// checkpoint): the batch of iteration `i` depends only on `seed` and
    /// `i`, so a resumed run repeats an uninterrupted one exactly.
    pub first: usize,
}

impl TrainParams {
    /// The studies' schedule: Adam from learning rate 1e-3, cosine decay to
    /// 1e-5 over all `iterations`, clipping at norm 10, seed 1, starting at
    /// iteration 1 (`method` to be set per variant).
    pub fn adam(batch: usize, iterations: usize) -> Self {
        Self { method: Method::Pre, batch, iterations, lr: 1e-3, lr_end: 1e-5, decay_over: iterations, clip: 10.0, seed: 1, first: 1 }
    }

    /// The schedule: cosine from `lr` to `lr_end` over `decay_over`.
    pub fn schedule(&self) -> Schedule {
        Schedule::Cosine { start: self.lr, end: self.lr_end, over: self.decay_over }
    }
}

/// One logged iteration.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct LogRow {
    /// Iteration (1-based).
    pub iteration: usize,
    /// Mini-batch loss.
    pub loss: f64,
    /// Gradient norm before clipping.
    pub grad_norm: f64,
    /// Seconds since training started.
    pub seconds: f64,
}

/// How often the ranks of a distributed run compare their parameters and
/// optimizer state ([`World::check_same`]), in iterations (and after the
/// last).
pub const SAME_STATE_EVERY: usize = 20;

/// How a run is watched from outside: when its observer saves a
/// checkpoint, and the flag that stops it (Ctrl-C). `Default`: saves only
/// when the run stops or ends, no flag.
#[derive(Clone, Copy, Debug, Default)]
pub struct Watch<'a> {
    /// When the observer's checkpoint is called ([`Trainer`]).
    pub checkpoint: CheckpointPolicy,
    /// Once set on any rank, the run saves and stops after the iteration.
    pub stop: Option<&'a std::sync::atomic::AtomicBool>,
}

impl From<&Row> for LogRow {
    fn from(r: &Row) -> LogRow {
        LogRow { iteration: r.iteration, loss: r.loss, grad_norm: r.grad_norm.unwrap_or(f64::NAN), seconds: r.seconds }
    }
}

/// Trains `theta` in place on batches from `data` with the library's
/// [`Trainer`] (iterations from `s.first`, the cosine schedule, clipping,
/// checkpoints and stops as `watch` says); `observer` sees every row and
/// saves the checkpoints ([`diffsim::train::CsvLog`] and a save function,
/// say). Returns where the time went and what the run did ([`Info`]:
/// whether it stopped early).
///
/// Over the ranks of `world` (data-parallel training), every rank holds
/// the same `theta` and `opt` on entry, draws the same batches and unrolls
/// its share of each ([`batch_gradient_over`]); the updates, and so the
/// parameters, are those of one process bit for bit, and the ranks check
/// that they agree every [`SAME_STATE_EVERY`] iterations. The observer
/// runs on every rank.
#[allow(clippy::too_many_arguments)]
pub fn train<P: SolProblem>(
    setup: &P,
    net: &Net,
    theta: &mut [f64],
    opt: &mut Optimizer,
    data: TrainData<'_>,
    s: &TrainParams,
    world: &World,
    watch: Watch<'_>,
    observer: impl Observer<Optimizer>,
) -> Result<(TimeShares, Info), TrainError> {
    let k = s.method.unroll();
    let steps: Vec<usize> = (1..=k).collect();
    let shares = std::cell::RefCell::new(TimeShares::default());
    // One source solver for fixed data (it may own work buffers), one per
    // batch for data drawn with a new viscosity.
    let fixed_source = setup.source();
    let mine = world.share(s.batch);
    let state_len = fixed_source.n_in();
    let mut trainer = Trainer::new(
        TrainerParams {
            first: s.first,
            iterations: s.iterations,
            schedule: s.schedule(),
            clip: s.clip,
            same_state_every: SAME_STATE_EVERY,
            checkpoint: watch.checkpoint,
        },
        world,
    );
    if let Some(flag) = watch.stop {
        trainer = trainer.stop_on(flag);
    }
    let batch_at = |it: usize| -> Result<SolBatch<'_, P>, TrainError> {
        // The batch of iteration `it` depends only on the seed and `it`;
        // every rank draws all of it (the generator's stream), keeping and
        // simulating only its share.
        let mut rng = StdRng::seed_from_u64(s.seed.wrapping_mul(0x9E37_79B9_7F4A_7C15) ^ it as u64);
        let mut source = Source::Fixed(&fixed_source);
        let generated: Vec<Trajectory>;
        let trajectories: &[Trajectory] = match data {
            TrainData::Fixed(d) => d,
            TrainData::Random { nu, horizon } => {
                let nu = if nu.1 > nu.0 { rng.random_range(nu.0..nu.1) } else { nu.0 };
                let random_setup = setup.with_viscosity(nu);
                generated = random_setup.dataset_share(s.batch, horizon + k, &mut rng, mine.clone());
                source = Source::Own(random_setup.source());
                &generated
            }
        };
        let mut batch: Vec<Sample> = Vec::with_capacity(mine.len());
        for b in 0..s.batch {
            let (traj, len) = match data {
                TrainData::Fixed(d) => {
                    let t = &d[rng.random_range(0..d.len())];
                    (Some(t), t.len())
                }
                TrainData::Random { horizon, .. } => (mine.contains(&b).then(|| &trajectories[b - mine.start]), horizon + k + 1),
            };
            let t0 = rng.random_range(0..len - k);
            let noise: Vec<f64> = match s.method {
                Method::Noise(sigma) => (0..state_len).map(|_| sigma * diffsim::nn::normal(&mut rng)).collect(),
                _ => Vec::new(),
            };
            if let Some(traj) = traj.filter(|_| mine.contains(&b)) {
                let mut x0 = traj[t0].clone();
                for (v, e) in x0.iter_mut().zip(&noise) {
                    *v += e;
                }
                batch.push(Sample { x0, targets: traj[t0 + 1..=t0 + k].to_vec() });
            }
        }
        let mode = if k <= 64 { Checkpointing::Store } else { Checkpointing::periodic_sqrt(k) };
        Ok(SolBatch { source, net, batch, unroll: k, steps: &steps, mode, world, batch_len: s.batch, shares: &shares })
    };
    let info = trainer.run_observed(opt, theta, batch_at, observer)?;
    let mut shares = shares.into_inner();
    shares.total = info.seconds;
    Ok((shares, info))
}

/// The source solver of a batch: the study's own, or one made for the
/// batch's drawn viscosity.
enum Source<'a, S> {
    Fixed(&'a S),
    Own(S),
}

/// One iteration's objective: the corrected solver unrolled from each of
/// this rank's samples, the batch shared over the ranks.
struct SolBatch<'a, P: SolProblem> {
    source: Source<'a, P::Solver>,
    net: &'a Net,
    batch: Vec<Sample>,
    unroll: usize,
    steps: &'a [usize],
    mode: Checkpointing,
    world: &'a World,
    batch_len: usize,
    shares: &'a std::cell::RefCell<TimeShares>,
}

impl<P: SolProblem> Objective for SolBatch<'_, P> {
    fn n_params(&self) -> usize {
        self.net.n_params()
    }
    fn loss_and_gradient(&mut self, theta: &[f64]) -> Result<(f64, Vec<f64>), TrainError> {
        let source = match &self.source {
            Source::Fixed(s) => *s,
            Source::Own(s) => s,
        };
        let coupled = Coupled::new(source, &[], self.net, Coupling::Add).expect("the study's network fits the solver");
        let r = batch_gradient_over(self.world, &coupled, theta, self.unroll, self.steps, &self.batch, self.batch_len, self.mode);
        self.shares.borrow_mut().add_timers(&coupled.timers);
        Ok(r?)
    }
}

/// Relative L2 error per step (`1..=steps`), averaged over the
/// trajectories, of the source solver (`theta = None`) or the corrected
/// one. A rollout that becomes non-finite is an error naming the step.
pub fn evaluate<P: SolProblem>(setup: &P, net: &Net, theta: Option<&[f64]>, data: &[Trajectory], steps: usize) -> Result<Vec<f64>, EvalError> {
    let source = setup.source();
    let coupled = Coupled::new(&source, &[], net, Coupling::Add).expect("the study's network fits the solver");
    let mut err = vec![0.0; steps];
    for (j, traj) in data.iter().enumerate() {
        let mut u = traj[0].clone();
        let mut y = vec![0.0; u.len()];
        for (t, e) in err.iter_mut().enumerate() {
            match theta {
                Some(th) => coupled.forward(&u, th, &mut y),
                None => source.forward(&u, &[], &mut y),
            }
            std::mem::swap(&mut u, &mut y);
            if u.iter().any(|v| !v.is_finite()) {
                return Err(EvalError { trajectory: j, step: t + 1 });
            }
            let r = &traj[t + 1];
            let num: f64 = u.iter().zip(r).map(|(a, b)| (a - b) * (a - b)).sum();
            let den: f64 = r.iter().map(|b| b * b).sum();
            *e += (num / den.max(1e-300)).sqrt() / data.len() as f64;
        }
    }
    Ok(err)
}

/// A rollout that blew up during evaluation.
#[derive(Clone, Copy, Debug, PartialEq, Eq, thiserror::Error)]
#[error("the rollout of test trajectory {trajectory} became non-finite at step {step}")]
pub struct EvalError {
    /// The trajectory.
    pub trajectory: usize,
    /// The step.
    pub step: usize,
}

/// Where the training batches come from.
#[derive(Clone, Copy, Debug)]
pub enum TrainData<'a> {
    /// Fixed reference trajectories (precomputed).
    Fixed(&'a [Trajectory]),
    /// Drawn afresh for every batch: initial states at random, the
    /// viscosity uniform in `nu` (one value per batch), start states up to
    /// `horizon` coarse steps into the trajectory. The solver is the data
    /// generator.
    Random {
        /// Viscosity range.
        nu: (f64, f64),
        /// Latest start step.
        horizon: usize,
    },
}

/// The settings of the whole study ([`study`]).
#[derive(Clone, Debug)]
pub struct StudyParams<P> {
    /// The problem: grids, time steps, data.
    pub setup: P,
    /// Training trajectories.
    pub train: usize,
    /// Training trajectories drawn before the test set (the standard
    /// count): with more, the rest are drawn after it, with fewer, the first
    /// `train` are used, so that the test set stays the same whatever
    /// `train` is.
    pub train_base: usize,
    /// Held-out test trajectories.
    pub test: usize,
    /// Coarse steps of each training trajectory.
    pub train_steps: usize,
    /// Coarse steps of the evaluation rollouts.
    pub eval_steps: usize,
    /// The variants trained (the source solver is always evaluated).
    pub methods: Vec<Method>,
    /// Batch, iterations, learning rate, clipping, seed (`method` is set per variant).
    pub settings: TrainParams,
    /// The correction network.
    pub net: Net,
}

impl Method {
    /// The studies' input noise σ of NOISE.
    pub const STANDARD_NOISE: f64 = 0.02;

    /// The studies' variants: PRE, NOISE (σ = 0.02), SOL-4, SOL-16.
    pub fn standard() -> Vec<Method> {
        vec![Method::Pre, Method::Noise(Self::STANDARD_NOISE), Method::Sol(4), Method::Sol(16)]
    }
}

/// One trained (or source) variant's results.
#[derive(Clone, Debug, serde::Serialize, serde::Deserialize)]
pub struct VariantResult {
    /// `source`, `pre`, `noise`, `sol4`, `sol16`.
    pub name: String,
    /// Relative L2 error per evaluation step, averaged over the test set.
    pub error: Vec<f64>,
    /// Its mean over the steps.
    pub mean_error: f64,
    /// The same mean on the training trajectories' first steps (a gap to
    /// `mean_error` means the network fits its data better than it
    /// generalises).
    pub train_mean_error: f64,
    /// Training loss per iteration.
    pub loss: Vec<f64>,
    /// Time shares of training.
    pub time: TimeShares,
    /// Wall seconds per training iteration.
    pub s_per_iter: f64,
}

/// What a solver-in-the-loop study found ([`study`]): every variant, the
/// source solver first, with what the table, the CSV and the one-line
/// result show.
#[derive(Clone, Debug, serde::Serialize, serde::Deserialize)]
pub struct SolReport {
    /// The variants in the order they ran (`source` first).
    pub variants: Vec<VariantResult>,
    /// Steps of the test rollouts.
    pub eval_steps: usize,
    /// Training iterations per variant.
    pub iterations: usize,
    /// Training trajectories.
    pub train_trajectories: usize,
    /// Threads the variants trained on (the time shares are of them).
    pub threads: usize,
}

impl SolReport {
    /// The report of `variants` trained as `cfg` says.
    pub fn new<P>(cfg: &StudyParams<P>, variants: Vec<VariantResult>) -> Self {
        SolReport {
            variants,
            eval_steps: cfg.eval_steps,
            iterations: cfg.settings.iterations,
            train_trajectories: cfg.train,
            threads: rayon::current_num_threads(),
        }
    }

    /// The variant called `name`.
    pub fn variant(&self, name: &str) -> Option<&VariantResult> {
        self.variants.iter().find(|v| v.name == name)
    }

    /// The Markdown table: each variant's mean error and its ratio to the
    /// source's, the error at the last step, the same on the training
    /// trajectories, seconds per iteration and where the time went.
    pub fn table(&self) -> String {
        let source = self.variants.first().map_or(f64::NAN, |v| v.mean_error);
        let mut table = format!(
            "| variant | mean rel. L2 error ({n} steps) | vs source | error at step {n} | same on training trajectories | s / iteration | solver | network | chaining + optimizer |\n|---|---|---|---|---|---|---|---|---|\n",
            n = self.eval_steps
        );
        for r in &self.variants {
            let t = &r.time;
            let parts = t.solver_fwd + t.solver_bwd + t.net_fwd + t.net_bwd;
            // Solver and network times are summed over threads; shares are of that sum plus the rest of the wall time.
            let (share_s, share_n, share_c) = if t.total > 0.0 {
                let rest = (t.total * self.threads as f64 - parts).max(0.0);
                let all = parts + rest;
                ((t.solver_fwd + t.solver_bwd) / all, (t.net_fwd + t.net_bwd) / all, rest / all)
            } else {
                (0.0, 0.0, 0.0)
            };
            let cell = |v: f64| if r.name == "source" { "–".to_string() } else { format!("{:.0}%", 100.0 * v) };
            table.push_str(&format!(
                "| {} | {:.4} | {:.2} | {:.4} | {:.4} | {} | {} | {} | {} |\n",
                r.name,
                r.mean_error,
                r.mean_error / source,
                r.error.last().copied().unwrap_or(f64::NAN),
                r.train_mean_error,
                if r.name == "source" { "–".to_string() } else { format!("{:.4}", r.s_per_iter) },
                cell(share_s),
                cell(share_n),
                cell(share_c),
            ));
        }
        table
    }

    /// `step,<variant>,…`: the test error per step of every variant.
    pub fn csv(&self) -> String {
        let mut s = format!("step,{}\n", self.variants.iter().map(|r| r.name.as_str()).collect::<Vec<_>>().join(","));
        for t in 0..self.eval_steps {
            s.push_str(&format!("{},{}\n", t + 1, self.variants.iter().map(|r| format!("{:.6e}", r.error[t])).collect::<Vec<_>>().join(",")));
        }
        s
    }

    /// The one-line result: the standard variants' mean errors (null when
    /// not run) and every variant that ran under its name,
    /// `train_s_per_iter` (SOL-16's), `iterations`, `threads`,
    /// `train_trajectories`, and `train_set` (each variant's error on the
    /// training trajectories).
    pub fn json(&self) -> serde_json::Map<String, serde_json::Value> {
        let mut obj = serde_json::Map::new();
        for k in ["source", "pre", "noise", "sol4", "sol16"] {
            obj.insert(k.into(), serde_json::Value::Null);
        }
        obj.insert("train_s_per_iter".into(), self.variant("sol16").map_or(f64::NAN, |r| r.s_per_iter).into());
        obj.insert("iterations".into(), self.iterations.into());
        obj.insert("threads".into(), self.threads.into());
        obj.insert("train_trajectories".into(), self.train_trajectories.into());
        obj.insert(
            "train_set".into(),
            self.variants.iter().map(|r| (r.name.clone(), serde_json::Value::from(r.train_mean_error))).collect::<serde_json::Map<_, _>>().into(),
        );
        for r in &self.variants {
            obj.insert(r.name.clone(), r.mean_error.into());
        }
        obj
    }
}

/// How a study saves its parts and learns of an interrupt ([`study`]).
pub struct Resumable<'a> {
    /// Where finished variants and the one in progress are saved.
    pub parts: &'a Parts,
    /// Seconds between two progress checkpoints of a variant.
    pub every_s: f64,
    /// Set once the run should stop (Ctrl-C): the variant in progress is
    /// checkpointed and the study returns [`StudyError::Interrupted`].
    pub stop: &'a std::sync::atomic::AtomicBool,
}

/// Runs the study: builds the data sets, evaluates the source solver,
/// trains each variant from the same initial network and evaluates it.
/// `progress(variant, row)` is called after every iteration. With
/// `resume`, variants finished in an earlier run are read back, the one in
/// progress goes on from its checkpoint, and the results are those of an
/// uninterrupted run (the batches of iteration `i` depend on the seed and
/// `i` alone; the times are this run's).
///
/// Over the ranks of `world` every variant trains data-parallel
/// ([`train`]); rank 0 alone reads and writes the parts and sends what it
/// read to the others; a stop is taken when any rank is asked to stop.
pub fn study<P: SolProblem>(
    cfg: &StudyParams<P>,
    resume: Option<Resumable<'_>>,
    world: &World,
    mut progress: impl FnMut(&str, LogRow),
) -> Result<Vec<VariantResult>, StudyError> {
    let mut rng = StdRng::seed_from_u64(cfg.settings.seed);
    let mut train_set = cfg.setup.dataset(cfg.train_base, cfg.train_steps, &mut rng);
    let test_set = cfg.setup.dataset(cfg.test, cfg.eval_steps, &mut rng);
    if cfg.train > cfg.train_base {
        train_set.extend(cfg.setup.dataset(cfg.train - cfg.train_base, cfg.train_steps, &mut rng));
    }
    train_set.truncate(cfg.train);
    let theta0 = initial_params(&cfg.net, cfg.settings.seed);
    let source = evaluate(&cfg.setup, &cfg.net, None, &test_set, cfg.eval_steps)?;
    let source_train = mean(&evaluate(&cfg.setup, &cfg.net, None, &train_set, cfg.eval_steps)?);
    let mut out = vec![VariantResult {
        name: "source".into(),
        mean_error: mean(&source),
        train_mean_error: source_train,
        error: source,
        loss: Vec::new(),
        time: TimeShares::default(),
        s_per_iter: 0.0,
    }];
    let total = cfg.settings.iterations;
    for &method in &cfg.methods {
        let name = method.name();
        let finished = match &resume {
            Some(r) => world.from_root(|| r.parts.finished::<VariantResult>(&name))?,
            None => None,
        };
        if let Some(done) = finished {
            for (k, &loss) in done.loss.iter().enumerate() {
                progress(&name, LogRow { iteration: k + 1, loss, grad_norm: f64::NAN, seconds: 0.0 });
            }
            out.push(done);
            continue;
        }
        let mut theta = theta0.clone();
        let mut opt = Optimizer::adam(cfg.settings.lr);
        let mut loss = Vec::with_capacity(total);
        let saved = match &resume {
            Some(r) => world.from_root(|| r.parts.progress(&name, theta.len(), total))?,
            None => None,
        };
        if let Some(p) = saved {
            (theta, opt, loss) = (p.theta, p.optimizer, p.loss);
            for (k, &l) in loss.iter().enumerate() {
                progress(&name, LogRow { iteration: k + 1, loss: l, grad_norm: f64::NAN, seconds: 0.0 });
            }
        }
        let first = loss.len() + 1;
        let s = TrainParams { method, first, iterations: total + 1 - first, ..cfg.settings };
        let watch = match &resume {
            Some(r) => Watch { checkpoint: CheckpointPolicy { every: usize::MAX, seconds: r.every_s }, stop: Some(r.stop) },
            None => Watch::default(),
        };
        let mut failure: Option<CheckpointError> = None;
        let loss_cell = std::cell::RefCell::new(&mut loss);
        let rows = diffsim::train::on_row(|row: &Row, _: &[f64], _: &Optimizer| {
            loss_cell.borrow_mut().push(row.loss);
            progress(&name, LogRow::from(row));
            std::ops::ControlFlow::Continue(())
        });
        let save = diffsim::train::save_with(|it: usize, theta: &[f64], opt: &Optimizer| {
            let (Some(r), true) = (&resume, world.is_root()) else { return Ok(()) };
            // The last iteration's state is the finished part, saved below.
            if it == total {
                return Ok(());
            }
            let p = PartProgress { iterations_done: it, theta: theta.to_vec(), optimizer: opt.clone(), loss: loss_cell.borrow().to_vec() };
            r.parts.save_progress(&name, &p).map_err(|e| {
                let text = e.to_string();
                failure = Some(e);
                TrainError::Observer(text)
            })
        });
        let trained = train(&cfg.setup, &cfg.net, &mut theta, &mut opt, TrainData::Fixed(&train_set), &s, world, watch, (rows, save));
        if let Some(e) = failure {
            return Err(e.into());
        }
        let (time, info) = trained?;
        if info.stopped {
            return Err(StudyError::Interrupted { variant: name, done: info.last, of: total });
        }
        let error = evaluate(&cfg.setup, &cfg.net, Some(&theta), &test_set, cfg.eval_steps)?;
        let train_mean_error = mean(&evaluate(&cfg.setup, &cfg.net, Some(&theta), &train_set, cfg.eval_steps)?);
        let ran = (total + 1 - first).max(1);
        let result = VariantResult { name, mean_error: mean(&error), train_mean_error, error, loss, s_per_iter: time.total / ran as f64, time };
        if let Some(r) = &resume
            && world.is_root()
        {
            r.parts.finish(&result.name, &result)?;
        }
        out.push(result);
    }
    Ok(out)
}

/// Fresh parameters for a correction network: Glorot weights, the last
/// layer *with parameters* zero (layers after it, such as a gather, have
/// none), so that training starts from the source solver.
pub fn initial_params(net: &Net, seed: u64) -> Vec<f64> {
    let mut theta = net.init(&mut StdRng::seed_from_u64(seed), diffsim::nn::Init::Glorot);
    let last = net.layers().iter().rev().map(|l| l.n_params()).find(|&k| k > 0).unwrap_or(0);
    let n = theta.len();
    theta[n - last..].fill(0.0);
    theta
}

/// The mean of `v`.
pub fn mean(v: &[f64]) -> f64 {
    v.iter().sum::<f64>() / v.len().max(1) as f64
}
