//! `diffsim run SCENE` and `diffsim grad SCENE`: simulate a scene file, or
//! take the gradient of its loss, writing `.npy` arrays and PNG images.

use std::path::{Path, PathBuf};

use npyz::WriterBuilder;

use super::CliError;
use diffsim::files::{OutDir, Outputs};
use diffsim::rollout::RolloutOperator;
use diffsim::scene::{AnyScene, Domain, Field, Scene, SteadyScene};

/// Arguments of `diffsim run`.
#[derive(Debug, clap::Args)]
pub struct RunArgs {
    /// The scene file (TOML; keys in docs/scenes.md).
    scene: PathBuf,
    /// Output directory.
    #[arg(long, default_value = "out")]
    out: PathBuf,
    #[command(flatten)]
    overwrite: super::Overwrite,
    /// Also write an image every this many steps.
    #[arg(long)]
    every: Option<usize>,
    /// Print the time and share of each declared effect.
    #[arg(long)]
    profile: bool,
    /// No progress bar and no summary.
    #[arg(long)]
    quiet: bool,
    /// 3D scenes: the slice written as PNG, `AXIS` (the middle plane) or
    /// `AXIS=INDEX` (`z=10`: the plane of cells k = 10); default z.
    #[arg(long, value_name = "AXIS[=INDEX]")]
    slice: Option<String>,
    /// 3D scenes: the axis of the maximum-intensity projection written as
    /// PNG; default z.
    #[arg(long, value_name = "AXIS")]
    mip: Option<String>,
}

impl RunArgs {
    /// The first of `--slice` and `--mip` given (pictures of a volume).
    fn view_option(&self) -> Option<&'static str> {
        if self.slice.is_some() {
            Some("--slice")
        } else if self.mip.is_some() {
            Some("--mip")
        } else {
            None
        }
    }
}

/// The pictures of a 3D scene: a slice (axis, cell index) and the axis of
/// a maximum-intensity projection.
#[derive(Clone, Copy, Debug)]
pub(super) struct Views {
    slice: (usize, Option<usize>),
    mip: usize,
}

impl Default for Views {
    /// `diffsim run`'s defaults: the middle z plane and the projection along z.
    fn default() -> Self {
        Views { slice: (2, None), mip: 2 }
    }
}

impl Views {
    /// `--slice` and `--mip` checked against the domain.
    fn parse(a: &RunArgs, domain: &Domain) -> Result<Self, CliError> {
        // Pictures of a volume: an option given for a line or a box would
        // silently do nothing.
        if !matches!(domain, Domain::Box3(_))
            && let Some(arg) = a.view_option()
        {
            return Err(CliError::Argument { arg, reason: format!("applies to 3D scenes only; this scene is {}D", domain.dims()) });
        }
        let slice = a.slice.as_deref().unwrap_or("z");
        let mip = a.mip.as_deref().unwrap_or("z");
        let axis = |arg: &'static str, name: &str| {
            diffsim::volume::axis_index(name).ok_or_else(|| CliError::Argument { arg, reason: format!("expected an axis x, y or z, got \"{name}\"") })
        };
        let (name, index) = match slice.split_once('=') {
            Some((name, index)) => {
                let index = index
                    .trim()
                    .parse::<usize>()
                    .map_err(|_| CliError::Argument { arg: "--slice", reason: format!("expected AXIS=INDEX with a cell index, got \"{slice}\"") })?;
                (name.trim(), Some(index))
            }
            None => (slice.trim(), None),
        };
        let views = Views { slice: (axis("--slice", name)?, index), mip: axis("--mip", mip.trim())? };
        if let (Domain::Box3(cfg), (ax, Some(k))) = (domain, views.slice)
            && k >= cfg.n[ax]
        {
            return Err(CliError::Argument { arg: "--slice", reason: format!("index {k} is past the {} cells along {name}", cfg.n[ax]) });
        }
        Ok(views)
    }
}

