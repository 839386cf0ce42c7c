//! Training that survives a kill: a run killed (SIGKILL) at several moments
//! and resumed each time ends with the uninterrupted run's `model.json`,
//! byte for byte; SIGTERM writes a checkpoint and says how to resume; a
//! folder holding another run is not overwritten; a checkpoint that is
//! truncated, corrupt, of another configuration or with optimizer state of
//! the wrong length is refused with what is wrong.

use std::path::{Path, PathBuf};
use std::process::{Command, Stdio};
use std::time::{Duration, Instant};

const CONFIG: &str = "tests/configs/tiny_sol.toml";

fn scratch(name: &str) -> PathBuf {
    let dir = std::env::temp_dir().join(format!("diffsim-resume-{name}-{}", std::process::id()));
    std::fs::remove_dir_all(&dir).ok();
    dir
}

fn train(out: &Path, extra: &[&str]) -> Command {
    let mut c = Command::new(crate::diffsim_bin());
    c.args(["train", CONFIG, "--out", out.to_str().unwrap(), "--quiet", "--checkpoint-every", "7"]).args(extra);
    c
}

fn run(out: &Path, extra: &[&str]) -> (i32, String) {
    let o = train(out, extra).output().unwrap();
    (o.status.code().unwrap_or(-1), String::from_utf8_lossy(&o.stderr).into())
}

fn iterations_done(out: &Path) -> u64 {
    let text = std::fs::read_to_string(out.join("checkpoint.json")).unwrap();
    let v: serde_json::Value = serde_json::from_str(&text).unwrap();
    v["iterations_done"].as_u64().unwrap()
}

/// Spawns the run and kills it with `signal` after `delay` unless it ends
/// first; returns its exit status and stderr.
fn run_until(out: &Path, extra: &[&str], delay: Duration, signal: &str) -> (Option<i32>, String) {
    let mut child = train(out, extra).stdout(Stdio::null()).stderr(Stdio::piped()).spawn().unwrap();
    let start = Instant::now();
    while start.elapsed() < delay {
        if child.try_wait().unwrap().is_some() {
            break;
        }
        std::thread::sleep(Duration::from_millis(10));
    }
    if child.try_wait().unwrap().is_none() {
        Command::new("kill").args([signal, &child.id().to_string()]).status().unwrap();
    }
    let o = child.wait_with_output().unwrap();
    (o.status.code(), String::from_utf8_lossy(&o.stderr).into())
}

#[test]
fn a_killed_run_resumed_ends_bit_identical() {
    let (whole, cut) = (scratch("whole"), scratch("cut"));
    let (code, err) = run(&whole, &[]);
    assert_eq!(code, 0, "{err}");
    // Killed at several moments, resumed each time.
    let mut kills_mid_run = 0;
    let mut attempt = 0;
    loop {
        let extra: &[&str] = if attempt == 0 { &[] } else { &["--resume"] };
        let delay = [900u64, 500, 700, 400, 800].get(attempt).map_or(Duration::from_secs(600), |&ms| Duration::from_millis(ms));
        let (code, err) = run_until(&cut, extra, delay, "-KILL");
        if code == Some(0) {
            break;
        }
        assert_eq!(code, None, "killed runs die by the signal: {err}");
        let done = iterations_done(&cut);
        if done > 0 && done < 4000 {
            kills_mid_run += 1;
        }
        attempt += 1;
        assert!(attempt < 20, "the run never finished");
    }
    assert!(kills_mid_run >= 2, "only {kills_mid_run} kills landed during training");
    let read = |d: &Path, f: &str| std::fs::read(d.join(f)).unwrap();
    assert!(read(&whole, "model.json") == read(&cut, "model.json"), "model.json differs after {attempt} kills");
    // The log holds each iteration once, in order.
    let log = String::from_utf8(read(&cut, "loss.csv")).unwrap();
    let its: Vec<u64> = log.lines().skip(1).map(|l| l.split(',').next().unwrap().parse().unwrap()).collect();
    assert_eq!(its, (1..=4000).collect::<Vec<_>>());
    // A finished folder is not overwritten by a fresh run.
    let (code, err) = run(&whole, &[]);
    assert!(code == 1 && err.contains("holds a run of this configuration (4000 iterations done)") && err.contains("--overwrite"), "{err}");
    std::fs::remove_dir_all(&whole).ok();
    std::fs::remove_dir_all(&cut).ok();
}

