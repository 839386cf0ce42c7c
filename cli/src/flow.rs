//! `diffsim experiment cavity` and `cylinder`: the viscous solver
//! ([`diffsim_solvers::flow`]) on the lid-driven cavity, compared with
//! Ghia, Ghia & Shin (1982), and on the flow around a cylinder, compared
//! with Schäfer & Turek (1996).

use std::path::PathBuf;
use std::time::Instant;

use diffsim_solvers::flow::ghia;
use diffsim_studies::cavity::{CavityParams, CavityReport};

use super::{CliError, plot_or_warn};
use crate::plot::{Axes, Series};

/// Arguments of `diffsim experiment cavity`.
#[derive(Debug, clap::Args)]
pub struct CavityArgs {
    /// Reynolds number (lid speed × side / ν); Ghia's tables exist for 100,
    /// 400 and 1000.
    #[arg(long, default_value_t = 100.0)]
    re: f64,
    /// Cells per side.
    #[arg(long, default_value_t = 128)]
    resolution: usize,
    /// Steady when max |du/dt| falls below this.
    #[arg(long, default_value_t = 1e-6)]
    tolerance: f64,
    /// Give up (an error) after this many time steps.
    #[arg(long, default_value_t = 2_000_000)]
    max_steps: usize,
    /// Print the result as one JSON object on the last line.
    #[arg(long)]
    json: bool,
    /// Also write the centreline profiles (CSV) and their plot over Ghia's
    /// points (PNG) to this directory.
    #[arg(long)]
    out: Option<PathBuf>,
    #[command(flatten)]
    overwrite: super::Overwrite,
}

/// The cavity's flags checked against the range where its method holds.
fn check_cavity(a: &CavityArgs) -> Result<(), CliError> {
    let (re, n, tolerance) = (a.re, a.resolution, a.tolerance);
    // Above Re ≈ 8000 the cavity's flow is no longer steady (and Ghia's
    // tables end at 10,000); at Re → ∞ the lid would not move the fluid at
    // all in a viscous march.
    if !(re > 0.0 && re <= 10_000.0) {
        return Err(CliError::Argument { arg: "--re", reason: format!("must be in (0, 10000] (where the cavity's flow is steady), got {re}") });
    }
    if !(4..=4096).contains(&n) {
        return Err(CliError::Argument { arg: "--resolution", reason: format!("must be between 4 and 4096 cells per side, got {n}") });
    }
    if !(tolerance.is_finite() && tolerance > 0.0) {
        return Err(CliError::Argument { arg: "--tolerance", reason: format!("must be a positive number, got {tolerance}") });
    }
    max_steps(a.max_steps)?;
    let cells = (n as u64) * (n as u64);
    diffsim::memory::check(
        "the cavity",
        format!("{n}² cells, {MARCH_ARRAYS} arrays of a cell"),
        diffsim::memory::f64s(&[cells, MARCH_ARRAYS]),
        Some("a smaller --resolution".into()),
    )?;
    Ok(())
}

/// Values per cell the explicit march holds (its fields, the pressure
/// solve's vectors and preconditioner): peak RSS measured at 128², 256²
/// and 512² grew by 155 bytes a cell (19 values); 24 leaves room.
const MARCH_ARRAYS: u64 = 24;

/// Bytes of the steady Newton solve on `cells` cells (its sparse LU):
/// peak RSS of 2D-1 at 10, 20, 30 cells per diameter (9 k to 81 k cells)
/// measured 16.2, 14.8, 16.5 KB a cell, and a free stream of 410 k cells
/// about 28 KB: 18 KB a cell up to 81 k cells, growing as the cube root
/// beyond (the factor's fill-in). `None` on overflow.
fn newton_bytes(cells: u64) -> Option<u64> {
    let per_cell = 18_000.0 * (cells as f64 / 81_180.0).cbrt().max(1.0);
    let bytes = cells as f64 * per_cell;
    (bytes < 1.8e19).then_some(bytes as u64)
}

/// Bytes per cell of the time-stepping channel flow (its sparse Cholesky
/// pressure factor): 4.1 and 4.0 KB a cell measured for 2D-2 at 10 and 20
/// cells per diameter, 2.5 KB for 2D-1's march.
const CHANNEL_BYTES_PER_CELL: u64 = 4_500;

