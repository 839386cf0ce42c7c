//! `diffsim train CONFIG` (one training run through the solver) and
//! `diffsim experiment sol-burgers` and `sol-wake` (the PRE / NOISE / SOL
//! studies).

use std::path::{Path, PathBuf};

use serde::Deserialize;
use serde::de::IntoDeserializer;

use super::{CliError, plot_or_warn};
use crate::plot::{Axes, Series};
use diffsim::distributed::World;
use diffsim::nn::{Activation, ParamStore};
use diffsim::train::Optimizer;
use diffsim::train::checkpoint::{Checkpoint, FORMAT, Parts, config_difference};
use diffsim::train::trainer::Row;
use diffsim::train::{CheckpointPolicy, CsvLog};
use diffsim_studies::burgers::{Method, StudyParams, TrainData, evaluate, initial_params, mean, study, train};
use diffsim_studies::config::TrainConfig;
use diffsim_studies::sol::SolProblem;
use diffsim_studies::sol::Watch;

/// Arguments of `diffsim train`.
#[derive(Debug, clap::Args)]
pub struct TrainArgs {
    /// The configuration (TOML; keys in docs/train.md).
    config: PathBuf,
    /// Output directory: loss.csv, loss.png, model.json, checkpoint.json.
    #[arg(long, default_value = "out/train")]
    out: PathBuf,
    /// Finish an interrupted run: continue from OUT/checkpoint.json to the
    /// configured number of iterations (the result is the uninterrupted
    /// run's, bit for bit).
    #[arg(long, conflicts_with_all = ["extend", "overwrite"])]
    resume: bool,
    /// Train a run further: this many iterations beyond OUT/checkpoint.json,
    /// past the configured total if need be.
    #[arg(long, value_name = "ITERATIONS", conflicts_with = "overwrite")]
    extend: Option<usize>,
    /// Start afresh in a folder that holds another run's files, replacing them.
    #[arg(long)]
    overwrite: bool,
    /// Write a checkpoint every this many iterations …
    #[arg(long, value_name = "ITERATIONS", default_value_t = 50)]
    checkpoint_every: usize,
    /// … or once this many seconds have passed since the last one.
    #[arg(long, value_name = "SECONDS", default_value_t = 30.0)]
    checkpoint_seconds: f64,
    /// Stop after this iteration, with its checkpoint written (a run cut
    /// into slices, as under a batch system's time limit); `--resume`
    /// continues it, under any number of ranks.
    #[arg(long, value_name = "ITERATION")]
    until: Option<u64>,
    /// No progress bar.
    #[arg(long)]
    quiet: bool,
}

/// Experiments.
#[derive(Debug, clap::Subcommand)]
pub enum ExperimentCommand {
    /// Solver-in-the-loop on Burgers: source vs PRE, NOISE, SOL-4, SOL-16.
    SolBurgers(SolArgs),
    /// Solver-in-the-loop in 2D: flow past a disc (64 × 32, 4× finer
    /// reference), source vs PRE, NOISE, SOL-4, SOL-16.
    SolWake(SolWakeArgs),
    /// Half-inverse gradients vs Adam on the linear and nonlinear coupled
    /// oscillators, in equal wall-clock budgets.
    HigOscillators(HigArgs),
    /// Inverse heat (64 × 64, ν·t = 8): SIP vs Adam vs plain gradient
    /// descent, same network, start and batches.
    SipHeat(SipArgs),
    /// Inverse smoke: a network recovers P2's initial smoke from the smoke
    /// T steps later, trained by SIP with the reverse-time inverse and by
    /// Adam through the solver, in equal wall-clock budgets.
    SipSmoke(super::pg::SipSmokeArgs),
    /// The lid-driven cavity marched to its steady state, its centreline
    /// extrema compared with Ghia, Ghia & Shin (1982).
    Cavity(super::flow::CavityArgs),
    /// The flow around a cylinder of Schäfer & Turek (1996): drag, lift and
    /// pressure difference (2d-1, steady) or their maxima and the Strouhal
    /// number (2d-2, periodic), against the published values.
    Cylinder(super::flow::CylinderArgs),
    /// Minimum-drag shape of a given area in the 2D-1 channel (Re 20): L-BFGS on
    /// the adjoint gradient of the steady drag, verified on a grid twice as fine.
    DragShape(super::flow::DragShapeArgs),
    /// A network from the Reynolds number (10–40) to a minimum-drag shape,
    /// trained through the steady solver; compared on held-out Re with shapes
    /// optimised one by one.
    DragNet(super::flow::DragNetArgs),
}

