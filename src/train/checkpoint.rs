//! Training checkpoints: all a run needs to go on exactly as if it had
//! never stopped. The parameters and the optimizer's state are saved with
//! the number of iterations done and the configuration's text; the random
//! state and the position in the data need no saving, because the batch of
//! iteration `i` is drawn from a generator seeded by the configuration's
//! seed and `i` alone ([`super::sol::TrainParams::first`]).
//!
//! Checkpoints are written atomically ([`crate::files::write_atomic`]) and
//! checked on reading: a truncated or corrupt file, another format, another
//! configuration (naming the first key that differs), another network or
//! optimizer state of the wrong shape is an error, never used.

use std::path::{Path, PathBuf};

use serde::{Deserialize, Serialize};

use super::Optimizer;
use crate::files::{ReadError, read_text, shorten, write_atomic};
use crate::nn::ParamStore;

/// The checkpoint format this build writes and reads.
pub const FORMAT: u32 = 1;

/// The largest checkpoint read (1 GiB of JSON: far beyond any network here).
pub const MAX_BYTES: u64 = 1 << 30;

/// A training run's state after some iterations.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct Checkpoint {
    /// [`FORMAT`] when written.
    pub format: u32,
    /// The configuration's text.
    pub config: String,
    /// Iterations done.
    pub iterations_done: u64,
    /// The network's parameters.
    pub params: ParamStore,
    /// The optimizer and its state.
    pub optimizer: Optimizer,
}

/// A checkpoint that cannot be written or used.
#[derive(Debug, thiserror::Error)]
pub enum CheckpointError {
    /// It could not be read.
    #[error(transparent)]
    Read(#[from] ReadError),
    /// It could not be written.
    #[error("cannot write {path}: {source}")]
    Write {
        /// The file.
        path: PathBuf,
        /// The cause.
        source: std::io::Error,
    },
    /// Not a checkpoint: truncated, corrupt or another kind of file.
    #[error("{path}: not a usable checkpoint (truncated or corrupt?): {reason}")]
    Corrupt {
        /// The file.
        path: PathBuf,
        /// What the reader found.
        reason: String,
    },
    /// Written by another checkpoint format.
    #[error("{path}: checkpoint format {found}; this diffsim reads format {FORMAT}")]
    Format {
        /// The file.
        path: PathBuf,
        /// Its format.
        found: u32,
    },
    /// Written for another configuration.
    #[error("{path}: written for another configuration: `{key}` is {then} there and {now} in this one")]
    Mismatch {
        /// The file.
        path: PathBuf,
        /// The first key that differs (`training.lr`).
        key: String,
        /// Its value in the checkpoint's configuration.
        then: String,
        /// Its value in the configuration given.
        now: String,
    },
    /// Its parameters or optimizer state do not fit the configuration.
    #[error("{path}: {reason}")]
    Invalid {
        /// The file.
        path: PathBuf,
        /// What does not fit.
        reason: String,
    },
}

impl Checkpoint {
    /// Writes the checkpoint to `path` atomically.
    pub fn save(&self, path: &Path) -> Result<(), CheckpointError> {
        let text = serde_json::to_string(self).map_err(|e| CheckpointError::Corrupt { path: path.to_path_buf(), reason: e.to_string() })?;
        write_atomic(path, text.as_bytes()).map_err(|source| CheckpointError::Write { path: path.to_path_buf(), source })
    }

    /// Reads the checkpoint at `path`, refusing a truncated or corrupt file
    /// and another format.
    pub fn load(path: &Path) -> Result<Checkpoint, CheckpointError> {
        let text = read_text(path, MAX_BYTES, "checkpoint")?;
        Self::parse(&text, path)
    }

    /// A checkpoint from its JSON text (`path` names it in errors).
    pub fn parse(text: &str, path: &Path) -> Result<Checkpoint, CheckpointError> {
        parse_versioned(text, path)
    }

