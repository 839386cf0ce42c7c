//! Scene files: the examples in `scenes/` run (at a few steps), every
//! malformed scene in `tests/scenes_bad/` is refused with its expected
//! message, only declared effects are built, and the gradient a scene
//! reports for a parameter matches finite differences of its loss.

use std::path::Path;

use diffsim::rollout::Checkpointing;
use diffsim::scene::{AnyScene, Scene};

/// The scene at `path` with `time.steps` replaced.
fn with_steps(path: &Path, steps: i64) -> Scene {
    let text = std::fs::read_to_string(path).unwrap();
    let mut table: toml::Table = toml::from_str(&text).unwrap();
    table["time"].as_table_mut().unwrap().insert("steps".into(), toml::Value::Integer(steps));
    // Loss steps beyond the new end move to it.
    if let Some(list) = table.get_mut("loss").and_then(|l| l.get_mut("steps")).and_then(|s| s.as_array_mut()) {
        for t in list.iter_mut() {
            *t = toml::Value::Integer(t.as_integer().unwrap().min(steps));
        }
    }
    Scene::parse_in(&toml::to_string(&table).unwrap(), path.parent().unwrap()).unwrap_or_else(|e| panic!("{}: {e}", path.display()))
}

fn files(dir: &str) -> Vec<std::path::PathBuf> {
    let root = Path::new(env!("CARGO_MANIFEST_DIR")).join(dir);
    let mut v: Vec<_> = std::fs::read_dir(root).unwrap().map(|e| e.unwrap().path()).filter(|p| p.extension().is_some_and(|e| e == "toml")).collect();
    v.sort();
    v
}

#[test]
fn example_scenes_run() {
    let all = files("scenes");
    assert!(all.len() >= 4);
    for path in &all {
        if let AnyScene::Steady(scene) = AnyScene::load(path).unwrap() {
            let run = scene.solve().unwrap_or_else(|e| panic!("{}: {e}", path.display()));
            assert!(run.state.residual < scene.newton.tolerance && run.forces.iter().flatten().all(|f| f.is_finite()));
            continue;
        }
        let scene = with_steps(path, 3);
        let x = scene.run(|_, _| {}).unwrap_or_else(|e| panic!("{}: {e}", path.display()));
        assert!(x.iter().all(|v| v.is_finite()));
        // The step is exactly the declared effects, in order.
        assert_eq!(scene.step.ops().len(), scene.effects.len(), "{}", path.display());
    }
}

#[test]
fn malformed_scenes_are_refused_with_their_message() {
    let all = files("tests/scenes_bad");
    assert!(all.len() >= 15);
    for path in &all {
        let text = std::fs::read_to_string(path).unwrap();
        let expect = text.lines().next().and_then(|l| l.strip_prefix("# expect: ")).unwrap_or_else(|| panic!("{}: no `# expect:` line", path.display()));
        let err = AnyScene::parse_in(&text, Path::new(".")).map(|_| ()).expect_err(&path.display().to_string()).to_string();
        assert!(err.contains(expect), "{}: expected `{expect}` in\n{err}", path.display());
    }
}

#[test]
fn only_declared_effects_are_built() {
    let scene = with_steps(&Path::new(env!("CARGO_MANIFEST_DIR")).join("scenes/heat.toml"), 1);
    assert_eq!(scene.effects, vec!["diffusion".to_string()]);
    let built = format!("{:?}", scene.step);
    for absent in ["Project", "Advect", "Buoyancy", "Force", "Inflow"] {
        assert!(!built.contains(absent), "{absent} built for a scene that does not declare it:\n{built}");
    }
    assert_eq!(scene.params.len(), 1, "one parameter: the diffusion's κ");
}