/// Arguments of `diffsim experiment sip-heat`.
#[derive(Debug, clap::Args)]
pub struct SipArgs {
    /// `small` (a one-level U-Net of width 8, batch 16, the Tikhonov
    /// inverse) or `published` (tum-pbs/SIP's: the Bayesian inverse, a
    /// 4-level U-Net of 16 filters in float32 with the mean correction,
    /// batch 128).
    #[arg(long, default_value = "small")]
    setup: String,
    /// Updates per optimizer (default 300 small, 50 published).
    #[arg(long)]
    iterations: Option<usize>,
    /// Held-out samples the error is measured on (default 32).
    #[arg(long)]
    test_samples: Option<usize>,
    /// Samples per batch (default 16 small, 128 published).
    #[arg(long)]
    batch: Option<usize>,
    /// Learning rate of plain gradient descent.
    #[arg(long)]
    gd_lr: Option<f64>,
    /// Print the result as one JSON object on the last line.
    #[arg(long)]
    json: bool,
    /// Output directory: table.md, error.csv, error.png.
    #[arg(long, default_value = "out/sip-heat")]
    out: PathBuf,
    /// Keep the optimizers' runs (OUT/parts) an interrupted run finished,
    /// with the same options, and run only the rest; a run interrupted
    /// midway starts again (it is not checkpointed inside). Without it the
    /// comparison starts afresh.
    #[arg(long)]
    resume: bool,
    #[command(flatten)]
    overwrite: super::Overwrite,
}

/// Arguments of `diffsim experiment hig-oscillators`.
#[derive(Debug, clap::Args)]
pub struct HigArgs {
    /// Training seconds per optimizer and problem (the published runs
    /// train for 3600; 10 is a quick look).
    #[arg(long, default_value_t = 60.0)]
    budget: f64,
    /// Instead of the time budget, this many updates per optimizer and
    /// problem: the same curves on any machine and any number of ranks.
    #[arg(long)]
    updates: Option<usize>,
    /// How HIG and Gauss-Newton decompose the batch Jacobian: auto (the
    /// Gram eigendecomposition in f64 where it is as accurate as the SVD,
    /// else the f64 SVD), svd, gram, or svd-f32 (the published code's
    /// precision).
    #[arg(long, default_value = "auto")]
    decomposition: String,
    /// Print the result as one JSON object on the last line.
    #[arg(long)]
    json: bool,
    /// Output directory: table.md, loss.csv (test loss against training
    /// seconds for HIG, Adam and Gauss-Newton), loss.png.
    #[arg(long, default_value = "out/hig-oscillators")]
    out: PathBuf,
    /// Keep the problems (OUT/parts) an interrupted run finished, with the
    /// same options, and run only the rest; a problem interrupted midway
    /// starts again (its runs race on the wall clock: a run cut and
    /// resumed would not be the same run). Without it the comparison starts
    /// afresh.
    #[arg(long)]
    resume: bool,
    #[command(flatten)]
    overwrite: super::Overwrite,
}

/// Options of every solver-in-the-loop study.
#[derive(Debug, clap::Args)]
pub struct StudyArgs {
    /// A reduced study (fewer updates and trajectories; same variants).
    #[arg(long)]
    quick: bool,
    /// Print the result as one JSON object on the last line.
    #[arg(long)]
    json: bool,
    /// Training iterations per variant (overrides the study's default).
    #[arg(long)]
    iterations: Option<usize>,
    /// Training trajectories (overrides the study's default; the test set
    /// does not depend on it).
    #[arg(long)]
    train: Option<usize>,
    /// Initial learning rate of Adam (overrides the default; the cosine
    /// schedule ends at a hundredth of it).
    #[arg(long)]
    lr: Option<f64>,
    /// The variants to train, comma-separated from pre, noise, sol4, sol16
    /// (or any solK); default all four.
    #[arg(long, value_delimiter = ',')]
    methods: Option<Vec<String>>,
    /// Seed of the data sets, the initial network and the batches (default 1).
    #[arg(long)]
    seed: Option<u64>,
    /// Input noise σ of the NOISE variant (default 0.02).
    #[arg(long)]
    noise: Option<f64>,
    /// The network's activation: relu, leaky_relu, tanh, gelu, swish or
    /// sigmoid (default: the study's).
    #[arg(long)]
    activation: Option<String>,
    /// Go on from an interrupted run's saved parts (OUT/parts: the
    /// finished variants and a checkpoint of the one in progress), with the
    /// same options; the results are the uninterrupted run's. Without it a
    /// run starts afresh.
    #[arg(long)]
    resume: bool,
    /// Seconds between two checkpoints of the variant in training (and
    /// one at Ctrl-C).
    #[arg(long, default_value_t = 30.0)]
    checkpoint_seconds: f64,
    #[command(flatten)]
    overwrite: super::Overwrite,
}

impl StudyArgs {
    /// The activation asked for, or `default`.
    fn activation(&self, default: Activation) -> Result<Activation, CliError> {
        let Some(name) = &self.activation else { return Ok(default) };
        let de: serde::de::value::StrDeserializer<'_, serde::de::value::Error> = name.as_str().into_deserializer();
        Activation::deserialize(de).map_err(|e| CliError::Argument { arg: "--activation", reason: e.to_string() })
    }

