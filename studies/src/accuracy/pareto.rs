//! Error versus cost: the configurations `diffsim pareto` sweeps, one
//! measurement per configuration, and the front of error versus time.

use diffsim_solvers::burgers::Advection1d;
use diffsim_solvers::smoke::Scheme;
use serde_json::{Map, Value, json};

use super::Diffusion;
use super::burgers::{BurgersRun, BurgersScheme};
use super::flow::{TaylorGreenRun, scheme_name};

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
/// implicit viscosity, and MacCormack with pressure tolerances 1e-2 and 1e-4.
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
        for tol in [1e-2, 1e-4] {
            runs.push(TaylorGreenRun { pressure_tolerance: tol, ..base(n, 1.0, Scheme::MacCormack { limiter: false }) });
        }
    }
    distinct(runs, |a, b| {
        a.n == b.n && a.scheme == b.scheme && a.diffusion == b.diffusion && a.pressure_tolerance == b.pressure_tolerance && a.steps().0 == b.steps().0
    })
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
