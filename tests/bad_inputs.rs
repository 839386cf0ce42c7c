//! The second probe's cases (issue 49) that run in seconds, kept fixed: a
//! bad input is one clear error naming what and where, a wrong result is
//! never reported, and no command writes outside its folder or over an
//! input. The slow and the signal cases are `scripts/probe`'s.

use std::path::{Path, PathBuf};
use std::process::{Command, Stdio};

use crate::cli::diffsim;

fn scratch(name: &str) -> PathBuf {
    let dir = std::env::temp_dir().join(format!("diffsim-bad-{name}-{}", std::process::id()));
    std::fs::remove_dir_all(&dir).ok();
    std::fs::create_dir_all(&dir).unwrap();
    dir
}

/// Fails with one `error:` line holding `needle`, no panic.
#[track_caller]
fn refused(args: &[&str], needle: &str) -> String {
    let (code, _, err) = diffsim(args);
    assert_ne!(code, 0, "{args:?} should fail");
    assert!(!err.contains("panicked"), "{args:?}: {err}");
    let lines: Vec<&str> = err.lines().filter(|l| l.starts_with("error")).collect();
    assert_eq!(lines.len(), 1, "{args:?}: {err}");
    assert!(lines[0].contains(needle), "{args:?}: expected `{needle}` in {err}");
    lines[0].to_string()
}

const SCENE: &str = "[domain]\nsize = [16, 16]\nboundary = \"closed\"\n[time]\ndt = 1.0\nsteps = 2\n\
    [fields.smoke]\ninit = SMOKE\n[fields.velocity]\ninit = \"zero\"\n\
    [[effects]]\nkind = \"buoyancy\"\ncoefficient = 0.1\n[[effects]]\nkind = \"advection\"\nscheme = \"semi_lagrangian\"\n\
    [[effects]]\nkind = \"pressure\"\n";

/// Smoke of `value` in a box, diffusing (implicitly: finite at any
/// magnitude), with a loss against zero.
fn diffusing(value: &str) -> String {
    format!(
        "[domain]\nsize = [16, 16]\nboundary = \"closed\"\n[time]\ndt = 1.0\nsteps = 2\n[fields.smoke]\n\
         init = {{ box = {{ lower = [4.0, 2.0], upper = [8.0, 6.0], value = {value} }} }}\n\
         [[effects]]\nkind = \"diffusion\"\nfields = [\"smoke\"]\nviscosity = 0.1\nscheme = \"implicit\"\n\
         [loss]\nfield = \"smoke\"\ntarget = \"zero\"\nwith_respect_to = [\"smoke.init\"]\n"
    )
}

fn scene(dir: &Path, smoke: &str) -> PathBuf {
    let path = dir.join("s.toml");
    std::fs::write(&path, SCENE.replace("SMOKE", smoke)).unwrap();
    path
}

#[test]
fn sizes_whose_buffers_overflow_are_refused_before_allocating() {
    refused(&["check", "--n", "2305843009213693952"], "check");
    refused(&["check", "--n", "18446744073709551615", "--steps", "1"], "check");
    refused(&["check", "--n", "16", "--steps", "4611686018427387904"], "invalid argument --steps");
}

#[test]
fn negative_numbers_are_values_of_their_option() {
    refused(&["check", "--n", "-1"], "'--n <N>'");
    refused(&["experiment", "cavity", "--re", "-1"], "invalid argument --re");
    refused(&["experiment", "drag-shape", "--re", "-5"], "invalid argument --re");
}

#[test]
fn experiments_refuse_flags_outside_their_method() {
    refused(&["experiment", "cavity", "--re", "1e15"], "where the cavity's flow is steady");
    refused(&["experiment", "cavity", "--re", "nan"], "invalid argument --re");
    refused(&["experiment", "drag-shape", "--re", "1e-300"], "invalid argument --re");
    refused(&["experiment", "drag-shape", "--u-max", "1e-300"], "invalid argument --u-max");
}

#[test]
fn new_refuses_keywords_and_folders_that_are_not_diffsim() {
    let dir = scratch("new");
    refused(&["new", dir.join("a").to_str().unwrap(), "--name", "fn"], "Rust keyword");
    refused(&["new", dir.join("b").to_str().unwrap(), "--name", "async"], "Rust keyword");
    let fake = dir.join("fake");
    std::fs::create_dir_all(fake.join("src")).unwrap();
    std::fs::write(fake.join("Cargo.toml"), "[package]\nname = \"other\"\n").unwrap();
    std::fs::write(fake.join("src/lib.rs"), "").unwrap();
    refused(&["new", dir.join("c").to_str().unwrap(), "--diffsim", fake.to_str().unwrap()], "names the package `other`");
    assert!(!dir.join("c").exists());
    std::fs::remove_dir_all(&dir).ok();
}