/// Arguments of `diffsim grad`.
#[derive(Debug, clap::Args)]
pub struct GradArgs {
    /// The scene file; needs a [loss].
    scene: PathBuf,
    /// Output directory.
    #[arg(long, default_value = "out")]
    out: PathBuf,
    #[command(flatten)]
    overwrite: super::Overwrite,
    /// Also run the gradient checks on the whole rollout and print them.
    #[arg(long)]
    check: bool,
    /// Print the time and share of each declared effect in the forward and
    /// backward passes.
    #[arg(long)]
    profile: bool,
    /// How the rollout's states are kept for the backward pass: `auto`
    /// (the fastest mode within --memory-budget), store, periodic[:K],
    /// binomial[:S].
    #[arg(long, default_value = "auto")]
    checkpoint: String,
}

/// Claims `out` for a command on the scene file `scene`: the scene and the
/// `.npy` files it reads are never written over, and a folder holding
/// another run's results is refused unless `--overwrite`
/// ([`diffsim::files::OutDir`]). A run is the scene's path and text (`run`
/// and `grad` of one scene share a folder; an edited scene is another
/// run), and `extra` (a sweep's `--set`).
pub(super) fn claim(out: &Path, scene: &Path, extra: &str, overwrite: super::Overwrite) -> Result<OutDir, CliError> {
    use std::hash::{Hash, Hasher};
    let canonical = std::fs::canonicalize(scene).unwrap_or_else(|_| scene.to_path_buf());
    let mut hash = std::hash::DefaultHasher::new();
    diffsim::files::read_bytes(scene, diffsim::scene::MAX_SCENE_BYTES, "scene file")?.hash(&mut hash);
    let mut inputs = diffsim::scene::input_files(scene);
    inputs.push(scene.to_path_buf());
    let refs: Vec<&Path> = inputs.iter().map(PathBuf::as_path).collect();
    Ok(OutDir::claim(out, &format!("{} (text {:016x}){extra}", canonical.display(), hash.finish()), &refs, overwrite.existing(false))?)
}

/// Writes `values` as a float64 `.npy` array of `shape` (row-major) to the
/// output `name`.
fn write_npy(out: &dyn Outputs, name: &str, shape: &[u64], values: &[f64]) -> Result<(), CliError> {
    let path = out.file(name)?;
    let io = |source| CliError::Io { path: path.clone(), source };
    let file = std::io::BufWriter::new(diffsim::files::create(&path).map_err(io)?);
    let mut w = npyz::WriteOptions::new().default_dtype().shape(shape).writer(file).begin_nd().map_err(io)?;
    w.extend(values.iter().copied()).map_err(io)?;
    w.finish().map_err(io)
}

/// The declared fields of a state as `.npy` files (`smoke.npy`; a 2D
/// velocity as `velocity_u.npy` `[N, N+1]` and `velocity_v.npy` `[N+1, N]`,
/// rows = y). Returns the file names.
pub(super) fn write_state(scene: &Scene, out: &dyn Outputs, x: &[f64]) -> Result<Vec<String>, CliError> {
    let mut names = Vec::new();
    for &field in &scene.fields {
        for a in scene.domain.arrays(field) {
            let name = format!("{}{}.npy", field.name(), a.suffix);
            write_npy(out, &name, &a.shape, &x[a.range])?;
            names.push(name);
        }
    }
    Ok(names)
}

