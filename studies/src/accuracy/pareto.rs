//! Error versus cost: the configurations `diffsim pareto` sweeps, one
//! measurement per configuration, and the front of error versus time
//! ([`run`] → [`ParetoReport`]).

use std::fmt::Write as _;

use diffsim::problems::burgers::P1;
use diffsim::problems::smoke::SmokeStep;
use diffsim::rollout::{Checkpointing, Gradient, Rollout, RolloutError};
use diffsim_solvers::burgers::Advection1d;
use diffsim_solvers::exact::TaylorGreen;
use diffsim_solvers::smoke::{Preconditioner, Scheme};
use serde_json::{Map, Value, json};

use super::burgers::{BurgersRun, BurgersScheme};
use super::flow::{AbcRun, NavierStokesRun, TaylorGreenRun, scheme_name};
use super::{AccuracyError, Diffusion};
use crate::StudyError;
use crate::measure::{median_time, peak_rss_bytes, reset_peak_rss};

/// One measured configuration.
#[derive(Clone, Debug)]
pub struct Measurement {
    /// The group it is plotted in (e.g. the scheme).
    pub family: String,
    /// Its settings, by name.
    pub params: Map<String, Value>,
    /// Error against the reference (exact solution or most accurate gradient).
    pub error: f64,
    /// Wall time in seconds (median of repeats).
    pub time_s: f64,
    /// Peak resident memory of the process while it ran, in bytes.
    pub peak_rss_bytes: u64,
    /// On the front of error versus time.
    pub pareto: bool,
}

impl Measurement {
    /// The JSON object: the settings, then `error`, `time_s`,
    /// `peak_rss_bytes`, `pareto`.
    pub fn to_json(&self) -> Value {
        let mut m = self.params.clone();
        m.insert("family".into(), json!(self.family));
        m.insert("error".into(), json!(self.error));
        m.insert("time_s".into(), json!(self.time_s));
        m.insert("peak_rss_bytes".into(), json!(self.peak_rss_bytes));
        m.insert("pareto".into(), json!(self.pareto));
        Value::Object(m)
    }
}

/// Marks the configurations no other one beats: a measurement is on the
/// front unless another has error and time both at most its own and one
/// of them strictly smaller. Non-finite errors are never on it.
pub fn mark_front(ms: &mut [Measurement]) {
    let dominated: Vec<bool> = ms
        .iter()
        .map(|a| {
            !a.error.is_finite()
                || ms.iter().any(|b| b.error.is_finite() && b.error <= a.error && b.time_s <= a.time_s && (b.error < a.error || b.time_s < a.time_s))
        })
        .collect();
    for (m, d) in ms.iter_mut().zip(dominated) {
        m.pareto = !d;
    }
}

/// The Burgers sweep: viscosity 0.05 to `t = 1` (the front steepens to a
/// width of about 0.1), resolutions `64…1024` (`quick`: `32…128`); P1's
/// fused scheme; upwind, semi-Lagrangian and MacCormack advection with
/// explicit diffusion at Courant numbers 0.25, 0.5, 1; the latter two also
/// with implicit diffusion (CG to 1e-8, and to 1e-3 at Courant number 1).
pub fn burgers_sweep(quick: bool) -> Vec<BurgersRun> {
    let sizes: &[usize] = if quick { &[32, 64, 128] } else { &[64, 128, 256, 512, 1024] };
    let (nu, t_end) = (0.05, 1.0);
    let mut runs = Vec::new();
    for &n in sizes {
        runs.push(BurgersRun::new(n, nu, t_end, 0.25, BurgersScheme::Fused));
        for advection in [Advection1d::Upwind, Advection1d::SemiLagrangian, Advection1d::MacCormack] {
            for cfl in [0.25, 0.5, 1.0] {
                runs.push(BurgersRun::new(n, nu, t_end, cfl, BurgersScheme::Split(advection, Diffusion::Explicit)));
                if advection != Advection1d::Upwind {
                    runs.push(BurgersRun::new(n, nu, t_end, cfl, BurgersScheme::Split(advection, Diffusion::Implicit { tolerance: 1e-8 })));
                }
            }
            if advection != Advection1d::Upwind {
                runs.push(BurgersRun::new(n, nu, t_end, 1.0, BurgersScheme::Split(advection, Diffusion::Implicit { tolerance: 1e-3 })));
            }
        }
    }
    // Explicit runs whose step the diffusion limits are the same run at
    // every Courant number: keep one.
    distinct(runs, |a, b| a.n == b.n && a.scheme == b.scheme && a.steps().0 == b.steps().0)
}