    /// Sets the overridden values, refusing zeros, non-positive learning
    /// rates, negative noise and unknown variants.
    fn apply<P>(&self, cfg: &mut StudyParams<P>) -> Result<(), CliError> {
        if !(self.checkpoint_seconds.is_finite() && self.checkpoint_seconds > 0.0) {
            return Err(CliError::Argument { arg: "--checkpoint-seconds", reason: format!("must be a positive number, got {}", self.checkpoint_seconds) });
        }
        if let Some(it) = self.iterations {
            if it == 0 {
                return Err(CliError::Argument { arg: "--iterations", reason: "must be at least 1".into() });
            }
            cfg.settings.iterations = it;
            cfg.settings.decay_over = it;
        }
        if let Some(n) = self.train {
            if n == 0 {
                return Err(CliError::Argument { arg: "--train", reason: "need at least one training trajectory".into() });
            }
            cfg.train = n;
        }
        if let Some(lr) = self.lr {
            if !(lr.is_finite() && lr > 0.0) {
                return Err(CliError::Argument { arg: "--lr", reason: format!("must be a positive number, got {lr}") });
            }
            cfg.settings.lr = lr;
            cfg.settings.lr_end = lr / 100.0;
        }
        if let Some(seed) = self.seed {
            cfg.settings.seed = seed;
        }
        if let Some(names) = &self.methods {
            cfg.methods = names
                .iter()
                .map(|name| match name.trim() {
                    "pre" => Ok(Method::Pre),
                    "noise" => Ok(Method::Noise(Method::STANDARD_NOISE)),
                    s => s
                        .strip_prefix("sol")
                        .and_then(|k| k.parse::<usize>().ok())
                        .filter(|&k| k >= 1)
                        .map(Method::Sol)
                        .ok_or_else(|| CliError::Argument { arg: "--methods", reason: format!("expected pre, noise or solK (K ≥ 1), got {s:?}") }),
                })
                .collect::<Result<_, _>>()?;
            if cfg.methods.is_empty() {
                return Err(CliError::Argument { arg: "--methods", reason: "name at least one variant".into() });
            }
            if let Some(k) = cfg.methods.iter().map(|m| m.unroll()).max().filter(|&k| k >= cfg.train_steps) {
                return Err(CliError::Argument {
                    arg: "--methods",
                    reason: format!("sol{k} unrolls {k} steps, but the training trajectories have {} steps", cfg.train_steps),
                });
            }
        }
        if let Some(sigma) = self.noise {
            if !(sigma.is_finite() && sigma >= 0.0) {
                return Err(CliError::Argument { arg: "--noise", reason: format!("must be a non-negative number, got {sigma}") });
            }
            for m in &mut cfg.methods {
                if let Method::Noise(s) = m {
                    *s = sigma;
                }
            }
        }
        Ok(())
    }
}

/// Arguments of `diffsim experiment sol-burgers` (defaults: 6000 updates,
/// 64 training trajectories; quick 1500 and 32).
#[derive(Debug, clap::Args)]
pub struct SolArgs {
    #[command(flatten)]
    study: StudyArgs,
    /// Output directory: table.md, errors.csv, error.png, loss.png.
    #[arg(long, default_value = "out/sol-burgers")]
    out: PathBuf,
    /// The correction network: conv-stack (P3's, 5505 parameters, 13 cells
    /// of receptive field), unet (one level, 32/64 channels, about 31 000
    /// parameters, most of the domain) or resnet (width 32, 3 blocks).
    #[arg(long, default_value = "conv-stack")]
    net: String,
    /// Channels of the network's hidden layers.
    #[arg(long, default_value_t = 32)]
    width: usize,
}

/// Arguments of `diffsim experiment sol-wake` (defaults: 1000 updates, 16
/// training trajectories, 64-step test rollouts; quick 300, 6 and 32).
#[derive(Debug, clap::Args)]
pub struct SolWakeArgs {
    #[command(flatten)]
    study: StudyArgs,
    /// Output directory: table.md, errors.csv, error.png, loss.png.
    #[arg(long, default_value = "out/sol-wake")]
    out: PathBuf,
    /// Coarse steps of each test rollout (overrides the default).
    #[arg(long)]
    steps: Option<usize>,
}

/// Writes a comparison's `table.md`, `error.csv` and `error.png` (the plot
/// only warns when it cannot be drawn).
pub(super) fn write_error_files(out: &Path, table: &str, csv: &str, axes: &Axes<'_>, series: &[Series]) -> Result<(), CliError> {
    let md = out.join("table.md");
    diffsim::files::write(&md, table).map_err(io(&md))?;
    let path = out.join("error.csv");
    diffsim::files::write(&path, csv).map_err(io(&path))?;
    plot_or_warn(&out.join("error.png"), axes, series);
    Ok(())
}

pub(super) fn io(path: &Path) -> impl FnOnce(std::io::Error) -> CliError + '_ {
    move |source| CliError::Io { path: path.to_path_buf(), source }
}

fn bar(len: usize, quiet: bool, prefix: &str) -> indicatif::ProgressBar {
    if quiet {
        return indicatif::ProgressBar::hidden();
    }
    let b = indicatif::ProgressBar::new(len as u64);
    if let Ok(style) = indicatif::ProgressStyle::with_template("{prefix:>8} {bar:30} {pos}/{len} {msg} (eta {eta})") {
        b.set_style(style);
    }
    b.set_prefix(prefix.to_string());
    b
}

/// Set by SIGINT or SIGTERM: training writes a checkpoint and stops.
static STOP: std::sync::atomic::AtomicBool = std::sync::atomic::AtomicBool::new(false);

/// The largest training configuration read.
const MAX_CONFIG_BYTES: u64 = 1 << 20;

