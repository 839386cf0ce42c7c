//! The "flow around a cylinder" benchmark of Schäfer & Turek (1996): a
//! channel 2.2 × 0.41, a cylinder of diameter 0.1 centred at (0.2, 0.2),
//! parabolic inflow on the left, no-slip walls top and bottom, outflow on
//! the right, ν = 10⁻³, ρ = 1. Case 2D-1 (peak inflow 0.3, Re 20) is
//! steady; case 2D-2 (peak 1.5, Re 100) sheds vortices periodically.

use super::{
    Convection, Flow2d, FlowError, Integrator, NewtonParams, Shape, SteadyFlow, SteadyParams, SteadyState, Stepper, WallSpeed, body::fluid_value_at, ladder,
    march_to_steady, max_speed,
};
use crate::boundary::{Boundary, Profile, Side};

/// Diameter of the cylinder.
pub const DIAMETER: f64 = 0.1;

/// Published reference intervals (Schäfer & Turek 1996, Table 3).
pub mod reference {
    /// 2D-1: drag coefficient (the tight value 5.57953523384).
    pub const CD_2D1: (f64, f64) = (5.57, 5.59);
    /// 2D-1: lift coefficient (tight 0.010618948146).
    pub const CL_2D1: (f64, f64) = (0.0104, 0.0110);
    /// 2D-1: pressure difference `p(0.15, 0.2) − p(0.25, 0.2)` (tight 0.11752016697).
    pub const DP_2D1: (f64, f64) = (0.1172, 0.1176);
    /// 2D-2: maximum drag coefficient.
    pub const CD_MAX_2D2: (f64, f64) = (3.22, 3.24);
    /// 2D-2: maximum lift coefficient.
    pub const CL_MAX_2D2: (f64, f64) = (0.99, 1.01);
    /// 2D-2: Strouhal number.
    pub const ST_2D2: (f64, f64) = (0.295, 0.305);
    /// 2D-2: pressure difference `p(0.15, 0.2) − p(0.25, 0.2)` half a period
    /// after the lift's maximum.
    pub const DP_2D2: (f64, f64) = (2.46, 2.50);
    /// The tight 2D-1 drag coefficient of the later high-accuracy computations.
    pub const CD_2D1_TIGHT: f64 = 5.57953523384;
    /// The tight 2D-1 pressure difference of the same computations.
    pub const DP_2D1_TIGHT: f64 = 0.11752016697;
}

/// The benchmark's channel and cylinder at `cells_per_d` cells per
/// diameter (a multiple of 10, so that the channel's height 0.41 is a whole
/// number of cells) and peak inflow `u_max`.
pub fn schafer_turek(cells_per_d: usize, u_max: f64) -> (Flow2d, Shape) {
    let h = DIAMETER / cells_per_d as f64;
    let cfg = Flow2d {
        nx: 22 * cells_per_d,
        ny: (4.1 * cells_per_d as f64).round() as usize,
        h,
        nu: 1e-3,
        boundary: Boundary { sides: [[Side::Inflow(Profile::Parabolic(u_max)), Side::Outflow], [Side::Closed, Side::Closed]] },
        wall_speed: WallSpeed::default(),
        convection: Convection::Second,
    };
    (cfg, Shape::Circle { center: [0.2, 0.2], radius: 0.5 * DIAMETER })
}

/// The channel's Poiseuille flow everywhere (the start of both cases).
pub fn poiseuille(cfg: &Flow2d, u_max: f64) -> Vec<f64> {
    let mut x = cfg.rest();
    for j in 0..cfg.ny {
        let t = (j as f64 + 0.5) / cfg.ny as f64;
        for i in 0..=cfg.nx {
            x[j * (cfg.nx + 1) + i] = 4.0 * u_max * t * (1.0 - t);
        }
    }
    x
}

/// The control volume of the force: cells within one diameter of the
/// cylinder's bounding box.
pub(crate) fn force_box(cfg: &Flow2d) -> [usize; 4] {
    let cell = |x: f64| (x / cfg.h).round() as usize;
    [cell(0.05), cell(0.35), cell(0.05), cell(0.35)]
}

/// Drag and lift coefficients `2F/(ρŪ²D)` of a force, `Ū = 2·u_max/3`.
pub fn coefficients(force: [f64; 2], u_max: f64) -> [f64; 2] {
    let ubar = 2.0 * u_max / 3.0;
    let scale = 2.0 / (ubar * ubar * DIAMETER);
    [force[0] * scale, force[1] * scale]
}

/// Case 2D-1's results.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Steady2d1 {
    /// Drag coefficient.
    pub cd: f64,
    /// Lift coefficient.
    pub cl: f64,
    /// `p(0.15, 0.2) − p(0.25, 0.2)` (each from a least-squares plane over
    /// the fluid cells near the point).
    pub dp: f64,
    /// Cells.
    pub cells: usize,
    /// Pseudo-time steps.
    pub steps: usize,
}

