//! `diffsim demo plume`: a rising smoke plume deflected by an obstacle,
//! rendered to PNG, so that a person can see the fluid solver behave.

use std::path::PathBuf;

use clap::Args;
use diffsim_solvers::smoke::MacGrid;

use super::CliError;
use diffsim::fluids::Inflow;
use diffsim::op::{Forward, OperatorExt};
use diffsim::problems::smoke::SmokeStep;

#[derive(Debug, Args)]
pub(super) struct PlumeArgs {
    /// Cells per side (≥ 16).
    #[arg(long, default_value_t = 64)]
    n: usize,
    /// Steps.
    #[arg(long, default_value_t = 150)]
    steps: usize,
    /// Output directory for plume.png.
    #[arg(long, default_value = "out")]
    out: PathBuf,
    #[command(flatten)]
    overwrite: super::Overwrite,
}

pub(super) fn plume(a: PlumeArgs) -> Result<(), CliError> {
    if a.n < 16 {
        return Err(CliError::Argument { arg: "--n", reason: format!("need at least 16 cells per side, got {}", a.n) });
    }
    let n = a.n;
    let cfg = MacGrid::p2(n);
    // A plate across the middle, off-centre so that the plume is deflected.
    let solid: Vec<bool> = (0..n * n)
        .map(|c| {
            let (i, j) = (c % n, c / n);
            (n * 6 / 16..n * 13 / 16).contains(&i) && (n / 2..n / 2 + n / 24 + 1).contains(&j)
        })
        .collect();
    let step = SmokeStep::new(cfg, 1e-6, 5000, diffsim_solvers::smoke::Preconditioner::Mic0).with_obstacles(&solid);
    let source = Inflow { cfg, region: [[n * 7 / 16, n * 9 / 16], [n / 16, n / 16 + 3]] };
    let mut x = vec![0.0; cfg.n_state()];
    let mut y = vec![0.0; cfg.n_state()];
    for t in 0..a.steps {
        x = source.eval(&x, &[1.0, 0.0, 0.5]);
        step.forward(&x, &[], &mut y);
        if let Some(e) = step.take_error() {
            return Err(CliError::Rollout(diffsim::rollout::RolloutError::Operator { pass: diffsim::rollout::Pass::Forward, error: e }));
        }
        std::mem::swap(&mut x, &mut y);
        if t + 1 == a.steps {
            break;
        }
    }
    let _out = super::claim_out(&a.out, a.overwrite, &[])?;
    let path = a.out.join("plume.png");
    write_png(&path, (n, n), &x[..cfg.n_s()], &solid).map_err(|e| CliError::Io { path: path.clone(), source: e })?;
    let mass: f64 = x[..cfg.n_s()].iter().sum();
    println!("plume: {n}×{n} cells, {} steps, smoke total {mass:.1}, CG iterations {} → {}", a.steps, step.project.log.cg_forward.get(), path.display());
    Ok(())
}

/// Smoke as grey levels (white = 1), solid cells in dark red, y up, each
/// cell 4×4 pixels.
pub(super) fn write_png(path: &std::path::Path, (nx, ny): (usize, usize), s: &[f64], solid: &[bool]) -> std::io::Result<()> {
    const SCALE: usize = 4;
    let (width, height) = (nx * SCALE, ny * SCALE);
    let mut rgb = vec![0u8; width * height * 3];
    for py in 0..height {
        for px in 0..width {
            let (i, j) = (px / SCALE, ny - 1 - py / SCALE);
            let c = j * nx + i;
            let pixel = if solid[c] {
                [140, 30, 30]
            } else {
                let g = (s[c].clamp(0.0, 1.0) * 255.0).round() as u8;
                [g, g, g]
            };
            rgb[(py * width + px) * 3..(py * width + px) * 3 + 3].copy_from_slice(&pixel);
        }
    }
    let file = std::io::BufWriter::new(diffsim::files::create(path)?);
    let mut enc = png::Encoder::new(file, width as u32, height as u32);
    enc.set_color(png::ColorType::Rgb);
    enc.set_depth(png::BitDepth::Eight);
    let mut w = enc.write_header().map_err(std::io::Error::other)?;
    w.write_image_data(&rgb).map_err(std::io::Error::other)?;
    Ok(())
}
