//! `diffsim experiment sip-smoke`: physical gradients for a fluid (SIP
//! with the reverse-time inverse of P2's solver against Adam).

use std::path::PathBuf;

use super::CliError;
use super::train::{io, write_error_files};
use crate::plot::{Axes, Series};
use diffsim_studies::smoke::{SHOWN, SmokeComparison, SmokeMethod, SmokeParams, compare, inverse_alone, inverse_misses};

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
    let fail = |e: diffsim::train::pg::PgError| CliError::Argument { arg: "sip-smoke", reason: e.to_string() };
    let quiet = a.json;
    let mut shown = (None, -1);
    let result = compare(&cfg, &[SmokeMethod::Sip, SmokeMethod::Adam], |m, t| {
        // Once per method and whole second.
        if !quiet && shown != (Some(m), t as i64) {
            shown = (Some(m), t as i64);
            eprint!("\r{}: {t:.0} of {:.0} s   ", m.name(), cfg.seconds);
        }
    })
    .map_err(|e| CliError::Argument { arg: "sip-smoke", reason: e.to_string() })?;
    if !quiet {
        eprintln!();
    }
    let inverse = inverse_alone(&cfg, a.inverse_iterations).map_err(fail)?;
    let (inv_x, inv_y) = *inverse.last().expect("inverse_alone reports iteration 0");
    let misses = inverse_misses(&cfg, &[1.0, 0.1, 0.01]).map_err(fail)?;

    let mut table =
        format!("| method | updates in {:.0} s | s per update | initial smoke MAE | re-simulated final smoke MAE |\n|---|---|---|---|---|\n", cfg.seconds);
    let mut csv = String::from("method,seconds,initial_mae,final_mae\n");
    let mut series = Vec::new();
    for (k, run) in result.runs.iter().enumerate() {
        let c = &run.curve;
        let resim = c.second_points.last().map_or(f64::NAN, |p| p.1);
        table.push_str(&format!("| {} | {} | {:.3} | {:.4} | {resim:.4} |\n", c.name, c.updates, c.seconds_per_update(), c.final_loss()));
        for (i, (t, e)) in c.points.iter().enumerate() {
            let r = c.second_points.get(i).map_or(f64::NAN, |p| p.1);
            csv.push_str(&format!("{},{t:.4},{e:.6e},{r:.6e}\n", c.name));
        }
        series.push(Series { name: format!("{} initial", c.name), points: c.points.clone(), color: k, markers: false });
        series.push(Series { name: format!("{} re-simulated final", c.name), points: c.second_points.clone(), color: k, markers: true });
    }
    table.push_str(&format!("| the inverse alone, {} iterations per sample | – | – | {inv_x:.4} | {inv_y:.4} |\n", a.inverse_iterations));
    table.push_str(&format!(
        "\nThe reverse-time inverse's promise, P(x + dx) ≈ P(x) + dy at held-out states (relative miss; dx = dy for comparison):\n\n| scale of dy | reverse time | with {} correction sweeps | dx = dy |\n|---|---|---|---|\n",
        cfg.refine
    ));
    for m in &misses {
        table.push_str(&format!("| {} | {:.3} | {:.3} | {:.3} |\n", m.scale, m.reverse_time, m.refined, m.unmoved));
    }
    let axes = Axes { title: "inverse smoke: held-out error vs training time", x: "seconds", y: "mean absolute error per cell", log_x: false, log_y: true };
    write_error_files(&a.out, &table, &csv, &axes, &series)?;
    let pictures = a.out.join("reconstructions.png");
    write_reconstructions(&pictures, cfg.n, &result).map_err(io(&pictures))?;
    if a.json {
        let (sip, adam) = (&result.runs[0].curve, &result.runs[1].curve);
        let last = |c: &diffsim_studies::oscillators::Curve| c.second_points.last().map_or(f64::NAN, |p| p.1);
        let obj = serde_json::json!({
            "sip": sip.final_loss(), "adam": adam.final_loss(), "time_s": cfg.seconds,
            "sip_resim": last(sip), "adam_resim": last(adam),
            "sip_updates": sip.updates, "adam_updates": adam.updates,
            "sip_s_per_update": sip.seconds_per_update(), "adam_s_per_update": adam.seconds_per_update(),
            "inverse": inv_x, "inverse_resim": inv_y, "inverse_iterations": a.inverse_iterations,
            "inverse_miss": misses.iter().map(|m| serde_json::json!({"scale": m.scale, "reverse_time": m.reverse_time, "refined": m.refined, "unmoved": m.unmoved})).collect::<Vec<_>>(),
            "n": cfg.n, "steps": cfg.steps, "refine": cfg.refine, "quick": a.quick,
        });
        println!("{obj}");
    } else {
        print!("{table}");
        println!("wrote table.md, error.csv, error.png, reconstructions.png to {}", a.out.display());
    }
    Ok(())
}

/// One row per shown held-out sample: the true initial smoke, the observed
/// final smoke, then each method's reconstruction; one-cell separators.
fn write_reconstructions(path: &std::path::Path, n: usize, r: &SmokeComparison) -> std::io::Result<()> {
    let rows = r.test.len().min(SHOWN);
    let cols = 2 + r.runs.len();
    let (w, h) = (cols * (n + 1) - 1, rows * (n + 1) - 1);
    let (mut field, mut solid) = (vec![0.0; w * h], vec![true; w * h]);
    for row in 0..rows {
        let s = &r.test[row];
        let mut panels: Vec<&[f64]> = vec![&s.truth, &s.observed];
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
