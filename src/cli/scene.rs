//! `diffsim run SCENE` and `diffsim grad SCENE`: simulate a scene file, or
//! take the gradient of its loss, writing `.npy` arrays and PNG images.

use std::path::{Path, PathBuf};

use npyz::WriterBuilder;

use super::CliError;
use crate::rollout::{Checkpointing, Rollout};
use crate::scene::Scene;

/// Arguments of `diffsim run`.
#[derive(Debug, clap::Args)]
pub struct RunArgs {
    /// The scene file (TOML; keys in docs/scenes.md).
    scene: PathBuf,
    /// Output directory.
    #[arg(long, default_value = "out")]
    out: PathBuf,
    /// Also write the smoke as PNG every this many steps.
    #[arg(long)]
    every: Option<usize>,
    /// Print the time and share of each declared effect.
    #[arg(long)]
    profile: bool,
    /// No progress output.
    #[arg(long)]
    quiet: bool,
}

/// Arguments of `diffsim grad`.
#[derive(Debug, clap::Args)]
pub struct GradArgs {
    /// The scene file; needs a [loss].
    scene: PathBuf,
    /// Output directory.
    #[arg(long, default_value = "out")]
    out: PathBuf,
    /// Also run the gradient checks on the whole rollout and print them.
    #[arg(long)]
    check: bool,
}

fn create_dir(out: &Path) -> Result<(), CliError> {
    std::fs::create_dir_all(out).map_err(|source| CliError::Io { path: out.to_path_buf(), source })
}

/// Writes `values` as a float64 `.npy` array of `shape` (row-major).
fn write_npy(path: &Path, shape: &[u64], values: &[f64]) -> Result<(), CliError> {
    let io = |source| CliError::Io { path: path.to_path_buf(), source };
    let file = std::io::BufWriter::new(std::fs::File::create(path).map_err(io)?);
    let mut w = npyz::WriteOptions::new().default_dtype().shape(shape).writer(file).begin_nd().map_err(io)?;
    w.extend(values.iter().copied()).map_err(io)?;
    w.finish().map_err(io)
}

/// The fields of a packed state as `.npy` files: smoke `[N, N]`, u `[N, N+1]`, v `[N+1, N]` (row j = y).
fn write_state(scene: &Scene, out: &Path, prefix: &str, x: &[f64]) -> Result<(), CliError> {
    let n = scene.cfg.n as u64;
    let (s, u, v) = scene.cfg.split(x);
    write_npy(&out.join(format!("{prefix}smoke.npy")), &[n, n], s)?;
    write_npy(&out.join(format!("{prefix}velocity_u.npy")), &[n, n + 1], u)?;
    write_npy(&out.join(format!("{prefix}velocity_v.npy")), &[n + 1, n], v)
}

fn png(scene: &Scene, path: &Path, x: &[f64]) -> Result<(), CliError> {
    let n = scene.cfg.n;
    let none = vec![false; n * n];
    super::demo::write_png(path, n, &x[scene.smoke_range()], scene.solid.as_deref().unwrap_or(&none))
        .map_err(|source| CliError::Io { path: path.to_path_buf(), source })
}

pub(super) fn run(a: RunArgs) -> Result<(), CliError> {
    let scene = Scene::load(&a.scene)?;
    create_dir(&a.out)?;
    let mut frames = Vec::new();
    let start = std::time::Instant::now();
    let x = if a.profile {
        profile(&scene)?
    } else {
        scene.run(|k, x| {
            if a.every.is_some_and(|e| e > 0 && k % e == 0) {
                frames.push((k, x.to_vec()));
            }
            if !a.quiet && std::io::IsTerminal::is_terminal(&std::io::stderr()) {
                eprint!("\rstep {k}/{}", scene.steps);
            }
        })?
    };
    let elapsed = start.elapsed().as_secs_f64();
    for (k, f) in &frames {
        png(&scene, &a.out.join(format!("smoke_{k:05}.png")), f)?;
    }
    write_state(&scene, &a.out, "", &x)?;
    png(&scene, &a.out.join("smoke.png"), &x)?;
    if !a.quiet {
        eprintln!(
            "\r{}: {n}×{n} cells, {} steps of {} in {elapsed:.2} s; effects: {}; wrote smoke.npy, velocity_u.npy, velocity_v.npy, smoke.png to {}",
            a.scene.display(),
            scene.steps,
            scene.dt,
            scene.effects.join(", "),
            a.out.display(),
            n = scene.cfg.n
        );
    }
    Ok(())
}

