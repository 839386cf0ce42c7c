//! The `diffsim` binary: bad arguments give a clear error and a non-zero
//! exit; a small P1 run prints one JSON line with the documented keys.

use std::process::Command;

/// Runs `diffsim` and returns (exit code, stdout, stderr).
pub(crate) fn diffsim(args: &[&str]) -> (i32, String, String) {
    let out = Command::new(crate::diffsim_bin()).args(args).output().unwrap();
    (out.status.code().unwrap_or(-1), String::from_utf8_lossy(&out.stdout).into(), String::from_utf8_lossy(&out.stderr).into())
}

#[track_caller]
fn fails_with(args: &[&str], needle: &str) {
    let (code, _, err) = diffsim(args);
    assert_ne!(code, 0, "{args:?} should fail");
    assert!(err.contains(needle), "{args:?}: stderr was {err}");
    assert!(!err.contains("panicked"), "{args:?}: {err}");
}

// One call per case, not a table: an array of tuples holding `Vec<&str>`
// tipped rustc's Enzyme type trees into an abort (docs/pitfalls.md).
#[test]
fn bench_p1_rejects_bad_arguments() {
    fails_with(&["bench", "p1", "--n", "2"], "invalid argument --n");
    fails_with(&["bench", "p1", "--steps", "0"], "invalid argument --steps");
    fails_with(&["bench", "p1", "--threads", "0"], "invalid argument --threads");
    fails_with(&["bench", "p1", "--checkpoint", "sometimes"], "unknown checkpointing");
    fails_with(&["bench", "p1", "--n", "many"], "invalid value 'many'");
}

#[test]
fn bench_p1_json_line() {
    let (code, out, err) = diffsim(&["bench", "p1", "--n", "37", "--steps", "5", "--threads", "1", "--json"]);
    assert_eq!(code, 0, "{err}");
    let v: serde_json::Value = serde_json::from_str(out.trim()).unwrap();
    for key in [
        "problem",
        "n",
        "steps",
        "threads",
        "forward_s",
        "grad_s",
        "hand_grad_s",
        "grad_over_forward",
        "enzyme_over_hand",
        "peak_rss_bytes",
        "loss",
        "grad_l2",
        "grad_0",
        "grad_n2",
    ] {
        assert!(v.get(key).is_some(), "missing {key} in {out}");
    }
    assert_eq!(v["problem"], "p1");
    assert_eq!(v["n"], 37);
    assert_eq!(v["threads"], 1);
    // The loss printed is the one the library computes.
    let p = diffsim::problems::burgers::P1::new(37, 5);
    assert!((v["loss"].as_f64().unwrap() - p.value().unwrap()).abs() < 1e-15);
    assert!(v["enzyme_hand_max_diff"].as_f64().unwrap() < 1e-14);
}

#[test]
fn enzyme_log_guard_flags_enzyme_errors_only() {
    let dir = std::env::temp_dir().join(format!("diffsim-guard-{}", std::process::id()));
    std::fs::create_dir_all(&dir).unwrap();
    let guard = concat!(env!("CARGO_MANIFEST_DIR"), "/scripts/cargo-enzyme");
    let check = |name: &str, text: &str| -> bool {
        let path = dir.join(name);
        std::fs::write(&path, text).unwrap();
        // stderr silenced: the guard echoes the error line, and this test's
        // own output must not trip the guard that runs the test suite.
        Command::new("bash").arg(guard).arg("--check-log").arg(&path).stderr(std::process::Stdio::null()).status().unwrap().success()
    };
    assert!(check("clean.log", "   Compiling diffsim v0.1.0\n    Finished `release` profile\n"));
    assert!(check("warning.log", "warning: <unknown>:0:0: in function f: Enzyme: Mismatched activity for: ...\n"));
    assert!(!check("error.log", "   Compiling diffsim\nerror: <unknown>:0:0: in function f: Enzyme: cannot deduce type of copy\n"));
    std::fs::remove_dir_all(&dir).ok();
}