/// The cells of Schäfer & Turek's 2.2 × 0.41 channel at `per_d` cells per
/// diameter (0.1).
fn channel_cells(per_d: usize) -> u64 {
    (22 * per_d as u64) * (41 * per_d as u64 / 10)
}

/// The most time steps a march to a steady state may take.
const MAX_MARCH_STEPS: usize = 100_000_000;

/// `--max-steps` within 1..=[`MAX_MARCH_STEPS`] (a march that has not
/// settled in 10⁸ steps will not; more is days of computing).
fn max_steps(n: usize) -> Result<(), CliError> {
    if (1..=MAX_MARCH_STEPS).contains(&n) {
        Ok(())
    } else {
        Err(CliError::Argument { arg: "--max-steps", reason: format!("must be between 1 and {MAX_MARCH_STEPS}, got {n}") })
    }
}

fn run_cavity(a: &CavityArgs) -> Result<CavityReport, CliError> {
    check_cavity(a)?;
    let (re, n) = (a.re, a.resolution);
    let spinner = if a.json { indicatif::ProgressBar::hidden() } else { indicatif::ProgressBar::new_spinner() };
    let p = CavityParams { re, resolution: n, tolerance: a.tolerance, max_steps: a.max_steps };
    let report = diffsim_studies::cavity::run(&p, |step, t, rate| {
        spinner.set_message(format!("cavity Re {re}, {n}²: step {step}, t = {t:.1}, max |du/dt| = {rate:.2e}"));
        spinner.tick();
    })
    .map_err(super::train::study_error("cavity"))?;
    spinner.finish_and_clear();
    Ok(report)
}

pub(super) fn cavity(a: CavityArgs) -> Result<(), CliError> {
    check_cavity(&a)?;
    // Held to the end: the folder is this run's while it writes.
    let _out = a.out.as_deref().map(|d| super::claim_out(d, a.overwrite, &[])).transpose()?;
    let report = run_cavity(&a)?;
    if let Some(dir) = &a.out {
        write_profiles(dir, &report)?;
    }
    if a.json {
        println!("{}", report.json());
        return Ok(());
    }
    println!("lid-driven cavity, Re {}, {}² cells: steady after {} steps, {:.1} s", a.re, a.resolution, report.steps, report.time_s);
    print!("{}", report.table());
    if let Some(dir) = &a.out {
        println!("wrote {} to {}", profile_names(a.re).join(", "), dir.display());
    }
    Ok(())
}

fn profile_names(re: f64) -> [String; 2] {
    [format!("cavity_re{re}.csv"), format!("cavity_re{re}.png")]
}

/// The two centreline profiles as CSV and as one plot over Ghia's points.
fn write_profiles(dir: &std::path::Path, run: &CavityReport) -> Result<(), CliError> {
    let io = |path: &std::path::Path| {
        let path = path.to_path_buf();
        move |source| CliError::Io { path, source }
    };
    let re = run.params.re;
    std::fs::create_dir_all(dir).map_err(io(dir))?;
    let [csv_name, png_name] = profile_names(re);
    let path = dir.join(csv_name);
    diffsim::files::write(&path, run.profiles_csv()).map_err(io(&path))?;
    let [u, v] = run.profiles();
    let mut series = vec![
        Series { name: "u on x = 1/2 (against y)".into(), points: u, color: 0, markers: false },
        Series { name: "v on y = 1/2 (against x)".into(), points: v, color: 1, markers: false },
    ];
    if let Some(g) = ghia(re) {
        series.push(Series {
            name: "Ghia et al. 1982, u".into(),
            points: g.u.at.iter().copied().zip(g.u.value.iter().copied()).collect(),
            color: 0,
            markers: true,
        });
        series.push(Series {
            name: "Ghia et al. 1982, v".into(),
            points: g.v.at.iter().copied().zip(g.v.value.iter().copied()).collect(),
            color: 1,
            markers: true,
        });
    }
    let title = format!("lid-driven cavity, Re {re}, {}x{} cells", run.cfg.nx, run.cfg.ny);
    plot_or_warn(&dir.join(png_name), &Axes { title: &title, x: "position along the centreline", y: "velocity", log_x: false, log_y: false }, &series);
    Ok(())
}