#[test]
fn sigterm_checkpoints_and_says_how_to_resume_and_bad_checkpoints_are_refused() {
    let out = scratch("term");
    let (code, err) = run_until(&out, &[], Duration::from_millis(1200), "-TERM");
    assert_eq!(code, Some(130), "{err}");
    assert!(err.contains("interrupted after iteration") && err.contains("--resume"), "{err}");
    let done = iterations_done(&out);
    assert!(done > 0 && err.contains(&format!("iteration {done} of 4000")), "{done}: {err}");
    let ckpt = out.join("checkpoint.json");
    let good = std::fs::read_to_string(&ckpt).unwrap();
    // Another configuration: the key that differs, both values.
    let other = out.join("other.toml");
    std::fs::write(&other, std::fs::read_to_string(CONFIG).unwrap().replace("lr = 1e-3", "lr = 2e-3")).unwrap();
    let o = Command::new(crate::diffsim_bin()).args(["train", other.to_str().unwrap(), "--out", out.to_str().unwrap(), "--resume"]).output().unwrap();
    let err = String::from_utf8_lossy(&o.stderr);
    assert!(!o.status.success() && err.contains("`training.lr` is 0.001 there and 0.002 in this one"), "{err}");
    // Truncated.
    std::fs::write(&ckpt, &good[..good.len() / 2]).unwrap();
    let (code, err) = run(&out, &["--resume"]);
    assert!(code == 1 && err.contains("not a usable checkpoint (truncated or corrupt?)"), "{err}");
    // Optimizer state of the wrong length (was a panic), and a wrapped step count.
    let mut v: serde_json::Value = serde_json::from_str(&good).unwrap();
    v["optimizer"]["adam"]["m"].as_array_mut().unwrap().truncate(5);
    std::fs::write(&ckpt, v.to_string()).unwrap();
    let (code, err) = run(&out, &["--resume"]);
    assert!(code == 1 && err.contains("adam state `m` has 5 values") && !err.contains("panicked"), "{err}");
    let mut v: serde_json::Value = serde_json::from_str(&good).unwrap();
    v["optimizer"]["adam"]["t"] = serde_json::json!(u64::MAX);
    std::fs::write(&ckpt, v.to_string()).unwrap();
    let (code, err) = run(&out, &["--resume"]);
    assert!(code == 1 && err.contains("step count"), "{err}");
    // The good one resumes to the end.
    std::fs::write(&ckpt, &good).unwrap();
    let (code, err) = run(&out, &["--resume"]);
    assert_eq!(code, 0, "{err}");
    assert_eq!(iterations_done(&out), 4000);
    // Nothing to resume; and --extend trains further, explicitly.
    let empty = scratch("empty");
    let (code, err) = run(&empty, &["--resume"]);
    assert!(code == 1 && err.contains("nothing to continue"), "{err}");
    let (code, err) = run(&out, &["--extend", "5"]);
    assert_eq!(code, 0, "{err}");
    assert_eq!(iterations_done(&out), 4005);
    // A FIFO as the configuration is refused before reading (it hung).
    let fifo = empty.with_extension("fifo");
    assert!(Command::new("mkfifo").arg(&fifo).status().unwrap().success());
    let o = Command::new(crate::diffsim_bin()).args(["train", fifo.to_str().unwrap(), "--out", empty.to_str().unwrap()]).output().unwrap();
    assert!(String::from_utf8_lossy(&o.stderr).contains("not a regular file (a FIFO)"));
    std::fs::remove_file(&fifo).ok();
    std::fs::remove_dir_all(&out).ok();
    std::fs::remove_dir_all(&empty).ok();
}

/// `diffsim experiment sol-burgers` on a small setting, with `extra`.
fn study(out: &Path, extra: &[&str]) -> Command {
    let mut c = Command::new(crate::diffsim_bin());
    c.args(["experiment", "sol-burgers", "--quick", "--iterations", "1500", "--methods", "pre,sol4", "--checkpoint-seconds", "0.1", "--json"])
        .args(["--out", out.to_str().unwrap()])
        .args(extra);
    c
}

