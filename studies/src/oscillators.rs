//! HIG against Adam and Gauss-Newton on the coupled oscillators, in equal
//! wall-clock budgets (the published comparison of Schnell, Holl & Thuerey,
//! ICLR 2022: 4096 training and 4096 test samples from U[0, 1)⁴, the target
//! is the start state, network 4 → 20 → 20 → 20 → controls).

use rand::rngs::StdRng;
use rand::{Rng, SeedableRng};

use diffsim::distributed::World;
use diffsim::nn::{Activation, Init, Net, presets};
use diffsim::op::Forward;
use diffsim::problems::oscillators::Oscillators;
use std::ops::ControlFlow;

use diffsim::train::hig::{ControlSample, Hig, HigError};
use diffsim::train::{ControlBatch, Optimizer, TrainError, Trainer, TrainerParams, UpdateRule};

/// The optimizers compared.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Hash)]
pub enum OscMethod {
    /// Half-inverse gradients.
    Hig,
    /// Adam on the plain gradient.
    Adam,
    /// Gauss-Newton: the truncated pseudo-inverse of the same Jacobian.
    GaussNewton,
}

impl OscMethod {
    /// The three, in the order they run.
    pub const ALL: [OscMethod; 3] = [OscMethod::Hig, OscMethod::Adam, OscMethod::GaussNewton];

    /// Its name in tables and JSON keys.
    pub fn name(self) -> &'static str {
        match self {
            OscMethod::Hig => "hig",
            OscMethod::Adam => "adam",
            OscMethod::GaussNewton => "gn",
        }
    }
}

/// One comparison's settings.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct OscParams {
    /// The physics.
    pub problem: Oscillators,
    /// The hidden layers' activation.
    pub activation: Activation,
    /// Training samples.
    pub samples: usize,
    /// Held-out samples the curves are measured on.
    pub test_samples: usize,
    /// HIG's batch.
    pub hig_batch: usize,
    /// HIG's settings.
    pub hig: Hig,
    /// Gauss-Newton's batch.
    pub gn_batch: usize,
    /// Gauss-Newton's settings.
    pub gn: Hig,
    /// Adam's batch.
    pub adam_batch: usize,
    /// Adam's learning rate.
    pub adam_lr: f64,
    /// Training seconds per optimizer.
    pub budget_s: f64,
    /// A fixed number of updates per optimizer instead of the time budget
    /// (the curve then has a point every 1/40 of them): the same run on
    /// any machine and any number of ranks.
    pub updates: Option<usize>,
    /// Seed of data and weights.
    pub seed: u64,
}

impl OscParams {
    /// The linear problem as in the book and the JAX peer: tanh, HIG batch
    /// 32, η = 1, truncation 1e-10; Adam batch 256, lr 1e-3; Gauss-Newton as
    /// HIG.
    pub fn linear(budget_s: f64) -> Self {
        Self {
            problem: Oscillators::linear(),
            activation: Activation::Tanh,
            samples: 4096,
            test_samples: 4096,
            hig_batch: 32,
            hig: Hig::half_inverse(1.0, 1e-10),
            gn_batch: 32,
            gn: Hig::gauss_newton(1.0, 1e-10),
            adam_batch: 256,
            adam_lr: 1e-3,
            budget_s,
            updates: None,
            seed: 1,
        }
    }

    /// The nonlinear problem as published (`Nonlinear_oscillators/`):
    /// ReLU, HIG and Gauss-Newton batch 128, η = 1, truncation 1e-6; Adam
    /// batch 512, lr 3e-4.
    pub fn nonlinear(budget_s: f64) -> Self {
        Self {
            problem: Oscillators::nonlinear(),
            activation: Activation::Relu,
            hig_batch: 128,
            hig: Hig::half_inverse(1.0, 1e-6),
            gn_batch: 128,
            gn: Hig::gauss_newton(1.0, 1e-6),
            adam_batch: 512,
            adam_lr: 3e-4,
            ..Self::linear(budget_s)
        }
    }

    /// The network 4 → 20 → 20 → 20 → one control per step.
    pub fn network(&self) -> Net {
        presets::mlp(&[4, 20, 20, 20, self.problem.steps], self.activation).expect("the preset is well formed")
    }

    /// The network's starting weights (Glorot, from the seed).
    pub fn initial_params(&self, net: &Net) -> Vec<f64> {
        net.init(&mut StdRng::seed_from_u64(self.seed + 1), Init::Glorot)
    }
}