/// The two cases of the Schäfer–Turek benchmark.
#[derive(Clone, Copy, Debug, PartialEq, Eq, clap::ValueEnum)]
pub enum CylinderCase {
    /// Re 20, steady: c_D, c_L, Δp.
    #[value(name = "2d-1")]
    Steady,
    /// Re 100, periodic shedding: maxima of c_D and c_L, Strouhal number.
    #[value(name = "2d-2")]
    Periodic,
}

/// How case 2D-1 reaches its steady state.
#[derive(Clone, Copy, Debug, PartialEq, Eq, clap::ValueEnum)]
pub enum SteadySolver {
    /// Newton's method on the discrete steady equations (sparse LU).
    Newton,
    /// Pseudo-time marching (explicit steps with the projection).
    March,
}

/// The advection's interpolation (`diffsim_solvers::flow::Convection`).
#[derive(Clone, Copy, Debug, PartialEq, Eq, clap::ValueEnum)]
pub enum ConvectionArg {
    /// Two-point averages (second-order central).
    Second,
    /// Four-point interpolation of the transported and transporting
    /// velocities (less dispersive).
    Fourth,
}

impl From<ConvectionArg> for diffsim_solvers::flow::Convection {
    fn from(c: ConvectionArg) -> Self {
        match c {
            ConvectionArg::Second => Self::Second,
            ConvectionArg::Fourth => Self::Fourth,
        }
    }
}

/// Arguments of `diffsim experiment cylinder`.
#[derive(Debug, clap::Args)]
pub struct CylinderArgs {
    /// Which case.
    #[arg(long, value_enum)]
    case: CylinderCase,
    /// Cells per cylinder diameter (a multiple of 10; default 40 for 2d-1,
    /// 30 for 2d-2).
    #[arg(long)]
    resolution: Option<usize>,
    /// 2d-1: Newton's method or pseudo-time marching (the same discrete
    /// steady state).
    #[arg(long, value_enum, default_value_t = SteadySolver::Newton)]
    solver: SteadySolver,
    /// The advection's interpolation (default: second for 2d-1, fourth
    /// for 2d-2).
    #[arg(long, value_enum)]
    convection: Option<ConvectionArg>,
    /// 2d-1 with --solver march: steady when max |du/dt| falls below this
    /// (default 1e-6).
    #[arg(long)]
    tolerance: Option<f64>,
    /// 2d-1 with --solver march: give up after this many pseudo-time steps
    /// (default 1000000).
    #[arg(long)]
    max_steps: Option<usize>,
    /// 2d-2: simulated time (from Poiseuille flow); the last 2 time units
    /// are measured (default 10).
    #[arg(long)]
    t_end: Option<f64>,
    /// Print the result as one JSON object on the last line.
    #[arg(long)]
    json: bool,
    /// 2d-1 by Newton: run these resolutions (cells per D, comma-separated)
    /// and report error against time as a table (and a plot with --out).
    #[arg(long, value_delimiter = ',')]
    sweep: Vec<usize>,
    /// 2d-2: also write the force coefficients over time (CSV, PNG) here;
    /// 2d-1 with --sweep: the error-against-time plot.
    #[arg(long)]
    out: Option<PathBuf>,
    #[command(flatten)]
    overwrite: super::Overwrite,
}