/// The runs without those `same` as an earlier one.
fn distinct<T>(runs: Vec<T>, same: impl Fn(&T, &T) -> bool) -> Vec<T> {
    let mut out: Vec<T> = Vec::new();
    for r in runs {
        if !out.iter().any(|o| same(o, &r)) {
            out.push(r);
        }
    }
    out
}

/// Family and settings of a Burgers run, for reports.
pub fn burgers_params(r: &BurgersRun) -> (String, Map<String, Value>) {
    let (steps, dt) = r.steps();
    let diffusion = r.scheme.diffusion();
    let fused = r.scheme == BurgersScheme::Fused;
    let family = if fused { "p1 fused upwind".to_string() } else { format!("{}/{}", r.scheme.advection_name(), diffusion) };
    let mut m = Map::new();
    m.insert("n".into(), json!(r.n));
    m.insert("advection".into(), json!(r.scheme.advection_name()));
    m.insert("diffusion".into(), json!(if fused { "explicit (fused)".to_string() } else { diffusion.to_string() }));
    m.insert("cfl".into(), json!(r.cfl));
    m.insert("tolerance".into(), tolerance(diffusion));
    m.insert("dt".into(), json!(dt));
    m.insert("steps".into(), json!(steps));
    (family, m)
}

fn tolerance(d: Diffusion) -> Value {
    match d {
        Diffusion::Implicit { tolerance } => json!(tolerance),
        Diffusion::Explicit => Value::Null,
    }
}

/// The Taylor–Green sweep: viscosity 0.01 to `t = 1`, resolutions
/// `16…128` (`quick`: `8…32`); semi-Lagrangian, MacCormack and limited
/// MacCormack advection at Courant numbers 0.5, 1, 2 with explicit
/// viscosity and pressure solves to 1e-8; at Courant number 1 also
/// implicit viscosity. (The projection of the periodic box is the FFT's:
/// no tolerance enters.)
pub fn taylor_green_sweep(quick: bool) -> Vec<TaylorGreenRun> {
    let sizes: &[usize] = if quick { &[8, 16, 32] } else { &[16, 32, 64, 128] };
    let base = |n, cfl, scheme| TaylorGreenRun { n, nu: 0.01, t_end: 1.0, cfl, scheme, diffusion: Diffusion::Explicit, pressure_tolerance: 1e-8 };
    let mut runs = Vec::new();
    for &n in sizes {
        for scheme in [Scheme::SemiLagrangian, Scheme::MacCormack { limiter: false }, Scheme::MacCormack { limiter: true }] {
            for cfl in [0.5, 1.0, 2.0] {
                runs.push(base(n, cfl, scheme));
            }
            runs.push(TaylorGreenRun { diffusion: Diffusion::Implicit { tolerance: 1e-8 }, ..base(n, 1.0, scheme) });
        }
    }
    distinct(runs, |a, b| {
        a.n == b.n && a.scheme == b.scheme && a.diffusion == b.diffusion && a.pressure_tolerance == b.pressure_tolerance && a.steps().0 == b.steps().0
    })
}

/// The same vortex by the Navier–Stokes operator (its sub-steps: one call
/// per Courant number 0.5, 1, 2, 4), MacCormack and semi-Lagrangian,
/// explicit and implicit viscosity, at the sweep's sizes.
pub fn navier_stokes_sweep(quick: bool) -> Vec<NavierStokesRun> {
    let mut runs = Vec::new();
    for tg in taylor_green_sweep(quick) {
        if tg.scheme == (Scheme::MacCormack { limiter: true }) || tg.cfl != 1.0 {
            continue;
        }
        for cfl in [0.5, 1.0, 2.0, 4.0] {
            runs.push(NavierStokesRun { cfl, ..NavierStokesRun::of(&tg) });
        }
    }
    distinct(runs, |a, b| a == b)
}

/// Family and settings of a Navier–Stokes operator run, for reports.
pub fn navier_stokes_params(r: &NavierStokesRun) -> (String, Map<String, Value>) {
    operator_params(r.n, r.scheme, r.viscosity, r.cfl, r.steps())
}

