//! Runs over several MPI ranks (`mpirun -np K diffsim …`): the world and
//! its exchanges, data-parallel training equal bit for bit to one process,
//! and failures of one rank that stop the whole run.

use std::path::Path;
use std::process::{Command, Stdio};
use std::time::{Duration, Instant};

use crate::cli::{diffsim, scratch_dir};

/// `mpirun --oversubscribe` as root (several ranks on these two cores),
/// its arguments to come.
fn launcher() -> Command {
    let mut c = Command::new("mpirun");
    c.arg("--oversubscribe").env("OMPI_ALLOW_RUN_AS_ROOT", "1").env("OMPI_ALLOW_RUN_AS_ROOT_CONFIRM", "1");
    c
}

/// (exit code, stdout, stderr) of a finished command.
fn output(c: &mut Command) -> (i32, String, String) {
    let out = c.output().expect("mpirun (scripts/system-packages installs Open MPI)");
    (out.status.code().unwrap_or(-1), String::from_utf8_lossy(&out.stdout).into(), String::from_utf8_lossy(&out.stderr).into())
}

/// `mpirun -np K diffsim ARGS`.
fn mpirun(k: usize, args: &[&str]) -> (i32, String, String) {
    output(launcher().args(["-np", &k.to_string(), crate::diffsim_bin()]).args(args))
}

#[test]
fn info_runs_as_several_mpi_ranks_and_one_process_commands_refuse_them() {
    // One process without mpirun is a world of one.
    let (code, out, err) = diffsim(&["info"]);
    assert_eq!(code, 0, "{err}");
    assert!(out.contains("ranks: 1") && out.contains("Open MPI"), "{out}");
    // Three ranks exchange their numbers; rank 0 alone prints.
    let (code, out, err) = mpirun(3, &["info"]);
    assert_eq!(code, 0, "{out}\n{err}");
    assert!(out.contains("ranks: 3") && out.contains("exchange between the ranks: ok"), "{out}");
    assert_eq!(out.matches("diffsim ").count(), 1, "only rank 0 prints: {out}");
    // The exchange benchmark over two ranks: a line per size, the data checked.
    let (code, out, err) = mpirun(2, &["bench", "exchange", "--repetitions", "3", "--json"]);
    assert_eq!(code, 0, "{out}\n{err}");
    let lines: Vec<serde_json::Value> = out.lines().map(|l| serde_json::from_str(l).unwrap()).collect();
    assert_eq!(lines.len(), 6, "{out}");
    assert!(lines.iter().all(|l| l["ranks"] == 2 && l["time_s"].as_f64().unwrap() > 0.0), "{out}");
    assert_eq!(lines[5]["bytes_in_per_rank"], 8 << 20);
    // A command that runs in one process says so and every rank exits non-zero.
    let (code, _, err) = mpirun(2, &["check", "--n", "8", "--steps", "2"]);
    assert_ne!(code, 0);
    assert!(err.contains("`diffsim check` runs in one process; it was started by mpirun as 2 processes"), "{err}");
}

#[test]
fn the_scaling_benchmark_measures_two_ranks_and_predicts_more() {
    let (code, out, err) = mpirun(2, &["bench", "scaling", "--workload", "p3", "--iterations", "2", "--threads", "1", "--json"]);
    assert_eq!(code, 0, "{out}\n{err}");
    let v: serde_json::Value = serde_json::from_str(out.trim()).unwrap_or_else(|e| panic!("{e}: {out}"));
    assert_eq!((v["ranks"].as_u64(), v["batch"].as_u64(), v["threads_per_rank"].as_u64()), (Some(2), Some(32), Some(1)));
    // Rank 0 receives rank 1's 16 samples: parameters and loss each.
    let params = v["params"].as_u64().unwrap();
    assert_eq!(v["bytes_in_per_rank"].as_u64(), Some(16 * (params + 1) * 8));
    for key in ["iteration_s", "share_s", "exchange_s", "efficiency_8", "efficiency_512", "rank_limit"] {
        assert!(v[key].as_f64().is_some_and(|x| x > 0.0), "{key}: {v}");
    }
    // Batch 32 over 64 ranks leaves ranks idle: at most half efficiency.
    assert!(v["efficiency_64"].as_f64().unwrap() <= 0.5, "{v}");
    let (code, _, err) = diffsim(&["bench", "scaling", "--workload", "p5"]);
    assert!(code != 0 && err.contains("unknown workload `p5`"), "{err}");
}