/// What a fresh run would replace in `out`, described for the refusal.
fn existing_run(out: &Path, config: &str) -> Option<String> {
    let ckpt = out.join("checkpoint.json");
    let files: Vec<&str> = ["checkpoint.json", "model.json", "loss.csv"].into_iter().filter(|f| out.join(f).exists()).collect();
    if files.is_empty() {
        return None;
    }
    let what = match Checkpoint::load(&ckpt) {
        Ok(c) => match config_difference(&c.config, config) {
            None => format!("a run of this configuration ({} iterations done): --resume to finish it, --extend N to train it further", c.iterations_done),
            Some((key, _, _)) => format!("a run of another configuration (`{key}` differs)"),
        },
        Err(_) => "another run's files".to_string(),
    };
    Some(format!("{} holds {what} ({}); --overwrite replaces them, or choose another --out", out.display(), files.join(", ")))
}

/// `diffsim train CONFIG`, in one process or data-parallel over the ranks
/// of `world` (`mpirun -np K diffsim train CONFIG`): every rank reads the
/// configuration and builds the data; rank 0 reads or starts the
/// checkpoint and sends it to the others, and alone writes the outputs.
/// The parameters are the same, bit for bit, for any number of ranks.
pub(super) fn train_cmd(a: TrainArgs, world: &World) -> Result<(), CliError> {
    let text = diffsim::files::read_text(&a.config, MAX_CONFIG_BYTES, "training configuration")?;
    let cfg = TrainConfig::parse(&text)?;
    if a.checkpoint_every == 0 || !(a.checkpoint_seconds.is_finite() && a.checkpoint_seconds > 0.0) {
        return Err(CliError::Argument { arg: "--checkpoint-every/--checkpoint-seconds", reason: "must be positive".into() });
    }
    // Every rank must train the same configuration.
    let bytes: Vec<f64> = text.bytes().map(f64::from).collect();
    world.check_same("configurations", || format!("reading {}", a.config.display()), &[&bytes])?;
    let ckpt_path = a.out.join("checkpoint.json");
    let log_path = a.out.join("loss.csv");
    let names = cfg.net.param_names();
    let mut layout = ParamStore::new();
    layout.add("net.", &names, &vec![0.0; cfg.net_params()]);
    let total = cfg.settings.iterations as u64;
    let (mut store, mut opt, done) = world.from_root(|| start_or_continue(&a, &cfg, &text, &layout))?;
    let full = match a.extend {
        Some(n) => target_of(done, n)?,
        None => total,
    };
    let target = match a.until {
        Some(until) if until <= done => {
            return Err(CliError::Argument { arg: "--until", reason: format!("the run is at iteration {done} already") });
        }
        Some(until) => full.min(until),
        None => full,
    };
    if world.is_root() && a.resume && done == total {
        eprintln!("the run had finished ({done} iterations); writing its outputs again");
    }
    let mut rng = <rand::rngs::StdRng as rand::SeedableRng>::seed_from_u64(cfg.settings.seed);
    let train_set = if cfg.nu_range.is_none() { cfg.setup.dataset(cfg.data.train, cfg.data.steps, &mut rng) } else { Vec::new() };
    let test_set = cfg.setup.dataset(cfg.data.test, cfg.data.test_steps, &mut rng);
    let data = match cfg.nu_range {
        None => TrainData::Fixed(&train_set),
        Some(nu) => TrainData::Random { nu, horizon: cfg.data.steps },
    };
    let iterations = usize::try_from(target - done).map_err(|_| CliError::Argument { arg: "--extend", reason: "too many iterations".into() })?;
    let settings = diffsim_studies::burgers::TrainParams { first: done as usize + 1, iterations, ..cfg.settings };
    // Rank 0 logs (the log trimmed to the checkpoint by start_or_continue)
    // and checkpoints; every rank stops at the same iteration.
    let mut log = if world.is_root() { CsvLog::append(&log_path).map_err(io(&log_path))? } else { CsvLog::none() };
    // Ctrl-C or a termination request: checkpoint and stop after the
    // current iteration (a second handler cannot be set; ignore).
    let _ = ctrlc::set_handler(|| STOP.store(true, std::sync::atomic::Ordering::SeqCst));
    let progress = bar(settings.iterations, a.quiet || !world.is_root(), &settings.method.name());
    let mut last_loss = f64::NAN;
    let rows = diffsim::train::on_row(|r: &Row, _: &[f64], _: &Optimizer| {
        last_loss = r.loss;
        progress.set_message(format!("loss {:.3e}", r.loss));
        progress.inc(1);
        std::ops::ControlFlow::Continue(())
    });
    let save = diffsim::train::save_with(|it: usize, theta: &[f64], opt: &Optimizer| {
        if !world.is_root() {
            return Ok(());
        }
        let params = ParamStore { entries: layout.entries.clone(), values: theta.to_vec() };
        let c = Checkpoint { format: FORMAT, config: text.clone(), iterations_done: it as u64, params, optimizer: opt.clone() };
        c.save(&ckpt_path).map_err(|e| diffsim::train::TrainError::Observer(e.to_string()))
    });
    let watch = Watch { checkpoint: CheckpointPolicy { every: a.checkpoint_every, seconds: a.checkpoint_seconds }, stop: Some(&STOP) };
    // The log is flushed before each checkpoint: it never lags it.
    let trained = train(&cfg.setup, &cfg.net, &mut store.values, &mut opt, data, &settings, world, watch, ((&mut log, rows), save));
    progress.finish_and_clear();
    let (time, info) = trained?;
    if info.stopped {
        return Err(interrupted(&a, info.last as u64, target));
    }
    if !world.is_root() {
        // Rank 0 writes the outputs; the other ranks are done.
        return Ok(());
    }
    log.flush().map_err(io(&log_path))?;
    if target < full {
        println!(
            "stopped after iteration {target} of {total} as asked (--until); continue with: diffsim train {} --out {} --resume",
            a.config.display(),
            a.out.display()
        );
        return Ok(());
    }
    // The whole loss history (this run and earlier ones) for the plot.
    let history = diffsim::files::read_text(&log_path, 1 << 30, "loss log")?;
    let points: Vec<(f64, f64)> = history
        .lines()
        .skip(1)
        .filter_map(|l| {
            let mut f = l.split(',');
            Some((f.next()?.parse().ok()?, f.next()?.parse().ok()?))
        })
        .collect();
    plot_or_warn(
        &a.out.join("loss.png"),
        &Axes { title: "training loss", x: "iteration", y: "loss", log_x: false, log_y: true },
        &[Series { name: settings.method.name(), points, color: 0, markers: false }],
    );
    let done = target;
    store.save(&a.out.join("model.json")).map_err(|e| CliError::Argument { arg: "--out", reason: e.to_string() })?;
    let source =
        evaluate(&cfg.setup, &cfg.net, None, &test_set, cfg.data.test_steps).map_err(|e| CliError::Argument { arg: "config", reason: e.to_string() })?;
    let corrected = evaluate(&cfg.setup, &cfg.net, Some(&store.values), &test_set, cfg.data.test_steps)
        .map_err(|e| CliError::Argument { arg: "config", reason: e.to_string() })?;
    let ranks = if world.size() > 1 { format!(" over {} ranks", world.size()) } else { String::new() };
    println!(
        "{} iterations ({} in total){ranks} in {:.1} s ({:.1} ms/iteration); last loss {:.3e}",
        settings.iterations,
        done,
        time.total,
        1e3 * time.total / settings.iterations.max(1) as f64,
        last_loss
    );
    println!(
        "test rollouts ({} steps): relative L2 error, mean over steps: source {:.4}, corrected {:.4}",
        cfg.data.test_steps,
        mean(&source),
        mean(&corrected)
    );
    println!("wrote loss.csv, loss.png, model.json, checkpoint.json to {}", a.out.display());
    Ok(())
}

