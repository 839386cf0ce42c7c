//! `diffsim experiment cavity`: the viscous solver
//! ([`diffsim_solvers::flow`]) on the lid-driven cavity, marched to its
//! steady state and compared with Ghia, Ghia & Shin (1982).

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
