//! `diffsim experiment cavity` and `cylinder`: the viscous solver
//! ([`diffsim_solvers::flow`]) on the lid-driven cavity, compared with
//! Ghia, Ghia & Shin (1982), and on the flow around a cylinder, compared
//! with Schäfer & Turek (1996).

use std::path::PathBuf;
use std::time::Instant;

use diffsim_solvers::flow::{CavityExtrema, Flow2d, SteadyOptions, Stepper, cavity_extrema, centrelines, ghia, march_to_steady};

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
}

/// What one cavity run gives.
struct CavityRun {
    cfg: Flow2d,
    x: Vec<f64>,
    extrema: CavityExtrema,
    steps: usize,
    time_s: f64,
}

fn run_cavity(a: &CavityArgs) -> Result<CavityRun, CliError> {
    let (re, n, tolerance) = (a.re, a.resolution, a.tolerance);
    if !(re.is_finite() && re > 0.0) {
        return Err(CliError::Argument { arg: "--re", reason: format!("must be a positive number, got {re}") });
    }
    if !(4..=4096).contains(&n) {
        return Err(CliError::Argument { arg: "--resolution", reason: format!("must be between 4 and 4096 cells per side, got {n}") });
    }
    if !(tolerance.is_finite() && tolerance > 0.0) {
        return Err(CliError::Argument { arg: "--tolerance", reason: format!("must be a positive number, got {tolerance}") });
    }
    let cfg = Flow2d::cavity(n, re);
    let start = Instant::now();
    let mut stepper = Stepper::new(cfg, 1e-10)?;
    let mut x = cfg.rest();
    let spinner = if a.json { indicatif::ProgressBar::hidden() } else { indicatif::ProgressBar::new_spinner() };
    let opts = SteadyOptions { tolerance, max_steps: a.max_steps, reference_speed: 1.0 };
    let report = march_to_steady(&mut stepper, &mut x, &opts, |step, t, rate| {
        if step % 500 == 0 {
            spinner.set_message(format!("cavity Re {re}, {n}²: step {step}, t = {t:.1}, max |du/dt| = {rate:.2e}"));
            spinner.tick();
        }
    })?;
    spinner.finish_and_clear();
    let extrema = cavity_extrema(&cfg, &x);
    Ok(CavityRun { cfg, x, extrema, steps: report.steps, time_s: start.elapsed().as_secs_f64() })
}

pub(super) fn cavity(a: CavityArgs) -> Result<(), CliError> {
    let run = run_cavity(&a)?;
    let e = run.extrema;
    let reference = ghia(a.re).map(|t| t.extrema());
    let rel = |ours: f64, theirs: f64| (ours - theirs) / theirs;
    if let Some(dir) = &a.out {
        write_profiles(dir, &run, a.re)?;
    }
    let cells = run.cfg.nx * run.cfg.ny;
    if a.json {
        let mut obj = serde_json::json!({
            "re": a.re, "resolution": a.resolution,
            "u_min": e.u_min.value, "y_at_u_min": e.u_min.at,
            "v_max": e.v_max.value, "x_at_v_max": e.v_max.at,
            "v_min": e.v_min.value, "x_at_v_min": e.v_min.at,
            "cells": cells, "steps": run.steps, "time_s": run.time_s,
        });
        if let Some(g) = reference {
            obj["ghia"] = serde_json::json!({
                "u_min": g.u_min.value, "y_at_u_min": g.u_min.at,
                "v_max": g.v_max.value, "x_at_v_max": g.v_max.at,
                "v_min": g.v_min.value, "x_at_v_min": g.v_min.at,
            });
            obj["relative_error"] = serde_json::json!({
                "u_min": rel(e.u_min.value, g.u_min.value),
                "v_max": rel(e.v_max.value, g.v_max.value),
                "v_min": rel(e.v_min.value, g.v_min.value),
            });
        }
        println!("{obj}");
        return Ok(());
    }
    println!("lid-driven cavity, Re {}, {}² cells: steady after {} steps, {:.1} s", a.re, a.resolution, run.steps, run.time_s);
    println!("| extremum | diffsim (at) | Ghia et al. 1982 (at) | difference in magnitude |\n|---|---|---|---|");
    let rows = [
        ("u_min (x = ½)", e.u_min, reference.map(|g| g.u_min)),
        ("v_max (y = ½)", e.v_max, reference.map(|g| g.v_max)),
        ("v_min (y = ½)", e.v_min, reference.map(|g| g.v_min)),
    ];
    for (name, ours, theirs) in rows.iter() {
        match theirs {
            Some(g) => println!("| {name} | {:.5} ({:.4}) | {:.5} ({:.4}) | {:+.2} % |", ours.value, ours.at, g.value, g.at, 100.0 * rel(ours.value, g.value)),
            None => println!("| {name} | {:.5} ({:.4}) | – | – |", ours.value, ours.at),
        }
    }
    if reference.is_none() {
        println!("(Ghia et al. tabulate Re 100, 400 and 1000 only)");
    }
    if let Some(dir) = &a.out {
        println!("wrote {} to {}", profile_names(a.re).join(", "), dir.display());
    }
    Ok(())
}