pub(super) fn cylinder(a: CylinderArgs) -> Result<(), CliError> {
    let per_d = a.resolution.unwrap_or(match a.case {
        CylinderCase::Steady => 40,
        CylinderCase::Periodic => 30,
    });
    if !(10..=200).contains(&per_d) || per_d % 10 != 0 {
        return Err(CliError::Argument {
            arg: "--resolution",
            reason: format!("cells per diameter must be a multiple of 10 between 10 and 200 (the channel is 4.1 diameters high), got {per_d}"),
        });
    }
    let convection: diffsim_solvers::flow::Convection = a
        .convection
        .unwrap_or(match a.case {
            CylinderCase::Steady => ConvectionArg::Second,
            CylinderCase::Periodic => ConvectionArg::Fourth,
        })
        .into();
    // Options of one case or solver given to another would do nothing.
    let march = a.case == CylinderCase::Steady && a.solver == SteadySolver::March;
    if !march && a.tolerance.is_some() {
        return Err(CliError::Argument { arg: "--tolerance", reason: "applies to case 2d-1 with --solver march only".into() });
    }
    if !march && a.max_steps.is_some() {
        return Err(CliError::Argument { arg: "--max-steps", reason: "applies to case 2d-1 with --solver march only".into() });
    }
    if a.case != CylinderCase::Periodic && a.t_end.is_some() {
        return Err(CliError::Argument { arg: "--t-end", reason: "applies to case 2d-2 only".into() });
    }
    let (tolerance, steps, t_end) = (a.tolerance.unwrap_or(1e-6), a.max_steps.unwrap_or(1_000_000), a.t_end.unwrap_or(10.0));
    if !(tolerance.is_finite() && tolerance > 0.0) {
        return Err(CliError::Argument { arg: "--tolerance", reason: format!("must be a positive number, got {tolerance}") });
    }
    max_steps(steps)?;
    // Memory: the finest grid the command solves, by its solver.
    let finest = a.sweep.iter().copied().chain([per_d]).max().unwrap_or(per_d);
    let cells = channel_cells(finest);
    let need = if a.case == CylinderCase::Steady && (a.solver == SteadySolver::Newton || !a.sweep.is_empty()) {
        newton_bytes(cells)
    } else {
        cells.checked_mul(CHANNEL_BYTES_PER_CELL)
    };
    diffsim::memory::check("the cylinder's channel", format!("{cells} cells at {finest} per diameter"), need, Some("a smaller --resolution".into()))?;
    // Beyond 1000 time units (Re 100's period is about 3.3) a run is an
    // input error, not a study: hours of steps with no end in sight.
    if !(t_end.is_finite() && t_end > 2.5 && t_end <= 1000.0) {
        return Err(CliError::Argument {
            arg: "--t-end",
            reason: format!("must exceed 2.5 (the last 2 time units are measured) and be at most 1000, got {t_end}"),
        });
    }
    if !a.sweep.is_empty() && a.case != CylinderCase::Steady {
        return Err(CliError::Argument { arg: "--sweep", reason: "only case 2d-1 has a sweep".into() });
    }
    if let Some(&bad) = a.sweep.iter().find(|&&r| !(10..=200).contains(&r) || r % 10 != 0) {
        return Err(CliError::Argument { arg: "--sweep", reason: format!("cells per diameter must be multiples of 10 between 10 and 200, got {bad}") });
    }
    // Held to the end: the folder is this run's while it writes.
    let _out = a.out.as_deref().map(|d| super::claim_out(d, a.overwrite, &[])).transpose()?;
    if !a.sweep.is_empty() {
        return cylinder_sweep(&a, convection);
    }
    use diffsim_studies::cylinder::{self, CylinderParams};
    let p = CylinderParams {
        case: match a.case {
            CylinderCase::Steady => cylinder::CylinderCase::Steady,
            CylinderCase::Periodic => cylinder::CylinderCase::Periodic,
        },
        resolution: per_d,
        solver: match a.solver {
            SteadySolver::Newton => cylinder::SteadySolver::Newton,
            SteadySolver::March => cylinder::SteadySolver::March,
        },
        convection,
        tolerance,
        max_steps: steps,
        t_end,
    };
    let spinner = if a.json { indicatif::ProgressBar::hidden() } else { indicatif::ProgressBar::new_spinner() };
    let report = cylinder::run(&p, |line| {
        spinner.set_message(line.to_string());
        spinner.tick();
    })
    .map_err(super::train::study_error("cylinder"))?;
    spinner.finish_and_clear();
    if let (Some(dir), Some(csv), cylinder::CylinderResult::Periodic(r)) = (&a.out, report.series_csv(), &report.result) {
        write_force_series(dir, &csv, &r.series, per_d)?;
    }
    if a.json {
        println!("{}", report.json());
    } else {
        print!("{}", report.table());
    }
    Ok(())
}

