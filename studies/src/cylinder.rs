//! Flow around a cylinder in a channel against Schäfer & Turek (1996):
//! case 2D-1 (Re 20, steady: c_D, c_L, Δp), by Newton's method or by
//! marching in pseudo-time to the same discrete steady state, and case 2D-2
//! (Re 100, periodic shedding: the peaks of c_D and c_L, the Strouhal
//! number, Δp), with the published intervals; and the error of 2D-1 against
//! wall time over resolutions ([`sweep`]).

use std::time::Instant;

use diffsim_solvers::flow::Convection;
use diffsim_solvers::flow::cylinder::{Periodic2d2, Steady2d1, reference, run_2d1, run_2d1_newton, run_2d2};

use crate::StudyError;

/// Which case of the benchmark.
#[derive(Clone, Copy, Debug, PartialEq, Eq, serde::Serialize, serde::Deserialize)]
pub enum CylinderCase {
    /// 2D-1: Re 20, steady.
    Steady,
    /// 2D-2: Re 100, periodic shedding.
    Periodic,
}

/// How case 2D-1 reaches its steady state.
#[derive(Clone, Copy, Debug, PartialEq, Eq, serde::Serialize, serde::Deserialize)]
pub enum SteadySolver {
    /// Newton's method on the discrete steady equations (sparse LU).
    Newton,
    /// Pseudo-time marching (explicit steps with the projection).
    March,
}

impl SteadySolver {
    /// `"newton"` or `"march"`, as the reports name it.
    pub fn name(self) -> &'static str {
        match self {
            SteadySolver::Newton => "newton",
            SteadySolver::March => "march",
        }
    }
}

/// The run's settings. [`CylinderParams::steady`] (also `Default`) and
/// [`CylinderParams::periodic`] are the published cases at the resolutions
/// and interpolations the docs report.
#[derive(Clone, Copy, Debug, PartialEq, serde::Serialize, serde::Deserialize)]
pub struct CylinderParams {
    /// Which case.
    pub case: CylinderCase,
    /// Cells per cylinder diameter (a multiple of 10).
    pub resolution: usize,
    /// 2D-1: Newton or the pseudo-time march.
    pub solver: SteadySolver,
    /// The advection's interpolation.
    pub convection: Convection,
    /// 2D-1 by marching: steady when `max |du/dt|` falls below this.
    pub tolerance: f64,
    /// 2D-1 by marching: more pseudo-time steps than this is an error.
    pub max_steps: usize,
    /// 2D-2: simulated time from Poiseuille flow (the last 2 units measured).
    pub t_end: f64,
}

impl CylinderParams {
    /// Case 2D-1 by Newton at 40 cells per diameter, second-order
    /// interpolation.
    pub fn steady() -> Self {
        CylinderParams {
            case: CylinderCase::Steady,
            resolution: 40,
            solver: SteadySolver::Newton,
            convection: Convection::Second,
            tolerance: 1e-6,
            max_steps: 1_000_000,
            t_end: 10.0,
        }
    }

    /// Case 2D-2 at 30 cells per diameter, fourth-order interpolation, to
    /// t = 10.
    pub fn periodic() -> Self {
        CylinderParams { case: CylinderCase::Periodic, resolution: 30, convection: Convection::Fourth, ..Self::steady() }
    }
}

impl Default for CylinderParams {
    fn default() -> Self {
        Self::steady()
    }
}

/// A case's figures.
#[derive(Clone, Debug, PartialEq)]
pub enum CylinderResult {
    /// Case 2D-1.
    Steady(Steady2d1),
    /// Case 2D-2 (with the coefficients' time series).
    Periodic(Periodic2d2),
}

/// What [`run`] found.
#[derive(Clone, Debug)]
pub struct CylinderReport {
    /// The settings.
    pub params: CylinderParams,
    /// The figures.
    pub result: CylinderResult,
    /// Wall seconds.
    pub time_s: f64,
}