fn profile_names(re: f64) -> [String; 2] {
    [format!("cavity_re{re}.csv"), format!("cavity_re{re}.png")]
}

/// The two centreline profiles as CSV and as one plot over Ghia's points.
fn write_profiles(dir: &std::path::Path, run: &CavityRun, re: f64) -> Result<(), CliError> {
    let io = |path: &std::path::Path| {
        let path = path.to_path_buf();
        move |source| CliError::Io { path, source }
    };
    std::fs::create_dir_all(dir).map_err(io(dir))?;
    let (ul, vl) = centrelines(&run.cfg, &run.x);
    let mut csv = String::from("line,position,velocity\n");
    for (&at, &val) in ul.at.iter().zip(&ul.value) {
        csv.push_str(&format!("u(x=0.5),{at:.6},{val:.8}\n"));
    }
    for (&at, &val) in vl.at.iter().zip(&vl.value) {
        csv.push_str(&format!("v(y=0.5),{at:.6},{val:.8}\n"));
    }
    let [csv_name, png_name] = profile_names(re);
    let path = dir.join(csv_name);
    std::fs::write(&path, csv).map_err(io(&path))?;
    let mut series = vec![
        Series { name: "u on x = 1/2 (against y)".into(), points: ul.at.iter().copied().zip(ul.value.iter().copied()).collect(), color: 0, markers: false },
        Series { name: "v on y = 1/2 (against x)".into(), points: vl.at.iter().copied().zip(vl.value.iter().copied()).collect(), color: 1, markers: false },
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

/// Arguments of `diffsim experiment cylinder`.
#[derive(Debug, clap::Args)]
pub struct CylinderArgs {
    /// Which case.
    #[arg(long, value_enum)]
    case: CylinderCase,
    /// Cells per cylinder diameter (a multiple of 10; default 20 for 2d-1,
    /// 30 for 2d-2).
    #[arg(long)]
    resolution: Option<usize>,
    /// 2d-1: steady when max |du/dt| falls below this.
    #[arg(long, default_value_t = 1e-6)]
    tolerance: f64,
    /// 2d-1: give up after this many pseudo-time steps.
    #[arg(long, default_value_t = 1_000_000)]
    max_steps: usize,
    /// 2d-2: simulated time (from Poiseuille flow); the last 2 time units
    /// are measured.
    #[arg(long, default_value_t = 10.0)]
    t_end: f64,
    /// Print the result as one JSON object on the last line.
    #[arg(long)]
    json: bool,
    /// 2d-2: also write the force coefficients over time (CSV, PNG) here.
    #[arg(long)]
    out: Option<PathBuf>,
}

pub(super) fn cylinder(a: CylinderArgs) -> Result<(), CliError> {
    use diffsim_solvers::flow::cylinder::{reference, run_2d1, run_2d2};
    let per_d = a.resolution.unwrap_or(match a.case {
        CylinderCase::Steady => 20,
        CylinderCase::Periodic => 30,
    });
    if !(10..=200).contains(&per_d) || per_d % 10 != 0 {
        return Err(CliError::Argument {
            arg: "--resolution",
            reason: format!("cells per diameter must be a multiple of 10 between 10 and 200 (the channel is 4.1 diameters high), got {per_d}"),
        });
    }
    let start = Instant::now();
    let spinner = if a.json { indicatif::ProgressBar::hidden() } else { indicatif::ProgressBar::new_spinner() };
    let within = |v: f64, (lo, hi): (f64, f64)| if (lo..=hi).contains(&v) { "inside" } else { "outside" };
    match a.case {
        CylinderCase::Steady => {
            if !(a.tolerance.is_finite() && a.tolerance > 0.0) {
                return Err(CliError::Argument { arg: "--tolerance", reason: format!("must be a positive number, got {}", a.tolerance) });
            }
            let r = run_2d1(per_d, a.tolerance, a.max_steps, |step, t, rate| {
                if step % 200 == 0 {
                    spinner.set_message(format!("2D-1, {per_d} cells per diameter: step {step}, t = {t:.2}, max |du/dt| = {rate:.2e}"));
                    spinner.tick();
                }
            })?;
            spinner.finish_and_clear();
            let time_s = start.elapsed().as_secs_f64();
            if a.json {
                let obj = serde_json::json!({"case": "2d-1", "resolution": per_d, "cd": r.cd, "cl": r.cl, "dp": r.dp, "cells": r.cells, "steps": r.steps, "time_s": time_s});
                println!("{obj}");
                return Ok(());
            }
            println!("Schäfer–Turek 2D-1 (Re 20), {per_d} cells per diameter, {} cells: steady after {} steps, {time_s:.1} s", r.cells, r.steps);
            println!("| quantity | diffsim | published | |\n|---|---|---|---|");
            println!(
                "| c_D | {:.4} | 5.57–5.59 (5.5795) | {} ({:+.2} % from 5.5795) |",
                r.cd,
                within(r.cd, reference::CD_2D1),
                100.0 * (r.cd / reference::CD_2D1_TIGHT - 1.0)
            );
            println!("| c_L | {:.4} | 0.0104–0.0110 | {} |", r.cl, within(r.cl, reference::CL_2D1));
            println!("| Δp | {:.4} | 0.1172–0.1176 | {} |", r.dp, within(r.dp, reference::DP_2D1));
        }
        CylinderCase::Periodic => {
            if !(a.t_end.is_finite() && a.t_end > 2.5) {
                return Err(CliError::Argument { arg: "--t-end", reason: format!("must exceed 2.5 (the last 2 time units are measured), got {}", a.t_end) });
            }
            let r = run_2d2(per_d, a.t_end, 2.0, |t, cl| {
                spinner.set_message(format!("2D-2, {per_d} cells per diameter: t = {t:.2} of {}, c_L = {cl:+.3}", a.t_end));
                spinner.tick();
            })?;
            spinner.finish_and_clear();
            let time_s = start.elapsed().as_secs_f64();
            if let Some(dir) = &a.out {
                write_force_series(dir, &r.series, per_d)?;
            }
            if a.json {
                let obj = serde_json::json!({"case": "2d-2", "resolution": per_d, "cd_max": r.cd_max, "cl_max": r.cl_max, "st": r.st, "cells": r.cells, "steps": r.steps, "time_s": time_s});
                println!("{obj}");
                return Ok(());
            }
            println!("Schäfer–Turek 2D-2 (Re 100), {per_d} cells per diameter, {} cells: {} steps to t = {}, {time_s:.1} s", r.cells, r.steps, a.t_end);
            println!("| quantity | diffsim | published | |\n|---|---|---|---|");
            println!("| c_D,max | {:.4} | 3.22–3.24 | {} |", r.cd_max, within(r.cd_max, reference::CD_MAX_2D2));
            println!("| c_L,max | {:.4} | 0.99–1.01 | {} |", r.cl_max, within(r.cl_max, reference::CL_MAX_2D2));
            println!("| St | {:.4} | 0.295–0.305 | {} |", r.st, within(r.st, reference::ST_2D2));
        }
    }
    Ok(())
}

/// c_D and c_L over time as CSV and a plot.
fn write_force_series(dir: &std::path::Path, series: &[[f64; 3]], per_d: usize) -> Result<(), CliError> {
    std::fs::create_dir_all(dir).map_err(|source| CliError::Io { path: dir.to_path_buf(), source })?;
    let mut csv = String::from("t,cd,cl\n");
    for s in series {
        csv.push_str(&format!("{:.6},{:.8},{:.8}\n", s[0], s[1], s[2]));
    }
    let path = dir.join("cylinder_2d2.csv");
    std::fs::write(&path, csv).map_err(|source| CliError::Io { path: path.clone(), source })?;
    let pick = |k: usize| series.iter().map(|s| (s[0], s[k])).collect::<Vec<_>>();
    let title = format!("Schäfer–Turek 2D-2, {per_d} cells per diameter");
    plot_or_warn(
        &dir.join("cylinder_2d2.png"),
        &Axes { title: &title, x: "t", y: "coefficient", log_x: false, log_y: false },
        &[Series { name: "c_D".into(), points: pick(1), color: 0, markers: false }, Series { name: "c_L".into(), points: pick(2), color: 1, markers: false }],
    );
    Ok(())
}