#[test]
fn scene_parameter_gradients_match_finite_differences() {
    // Buoyancy coefficient and the initial smoke of the obstacle scene (a
    // few steps), against central differences of the loss.
    let scene = with_steps(&root().join("scenes/smoke_obstacle.toml"), 6);
    let loss = scene.loss.as_ref().unwrap();
    let g = scene.gradient(loss, Checkpointing::Store).unwrap();
    let value = |p: &[f64], x0: &[f64]| scene.loss_value(loss, x0, p).unwrap();
    let (_, index, _) = scene.named.iter().find(|(n, _, _)| n == "buoyancy.coefficient").unwrap().clone();
    let h = 1e-5;
    let (mut up, mut down) = (scene.params.clone(), scene.params.clone());
    up[index] += h;
    down[index] -= h;
    let fd = (value(&up, &scene.x0) - value(&down, &scene.x0)) / (2.0 * h);
    let ad = grad_of(&g, "buoyancy.coefficient")[0];
    assert!((fd - ad).abs() <= 1e-6 * fd.abs().max(1.0), "buoyancy: finite differences {fd} vs gradient {ad}");
    let c = scene.cfg().n[0] * 16 + 30;
    let (mut up, mut down) = (scene.x0.clone(), scene.x0.clone());
    up[c] += h;
    down[c] -= h;
    let fd = (value(&scene.params, &up) - value(&scene.params, &down)) / (2.0 * h);
    let ad = grad_of(&g, "smoke.init")[c];
    assert!((fd - ad).abs() <= 1e-6 * fd.abs().max(1e-3), "smoke.init[{c}]: {fd} vs {ad}");
}

fn root() -> std::path::PathBuf {
    Path::new(env!("CARGO_MANIFEST_DIR")).to_path_buf()
}

/// The gradient with respect to `name`, its arrays concatenated.
fn grad_of(g: &diffsim::scene::SceneGradient, name: &str) -> Vec<f64> {
    g.inputs.iter().find(|i| i.name == name).unwrap_or_else(|| panic!("no gradient for {name}")).arrays.iter().flat_map(|(_, _, v)| v.clone()).collect()
}

#[test]
fn control_force_gradient_per_step_with_losses_at_listed_steps() {
    // A time-varying force (one field per step) and a loss at steps 2 and 5:
    // the per-step gradient against central differences of the loss, for
    // entries in the first, a middle and the last step.
    let text = r#"
        [domain]
        size = [8, 8]
        boundary = { x = "periodic", y = "closed" }
        [time]
        dt = 0.5
        steps = 5
        [fields.smoke]
        init = { disc = { center = [4.0, 3.0], radius = 2.5 } }
        [fields.velocity]
        init = { sine = { amplitude = 0.3, wavenumber = [1.0, 1.0] } }
        [[effects]]
        kind = "advection"
        [[effects]]
        kind = "force"
        value = [0.1, 0.05]
        [[effects]]
        kind = "pressure"
        tolerance = 1e-12
        [loss]
        field = "smoke"
        target = { box = { lower = [2.0, 4.0], upper = [6.0, 7.0] } }
        steps = [2, 5]
        with_respect_to = ["force.control", "smoke.init"]
    "#;
    let scene = Scene::parse(text).unwrap();
    assert!(scene.per_step());
    let loss = scene.loss.as_ref().unwrap();
    assert_eq!(loss.steps, vec![2, 5]);
    let g = scene.gradient(loss, Checkpointing::periodic_sqrt(scene.steps)).unwrap();
    let input = g.inputs.iter().find(|i| i.name == "force.control").unwrap();
    let (nu, np, steps) = (scene.cfg().n_face(0), scene.params.len(), scene.steps);
    assert_eq!(input.arrays[0].1, vec![steps as u64, 8, 9]);
    assert_eq!(input.arrays[1].1, vec![steps as u64, 9, 8]);
    let p = scene.rollout_params();
    let h = 1e-6;
    let c = scene.controls.iter().find(|c| c.name == "force.control").unwrap();
    // After the last loss step the control has no effect.
    for (t, face, comp) in [(0, 3 * 9 + 4, 0), (2, 4 * 8 + 4, 1), (4, 30, 0)] {
        let i = t * np + c.arrays[comp].range.start + face;
        let (mut up, mut down) = (p.clone(), p.clone());
        up[i] += h;
        down[i] -= h;
        let fd = (scene.loss_value(loss, &scene.x0, &up).unwrap() - scene.loss_value(loss, &scene.x0, &down).unwrap()) / (2.0 * h);
        let ad = input.arrays[comp].2[t * nu + face];
        assert!((fd - ad).abs() <= 1e-6 * fd.abs().max(1e-4), "step {t}, face {face}, component {comp}: {fd} vs {ad}");
    }
    // The loss counts both listed steps: it equals the sum of the two
    // single-step losses.
    let at = |steps: Vec<usize>| {
        let l = diffsim::scene::SceneLoss { steps, ..loss.clone() };
        scene.loss_value(&l, &scene.x0, &p).unwrap()
    };
    assert!((at(vec![2, 5]) - at(vec![2]) - at(vec![5])).abs() < 1e-12 * at(vec![2, 5]));
    assert!((at(vec![2, 5]) - g.loss).abs() < 1e-12 * g.loss);
}

