//! Replays every input the fuzzer kept (`fuzz/corpus/TARGET`: the minimised
//! corpus; `fuzz/found/TARGET`: the inputs that crashed, hung or panicked
//! before their fix) through the fuzz targets' own functions in
//! [`diffsim_cli::fuzz`], and the hand-written seeds (`fuzz/seeds/TARGET`, the
//! scenes and configurations of the repository, good and bad). A fixed crash stays
//! fixed; docs/fuzzing.md says how to run the fuzzer itself.

use std::path::{Path, PathBuf};

fn inputs(dirs: &[&str]) -> Vec<PathBuf> {
    let mut out = Vec::new();
    for d in dirs {
        let dir = Path::new(env!("CARGO_MANIFEST_DIR")).join(d);
        let Ok(entries) = std::fs::read_dir(&dir) else { continue };
        out.extend(entries.filter_map(|e| e.ok().map(|e| e.path())).filter(|p| p.is_file()));
    }
    out.sort();
    out
}

/// Feeds each input to `target`, naming the one that panics.
fn replay(target: &str, run: fn(&[u8]), seeds: &[&str]) -> usize {
    let corpus = format!("fuzz/corpus/{target}");
    let found = format!("fuzz/found/{target}");
    let own = format!("fuzz/seeds/{target}");
    let mut dirs = vec![corpus.as_str(), found.as_str(), own.as_str()];
    dirs.extend_from_slice(seeds);
    let all = inputs(&dirs);
    for path in &all {
        let data = std::fs::read(path).unwrap();
        if std::panic::catch_unwind(|| run(&data)).is_err() {
            panic!("fuzz target {target} panicked on {}", path.display());
        }
    }
    all.len()
}

#[test]
fn scene_inputs() {
    let n = replay("scene", diffsim_cli::fuzz::scene, &["scenes", "tests/scenes_bad"]);
    assert!(n >= 40, "only {n} scene inputs");
}

#[test]
fn config_inputs() {
    let n = replay("config", diffsim_cli::fuzz::config, &["configs", "tests/configs_bad"]);
    assert!(n >= 9, "only {n} configuration inputs");
}

#[test]
fn npy_inputs() {
    let n = replay("npy", diffsim_cli::fuzz::npy, &[]);
    assert!(n >= 1, "no .npy inputs");
}

#[test]
fn params_inputs() {
    let n = replay("params", diffsim_cli::fuzz::params, &[]);
    assert!(n >= 1, "no parameter-store inputs");
}

/// The targets' own checks fire: an over-long message or a panic in a
/// reader would fail the replay, not pass unseen.
#[test]
fn targets_accept_and_refuse() {
    // A valid scene runs (and a garbage one is refused) without a panic.
    diffsim_cli::fuzz::scene(std::fs::read("scenes/heat.toml").unwrap().as_slice());
    diffsim_cli::fuzz::scene(b"size = [");
    // A `.npy` of the wrong shape is refused; the right one is read.
    let mut npy = vec![0x80 | 3]; // a line of 4 values
    npy.extend(npy_file(&[4], &[1.0, 2.0, 3.0, 4.0]));
    diffsim_cli::fuzz::npy(&npy);
    assert_eq!(diffsim::scene::npy_values(&npy[1..], &[4]).unwrap(), vec![1.0, 2.0, 3.0, 4.0]);
    assert!(diffsim::scene::npy_values(&npy[1..], &[2, 2]).unwrap_err().contains("shape [4], expected [2, 2]"));
}

/// A float64 `.npy` file of `shape` holding `values`.
pub fn npy_file(shape: &[u64], values: &[f64]) -> Vec<u8> {
    use npyz::WriterBuilder;
    let mut out = Vec::new();
    let mut w = npyz::WriteOptions::new().default_dtype().shape(shape).writer(&mut out).begin_nd().unwrap();
    w.extend(values.iter().copied()).unwrap();
    w.finish().unwrap();
    out
}