    /// Checks that the checkpoint continues a run of `config` (the text;
    /// `training.iterations` may differ) with parameters laid out as
    /// `layout` and an optimizer of kind `optimizer` whose state fits them.
    pub fn check(&self, path: &Path, config: &str, layout: &ParamStore, optimizer: &str) -> Result<(), CheckpointError> {
        let invalid = |reason: String| CheckpointError::Invalid { path: path.to_path_buf(), reason };
        if let Some((key, then, now)) = config_difference(&self.config, config) {
            return Err(CheckpointError::Mismatch { path: path.to_path_buf(), key, then, now });
        }
        layout.check_layout(&self.params).map_err(|e| invalid(format!("its network does not fit this configuration's: {e}")))?;
        self.params.validate().map_err(|e| invalid(format!("its parameters: {e}")))?;
        if self.optimizer.kind() != optimizer {
            return Err(invalid(format!("its optimizer is {}, this configuration's is {optimizer}", self.optimizer.kind())));
        }
        self.optimizer.validate(self.params.values.len()).map_err(|e| invalid(format!("its optimizer state: {e}")))?;
        // One update per iteration: a count that disagrees means the file
        // was edited or mixed from two runs, and resuming would not give
        // the uninterrupted run.
        match self.optimizer.steps_taken() {
            Some(t) if t != self.iterations_done => Err(invalid(format!(
                "its {} optimizer has taken {t} steps but its iteration count is {} (one step per iteration): the file was altered",
                self.optimizer.kind(),
                self.iterations_done
            ))),
            _ => Ok(()),
        }
    }
}

/// A JSON file of this format version (`path` names it in errors): the
/// format is read first, so that a newer file is named as such.
fn parse_versioned<T: serde::de::DeserializeOwned>(text: &str, path: &Path) -> Result<T, CheckpointError> {
    let corrupt = |e: serde_json::Error| CheckpointError::Corrupt { path: path.to_path_buf(), reason: shorten(&e.to_string(), 200) };
    let head: serde_json::Value = serde_json::from_str(text).map_err(corrupt)?;
    match head.get("format").and_then(serde_json::Value::as_u64) {
        Some(f) if f == FORMAT as u64 => {}
        Some(f) => return Err(CheckpointError::Format { path: path.to_path_buf(), found: u32::try_from(f).unwrap_or(u32::MAX) }),
        None => return Err(CheckpointError::Corrupt { path: path.to_path_buf(), reason: "no `format` field".into() }),
    }
    serde_json::from_value(head).map_err(corrupt)
}

/// The first key (as a dotted path) whose value differs between two
/// configurations' texts, with both values shortened for display;
/// `training.iterations` (the run's length) is not compared. Texts that do
/// not parse differ at the root.
pub fn config_difference(then: &str, now: &str) -> Option<(String, String, String)> {
    let parse = |t: &str| t.parse::<toml::Table>().ok();
    let (Some(a), Some(b)) = (parse(then), parse(now)) else {
        return (then != now).then(|| ("(the whole file)".into(), "unreadable".into(), "readable".into()));
    };
    table_difference("", &a, &b)
}

fn table_difference(prefix: &str, a: &toml::Table, b: &toml::Table) -> Option<(String, String, String)> {
    let show = |v: Option<&toml::Value>| v.map_or("absent".to_string(), |v| shorten(&v.to_string(), 60));
    let mut keys: Vec<&String> = a.keys().chain(b.keys()).collect();
    keys.sort();
    keys.dedup();
    for k in keys {
        let path = if prefix.is_empty() { k.clone() } else { format!("{prefix}.{k}") };
        if path == "training.iterations" {
            continue;
        }
        match (a.get(k), b.get(k)) {
            (Some(toml::Value::Table(x)), Some(toml::Value::Table(y))) => {
                if let Some(d) = table_difference(&path, x, y) {
                    return Some(d);
                }
            }
            (x, y) if x != y => return Some((path, show(x), show(y))),
            _ => {}
        }
    }
    None
}

/// A long study's saved parts (`OUT/parts/`): the result of each finished
/// part (a trained variant of a solver-in-the-loop study) and a checkpoint
/// of the part in progress, every file stamped with the study's settings,
/// so that `--resume` keeps what is done, goes on where the run stopped and
/// refuses the parts of another study.
#[derive(Debug)]
pub struct Parts {
    dir: PathBuf,
    settings: String,
}

/// A part's file: the study's settings and the value.
#[derive(Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
struct Stamped<T> {
    format: u32,
    settings: String,
    value: T,
}

/// A part in progress: its parameters and optimizer after
/// `iterations_done` iterations, and the losses of those iterations.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct PartProgress {
    /// Iterations done.
    pub iterations_done: usize,
    /// The parameters.
    pub theta: Vec<f64>,
    /// The optimizer and its state.
    pub optimizer: Optimizer,
    /// The loss of each iteration done.
    pub loss: Vec<f64>,
}