#[test]
fn info_prints_no_nul_byte() {
    let (code, out, err) = diffsim(&["info"]);
    assert_eq!(code, 0, "{err}");
    assert!(!out.contains('\0'), "{out:?}");
}

/// `DIFFSIM_MAX_ISA` caps the vector instructions (`info` says which run);
/// a value that names none is refused before any work.
#[test]
fn the_vector_cap_is_reported_and_a_bad_one_refused() {
    let run = |isa: &str, args: &[&str]| {
        let out = Command::new(crate::diffsim_bin()).args(args).env("DIFFSIM_MAX_ISA", isa).output().unwrap();
        (out.status.code(), String::from_utf8_lossy(&out.stdout).into_owned(), String::from_utf8_lossy(&out.stderr).into_owned())
    };
    let (code, out, err) = run("baseline", &["info"]);
    assert_eq!(code, Some(0), "{err}");
    assert!(out.contains("vector instructions: baseline (capped by DIFFSIM_MAX_ISA)"), "{out}");
    let (code, out, err) = run("sse9", &["check", "--n", "8", "--steps", "2"]);
    assert_eq!(code, Some(1), "{out}");
    assert!(out.is_empty() && err.contains("DIFFSIM_MAX_ISA=\"sse9\": expected avx512, avx2 or baseline") && !err.contains("panicked"), "{err}");
    // The same check under the cap gives the same numbers as without it.
    let (code, capped, err) = run("baseline", &["check", "--n", "8", "--steps", "2"]);
    assert_eq!(code, Some(0), "{err}");
    let (code, plain, err) = diffsim(&["check", "--n", "8", "--steps", "2"]);
    assert_eq!(code, 0, "{err}");
    assert_eq!(capped, plain);
}

#[test]
fn output_that_cannot_be_written_is_an_error_and_a_closed_pipe_ends_quietly() {
    let full = std::fs::OpenOptions::new().write(true).open("/dev/full").unwrap();
    let out = Command::new(crate::diffsim_bin()).args(["check", "--n", "8", "--steps", "2"]).stdout(full).output().unwrap();
    let err = String::from_utf8_lossy(&out.stderr);
    assert_eq!(out.status.code(), Some(1), "{err}");
    assert!(err.contains("error: cannot write the output: No space left on device") && !err.contains("panicked"), "{err}");
    // A reader that closes at once: the command ends (by SIGPIPE) without a word.
    let mut child =
        Command::new(crate::diffsim_bin()).args(["check", "--n", "8", "--steps", "2"]).stdout(Stdio::piped()).stderr(Stdio::piped()).spawn().unwrap();
    drop(child.stdout.take());
    let out = child.wait_with_output().unwrap();
    let err = String::from_utf8_lossy(&out.stderr);
    assert!(!err.contains("panicked") && !err.contains("error"), "{err}");
}

#[test]
fn outputs_never_go_through_a_planted_link_or_over_an_input() {
    let dir = scratch("links");
    let s = scene(&dir, "{ box = { lower = [4.0, 2.0], upper = [8.0, 6.0], value = 1.0 } }");
    let outside = dir.join("precious.npy");
    std::fs::write(&outside, "keep me").unwrap();
    let out = dir.join("o");
    std::fs::create_dir_all(&out).unwrap();
    std::os::unix::fs::symlink(&outside, out.join("smoke.npy")).unwrap();
    // A folder holding a link it did not write is another's: refused, then
    // with --overwrite the link is replaced, not written through.
    refused(&["run", s.to_str().unwrap(), "--out", out.to_str().unwrap(), "--quiet"], "--overwrite");
    let (code, _, err) = diffsim(&["run", s.to_str().unwrap(), "--out", out.to_str().unwrap(), "--quiet", "--overwrite"]);
    assert_eq!(code, 0, "{err}");
    assert_eq!(std::fs::read(&outside).unwrap(), b"keep me");
    assert!(!std::fs::symlink_metadata(out.join("smoke.npy")).unwrap().file_type().is_symlink());
    // --out as a dangling link, and as a loop.
    std::os::unix::fs::symlink(dir.join("nowhere"), dir.join("dangling")).unwrap();
    refused(&["run", s.to_str().unwrap(), "--out", dir.join("dangling").to_str().unwrap()], "which does not exist");
    std::os::unix::fs::symlink(dir.join("loop"), dir.join("loop")).unwrap();
    refused(&["run", s.to_str().unwrap(), "--out", dir.join("loop").to_str().unwrap()], "loops back on itself");
    // The scene's own folder: its .npy input is never written over, even
    // with --overwrite.
    let input = dir.join("in");
    std::fs::create_dir_all(&input).unwrap();
    let mut npy = Vec::new();
    {
        use npyz::WriterBuilder;
        let mut w = npyz::WriteOptions::new().default_dtype().shape(&[16, 16]).writer(&mut npy).begin_nd().unwrap();
        w.extend(vec![0.25f64; 256]).unwrap();
        w.finish().unwrap();
    }
    std::fs::write(input.join("smoke.npy"), &npy).unwrap();
    let s2 = input.join("s.toml");
    std::fs::write(&s2, SCENE.replace("SMOKE", "{ npy = \"smoke.npy\" }")).unwrap();
    refused(&["run", s2.to_str().unwrap(), "--out", input.to_str().unwrap(), "--overwrite"], "would overwrite the input");
    assert_eq!(std::fs::read(input.join("smoke.npy")).unwrap(), npy);
    std::fs::remove_dir_all(&dir).ok();
}

