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
    let mut c = Command::new(env!("CARGO_BIN_EXE_diffsim"));
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
    let o = Command::new(env!("CARGO_BIN_EXE_diffsim")).args(["train", other.to_str().unwrap(), "--out", out.to_str().unwrap(), "--resume"]).output().unwrap();
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
    let o = Command::new(env!("CARGO_BIN_EXE_diffsim")).args(["train", fifo.to_str().unwrap(), "--out", empty.to_str().unwrap()]).output().unwrap();
    assert!(String::from_utf8_lossy(&o.stderr).contains("not a regular file (a FIFO)"));
    std::fs::remove_file(&fifo).ok();
    std::fs::remove_dir_all(&out).ok();
    std::fs::remove_dir_all(&empty).ok();
}