/// Family and settings of a run of the Navier–Stokes operator on `n`
/// cells per side in `(calls, time of each)`, for reports.
fn operator_params(n: usize, scheme: Scheme, viscosity: Diffusion, cfl: f64, (steps, dt): (usize, f64)) -> (String, Map<String, Value>) {
    let family = format!("operator/{}/{}", scheme_name(scheme), viscosity);
    let mut m = Map::new();
    m.insert("n".into(), json!(n));
    m.insert("advection".into(), json!(scheme_name(scheme)));
    m.insert("diffusion".into(), json!(viscosity.to_string()));
    m.insert("cfl".into(), json!(cfl));
    m.insert("diffusion_tolerance".into(), tolerance(viscosity));
    m.insert("dt".into(), json!(dt));
    m.insert("steps".into(), json!(steps));
    (family, m)
}

/// The 3D Arnold–Beltrami–Childress flow (ν = 0.05 to `t = 1`) by the
/// Navier–Stokes operator: semi-Lagrangian and MacCormack advection, calls
/// of Courant number 0.5, 1, 2 and 4 (on the largest speed) split into
/// sub-steps, explicit viscosity, and implicit at Courant number 1;
/// `8³…32³` (`quick`: `8³, 16³`).
pub fn abc_sweep(quick: bool) -> Vec<AbcRun> {
    let sizes: &[usize] = if quick { &[8, 16] } else { &[8, 16, 32] };
    let mut runs = Vec::new();
    for &n in sizes {
        for scheme in [Scheme::SemiLagrangian, Scheme::MacCormack { limiter: false }] {
            let base = AbcRun { n, nu: 0.05, t_end: 1.0, cfl: 1.0, scheme, viscosity: Diffusion::Explicit };
            for cfl in [0.5, 1.0, 2.0, 4.0] {
                runs.push(AbcRun { cfl, ..base });
            }
            runs.push(AbcRun { viscosity: Diffusion::Implicit { tolerance: 1e-8 }, ..base });
        }
    }
    runs
}

/// Family and settings of an ABC run, for reports.
pub fn abc_params(r: &AbcRun) -> (String, Map<String, Value>) {
    operator_params(r.n, r.scheme, r.viscosity, r.cfl, r.steps())
}

/// Family and settings of a Taylor–Green run, for reports.
pub fn taylor_green_params(r: &TaylorGreenRun) -> (String, Map<String, Value>) {
    let (steps, dt) = r.steps();
    let family = format!("{}/{}", scheme_name(r.scheme), r.diffusion);
    let mut m = Map::new();
    m.insert("n".into(), json!(r.n));
    m.insert("advection".into(), json!(scheme_name(r.scheme)));
    m.insert("diffusion".into(), json!(r.diffusion.to_string()));
    m.insert("cfl".into(), json!(r.cfl));
    m.insert("diffusion_tolerance".into(), tolerance(r.diffusion));
    m.insert("pressure_tolerance".into(), json!(r.pressure_tolerance));
    m.insert("dt".into(), json!(dt));
    m.insert("steps".into(), json!(steps));
    (family, m)
}

/// What `diffsim pareto` sweeps.
#[derive(Clone, Copy, Debug, PartialEq, Eq, serde::Serialize, serde::Deserialize)]
pub enum ParetoProblem {
    /// Viscous Burgers (ν = 0.05, u₀ = sin x, t = 1) against Cole–Hopf.
    Burgers,
    /// The Taylor–Green vortex (ν = 0.01, t = 1) against its exact decay.
    TaylorGreen,
    /// The 3D Arnold–Beltrami–Childress flow (ν = 0.05, t = 1) by the
    /// Navier–Stokes operator against its exact decay.
    Abc,
    /// Schäfer–Turek's case 2D-1: c_D against the tight reference, by
    /// Newton's method and by pseudo-time marching.
    Cylinder,
    /// P1's gradient: Enzyme and hand-written adjoints with every
    /// checkpointing mode against central differences.
    BurgersGradients,
    /// The gradient of a Taylor–Green rollout of the smoke step with
    /// respect to its start, the same methods.
    TaylorGreenGradients,
}