#[test]
fn a_folder_holds_one_run_at_a_time() {
    let dir = scratch("claims");
    let a = scene(&dir, "\"zero\"");
    let b = dir.join("b.toml");
    std::fs::write(&b, SCENE.replace("SMOKE", "\"zero\"").replace("steps = 2", "steps = 3")).unwrap();
    let out = dir.join("o");
    let o = out.to_str().unwrap();
    let (code, _, err) = diffsim(&["run", a.to_str().unwrap(), "--out", o, "--quiet"]);
    assert_eq!(code, 0, "{err}");
    // The same run again replaces its own results; another is refused.
    let (code, _, err) = diffsim(&["run", a.to_str().unwrap(), "--out", o, "--quiet"]);
    assert_eq!(code, 0, "{err}");
    refused(&["run", b.to_str().unwrap(), "--out", o, "--quiet"], "holds the results of another run");
    refused(&["sweep", b.to_str().unwrap(), "--set", "time.steps=2,3", "--out", o, "--quiet"], "holds the results of another run");
    // While a command holds the folder's lock, a second one is refused.
    let lock = std::fs::OpenOptions::new().read(true).write(true).open(out.join(".diffsim.lock")).unwrap();
    lock.lock().unwrap();
    refused(&["run", a.to_str().unwrap(), "--out", o, "--quiet"], "another diffsim command is writing into this folder");
    lock.unlock().unwrap();
    // --overwrite replaces the other run's files: none stays beside.
    let (code, _, err) = diffsim(&["sweep", b.to_str().unwrap(), "--set", "time.steps=2,3", "--out", o, "--quiet", "--overwrite"]);
    assert_eq!(code, 0, "{err}");
    assert!(!out.join("smoke.npy").exists() && out.join("run-0001").is_dir() && out.join("runs.csv").exists());
    std::fs::remove_dir_all(&dir).ok();
}

#[test]
fn sweeps_refuse_a_key_twice_cite_the_users_file_and_table_non_finite_figures() {
    let dir = scratch("sweep");
    let s = scene(&dir, "\"zero\"");
    let o = dir.join("o");
    let (sp, op) = (s.to_str().unwrap(), o.to_str().unwrap());
    refused(&["sweep", sp, "--set", "time.steps=2", "--set", "time.steps=3", "--out", op], "`time.steps` is given twice");
    let err = refused(&["sweep", sp, "--set", "time.dt=1,-1", "--out", op], "with time.dt=-1");
    assert!(err.contains(sp) && !err.contains("line "), "{err}");
    // A loss that overflows (finite fields of 1e200) is that run's error in
    // the table, not a crash.
    let t = dir.join("t.toml");
    let text = diffusing("1.0");
    std::fs::write(&t, text).unwrap();
    let (code, _, err) = diffsim(&["sweep", t.to_str().unwrap(), "--set", "fields.smoke.init.box.value=1.0,1e200", "--out", op, "--quiet", "--overwrite"]);
    assert_ne!(code, 0, "{err}");
    assert!(!err.contains("panicked") && err.contains("1 of 2 runs failed"), "{err}");
    let csv = std::fs::read_to_string(o.join("runs.csv")).unwrap();
    assert!(csv.contains("the loss came out inf"), "{csv}");
    std::fs::remove_dir_all(&dir).ok();
}

#[test]
fn a_gradient_or_loss_that_overflows_is_not_reported() {
    let dir = scratch("grad");
    let t = dir.join("t.toml");
    let text = diffusing("1e200");
    std::fs::write(&t, text).unwrap();
    // Every state is finite (1e200), the loss (their squares) is not.
    refused(&["grad", t.to_str().unwrap(), "--out", dir.join("o").to_str().unwrap()], "the loss is not finite (inf) though every state of the rollout is");
    assert!(!dir.join("o").join("grad_smoke_init.npy").exists());
    std::fs::remove_dir_all(&dir).ok();
}