#[test]
fn one_d_scenes_burgers_and_heat() {
    use diffsim::scene::{Domain, Field};
    // Heat on a periodic line: a sine mode decays by exactly
    // 1/(1 + κ·λ) per implicit step, λ = 2 − 2·cos(2πk/n) the discrete
    // Laplacian's eigenvalue, κ = ν·dt/dx².
    let text = r#"
        [domain]
        size = [32]
        length = 2.0
        boundary = "periodic"
        [time]
        dt = 0.01
        steps = 7
        [fields.smoke]
        init = { sine = { amplitude = 1.0, wavenumber = [3.0] } }
        [[effects]]
        kind = "diffusion"
        fields = ["smoke"]
        viscosity = 0.3
        tolerance = 1e-13
    "#;
    let scene = Scene::parse(text).unwrap();
    let Domain::Line(line) = scene.domain else { panic!("a line") };
    assert!((line.dx - 2.0 / 32.0).abs() < 1e-15);
    let x = scene.run(|_, _| {}).unwrap();
    let kappa = 0.3 * 0.01 / (line.dx * line.dx);
    let lambda = 2.0 - 2.0 * (std::f64::consts::TAU * 3.0 / 32.0).cos();
    let decay = (1.0 / (1.0 + kappa * lambda)).powi(7);
    for (i, &xi) in x.iter().enumerate().take(32) {
        let exact = decay * (std::f64::consts::TAU * 3.0 * i as f64 / 32.0).sin();
        assert!((xi - exact).abs() < 1e-10, "cell {i}: {xi} vs {exact}");
    }
    // The velocity was not declared: it stays zero and is not written.
    assert_eq!(scene.fields, vec![Field::Smoke]);

    // Burgers from the example scene: advection then explicit diffusion,
    // each step equal to the solver functions called directly.
    let scene = with_steps(&root().join("scenes/burgers.toml"), 5);
    let Domain::Line(l) = scene.domain else { panic!("a line") };
    let mut u = scene.x0[scene.domain.range(Field::Velocity)].to_vec();
    let cfg = diffsim_solvers::burgers::Burgers1d { n: l.n, dx: l.dx, dt: scene.dt, nu: 0.0 };
    let grid = diffsim_solvers::diffusion::Grid::line(l.n, true);
    let (_, kappa_index, _) = scene.named.iter().find(|(n, _, _)| n == "diffusion.viscosity").unwrap().clone();
    let mut tmp = vec![0.0; l.n];
    for _ in 0..5 {
        diffsim_solvers::burgers::step(&cfg, &u, &mut tmp);
        diffsim_solvers::diffusion::explicit(&grid, scene.params[kappa_index], &tmp, &mut u);
    }
    let x = scene.run(|_, _| {}).unwrap();
    let got = &x[scene.domain.range(Field::Velocity)];
    for i in 0..l.n {
        assert!((got[i] - u[i]).abs() < 1e-14, "cell {i}: {} vs {}", got[i], u[i]);
    }
    // Its viscosity gradient against central differences.
    let loss = scene.loss.as_ref().expect("burgers.toml has a loss");
    let g = scene.gradient(loss, Checkpointing::Store).unwrap();
    let (_, index, factor) = scene.named.iter().find(|(n, _, _)| n == "diffusion.viscosity").unwrap().clone();
    let h = 1e-7;
    let (mut up, mut down) = (scene.params.clone(), scene.params.clone());
    up[index] += h * factor;
    down[index] -= h * factor;
    let fd = (scene.loss_value(loss, &scene.x0, &up).unwrap() - scene.loss_value(loss, &scene.x0, &down).unwrap()) / (2.0 * h);
    let ad = grad_of(&g, "diffusion.viscosity")[0];
    assert!((fd - ad).abs() <= 1e-5 * fd.abs().max(1e-6), "viscosity: {fd} vs {ad}");
}