/// An image of a state: the smoke of a box (the speed when it has no smoke),
/// a slice and a maximum-intensity projection of it in 3D, or a plot of
/// each field of a line. Returns the file names.
pub(super) fn write_images(scene: &Scene, out: &dyn Outputs, tag: &str, x: &[f64], views: Views) -> Result<Vec<String>, CliError> {
    let io = |path: PathBuf| move |source| CliError::Io { path, source };
    let mut names = Vec::new();
    match &scene.domain {
        Domain::Line(line) => {
            use crate::plot::{Axes, Series};
            for &field in &scene.fields {
                let name = format!("{}{tag}.png", field.name());
                let path = out.file(&name)?;
                let points = x[scene.domain.range(field)].iter().enumerate().map(|(i, v)| (i as f64 * line.dx, *v)).collect();
                let axes = Axes { title: field.name(), x: "x", y: field.name(), log_x: false, log_y: false };
                if super::plot_or_warn(&path, &axes, &[Series { name: field.name().to_string(), points, color: 0, markers: false }]) {
                    names.push(name);
                }
            }
        }
        Domain::Box(cfg) => {
            let (n, ny) = (cfg.n[0], cfg.n[1]);
            let none = vec![false; cfg.n_s()];
            let solid = scene.solid.as_deref().unwrap_or(&none);
            let (name, values) = if scene.fields.contains(&Field::Smoke) {
                (format!("smoke{tag}.png"), x[scene.domain.range(Field::Smoke)].to_vec())
            } else {
                (format!("speed{tag}.png"), relative_speed(cfg, cfg.split(x).1))
            };
            let path = out.file(&name)?;
            super::demo::write_png(&path, (n, ny), &values, solid).map_err(io(path.clone()))?;
            names.push(name);
        }
        Domain::Box3(cfg) => {
            use diffsim::volume::{any_projection, max_projection, slice, slice_marks};
            let dims = cfg.n;
            let none = vec![false; cfg.n_s()];
            let solid = scene.solid.as_deref().unwrap_or(&none);
            let (field, values) = if scene.fields.contains(&Field::Smoke) {
                ("smoke", x[scene.domain.range(Field::Smoke)].to_vec())
            } else {
                ("speed", relative_speed(cfg, cfg.split(x).1))
            };
            let names_axis = diffsim::volume::AXES;
            let (ax, index) = views.slice;
            let k = index.unwrap_or(dims[ax] / 2);
            let plane = slice(dims, &values, ax, k);
            let name = format!("{field}_slice_{}{k}{tag}.png", names_axis[ax]);
            let path = out.file(&name)?;
            super::demo::write_png(&path, (plane.width, plane.height), &plane.values, &slice_marks(dims, solid, ax, k)).map_err(io(path.clone()))?;
            names.push(name);
            // The projection: obstacles shown where no smoke lies along the ray.
            let mip = max_projection(dims, &values, views.mip);
            let marks: Vec<bool> = any_projection(dims, solid, views.mip).iter().zip(&mip.values).map(|(&m, &v)| m && v < 0.02).collect();
            let name = format!("{field}_mip_{}{tag}.png", names_axis[views.mip]);
            let path = out.file(&name)?;
            super::demo::write_png(&path, (mip.width, mip.height), &mip.values, &marks).map_err(io(path.clone()))?;
            names.push(name);
        }
    }
    Ok(names)
}

/// The speed at the cell centres of the MAC velocity `vel` of the box
/// `cfg` (2D or 3D), scaled to its maximum.
fn relative_speed<const D: usize>(cfg: &diffsim_solvers::smoke::MacGrid<D>, vel: [&[f64]; D]) -> Vec<f64> {
    use diffsim_solvers::mac::At;
    let mac = cfg.mac();
    let cells = mac.lattice(At::Centre);
    let mut speed = vec![0.0; cells.len];
    for q in cells.points() {
        speed[cells.index(q)] = mac.velocity(At::Centre, vel, q).iter().map(|v| v * v).sum::<f64>().sqrt();
    }
    scaled_to_max(speed)
}

/// `values` divided by their maximum.
fn scaled_to_max(values: Vec<f64>) -> Vec<f64> {
    let max = values.iter().fold(0.0f64, |m, &s| m.max(s)).max(1e-300);
    values.iter().map(|s| s / max).collect()
}

fn progress(steps: usize, quiet: bool) -> indicatif::ProgressBar {
    if quiet {
        return indicatif::ProgressBar::hidden();
    }
    // Drawn only when stderr is a terminal.
    let bar = indicatif::ProgressBar::new(steps as u64);
    if let Ok(style) = indicatif::ProgressStyle::with_template("{bar:40} {pos}/{len} steps {elapsed} (eta {eta})") {
        bar.set_style(style);
    }
    bar
}

