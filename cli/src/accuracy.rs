//! The accuracy commands: `diffsim pareto PROBLEM [--gradients]` (error
//! versus time and memory over a sweep of configurations, with the Pareto
//! front marked) and `diffsim stability` (the hard cases).

use std::fmt::Write as _;
use std::path::{Path, PathBuf};

use diffsim_solvers::exact::TaylorGreen;
use diffsim_solvers::smoke::Preconditioner;
use serde_json::{Map, Value, json};

use super::{CliError, median_time, peak_rss_bytes, plot_or_warn, reset_peak_rss};
use crate::plot::{Axes, Series};
use diffsim::problems::burgers::P1;
use diffsim::problems::smoke::SmokeStep;
use diffsim::rollout::{Checkpointing, Gradient, Rollout, RolloutError};
use diffsim_studies::accuracy::AccuracyError;
use diffsim_studies::accuracy::pareto::{Measurement, burgers_params, burgers_sweep, mark_front, taylor_green_params, taylor_green_sweep};

/// The problems `diffsim pareto` sweeps.
#[derive(Clone, Copy, Debug, PartialEq, Eq, clap::ValueEnum)]
pub enum Problem {
    /// Viscous Burgers (ν = 0.05, u₀ = sin x, t = 1) against Cole–Hopf.
    Burgers,
    /// The Taylor–Green vortex (ν = 0.01, t = 1) against its exact decay.
    TaylorGreen,
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

/// Times `f` (median over repeats within `budget` seconds) and measures the
/// peak resident memory while it runs.
fn measure<T>(budget: f64, f: impl FnMut() -> T) -> (T, f64, u64) {
    reset_peak_rss();
    let (time, out) = median_time(budget, 1, 20, f);
    (out, time, peak_rss_bytes())
}

/// Times `run` (only the simulation; the exact solution is evaluated after)
/// and returns its error by `error`.
fn timed_error(budget: f64, run: impl FnMut() -> Result<Vec<f64>, AccuracyError>, error: impl Fn(&[f64]) -> f64) -> (Result<f64, AccuracyError>, f64, u64) {
    let (u, time, peak) = measure(budget, run);
    (u.map(|u| error(&u)), time, peak)
}

fn accuracy_row(family: String, params: Map<String, Value>, r: (Result<f64, AccuracyError>, f64, u64)) -> Measurement {
    let (result, time_s, peak_rss_bytes) = r;
    let error = result.unwrap_or_else(|e| {
        eprintln!("warning: {family} {}: {e}", Value::Object(params.clone()));
        f64::NAN
    });
    Measurement { family, params, error, time_s, peak_rss_bytes, pareto: false }
}

/// Runs `diffsim pareto`.
pub fn pareto(a: ParetoArgs) -> Result<(), CliError> {
    if !(a.budget >= 0.0 && a.budget <= 86_400.0) {
        return Err(CliError::Argument { arg: "--budget", reason: format!("must be between 0 and 86400 seconds (a day), got {}", a.budget) });
    }
    let name = match (a.problem, a.gradients) {
        (Problem::Burgers, false) => "burgers",
        (Problem::TaylorGreen, false) => "taylor-green",
        (Problem::Cylinder, false) => "cylinder",
        (Problem::Cylinder, true) => {
            return Err(CliError::Argument {
                arg: "--gradients",
                reason: "the cylinder has no gradient sweep (its shape gradient is checked by `diffsim grad scenes/drag_body.toml --check`)".into(),
            });
        }
        (Problem::Burgers, true) => "burgers-gradients",
        (Problem::TaylorGreen, true) => "taylor-green-gradients",
    };
    // Each problem has its own subfolder, claimed before the sweep runs.
    let dir = a.out.join(name);
    let _out = super::claim_out(&dir, a.overwrite, &[])?;
    let (title, mut rows) = match (a.problem, a.gradients) {
        (Problem::Burgers, false) => {
            let rows = burgers_sweep(a.quick)
                .iter()
                .map(|r| {
                    let (family, params) = burgers_params(r);
                    accuracy_row(family, params, timed_error(a.budget, || r.run(), |u| r.error_of(u)))
                })
                .collect();
            ("Burgers (ν = 0.05, t = 1): error vs time", rows)
        }
        (Problem::TaylorGreen, false) => {
            let rows = taylor_green_sweep(a.quick)
                .iter()
                .map(|r| {
                    let (family, params) = taylor_green_params(r);
                    accuracy_row(family, params, timed_error(a.budget, || r.run(), |u| r.error_of(u)))
                })
                .collect();
            ("Taylor–Green vortex (ν = 0.01, t = 1): error vs time", rows)
        }
        // (--gradients for the cylinder was refused above.)
        (Problem::Cylinder, _) => ("Schäfer–Turek 2D-1 (Re 20): c_D error vs time", cylinder_rows(a.budget, a.quick)),
        (Problem::Burgers, true) => {
            let p = if a.quick { P1::new(64, 64) } else { P1::new(256, 256) };
            let rows = gradient_rows(
                a.budget,
                p.steps,
                |enzyme, mode| if enzyme { p.grad_enzyme(mode) } else { p.grad_hand(mode) },
                |u0| {
                    let mut q = p.clone();
                    q.u0 = u0.to_vec();
                    q.value().unwrap_or(f64::NAN)
                },
                &p.u0,
            )?;
            ("P1 Burgers gradient: error vs time", rows)
        }
        (Problem::TaylorGreen, true) => {
            let (n, steps) = if a.quick { (8, 4) } else { (16, 8) };
            let tg = TaylorGreenGradient::new(n, steps);
            let rows = gradient_rows(a.budget, steps, |enzyme, mode| tg.gradient(enzyme, mode), |x0| tg.value(x0), &tg.x0)?;
            ("Taylor–Green gradient (∂L/∂x₀): error vs time", rows)
        }
    };
    mark_front(&mut rows);
    write_report(&dir, title, &rows)?;
    if a.json {
        println!("{}", Value::Array(rows.iter().map(Measurement::to_json).collect()));
    } else {
        print!("{}", markdown(&rows));
        println!("\nwritten to {}", dir.display());
    }
    Ok(())
}

/// Case 2D-1 at several resolutions (cells per diameter) by Newton's method
/// and by marching in pseudo-time to `max |du/dt| < 1e-6` (the same
/// discrete steady state, reached two ways): c_D's relative error against
/// the tight reference value.
fn cylinder_rows(budget: f64, quick: bool) -> Vec<Measurement> {
    use diffsim_solvers::flow::Convection;
    use diffsim_solvers::flow::cylinder::{reference, run_2d1, run_2d1_newton};
    let (newton, march): (&[usize], &[usize]) = if quick { (&[10, 20], &[10]) } else { (&[10, 20, 30, 40], &[10, 20]) };
    let mut rows = Vec::new();
    // The march first: the peak-memory reset cannot return what the
    // allocator keeps from a larger run before.
    for (solver, list) in [("march", march), ("newton", newton)] {
        for &per_d in list {
            let (result, time_s, peak) = measure(budget, || {
                if solver == "newton" { run_2d1_newton(per_d, Convection::Second) } else { run_2d1(per_d, Convection::Second, 1e-6, 1_000_000, |_, _, _| {}) }
            });
            let mut params = Map::new();
            params.insert("solver".into(), json!(solver));
            params.insert("cells_per_d".into(), json!(per_d));
            params.insert("cells".into(), result.as_ref().map_or(Value::Null, |r| json!(r.cells)));
            let error = result.map(|r| (r.cd / reference::CD_2D1_TIGHT - 1.0).abs()).map_err(AccuracyError::Flow);
            rows.push(accuracy_row(format!("{solver} (cut cells)"), params, (error, time_s, peak)));
        }
    }
    rows
}

/// The gradient of a rollout loss by the Enzyme and hand-written adjoints
/// (`grad(enzyme, mode)`) with every checkpointing mode, and by central
/// differences of `value` at steps 1e-2…1e-10; errors relative to the
/// hand-written adjoint with stored states (whose own error is its
/// distance to the Enzyme one with stored states).
fn gradient_rows(
    budget: f64,
    steps: usize,
    grad: impl Fn(bool, Checkpointing) -> Result<Gradient, RolloutError>,
    value: impl Fn(&[f64]) -> f64,
    x0: &[f64],
) -> Result<Vec<Measurement>, CliError> {
    let modes = [Checkpointing::Store, Checkpointing::periodic_sqrt(steps), Checkpointing::binomial_log(steps)];
    let reference = grad(false, Checkpointing::Store)?.dx0;
    let enzyme_stored = grad(true, Checkpointing::Store)?.dx0;
    let rel = |g: &[f64], r: &[f64]| diffsim_studies::accuracy::relative_l2(g, r);
    let mut rows = Vec::new();
    for enzyme in [true, false] {
        for mode in modes {
            let (g, time_s, peak) = measure(budget, || grad(enzyme, mode));
            let g = g?;
            let method = if enzyme { "enzyme" } else { "hand" };
            let error = if !enzyme && mode == Checkpointing::Store { rel(&g.dx0, &enzyme_stored) } else { rel(&g.dx0, &reference) };
            let mut params = Map::new();
            params.insert("method".into(), json!(method));
            params.insert("checkpointing".into(), json!(mode.to_string()));
            params.insert("fd_step".into(), Value::Null);
            params.insert("peak_states".into(), json!(g.stats.peak_states));
            params.insert("step_evaluations".into(), json!(g.stats.step_evaluations));
            let family = format!("{method} adjoint");
            rows.push(Measurement { family, params, error, time_s, peak_rss_bytes: peak, pareto: false });
        }
    }
    for eps in [1e-2, 1e-4, 1e-6, 1e-8, 1e-10] {
        let (g, time_s, peak) = measure(budget, || diffsim::check::central_gradient(&value, x0, eps));
        let mut params = Map::new();
        params.insert("method".into(), json!("finite differences"));
        params.insert("checkpointing".into(), Value::Null);
        params.insert("fd_step".into(), json!(eps));
        params.insert("peak_states".into(), json!(2));
        params.insert("step_evaluations".into(), json!(2 * x0.len() * steps));
        rows.push(Measurement { family: "finite differences".into(), params, error: rel(&g, &reference), time_s, peak_rss_bytes: peak, pareto: false });
    }
    Ok(rows)
}

/// The P2-style smoke step (semi-Lagrangian advection, pressure solve to
/// 1e-10) on a periodic box from a Taylor–Green velocity with a uniform
/// drift, carrying a smoke blob; loss `½‖x_T − x*‖²` with `x*` the exact vortex at `T` and no smoke.
struct TaylorGreenGradient {
    step: SmokeStep,
    /// The same step with the hand-written adjoint.
    hand: SmokeStep,
    steps: usize,
    x0: Vec<f64>,
    target: Vec<f64>,
}

impl TaylorGreenGradient {
    fn new(n: usize, steps: usize) -> Self {
        let cfg = diffsim_studies::accuracy::flow::periodic_box(n);
        let h = diffsim_studies::accuracy::flow::LENGTH / n as f64;
        // Half a cell per unit step at most.
        let tg = TaylorGreen { length: diffsim_studies::accuracy::flow::LENGTH, amplitude: 0.5 * h, nu: 0.0 };
        let blob = diffsim_solvers::exact::Translation { length: diffsim_studies::accuracy::flow::LENGTH, velocity: (0.0, 0.0) }.cells(n, 0.0);
        let pack = |t: f64, s: &[f64]| {
            let (u, v) = tg.mac(n, t);
            let mut x = s.to_vec();
            x.extend(u);
            x.extend(v);
            x
        };
        // A uniform drift on top keeps every trace off the grid nodes: where
        // the vortex alone is still (on whole lines of faces) the traced
        // position would sit on a node, a kink of the bilinear sample where
        // central differences and the adjoint take different one-sided
        // derivatives.
        let mut x0 = pack(0.0, &blob);
        let ns = n * n;
        for (k, a) in x0[ns..].iter_mut().enumerate() {
            *a += if k < n * (n + 1) { 0.137 } else { 0.071 };
        }
        let target = pack(steps as f64, &vec![0.0; n * n]);
        let step = || SmokeStep::new(cfg, 1e-10, 10_000, Preconditioner::None);
        Self { step: step(), hand: step().with_hand_adjoint(), steps, x0, target }
    }