/// A run stopped at a signal after iteration `at`.
fn interrupted(a: &TrainArgs, at: u64, target: u64) -> CliError {
    CliError::Interrupted {
        done: at,
        target,
        detail: String::new(),
        resume: format!("diffsim train {} --out {} --resume", a.config.display(), a.out.display()),
    }
}

/// Rank 0's part of starting `diffsim train`: the parameters, optimizer
/// and iterations done, from the checkpoint (`--resume`, `--extend`) or
/// fresh (then written as the checkpoint of iteration 0).
/// The iteration `--extend n` trains to from `done`: at least one more,
/// and within [`MAX_ITERATIONS`].
fn target_of(done: u64, n: usize) -> Result<u64, CliError> {
    let arg = "--extend";
    if n == 0 {
        return Err(CliError::Argument { arg, reason: "must be at least 1 (the number of iterations to train beyond the checkpoint)".into() });
    }
    match done.checked_add(n as u64) {
        Some(t) if t <= MAX_ITERATIONS => Ok(t),
        _ => Err(CliError::Argument { arg, reason: format!("{done} + {n} iterations is past the most a run may have ({MAX_ITERATIONS})") }),
    }
}

/// The most iterations a training run may reach by `--extend`.
const MAX_ITERATIONS: u64 = 1 << 40;

fn start_or_continue(a: &TrainArgs, cfg: &TrainConfig, text: &str, layout: &ParamStore) -> Result<(ParamStore, Optimizer, u64), CliError> {
    std::fs::create_dir_all(&a.out).map_err(io(&a.out))?;
    let ckpt_path = a.out.join("checkpoint.json");
    let log_path = a.out.join("loss.csv");
    let total = cfg.settings.iterations as u64;
    if a.resume || a.extend.is_some() {
        if !ckpt_path.exists() {
            return Err(CliError::Argument {
                arg: if a.resume { "--resume" } else { "--extend" },
                reason: format!("nothing to continue: {} does not exist (start the run without it)", ckpt_path.display()),
            });
        }
        let c = Checkpoint::load(&ckpt_path)?;
        c.check(&ckpt_path, text, layout, &cfg.optimizer)?;
        // Counts are checked before anything is written (the log's trim below).
        if let Some(n) = a.extend {
            target_of(c.iterations_done, n)?;
        }
        if a.resume && c.iterations_done > total {
            return Err(CliError::Argument {
                arg: "--resume",
                reason: format!("the checkpoint has {} iterations, more than the configured {total} (use --extend to train further)", c.iterations_done),
            });
        }
        CsvLog::trim(&log_path, c.iterations_done as usize).map_err(io(&log_path))?;
        return Ok((c.params, c.optimizer, c.iterations_done));
    }
    if !a.overwrite
        && let Some(what) = existing_run(&a.out, text)
    {
        return Err(CliError::Argument { arg: "--out", reason: what });
    }
    let mut store = layout.clone();
    store.values = initial_params(&cfg.net, cfg.settings.seed);
    let opt = if cfg.optimizer == "sgd" { Optimizer::sgd(cfg.settings.lr) } else { Optimizer::adam(cfg.settings.lr) };
    // Iteration 0 is a checkpoint too: from the first moment the folder
    // names its configuration and can be resumed.
    Checkpoint { format: FORMAT, config: text.to_string(), iterations_done: 0, params: store.clone(), optimizer: opt.clone() }.save(&ckpt_path)?;
    CsvLog::trim(&log_path, 0).map_err(io(&log_path))?;
    Ok((store, opt, 0))
}