pub(super) fn run(a: RunArgs) -> Result<(), CliError> {
    let scene = match AnyScene::load(&a.scene)? {
        AnyScene::Stepped(scene) => *scene,
        AnyScene::Steady(scene) => return run_steady(&a, &scene),
    };
    if a.every == Some(0) {
        return Err(CliError::Argument { arg: "--every", reason: "must be at least 1 (a frame every this many steps)".into() });
    }
    let views = Views::parse(&a, &scene.domain)?;
    let out = claim(&a.out, &a.scene, "", a.overwrite)?;
    let start = std::time::Instant::now();
    let x = if a.profile {
        let (x, table) = profile_run(&scene)?;
        println!("{table}");
        x
    } else {
        let bar = progress(scene.steps, a.quiet);
        // Frames go to disk as they come (memory stays one state); the
        // first failed write stops the writing and is reported.
        let mut failed = None;
        let mut estimated = false;
        let x = scene.run(|k, x| {
            if failed.is_none()
                && a.every.is_some_and(|e| k % e == 0)
                && let Err(e) = write_images(&scene, &out, &format!("_{k:05}"), x, views)
            {
                failed = Some(e);
            }
            bar.inc(1);
            // A long run says so up front (the bar is drawn on a terminal
            // only): its estimate from the steps done after about a second.
            if !a.quiet && !estimated && k < scene.steps {
                let spent = start.elapsed().as_secs_f64();
                if spent > 1.0 {
                    estimated = true;
                    let total = spent / k as f64 * scene.steps as f64;
                    if total > 60.0 {
                        bar.suspend(|| {
                            eprintln!("{} steps: about {} in all at {:.3} s a step (step {k} done)", scene.steps, duration(total), spent / k as f64)
                        });
                    }
                }
            }
        });
        bar.finish_and_clear();
        if let Some(e) = failed {
            return Err(e);
        }
        x?
    };
    let elapsed = start.elapsed().as_secs_f64();
    let mut written = write_state(&scene, &out, &x)?;
    written.extend(write_images(&scene, &out, "", &x, views)?);
    out.finish()?;
    if !a.quiet {
        eprintln!(
            "{}: {}, {} steps of {} in {elapsed:.2} s; effects: {}; wrote {} to {}",
            a.scene.display(),
            describe(&scene.domain),
            scene.steps,
            scene.dt,
            scene.effects.join(", "),
            written.join(", "),
            a.out.display(),
        );
    }
    Ok(())
}