    fn loss(&self) -> impl Fn(&[f64], &mut [f64]) -> f64 + '_ {
        |x, g| {
            let mut sum = 0.0;
            for ((g, &a), &b) in g.iter_mut().zip(x).zip(&self.target) {
                *g = a - b;
                sum += 0.5 * (a - b) * (a - b);
            }
            sum
        }
    }

    fn gradient(&self, enzyme: bool, mode: Checkpointing) -> Result<Gradient, RolloutError> {
        let step = if enzyme { &self.step } else { &self.hand };
        Rollout::new(step, &[], self.steps)?.value_and_grad(&self.x0, &self.loss(), mode)
    }

    fn value(&self, x0: &[f64]) -> f64 {
        Rollout::new(&self.step, &[], self.steps).and_then(|r| r.loss(x0, &self.loss())).unwrap_or(f64::NAN)
    }
}

/// The markdown table of the measurements (front marked with ✓).
fn markdown(rows: &[Measurement]) -> String {
    let keys = param_keys(rows);
    let mut s = String::new();
    let _ = writeln!(s, "| family | {} | error | time (s) | peak RSS (MiB) | Pareto |", keys.join(" | "));
    let _ = writeln!(s, "|{}", "---|".repeat(keys.len() + 5));
    for r in rows {
        let vals: Vec<String> = keys.iter().map(|k| r.params.get(k).map_or(String::new(), cell)).collect();
        let _ = writeln!(
            s,
            "| {} | {} | {:.3e} | {:.3e} | {:.1} | {} |",
            r.family,
            vals.join(" | "),
            r.error,
            r.time_s,
            r.peak_rss_bytes as f64 / (1024.0 * 1024.0),
            if r.pareto { "✓" } else { "" }
        );
    }
    s
}