#[test]
fn initial_values_from_npy_files() {
    use npyz::WriterBuilder;
    let dir = std::env::temp_dir().join(format!("diffsim-npy-{}", std::process::id()));
    std::fs::create_dir_all(&dir).unwrap();
    let write = |name: &str, shape: &[u64], v: &[f64]| {
        let f = std::fs::File::create(dir.join(name)).unwrap();
        let mut w = npyz::WriteOptions::new().default_dtype().shape(shape).writer(f).begin_nd().unwrap();
        w.extend(v.iter().copied()).unwrap();
        w.finish().unwrap();
    };
    let s: Vec<f64> = (0..64).map(|k| k as f64 / 64.0).collect();
    write("s.npy", &[8, 8], &s);
    let u: Vec<f64> = (0..72).map(|k| 0.01 * k as f64).collect();
    write("u.npy", &[8, 9], &u);
    write("v.npy", &[9, 8], &u);
    write("wrong.npy", &[8, 9], &u);
    std::fs::write(dir.join("garbage.npy"), b"not an npy file").unwrap();
    let scene = |smoke: &str, velocity: &str| {
        Scene::parse_in(
            &format!(
                "[domain]\nsize = [8, 8]\n[time]\ndt = 1.0\nsteps = 1\n[fields.smoke]\ninit = {{ npy = {smoke} }}\n[fields.velocity]\ninit = {{ npy = {velocity} }}\n[[effects]]\nkind = \"advection\"\n"
            ),
            &dir,
        )
    };
    let ok = scene("\"s.npy\"", "[\"u.npy\", \"v.npy\"]").unwrap();
    assert_eq!(&ok.x0[..64], &s[..]);
    // Interior faces as given; the closed walls are set to zero.
    let (_, [u0, _]) = ok.cfg().split(&ok.x0);
    assert_eq!(u0[9 + 4], u[9 + 4]);
    assert_eq!(u0[9], 0.0);
    let cases = vec![("\"missing.npy\"", "cannot read"), ("\"garbage.npy\"", "not a valid .npy"), ("\"wrong.npy\"", "shape [8, 9], expected [8, 8]")];
    for (smoke, expect) in cases {
        let err = scene(smoke, "[\"u.npy\", \"v.npy\"]").unwrap_err().to_string();
        assert!(err.contains(expect) && err.contains("fields.smoke.init.npy") && err.contains("line 6"), "{smoke}: {err}");
    }
    let err = scene("\"s.npy\"", "\"u.npy\"").unwrap_err().to_string();
    assert!(err.contains("expected 2 files [u, v]"), "{err}");
    std::fs::remove_dir_all(&dir).unwrap();
}

#[test]
fn undeclared_effects_never_run() {
    // Operation counts over a run and a gradient: only the declared
    // effects' operators appear.
    use diffsim::op::count;
    let heat = with_steps(&root().join("scenes/heat.toml"), 2);
    count::start();
    heat.run(|_, _| {}).unwrap();
    heat.gradient(heat.loss.as_ref().unwrap(), Checkpointing::Store).unwrap();
    let counts = count::stop();
    let names: Vec<&str> = counts.iter().map(|c| c.name).collect();
    assert_eq!(names, vec!["DiffuseImplicit"], "{counts:?}");
    // Two steps forward in the run, two in the gradient's forward pass, two VJPs.
    assert_eq!((counts[0].forward, counts[0].vjp, counts[0].jvp), (4, 2, 0));

    // The obstacle scene: advection (smoke and velocity semi-Lagrangian in
    // a closed box: P2's explicit step), buoyancy, pressure; never
    // diffusion, force or inflow.
    let scene = with_steps(&root().join("scenes/smoke_obstacle.toml"), 2);
    count::start();
    scene.run(|_, _| {}).unwrap();
    let counts = count::stop();
    let mut names: Vec<&str> = counts.iter().map(|c| c.name).collect();
    names.sort_unstable();
    assert_eq!(names, vec!["Buoyancy<2>", "Project", "SmokeAdvect"], "{counts:?}");
    assert!(counts.iter().all(|c| c.forward == 2 && c.vjp == 0));
}