impl ParetoProblem {
    /// The folder and report name (`burgers`, `taylor-green-gradients`, …).
    pub fn name(self) -> &'static str {
        match self {
            ParetoProblem::Burgers => "burgers",
            ParetoProblem::TaylorGreen => "taylor-green",
            ParetoProblem::Abc => "abc",
            ParetoProblem::Cylinder => "cylinder",
            ParetoProblem::BurgersGradients => "burgers-gradients",
            ParetoProblem::TaylorGreenGradients => "taylor-green-gradients",
        }
    }

    /// The report's title.
    pub fn title(self) -> &'static str {
        match self {
            ParetoProblem::Burgers => "Burgers (ν = 0.05, t = 1): error vs time",
            ParetoProblem::TaylorGreen => "Taylor–Green vortex (ν = 0.01, t = 1): error vs time",
            ParetoProblem::Abc => "ABC flow, 3D (ν = 0.05, t = 1): error vs time",
            ParetoProblem::Cylinder => "Schäfer–Turek 2D-1 (Re 20): c_D error vs time",
            ParetoProblem::BurgersGradients => "P1 Burgers gradient: error vs time",
            ParetoProblem::TaylorGreenGradients => "Taylor–Green gradient (∂L/∂x₀): error vs time",
        }
    }
}

/// The sweep's settings.
#[derive(Clone, Copy, Debug, PartialEq, serde::Serialize, serde::Deserialize)]
pub struct ParetoParams {
    /// What is swept.
    pub problem: ParetoProblem,
    /// Smaller grids (a run of seconds).
    pub quick: bool,
    /// Seconds of repeats per configuration for the median time.
    pub budget: f64,
}

/// `(time, error)` points of a plot.
pub type Points = Vec<(f64, f64)>;

/// Every configuration measured, the front marked ([`run`]).
#[derive(Clone, Debug)]
pub struct ParetoReport {
    /// The settings.
    pub params: ParetoParams,
    /// One row per configuration.
    pub rows: Vec<Measurement>,
    /// Configurations whose run failed (their error is NaN), one line each.
    pub warnings: Vec<String>,
}

/// Measures every configuration of the sweep (error, median time, peak
/// memory) and marks the front of error against time.
///
/// # Errors
/// A gradient sweep whose reference gradient cannot be computed.
pub fn run(p: &ParetoParams) -> Result<ParetoReport, StudyError> {
    let (budget, quick) = (p.budget, p.quick);
    let mut warnings = Vec::new();
    let mut rows = match p.problem {
        ParetoProblem::Burgers => burgers_sweep(quick)
            .iter()
            .map(|r| {
                let (family, params) = burgers_params(r);
                accuracy_row(family, params, timed_error(budget, || r.run(), |u| r.error_of(u)), &mut warnings)
            })
            .collect(),
        ParetoProblem::TaylorGreen => {
            let mut rows: Vec<Measurement> = taylor_green_sweep(quick)
                .iter()
                .map(|r| {
                    let (family, params) = taylor_green_params(r);
                    accuracy_row(family, params, timed_error(budget, || r.run(), |u| r.error_of(u)), &mut warnings)
                })
                .collect();
            for r in navier_stokes_sweep(quick) {
                let (family, params) = navier_stokes_params(&r);
                rows.push(accuracy_row(family, params, timed_error(budget, || r.run(), |u| r.error_of(u)), &mut warnings));
            }
            rows
        }
        ParetoProblem::Abc => abc_sweep(quick)
            .iter()
            .map(|r| {
                let (family, params) = abc_params(r);
                accuracy_row(family, params, timed_error(budget, || r.run(), |u| r.error_of(u)), &mut warnings)
            })
            .collect(),
        ParetoProblem::Cylinder => cylinder_rows(budget, quick, &mut warnings),
        ParetoProblem::BurgersGradients => {
            let p = if quick { P1::new(64, 64) } else { P1::new(256, 256) };
            gradient_rows(
                budget,
                p.steps,
                |enzyme, mode| if enzyme { p.grad_enzyme(mode) } else { p.grad_hand(mode) },
                |u0| {
                    let mut q = p.clone();
                    q.u0 = u0.to_vec();
                    q.value().unwrap_or(f64::NAN)
                },
                &p.u0,
            )?
        }
        ParetoProblem::TaylorGreenGradients => {
            let (n, steps) = if quick { (8, 4) } else { (16, 8) };
            let tg = TaylorGreenGradient::new(n, steps);
            gradient_rows(budget, steps, |enzyme, mode| tg.gradient(enzyme, mode), |x0| tg.value(x0), &tg.x0)?
        }
    };
    mark_front(&mut rows);
    Ok(ParetoReport { params: *p, rows, warnings })
}