/// Loss versus training time of one optimizer.
#[derive(Clone, Debug, Default, serde::Serialize, serde::Deserialize)]
pub struct Curve {
    /// `hig`, `adam`, `gn`, …
    pub name: String,
    /// `(training seconds, loss on the held-out samples)`.
    pub points: Vec<(f64, f64)>,
    /// Updates taken.
    pub updates: usize,
    /// Training seconds (evaluations excluded).
    pub seconds: f64,
    /// The update after which the run stopped because the step or the
    /// test loss was no longer finite (the curve ends at the last finite
    /// point).
    #[serde(default)]
    pub diverged_after: Option<usize>,
    /// A second error measure at the same times, where the comparison has
    /// one (inverse heat: the notebook's x-L2 beside the L1 error; inverse
    /// smoke: the re-simulated final smoke's error beside the initial's).
    #[serde(default, alias = "l2_points")]
    pub second_points: Vec<(f64, f64)>,
}

impl Curve {
    /// The last loss.
    pub fn final_loss(&self) -> f64 {
        self.points.last().map_or(f64::NAN, |p| p.1)
    }

    /// Training seconds per update.
    pub fn seconds_per_update(&self) -> f64 {
        self.seconds / self.updates.max(1) as f64
    }
}

/// The published data: `samples + test_samples` states from U[0, 1)⁴,
/// split into training and test sets; each target is its start state.
pub fn datasets(cfg: &OscParams) -> (Vec<ControlSample>, Vec<ControlSample>) {
    let mut rng = StdRng::seed_from_u64(cfg.seed);
    let mut all: Vec<ControlSample> = (0..cfg.samples + cfg.test_samples)
        .map(|_| {
            let x: Vec<f64> = (0..4).map(|_| rng.random::<f64>()).collect();
            ControlSample { x0: x.clone(), target: x }
        })
        .collect();
    let test = all.split_off(cfg.samples);
    (all, test)
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

/// Trains the same initial network with each of `methods`, each for
/// `budget_s` seconds of training (evaluation excluded) or
/// [`OscParams::updates`] updates, recording the test-set loss about 40
/// times along the way. A run whose step or loss stops being finite ends
/// there, with [`Curve::diverged_after`] set (a result of the comparison,
/// not an error). `progress(method, seconds)` is called after each
/// evaluation.
///
/// Each method is an [`UpdateRule`] trained by the library's [`Trainer`]
/// on a [`ControlBatch`] per iteration (the training set's batches in
/// order, an epoch after another). Over the ranks of `world` each batch is
/// shared, HIG's Jacobian is decomposed once on rank 0, and rank 0's clock
/// decides for all when a time budget is spent.
pub fn compare(cfg: &OscParams, methods: &[OscMethod], world: &World, mut progress: impl FnMut(OscMethod, f64)) -> Result<Vec<Curve>, TrainError> {
    let (data, test) = datasets(cfg);
    let net = cfg.network();
    let theta0 = cfg.initial_params(&net);
    let every = cfg.budget_s / 40.0;
    let every_update = cfg.updates.map(|n| (n / 40).max(1));
    let mut curves = Vec::new();
    for &method in methods {
        let mut theta = theta0.clone();
        let (mut rule, batch): (Box<dyn UpdateRule>, usize) = match method {
            OscMethod::Hig => (Box::new(cfg.hig), cfg.hig_batch),
            OscMethod::Adam => (Box::new(Optimizer::adam(cfg.adam_lr)), cfg.adam_batch),
            OscMethod::GaussNewton => (Box::new(cfg.gn), cfg.gn_batch),
        };
        let mine = world.share(batch);
        let per_epoch = (data.len() / batch).max(1);
        let mut points = vec![(0.0, dataset_loss(&cfg.problem, &net, &theta, &test))];
        let (mut trained, mut next, mut updates) = (0.0, every, 0);
        let mut diverged_after = None;
        // A time budget runs until it is spent: the trainer's count is
        // only a bound.
        let iterations = match cfg.updates {
            Some(n) => n,
            None if cfg.budget_s > 0.0 => usize::MAX / 4,
            None => 0,
        };
        let trainer = Trainer::new(TrainerParams { iterations, ..TrainerParams::default() }, world);
        let batch_at = |it: usize| {
            let at = ((it - 1) % per_epoch) * batch;
            Ok(ControlBatch::new(&cfg.problem, &net, &data[at..at + batch][mine.clone()]).over(world, batch))
        };
        let run = trainer.run(rule.as_mut(), &mut theta, batch_at, |row, theta, _| {
            // Rank 0's clock decides for every rank.
            trained = world.broadcast(vec![trained + row.step_seconds])[0];
            updates = row.iteration;
            let evaluate = match (cfg.updates, every_update) {
                (Some(n), Some(e)) => updates % e == 0 || updates == n,
                _ => trained >= next || trained >= cfg.budget_s,
            };
            if evaluate {
                let l = dataset_loss(&cfg.problem, &net, theta, &test);
                if !l.is_finite() {
                    diverged_after = Some(updates);
                    return ControlFlow::Break(());
                }
                points.push((trained, l));
                progress(method, trained);
                next += every;
            }
            if cfg.updates.is_none() && trained >= cfg.budget_s { ControlFlow::Break(()) } else { ControlFlow::Continue(()) }
        });
        match run {
            Ok(_) => {}
            // A step that is no longer finite ends the curve there.
            Err(TrainError::Hig(HigError::NonFinite) | TrainError::NonFinite { .. }) => diverged_after = Some(updates),
            Err(e) => return Err(e),
        }
        curves.push(Curve { name: method.name().to_string(), points, updates, seconds: trained, diverged_after, second_points: Vec::new() });
    }
    Ok(curves)
}

/// What the study found ([`run`]): each problem's curves, in
/// [`OscMethod::ALL`]'s order.
#[derive(Clone, Debug, serde::Serialize, serde::Deserialize)]
pub struct OscReport {
    /// The training budget per optimizer, seconds.
    pub budget_s: f64,
    /// The linear problem's curves.
    pub linear: Vec<Curve>,
    /// The nonlinear problem's curves.
    pub nonlinear: Vec<Curve>,
}

/// The study: every optimizer on the linear and on the nonlinear problem
/// ([`compare`]), each problem one part of `parts` (saved when finished,
/// read back when an interrupted run is resumed; a problem interrupted
/// midway runs again, its budget being wall-clock time). Over the ranks
/// of `world` the batches are shared. `progress(problem, method, seconds)`
/// after each evaluation.
///
/// # Errors
/// A training error other than a divergence (which ends a curve), or a
/// part that cannot be read or saved.
pub fn run(
    linear: &OscParams,
    nonlinear: &OscParams,
    world: &World,
    parts: Option<&diffsim::train::checkpoint::Parts>,
    mut progress: impl FnMut(&'static str, OscMethod, f64),
) -> Result<OscReport, crate::StudyError> {
    let mut one = |name: &'static str, cfg: &OscParams| {
        crate::part(world, parts, name, || -> Result<Vec<Curve>, crate::StudyError> { Ok(compare(cfg, &OscMethod::ALL, world, |m, t| progress(name, m, t))?) })
    };
    let linear_curves = one("linear", linear)?;
    let nonlinear_curves = one("nonlinear", nonlinear)?;
    Ok(OscReport { budget_s: linear.budget_s, linear: linear_curves, nonlinear: nonlinear_curves })
}

impl OscReport {
    /// The two problems with their labels and JSON key suffixes.
    fn problems(&self) -> [(&'static str, &'static str, &[Curve]); 2] {
        [("linear", "", &self.linear), ("nonlinear", "_nonlinear", &self.nonlinear)]
    }

    /// The Markdown table: updates in the budget, seconds per update and
    /// the final test loss per problem and optimizer.
    pub fn table(&self) -> String {
        let mut table = format!("| problem | optimizer | updates in {:.0} s | s per update | final test loss |\n|---|---|---|---|---|\n", self.budget_s);
        for (label, _, curves) in self.problems() {
            for c in curves {
                let diverged = c.diverged_after.map_or(String::new(), |u| format!(" (diverged after {u} updates)"));
                table.push_str(&format!("| {label} | {} | {} | {:.4} | {:.3e}{diverged} |\n", c.name, c.updates, c.seconds_per_update(), c.final_loss()));
            }
        }
        table
    }

    /// `problem,optimizer,seconds,test_loss`, one row per recorded point.
    pub fn csv(&self) -> String {
        let mut csv = String::from("problem,optimizer,seconds,test_loss\n");
        for (label, _, curves) in self.problems() {
            for c in curves {
                for (t, l) in &c.points {
                    csv.push_str(&format!("{label},{},{t:.4},{l:.6e}\n", c.name));
                }
            }
        }
        csv
    }

    /// The one-line result: per optimizer (suffixed `_nonlinear` on the
    /// nonlinear problem) its final test loss, seconds per update, updates
    /// and whether it diverged; and `budget_s`.
    pub fn json(&self) -> serde_json::Map<String, serde_json::Value> {
        let mut obj = serde_json::Map::new();
        for (_, suffix, curves) in self.problems() {
            for c in curves {
                obj.insert(format!("{}{suffix}", c.name), c.final_loss().into());
                obj.insert(format!("{}{suffix}_s_per_update", c.name), c.seconds_per_update().into());
                obj.insert(format!("{}{suffix}_updates", c.name), c.updates.into());
                obj.insert(format!("{}{suffix}_diverged", c.name), c.diverged_after.is_some().into());
            }
        }
        obj.insert("budget_s".into(), self.budget_s.into());
        obj
    }
}