#[test]
fn an_interrupted_study_resumed_gives_the_uninterrupted_results() {
    let (whole, cut) = (scratch("study-whole"), scratch("study-cut"));
    let start = Instant::now();
    let o = study(&whole, &[]).output().unwrap();
    assert!(o.status.success(), "{}", String::from_utf8_lossy(&o.stderr));
    // Interrupts at fractions of the whole run's time (the machine's speed varies).
    let whole_s = start.elapsed().as_secs_f64();
    // Interrupted (SIGTERM: the variant in progress is checkpointed) or
    // killed (SIGKILL: the last periodic checkpoint) at several moments.
    // When the runs outpace the whole run's time (a load that eased) and
    // the study ends before two interrupts landed, it starts afresh with
    // earlier interrupts.
    let (mut landed, mut attempt) = (0, 0);
    for scale in [1.0, 0.5, 0.25, 0.125] {
        std::fs::remove_dir_all(&cut).ok();
        (landed, attempt) = (0, 0);
        loop {
            let extra: &[&str] = if attempt == 0 { &[] } else { &["--resume"] };
            let mut child = study(&cut, extra).stdout(Stdio::null()).stderr(Stdio::piped()).spawn().unwrap();
            let delay = Duration::from_secs_f64(scale * whole_s * [0.4, 0.25, 0.3, 0.2].get(attempt).copied().unwrap_or(1000.0));
            let start = Instant::now();
            while start.elapsed() < delay && child.try_wait().unwrap().is_none() {
                std::thread::sleep(Duration::from_millis(10));
            }
            let signal = if attempt % 2 == 0 { "-TERM" } else { "-KILL" };
            if child.try_wait().unwrap().is_none() {
                Command::new("kill").args([signal, &child.id().to_string()]).status().unwrap();
            }
            let o = child.wait_with_output().unwrap();
            let err = String::from_utf8_lossy(&o.stderr);
            match o.status.code() {
                Some(0) => break,
                Some(130) => {
                    assert!(err.contains("in variant") && err.contains("--resume"), "{err}");
                    landed += 1;
                }
                None => landed += usize::from(cut.join("parts").exists()),
                Some(c) => panic!("exit {c}: {err}"),
            }
            attempt += 1;
            assert!(attempt < 12, "the study never finished");
        }
        if landed >= 2 {
            break;
        }
    }
    assert!(landed >= 2, "only {landed} interrupts landed during the study");
    let read = |d: &Path| std::fs::read_to_string(d.join("errors.csv")).unwrap();
    assert_eq!(read(&whole), read(&cut), "errors.csv differs after {attempt} interrupts");
    // The parts of another setting are refused with the setting named.
    let o = study(&cut, &["--resume", "--lr", "0.002"]).output().unwrap();
    let err = String::from_utf8_lossy(&o.stderr);
    assert!(!o.status.success() && err.contains("other settings") && err.contains("lr: 0.002"), "{err}");
    std::fs::remove_dir_all(&whole).ok();
    std::fs::remove_dir_all(&cut).ok();
}

/// `diffsim experiment sip-heat` with `iterations` updates per optimizer.
fn sip(out: &Path, iterations: &str, extra: &[&str]) -> std::process::Output {
    Command::new(crate::diffsim_bin())
        .args(["experiment", "sip-heat", "--iterations", iterations, "--json", "--out", out.to_str().unwrap()])
        .args(extra)
        .output()
        .unwrap()
}

#[test]
fn a_comparison_resumes_per_optimizer_and_says_what_it_cannot_resume() {
    let out = scratch("sip");
    let o = sip(&out, "3", &[]);
    assert!(o.status.success(), "{}", String::from_utf8_lossy(&o.stderr));
    let first = std::fs::read_to_string(out.join("error.csv")).unwrap();
    // As if the run had been cut during gradient descent: SIP's and Adam's
    // runs are read back (their wall-clock times too), only GD runs again.
    std::fs::remove_file(out.join("parts/gd.done.json")).unwrap();
    let o = sip(&out, "3", &["--resume"]);
    assert!(o.status.success(), "{}", String::from_utf8_lossy(&o.stderr));
    let again = std::fs::read_to_string(out.join("error.csv")).unwrap();
    let rows = |t: &str, name: &str| t.lines().filter(|l| l.starts_with(name)).map(String::from).collect::<Vec<_>>();
    assert_eq!(rows(&first, "sip,"), rows(&again, "sip,"));
    assert_eq!(rows(&first, "adam,"), rows(&again, "adam,"));
    assert_eq!(rows(&again, "gd,").len(), rows(&first, "gd,").len());
    // Other options: the saved parts are refused, naming the setting.
    let o = sip(&out, "4", &["--resume"]);
    let err = String::from_utf8_lossy(&o.stderr);
    assert!(!o.status.success() && err.contains("other settings") && err.contains("iterations: 4"), "{err}");
    // Ctrl-C (here SIGTERM) says what is kept and what starts again.
    let child = Command::new(crate::diffsim_bin())
        // (Other settings than the folder's run: --overwrite, or it is refused.)
        .args(["experiment", "sip-heat", "--iterations", "100000", "--overwrite", "--out", out.to_str().unwrap()])
        .stdout(Stdio::null())
        .stderr(Stdio::piped())
        .spawn()
        .unwrap();
    std::thread::sleep(Duration::from_millis(1500));
    Command::new("kill").args(["-TERM", &child.id().to_string()]).status().unwrap();
    let o = child.wait_with_output().unwrap();
    let err = String::from_utf8_lossy(&o.stderr);
    assert_eq!(o.status.code(), Some(130), "{err}");
    assert!(err.contains("finished parts are kept") && err.contains("--resume") && err.contains("cannot be resumed midway"), "{err}");
    std::fs::remove_dir_all(&out).ok();
}