pub(super) fn experiment(c: ExperimentCommand, world: &World) -> Result<(), CliError> {
    match c {
        ExperimentCommand::SolBurgers(a) => sol_burgers(a, world),
        ExperimentCommand::SolWake(a) => sol_wake(a, world),
        ExperimentCommand::HigOscillators(a) => hig_oscillators(a, world),
        ExperimentCommand::SipHeat(a) => sip_heat(a),
        ExperimentCommand::SipSmoke(a) => super::pg::sip_smoke(a),
        ExperimentCommand::Cavity(a) => super::flow::cavity(a),
        ExperimentCommand::Cylinder(a) => super::flow::cylinder(a),
        ExperimentCommand::DragShape(a) => super::flow::drag_shape(a),
        ExperimentCommand::DragNet(a) => super::flow::drag_net(a),
    }
}

/// A study's error as the command line reports it: a part that cannot be
/// saved as itself, a training error in its own words.
pub(super) fn study_error(arg: &'static str) -> impl FnOnce(diffsim_studies::StudyError) -> CliError {
    use diffsim_studies::StudyError;
    move |e| match e {
        StudyError::Part(e) => e.into(),
        StudyError::Train(e) => CliError::Argument { arg, reason: e.to_string() },
        StudyError::Flow(e) => e.into(),
        StudyError::Rollout(e) => e.into(),
        StudyError::NotReported { what, reason } => CliError::NotReported { what, reason },
        e => CliError::Argument { arg, reason: e.to_string() },
    }
}

/// This command line with `--resume` (once, at the end).
fn resume_command() -> String {
    let args: Vec<String> = std::env::args().skip(1).filter(|a| a != "--resume").collect();
    format!("diffsim {} --resume", args.join(" "))
}

/// Ctrl-C in a study whose parts are not checkpointed inside: says what is
/// kept and how to go on, and exits with 130 (a part being saved is
/// written atomically: there or not).
fn exit_on_interrupt(out: &Path, parts: &'static str) {
    let dir = out.join("parts");
    let resume = resume_command();
    let _ = ctrlc::set_handler(move || {
        eprintln!(
            "interrupted: the finished parts are kept in {}; `{resume}` runs only the rest ({parts} cannot be resumed midway and starts again)",
            dir.display()
        );
        std::process::exit(130);
    });
}

fn sip_heat(a: SipArgs) -> Result<(), CliError> {
    use diffsim_studies::heat::{HeatParams, Method, run};
    let mut cfg = match a.setup.as_str() {
        "small" => HeatParams::standard(),
        "published" => HeatParams::published(50),
        other => return Err(CliError::Argument { arg: "--setup", reason: diffsim::words::unknown("setup", other, &["small", "published"]) }),
    };
    if let Some(it) = a.iterations {
        if it == 0 {
            return Err(CliError::Argument { arg: "--iterations", reason: "must be at least 1".into() });
        }
        cfg.iterations = it;
    }
    if let Some(n) = a.test_samples {
        if n == 0 {
            return Err(CliError::Argument { arg: "--test-samples", reason: "must be at least 1".into() });
        }
        cfg.test_samples = n;
    }
    if let Some(n) = a.batch {
        if n == 0 {
            return Err(CliError::Argument { arg: "--batch", reason: "must be at least 1".into() });
        }
        cfg.batch = n;
    }
    if let Some(lr) = a.gd_lr {
        if !(lr.is_finite() && lr > 0.0) {
            return Err(CliError::Argument { arg: "--gd-lr", reason: format!("must be a positive number, got {lr}") });
        }
        cfg.gd_lr = lr;
    }
    // Held to the end: the folder is this run's while it writes.
    let _out = super::claim_out(&a.out, a.overwrite, &[])?;
    let parts = Parts::open(&a.out.join("parts"), format!("sip-heat\n{cfg:#?}"), a.resume)?;
    exit_on_interrupt(&a.out, "each optimizer's run");
    let progress = bar(Method::ALL.len() * cfg.iterations, a.json, "train");
    let start = std::time::Instant::now();
    let report = run(&cfg, Some(&parts), |m, _| {
        progress.set_message(m.name());
        progress.inc(1);
    })
    .map_err(study_error("sip-heat"))?;
    progress.finish_and_clear();
    let table = report.table();
    let series: Vec<Series> =
        report.curves.iter().enumerate().map(|(k, c)| Series { name: c.name.clone(), points: c.points.clone(), color: k, markers: false }).collect();
    write_error_files(
        &a.out,
        &table,
        &report.csv(),
        &Axes { title: "inverse heat: state error vs training time", x: "seconds", y: "mean L1 error of x", log_x: false, log_y: true },
        &series,
    )?;
    let budget_s = start.elapsed().as_secs_f64();
    if a.json {
        let mut obj = report.json();
        obj.insert("setup".into(), a.setup.clone().into());
        obj.insert("iterations".into(), cfg.iterations.into());
        obj.insert("budget_s".into(), budget_s.into());
        println!("{}", serde_json::Value::Object(obj));
    } else {
        print!("{table}");
        println!("wrote table.md, error.csv, error.png to {} ({budget_s:.0} s)", a.out.display());
    }
    Ok(())
}