#[test]
fn training_counts_and_checkpoints_are_checked_before_anything_is_written() {
    let dir = scratch("train");
    let o = dir.join("o");
    let op = o.to_str().unwrap();
    let (code, _, err) = diffsim(&["train", "tests/configs/tiny_sol.toml", "--out", op, "--quiet", "--until", "3"]);
    assert_eq!(code, 0, "{err}");
    let log = std::fs::read(o.join("loss.csv")).unwrap();
    let ckpt = std::fs::read(o.join("checkpoint.json")).unwrap();
    refused(&["train", "tests/configs/tiny_sol.toml", "--out", op, "--quiet", "--extend", "0"], "invalid argument --extend");
    refused(&["train", "tests/configs/tiny_sol.toml", "--out", op, "--quiet", "--extend", "18446744073709551615"], "past the most a run may have");
    assert_eq!(std::fs::read(o.join("loss.csv")).unwrap(), log);
    assert_eq!(std::fs::read(o.join("checkpoint.json")).unwrap(), ckpt);
    // A checkpoint whose iteration count disagrees with its optimizer's steps.
    let mut v: serde_json::Value = serde_json::from_slice(&ckpt).unwrap();
    v["iterations_done"] = serde_json::json!(v["iterations_done"].as_u64().unwrap() + 1);
    std::fs::write(o.join("checkpoint.json"), v.to_string()).unwrap();
    refused(&["train", "tests/configs/tiny_sol.toml", "--out", op, "--quiet", "--resume"], "the file was altered");
    std::fs::remove_dir_all(&dir).ok();
}

#[test]
fn options_that_do_not_apply_and_requests_past_any_patience_are_refused() {
    refused(&["experiment", "cylinder", "--case", "2d-1", "--t-end", "5"], "--t-end: applies to case 2d-2 only");
    refused(&["experiment", "cylinder", "--case", "2d-1", "--tolerance", "1e300"], "--tolerance: applies to case 2d-1 with --solver march only");
    refused(&["experiment", "cylinder", "--case", "2d-2", "--t-end", "1e300"], "invalid argument --t-end");
    refused(&["experiment", "cavity", "--max-steps", "18446744073709551615"], "invalid argument --max-steps");
    refused(&["experiment", "hig-oscillators", "--budget", "1e300"], "invalid argument --budget");
    refused(&["--memory-budget", "50MB", "experiment", "cavity", "--resolution", "2048"], "more than the memory budget of 50.0 MB");
    refused(&["--memory-budget", "50MB", "experiment", "cylinder", "--case", "2d-1"], "more than the memory budget of 50.0 MB");
    refused(&["--memory-budget", "50MB", "experiment", "drag-shape"], "--no-verify");
    let dir = scratch("views");
    let s = scene(&dir, "\"zero\"");
    refused(&["run", s.to_str().unwrap(), "--out", dir.join("o").to_str().unwrap(), "--slice", "z=1"], "--slice: applies to 3D scenes only; this scene is 2D");
    refused(&["run", "scenes/drag_body.toml", "--out", dir.join("o2").to_str().unwrap(), "--every", "5"], "--every: does not apply to a steady scene");
    std::fs::remove_dir_all(&dir).ok();
}

#[test]
fn an_experiments_folder_is_its_own() {
    let dir = scratch("experiment-out");
    let o = dir.join("o");
    std::fs::create_dir_all(&o).unwrap();
    std::fs::write(o.join("notes.txt"), "mine").unwrap();
    let op = o.to_str().unwrap();
    let cavity = ["experiment", "cavity", "--re", "100", "--resolution", "16", "--json", "--out", op];
    refused(&cavity, "holds files that no diffsim run wrote (notes.txt)");
    let mut again: Vec<&str> = cavity.to_vec();
    again.push("--overwrite");
    let (code, _, err) = diffsim(&again);
    assert_eq!(code, 0, "{err}");
    assert_eq!(std::fs::read_to_string(o.join("notes.txt")).unwrap(), "mine", "--overwrite keeps the user's files");
    // The same experiment again writes beside its results; another is refused.
    let (code, _, err) = diffsim(&cavity);
    assert_eq!(code, 0, "{err}");
    refused(
        &["experiment", "cavity", "--re", "400", "--resolution", "16", "--json", "--out", op],
        "holds the results of another run (`diffsim experiment cavity --re 100",
    );
    std::fs::remove_dir_all(&dir).ok();
}