/// A steady scene's drag gradient with respect to two bodies' shapes (the
/// implicit adjoint) against central differences of the scene's loss over
/// whole re-solves; and the loss is the drag coefficient the forces give.
#[test]
fn steady_scene_drag_gradient_matches_resolves() {
    let text = r#"
[domain]
size = [60, 41]
cell = 0.01
boundary = { left = { inflow = [0.3, 0.0], profile = "parabolic" }, right = "outflow" }

[steady]
viscosity = 1e-3

[[obstacles]]
fourier = { center = [0.2013, 0.2007], r0 = 0.0503, cos = [0.004], sin = [0.002] }

[[obstacles]]
polygon = { vertices = [[0.3813, 0.1717], [0.4671, 0.2043], [0.3827, 0.2331]] }  # off the grid lines (kinks)

[loss]
kind = "drag"
obstacle = 0
reference = { speed = 0.2, length = 0.1 }
with_respect_to = ["obstacles[0].shape", "obstacles[1].shape"]
"#;
    let AnyScene::Steady(mut scene) = AnyScene::parse_in(text, Path::new(".")).unwrap() else { panic!("a steady scene") };
    let loss = scene.loss.clone().unwrap();
    let (run, g) = scene.gradient(&loss).unwrap();
    assert!((g.loss - 2.0 / (0.04 * 0.1) * run.forces[0][0]).abs() < 1e-12 * g.loss.abs());
    assert_eq!(g.inputs.len(), 2);
    assert_eq!(g.inputs[0].1, ["cx", "cy", "r0", "cos[0]", "sin[0]"]);
    assert_eq!(g.inputs[1].2.len(), 6);
    let eps = 1e-6;
    for (b, k) in [(0usize, 2usize), (0, 3), (1, 2), (1, 3)] {
        let shape = scene.shapes[b].clone();
        let mut value = |d: f64| {
            let mut p = shape.params();
            p[k] += d;
            scene.shapes[b] = shape.with_params(&p).unwrap();
            let run = scene.solve().unwrap();
            scene.loss_value(&loss, &run)
        };
        let fd = (value(eps) - value(-eps)) / (2.0 * eps);
        scene.shapes[b] = shape;
        let adjoint = g.inputs[b].2[k];
        assert!((fd - adjoint).abs() < 1e-5 * (1.0 + adjoint.abs()), "body {b} parameter {k}: adjoint {adjoint}, differences {fd}");
        assert!(adjoint.abs() > 1e-3, "body {b} parameter {k}: {adjoint}");
    }
}

/// Fourier and polygon obstacles in a scene stepped in time are the cells
/// whose centres they hold.
#[test]
fn shaped_obstacles_in_a_stepped_scene_are_cell_masks() {
    let text = r#"
[domain]
size = [16, 16]
[time]
dt = 1.0
steps = 1
[fields.velocity]
init = "zero"
[[effects]]
kind = "pressure"
[[obstacles]]
fourier = { center = [5.0, 8.0], r0 = 2.5, cos = [0.0, 0.5] }
[[obstacles]]
polygon = { vertices = [[10.0, 4.0], [14.0, 4.0], [12.0, 12.0]] }
"#;
    let scene = Scene::parse(text).unwrap();
    let solid = scene.solid.as_ref().unwrap();
    let at = |i: usize, j: usize| solid[j * 16 + i];
    // r(0) = 3: cells centred at x 5.5 … 7.5 on row 8 are inside, 8.5 not.
    assert!(at(5, 7) && at(7, 7) && !at(8, 7));
    // The triangle: its centroid's cell, not a corner outside it.
    assert!(at(12, 6) && !at(10, 11));
    assert!(!at(0, 0) && !at(15, 15));
}

#[test]
fn a_failing_effect_is_named_with_its_step() {
    let text = r#"
[domain]
size = [16, 16]
[time]
dt = 1.0
steps = 3
[fields.smoke]
init = { box = { lower = [4.0, 4.0], upper = [8.0, 8.0], value = 1.0 } }
[fields.velocity]
init = { uniform = [0.3, 0.1] }
[[effects]]
kind = "advection"
fields = ["smoke", "velocity"]
[[effects]]
kind = "pressure"
tolerance = 1e-14
max_iterations = 1
"#;
    let scene = diffsim::scene::Scene::parse(text).unwrap();
    let err = scene.run(|_, _| {}).unwrap_err().to_string();
    assert!(err.starts_with("step 1: effects[1] (pressure): linear solve did not converge"), "{err}");
}