fn cell(v: &Value) -> String {
    match v {
        Value::Null => "–".into(),
        Value::String(s) => s.clone(),
        Value::Number(x) => match x.as_f64() {
            Some(f) if x.is_f64() => format!("{f:.3e}"),
            _ => x.to_string(),
        },
        other => other.to_string(),
    }
}

/// Setting names in order of first appearance.
fn param_keys(rows: &[Measurement]) -> Vec<String> {
    let mut keys: Vec<String> = Vec::new();
    for r in rows {
        for k in r.params.keys() {
            if !keys.contains(k) {
                keys.push(k.clone());
            }
        }
    }
    keys
}

/// results.csv, table.md, error_time.png and error_time.svg in `dir`.
fn write_report(dir: &Path, title: &str, rows: &[Measurement]) -> Result<(), CliError> {
    let io = |path: PathBuf| move |source| CliError::Io { path, source };
    std::fs::create_dir_all(dir).map_err(io(dir.to_path_buf()))?;
    let keys = param_keys(rows);
    let mut csv = format!("family,{},error,time_s,peak_rss_bytes,pareto\n", keys.join(","));
    for r in rows {
        let vals: Vec<String> = keys
            .iter()
            .map(|k| r.params.get(k).map_or(String::new(), |v| if v.is_null() { String::new() } else { v.to_string().trim_matches('"').to_string() }))
            .collect();
        let _ = writeln!(csv, "{},{},{:e},{:e},{},{}", r.family, vals.join(","), r.error, r.time_s, r.peak_rss_bytes, r.pareto);
    }
    diffsim::files::write(&dir.join("results.csv"), csv).map_err(io(dir.join("results.csv")))?;
    diffsim::files::write(&dir.join("table.md"), format!("# {title}\n\n{}", markdown(rows))).map_err(io(dir.join("table.md")))?;
    let mut families: Vec<&str> = Vec::new();
    for r in rows {
        if !families.contains(&r.family.as_str()) {
            families.push(&r.family);
        }
    }
    let mut series: Vec<Series> = families
        .iter()
        .enumerate()
        .map(|(k, f)| Series {
            name: f.to_string(),
            // An error of exactly 0 (bit-identical to the reference) drawn at
            // 1e-17 so that the log axis keeps it.
            points: rows.iter().filter(|r| r.family == *f).map(|r| (r.time_s, r.error.max(1e-17))).collect(),
            color: k,
            markers: true,
        })
        .collect();
    let mut front: Vec<(f64, f64)> = rows.iter().filter(|r| r.pareto).map(|r| (r.time_s, r.error.max(1e-17))).collect();
    front.sort_by(|a, b| a.0.total_cmp(&b.0));
    series.push(Series { name: "Pareto front".into(), points: front, color: families.len(), markers: false });
    let axes = Axes { title, x: "wall time (s)", y: "relative error", log_x: true, log_y: true };
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