#[test]
fn a_launch_is_recognised_from_its_environment() {
    use diffsim::distributed::{DistributedError, launched_size_in};
    let env = |pairs: &'static [(&'static str, &'static str)]| move |k: &str| pairs.iter().find(|(n, _)| *n == k).map(|(_, v)| v.to_string());
    assert_eq!(launched_size_in(env(&[])), None);
    assert_eq!(launched_size_in(env(&[("OMPI_COMM_WORLD_SIZE", "4")])), Some(4));
    assert_eq!(launched_size_in(env(&[("PMI_SIZE", "2")])), Some(2));
    // What a build without MPI says when started as several processes.
    let e = DistributedError::BuiltWithoutMpi { size: 3 }.to_string();
    assert!(e.contains("built without MPI") && e.contains("one of 3 processes"), "{e}");
}

/// A small `diffsim train` configuration (4 iterations of batch 16, SOL-4)
/// with `edit` applied, written to `dir/NAME`.
fn tiny_config(dir: &Path, name: &str, edit: impl Fn(String) -> String) -> String {
    std::fs::create_dir_all(dir).unwrap();
    let text = std::fs::read_to_string("configs/sol_burgers.toml")
        .unwrap()
        .replace("iterations = 600", "iterations = 4")
        .replace("train = 32", "train = 4")
        .replace("test = 8", "test = 2")
        .replace("steps = 144", "steps = 40")
        .replace("test_steps = 128", "test_steps = 20")
        .replace("unroll = 16", "unroll = 4");
    let path = dir.join(name);
    std::fs::write(&path, edit(text)).unwrap();
    path.to_str().unwrap().to_string()
}

/// The files of a training run that must not depend on the ranks: the
/// model, the checkpoint, and the loss log without its wall times.
fn trained(out: &Path) -> (String, String, String) {
    let read = |f: &str| std::fs::read_to_string(out.join(f)).unwrap_or_else(|e| panic!("{f}: {e}"));
    let losses = read("loss.csv").lines().map(|l| l.rsplit_once(',').unwrap().0.to_string()).collect::<Vec<_>>().join("\n");
    (read("model.json"), read("checkpoint.json"), losses)
}

#[test]
fn training_over_one_two_and_three_ranks_gives_the_same_parameters_bit_for_bit() {
    let dir = scratch_dir("mpi-train");
    let d = |s: &str| dir.join(s).to_str().unwrap().to_string();
    // Fixed data, and data drawn afresh per batch (each rank simulates its
    // share). One call each: an array of tuples trips Enzyme's type
    // analysis in this crate (docs/pitfalls.md).
    same_on_one_two_and_three_ranks(&dir, "fixed", |t| t);
    same_on_one_two_and_three_ranks(&dir, "random", |t| t.replace("viscosity = 0.01", "viscosity = [0.005, 0.02]"));
    // Cut after iteration 2 on two ranks, resumed on three: the
    // uninterrupted run's files.
    let c = d("fixed.toml");
    let out = d("sliced");
    let (code, stdout, err) = mpirun(2, &["train", &c, "--out", &out, "--quiet", "--until", "2"]);
    assert_eq!(code, 0, "{stdout}\n{err}");
    assert!(stdout.contains("stopped after iteration 2 of 4 as asked"), "{stdout}");
    assert!(!Path::new(&out).join("model.json").exists());
    let (code, stdout, err) = mpirun(3, &["train", &c, "--out", &out, "--quiet", "--resume"]);
    assert_eq!(code, 0, "{stdout}\n{err}");
    assert!(trained(Path::new(&out)) == trained(&dir.join("fixed1")), "resumed on 3 ranks after 2 differs from one uninterrupted process");
    std::fs::remove_dir_all(&dir).ok();
}