impl Parts {
    /// The parts in `dir` of a study with `settings` (a full description
    /// of everything its results depend on, one setting per line). Without
    /// `resume` earlier parts are removed: the study starts afresh.
    pub fn open(dir: &Path, settings: String, resume: bool) -> Result<Parts, CheckpointError> {
        let write = |source| CheckpointError::Write { path: dir.to_path_buf(), source };
        if !resume && dir.exists() {
            std::fs::remove_dir_all(dir).map_err(write)?;
        }
        std::fs::create_dir_all(dir).map_err(write)?;
        Ok(Parts { dir: dir.to_path_buf(), settings })
    }

    /// The parts another process keeps (rank 0 of a distributed run): the
    /// same names, no file touched here.
    pub fn kept_elsewhere(dir: &Path, settings: String) -> Parts {
        Parts { dir: dir.to_path_buf(), settings }
    }

    fn path(&self, name: &str, kind: &str) -> PathBuf {
        self.dir.join(format!("{name}.{kind}.json"))
    }

    fn read<T: serde::de::DeserializeOwned>(&self, path: &Path) -> Result<Option<T>, CheckpointError> {
        if !path.exists() {
            return Ok(None);
        }
        let text = read_text(path, MAX_BYTES, "study part")?;
        let part: Stamped<T> = parse_versioned(&text, path)?;
        if part.settings != self.settings {
            // The first setting that differs, by line.
            let (then, now) = part.settings.lines().zip(self.settings.lines()).find(|(a, b)| a != b).unwrap_or(("(fewer settings)", "(more settings)"));
            return Err(CheckpointError::Invalid {
                path: path.to_path_buf(),
                reason: format!(
                    "written by a run of the study with other settings (`{}` there, `{}` now); run without --resume to start afresh, or use another --out",
                    shorten(then.trim(), 80),
                    shorten(now.trim(), 80)
                ),
            });
        }
        Ok(Some(part.value))
    }

    fn write<T: Serialize>(&self, path: &Path, value: T) -> Result<(), CheckpointError> {
        let part = Stamped { format: FORMAT, settings: self.settings.clone(), value };
        let text = serde_json::to_string(&part).map_err(|e| CheckpointError::Corrupt { path: path.to_path_buf(), reason: e.to_string() })?;
        write_atomic(path, text.as_bytes()).map_err(|source| CheckpointError::Write { path: path.to_path_buf(), source })
    }

    /// The result of part `name`, when it finished in an earlier run.
    pub fn finished<T: serde::de::DeserializeOwned>(&self, name: &str) -> Result<Option<T>, CheckpointError> {
        self.read(&self.path(name, "done"))
    }

    /// Saves the result of part `name` and drops its progress checkpoint.
    pub fn finish<T: Serialize>(&self, name: &str, result: &T) -> Result<(), CheckpointError> {
        self.write(&self.path(name, "done"), result)?;
        let p = self.path(name, "progress");
        if p.exists() {
            std::fs::remove_file(&p).map_err(|source| CheckpointError::Write { path: p, source })?;
        }
        Ok(())
    }

    /// Part `name`'s progress checkpoint, checked against `params`
    /// parameters and at most `iterations` iterations.
    pub fn progress(&self, name: &str, params: usize, iterations: usize) -> Result<Option<PartProgress>, CheckpointError> {
        let path = self.path(name, "progress");
        let Some(p) = self.read::<PartProgress>(&path)? else { return Ok(None) };
        let invalid = |reason: String| CheckpointError::Invalid { path: path.clone(), reason };
        if p.theta.len() != params {
            return Err(invalid(format!("{} parameters, the network has {params}", p.theta.len())));
        }
        if p.iterations_done > iterations || p.loss.len() != p.iterations_done {
            return Err(invalid(format!("{} iterations with {} losses, of {iterations}", p.iterations_done, p.loss.len())));
        }
        if let Some(i) = p.theta.iter().position(|v| !v.is_finite()) {
            return Err(invalid(format!("parameter {i} is {}", p.theta[i])));
        }
        p.optimizer.validate(params).map_err(|e| invalid(format!("its optimizer state: {e}")))?;
        Ok(Some(p))
    }

    /// Saves part `name`'s progress.
    pub fn save_progress(&self, name: &str, progress: &PartProgress) -> Result<(), CheckpointError> {
        self.write(&self.path(name, "progress"), progress)
    }
}
