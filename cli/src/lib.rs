//! The `diffsim` command line: argument parsing and the subcommands.

mod accuracy;
mod bench;
mod demo;
mod flow;
pub mod fuzz;
mod new;
mod pg;
pub mod plot;
mod scaling;
mod scene;
mod sweep;
mod train;

use clap::{Parser, Subcommand};
use thiserror::Error;

pub use diffsim_studies::measure::{interleaved_times, median_time, peak_rss_bytes, reset_peak_rss};

/// Errors reported by the command line: printed as one message, exit code 1.
#[derive(Debug, Error)]
pub enum CliError {
    /// An argument is out of its range.
    #[error("invalid argument {arg}: {reason}")]
    Argument {
        /// The flag.
        arg: &'static str,
        /// What is wrong with it.
        reason: String,
    },
    /// A rollout failed.
    #[error(transparent)]
    Rollout(#[from] diffsim::rollout::RolloutError),
    /// Training failed (a rollout, or ranks that no longer agree).
    #[error("training: {0}")]
    Train(#[from] diffsim_studies::sol::TrainError),
    /// A file could not be written.
    #[error("cannot write {path}: {source}")]
    Io {
        /// The file or directory.
        path: std::path::PathBuf,
        /// The cause.
        source: std::io::Error,
    },
    /// An output folder cannot be used (another run's, locked, an input).
    #[error(transparent)]
    Out(#[from] diffsim::files::OutDirError),
    /// An input file could not be read.
    #[error(transparent)]
    Read(#[from] diffsim::files::ReadError),
    /// A run does not fit the memory budget.
    #[error(transparent)]
    Memory(#[from] diffsim::memory::MemoryError),
    /// `DIFFSIM_MAX_ISA` names no instruction set.
    #[error(transparent)]
    Isa(#[from] diffsim_solvers::simd::IsaError),
    /// A training checkpoint cannot be written or used.
    #[error(transparent)]
    Checkpoint(#[from] diffsim::train::checkpoint::CheckpointError),
    /// Training stopped at a signal after writing a checkpoint.
    #[error("interrupted after iteration {done} of {target}{detail}; the checkpoint is written. Resume with: {resume}")]
    Interrupted {
        /// Iterations done (and checkpointed).
        done: u64,
        /// Iterations the run was to reach.
        target: u64,
        /// More on where (`" in variant sol4"`), or empty.
        detail: String,
        /// The command that resumes it.
        resume: String,
    },
    /// A scene file is malformed.
    #[error(transparent)]
    Scene(#[from] diffsim::scene::SceneError),
    /// A viscous flow could not be simulated.
    #[error(transparent)]
    Flow(#[from] diffsim_solvers::flow::FlowError),
    /// Training the shape network failed.
    #[error(transparent)]
    ShapeNet(#[from] diffsim_studies::shape_net::ShapeNetError),
    /// A scene run failed.
    #[error(transparent)]
    Run(#[from] diffsim::scene::RunError),
    /// A run against an exact solution failed.
    #[error(transparent)]
    Accuracy(#[from] diffsim_studies::accuracy::AccuracyError),
    /// A stability case did not pass (the report is printed above).
    #[error("{0} stability case(s) did not pass (see the report above)")]
    StabilityFailed(usize),
    /// A gradient check did not pass (the report is printed above).
    #[error("a gradient check did not pass (see the report above)")]
    ChecksFailed,
    /// A training configuration is malformed.
    #[error(transparent)]
    Config(#[from] diffsim_studies::config::ConfigError),
    /// The processes of an mpirun cannot work together.
    #[error(transparent)]
    Distributed(#[from] diffsim::distributed::DistributedError),
    /// A run ended with a figure that is not a result (NaN, infinite, or
    /// outside what the method can give): nothing is printed as if it were.
    #[error("{what}: {reason}; no result is reported")]
    NotReported {
        /// The run.
        what: String,
        /// The figure and what is wrong with it.
        reason: String,
    },
    /// An error every rank reached together (they agreed on it first), so
    /// that rank 0 alone reports it.
    #[error(transparent)]
    EveryRank(Box<CliError>),
    /// The thread pool could not be built.
    #[error("cannot start {threads} threads: {source}")]
    Threads {
        /// Requested thread count.
        threads: usize,
        /// The cause.
        source: rayon::ThreadPoolBuildError,
    },
}

/// diffsim: differentiable physics with Enzyme-generated adjoints.
#[derive(Debug, Parser)]
#[command(name = "diffsim", version, about)]
pub struct Cli {
    #[command(subcommand)]
    command: Command,
    /// Memory the command may use (`50MB`, `2GiB`; default half of the
    /// machine's memory): a run that cannot fit is refused up front with
    /// its estimate, and a gradient picks its checkpointing to fit.
    #[arg(long, global = true, value_name = "BYTES")]
    memory_budget: Option<String>,
}

#[derive(Debug, Subcommand)]
enum Command {
    /// Benchmark problems of docs/benchmarks.md.
    #[command(subcommand)]
    Bench(bench::BenchCommand),
    /// Demonstrations.
    #[command(subcommand)]
    Demo(DemoCommand),
    /// Gradient checks (finite differences, Taylor, dot product) of a whole
    /// P1 rollout, Enzyme and hand-written.
    Check(CheckArgs),
    /// Simulate a scene file; writes the fields as .npy and the smoke as PNG.
    Run(scene::RunArgs),
    /// The loss of a scene file and its gradient with respect to the inputs
    /// its [loss] names, as .npy; --check runs the gradient checks.
    Grad(scene::GradArgs),
    /// Run a scene for every combination of values of some of its keys
    /// (`--set KEY=V1,V2,…`), spread over the ranks under `mpirun -np K`;
    /// writes each run's fields and pictures and one table of the runs.
    Sweep(sweep::SweepArgs),
    /// Train a correction network through the coarse Burgers solver from a
    /// TOML configuration; writes the loss log, its plot, the model and a
    /// checkpoint to resume from.
    Train(train::TrainArgs),
    /// Experiments that reproduce published studies.
    #[command(subcommand)]
    Experiment(train::ExperimentCommand),
    /// Error against exact solutions versus wall time and memory over a
    /// sweep of resolutions, time steps, schemes and tolerances (or, with
    /// --gradients, of gradient methods); marks the Pareto front and writes
    /// a CSV, a markdown table and plots (PNG, SVG).
    Pareto(accuracy::ParetoArgs),
    /// The hard cases (stiff diffusion, shocks, long rollouts,
    /// ill-conditioned solves, near-singular Jacobians, NaN detection): a
    /// report, and a non-zero exit if any case is not stable.
    Stability(accuracy::StabilityArgs),
    /// A crate of your own on diffsim, ready to build: a solver (Fisher–KPP)
    /// with its gradient checks, a rollout with a loss at several steps, the
    /// checks through it for the initial state and the parameters, and an
    /// Adam fit; the toolchain file, the profile settings and the Enzyme log
    /// guard. Then: cd PATH && cargo run --release.
    New(new::NewArgs),
    /// What this build has (version, threads, MPI) and, under `mpirun -np
    /// K`, the ranks it runs as, checked by an exchange between them.
    Info,
}

#[derive(Debug, clap::Args)]
struct CheckArgs {
    /// Cells (≥ 3).
    #[arg(long, default_value_t = 256)]
    n: usize,
    /// Steps (≥ 1).
    #[arg(long, default_value_t = 256)]
    steps: usize,
}

#[derive(Debug, Subcommand)]
enum DemoCommand {
    /// A smoke plume rising around an obstacle, written as PNG.
    Plume(demo::PlumeArgs),
}

/// The `diffsim` command: parses the arguments (negative numbers are
/// values, `--re -1`, not flags), runs, and on an error prints one line and
/// exits non-zero.
pub fn main() {
    use clap::{CommandFactory, FromArgMatches};
    // A closed pipe (`diffsim … | head`) ends the command quietly, as
    // command-line tools do; Rust ignores SIGPIPE, and the write then fails.
    // SAFETY: setting a signal's disposition to its default at start-up,
    // before any thread exists.
    unsafe {
        libc::signal(libc::SIGPIPE, libc::SIG_DFL);
    }
    diffsim::memory::keep_freed_memory();
    // Standard output that cannot be written (a full disk, /dev/full) is an
    // error that says so, not a backtrace: `println!` panics there, and the
    // hook turns that one panic into the error line and exit code 1.
    let default = std::panic::take_hook();
    std::panic::set_hook(Box::new(move |info| {
        let message = info.payload().downcast_ref::<String>().map(String::as_str).or_else(|| info.payload().downcast_ref::<&str>().copied());
        match message.and_then(|m| m.strip_prefix("failed printing to stdout: ")) {
            Some(cause) => {
                say_error(&format!("error: cannot write the output: {cause}"));
                std::process::exit(1);
            }
            None => default(info),
        }
    }));
    fn negative(c: clap::Command) -> clap::Command {
        c.allow_negative_numbers(true).mut_subcommands(negative)
    }
    let matches = negative(Cli::command()).get_matches();
    let cli = Cli::from_arg_matches(&matches).unwrap_or_else(|e| e.exit());
    if let Err(e) = run(cli) {
        say_error(&format!("error: {e}"));
        std::process::exit(e.exit_code());
    }
}

/// Writes one error line to standard error in a single write: ranks of an
/// mpirun share the terminal, and `eprintln!` writes a formatted line in
/// pieces, which interleaved ("error on rank error on rank 0 of 21: …").
fn say_error(line: &str) {
    use std::io::Write;
    let _ = std::io::stderr().write_all(format!("{line}\n").as_bytes());
}

/// `--overwrite` for commands whose `--out` is claimed by [`claim_out`].
#[derive(Debug, Clone, Copy, clap::Args)]
pub(crate) struct Overwrite {
    /// Write into --out even when it holds another run's results or other
    /// files (the earlier run's files are removed, others kept).
    #[arg(long)]
    overwrite: bool,
}

impl Overwrite {
    /// What a claim does with a folder holding another run's results:
    /// continue it for a `--resume`, replace them for `--overwrite`, else
    /// refuse.
    fn existing(self, resume: bool) -> diffsim::files::Existing {
        use diffsim::files::Existing;
        match (resume, self.overwrite) {
            (true, _) => Existing::Continue,
            (false, true) => Existing::Replace,
            (false, false) => Existing::Refuse,
        }
    }
}

/// Claims the output folder `dir` for this command
/// ([`diffsim::files::OutDir`]): the run is the command line without the
/// options that do not change its results (`--out`, `--overwrite`,
/// `--resume`, `--quiet`, `--json`), so the same experiment again writes
/// beside its results, another is refused unless `--overwrite`, and
/// `--resume` continues whatever the folder holds (the study's saved parts
/// check their settings); `inputs` are never written over.
fn claim_out(dir: &std::path::Path, overwrite: Overwrite, inputs: &[&std::path::Path]) -> Result<diffsim::files::OutDir, CliError> {
    let mut words = Vec::new();
    let mut resume = false;
    let mut args = std::env::args().skip(1);
    while let Some(a) = args.next() {
        match a.as_str() {
            "--out" => {
                args.next();
            }
            "--resume" => resume = true,
            "--overwrite" | "--quiet" | "--json" => {}
            _ if a.starts_with("--out=") => {}
            _ => words.push(a),
        }
    }
    // A resumed study continues its folder: its saved parts name any
    // setting that differs.
    Ok(diffsim::files::OutDir::claim(dir, &format!("diffsim {}", words.join(" ")), inputs, overwrite.existing(resume))?)
}

/// Refuses a run's figures when one is NaN or infinite: `what` names the
/// run, `figures` each figure by name.
fn finite_figures(what: &str, figures: &[(&str, f64)]) -> Result<(), CliError> {
    diffsim_studies::finite_figures(what, figures).map_err(train::study_error("figures"))
}

/// Writes a line plot; a plot that cannot be drawn (no font) is a warning,
/// not an error (the CSV or .npy beside it holds the numbers). Returns
/// whether it was written.
fn plot_or_warn(path: &std::path::Path, axes: &crate::plot::Axes<'_>, series: &[crate::plot::Series]) -> bool {
    match crate::plot::line_plot(path, axes, series) {
        Ok(()) => true,
        Err(e) => {
            eprintln!("warning: {e}");
            false
        }
    }
}

/// The checkpointing of a gradient for `job`, with `other` bytes held
/// besides: as given by `--checkpoint` (refused when its states exceed the
/// memory budget), or for `auto` the fastest mode within the budget by the
/// cost model ([`diffsim::rollout::plan`]). Returns the plan and whether it
/// was chosen.
fn checkpointing(arg: &str, job: &diffsim::rollout::plan::Job, other: u64, what: &str) -> Result<(diffsim::rollout::plan::Plan, bool), CliError> {
    use diffsim::rollout::{Checkpointing, plan};
    if arg == "auto" {
        return Ok((plan::choose(job, other, diffsim::memory::budget(), what)?, true));
    }
    let mode: Checkpointing = arg.parse().map_err(|reason| CliError::Argument { arg: "--checkpoint", reason })?;
    let p = plan::estimate(mode.resolve(job.steps), job);
    let hint = Some("--checkpoint auto to choose a mode that fits".into());
    diffsim::memory::check(what, plan::describe(&p, job, other), Some(p.bytes.saturating_add(other)), hint)?;
    Ok((p, false))
}

/// Runs the command line.
pub fn run(cli: Cli) -> Result<(), CliError> {
    diffsim_solvers::simd::max_isa_from_env()?;
    if let Some(b) = &cli.memory_budget {
        diffsim::memory::set_budget(diffsim::memory::parse_bytes(b)?);
    }
    let world = diffsim::distributed::World::from_launch()?;
    // The commands that run over several ranks so far; the others refuse them.
    let name = match &cli.command {
        Command::Info | Command::Bench(bench::BenchCommand::Exchange(_) | bench::BenchCommand::Scaling(_)) => "",
        Command::Bench(_) => "bench",
        Command::Demo(_) => "demo",
        Command::Check(_) => "check",
        Command::Run(_) => "run",
        Command::Grad(_) => "grad",
        Command::Train(_) | Command::Sweep(_) => "",
        Command::Experiment(train::ExperimentCommand::SolBurgers(_) | train::ExperimentCommand::SolWake(_) | train::ExperimentCommand::HigOscillators(_)) => "",
        Command::Experiment(_) => "experiment",
        Command::Pareto(_) => "pareto",
        Command::Stability(_) => "stability",
        Command::New(_) => "new",
    };
    let result = if name.is_empty() { Ok(()) } else { world.one_process(name).map_err(CliError::from) }.and_then(|()| dispatch(cli.command, &world));
    match result {
        // An error on some ranks only (bad input one rank sees, a failed
        // write on rank 0) stops every rank: the others may be waiting in
        // an exchange for this one.
        Err(e) if world.size() > 1 && !e.on_every_rank() => {
            say_error(&format!("error on rank {} of {}: {e}", world.rank(), world.size()));
            world.abort(e.exit_code())
        }
        // The same error on every rank: rank 0 says it, then all exit
        // alike (after it has: mpirun stops the job at the first non-zero
        // exit).
        Err(e) if world.size() > 1 => {
            if world.is_root() {
                say_error(&format!("error: {e}"));
            }
            world.barrier();
            let code = e.exit_code();
            drop(world);
            std::process::exit(code)
        }
        r => r,
    }
}

impl CliError {
    /// The exit code: 130 for a run stopped by a signal (the shell's code
    /// for SIGINT), 1 for every other error.
    pub fn exit_code(&self) -> i32 {
        if matches!(self, CliError::Interrupted { .. }) { 130 } else { 1 }
    }

    /// Whether every rank of a run reaches this error together (a refusal
    /// of several ranks, a stop all ranks agreed on), so that they can end
    /// normally; any other error stops the run at once.
    fn on_every_rank(&self) -> bool {
        matches!(
            self,
            CliError::Interrupted { .. } | CliError::EveryRank(_) | CliError::Distributed(diffsim::distributed::DistributedError::OneProcessOnly { .. })
        )
    }
}

fn dispatch(command: Command, world: &diffsim::distributed::World) -> Result<(), CliError> {
    match command {
        Command::Info => info(world),
        Command::Bench(b) => bench::run(b, world),
        Command::Demo(DemoCommand::Plume(a)) => demo::plume(a),
        Command::Check(a) => check_p1(a),
        Command::Run(a) => scene::run(a),
        Command::Grad(a) => scene::grad(a),
        Command::Train(a) => train::train_cmd(a, world),
        Command::Sweep(a) => sweep::sweep(a, world),
        Command::Experiment(e) => train::experiment(e, world),
        Command::Pareto(a) => accuracy::pareto(a),
        Command::Stability(a) => accuracy::stability(a),
        Command::New(a) => new::new(a),
    }
}

/// `diffsim info`: the build, and the ranks with an exchange between them
/// (each rank's number and threads gathered on every rank; rank 0 prints).
fn info(world: &diffsim::distributed::World) -> Result<(), CliError> {
    let threads = rayon::current_num_threads();
    let all = world.all_gather(&[world.rank() as f64, threads as f64]);
    let ranks_ok = all.chunks(2).enumerate().all(|(r, c)| c[0] == r as f64);
    if world.is_root() {
        println!("diffsim {}", env!("CARGO_PKG_VERSION"));
        let isa = diffsim_solvers::simd::isa();
        let capped = if std::env::var_os(diffsim_solvers::simd::MAX_ISA_VAR).is_some() {
            format!(" (capped by {})", diffsim_solvers::simd::MAX_ISA_VAR)
        } else {
            String::new()
        };
        println!("vector instructions: {}{capped}", isa.name());
        println!("MPI: {}", diffsim::distributed::World::library().unwrap_or_else(|| "not in this build (built without the `mpi` feature)".into()));
        let per_rank: Vec<String> = all.chunks(2).map(|c| format!("{}", c[1])).collect();
        println!("ranks: {} (threads per rank: {}); exchange between the ranks: {}", world.size(), per_rank.join(", "), if ranks_ok { "ok" } else { "WRONG" });
    }
    Ok(())
}

/// Runs the three gradient checks on the P1 rollout `u0 ↦ u_T`.
/// The most steps `diffsim check` takes (its finite differences run the
/// rollout twice per cell: a million steps is already hours).
const MAX_CHECK_STEPS: usize = 1_000_000;

fn check_p1(a: CheckArgs) -> Result<(), CliError> {
    use diffsim::check::{CheckParams, check_all};
    use diffsim::problems::burgers::{BurgersEnzyme, BurgersHand, P1};
    use diffsim::rollout::{Checkpointing, Rollout, RolloutOperator};
    if a.n < 3 {
        return Err(CliError::Argument { arg: "--n", reason: format!("need at least 3 cells, got {}", a.n) });
    }
    if !(1..=MAX_CHECK_STEPS).contains(&a.steps) {
        return Err(CliError::Argument { arg: "--steps", reason: format!("need 1 to {MAX_CHECK_STEPS} steps, got {}", a.steps) });
    }
    // The states the binomial checkpointing keeps (⌈log₂ T⌉ + 1) and the
    // checks' own vectors (a few dozen of N), each N values, before any is
    // allocated: a size whose buffers overflow is refused here.
    let copies = 40 + u64::from(usize::BITS - a.steps.leading_zeros());
    diffsim::memory::check("check", format!("{} cells, {} steps", a.n, a.steps), diffsim::memory::f64s(&[a.n as u64, copies]), None)?;
    let p = P1::new(a.n, a.steps);
    let mode = Checkpointing::binomial_log(a.steps);
    let opts = CheckParams::default();
    let enzyme = BurgersEnzyme(p.cfg);
    let r = check_all(&RolloutOperator { rollout: Rollout::new(&enzyme, &[], a.steps)?, mode }, &p.u0, &[], &opts);
    println!("P1 rollout N = {} T = {} ({mode}), Enzyme step VJPs:\n{r}\n", a.n, a.steps);
    let passed = r.passed();
    let hand = BurgersHand(p.cfg);
    let r = check_all(&RolloutOperator { rollout: Rollout::new(&hand, &[], a.steps)?, mode }, &p.u0, &[], &opts);
    println!("P1 rollout, hand-written step adjoints:\n{r}");
    if passed && r.passed() {
        println!("\nall checks passed");
        Ok(())
    } else {
        Err(CliError::ChecksFailed)
    }
}