/// Case 2D-1 with the advection's `convection`: marched from Poiseuille
/// flow to the steady state (`max |du/dt| < tolerance`). `observe(step,
/// time, rate)` after every step.
pub fn run_2d1(
    cells_per_d: usize,
    convection: Convection,
    tolerance: f64,
    max_steps: usize,
    observe: impl FnMut(usize, f64, f64),
) -> Result<Steady2d1, FlowError> {
    let u_max = 0.3;
    let (cfg, shape) = schafer_turek(cells_per_d, u_max);
    let cfg = Flow2d { convection, ..cfg };
    let mut stepper = Stepper::with_bodies(cfg, 1e-10, std::slice::from_ref(&shape))?;
    let mut x = poiseuille(&cfg, u_max);
    let report = march_to_steady(&mut stepper, &mut x, &SteadyParams { tolerance, max_steps, reference_speed: 1.5 * u_max }, observe)?;
    let [cd, cl] = coefficients(stepper.force_in_box(&x, None, force_box(&cfg)), u_max);
    let p = stepper.pressure();
    let at = |x: f64| fluid_value_at(&cfg, stepper.cut(), &p, x, 0.2).unwrap_or(f64::NAN);
    Ok(Steady2d1 { cd, cl, dp: at(0.15) - at(0.25), cells: cfg.nx * cfg.ny, steps: report.steps })
}

/// Case 2D-1 by Newton's method on the discrete steady equations
/// ([`SteadyFlow`], the same equations the march of [`run_2d1`] converges
/// to), from Poiseuille flow; `steps` counts Newton steps.
pub fn run_2d1_newton(cells_per_d: usize, convection: Convection) -> Result<Steady2d1, FlowError> {
    let u_max = 0.3;
    let (cfg, shape) = schafer_turek(cells_per_d, u_max);
    let cfg = Flow2d { convection, ..cfg };
    let (flow, state) = steady_from_poiseuille(cfg, &shape, u_max)?;
    let [cd, cl] = coefficients(flow.force(&state, force_box(&cfg)), u_max);
    let at = |x: f64| fluid_value_at(&cfg, Some(flow.cut()), &state.pressure, x, 0.2).unwrap_or(f64::NAN);
    Ok(Steady2d1 { cd, cl, dp: at(0.15) - at(0.25), cells: cfg.nx * cfg.ny, steps: state.steps })
}

/// The steady flow around `shape` on `cfg`, by Newton's method from
/// Poiseuille flow of peak `u_max`.
fn steady_from_poiseuille(cfg: Flow2d, shape: &Shape, u_max: f64) -> Result<(SteadyFlow, SteadyState), FlowError> {
    let flow = SteadyFlow::new(cfg, std::slice::from_ref(shape))?;
    let state = flow.solve(&poiseuille(&cfg, u_max), &NewtonParams::default())?;
    Ok((flow, state))
}

/// Case 2D-2's results.
#[derive(Clone, Debug, PartialEq)]
pub struct Periodic2d2 {
    /// Largest drag coefficient over the measured periods.
    pub cd_max: f64,
    /// Largest lift coefficient over the measured periods.
    pub cl_max: f64,
    /// Smallest lift coefficient over the measured periods.
    pub cl_min: f64,
    /// Time-averaged lift coefficient over the measured periods (the
    /// channel is not symmetric about the cylinder, so it is not zero).
    pub cl_mean: f64,
    /// Strouhal number `f·D/Ū` from the lift's period.
    pub st: f64,
    /// Pressure difference `p(0.15, 0.2) − p(0.25, 0.2)` half a period
    /// after the lift's maximum (the benchmark's `ΔP(t₀ + 1/(2f))`).
    pub dp: f64,
    /// Cells.
    pub cells: usize,
    /// Time steps.
    pub steps: usize,
    /// `(t, c_D, c_L, Δp)` at the middle of every step.
    pub series: Vec<[f64; 4]>,
}