#[test]
fn the_taylor_green_scene_decays_as_the_exact_solution() {
    // scenes/taylor_green.toml: advection, viscosity and pressure declared
    // on a periodic box reproduce the exact decay exp(−2ν(2π/L)²t). The
    // same vortex is an exact solution in a closed box too: its velocity
    // vanishes across every wall and its tangential part has no gradient
    // there, the free-slip condition of diffsim's closed sides; the walled
    // solve (multigrid CG, the walls' viscosity) must decay the same way.
    let path = Path::new(env!("CARGO_MANIFEST_DIR")).join("scenes/taylor_green.toml");
    let text = std::fs::read_to_string(&path).unwrap();
    // (The two texts one by one: an array of tuples iterated by value
    // aborts Enzyme's type analysis in this crate, docs/pitfalls.md.)
    for boundary in ["periodic", "closed"] {
        let text = text.replace("boundary = \"periodic\"", &format!("boundary = \"{boundary}\""));
        assert!(text.contains(&format!("boundary = \"{boundary}\"")));
        let scene = Scene::parse(&text).unwrap();
        let x0 = scene.x0.clone();
        let x = scene.run(|_, _| {}).unwrap();
        let (nu, t, l) = (0.2, 40.0, 64.0);
        let decay = (-2.0 * nu * (std::f64::consts::TAU / l).powi(2) * t).exp();
        let peak = x0.iter().fold(0.0f64, |m, v| m.max(v.abs()));
        let err = x.iter().zip(&x0).fold(0.0f64, |m, (a, b)| m.max((a - decay * b).abs()));
        // Measured: 1.6% of the peak in both (the schemes' error at 64², 40 steps).
        assert!(decay < 0.9 && err < 0.02 * peak, "{boundary}: largest error {err:.3e} against a decay to {decay:.4} of {peak}");
    }
}

#[test]
fn the_navier_stokes_effect_decays_taylor_green_and_names_its_parameters() {
    // The same vortex, the three effects replaced by the one Navier–Stokes
    // step (MacCormack, explicit viscosity, sub-steps), periodic and closed.
    let path = Path::new(env!("CARGO_MANIFEST_DIR")).join("scenes/taylor_green.toml");
    let text = std::fs::read_to_string(&path).unwrap();
    let effects = text.find("[[effects]]").unwrap();
    let one = format!("{}[[effects]]\nkind = \"navier_stokes\"\nviscosity = 0.2\ntolerance = 1e-10\n", &text[..effects]);
    for boundary in ["periodic", "closed"] {
        let text = one.replace("boundary = \"periodic\"", &format!("boundary = \"{boundary}\""));
        let scene = Scene::parse(&text).unwrap();
        assert_eq!(scene.effects, ["navier_stokes"]);
        let (_, viscosity, _) = scene.named.iter().find(|(n, _, _)| n == "navier_stokes.viscosity").unwrap().clone();
        let (_, dt, _) = scene.named.iter().find(|(n, _, _)| n == "navier_stokes.dt").unwrap().clone();
        assert_eq!((scene.params[viscosity], scene.params[dt]), (0.2, 1.0));
        let x0 = scene.x0.clone();
        let x = scene.run(|_, _| {}).unwrap();
        let decay = (-2.0 * 0.2 * (std::f64::consts::TAU / 64.0).powi(2) * 40.0).exp();
        let peak = x0.iter().fold(0.0f64, |m, v| m.max(v.abs()));
        let err = x.iter().zip(&x0).fold(0.0f64, |m, (a, b)| m.max((a - decay * b).abs()));
        assert!(err < 0.02 * peak, "{boundary}: largest error {err:.3e} against a decay to {decay:.4} of {peak}");
    }
}

#[test]
fn no_slip_walls_slow_a_channel_flow_where_free_slip_walls_do_not() {
    // A uniform inflow into a channel: between free-slip (closed) walls the
    // flow stays a plug; between no-slip walls the viscosity slows it next
    // to the walls.
    let channel = |walls: &str| {
        format!(
            "[domain]\nsize = [24, 12]\nboundary = {{ y = \"{walls}\", left = {{ inflow = [1.0, 0.0] }}, right = \"outflow\" }}\n\
             [time]\ndt = 0.5\nsteps = 40\n[fields.velocity]\ninit = \"zero\"\n\
             [[effects]]\nkind = \"navier_stokes\"\nviscosity = 1.0\nscheme = \"semi_lagrangian\"\ntolerance = 1e-10\n"
        )
    };
    let (nx, ny) = (24, 12);
    let u = |x: &[f64], j: usize| x[nx * ny + j * (nx + 1) + nx - 2];
    let free = Scene::parse(&channel("free-slip")).unwrap().run(|_, _| {}).unwrap();
    let ratio = u(&free, 0) / u(&free, ny / 2);
    assert!((ratio - 1.0).abs() < 1e-6, "free slip: wall row / middle row = {ratio}");
    let held = Scene::parse(&channel("no-slip")).unwrap().run(|_, _| {}).unwrap();
    let ratio = u(&held, 0) / u(&held, ny / 2);
    assert!(ratio < 0.8, "no slip: wall row / middle row = {ratio}");
    // Mass: what flows in leaves (the middle row faster than the inflow).
    assert!(u(&held, ny / 2) > 1.05, "no slip: middle row {}", u(&held, ny / 2));
}