/// 2D-1 by Newton at several resolutions: error against wall time (c_D and
/// Δp against the tight values).
fn cylinder_sweep(a: &CylinderArgs, convection: diffsim_solvers::flow::Convection) -> Result<(), CliError> {
    let report = diffsim_studies::cylinder::sweep(&a.sweep, convection).map_err(super::train::study_error("cylinder"))?;
    if a.json {
        println!("{}", report.json());
    } else {
        print!("{}", report.table());
    }
    if let Some(dir) = &a.out {
        std::fs::create_dir_all(dir).map_err(|source| CliError::Io { path: dir.to_path_buf(), source })?;
        let points = |f: &dyn Fn(&diffsim_studies::cylinder::SweepRow) -> f64| report.rows.iter().map(|r| (r.time_s, f(r).max(1e-12))).collect::<Vec<_>>();
        plot_or_warn(
            &dir.join("cylinder_2d1_error_time.png"),
            &Axes { title: "Schäfer–Turek 2D-1 by Newton: error against wall time", x: "wall time (s)", y: "relative error", log_x: true, log_y: true },
            &[
                Series { name: "c_D (against 5.57954)".into(), points: points(&|r| r.cd_error()), color: 0, markers: true },
                Series { name: "Δp (against 0.11752)".into(), points: points(&|r| r.dp_error()), color: 1, markers: true },
            ],
        );
    }
    Ok(())
}

/// c_D and c_L over time as CSV and a plot.
fn write_force_series(dir: &std::path::Path, csv: &str, series: &[[f64; 4]], per_d: usize) -> Result<(), CliError> {
    std::fs::create_dir_all(dir).map_err(|source| CliError::Io { path: dir.to_path_buf(), source })?;
    let path = dir.join("cylinder_2d2.csv");
    diffsim::files::write(&path, csv).map_err(|source| CliError::Io { path: path.clone(), source })?;
    let pick = |k: usize| series.iter().map(|s| (s[0], s[k])).collect::<Vec<_>>();
    let title = format!("Schäfer–Turek 2D-2, {per_d} cells per diameter");
    plot_or_warn(
        &dir.join("cylinder_2d2.png"),
        &Axes { title: &title, x: "t", y: "coefficient", log_x: false, log_y: false },
        &[Series { name: "c_D".into(), points: pick(1), color: 0, markers: false }, Series { name: "c_L".into(), points: pick(2), color: 1, markers: false }],
    );
    Ok(())
}

/// Arguments of `diffsim experiment drag-shape`.
#[derive(Debug, clap::Args)]
pub struct DragShapeArgs {
    /// A coarse grid (10 cells per diameter, verified at 20): a few minutes at most.
    #[arg(long)]
    quick: bool,
    /// Cells per diameter of the optimisation (a multiple of 10; default
    /// 20, or 10 with --quick); the verification runs at twice this.
    #[arg(long)]
    resolution: Option<usize>,
    /// Highest Fourier mode K of the shape (modes 2..=K, cosine and sine).
    #[arg(long, default_value_t = 8)]
    modes: usize,
    /// Peak inflow speed (0.3: Re 20, the benchmark's 2D-1; Re = 2/3·u_max·D/ν).
    #[arg(long, default_value_t = 0.3, conflicts_with = "re")]
    u_max: f64,
    /// The Reynolds number Ū·D/ν instead of --u-max (up to 40).
    #[arg(long)]
    re: Option<f64>,
    /// Put the body in a free stream instead of the benchmark's channel: a
    /// square box reaching this many diameters from the body's centre to
    /// each side (uniform inflow, outflow, the top and bottom walls sliding
    /// with the stream).
    #[arg(long, value_name = "HALF_WIDTH")]
    free_stream: Option<f64>,
    /// L-BFGS iterations at most.
    #[arg(long, default_value_t = 60)]
    max_iterations: usize,
    /// Iterations of gradient sampling after L-BFGS, when L-BFGS stopped
    /// short of shrinking the projected gradient 100× (its line search
    /// stalls at kinks of the discrete drag); 0 for none. Each samples the
    /// gradient at as many shapes as coefficients + 1.
    #[arg(long, default_value_t = 20)]
    sampling_iterations: usize,
    /// Start from the final shape of an earlier run instead of the cylinder:
    /// a file whose last line is that run's `--json` line (its Fourier
    /// modes 2.., rescaled to the cylinder's area; to continue on a finer
    /// grid or in another stream).
    #[arg(long, value_name = "FILE")]
    start_shape: Option<PathBuf>,
    /// Skip the re-simulation on a grid twice as fine (it needs about four
    /// times the memory: a wide free stream may not fit).
    #[arg(long)]
    no_verify: bool,
    /// Print the result as one JSON object on the last line.
    #[arg(long)]
    json: bool,
    /// Write the shapes over the iterations and the drag history (PNG, CSV) here.
    #[arg(long)]
    out: Option<PathBuf>,
    #[command(flatten)]
    overwrite: super::Overwrite,
}