/// Runs the case. `progress(line)` describes where the run is (Newton's
/// start, every 200 pseudo-time steps, every time step of 2D-2).
///
/// # Errors
/// A flow that cannot be simulated or does not settle, or a figure that is
/// not finite ([`StudyError::NotReported`]).
pub fn run(p: &CylinderParams, mut progress: impl FnMut(&str)) -> Result<CylinderReport, StudyError> {
    let (per_d, convection) = (p.resolution, p.convection);
    let start = Instant::now();
    let result = match p.case {
        CylinderCase::Steady => {
            let r = match p.solver {
                SteadySolver::Newton => {
                    progress(&format!("2D-1, {per_d} cells per diameter: Newton's method"));
                    run_2d1_newton(per_d, convection)?
                }
                SteadySolver::March => run_2d1(per_d, convection, p.tolerance, p.max_steps, |step, t, rate| {
                    if step % 200 == 0 {
                        progress(&format!("2D-1, {per_d} cells per diameter: step {step}, t = {t:.2}, max |du/dt| = {rate:.2e}"));
                    }
                })?,
            };
            crate::finite_figures("cylinder 2D-1", &[("c_D", r.cd), ("c_L", r.cl), ("Δp", r.dp)])?;
            CylinderResult::Steady(r)
        }
        CylinderCase::Periodic => {
            let t_end = p.t_end;
            let r = run_2d2(per_d, convection, t_end, 2.0, |t, cl| {
                progress(&format!("2D-2, {per_d} cells per diameter: t = {t:.2} of {t_end}, c_L = {cl:+.3}"));
            })?;
            let figures = [("c_D,max", r.cd_max), ("c_L,max", r.cl_max), ("c_L,min", r.cl_min), ("St", r.st), ("Δp", r.dp)];
            crate::finite_figures("cylinder 2D-2", &figures)?;
            CylinderResult::Periodic(r)
        }
    };
    Ok(CylinderReport { params: *p, result, time_s: start.elapsed().as_secs_f64() })
}

/// `"inside"` when `v` lies in the published interval.
fn within(v: f64, (lo, hi): (f64, f64)) -> &'static str {
    if (lo..=hi).contains(&v) { "inside" } else { "outside" }
}

impl CylinderReport {
    /// The one-line result (`case`, `convection`, `resolution`, the
    /// figures, `cells`, `steps`, `time_s`; 2D-1 also `solver`).
    pub fn json(&self) -> serde_json::Value {
        let (p, time_s) = (&self.params, self.time_s);
        let scheme = p.convection.name();
        match &self.result {
            CylinderResult::Steady(r) => serde_json::json!({
                "case": "2d-1", "solver": p.solver.name(), "convection": scheme, "resolution": p.resolution,
                "cd": r.cd, "cl": r.cl, "dp": r.dp, "cells": r.cells, "steps": r.steps, "time_s": time_s,
            }),
            CylinderResult::Periodic(r) => serde_json::json!({
                "case": "2d-2", "convection": scheme, "resolution": p.resolution,
                "cd_max": r.cd_max, "cl_max": r.cl_max, "cl_min": r.cl_min, "cl_mean": r.cl_mean, "st": r.st, "dp": r.dp,
                "cells": r.cells, "steps": r.steps, "time_s": time_s,
            }),
        }
    }

    /// The heading line and the Markdown table of the figures against the
    /// published intervals.
    pub fn table(&self) -> String {
        let (p, time_s) = (&self.params, self.time_s);
        let (per_d, scheme) = (p.resolution, p.convection.name());
        let mut out = String::new();
        match &self.result {
            CylinderResult::Steady(r) => {
                let how = match p.solver {
                    SteadySolver::Newton => "Newton steps",
                    SteadySolver::March => "pseudo-time steps",
                };
                out.push_str(&format!(
                    "Schäfer–Turek 2D-1 (Re 20), {per_d} cells per diameter, {} cells, {scheme}-order convection: steady after {} {how}, {time_s:.1} s\n",
                    r.cells, r.steps
                ));
                out.push_str("| quantity | diffsim | published | |\n|---|---|---|---|\n");
                out.push_str(&format!(
                    "| c_D | {:.4} | 5.57–5.59 (5.5795) | {} ({:+.2} % from 5.5795) |\n",
                    r.cd,
                    within(r.cd, reference::CD_2D1),
                    100.0 * (r.cd / reference::CD_2D1_TIGHT - 1.0)
                ));
                out.push_str(&format!("| c_L | {:.4} | 0.0104–0.0110 | {} |\n", r.cl, within(r.cl, reference::CL_2D1)));
                out.push_str(&format!("| Δp | {:.4} | 0.1172–0.1176 | {} |\n", r.dp, within(r.dp, reference::DP_2D1)));
            }
            CylinderResult::Periodic(r) => {
                out.push_str(&format!(
                    "Schäfer–Turek 2D-2 (Re 100), {per_d} cells per diameter, {} cells, {scheme}-order convection: {} steps to t = {}, {time_s:.1} s\n",
                    r.cells, r.steps, p.t_end
                ));
                out.push_str("| quantity | diffsim | published | |\n|---|---|---|---|\n");
                out.push_str(&format!("| c_D,max | {:.4} | 3.22–3.24 | {} |\n", r.cd_max, within(r.cd_max, reference::CD_MAX_2D2)));
                out.push_str(&format!("| c_L,max | {:.4} | 0.99–1.01 | {} |\n", r.cl_max, within(r.cl_max, reference::CL_MAX_2D2)));
                out.push_str(&format!("| St | {:.4} | 0.295–0.305 | {} |\n", r.st, within(r.st, reference::ST_2D2)));
                out.push_str(&format!("| Δp(t₀ + 1/2f) | {:.4} | 2.46–2.50 | {} |\n", r.dp, within(r.dp, reference::DP_2D2)));
                out.push_str(&format!("| c_L,min | {:.4} | (not published) | |\n", r.cl_min));
                out.push_str(&format!("| mean c_L | {:+.4} | (not published) | |\n", r.cl_mean));
            }
        }
        out
    }