/// Runs the scene timing each effect (and only the declared ones).
fn profile(scene: &Scene) -> Result<Vec<f64>, CliError> {
    let mut times = vec![0.0f64; scene.effects.len()];
    let total = std::time::Instant::now();
    // The clock restarts after each effect and after the per-step checks.
    let t = std::cell::Cell::new(std::time::Instant::now());
    let x = scene.run_with(
        |_, _| t.set(std::time::Instant::now()),
        |e| {
            times[e] += t.get().elapsed().as_secs_f64();
            t.set(std::time::Instant::now());
        },
    )?;
    let total = total.elapsed().as_secs_f64();
    let sum: f64 = times.iter().sum();
    println!("{:<4} {:<12} {:>10} {:>7}", "#", "effect", "time ms", "share");
    for (k, (name, t)) in scene.effects.iter().zip(&times).enumerate() {
        println!("{k:<4} {name:<12} {:>10.3} {:>6.1}%", t * 1e3, 100.0 * t / sum);
    }
    println!("sum of effects {:.3} ms, whole run {:.3} ms", sum * 1e3, total * 1e3);
    Ok(x)
}

pub(super) fn grad(a: GradArgs) -> Result<(), CliError> {
    let scene = Scene::load(&a.scene)?;
    let Some((target, wrt)) = &scene.loss else {
        return Err(crate::scene::SceneError::key("loss", "`diffsim grad` needs a [loss] table").into());
    };
    create_dir(&a.out)?;
    let ns = scene.cfg.n_s();
    let loss = |x: &[f64], g: &mut [f64]| diffsim_solvers::smoke::p2_loss(&scene.cfg, x, target, g);
    let rollout = Rollout::new(&scene.step, &scene.params, scene.steps)?;
    let g = rollout.value_and_grad(&scene.x0, &loss, Checkpointing::periodic_sqrt(scene.steps))?;
    println!("loss {:.10e}", g.loss);
    let n = scene.cfg.n as u64;
    for w in wrt {
        match w.as_str() {
            "smoke.init" => {
                write_npy(&a.out.join("grad_smoke_init.npy"), &[n, n], &g.dx0[..ns])?;
                println!("d loss / d smoke.init: ‖·‖ = {:.6e} → grad_smoke_init.npy", norm(&g.dx0[..ns]));
            }
            "velocity.init" => {
                write_state(&scene, &a.out, "grad_", &g.dx0)?;
                println!("d loss / d velocity.init: ‖·‖ = {:.6e} → grad_velocity_u.npy, grad_velocity_v.npy", norm(&g.dx0[ns..]));
            }
            name => {
                let (_, index, factor) = scene.named.iter().find(|(s, _, _)| s == name).expect("checked when the scene was built");
                let d = g.dp[*index] * factor;
                println!("d loss / d {name} = {d:.10e}");
                write_npy(&a.out.join(format!("grad_{}.npy", name.replace(['.', '[', ']'], "_"))), &[1], &[d])?;
            }
        }
    }
    if a.check {
        use crate::check::{CheckOptions, check_all};
        use crate::rollout::RolloutOperator;
        // The rollout x₀ ↦ x_T under the chosen checkpointing.
        let op = RolloutOperator { rollout, mode: Checkpointing::periodic_sqrt(scene.steps) };
        let report = check_all(&op, &scene.x0, &[], &CheckOptions::default());
        println!("{report}");
        if !report.passed() {
            return Err(CliError::ChecksFailed);
        }
    }
    Ok(())
}

fn norm(v: &[f64]) -> f64 {
    v.iter().map(|a| a * a).sum::<f64>().sqrt()
}