impl ParetoReport {
    /// The report's title.
    pub fn title(&self) -> &'static str {
        self.params.problem.title()
    }

    /// The rows as one JSON array.
    pub fn json(&self) -> Value {
        Value::Array(self.rows.iter().map(Measurement::to_json).collect())
    }

    /// The Markdown table (the front marked with ✓).
    pub fn markdown(&self) -> String {
        markdown(&self.rows)
    }

    /// `results.csv`: the settings by name, then error, time, peak memory
    /// and whether on the front.
    pub fn csv(&self) -> String {
        let keys = param_keys(&self.rows);
        let mut csv = format!("family,{},error,time_s,peak_rss_bytes,pareto\n", keys.join(","));
        for r in &self.rows {
            let vals: Vec<String> = keys
                .iter()
                .map(|k| r.params.get(k).map_or(String::new(), |v| if v.is_null() { String::new() } else { v.to_string().trim_matches('"').to_string() }))
                .collect();
            let _ = writeln!(csv, "{},{},{:e},{:e},{},{}", r.family, vals.join(","), r.error, r.time_s, r.peak_rss_bytes, r.pareto);
        }
        csv
    }

    /// The families in order of first appearance, each with its points
    /// `(time, error)` (an error of exactly 0 drawn at 1e-17 so that a log
    /// axis keeps it), and the front's points sorted by time.
    pub fn series(&self) -> (Vec<(String, Points)>, Points) {
        let mut families: Vec<&str> = Vec::new();
        for r in &self.rows {
            if !families.contains(&r.family.as_str()) {
                families.push(&r.family);
            }
        }
        let series =
            families.iter().map(|f| (f.to_string(), self.rows.iter().filter(|r| r.family == *f).map(|r| (r.time_s, r.error.max(1e-17))).collect())).collect();
        let mut front: Vec<(f64, f64)> = self.rows.iter().filter(|r| r.pareto).map(|r| (r.time_s, r.error.max(1e-17))).collect();
        front.sort_by(|a, b| a.0.total_cmp(&b.0));
        (series, front)
    }
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

/// The row of a configuration; a run that failed gets a NaN error and a
/// line in `warnings`.
fn accuracy_row(family: String, params: Map<String, Value>, r: (Result<f64, AccuracyError>, f64, u64), warnings: &mut Vec<String>) -> Measurement {
    let (result, time_s, peak_rss_bytes) = r;
    let error = result.unwrap_or_else(|e| {
        warnings.push(format!("{family} {}: {e}", Value::Object(params.clone())));
        f64::NAN
    });
    Measurement { family, params, error, time_s, peak_rss_bytes, pareto: false }
}

/// Case 2D-1 at several resolutions (cells per diameter) by Newton's method
/// and by marching in pseudo-time to `max |du/dt| < 1e-6` (the same
/// discrete steady state, reached two ways): c_D's relative error against
/// the tight reference value.
fn cylinder_rows(budget: f64, quick: bool, warnings: &mut Vec<String>) -> Vec<Measurement> {
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
            rows.push(accuracy_row(format!("{solver} (cut cells)"), params, (error, time_s, peak), warnings));
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
) -> Result<Vec<Measurement>, StudyError> {
    let modes = [Checkpointing::Store, Checkpointing::periodic_sqrt(steps), Checkpointing::binomial_log(steps)];
    let reference = grad(false, Checkpointing::Store)?.dx0;
    let enzyme_stored = grad(true, Checkpointing::Store)?.dx0;
    let rel = |g: &[f64], r: &[f64]| super::relative_l2(g, r);
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
    step: SmokeStep<2>,
    /// The same step with the hand-written adjoint.
    hand: SmokeStep<2>,
    steps: usize,
    x0: Vec<f64>,
    target: Vec<f64>,
}

impl TaylorGreenGradient {
    fn new(n: usize, steps: usize) -> Self {
        let cfg = super::flow::periodic_box(n);
        let h = super::flow::LENGTH / n as f64;
        // Half a cell per unit step at most.
        let tg = TaylorGreen { length: super::flow::LENGTH, amplitude: 0.5 * h, nu: 0.0 };
        let blob = diffsim_solvers::exact::Translation { length: super::flow::LENGTH, velocity: (0.0, 0.0) }.cells(n, 0.0);
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