/// `cargo-enzyme run` and `test` judge the compiler's messages only: a
/// program that prints what looks like an Enzyme error (as a user's
/// gradient check may) runs, exits 0, and its output and arguments reach it.
#[test]
fn the_guard_does_not_judge_what_a_program_prints() {
    let dir = std::env::temp_dir().join(format!("diffsim-guard-run-{}", std::process::id()));
    std::fs::create_dir_all(dir.join("src")).unwrap();
    let manifest = concat!(env!("CARGO_MANIFEST_DIR"), "/rust-toolchain.toml");
    std::fs::copy(manifest, dir.join("rust-toolchain.toml")).unwrap();
    std::fs::write(dir.join("Cargo.toml"), "[package]\nname = \"prints-errors\"\nversion = \"0.1.0\"\nedition = \"2024\"\n").unwrap();
    let main = r#"fn main() {
    let line = format!("{}: <unknown>:0:0: in function f: {}: a gradient check failed", "error", "Enzyme");
    println!("{line}");
    eprintln!("{line}");
    println!("args: {:?}", std::env::args().skip(1).collect::<Vec<_>>());
}
#[test]
fn prints() {
    println!("{}: in function g: {}: fake", "error", "Enzyme");
}
"#;
    std::fs::write(dir.join("src/main.rs"), main).unwrap();
    let guard = concat!(env!("CARGO_MANIFEST_DIR"), "/scripts/cargo-enzyme");
    let run = |args: &[&str]| Command::new("bash").arg(guard).args(args).current_dir(&dir).env_remove("CARGO_TARGET_DIR").output().unwrap();
    let out = run(&["run", "--release", "--", "--flag", "x"]);
    let (stdout, stderr) = (String::from_utf8_lossy(&out.stdout), String::from_utf8_lossy(&out.stderr));
    assert!(out.status.success(), "{stdout}\n{stderr}");
    assert!(stdout.contains("a gradient check failed") && stdout.contains(r#"args: ["--flag", "x"]"#), "{stdout}");
    assert!(!stderr.contains("enzyme guard"), "{stderr}");
    let out = run(&["test", "--release", "--", "--nocapture"]);
    assert!(out.status.success(), "{}", String::from_utf8_lossy(&out.stderr));
    assert!(String::from_utf8_lossy(&out.stdout).contains("Enzyme: fake"));
    std::fs::remove_dir_all(&dir).ok();
}

#[test]
fn demo_plume_writes_a_png() {
    let dir = std::env::temp_dir().join(format!("diffsim-plume-{}", std::process::id()));
    let (code, out, err) = diffsim(&["demo", "plume", "--n", "24", "--steps", "20", "--out", dir.to_str().unwrap()]);
    assert_eq!(code, 0, "{err}");
    assert!(out.contains("plume.png"), "{out}");
    let bytes = std::fs::read(dir.join("plume.png")).unwrap();
    assert_eq!(&bytes[1..4], b"PNG");
    std::fs::remove_dir_all(&dir).ok();
    fails_with(&["demo", "plume", "--n", "4"], "invalid argument --n");
}

#[test]
fn check_command_runs_the_three_checks_on_a_p1_rollout() {
    let (code, out, err) = diffsim(&["check", "--n", "24", "--steps", "30"]);
    assert_eq!(code, 0, "{out}\n{err}");
    assert_eq!(out.matches("→ pass").count(), 6, "{out}");
    fails_with(&["check", "--n", "2"], "invalid argument --n");
}

#[test]
fn scene_commands_write_their_outputs_and_refuse_bad_scenes() {
    let out = std::env::temp_dir().join(format!("diffsim-scene-{}", std::process::id()));
    let o = out.to_str().unwrap();
    let (code, _, err) = diffsim(&["run", "scenes/heat.toml", "--out", o, "--quiet"]);
    assert_eq!(code, 0, "{err}");
    for f in ["smoke.npy", "smoke.png"] {
        assert!(out.join(f).exists(), "{f} missing");
    }
    // The heat scene declares no velocity: none is written.
    assert!(!out.join("velocity_u.npy").exists());
    let (code, stdout, err) = diffsim(&["grad", "scenes/heat.toml", "--out", o]);
    assert_eq!(code, 0, "{err}");
    assert!(stdout.contains("d loss / d diffusion.viscosity"), "{stdout}");
    assert!(out.join("grad_diffusion_viscosity.npy").exists());
    let (code, stdout, _) = diffsim(&["run", "scenes/heat.toml", "--out", o, "--profile", "--quiet"]);
    assert_eq!(code, 0);
    assert!(stdout.contains("diffusion") && !stdout.contains("pressure"), "{stdout}");
    fails_with(&["run", "tests/scenes_bad/unknown_kind.toml", "--out", o], "did you mean `advection`");
    // A 1D scene: its field as .npy and a plot; the gradient with a profile
    // of both passes.
    // (Another scene: its results replace the heat scene's only when asked.)
    fails_with(&["run", "scenes/burgers.toml", "--out", o, "--quiet"], "holds the results of another run");
    let (code, _, err) = diffsim(&["run", "scenes/burgers.toml", "--out", o, "--quiet", "--overwrite"]);
    assert_eq!(code, 0, "{err}");
    assert!(out.join("velocity.npy").exists() && out.join("velocity.png").exists());
    let (code, stdout, err) = diffsim(&["grad", "scenes/burgers.toml", "--out", o, "--profile"]);
    assert_eq!(code, 0, "{err}");
    assert!(out.join("grad_velocity_init.npy").exists());
    assert!(stdout.contains("forward (diffsim run)") && stdout.contains("backward (VJPs"), "{stdout}");
    std::fs::remove_dir_all(&out).ok();
}

#[test]
fn steady_scene_commands_report_forces_and_the_shape_gradient() {
    let out = std::env::temp_dir().join(format!("diffsim-steady-{}", std::process::id()));
    let o = out.to_str().unwrap();
    let (code, stdout, err) = diffsim(&["run", "scenes/drag_body.toml", "--out", o]);
    assert_eq!(code, 0, "{err}");
    assert!(stdout.contains("obstacles[0]: force") && stdout.contains("c_D"), "{stdout}");
    let cd: f64 = stdout.split("c_D ").nth(1).and_then(|r| r.split(',').next()).unwrap().parse().unwrap();
    assert!(err.contains("Newton steps"), "{err}");
    for f in ["velocity_u.npy", "velocity_v.npy", "pressure.npy", "speed.png"] {
        assert!(out.join(f).exists(), "{f} missing");
    }
    let (code, stdout, err) = diffsim(&["grad", "scenes/drag_body.toml", "--out", o]);
    assert_eq!(code, 0, "{err}");
    assert!(stdout.contains("(drag of obstacles[0])") && stdout.contains("d loss / d obstacles[0].shape") && stdout.contains("cos[1]"), "{stdout}");
    // The drag coefficient the loss reports is the one `run` prints.
    let loss: f64 = stdout.split_whitespace().nth(1).unwrap().parse().unwrap();
    assert!((4.0..7.0).contains(&loss) && (loss - cd).abs() < 1e-5, "{stdout}");
    assert!(out.join("grad_obstacles_0_shape.npy").exists());
    fails_with(&["grad", "tests/scenes_bad/steady_negative_radius.toml", "--out", o], "line 10: `obstacles[0]`: shape: the radius is");
    std::fs::remove_dir_all(&out).ok();
}

#[test]
fn train_and_experiment_commands() {
    let out = std::env::temp_dir().join(format!("diffsim-train-{}", std::process::id()));
    let o = out.to_str().unwrap();
    let cfg = out.join("tiny.toml");
    std::fs::create_dir_all(&out).unwrap();
    let text = std::fs::read_to_string("configs/sol_burgers.toml").unwrap();
    let tiny = text
        .replace("iterations = 600", "iterations = 3")
        .replace("train = 32", "train = 4")
        .replace("test = 8", "test = 2")
        .replace("steps = 144", "steps = 40")
        .replace("test_steps = 128", "test_steps = 20")
        .replace("unroll = 16", "unroll = 4");
    std::fs::write(&cfg, &tiny).unwrap();
    let c = cfg.to_str().unwrap();
    let (code, stdout, err) = diffsim(&["train", c, "--out", o, "--quiet"]);
    assert_eq!(code, 0, "{stdout}\n{err}");
    assert!(stdout.contains("3 iterations (3 in total)") && stdout.contains("corrected"), "{stdout}");
    for f in ["loss.csv", "loss.png", "model.json", "checkpoint.json"] {
        assert!(out.join(f).exists(), "{f} missing");
    }
    // A finished run resumed only writes its outputs again; --extend trains on.
    let (code, stdout, err) = diffsim(&["train", c, "--out", o, "--quiet", "--resume"]);
    assert_eq!(code, 0, "{err}");
    assert!(stdout.contains("0 iterations (3 in total)") && err.contains("the run had finished"), "{stdout}");
    let (code, stdout, err) = diffsim(&["train", c, "--out", o, "--quiet", "--extend", "3"]);
    assert_eq!(code, 0, "{err}");
    assert!(stdout.contains("(6 in total)"), "{stdout}");
    assert_eq!(std::fs::read_to_string(out.join("loss.csv")).unwrap().lines().count(), 7);
    // Data generated on the fly with a viscosity range (another
    // configuration: the folder's run is replaced only when asked).
    std::fs::write(&cfg, tiny.replace("viscosity = 0.01", "viscosity = [0.005, 0.02]")).unwrap();
    fails_with(&["train", c, "--out", o, "--quiet"], "holds a run of another configuration (`problem.viscosity` differs)");
    let (code, _, err) = diffsim(&["train", c, "--out", o, "--quiet", "--overwrite"]);
    assert_eq!(code, 0, "{err}");
    // Mistakes name the key.
    std::fs::write(&cfg, tiny.replace("method = \"sol\"", "method = \"sol2\"")).unwrap();
    fails_with(&["train", c, "--out", o], "`training.method`: unknown method `sol2`; did you mean `sol`?");
    std::fs::write(&cfg, tiny.replace("kernel = 5", "kernel = 4")).unwrap();
    fails_with(&["train", c, "--out", o], "`network.kernel`: must be odd");
    std::fs::write(&cfg, tiny.replace("lr = 1e-3", "lr = -1")).unwrap();
    fails_with(&["train", c, "--out", o], "`training.lr`");
    std::fs::write(&cfg, tiny.replace("batch = 16", "bacth = 16")).unwrap();
    fails_with(&["train", c, "--out", o], "did you mean `batch`");
    fails_with(
        &["experiment", "sol-burgers", "--net", "transformer", "--overwrite", "--out", o],
        "invalid argument --net: expected conv-stack, unet or resnet",
    );
    // The study, reduced to two updates per variant (with the U-Net): one JSON object last.
    fails_with(&["experiment", "sol-burgers", "--train", "0", "--overwrite", "--out", o], "invalid argument --train: need at least one training trajectory");
    let (code, stdout, err) =
        diffsim(&["experiment", "sol-burgers", "--quick", "--iterations", "2", "--net", "unet", "--train", "4", "--json", "--overwrite", "--out", o]);
    assert_eq!(code, 0, "{err}");
    let last: serde_json::Value = serde_json::from_str(stdout.lines().last().unwrap()).unwrap();
    for key in ["source", "pre", "noise", "sol4", "sol16", "train_s_per_iter"] {
        assert!(last[key].as_f64().is_some_and(f64::is_finite), "{key} in {last}");
        if key != "train_s_per_iter" {
            assert!(last["train_set"][key].as_f64().is_some_and(f64::is_finite), "train_set.{key} in {last}");
        }
    }
    assert_eq!(last["train_trajectories"], 4);
    // A subset of variants, another unroll length, activation and width.
    fails_with(
        &["experiment", "sol-burgers", "--methods", "pre,sol0", "--overwrite", "--out", o],
        "invalid argument --methods: expected pre, noise or solK (K ≥ 1), got \"sol0\"",
    );
    fails_with(
        &["experiment", "sol-burgers", "--activation", "sigmoidal", "--overwrite", "--out", o],
        "invalid argument --activation: unknown variant `sigmoidal`",
    );
    fails_with(&["experiment", "sol-burgers", "--lr", "0", "--overwrite", "--out", o], "invalid argument --lr: must be a positive number");
    fails_with(&["experiment", "sol-burgers", "--noise=-1", "--overwrite", "--out", o], "invalid argument --noise: must be a non-negative number");
    fails_with(&["experiment", "sol-burgers", "--width", "0", "--overwrite", "--out", o], "invalid argument --width: must be at least 1");
    let (code, stdout, err) = diffsim(&[
        "experiment",
        "sol-burgers",
        "--quick",
        "--iterations",
        "2",
        "--methods",
        "pre,noise,sol3",
        "--noise",
        "0.01",
        "--activation",
        "tanh",
        "--width",
        "8",
        "--train",
        "4",
        "--json",
        "--overwrite",
        "--out",
        o,
    ]);
    assert_eq!(code, 0, "{err}");
    let subset: serde_json::Value = serde_json::from_str(stdout.lines().last().unwrap()).unwrap();
    assert!(subset["sol3"].as_f64().is_some_and(f64::is_finite) && subset["pre"].as_f64().is_some(), "{subset}");
    assert!(subset["sol16"].is_null() && subset["noise"].as_f64().is_some(), "{subset}");
    assert_eq!(subset["source"], last["source"]);
    // Another seed draws other test trajectories.
    let (code, stdout, err) = diffsim(&[
        "experiment",
        "sol-burgers",
        "--quick",
        "--iterations",
        "1",
        "--methods",
        "pre",
        "--train",
        "4",
        "--seed",
        "7",
        "--json",
        "--overwrite",
        "--out",
        o,
    ]);
    assert_eq!(code, 0, "{err}");
    let seeded: serde_json::Value = serde_json::from_str(stdout.lines().last().unwrap()).unwrap();
    assert_ne!(seeded["source"], last["source"]);
    // The test set does not depend on the number of training trajectories
    // (fewer or more than the standard count).
    let (code, stdout, err) = diffsim(&["experiment", "sol-burgers", "--quick", "--iterations", "1", "--train", "40", "--json", "--overwrite", "--out", o]);
    assert_eq!(code, 0, "{err}");
    let more: serde_json::Value = serde_json::from_str(stdout.lines().last().unwrap()).unwrap();
    assert_eq!(more["source"], last["source"]);
    assert_ne!(more["train_set"]["source"], last["train_set"]["source"]);
    for f in ["table.md", "errors.csv", "error.png", "loss.png"] {
        assert!(out.join(f).exists(), "{f} missing");
    }
    std::fs::remove_dir_all(&out).ok();
}

/// Issue 5's promise for the reduced Burgers study: SOL-16 below both PRE
/// and the source solver (and within a third of the source's error). The
/// study is deterministic (fixed seeds, sums in sample order, no fused
/// multiply-add), so this is the same run on every machine; about 35 s.
#[test]
fn sol_wake_experiment_runs_reduced_and_reports_json() {
    let out = std::env::temp_dir().join(format!("diffsim-wake-{}", std::process::id()));
    let o = out.to_str().unwrap();
    fails_with(&["experiment", "sol-wake", "--train", "0", "--overwrite", "--out", o], "invalid argument --train: need at least one training trajectory");
    fails_with(&["experiment", "sol-wake", "--steps", "0", "--overwrite", "--out", o], "invalid argument --steps: must be at least 1");
    // One update per variant, one training trajectory, 2-step test rollouts.
    let (code, stdout, err) =
        diffsim(&["experiment", "sol-wake", "--quick", "--iterations", "1", "--train", "1", "--steps", "2", "--json", "--overwrite", "--out", o]);
    assert_eq!(code, 0, "{err}");
    let last: serde_json::Value = serde_json::from_str(stdout.lines().last().unwrap()).unwrap();
    for key in ["source", "pre", "noise", "sol4", "sol16", "train_s_per_iter"] {
        assert!(last[key].as_f64().is_some_and(|v| v.is_finite() && v >= 0.0), "{key} in {last}");
    }
    // The coarse solver drifts from the 4× finer reference.
    assert!(last["source"].as_f64().unwrap() > 1e-4, "{last}");
    for f in ["table.md", "errors.csv", "error.png", "loss.png"] {
        assert!(out.join(f).exists(), "{f} missing");
    }
    std::fs::remove_dir_all(&out).ok();
}

#[test]
fn sip_heat_experiment_runs_and_reports_json() {
    let out = std::env::temp_dir().join(format!("diffsim-sip-{}", std::process::id()));
    let o = out.to_str().unwrap();
    let (code, stdout, err) = diffsim(&["experiment", "sip-heat", "--iterations", "1", "--json", "--overwrite", "--out", o]);
    assert_eq!(code, 0, "{err}");
    let last: serde_json::Value = serde_json::from_str(stdout.lines().last().unwrap()).unwrap();
    for key in ["sip", "adam", "gd", "sip_s", "adam_s", "gd_s", "sip_x_l2", "inverse", "inverse_x_l2", "budget_s"] {
        assert!(last[key].as_f64().is_some_and(f64::is_finite), "{key} in {last}");
    }
    assert!(out.join("error.png").exists() && out.join("table.md").exists() && out.join("error.csv").exists());
    fails_with(&["experiment", "sip-heat", "--iterations", "0", "--overwrite", "--out", o], "invalid argument --iterations");
    fails_with(&["experiment", "sip-heat", "--setup", "publish", "--overwrite", "--out", o], "did you mean `published`");
    std::fs::remove_dir_all(&out).ok();
}

#[test]
fn sip_smoke_experiment_runs_and_reports_json() {
    let out = std::env::temp_dir().join(format!("diffsim-sip-smoke-{}", std::process::id()));
    let o = out.to_str().unwrap();
    let (code, stdout, err) =
        diffsim(&["experiment", "sip-smoke", "--quick", "--seconds", "0.5", "--inverse-iterations", "2", "--json", "--overwrite", "--out", o]);
    assert_eq!(code, 0, "{err}");
    let last: serde_json::Value = serde_json::from_str(stdout.lines().last().unwrap()).unwrap();
    for key in ["sip", "adam", "time_s", "sip_resim", "adam_resim", "sip_s_per_update", "adam_s_per_update", "inverse", "inverse_resim"] {
        assert!(last[key].as_f64().is_some_and(|v| v.is_finite() && v > 0.0), "{key} in {last}");
    }
    assert_eq!(last["inverse_miss"].as_array().map(Vec::len), Some(3), "{last}");
    for f in ["table.md", "error.csv", "error.png", "reconstructions.png"] {
        assert!(out.join(f).exists(), "{f} missing");
    }
    fails_with(&["experiment", "sip-smoke", "--seconds", "0", "--overwrite", "--out", o], "invalid argument --seconds");
    std::fs::remove_dir_all(&out).ok();
}

#[test]
fn cavity_experiment_reports_json_and_writes_its_profiles() {
    let out = std::env::temp_dir().join(format!("diffsim-cavity-{}", std::process::id()));
    let o = out.to_str().unwrap();
    let (code, stdout, err) = diffsim(&["experiment", "cavity", "--re", "100", "--resolution", "16", "--json", "--overwrite", "--out", o]);
    assert_eq!(code, 0, "{err}");
    let last: serde_json::Value = serde_json::from_str(stdout.lines().last().unwrap()).unwrap();
    for key in ["u_min", "y_at_u_min", "v_max", "x_at_v_max", "v_min", "x_at_v_min", "time_s"] {
        assert!(last[key].as_f64().is_some_and(f64::is_finite), "{key} in {last}");
    }
    assert_eq!(last["cells"].as_u64(), Some(256), "{last}");
    assert!(last["steps"].as_u64().is_some_and(|s| s > 10), "{last}");
    assert!(last["ghia"]["v_max"].as_f64().is_some() && last["relative_error"]["u_min"].as_f64().is_some(), "{last}");
    assert!(out.join("cavity_re100.csv").exists() && out.join("cavity_re100.png").exists());
    fails_with(&["experiment", "cavity", "--re", "0"], "invalid argument --re");
    fails_with(&["experiment", "cavity", "--resolution", "2"], "invalid argument --resolution");
    fails_with(&["experiment", "cavity", "--resolution", "8", "--max-steps", "10"], "no steady state after 10 steps");
    std::fs::remove_dir_all(&out).ok();
}

/// The command line's part of the cylinder study (the figures are tested
/// through the report in `studies.rs`): the JSON line, the sweep's and the
/// flags' errors.
#[test]
fn cylinder_experiment_prints_its_report_and_refuses_bad_flags() {
    let (code, stdout, err) = diffsim(&["experiment", "cylinder", "--case", "2d-1", "--resolution", "10", "--json"]);
    assert_eq!(code, 0, "{err}");
    let last: serde_json::Value = serde_json::from_str(stdout.lines().last().unwrap()).unwrap();
    for key in ["cd", "cl", "dp", "time_s"] {
        assert!(last[key].as_f64().is_some_and(f64::is_finite), "{key} in {last}");
    }
    assert_eq!((last["case"].as_str(), last["solver"].as_str(), last["cells"].as_u64()), (Some("2d-1"), Some("newton"), Some(220 * 41)), "{last}");
    let (code, stdout, err) = diffsim(&["experiment", "cylinder", "--case", "2d-1", "--resolution", "10"]);
    assert_eq!(code, 0, "{err}");
    assert!(stdout.contains("Schäfer–Turek 2D-1 (Re 20), 10 cells per diameter") && stdout.contains("| c_D |"), "{stdout}");
    let (code, stdout, err) = diffsim(&["experiment", "cylinder", "--case", "2d-1", "--sweep", "10", "--json"]);
    assert_eq!(code, 0, "{err}");
    let sweep: serde_json::Value = serde_json::from_str(stdout.lines().last().unwrap()).unwrap();
    assert_eq!(sweep["sweep"].as_array().map(Vec::len), Some(1), "{sweep}");
    fails_with(&["experiment", "cylinder", "--case", "2d-2", "--sweep", "10"], "invalid argument --sweep");
    fails_with(&["experiment", "cylinder", "--case", "2d-1", "--sweep", "15"], "invalid argument --sweep");
    fails_with(&["experiment", "cylinder", "--case", "2d-1", "--resolution", "15"], "invalid argument --resolution");
    fails_with(&["experiment", "cylinder", "--case", "2d-2", "--t-end", "1"], "invalid argument --t-end");
}

/// The command line's part of the shape optimisation (the study itself is
/// tested through its report in `studies.rs`): the JSON line, the plots and
/// the history written, the flags' errors, and continuing from the shape a
/// file holds.
#[test]
fn drag_shape_experiment_writes_its_report_and_continues_from_a_file() {
    let out = std::env::temp_dir().join(format!("diffsim-drag-shape-{}", std::process::id()));
    let dir = out.to_str().unwrap();
    let (code, stdout, err) = diffsim(&[
        "experiment",
        "drag-shape",
        "--quick",
        "--modes",
        "4",
        "--max-iterations",
        "2",
        "--sampling-iterations",
        "0",
        "--json",
        "--overwrite",
        "--out",
        dir,
    ]);
    assert_eq!(code, 0, "{err}");
    let last: serde_json::Value = serde_json::from_str(stdout.lines().last().unwrap()).unwrap();
    for key in ["cd_start", "cd_end", "area_start", "area_end", "time_s", "cd_start_fine", "cd_end_fine"] {
        assert!(last[key].as_f64().is_some_and(f64::is_finite), "{key} in {last}");
    }
    assert!(last["iterations"].as_u64().is_some_and(|n| (1..=2).contains(&n)), "{last}");
    let f = |k: &str| last[k].as_f64().unwrap();
    assert!(f("cd_end") < f("cd_start"), "{last}");
    for file in ["drag_shapes.png", "drag_shape_history.png", "drag_shape_history.csv"] {
        assert!(out.join(file).exists(), "{file} not written");
    }
    fails_with(&["experiment", "drag-shape", "--modes", "1"], "invalid argument --modes");
    fails_with(&["experiment", "drag-shape", "--u-max", "2"], "invalid argument --u-max");
    fails_with(&["experiment", "drag-shape", "--re", "50"], "invalid argument --re");
    fails_with(&["experiment", "drag-shape", "--free-stream", "1"], "invalid argument --free-stream");
    // Continuing from the final shape: the start is that shape, its drag the
    // end's (same grid, r₀ recomputed from the area), and the reduction
    // still counts from the cylinder.
    let saved = out.join("end.json");
    std::fs::write(&saved, &stdout).unwrap();
    let (code, again, err) = diffsim(&[
        "experiment",
        "drag-shape",
        "--quick",
        "--modes",
        "4",
        "--max-iterations",
        "0",
        "--sampling-iterations",
        "0",
        "--no-verify",
        "--json",
        "--start-shape",
        saved.to_str().unwrap(),
    ]);
    assert_eq!(code, 0, "{err}");
    let next: serde_json::Value = serde_json::from_str(again.lines().last().unwrap()).unwrap();
    let g = |k: &str| next[k].as_f64().unwrap();
    assert!((g("cd_start") - f("cd_end")).abs() < 1e-8 * f("cd_end"), "{next} after {last}");
    assert!((g("cd_cylinder") - f("cd_start")).abs() < 1e-8 * f("cd_start"), "{next}");
    assert!((g("reduction_pct") - f("reduction_pct")).abs() < 1e-6, "{next}");
    assert!(next["cd_start_fine"].is_null(), "--no-verify still verified: {next}");
    std::fs::write(&saved, "{\"shape\": {\"params\": [0.2, 0.2, 0.05, 0.01, 0.0, 0.0, 0.0]}}").unwrap();
    fails_with(&["experiment", "drag-shape", "--start-shape", saved.to_str().unwrap()], "its mode 1 is not zero");
    std::fs::remove_dir_all(&out).ok();
}

/// The Re ↦ shape network, a few updates on the coarse grid: the training
/// loss falls, and on held-out Reynolds numbers its shapes beat the cylinder.
#[test]
fn drag_net_experiment_trains_through_the_solver() {
    let (code, stdout, err) = diffsim(&["experiment", "drag-net", "--quick", "--iterations", "8", "--json"]);
    assert_eq!(code, 0, "{err}");
    let last: serde_json::Value = serde_json::from_str(stdout.lines().last().unwrap()).unwrap();
    let (start, end) = (last["loss_start"].as_f64().unwrap(), last["loss_end"].as_f64().unwrap());
    assert!(end < start - 0.02, "{last}");
    let held = last["held_out"].as_array().unwrap();
    assert_eq!(held.len(), 2, "{last}");
    for h in held {
        assert!(h["cd_network"].as_f64().unwrap() < h["cd_cylinder"].as_f64().unwrap(), "{h}");
        assert!(h["cd_optimised"].as_f64().unwrap() < h["cd_cylinder"].as_f64().unwrap(), "{h}");
    }
    fails_with(&["experiment", "drag-net", "--lr", "0"], "invalid argument --lr");
}

#[test]
fn hig_oscillators_experiment_runs_and_reports_json() {
    let out = std::env::temp_dir().join(format!("diffsim-hig-{}", std::process::id()));
    let o = out.to_str().unwrap();
    let (code, stdout, err) = diffsim(&["experiment", "hig-oscillators", "--budget", "0.3", "--json", "--overwrite", "--out", o]);
    assert_eq!(code, 0, "{err}");
    let last: serde_json::Value = serde_json::from_str(stdout.lines().last().unwrap()).unwrap();
    for key in [
        "hig",
        "adam",
        "gn",
        "hig_nonlinear",
        "adam_nonlinear",
        "gn_nonlinear",
        "budget_s",
        "hig_s_per_update",
        "adam_s_per_update",
        "hig_nonlinear_s_per_update",
        "adam_nonlinear_s_per_update",
    ] {
        assert!(last[key].as_f64().is_some_and(f64::is_finite), "{key} in {last}");
    }
    assert!(out.join("loss.png").exists() && out.join("table.md").exists());
    fails_with(&["experiment", "hig-oscillators", "--budget", "0", "--overwrite", "--out", o], "invalid argument --budget");
    std::fs::remove_dir_all(&out).ok();
}

#[test]
fn pareto_and_stability_commands_report_json() {
    let out = std::env::temp_dir().join(format!("diffsim-pareto-{}", std::process::id()));
    let o = out.to_str().unwrap();
    // Forward sweep: every configuration with its settings and figures,
    // the front non-empty, all four files written.
    let (code, stdout, err) = diffsim(&["pareto", "burgers", "--quick", "--budget", "0", "--json", "--out", o]);
    assert_eq!(code, 0, "{err}");
    let rows: serde_json::Value = serde_json::from_str(stdout.lines().last().unwrap()).unwrap();
    let rows = rows.as_array().unwrap();
    assert!(rows.len() >= 20, "{} configurations", rows.len());
    for r in rows {
        assert!(r["error"].as_f64().is_some_and(|e| e > 0.0 && e < 0.5), "{r}");
        assert!(r["time_s"].as_f64().is_some_and(|t| t > 0.0) && r["peak_rss_bytes"].as_u64().is_some() && r["pareto"].is_boolean(), "{r}");
        assert!(r["n"].is_u64() && r["advection"].is_string() && r["cfl"].is_f64(), "{r}");
    }
    assert!(rows.iter().any(|r| r["pareto"] == true));
    for f in ["results.csv", "table.md", "error_time.png", "error_time.svg"] {
        assert!(out.join("burgers").join(f).exists(), "{f}");
    }
    // Another sweep's settings into the same folder are refused before
    // anything runs; --overwrite replaces it.
    fails_with(&["pareto", "burgers", "--quick", "--budget", "0.001", "--out", o], "--overwrite");
    assert!(out.join("burgers").join("results.csv").exists());
    // The gradient and cylinder sweeps' figures are tested through their
    // reports (studies.rs); here, what the command refuses.
    fails_with(&["pareto", "heat"], "invalid value 'heat'");
    fails_with(&["pareto", "cylinder", "--gradients"], "no gradient sweep");
    // Stability report.
    let (code, stdout, err) = diffsim(&["stability", "--json"]);
    assert_eq!(code, 0, "{err}");
    let cases: serde_json::Value = serde_json::from_str(stdout.lines().last().unwrap()).unwrap();
    let cases = cases.as_array().unwrap();
    assert!(cases.len() >= 9 && cases.iter().all(|c| c["case"].is_string() && c["passed"] == true), "{cases:?}");
    std::fs::remove_dir_all(&out).ok();
}

/// `bench implicit-heat`: the JSON line of a small run (the gradient
/// makes no forward solve of its own: as many forward CG iterations as the
/// forward run), the comparison with Enzyme through CG, and its flags.
#[test]
fn bench_implicit_heat_json_line() {
    let (code, stdout, err) = diffsim(&["bench", "implicit-heat", "--n", "12", "--steps", "4", "--budget", "0", "--compare", "--json"]);
    assert_eq!(code, 0, "{err}");
    let v: serde_json::Value = serde_json::from_str(stdout.lines().last().unwrap()).unwrap();
    assert_eq!((v["problem"].as_str(), v["n"].as_u64(), v["steps"].as_u64()), (Some("implicit-heat"), Some(12), Some(4)), "{v}");
    assert!(v["grad_over_forward"].as_f64().is_some_and(|r| r > 0.0), "{v}");
    assert_eq!(v["cg_gradient_forward_iterations"], v["cg_forward_iterations"], "{v}");
    assert!(v["cg_adjoint_iterations"].as_u64().is_some_and(|k| k > 0), "{v}");
    let rows = v["compare"].as_array().unwrap();
    assert_eq!(rows.len(), 4);
    // The implicit rule's gradient converges with the tolerance.
    let last = &rows[3];
    assert!(last["implicit_error"].as_f64().unwrap() < 1e-9, "{v}");
    assert!(rows.iter().all(|r| r["through_cg_error"].as_f64().is_some_and(f64::is_finite)), "{v}");
    fails_with(&["bench", "implicit-heat", "--n", "1"], "invalid argument --n");
    fails_with(&["bench", "implicit-heat", "--steps", "0"], "invalid argument --steps");
    fails_with(&["bench", "implicit-heat", "--budget=-1"], "invalid argument --budget");
}

#[test]
fn bench_p3_json_line() {
    let (code, stdout, err) = diffsim(&["bench", "p3", "--iterations", "2", "--threads", "2", "--json"]);
    assert_eq!(code, 0, "{err}");
    let v: serde_json::Value = serde_json::from_str(stdout.lines().last().unwrap()).unwrap();
    assert_eq!(v["problem"], "p3");
    assert_eq!(v["dtype"], "f64");
    assert_eq!((v["threads"].as_u64(), v["params"].as_u64(), v["batch"].as_u64(), v["unroll"].as_u64()), (Some(2), Some(5505), Some(32), Some(16)));
    assert!(v["s_per_iter"].as_f64().is_some_and(|s| s > 0.0));
    let mut total = 0.0;
    for key in ["solver_fwd", "solver_bwd", "net_fwd", "net_bwd", "optimizer"] {
        let share = v[key].as_f64().unwrap_or(-1.0);
        assert!((0.0..=1.0).contains(&share), "{key} = {share}");
        total += share;
    }
    assert!(total <= 1.0 + 1e-9 && total > 0.5, "shares sum to {total}");
    fails_with(&["bench", "p3", "--dtype", "f16"], "invalid argument --dtype");
    fails_with(&["bench", "p3", "--iterations", "0"], "invalid argument --iterations");
}

/// A fresh temporary folder under the target directory.
pub(crate) fn scratch_dir(name: &str) -> std::path::PathBuf {
    let dir = std::path::Path::new(env!("CARGO_TARGET_TMPDIR")).join(name);
    let _ = std::fs::remove_dir_all(&dir);
    dir
}

#[test]
fn new_writes_a_crate_with_its_names_the_toolchain_and_the_guard() {
    let dir = scratch_dir("new-crate");
    let (code, out, err) = diffsim(&["new", dir.to_str().unwrap(), "--name", "heat-fit"]);
    assert_eq!(code, 0, "{err}");
    assert!(out.contains("cargo run --release"), "{out}");
    let read = |f: &str| std::fs::read_to_string(dir.join(f)).unwrap_or_else(|e| panic!("{f}: {e}"));
    let root = read("Cargo.toml");
    assert!(root.contains("name = \"heat-fit\"") && root.contains("heat-fit-solver = { path = \"solver\" }"), "{root}");
    assert!(root.contains("[profile.release.package.heat-fit-solver]") && root.contains("[profile.release.package.heat-fit-run]"), "{root}");
    assert!(!root.contains("starter"), "{root}");
    let checkout = std::fs::canonicalize(env!("CARGO_MANIFEST_DIR")).unwrap();
    assert!(root.contains(&format!("diffsim = {{ path = \"{}\" }}", checkout.display())), "{root}");
    assert!(read("src/lib.rs").contains("use heat_fit_solver::{"));
    assert!(read("run/src/main.rs").contains("heat_fit::main()"));
    assert!(read("run/tests/checks.rs").contains("heat_fit::run().unwrap()"));
    assert!(read("run/Cargo.toml").contains("name = \"heat-fit\""));
    assert_eq!(read("rust-toolchain.toml"), std::fs::read_to_string(checkout.join("rust-toolchain.toml")).unwrap());
    let guard = read("cargo-enzyme");
    assert!(guard.contains(&format!("pitfalls=\"{}/docs/pitfalls.md\"", checkout.display())), "the guard's pitfalls line was not replaced");
    let config = read(".cargo/config.toml");
    assert!(config.contains(&format!("target-dir = \"{}/target\"", checkout.display())), "{config}");
    assert!(config.contains(&format!("rustc-wrapper = \"{}/scripts/rustc-guard\"", checkout.display())), "{config}");
    assert!(checkout.join("scripts/rustc-guard").is_file());
    // Not over an existing crate.
    fails_with(&["new", dir.to_str().unwrap()], "exists and is not an empty folder");
}

/// `--template implicit` writes the implicit step's crate (its physics a
/// right-hand side for the integrator), its names replaced; an unknown
/// template is refused with the choices.
#[test]
fn new_writes_the_implicit_template() {
    let dir = scratch_dir("new-implicit");
    let (code, _, err) = diffsim(&["new", dir.to_str().unwrap(), "--name", "cool-down", "--template", "implicit"]);
    assert_eq!(code, 0, "{err}");
    let read = |f: &str| std::fs::read_to_string(dir.join(f)).unwrap_or_else(|e| panic!("{f}: {e}"));
    let solver = read("solver/src/lib.rs");
    assert!(solver.contains("diffsim::ode_system!(Heat => heat_rate);"), "{solver}");
    assert!(read("src/lib.rs").contains("use cool_down_solver::{Heat, step};"));
    assert!(read("run/tests/checks.rs").contains("cool_down::run().unwrap()"));
    assert!(!read("Cargo.toml").contains("starter"));
    let (code, _, err) = diffsim(&["new", scratch_dir("new-unknown").to_str().unwrap(), "--template", "explicitly"]);
    assert_ne!(code, 0);
    assert!(err.contains("starter") && err.contains("implicit"), "{err}");
}

#[test]
fn new_rejects_bad_names_with_a_message() {
    let dir = scratch_dir("Bad Name");
    fails_with(&["new", dir.to_str().unwrap()], "is not a package name");
    fails_with(&["new", scratch_dir("x").to_str().unwrap(), "--name", "diffsim"], "clashes");
    fails_with(&["new", scratch_dir("y").to_str().unwrap(), "--name", "9lives"], "is not a package name");
    fails_with(&["new", scratch_dir("z").to_str().unwrap(), "--diffsim", "/nonexistent/diffsim"], "cannot find the diffsim checkout");
    assert!(!scratch_dir("x").exists());
}

/// Runs the build guard on a saved log; returns (exit code, stderr).
fn guard_on(log_text: &str, name: &str) -> (i32, String) {
    let log = scratch_dir(name).with_extension("log");
    std::fs::write(&log, log_text).unwrap();
    let out = Command::new(concat!(env!("CARGO_MANIFEST_DIR"), "/scripts/cargo-enzyme")).arg("--check-log").arg(&log).output().unwrap();
    (out.status.code().unwrap_or(-1), String::from_utf8_lossy(&out.stderr).into())
}

#[test]
fn the_guard_explains_the_failures_it_knows() {
    let abort = "inserting into : {[0]:Pointer, [0,-1]:Pointer} with [0,-1] of Integer\nillegal insertion\nUNREACHABLE executed at /checkout/src/tools/enzyme/enzyme/Enzyme/TypeAnalysis/TypeTree.h:330!\nerror: could not compile `single` (bin \"single\")\n\nCaused by:\n  process didn't exit successfully: `/x/rustc --crate-name single --edition=2024 single/src/main.rs -Zautodiff=Enable` (signal: 6, SIGABRT: process abort signal)\n";
    let (_, err) = guard_on(abort, "guard-typetree");
    assert!(err.contains("Enzyme's type analysis") && err.contains("crate 'single'") && err.contains("docs/pitfalls.md"), "{err}");
    let (_, err) =
        guard_on("error: process didn't exit successfully: `/x/rustc --crate-name foo` (signal: 11, SIGSEGV: invalid memory reference)\n", "guard-signal");
    assert!(err.contains("killed by a signal while compiling crate 'foo'"), "{err}");
    let (_, err) = guard_on("error: using the autodiff feature requires -Z autodiff=Enable\n", "guard-flag");
    assert!(err.contains("[profile.release.package.NAME]"), "{err}");
    let (_, err) = guard_on("error: using the autodiff feature requires setting `lto=\"fat\"` in your Cargo.toml\n", "guard-lto");
    assert!(err.contains("lto = \"fat\""), "{err}");
    let (_, err) = guard_on("rust-lld: error: undefined symbol: __enzyme_autodiff_RNvNvCs_6solver\n", "guard-unflagged");
    assert!(err.contains("final binary was linked without the autodiff flag"), "{err}");
    // An Enzyme error line fails the check (the gradient would be wrong).
    let (code, err) = guard_on("error: <unknown>:0:0: in function f: Enzyme: Cannot deduce type of memset\n", "guard-error");
    assert_ne!(code, 0, "{err}");
    let (code, err) = guard_on("   Compiling foo v0.1.0\n    Finished `release` profile\n", "guard-clean");
    assert_eq!((code, err.as_str()), (0, ""));
}

/// Runs the rustc wrapper with `echo` standing in for rustc; returns (exit
/// code, stdout, stderr). Each call gets its own TMPDIR (the wrapper says
/// its message once per parent process, marked there).
fn release_guard(args: &[&str], allow_debug: bool) -> (i32, String, String) {
    let tmp = scratch_dir(&format!("guard-tmp-{}", args.join("").len()));
    std::fs::create_dir_all(&tmp).unwrap();
    let mut cmd = Command::new(concat!(env!("CARGO_MANIFEST_DIR"), "/scripts/rustc-guard"));
    cmd.arg("echo").args(args).env("TMPDIR", &tmp).env_remove("DIFFSIM_ALLOW_DEBUG");
    if allow_debug {
        cmd.env("DIFFSIM_ALLOW_DEBUG", "1");
    }
    let out = cmd.output().unwrap();
    (out.status.code().unwrap_or(-1), String::from_utf8_lossy(&out.stdout).into(), String::from_utf8_lossy(&out.stderr).into())
}

#[test]
fn the_rustc_wrapper_stops_debug_builds_only() {
    // A debug build's crate (both cargo layouts): stopped, with the message.
    let (code, out, err) = release_guard(&["--emit=dep-info,metadata,link", "-C", "debuginfo=2", "--out-dir", "/p/target/debug/deps"], false);
    assert_eq!(code, 1, "{out}");
    assert!(out.is_empty() && err.contains("diffsim needs a release build") && err.contains("cargo build --release"), "{err}");
    let (code, _, err) = release_guard(&["--emit=dep-info,link", "-C", "debuginfo=1", "--out-dir", "/p/target/debug/build/foo/0123/out"], false);
    assert_eq!(code, 1, "{err}");
    // A check (metadata only), what a check builds for the host (build
    // scripts, proc macros: no debug info), a release build, cargo's
    // queries: rustc runs unchanged.
    let (code, out, _) = release_guard(&["--emit=dep-info,metadata,link", "--out-dir", "/p/target/debug/build/autocfg/0123/out"], false);
    assert_eq!((code, out.trim()), (0, "--emit=dep-info,metadata,link --out-dir /p/target/debug/build/autocfg/0123/out"));
    let (code, out, _) = release_guard(&["--emit=dep-info,metadata", "--out-dir", "/p/target/debug/deps"], false);
    assert_eq!((code, out.trim()), (0, "--emit=dep-info,metadata --out-dir /p/target/debug/deps"));
    let (code, out, _) = release_guard(&["--emit=dep-info,metadata,link", "--out-dir", "/p/target/release/build/foo/0123/out"], false);
    assert_eq!((code, out.trim()), (0, "--emit=dep-info,metadata,link --out-dir /p/target/release/build/foo/0123/out"));
    let (code, out, _) = release_guard(&["-vV"], false);
    assert_eq!((code, out.trim()), (0, "-vV"));
    // The way out it names.
    let (code, _, _) = release_guard(&["--emit=link", "-C", "debuginfo=2", "--out-dir", "/p/target/debug/deps"], true);
    assert_eq!(code, 0);
}

#[test]
fn the_rustc_wrapper_explains_a_compiler_killed_by_a_signal() {
    use std::os::unix::process::ExitStatusExt;
    // A stand-in for rustc that dies of SIGABRT, as rustc does when Enzyme's
    // type analysis aborts.
    let out = Command::new(concat!(env!("CARGO_MANIFEST_DIR"), "/scripts/rustc-guard"))
        .args(["sh", "-c", "kill -ABRT $$", "--crate-name", "my_solver_solver", "--emit=link", "--out-dir", "/p/target/release/deps"])
        .output()
        .unwrap();
    let err = String::from_utf8_lossy(&out.stderr);
    assert!(err.contains("killed by signal 6 while compiling crate 'my_solver_solver'") && err.contains("docs/pitfalls.md"), "{err}");
    // It dies of the same signal, so that cargo reports it as before.
    assert_eq!(out.status.signal(), Some(6), "{:?}", out.status);
}

#[test]
fn three_d_scenes_run_draw_and_check_their_gradient() {
    let out = std::env::temp_dir().join(format!("diffsim-scene3d-{}", std::process::id()));
    let o = out.to_str().unwrap();
    let (code, _, err) = diffsim(&["run", "tests/scenes_moving/moving3d.toml", "--out", o, "--quiet", "--slice", "x=2", "--mip", "y"]);
    assert_eq!(code, 0, "{err}");
    for f in ["smoke.npy", "velocity_u.npy", "velocity_v.npy", "velocity_w.npy", "smoke_slice_x2.png", "smoke_mip_y.png"] {
        assert!(out.join(f).exists(), "{f} missing");
    }
    // The volume in numpy order [z, y, x], and the slice as a PNG of (z, y).
    let bytes = std::fs::read(out.join("smoke.npy")).unwrap();
    assert!(diffsim::scene::npy_values(&bytes, &[8, 10, 8]).is_ok());
    let png = png::Decoder::new(std::io::BufReader::new(std::fs::File::open(out.join("smoke_slice_x2.png")).unwrap())).read_info().unwrap();
    assert_eq!((png.info().width, png.info().height), (8 * 4, 10 * 4));
    fails_with(&["run", "tests/scenes_moving/moving3d.toml", "--out", o, "--slice", "y=10"], "index 10 is past the 10 cells along y");
    fails_with(&["run", "tests/scenes_moving/moving3d.toml", "--out", o, "--mip", "w"], "expected an axis x, y or z");
    // From a moving state every check passes.
    let (code, stdout, err) = diffsim(&["grad", "tests/scenes_moving/moving3d.toml", "--out", o, "--check"]);
    assert_eq!(code, 0, "{stdout}\n{err}");
    assert_eq!(stdout.matches("→ pass").count(), 3, "{stdout}");
    for f in ["grad_smoke_init.npy", "grad_velocity_init_w.npy", "grad_buoyancy_coefficient.npy"] {
        assert!(out.join(f).exists(), "{f} missing");
    }
    // A 3D channel (inflow, outflow, periodic z, a sphere) passes too.
    let (code, stdout, err) = diffsim(&["grad", "tests/scenes_moving/channel3d.toml", "--out", o, "--check", "--overwrite"]);
    assert_eq!(code, 0, "{stdout}\n{err}");
    assert_eq!(stdout.matches("→ pass").count(), 3, "{stdout}");
    // A 2D scene from a moving state passes too (the faces the closed
    // sides set are no kink of the step).
    let (code, stdout, err) = diffsim(&["grad", "tests/scenes_moving/moving2d.toml", "--out", o, "--check", "--overwrite"]);
    assert_eq!(code, 0, "{stdout}\n{err}");
    assert_eq!(stdout.matches("→ pass").count(), 3, "{stdout}");
    // From rest (2D here) the rollout kinks: inconclusive, said so, no failure.
    let (code, stdout, err) = diffsim(&["grad", "scenes/smoke_obstacle.toml", "--out", o, "--check", "--overwrite"]);
    assert_eq!(code, 0, "{stdout}\n{err}");
    assert!(!stdout.contains("FAIL"), "{stdout}");
    assert!(stdout.contains("inconclusive (kink)") && stdout.contains("note: the rollout has a kink"), "{stdout}");
}
