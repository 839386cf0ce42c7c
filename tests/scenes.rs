//! Scene files: the examples in `scenes/` run (at a few steps), every
//! malformed scene in `tests/scenes_bad/` is refused with its expected
//! message, only declared effects are built, and the gradient a scene
//! reports for a parameter matches finite differences of its loss.

use std::path::Path;

use diffsim::rollout::{Checkpointing, Rollout};
use diffsim::scene::Scene;

/// The scene at `path` with `time.steps` replaced.
fn with_steps(path: &Path, steps: i64) -> Scene {
    let text = std::fs::read_to_string(path).unwrap();
    let mut table: toml::Table = toml::from_str(&text).unwrap();
    table["time"].as_table_mut().unwrap().insert("steps".into(), toml::Value::Integer(steps));
    Scene::parse(&toml::to_string(&table).unwrap()).unwrap_or_else(|e| panic!("{}: {e}", path.display()))
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
        let err = Scene::parse(&text).map(|_| ()).expect_err(&path.display().to_string()).to_string();
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
    let scene = with_steps(&Path::new(env!("CARGO_MANIFEST_DIR")).join("scenes/smoke_obstacle.toml"), 6);
    let (target, _) = scene.loss.as_ref().unwrap();
    let loss = |x: &[f64], g: &mut [f64]| diffsim_solvers::smoke::p2_loss(&scene.cfg, x, target, g);
    let value = |p: &[f64], x0: &[f64]| Rollout::new(&scene.step, p, scene.steps).unwrap().loss(x0, &loss).unwrap();
    let g = Rollout::new(&scene.step, &scene.params, scene.steps).unwrap().value_and_grad(&scene.x0, &loss, Checkpointing::Store).unwrap();
    let (_, index, factor) = scene.named.iter().find(|(n, _, _)| n == "buoyancy.coefficient").unwrap().clone();
    let h = 1e-5;
    let (mut up, mut down) = (scene.params.clone(), scene.params.clone());
    up[index] += h;
    down[index] -= h;
    let fd = (value(&up, &scene.x0) - value(&down, &scene.x0)) / (2.0 * h);
    let ad = g.dp[index] * factor;
    assert!((fd - ad).abs() <= 1e-6 * fd.abs().max(1.0), "buoyancy: finite differences {fd} vs gradient {ad}");
    let c = scene.cfg.n * 16 + 30;
    let (mut up, mut down) = (scene.x0.clone(), scene.x0.clone());
    up[c] += h;
    down[c] -= h;
    let fd = (value(&scene.params, &up) - value(&scene.params, &down)) / (2.0 * h);
    assert!((fd - g.dx0[c]).abs() <= 1e-6 * fd.abs().max(1e-3), "smoke.init[{c}]: {fd} vs {}", g.dx0[c]);
}