fn hig_oscillators(a: HigArgs, world: &World) -> Result<(), CliError> {
    use diffsim_studies::oscillators::{OscMethod, OscParams, run};
    // A day per method at most: a longer wall-clock budget is an input
    // error, not a study.
    if !(a.budget > 0.0 && a.budget <= 86_400.0) {
        return Err(CliError::Argument { arg: "--budget", reason: format!("must be a positive number of seconds, at most 86400 (a day), got {}", a.budget) });
    }
    use diffsim::train::hig::PowerMethod;
    let method = match a.decomposition.as_str() {
        "auto" => None,
        "svd" => Some(PowerMethod::SVD_F64),
        "gram" => Some(PowerMethod::GRAM_F64),
        "svd-f32" => Some(PowerMethod::SVD_F32),
        other => {
            return Err(CliError::Argument {
                arg: "--decomposition",
                reason: diffsim::words::unknown("decomposition", other, &["auto", "svd", "gram", "svd-f32"]),
            });
        }
    };
    if a.updates == Some(0) {
        return Err(CliError::Argument { arg: "--updates", reason: "must be at least 1".into() });
    }
    let (mut lin, mut nonlin) = (OscParams::linear(a.budget), OscParams::nonlinear(a.budget));
    (lin.hig.method, lin.gn.method, nonlin.hig.method, nonlin.gn.method) = (method, method, method, method);
    (lin.updates, nonlin.updates) = (a.updates, a.updates);
    let settings = format!("hig-oscillators\n{lin:#?}\n{nonlin:#?}");
    // Rank 0 holds the folder to the end: it alone writes there.
    let _out = if world.is_root() { Some(super::claim_out(&a.out, a.overwrite, &[])?) } else { None };
    let parts = if world.is_root() { Parts::open(&a.out.join("parts"), settings, a.resume)? } else { Parts::kept_elsewhere(&a.out.join("parts"), settings) };
    exit_on_interrupt(&a.out, "each problem's runs (timed by the wall clock)");
    let quiet = a.json || !world.is_root();
    let say = |problem: &'static str, m: OscMethod, t: f64| {
        if !quiet {
            eprint!("\r{problem}: {} {t:.0} s   ", m.name());
        }
    };
    let report = run(&lin, &nonlin, world, Some(&parts), say).map_err(study_error("hig-oscillators"))?;
    if !world.is_root() {
        return Ok(());
    }
    if !a.json {
        eprintln!();
    }
    let table = report.table();
    let md = a.out.join("table.md");
    diffsim::files::write(&md, &table).map_err(io(&md))?;
    let path = a.out.join("loss.csv");
    diffsim::files::write(&path, report.csv()).map_err(io(&path))?;
    let mut series = Vec::new();
    for (problem, (label, curves)) in [("linear", &report.linear), ("nonlinear", &report.nonlinear)].into_iter().enumerate() {
        for (k, c) in curves.iter().enumerate() {
            series.push(Series { name: format!("{} ({label})", c.name), points: c.points.clone(), color: 3 * problem + k, markers: false });
        }
    }
    plot_or_warn(
        &a.out.join("loss.png"),
        &Axes { title: "coupled oscillators: test loss vs training time", x: "seconds", y: "test loss", log_x: false, log_y: true },
        &series,
    );
    if a.json {
        println!("{}", serde_json::Value::Object(report.json()));
    } else {
        print!("{table}");
        println!("wrote table.md, loss.csv, loss.png to {}", a.out.display());
    }
    Ok(())
}

fn sol_burgers(a: SolArgs, world: &World) -> Result<(), CliError> {
    let mut cfg = StudyParams::standard(a.study.quick);
    if a.width == 0 {
        return Err(CliError::Argument { arg: "--width", reason: "must be at least 1".into() });
    }
    let act = a.study.activation(diffsim_studies::burgers::STUDY_ACTIVATION)?;
    cfg.net =
        diffsim_studies::burgers::correction_net(&a.net, cfg.setup.coarse.n, a.width, act).map_err(|reason| CliError::Argument { arg: "--net", reason })?;
    a.study.apply(&mut cfg)?;
    run_sol_study(&cfg, "sol-burgers", "Burgers", &a.study, &a.out, world)
}