/// `(f(h) − f(−h)) / 2h`.
pub(crate) fn central(f: impl Fn(f64) -> f64, h: f64) -> f64 {
    (f(h) - f(-h)) / (2.0 * h)
}

/// P4 written as a scene file: the advection, buoyancy and projection as
/// three declared effects.
const P4_SCENE: &str = r#"
[domain]
size = [32, 32, 32]

[time]
dt = 1.0
steps = 10

[fields.smoke]
init = { sphere = { center = [16.0, 8.0, 16.0], radius = 4.0 } }
[fields.velocity]
init = "zero"

[[effects]]
kind = "advection"

[[effects]]
kind = "buoyancy"
coefficient = 0.1

[[effects]]
kind = "pressure"

[loss]
field = "smoke"
target = { sphere = { center = [16.0, 24.0, 16.0], radius = 4.0 } }
with_respect_to = ["smoke.init"]
"#;

#[test]
fn a_3d_scene_reproduces_the_p4_reference_table() {
    use diffsim::scene::Scene;
    use diffsim_solvers::smoke::{P4_SIZES, probe};
    let scene = Scene::parse(P4_SCENE).unwrap();
    assert_eq!(scene.effects, ["advection", "buoyancy", "pressure"]);
    let r = &P4_SIZES[0];
    assert_eq!((r.n, r.steps), (32, 10));
    let g = scene.gradient(scene.loss.as_ref().unwrap(), Checkpointing::Store).unwrap();
    let gs = &g.inputs[0].arrays[0].2;
    let l2 = gs.iter().map(|v| v * v).sum::<f64>().sqrt();
    assert!((g.loss - r.loss).abs() <= 1e-6 * r.loss, "loss {} vs {}", g.loss, r.loss);
    assert!((l2 - r.grad_l2).abs() <= 1e-6 * r.grad_l2, "‖∇L‖ {l2} vs {}", r.grad_l2);
    assert!((gs[0] - r.grad_0).abs() <= 1e-6 * r.grad_l2 && (gs[probe::<3>(32)] - r.grad_probe).abs() <= 1e-6 * r.grad_l2);
    assert_eq!(g.inputs[0].arrays[0].1, vec![32, 32, 32]);
}

#[test]
fn a_3d_scene_with_obstacles_and_inflow_has_the_gradient_of_its_loss() {
    use diffsim::scene::Scene;
    let text = r#"
[domain]
size = [10, 12, 9]

[time]
dt = 0.8
steps = 4

[fields.smoke]
init = { sphere = { center = [5.0, 3.0, 5.0], radius = 2.5 } }
[fields.velocity]
init = { uniform = [0.2, 0.3, -0.1] }

[[obstacles]]
cylinder = { center = [5.0, 7.0, 0.0], radius = 1.6, axis = "z", extent = [2.0, 8.0] }

[[effects]]
kind = "inflow"
region = { box = { lower = [4.0, 0.0, 4.0], upper = [6.0, 1.0, 6.0] } }
smoke = 1.0
velocity = [0.0, 0.5, 0.0]

[[effects]]
kind = "advection"

[[effects]]
kind = "buoyancy"
coefficient = 0.2
axis = "y"

[[effects]]
kind = "diffusion"
fields = ["smoke", "velocity"]
viscosity = 0.05
scheme = "implicit"
tolerance = 1e-13

[[effects]]
kind = "force"
value = [0.0, 0.0, 0.05]

[[effects]]
kind = "pressure"
tolerance = 1e-13

[loss]
field = "smoke"
target = { box = { lower = [3.0, 6.0, 3.0], upper = [7.0, 9.0, 7.0] } }
with_respect_to = ["smoke.init", "buoyancy.coefficient"]
"#;
    let scene = Scene::parse(text).unwrap();
    let loss = scene.loss.as_ref().unwrap();
    let g = scene.gradient(loss, Checkpointing::Store).unwrap();
    let p = scene.rollout_params();
    // ∂L/∂b against central differences of whole runs.
    let (_, index, _) = scene.named.iter().find(|(n, _, _)| n == "buoyancy.coefficient").unwrap().clone();
    let h = 1e-5;
    let fd = crate::scenes::central(
        |d| {
            let mut q = p.clone();
            q[index] += d;
            scene.loss_value(loss, &scene.x0, &q).unwrap()
        },
        h,
    );
    let db = g.inputs[1].arrays[0].2[0];
    assert!((fd - db).abs() <= 1e-6 * fd.abs().max(1e-8), "∂L/∂b {db} vs finite differences {fd}");
    // A directional derivative along a smooth change of the initial smoke.
    let gs = &g.inputs[0].arrays[0].2;
    let dir: Vec<f64> = crate::smoke::field(gs.len(), 5);
    let fd = crate::scenes::central(
        |d| {
            // The smoke moved along `dir`, the velocity as it was.
            let x: Vec<f64> = scene.x0.iter().zip(dir.iter().chain(std::iter::repeat(&0.0))).map(|(x, v)| x + d * v).collect();
            scene.loss_value(loss, &x, &p).unwrap()
        },
        h,
    );
    let dot: f64 = gs.iter().zip(&dir).map(|(a, b)| a * b).sum();
    assert!((fd - dot).abs() <= 1e-6 * fd.abs(), "∂L/∂s₀·d {dot} vs finite differences {fd}");
}