pub(super) fn drag_shape(a: DragShapeArgs) -> Result<(), CliError> {
    use diffsim_solvers::flow::drag_shape::{DragShapeParams, Stream, start_shape};
    use diffsim_studies::drag_shape::DragStudyParams;
    let per_d = a.resolution.unwrap_or(if a.quick { 10 } else { 20 });
    if !(10..=100).contains(&per_d) || per_d % 10 != 0 {
        return Err(CliError::Argument { arg: "--resolution", reason: format!("cells per diameter must be a multiple of 10 between 10 and 100, got {per_d}") });
    }
    if !(2..=16).contains(&a.modes) {
        return Err(CliError::Argument { arg: "--modes", reason: format!("the highest mode must be between 2 and 16, got {}", a.modes) });
    }
    let u_max = match a.re {
        Some(re) if (0.1..=40.0).contains(&re) => 1.5 * re * 1e-3 / diffsim_solvers::flow::cylinder::DIAMETER,
        Some(re) => {
            return Err(CliError::Argument {
                arg: "--re",
                reason: format!("must be in [0.1, 40] (where the flow stays steady and its drag coefficient is resolved), got {re}"),
            });
        }
        None => a.u_max,
    };
    if !(0.0015..=0.6).contains(&u_max) {
        return Err(CliError::Argument {
            arg: "--u-max",
            reason: format!("must be in [0.0015, 0.6] (Re 0.1 to 40, where the flow stays steady and its drag coefficient is resolved), got {}", a.u_max),
        });
    }
    let stream = match a.free_stream {
        None => Stream::Channel,
        Some(w) if w.is_finite() && (2.0..=40.0).contains(&w) => Stream::Free { half_width: w },
        Some(w) => {
            return Err(CliError::Argument { arg: "--free-stream", reason: format!("the box's half-width must be between 2 and 40 diameters, got {w}") });
        }
    };
    let opts = DragShapeParams {
        stream,
        cells_per_d: per_d,
        modes: a.modes,
        u_max,
        max_iterations: a.max_iterations,
        gradient_reduction: 100.0,
        sampling_iterations: a.sampling_iterations,
    };
    let setting = stream.setting(per_d, u_max)?;
    // Memory: Newton's sparse LU on the grid, or on the verification's
    // grid twice as fine (four times the cells).
    let cells = (setting.cfg.nx * setting.cfg.ny) as u64 * if a.no_verify { 1 } else { 4 };
    diffsim::memory::check(
        "drag-shape",
        format!("{cells} cells{} for Newton's solve", if a.no_verify { "" } else { " in the verification" }),
        newton_bytes(cells),
        Some(if a.no_verify { "a smaller --resolution".into() } else { "--no-verify, or a smaller --resolution".into() }),
    )?;
    let start = match &a.start_shape {
        None => None,
        Some(path) => {
            let q = start_coefficients(path, a.modes)?;
            start_shape(&setting, a.modes, &q).map_err(|e| CliError::Argument { arg: "--start-shape", reason: format!("{}: {e}", path.display()) })?;
            Some(q)
        }
    };
    // Held to the end: the folder is this run's while it writes; the start
    // shape's file is never written over.
    let inputs: Vec<&std::path::Path> = a.start_shape.as_deref().into_iter().collect();
    let _out = a.out.as_deref().map(|d| super::claim_out(d, a.overwrite, &inputs)).transpose()?;
    let p = DragStudyParams { optimise: opts, start, verify: !a.no_verify };
    if !a.json {
        eprintln!("minimising the drag in {} at Re {}, {per_d} cells per diameter, modes 2..={} …", p.place(), p.reynolds_shown(), a.modes);
    }
    let report = diffsim_studies::drag_shape::run(&p).map_err(super::train::study_error("drag-shape"))?;
    if let Some(dir) = &a.out {
        write_drag_shapes(dir, &report.result, per_d)?;
    }
    if a.json {
        println!("{}", report.json());
    } else {
        let from = a.start_shape.as_ref().map(|path| path.display().to_string());
        print!("{}", report.table(from.as_deref()));
    }
    Ok(())
}