/// Refuses a loss or a gradient that overflowed (`inputs`: each input's
/// name and values): nothing is reported as a result.
fn finite_gradient<'a, V: Iterator<Item = &'a f64>>(loss: f64, inputs: impl Iterator<Item = (&'a str, V)>) -> Result<(), CliError> {
    super::finite_figures("grad", &[("the loss", loss)])?;
    for (name, mut values) in inputs {
        if let Some(v) = values.find(|v| !v.is_finite()) {
            return Err(CliError::NotReported { what: "grad".into(), reason: format!("the gradient with respect to {name} holds {v}") });
        }
    }
    Ok(())
}

/// Seconds as `42 s`, `17 min` or `3.2 h`.
pub(super) fn duration(s: f64) -> String {
    if s < 120.0 {
        format!("{s:.0} s")
    } else if s < 7200.0 {
        format!("{:.0} min", s / 60.0)
    } else {
        format!("{:.1} h", s / 3600.0)
    }
}

fn describe(d: &Domain) -> String {
    match d {
        Domain::Line(l) => format!("{} cells on a line of length {}", l.n, l.n as f64 * l.dx),
        Domain::Box(cfg) => format!("{}×{} cells", cfg.n[0], cfg.n[1]),
        Domain::Box3(cfg) => format!("{}×{}×{} cells", cfg.n[0], cfg.n[1], cfg.n[2]),
    }
}

/// A table of time per effect: one row per effect, its share, and the sum
/// of the rows against the whole measured time.
fn table(names: &[String], times: &[f64], total: f64, title: &str) -> String {
    use std::fmt::Write;
    let sum: f64 = times.iter().sum();
    let mut s = format!("{title}\n{:<4} {:<12} {:>10} {:>7}\n", "#", "effect", "time ms", "share");
    for (k, (name, t)) in names.iter().zip(times).enumerate() {
        let _ = writeln!(s, "{k:<4} {name:<12} {:>10.3} {:>6.1}%", t * 1e3, 100.0 * t / sum.max(1e-300));
    }
    let _ = write!(s, "sum of effects {:.3} ms, whole pass {:.3} ms", sum * 1e3, total * 1e3);
    s
}

/// Runs the scene timing each effect (and only the declared ones).
fn profile_run(scene: &Scene) -> Result<(Vec<f64>, String), CliError> {
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
    Ok((x, table(&scene.effects, &times, total, "forward (diffsim run)")))
}

/// The backward pass timed per effect: each effect's VJP at the states of a
/// stored forward run, in reverse order.
fn profile_backward(scene: &Scene) -> Result<String, CliError> {
    let n = scene.x0.len();
    let mut states = vec![scene.x0.clone()];
    scene.run(|_, x| states.push(x.to_vec()))?;
    let ops = scene.step.ops();
    let mut times = vec![0.0f64; ops.len()];
    let total = std::time::Instant::now();
    let mut lam = vec![1.0; n];
    let (mut inner, mut next) = (vec![0.0; n], vec![0.0; n]);
    for x in states[..scene.steps].iter().rev() {
        // The intermediate states of this step, then the effects' VJPs backwards.
        let mut mids = vec![x.clone()];
        for (k, op) in ops.iter().enumerate() {
            let r = scene.step.param_range(k);
            op.forward(mids.last().expect("starts with x"), &scene.params[r], &mut inner);
            mids.push(inner.clone());
        }
        let mut dp = vec![0.0; scene.params.len()];
        for (k, op) in ops.iter().enumerate().rev() {
            let r = scene.step.param_range(k);
            let t = std::time::Instant::now();
            next.fill(0.0);
            op.vjp(&mids[k], &scene.params[r.clone()], &mut lam, &mut next, &mut dp[r]);
            times[k] += t.elapsed().as_secs_f64();
            std::mem::swap(&mut lam, &mut next);
        }
    }
    let total = total.elapsed().as_secs_f64();
    Ok(table(&scene.effects, &times, total, "backward (VJPs of each effect; the whole pass includes recomputing the step's intermediate states)"))
}

/// The checkpointing of a scene's gradient (see [`super::checkpointing`]):
/// the states are the scene's; besides them the grid's work arrays and, for
/// a control per step, its values and gradient at every step.
fn gradient_plan(scene: &Scene, arg: &str) -> Result<(diffsim::rollout::plan::Plan, bool), CliError> {
    use diffsim::op::Forward;
    let n = scene.x0.len() as u64;
    let per_step = if scene.per_step() { diffsim::memory::f64s(&[scene.params.len() as u64, scene.steps as u64, 2]) } else { Some(0) };
    let other = diffsim::memory::f64s(&[n, 8]).zip(per_step).and_then(|(a, b)| a.checked_add(b));
    let detail = format!("{} values per state over {} steps", n, scene.steps);
    diffsim::memory::check("the scene's gradient", detail, other, None)?;
    // One step from x₀ times a step for the cost model.
    let step_s = {
        let mut y = vec![0.0; scene.x0.len()];
        let t = std::time::Instant::now();
        scene.step.forward(&scene.x0, &scene.params, &mut y);
        t.elapsed().as_secs_f64()
    };
    let job = diffsim::rollout::plan::Job { steps: scene.steps, state_bytes: 8 * n, copies: 1, forward_s: step_s };
    super::checkpointing(arg, &job, other.unwrap_or(0), "the scene's gradient")
}

pub(super) fn grad(a: GradArgs) -> Result<(), CliError> {
    let scene = match AnyScene::load(&a.scene)? {
        AnyScene::Stepped(scene) => *scene,
        AnyScene::Steady(scene) => return grad_steady(&a, &scene),
    };
    let Some(loss) = &scene.loss else {
        return Err(diffsim::scene::SceneError::key("loss", "`diffsim grad` needs a [loss] table").into());
    };
    let (plan, chosen) = gradient_plan(&scene, &a.checkpoint)?;
    let mode = plan.mode;
    let out = claim(&a.out, &a.scene, "", a.overwrite)?;
    let g = scene.gradient(loss, mode)?;
    finite_gradient(g.loss, g.inputs.iter().map(|i| (i.name.as_str(), i.arrays.iter().flat_map(|(_, _, v)| v))))?;
    let how = if chosen { "chosen within" } else { "given; budget" };
    eprintln!("memory plan ({how} {}): {plan}", diffsim::memory::human(diffsim::memory::budget()));
    println!("loss {:.10e}", g.loss);
    for input in &g.inputs {
        let norm = input.arrays.iter().flat_map(|(_, _, v)| v).map(|a| a * a).sum::<f64>().sqrt();
        let files: Vec<String> = input.arrays.iter().map(|(stem, _, _)| format!("{stem}.npy")).collect();
        for (stem, shape, values) in &input.arrays {
            write_npy(&out, &format!("{stem}.npy"), shape, values)?;
        }
        match input.arrays.as_slice() {
            [(_, shape, v)] if shape == &[1] => println!("d loss / d {} = {:.10e} → {}", input.name, v[0], files.join(", ")),
            _ => println!("d loss / d {}: ‖·‖ = {norm:.6e} → {}", input.name, files.join(", ")),
        }
    }
    out.finish()?;
    if a.profile {
        println!("{}", profile_run(&scene)?.1);
        println!("{}", profile_backward(&scene)?);
    }
    if a.check {
        use diffsim::check::{CheckParams, check_all};
        // The rollout x₀ ↦ x_T under the chosen checkpointing.
        let p = scene.rollout_params();
        let op = RolloutOperator { rollout: scene.rollout(&p)?, mode };
        let report = check_all(&op, &scene.x0, &[], &CheckParams::default());
        println!("{report}");
        if report.failed() {
            return Err(CliError::ChecksFailed);
        }
        if !report.passed() {
            // A fluid at rest traces every point onto a lattice plane: the
            // rollout kinks there, and no step can tell a gradient apart.
            println!(
                "note: the rollout has a kink at this initial state (a fluid at rest is one: every traced point lies on a lattice plane); the checks that say so are inconclusive, not failed: start from a moving state to check every direction"
            );
        }
    }
    Ok(())
}

/// Writes a solved steady scene: `velocity_u.npy`, `velocity_v.npy`,
/// `pressure.npy` (rows = y) and `speed.png` (bodies' cells dark red).
/// Returns the file names.
pub(super) fn write_steady(scene: &SteadyScene, run: &diffsim::scene::SteadyRun, out: &dyn Outputs) -> Result<Vec<String>, CliError> {
    let (nx, ny) = (scene.flow.nx as u64, scene.flow.ny as u64);
    let (u, v) = run.state.x.split_at(scene.flow.n_u());
    write_npy(out, "velocity_u.npy", &[ny, nx + 1], u)?;
    write_npy(out, "velocity_v.npy", &[ny + 1, nx], v)?;
    write_npy(out, "pressure.npy", &[ny, nx], &run.state.pressure)?;
    let mut names: Vec<String> = vec!["velocity_u.npy".into(), "velocity_v.npy".into(), "pressure.npy".into()];
    let (nx, ny, h) = (scene.flow.nx, scene.flow.ny, scene.flow.h);
    let solid: Vec<bool> = (0..nx * ny).map(|c| scene.shapes.iter().any(|b| b.level(((c % nx) as f64 + 0.5) * h, ((c / nx) as f64 + 0.5) * h) < 0.0)).collect();
    let path = out.file("speed.png")?;
    let grid = diffsim_solvers::smoke::MacGrid::new([nx, ny]);
    super::demo::write_png(&path, (nx, ny), &relative_speed(&grid, [u, v]), &solid).map_err(|source| CliError::Io { path: path.clone(), source })?;
    names.push("speed.png".into());
    Ok(names)
}

/// The force on each body (and its coefficient when the loss gives a
/// reference), one line each.
fn describe_forces(scene: &SteadyScene, run: &diffsim::scene::SteadyRun) -> String {
    let scale = scene.loss.as_ref().map(|l| l.scale).filter(|&s| s != 1.0);
    let lines: Vec<String> = run
        .forces
        .iter()
        .enumerate()
        .map(|(k, f)| {
            let coefficients = scale.map(|s| format!(", c_D {:.6}, c_L {:.6}", s * f[0], s * f[1])).unwrap_or_default();
            format!("obstacles[{k}]: force ({:.6e}, {:.6e}){coefficients}", f[0], f[1])
        })
        .collect();
    lines.join("\n")
}

fn run_steady(a: &RunArgs, scene: &SteadyScene) -> Result<(), CliError> {
    // A steady scene has no steps and no volume: these would do nothing.
    if let Some(arg) = a.every.map(|_| "--every").or(a.view_option()) {
        return Err(CliError::Argument { arg, reason: "does not apply to a steady scene (no steps, no volume)".into() });
    }
    let out = claim(&a.out, &a.scene, "", a.overwrite)?;
    let start = std::time::Instant::now();
    let run = scene.solve()?;
    let elapsed = start.elapsed().as_secs_f64();
    let written = write_steady(scene, &run, &out)?;
    out.finish()?;
    if !a.quiet {
        println!("{}", describe_forces(scene, &run));
        eprintln!(
            "{}: steady flow on {}×{} cells of {}, {} Newton steps (residual {:.1e}) in {elapsed:.2} s; wrote {} to {}",
            a.scene.display(),
            scene.flow.nx,
            scene.flow.ny,
            scene.flow.h,
            run.state.steps,
            run.state.residual,
            written.join(", "),
            a.out.display(),
        );
    }
    Ok(())
}

fn grad_steady(a: &GradArgs, scene: &SteadyScene) -> Result<(), CliError> {
    let Some(loss) = &scene.loss else {
        return Err(diffsim::scene::SceneError::key("loss", "`diffsim grad` needs a [loss] table").into());
    };
    if a.profile {
        eprintln!("--profile times each effect of a scene stepped in time; a steady scene has none (the solve and adjoint times follow)");
    }
    let out = claim(&a.out, &a.scene, "", a.overwrite)?;
    let start = std::time::Instant::now();
    let (run, g) = scene.gradient(loss)?;
    finite_gradient(g.loss, g.inputs.iter().map(|(name, _, values)| (name.as_str(), values.iter())))?;
    let elapsed = start.elapsed().as_secs_f64();
    println!("loss {:.10e} ({} of obstacles[{}])", g.loss, loss.kind(), loss.obstacle);
    for (name, params, values) in &g.inputs {
        let stem = diffsim::scene::grad_stem(name);
        write_npy(&out, &format!("{stem}.npy"), &[values.len() as u64], values)?;
        let listed: Vec<String> = params.iter().zip(values).map(|(p, v)| format!("{p} {v:.6e}")).collect();
        println!("d loss / d {name} → {stem}.npy: {}", listed.join(", "));
    }
    eprintln!("{} Newton steps and one adjoint solve in {elapsed:.2} s", run.state.steps);
    out.finish()?;
    if a.check {
        use diffsim::check::{CheckParams, check_all};
        // The force on the loss's body as a function of every body's
        // parameters: adjoint (VJP) against whole re-solves and the tangent
        // equations (JVP). Newton's residual floor limits the differences'
        // accuracy, hence the looser tolerance.
        let op = scene.force_operator(loss.obstacle)?;
        let report = check_all(&op, &scene.params(), &[], &CheckParams { tol: 1e-5, max_indices: 8, ..Default::default() });
        println!("{report}");
        if !report.passed() {
            return Err(CliError::ChecksFailed);
        }
    }
    Ok(())
}