/// Trains configuration `name` (the tiny one with `edit`) in one process
/// and over 2 and 3 ranks: the same files.
fn same_on_one_two_and_three_ranks(dir: &Path, name: &str, edit: impl Fn(String) -> String) {
    let c = tiny_config(dir, &format!("{name}.toml"), edit);
    let out = |k: usize| dir.join(format!("{name}{k}")).to_str().unwrap().to_string();
    let (code, one, err) = diffsim(&["train", &c, "--out", &out(1), "--quiet"]);
    assert_eq!(code, 0, "{one}\n{err}");
    let reference = trained(Path::new(&out(1)));
    for k in 2..=3 {
        let (code, stdout, err) = mpirun(k, &["train", &c, "--out", &out(k), "--quiet"]);
        assert_eq!(code, 0, "{stdout}\n{err}");
        assert_eq!(stdout.matches("4 iterations (4 in total) over").count(), 1, "rank 0 alone prints: {stdout}");
        assert!(stdout.contains(&format!("over {k} ranks")), "{stdout}");
        let got = trained(Path::new(&out(k)));
        assert!(got == reference, "{name} data: {k} ranks differ from one process:\n{}\n{}", got.2, reference.2);
    }
}

#[test]
fn a_study_over_two_ranks_writes_the_results_of_one_process() {
    let dir = scratch_dir("mpi-study");
    let args = |out: &Path| {
        ["experiment", "sol-burgers", "--quick", "--iterations", "12", "--methods", "noise,sol4", "--train", "8", "--json", "--out", out.to_str().unwrap()]
            .map(String::from)
            .to_vec()
    };
    let one: Vec<String> = args(&dir.join("one"));
    let (code, stdout, err) = diffsim(&one.iter().map(String::as_str).collect::<Vec<_>>());
    assert_eq!(code, 0, "{stdout}\n{err}");
    let two: Vec<String> = args(&dir.join("two"));
    let (code, stdout2, err) = mpirun(2, &two.iter().map(String::as_str).collect::<Vec<_>>());
    assert_eq!(code, 0, "{stdout2}\n{err}");
    assert_eq!(stdout2.lines().count(), 1, "rank 0 alone prints: {stdout2}");
    let read = |d: &str| std::fs::read_to_string(dir.join(d).join("errors.csv")).unwrap();
    assert_eq!(read("one"), read("two"));
    let field = |s: &str, k: &str| serde_json::from_str::<serde_json::Value>(s.trim()).unwrap()[k].clone();
    assert_eq!(field(&stdout, "sol4"), field(&stdout2, "sol4"));
    std::fs::remove_dir_all(&dir).ok();
}

#[test]
fn half_inverse_gradients_over_three_ranks_take_the_steps_of_one_process() {
    // HIG, Gauss-Newton and Adam, each 5 updates on both oscillator
    // problems: batches of 32 to 512 split 3 ways, the Jacobian decomposed
    // on rank 0.
    let dir = scratch_dir("mpi-hig");
    let o = |d: &str| dir.join(d).to_str().unwrap().to_string();
    let (code, one, err) = diffsim(&["experiment", "hig-oscillators", "--updates", "5", "--json", "--out", &o("one")]);
    assert_eq!(code, 0, "{one}\n{err}");
    let (code, three, err) = mpirun(3, &["experiment", "hig-oscillators", "--updates", "5", "--json", "--out", &o("three")]);
    assert_eq!(code, 0, "{three}\n{err}");
    let json = |s: &str| serde_json::from_str::<serde_json::Value>(s.lines().last().unwrap()).unwrap();
    let (one, three) = (json(&one), json(&three));
    for key in ["hig", "gn", "adam", "hig_nonlinear", "gn_nonlinear", "adam_nonlinear"] {
        assert!(one[key].as_f64().unwrap().is_finite(), "{key}: {one}");
        assert_eq!(one[key], three[key], "{key}");
        assert_eq!(three[&format!("{key}_updates")], 5, "{key}");
    }
    let losses = |d: &str| {
        let t = std::fs::read_to_string(dir.join(d).join("loss.csv")).unwrap();
        // problem,optimizer,seconds,test_loss: all but the seconds.
        t.lines().map(|l| l.split(',').enumerate().filter(|(i, _)| *i != 2).map(|(_, f)| f).collect::<Vec<_>>().join(",")).collect::<Vec<_>>()
    };
    assert_eq!(losses("one"), losses("three"));
    std::fs::remove_dir_all(&dir).ok();
}