/// The free Fourier coefficients `(a₂…a_K, b₂…b_K)` of the final shape of
/// an earlier `drag-shape --json` run (the last line of `path`), padded to
/// `modes`.
fn start_coefficients(path: &std::path::Path, modes: usize) -> Result<Vec<f64>, CliError> {
    let fail = |reason: String| CliError::Argument { arg: "--start-shape", reason: format!("{}: {reason}", path.display()) };
    // A regular file of at most a megabyte (a --json log of runs is far smaller).
    let text = diffsim::files::read_text(path, 1 << 20, "shape file").map_err(|e| fail(e.to_string()))?;
    let line = text.lines().rev().find(|l| !l.trim().is_empty()).ok_or_else(|| fail("the file is empty".into()))?;
    let json: serde_json::Value = serde_json::from_str(line).map_err(|e| fail(format!("its last line is not a JSON object: {e}")))?;
    let params: Vec<f64> = json["shape"]["params"]
        .as_array()
        .and_then(|a| a.iter().map(|v| v.as_f64()).collect())
        .ok_or_else(|| fail("its last line has no shape.params (the --json line of drag-shape)".into()))?;
    // [cx, cy, r₀, a₁…a_K, b₁…b_K]
    if params.len() < 5 || params.len() % 2 == 0 {
        return Err(fail(format!("shape.params has {} numbers, not those of a Fourier shape [cx, cy, r0, a1..aK, b1..bK]", params.len())));
    }
    let k = (params.len() - 3) / 2;
    let (cos, sin) = params[3..].split_at(k);
    if cos[0] != 0.0 || sin[0] != 0.0 {
        return Err(fail("its mode 1 is not zero (the optimiser keeps the body in place and leaves mode 1 out)".into()));
    }
    if cos.iter().chain(sin).enumerate().any(|(i, &c)| i % k >= modes && c != 0.0) {
        return Err(fail(format!("it has modes up to {k}, above --modes {modes}")));
    }
    let pick = |part: &[f64]| (2..=modes).map(|m| part.get(m - 1).copied().unwrap_or(0.0)).collect::<Vec<f64>>();
    Ok([pick(cos), pick(sin)].concat())
}

