//! What the fuzz targets do with one input. The targets in `fuzz/` (cargo
//! fuzz, libFuzzer; `scripts/fuzz`, docs/fuzzing.md) are one call each into
//! this module, and the test suite calls the same functions on every kept
//! input (`fuzz/corpus/TARGET`, `fuzz/found/TARGET`), so that a fixed crash
//! stays fixed.
//!
//! Each function feeds its bytes to a reader of user input and goes on with
//! what the reader accepts, as a command would (a scene is built and, when
//! small, run and differentiated). A reader may refuse the input with an
//! error; it must never panic, hang or allocate past the memory budget, and
//! its message must be short enough to read. The checks run with a budget of
//! [`BUDGET`] bytes on the calling thread ([`diffsim::memory::with_budget`]).

use std::path::Path;

use diffsim::memory::with_budget;
use diffsim::nn::ParamStore;
use diffsim::rollout::Checkpointing;
use diffsim::scene::{AnyScene, npy_values};
use diffsim::train::checkpoint::Checkpoint;
use diffsim_studies::config::TrainConfig;

/// The memory budget of a fuzzed input: 256 MiB (libFuzzer's own limit is
/// 2 GiB; an input that fits the budget never comes near it).
pub const BUDGET: u64 = 256 << 20;

/// Most characters an error message may have: messages quote what they
/// refuse, shortened (an input of a megabyte gives a line, not a page).
pub const MAX_MESSAGE: usize = 2000;

/// Runs a stepped scene when its state × steps is at most this many values
/// (a few milliseconds), and differentiates it at a tenth of that.
const RUN_WORK: usize = 200_000;

/// The folder a fuzzed scene's `.npy` paths are relative to
/// (`fuzz/npy` of this checkout: small arrays the corpus names).
pub fn npy_dir() -> &'static Path {
    Path::new(concat!(env!("CARGO_MANIFEST_DIR"), "/../fuzz/npy"))
}

/// The configuration a fuzzed checkpoint is checked against (a network of
/// 15 parameters: a whole checkpoint is a short input).
const CONFIG: &str = include_str!("../../fuzz/train_tiny.toml");

fn message(what: &str, e: &dyn std::fmt::Display) {
    let m = e.to_string();
    assert!(!m.is_empty(), "{what}: an empty error message");
    assert!(m.chars().count() <= MAX_MESSAGE, "{what}: an error message of {} characters: {}…", m.chars().count(), diffsim::files::shorten(&m, 200));
}

/// A scene file: parsed and built; a small stepped scene is run, and
/// differentiated when it declares a loss.
pub fn scene(data: &[u8]) {
    let Ok(text) = std::str::from_utf8(data) else { return };
    with_budget(BUDGET, || match AnyScene::parse_in(text, npy_dir()) {
        Err(e) => message("scene", &e),
        Ok(AnyScene::Steady(_)) => {}
        Ok(AnyScene::Stepped(s)) => {
            let work = s.x0.len().saturating_mul(s.steps);
            if work > RUN_WORK {
                return;
            }
            if let Err(e) = s.run(|_, _| {}) {
                message("scene run", &e);
            }
            if let Some(loss) = &s.loss
                && work <= RUN_WORK / 10
                && let Err(e) = s.gradient(loss, Checkpointing::Store)
            {
                message("scene gradient", &e);
            }
        }
    })
}

/// A training configuration: parsed and checked.
pub fn config(data: &[u8]) {
    let Ok(text) = std::str::from_utf8(data) else { return };
    with_budget(BUDGET, || {
        if let Err(e) = TrainConfig::parse(text) {
            message("config", &e);
        }
    })
}

/// A `.npy` file: the first byte chooses the expected shape (bit 7 a line
/// of 1 to 64 values, else rows 1 to 8 by bits 3-5 and columns 1 to 8 by
/// bits 0-2), the rest is the file.
pub fn npy(data: &[u8]) {
    let Some((&b, bytes)) = data.split_first() else { return };
    let shape: Vec<u64> = if b & 0x80 != 0 { vec![u64::from(b & 0x3f) + 1] } else { vec![u64::from((b >> 3) & 7) + 1, u64::from(b & 7) + 1] };
    with_budget(BUDGET, || match npy_values(bytes, &shape) {
        Err(e) => message("npy", &e),
        Ok(v) => assert_eq!(v.len() as u64, shape.iter().product::<u64>(), "npy: {} values for the shape {shape:?}", v.len()),
    })
}

/// A parameter store (`model.json`) and a training checkpoint: both
/// readers on the same text; an accepted checkpoint is checked against
/// `fuzz/train_tiny.toml`, as `train --resume` does.
pub fn params(data: &[u8]) {
    let Ok(text) = std::str::from_utf8(data) else { return };
    with_budget(BUDGET, || {
        if let Err(e) = ParamStore::parse(text) {
            message("parameter store", &e);
        }
        let path = Path::new("checkpoint.json");
        match Checkpoint::parse(text, path) {
            Err(e) => message("checkpoint", &e),
            Ok(c) => {
                let cfg = match TrainConfig::parse(CONFIG) {
                    Ok(cfg) => cfg,
                    Err(e) => panic!("fuzz/train_tiny.toml: {e}"),
                };
                let mut layout = ParamStore::new();
                layout.add("net.", &cfg.net.param_names(), &vec![0.0; cfg.net_params()]);
                if let Err(e) = c.check(path, CONFIG, &layout, &cfg.optimizer) {
                    message("checkpoint check", &e);
                }
            }
        }
    })
}