    /// 2D-2's coefficients over time as CSV (`t,cd,cl,dp`); `None` for 2D-1.
    pub fn series_csv(&self) -> Option<String> {
        let CylinderResult::Periodic(r) = &self.result else { return None };
        let mut csv = String::from("t,cd,cl,dp\n");
        for s in &r.series {
            csv.push_str(&format!("{:.6},{:.8},{:.8},{:.8}\n", s[0], s[1], s[2], s[3]));
        }
        Some(csv)
    }
}

/// One resolution of the [`sweep`].
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct SweepRow {
    /// Cells per diameter.
    pub resolution: usize,
    /// 2D-1's figures there.
    pub result: Steady2d1,
    /// Wall seconds.
    pub time_s: f64,
}

impl SweepRow {
    /// c_D's relative error against the tight reference 5.57954.
    pub fn cd_error(&self) -> f64 {
        (self.result.cd / reference::CD_2D1_TIGHT - 1.0).abs()
    }

    /// Δp's relative error against the tight reference 0.11752.
    pub fn dp_error(&self) -> f64 {
        (self.result.dp / reference::DP_2D1_TIGHT - 1.0).abs()
    }
}

/// Case 2D-1 by Newton at several resolutions: error against wall time.
#[derive(Clone, Debug)]
pub struct SweepReport {
    /// One row per resolution, in the order asked.
    pub rows: Vec<SweepRow>,
}

/// Runs 2D-1 by Newton at each of `resolutions` (cells per diameter) with
/// `convection`.
///
/// # Errors
/// A resolution whose flow cannot be solved, or a figure not finite.
pub fn sweep(resolutions: &[usize], convection: Convection) -> Result<SweepReport, StudyError> {
    let mut rows = Vec::with_capacity(resolutions.len());
    for &resolution in resolutions {
        let t = Instant::now();
        let result = run_2d1_newton(resolution, convection)?;
        crate::finite_figures(&format!("cylinder 2D-1 at {resolution} cells per diameter"), &[("c_D", result.cd), ("Δp", result.dp)])?;
        rows.push(SweepRow { resolution, result, time_s: t.elapsed().as_secs_f64() });
    }
    Ok(SweepReport { rows })
}

impl SweepReport {
    /// The one-line result: `{"case": "2d-1", "solver": "newton", "sweep": [rows]}`.
    pub fn json(&self) -> serde_json::Value {
        let list: Vec<serde_json::Value> = self
            .rows
            .iter()
            .map(|row| {
                let r = &row.result;
                serde_json::json!({
                    "resolution": row.resolution, "cells": r.cells, "cd": r.cd, "cl": r.cl, "dp": r.dp,
                    "cd_error": row.cd_error(), "dp_error": row.dp_error(), "time_s": row.time_s,
                })
            })
            .collect();
        serde_json::json!({"case": "2d-1", "solver": "newton", "sweep": list})
    }

    /// The heading line and the Markdown table, a row per resolution.
    pub fn table(&self) -> String {
        let mut out = String::from(
            "Schäfer–Turek 2D-1 by Newton's method: error against wall time\n| cells per D | cells | c_D | c_D error | c_L | Δp | Δp error | time |\n|---|---|---|---|---|---|---|---|\n",
        );
        for row in &self.rows {
            let r = &row.result;
            out.push_str(&format!(
                "| {} | {} | {:.5} | {:.3} % | {:.5} | {:.5} | {:.2} % | {:.1} s |\n",
                row.resolution,
                r.cells,
                r.cd,
                100.0 * row.cd_error(),
                r.cl,
                r.dp,
                100.0 * row.dp_error(),
                row.time_s
            ));
        }
        out
    }
}