/// The shapes over the iterations (PNG) and the drag history (CSV, PNG).
fn write_drag_shapes(dir: &std::path::Path, r: &diffsim_solvers::flow::drag_shape::DragShapeResult, per_d: usize) -> Result<(), CliError> {
    std::fs::create_dir_all(dir).map_err(|source| CliError::Io { path: dir.to_path_buf(), source })?;
    let mut csv = String::from("iteration,cd,gradient_norm\n");
    for (k, h) in r.history.iter().enumerate() {
        csv.push_str(&format!("{k},{:.8},{:.6e}\n", h.cd, h.gradient_norm));
    }
    let path = dir.join("drag_shape_history.csv");
    diffsim::files::write(&path, csv).map_err(|source| CliError::Io { path: path.clone(), source })?;
    let history: Vec<(f64, f64)> = r.history.iter().enumerate().map(|(k, h)| (k as f64, h.cd)).collect();
    plot_or_warn(
        &dir.join("drag_shape_history.png"),
        &Axes { title: &format!("drag over the L-BFGS iterations, {per_d} cells per diameter"), x: "iteration", y: "c_D", log_x: false, log_y: false },
        &[Series { name: "c_D".into(), points: history, color: 0, markers: true }],
    );
    // Boundaries of a few iterates, the start and the end among them.
    let outline = |s: &diffsim_solvers::flow::Shape| -> Vec<(f64, f64)> {
        let mut points: Vec<(f64, f64)> = s.outline(360).into_iter().map(|[x, y]| (x, y)).collect();
        points.push(points[0]);
        points
    };
    let n = r.history.len();
    let mut picks: Vec<usize> = [0, n / 8, n / 4, n / 2, n - 1].into_iter().filter(|&k| k < n).collect();
    picks.dedup();
    let mut series: Vec<Series> = picks
        .iter()
        .enumerate()
        .map(|(c, &k)| Series { name: format!("iteration {k}: c_D {:.3}", r.history[k].cd), points: outline(&r.history[k].shape), color: c, markers: false })
        .collect();
    // The plot's window (two lone points, which draw nothing) at the aspect
    // of its area, so that shapes are to scale, with room for the legend.
    series.push(Series { name: String::new(), points: vec![(0.05, 0.0825)], color: 7, markers: false });
    series.push(Series { name: String::new(), points: vec![(0.45, 0.3175)], color: 7, markers: false });
    plot_or_warn(
        &dir.join("drag_shapes.png"),
        &Axes {
            title: &format!("shapes of equal area over the iterations (flow from the left), {per_d} cells per diameter"),
            x: "x",
            y: "y",
            log_x: false,
            log_y: false,
        },
        &series,
    );
    Ok(())
}

/// Arguments of `diffsim experiment drag-net`.
#[derive(Debug, clap::Args)]
pub struct DragNetArgs {
    /// 10 cells per diameter (else 20).
    #[arg(long)]
    quick: bool,
    /// Adam updates.
    #[arg(long, default_value_t = 40)]
    iterations: usize,
    /// Adam's learning rate.
    #[arg(long, default_value_t = 0.05)]
    lr: f64,
    /// Print the result as one JSON object on the last line.
    #[arg(long)]
    json: bool,
}

pub(super) fn drag_net(a: DragNetArgs) -> Result<(), CliError> {
    use diffsim_studies::shape_net::{ShapeNetParams, train};
    if !(a.lr.is_finite() && a.lr > 0.0) {
        return Err(CliError::Argument { arg: "--lr", reason: format!("must be a positive number, got {}", a.lr) });
    }
    // No training is no study: the held-out comparison would report an
    // untrained network.
    if a.iterations == 0 {
        return Err(CliError::Argument { arg: "--iterations", reason: "must be at least 1 (the network's training updates)".into() });
    }
    let opts = ShapeNetParams {
        cells_per_d: if a.quick { 10 } else { 20 },
        modes: 4,
        train_re: vec![10.0, 20.0, 30.0, 40.0],
        test_re: vec![15.0, 35.0],
        iterations: a.iterations,
        lr: a.lr,
        seed: 7,
    };
    let start = Instant::now();
    let spinner = if a.json { indicatif::ProgressBar::hidden() } else { indicatif::ProgressBar::new_spinner() };
    let r = train(&opts, |it, loss| {
        spinner.set_message(format!("update {it}: mean c_D / c_D,cylinder = {loss:.4}"));
        spinner.tick();
    })?;
    spinner.finish_and_clear();
    let time_s = start.elapsed().as_secs_f64();
    if a.json {
        let mut obj = r.json();
        obj.insert("resolution".into(), opts.cells_per_d.into());
        obj.insert("train_re".into(), serde_json::json!(opts.train_re));
        obj.insert("time_s".into(), time_s.into());
        println!("{}", serde_json::Value::Object(obj));
        return Ok(());
    }
    println!(
        "Re ↦ shape network trained through the steady solver at Re {:?}, {} cells per diameter: mean c_D/c_D,cylinder {:.4} → {:.4} in {} updates, {:.1} s",
        opts.train_re,
        opts.cells_per_d,
        r.losses.first().copied().unwrap_or(f64::NAN),
        r.losses.last().copied().unwrap_or(f64::NAN),
        r.losses.len(),
        r.train_s
    );
    print!("{}", r.table());
    Ok(())
}