#[test]
fn a_sweep_over_three_ranks_writes_the_files_of_one_process() {
    let dir = scratch_dir("mpi-sweep");
    let o = |d: &str| dir.join(d).to_str().unwrap().to_string();
    let sweep = |out: String| {
        [
            "sweep",
            "tests/scenes_moving/moving2d.toml",
            "--set",
            "effects[1].coefficient=0.05,0.1,0.2",
            "--set",
            "time.steps=2,3",
            "--out",
            &out,
            "--quiet",
            "--json",
        ]
        .map(String::from)
    };
    let (code, one, err) = diffsim(&sweep(o("one")).each_ref().map(String::as_str));
    assert_eq!(code, 0, "{one}\n{err}");
    let (code, three, err) = mpirun(3, &sweep(o("three")).each_ref().map(String::as_str));
    assert_eq!(code, 0, "{three}\n{err}");
    assert!(three.contains("6 runs (0 failed) over 3 rank(s)"), "{three}");
    // Every run's fields and pictures, byte for byte.
    for run in 0..6 {
        let folder = format!("run-{run:04}");
        let mut files: Vec<String> = std::fs::read_dir(dir.join("one").join(&folder)).unwrap().map(|e| e.unwrap().file_name().into_string().unwrap()).collect();
        files.sort();
        assert!(files.contains(&"smoke.npy".to_string()) && files.iter().any(|f| f.ends_with(".png")), "{files:?}");
        for f in &files {
            let read = |d: &str| std::fs::read(dir.join(d).join(&folder).join(f)).unwrap();
            assert!(read("one") == read("three"), "{folder}/{f} differs");
        }
    }
    // The table, but for the times.
    let table = |d: &str| {
        let t = std::fs::read_to_string(dir.join(d).join("runs.csv")).unwrap();
        let time = t.lines().next().unwrap().split(',').position(|c| c == "time_s").unwrap();
        t.lines().map(|l| l.split(',').enumerate().filter(|(i, _)| *i != time).map(|(_, c)| c).collect::<Vec<_>>().join(",")).collect::<Vec<_>>()
    };
    assert_eq!(table("one"), table("three"));
    assert_eq!(table("one")[0], "run,effects[1].coefficient,time.steps,status,loss,smoke_mean,smoke_max_abs,velocity_mean,velocity_max_abs");
    // Run 3 is the scene as written (coefficient 0.1, 3 steps): its loss
    // is the one `diffsim grad` reports.
    let rows: Vec<serde_json::Value> = serde_json::from_str(one.lines().find(|l| l.starts_with('[')).unwrap()).unwrap();
    assert_eq!((rows[3]["effects[1].coefficient"].as_f64(), rows[3]["time.steps"].as_i64()), (Some(0.1), Some(3)));
    let (code, grad, err) = diffsim(&["grad", "tests/scenes_moving/moving2d.toml", "--out", &o("grad")]);
    assert_eq!(code, 0, "{err}");
    let loss: f64 = grad.split_whitespace().nth(1).unwrap().parse().unwrap();
    let swept = rows[3]["loss"].as_f64().unwrap();
    assert!((swept - loss).abs() <= 1e-9 * loss.abs(), "sweep {swept} vs grad {loss}");
    // Mistakes name the key, before anything runs.
    let fails = |set: &str, needle: &str| {
        let (code, _, err) = diffsim(&["sweep", "tests/scenes_moving/moving2d.toml", "--set", set, "--out", &o("bad")]);
        assert!(code != 0 && err.contains(needle) && !err.contains("panicked"), "{set}: {err}");
    };
    fails("effects[5].coefficient=1", "`effects[5].coefficient`: entry [5] does not exist (the scene has 3)");
    fails("effects[1].coeficient=1,2", "did you mean `coefficient`");
    fails("time.steps", "expected KEY=V1,V2");
    fails("time.steps=2,,3", "an empty value");
    fails("time.dt=-1", "run 0: tests/scenes_moving/moving2d.toml with time.dt=-1: scene: `time.dt`");
    assert!(!dir.join("bad").exists(), "nothing runs when a combination is bad");
    std::fs::remove_dir_all(&dir).ok();
}