#[test]
fn a_3d_obstacle_mask_comes_from_a_npy_file() {
    use diffsim::scene::Scene;
    use npyz::WriterBuilder;
    // A mask [nz, ny, nx] with a solid slab across the middle of y, except
    // a hole; written as float64 like `diffsim run` writes volumes.
    let (nx, ny, nz) = (6, 8, 5);
    let mut mask = vec![0.0; nx * ny * nz];
    for k in 0..nz {
        for i in 0..nx {
            if (i, k) != (2, 2) {
                mask[(k * ny + 4) * nx + i] = 1.0;
            }
        }
    }
    let dir = std::env::temp_dir().join(format!("diffsim-mask-{}", std::process::id()));
    std::fs::create_dir_all(&dir).unwrap();
    let file = std::io::BufWriter::new(std::fs::File::create(dir.join("mask.npy")).unwrap());
    let mut w = npyz::WriteOptions::new().default_dtype().shape(&[nz as u64, ny as u64, nx as u64]).writer(file).begin_nd().unwrap();
    w.extend(mask.iter().copied()).unwrap();
    w.finish().unwrap();
    let text = r#"
[domain]
size = [6, 8, 5]
[time]
dt = 1.0
steps = 2
[fields.velocity]
init = { sine = { amplitude = 0.5, wavenumber = [1.0, 1.0, 1.0] } }
[[obstacles]]
npy = "mask.npy"
[[effects]]
kind = "pressure"
"#;
    let scene = Scene::parse_in(text, &dir).unwrap();
    let solid = scene.solid.as_ref().unwrap();
    assert_eq!(solid.iter().filter(|&&s| s).count(), nx * nz - 1);
    assert!(solid[(4 * ny + 4) * nx + 3] && !solid[(2 * ny + 4) * nx + 2]);
    // No flow through the slab's faces; and since the box is closed, the net
    // flux through the plane of the slab is zero, so the hole, its only
    // opening, carries none either.
    let x = scene.run(|_, _| {}).unwrap();
    let v = &x[scene.domain.range(diffsim::scene::Field::Velocity)][(nx + 1) * ny * nz..][..nx * (ny + 1) * nz];
    for k in 0..nz {
        for i in 0..nx {
            let face = (k * (ny + 1) + 4) * nx + i;
            if (i, k) == (2, 2) {
                assert!(v[face].abs() < 1e-8, "net flux through the hole {}", v[face]);
            } else {
                assert_eq!(v[face], 0.0, "flow into the slab at ({i}, {k})");
            }
        }
    }
    assert!(v.iter().any(|v| v.abs() > 1e-3), "the flow vanished");
    // A mask of the wrong shape is refused with the file named.
    let bad = text.replace("size = [6, 8, 5]", "size = [6, 8, 6]");
    let err = Scene::parse_in(&bad, &dir).unwrap_err().to_string();
    assert!(err.contains("mask.npy") && err.contains("shape"), "{err}");
}
