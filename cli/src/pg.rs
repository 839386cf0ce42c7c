//! `diffsim experiment sip-smoke`: physical gradients for a fluid (SIP
//! with the reverse-time inverse of P2's solver against Adam).

use std::path::PathBuf;

use super::CliError;
use super::train::{io, write_error_files};
use crate::plot::{Axes, Series};
use diffsim_studies::smoke::{SmokeParams, SmokeReport, run};

/// Arguments of `diffsim experiment sip-smoke`.
#[derive(Debug, clap::Args)]
pub struct SipSmokeArgs {
    /// A quick look: 16 × 16 cells, 10 s per method (else 32 × 32, 120 s;
    /// 16 steps in both).
    #[arg(long)]
    quick: bool,
    /// Training seconds per method (overrides the default of the mode).
    #[arg(long)]
    seconds: Option<f64>,
    /// SIP: defect-correction sweeps after each reverse-time inverse step
    /// (each one more forward and inverse simulation per sample).
    #[arg(long, default_value_t = 0)]
    refine: usize,
    /// Iterations of the inverse alone (per held-out sample, no network)
    /// reported beside the networks.
    #[arg(long, default_value_t = 10)]
    inverse_iterations: usize,
    /// Print the result as one JSON object on the last line.
    #[arg(long)]
    json: bool,
    /// Output directory: table.md, error.csv, error.png, reconstructions.png.
    #[arg(long, default_value = "out/sip-smoke")]
    out: PathBuf,
    #[command(flatten)]
    overwrite: super::Overwrite,
}

/// Runs the comparison and writes its table, curves and pictures.
pub(super) fn sip_smoke(a: SipSmokeArgs) -> Result<(), CliError> {
    let mut cfg = if a.quick { SmokeParams::quick() } else { SmokeParams::standard() };
    if let Some(s) = a.seconds {
        // A day per method at most: the study compares equal budgets, and
        // a longer one is an input error, not a study.
        if !(s > 0.0 && s <= 86_400.0) {
            return Err(CliError::Argument { arg: "--seconds", reason: format!("must be a positive number of seconds, at most 86400 (a day), got {s}") });
        }
        cfg.seconds = s;
    }
    cfg.refine = a.refine;
    // Held to the end: the folder is this run's while it writes.
    let _out = super::claim_out(&a.out, a.overwrite, &[])?;
    let quiet = a.json;
    let mut shown = (None, -1);
    let report = run(&cfg, a.inverse_iterations, |m, t| {
        // Once per method and whole second.
        if !quiet && shown != (Some(m), t as i64) {
            shown = (Some(m), t as i64);
            eprint!("\r{}: {t:.0} of {:.0} s   ", m.name(), cfg.seconds);
        }
    })
    .map_err(super::train::study_error("sip-smoke"))?;
    if !quiet {
        eprintln!();
    }
    let table = report.table();
    let mut series = Vec::new();
    for (k, run) in report.runs.iter().enumerate() {
        let c = &run.curve;
        series.push(Series { name: format!("{} initial", c.name), points: c.points.clone(), color: k, markers: false });
        series.push(Series { name: format!("{} re-simulated final", c.name), points: c.second_points.clone(), color: k, markers: true });
    }
    let axes = Axes { title: "inverse smoke: held-out error vs training time", x: "seconds", y: "mean absolute error per cell", log_x: false, log_y: true };
    write_error_files(&a.out, &table, &report.csv(), &axes, &series)?;
    let pictures = a.out.join("reconstructions.png");
    write_reconstructions(&pictures, &report).map_err(io(&pictures))?;
    if a.json {
        let mut obj = report.json();
        obj.insert("quick".into(), a.quick.into());
        println!("{}", serde_json::Value::Object(obj));
    } else {
        print!("{table}");
        println!("wrote table.md, error.csv, error.png, reconstructions.png to {}", a.out.display());
    }
    Ok(())
}

/// One row per shown held-out sample: the true initial smoke, the observed
/// final smoke, then each method's reconstruction; one-cell separators.
fn write_reconstructions(path: &std::path::Path, r: &SmokeReport) -> std::io::Result<()> {
    let n = r.n;
    let rows = r.truth.len();
    let cols = 2 + r.runs.len();
    let (w, h) = (cols * (n + 1) - 1, rows * (n + 1) - 1);
    let (mut field, mut solid) = (vec![0.0; w * h], vec![true; w * h]);
    for row in 0..rows {
        let mut panels: Vec<&[f64]> = vec![&r.truth[row], &r.observed[row]];
        panels.extend(r.runs.iter().map(|run| run.shown[row].as_slice()));
        for (col, panel) in panels.iter().enumerate() {
            // Row 0 at the top: rows are stacked downwards in y-up pictures.
            let (x0, y0) = (col * (n + 1), (rows - 1 - row) * (n + 1));
            for j in 0..n {
                for i in 0..n {
                    let c = (y0 + j) * w + x0 + i;
                    field[c] = panel[j * n + i];
                    solid[c] = false;
                }
            }
        }
    }
    super::demo::write_png(path, (w, h), &field, &solid)
}