#[test]
fn a_rank_that_fails_stops_the_whole_run_with_its_rank_and_cause() {
    let dir = scratch_dir("mpi-faults");
    let good = tiny_config(&dir, "good.toml", |t| t);
    let out = dir.join("out");
    let o = out.to_str().unwrap();
    // Bad input that rank 1 alone sees: its configuration is missing.
    let missing = dir.join("missing.toml");
    let (code, _, err) = output(
        launcher().args(["-np", "1", crate::diffsim_bin(), "train", &good, "--out", o, "--quiet", ":", "-np", "1", crate::diffsim_bin(), "train"]).args([
            missing.to_str().unwrap(),
            "--out",
            o,
            "--quiet",
        ]),
    );
    assert_ne!(code, 0);
    assert!(err.contains("error on rank 1 of 2") && err.contains("missing.toml"), "{err}");
    // Another configuration on rank 1: found before any training.
    let other = tiny_config(&dir, "other.toml", |t| t.replace("lr = 1e-3", "lr = 2e-3"));
    let (code, _, err) = output(
        launcher()
            .args(["-np", "1", crate::diffsim_bin(), "train", &good, "--out", o, "--quiet", "--overwrite", ":", "-np", "1", crate::diffsim_bin()])
            .args(["train", &other, "--out", o, "--quiet", "--overwrite"]),
    );
    assert_ne!(code, 0);
    assert!(err.contains("rank 1's configurations differ from rank 0's"), "{err}");
    // A rank killed by a signal in the middle of a run: every rank stops
    // within seconds, mpirun names the rank and the signal, and the
    // checkpoint rank 0 wrote is whole.
    let long = tiny_config(&dir, "long.toml", |t| t.replace("iterations = 4", "iterations = 100000"));
    let mut job = launcher()
        .args(["-np", "2", crate::diffsim_bin(), "train", &long, "--out", o, "--quiet", "--overwrite", "--checkpoint-every", "5"])
        .stdout(Stdio::null())
        .stderr(Stdio::piped())
        .spawn()
        .unwrap();
    let log = out.join("loss.csv");
    let start = Instant::now();
    while std::fs::read_to_string(&log).map_or(0, |t| t.lines().count()) < 12 {
        assert!(start.elapsed() < Duration::from_secs(120), "training never started");
        assert!(job.try_wait().unwrap().is_none(), "the job ended early");
        std::thread::sleep(Duration::from_millis(50));
    }
    let rank1 = rank_pid(job.id(), 1).expect("rank 1's process");
    Command::new("kill").args(["-KILL", &rank1.to_string()]).status().unwrap();
    let killed = Instant::now();
    while job.try_wait().unwrap().is_none() {
        assert!(killed.elapsed() < Duration::from_secs(30), "the job still runs 30 s after a rank was killed");
        std::thread::sleep(Duration::from_millis(50));
    }
    let o = job.wait_with_output().unwrap();
    let err = String::from_utf8_lossy(&o.stderr);
    assert!(!o.status.success());
    assert!(err.contains("rank 1") && err.contains("signal 9"), "{err}");
    let ckpt: serde_json::Value = serde_json::from_str(&std::fs::read_to_string(out.join("checkpoint.json")).unwrap()).expect("a whole checkpoint");
    assert!(ckpt["iterations_done"].as_u64().unwrap() >= 5);
    std::fs::remove_dir_all(&dir).ok();
}

/// The process of rank `rank` among the descendants of `launcher`.
fn rank_pid(launcher: u32, rank: usize) -> Option<u32> {
    let children = |pid: u32| -> Vec<u32> {
        std::fs::read_to_string(format!("/proc/{pid}/task/{pid}/children")).unwrap_or_default().split_whitespace().filter_map(|p| p.parse().ok()).collect()
    };
    let mut todo = children(launcher);
    while let Some(pid) = todo.pop() {
        let env = std::fs::read(format!("/proc/{pid}/environ")).unwrap_or_default();
        if env.split(|&b| b == 0).any(|v| v == format!("OMPI_COMM_WORLD_RANK={rank}").as_bytes()) {
            return Some(pid);
        }
        todo.extend(children(pid));
    }
    None
}