fn sol_wake(a: SolWakeArgs, world: &World) -> Result<(), CliError> {
    let mut cfg = StudyParams::wake(a.study.quick);
    cfg.net = cfg.setup.network(a.study.activation(diffsim_studies::wake::STUDY_ACTIVATION)?);
    a.study.apply(&mut cfg)?;
    if let Some(t) = a.steps {
        if t == 0 {
            return Err(CliError::Argument { arg: "--steps", reason: "must be at least 1".into() });
        }
        cfg.eval_steps = t;
        cfg.train_steps = t + 16;
    }
    if !a.study.json && world.is_root() {
        let fine = cfg.setup.fine();
        println!("computing {} reference trajectories on the {}×{} grid …", cfg.train + cfg.test, fine.n[0], fine.n[1]);
    }
    run_sol_study(&cfg, "sol-wake", "flow past a disc", &a.study, &a.out, world)
}

/// Runs a solver-in-the-loop study; writes its table, errors per step,
/// plots and (with `json`) the one-line result.
/// Saved parts live in `OUT/parts`; with `resume` the study goes on from
/// them. Ctrl-C checkpoints the variant in progress and exits with the
/// command that resumes. Over several ranks the variants train
/// data-parallel and rank 0 writes every file.
fn run_sol_study<P: SolProblem + std::fmt::Debug>(
    cfg: &StudyParams<P>,
    command: &'static str,
    title: &str,
    study_args: &StudyArgs,
    out: &Path,
    world: &World,
) -> Result<(), CliError> {
    use diffsim_studies::sol::{Resumable, StudyError};
    let json = study_args.json;
    // Everything the results depend on, one setting per line.
    let settings = format!("{command}\n{cfg:#?}");
    // Rank 0 holds the folder to the end: it alone writes there.
    let _out = if world.is_root() { Some(super::claim_out(out, study_args.overwrite, &[])?) } else { None };
    let parts =
        if world.is_root() { Parts::open(&out.join("parts"), settings, study_args.resume)? } else { Parts::kept_elsewhere(&out.join("parts"), settings) };
    let total = cfg.methods.len() * cfg.settings.iterations;
    let progress = bar(total, json || !world.is_root(), "train");
    let _ = ctrlc::set_handler(|| STOP.store(true, std::sync::atomic::Ordering::SeqCst));
    let resumable = Resumable { parts: &parts, every_s: study_args.checkpoint_seconds, stop: &STOP };
    let results = study(cfg, Some(resumable), world, |name, r| {
        progress.set_message(format!("{name} loss {:.3e}", r.loss));
        progress.inc(1);
    });
    progress.finish_and_clear();
    let results = match results {
        Ok(r) => r,
        Err(StudyError::Interrupted { variant, done, of }) => {
            return Err(CliError::Interrupted { done: done as u64, target: of as u64, detail: format!(" in variant {variant}"), resume: resume_command() });
        }
        Err(StudyError::Part(e)) => return Err(e.into()),
        Err(e) => return Err(CliError::Argument { arg: command, reason: e.to_string() }),
    };
    if !world.is_root() {
        return Ok(());
    }

    let report = diffsim_studies::sol::SolReport::new(cfg, results);
    let results = &report.variants;
    let table = report.table();
    let md = out.join("table.md");
    diffsim::files::write(&md, &table).map_err(io(&md))?;
    // Errors per step.
    let csv = out.join("errors.csv");
    diffsim::files::write(&csv, report.csv()).map_err(io(&csv))?;
    let err_series: Vec<Series> = results
        .iter()
        .enumerate()
        .map(|(k, r)| Series {
            name: r.name.clone(),
            points: r.error.iter().enumerate().map(|(t, e)| ((t + 1) as f64, *e)).collect(),
            color: k,
            markers: false,
        })
        .collect();
    plot_or_warn(
        &out.join("error.png"),
        &Axes { title: &format!("{title}, {}-step test rollouts", cfg.eval_steps), x: "step", y: "relative L2 error", log_x: false, log_y: true },
        &err_series,
    );
    // Loss curves as moving averages over 50 iterations (a batch of 16 is noisy).
    let loss_series: Vec<Series> = results
        .iter()
        .enumerate()
        .skip(1)
        .map(|(k, r)| Series { name: r.name.clone(), points: moving_average(&r.loss, 50), color: k, markers: false })
        .collect();
    plot_or_warn(
        &out.join("loss.png"),
        &Axes { title: "training loss (moving average of 50)", x: "iteration", y: "loss", log_x: false, log_y: true },
        &loss_series,
    );
    if !json {
        print!("{table}");
        println!("wrote table.md, errors.csv, error.png, loss.png to {}", out.display());
    }
    if json {
        println!("{}", serde_json::Value::Object(report.json()));
    }
    Ok(())
}

/// `(i, mean of v[i+1−w..=i])` for every full window, 1-based iterations.
fn moving_average(v: &[f64], w: usize) -> Vec<(f64, f64)> {
    if v.len() < w {
        return v.iter().enumerate().map(|(i, l)| ((i + 1) as f64, *l)).collect();
    }
    let mut sum: f64 = v[..w].iter().sum();
    let mut out = vec![(w as f64, sum / w as f64)];
    for i in w..v.len() {
        sum += v[i] - v[i - w];
        out.push(((i + 1) as f64, sum / w as f64));
    }
    out
}
