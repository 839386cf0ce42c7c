//! The accuracy commands: `diffsim pareto PROBLEM [--gradients]` (error
//! versus time and memory over a sweep of configurations, with the Pareto
//! front marked) and `diffsim stability` (the hard cases).

use std::path::{Path, PathBuf};

use serde_json::Value;

use super::{CliError, plot_or_warn};
use crate::plot::{Axes, Series};
use diffsim_studies::accuracy::pareto::{ParetoParams, ParetoProblem, ParetoReport, run};

/// The problems `diffsim pareto` sweeps.
#[derive(Clone, Copy, Debug, PartialEq, Eq, clap::ValueEnum)]
pub enum Problem {
    /// Viscous Burgers (ν = 0.05, u₀ = sin x, t = 1) against Cole–Hopf.
    Burgers,
    /// The Taylor–Green vortex (ν = 0.01, t = 1) against its exact decay.
    TaylorGreen,
    /// The 3D Arnold–Beltrami–Childress flow (ν = 0.05, t = 1) by the
    /// Navier–Stokes operator against its exact decay.
    Abc,
    /// Schäfer–Turek's cylinder, case 2D-1: c_D against the tight
    /// reference value, by Newton's method and by pseudo-time marching.
    Cylinder,
}

/// Arguments of `diffsim pareto`.
#[derive(Debug, clap::Args)]
pub struct ParetoArgs {
    /// The problem.
    problem: Problem,
    /// Sweep gradient computations instead (finite differences at several
    /// steps, Enzyme and hand-written adjoints, stored and checkpointed).
    #[arg(long)]
    gradients: bool,
    /// Smaller grids (a run of seconds).
    #[arg(long)]
    quick: bool,
    /// Seconds of repeats per configuration for the median time.
    #[arg(long, default_value_t = 0.3)]
    budget: f64,
    /// Output directory (a subdirectory per problem): results.csv, table.md,
    /// error_time.png, error_time.svg.
    #[arg(long, default_value = "out/pareto")]
    out: PathBuf,
    #[command(flatten)]
    overwrite: super::Overwrite,
    /// Print one JSON array of the configurations as the last line.
    #[arg(long)]
    json: bool,
}

/// Runs `diffsim pareto`.
pub fn pareto(a: ParetoArgs) -> Result<(), CliError> {
    if !(a.budget >= 0.0 && a.budget <= 86_400.0) {
        return Err(CliError::Argument { arg: "--budget", reason: format!("must be between 0 and 86400 seconds (a day), got {}", a.budget) });
    }
    let problem = match (a.problem, a.gradients) {
        (Problem::Burgers, false) => ParetoProblem::Burgers,
        (Problem::TaylorGreen, false) => ParetoProblem::TaylorGreen,
        (Problem::Abc, false) => ParetoProblem::Abc,
        (Problem::Cylinder, false) => ParetoProblem::Cylinder,
        (Problem::Abc, true) => {
            return Err(CliError::Argument {
                arg: "--gradients",
                reason: "the ABC flow has no gradient sweep (the Navier–Stokes operator's gradient is checked in tests/navier_stokes.rs)".into(),
            });
        }
        (Problem::Cylinder, true) => {
            return Err(CliError::Argument {
                arg: "--gradients",
                reason: "the cylinder has no gradient sweep (its shape gradient is checked by `diffsim grad scenes/drag_body.toml --check`)".into(),
            });
        }
        (Problem::Burgers, true) => ParetoProblem::BurgersGradients,
        (Problem::TaylorGreen, true) => ParetoProblem::TaylorGreenGradients,
    };
    // Each problem has its own subfolder, claimed before the sweep runs.
    let dir = a.out.join(problem.name());
    let _out = super::claim_out(&dir, a.overwrite, &[])?;
    let report = run(&ParetoParams { problem, quick: a.quick, budget: a.budget }).map_err(super::train::study_error("pareto"))?;
    for w in &report.warnings {
        eprintln!("warning: {w}");
    }
    write_report(&dir, &report)?;
    if a.json {
        println!("{}", report.json());
    } else {
        print!("{}", report.markdown());
        println!("\nwritten to {}", dir.display());
    }
    Ok(())
}

/// results.csv, table.md, error_time.png and error_time.svg in `dir`.
fn write_report(dir: &Path, report: &ParetoReport) -> Result<(), CliError> {
    let io = |path: PathBuf| move |source| CliError::Io { path, source };
    std::fs::create_dir_all(dir).map_err(io(dir.to_path_buf()))?;
    diffsim::files::write(&dir.join("results.csv"), report.csv()).map_err(io(dir.join("results.csv")))?;
    diffsim::files::write(&dir.join("table.md"), format!("# {}\n\n{}", report.title(), report.markdown())).map_err(io(dir.join("table.md")))?;
    let (families, front) = report.series();
    let k = families.len();
    let mut series: Vec<Series> = families.into_iter().enumerate().map(|(color, (name, points))| Series { name, points, color, markers: true }).collect();
    series.push(Series { name: "Pareto front".into(), points: front, color: k, markers: false });
    let axes = Axes { title: report.title(), x: "wall time (s)", y: "relative error", log_x: true, log_y: true };
    for ext in ["png", "svg"] {
        plot_or_warn(&dir.join(format!("error_time.{ext}")), &axes, &series);
    }
    Ok(())
}

/// Arguments of `diffsim stability`.
#[derive(Debug, clap::Args)]
pub struct StabilityArgs {
    /// Print one JSON array of the cases as the last line.
    #[arg(long)]
    json: bool,
}

/// Runs `diffsim stability`.
pub fn stability(a: StabilityArgs) -> Result<(), CliError> {
    let cases = diffsim_studies::accuracy::stability::run_all();
    for c in &cases {
        println!("{:<32} {:<6} {}", c.case, if c.passed { "passed" } else { "FAILED" }, c.summary);
    }
    if a.json {
        println!("{}", Value::Array(cases.iter().map(|c| c.to_json()).collect()));
    }
    match cases.iter().filter(|c| !c.passed).count() {
        0 => Ok(()),
        k => Err(CliError::StabilityFailed(k)),
    }
}