/// Case 2D-2 with the advection's `convection`: SSP-RK3 from Poiseuille
/// flow to `t_end`, the step the largest stable one (Courant number 0.8 of
/// RK3's limit) for the current speed; the force and `Δp` (the pressure by
/// [`fluid_value_at`]) at the middle of every step, measured over the last
/// `measure` time units by [`periodic_measures`].
pub fn run_2d2(cells_per_d: usize, convection: Convection, t_end: f64, measure: f64, mut observe: impl FnMut(f64, f64)) -> Result<Periodic2d2, FlowError> {
    let u_max = 1.5;
    let (cfg, shape) = schafer_turek(cells_per_d, u_max);
    let cfg = Flow2d { convection, ..cfg };
    let mut stepper = Stepper::with_bodies(cfg, 1e-10, std::slice::from_ref(&shape))?;
    let mut x = poiseuille(&cfg, u_max);
    let (mut t, mut steps) = (0.0, 0);
    let mut series = Vec::new();
    let (mut before, mut mid, mut dudt) = (x.clone(), x.clone(), x.clone());
    let cells = force_box(&cfg);
    let dt0 = Integrator::Rk3.stable_dt(&cfg, 1.5 * u_max);
    while t < t_end {
        let dt = ladder(dt0, Integrator::Rk3.stable_dt(&cfg, max_speed(&cfg, &x).max(1.5 * u_max)));
        before.copy_from_slice(&x);
        stepper.step(&mut x, dt, Integrator::Rk3)?;
        for ((m, d), (&a, &b)) in mid.iter_mut().zip(dudt.iter_mut()).zip(before.iter().zip(&x)) {
            *m = 0.5 * (a + b);
            *d = (b - a) / dt;
        }
        let [cd, cl] = coefficients(stepper.force_in_box(&mid, Some(&dudt), cells), u_max);
        let p = stepper.pressure();
        let at = |x: f64| fluid_value_at(&cfg, stepper.cut(), &p, x, 0.2).unwrap_or(f64::NAN);
        series.push([t + 0.5 * dt, cd, cl, at(0.15) - at(0.25)]);
        t += dt;
        steps += 1;
        observe(t, cl);
    }
    let m = periodic_measures(&series, t_end - measure)?;
    let st = DIAMETER / (m.period * 2.0 * u_max / 3.0);
    Ok(Periodic2d2 { cd_max: m.cd_max, cl_max: m.cl_max, cl_min: m.cl_min, cl_mean: m.cl_mean, st, dp: m.dp, cells: cfg.nx * cfg.ny, steps, series })
}

/// What case 2D-2 measures of a periodic series.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct PeriodicMeasures {
    /// Largest drag coefficient.
    pub cd_max: f64,
    /// Largest lift coefficient.
    pub cl_max: f64,
    /// Smallest lift coefficient.
    pub cl_min: f64,
    /// The lift's time average over whole periods.
    pub cl_mean: f64,
    /// The lift's period.
    pub period: f64,
    /// `Δp` half a period after the lift's maximum.
    pub dp: f64,
}

/// The benchmark's measures of the samples `(t, c_D, c_L, Δp)` from time
/// `from` on: the extrema; the period as the mean spacing of the lift's
/// upward crossings of its sample mean (interpolated linearly); the lift's
/// time average over the whole periods between the first and the last
/// crossing (trapezoidal rule); `Δp` at `t₀ + T/2`, `t₀` the time of the
/// largest lift sample (at `t₀ − T/2`, the same phase, when that falls past
/// the end), interpolated linearly. An error when fewer than two periods
/// fit.
pub fn periodic_measures(series: &[[f64; 4]], from: f64) -> Result<PeriodicMeasures, FlowError> {
    let tail: Vec<[f64; 4]> = series.iter().copied().filter(|s| s[0] >= from).collect();
    let cd_max = tail.iter().map(|s| s[1]).fold(f64::NEG_INFINITY, f64::max);
    let cl_max = tail.iter().map(|s| s[2]).fold(f64::NEG_INFINITY, f64::max);
    let cl_min = tail.iter().map(|s| s[2]).fold(f64::INFINITY, f64::min);
    let mean = tail.iter().map(|s| s[2]).sum::<f64>() / tail.len().max(1) as f64;
    let mut ups = Vec::new();
    for w in tail.windows(2) {
        let (a, b) = (w[0][2] - mean, w[1][2] - mean);
        if a < 0.0 && b >= 0.0 {
            ups.push(w[0][0] + (w[1][0] - w[0][0]) * (-a) / (b - a));
        }
    }
    if ups.len() < 3 {
        return Err(FlowError::NotPeriodic { crossings: ups.len() });
    }
    let (first, last) = (ups[0], ups[ups.len() - 1]);
    let period = (last - first) / (ups.len() - 1) as f64;
    // Column `k` at time `t`, interpolated linearly between samples.
    let at = |t: f64, k: usize| {
        tail.windows(2).find(|w| w[0][0] <= t && t <= w[1][0]).map_or(f64::NAN, |w| w[0][k] + (w[1][k] - w[0][k]) * (t - w[0][0]) / (w[1][0] - w[0][0]))
    };
    // The samples between the first and the last crossing, with the lift
    // interpolated at both ends, integrated by the trapezoidal rule.
    let mut points = vec![(first, at(first, 2))];
    points.extend(tail.iter().filter(|s| s[0] > first && s[0] < last).map(|s| (s[0], s[2])));
    points.push((last, at(last, 2)));
    let area: f64 = points.windows(2).map(|w| 0.5 * (w[0].1 + w[1].1) * (w[1].0 - w[0].0)).sum();
    let cl_mean = area / (last - first);
    let t0 = tail.iter().fold((f64::NAN, f64::NEG_INFINITY), |best, s| if s[2] > best.1 { (s[0], s[2]) } else { best }).0;
    let end = tail[tail.len() - 1][0];
    let phase = if t0 + 0.5 * period <= end { t0 + 0.5 * period } else { t0 - 0.5 * period };
    Ok(PeriodicMeasures { cd_max, cl_max, cl_min, cl_mean, period, dp: at(phase, 3) })
}
