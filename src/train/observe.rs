//! What a training run does besides its updates: observers of the rows
//! ([`Observer`]), the CSV log ([`CsvLog`]), checkpoints by a policy
//! ([`CheckpointPolicy`], [`SaveWith`]), and a stop asked for from outside
//! (a flag the trainer reads every iteration; the command line sets it on
//! Ctrl-C).
//!
//! The trainer calls [`Observer::row`] after every iteration and
//! [`Observer::checkpoint`] when its [`CheckpointPolicy`] is due, when a
//! stop was asked for, and after the last iteration; observers combine as
//! pairs `(a, b)` (`a` first: a log is flushed before the checkpoint that
//! follows it, so it never lags it).

use std::io::Write;
use std::ops::ControlFlow;
use std::path::{Path, PathBuf};
use std::time::Instant;

use super::rule::TrainError;
use super::trainer::Row;

/// Sees every iteration of a run and saves its state when asked.
pub trait Observer<R: ?Sized> {
    /// After every iteration, with the parameters and the rule after its
    /// update. `Break` stops the run (the trainer saves a checkpoint first).
    ///
    /// # Errors
    /// What the observer could not do (a log that cannot be written): the
    /// run stops with it.
    fn row(&mut self, row: &Row, theta: &[f64], rule: &R) -> Result<ControlFlow<()>, TrainError>;

    /// Saves the state after iteration `iteration` (the default: nothing).
    ///
    /// # Errors
    /// A checkpoint that cannot be written: the run stops with it.
    fn checkpoint(&mut self, iteration: usize, theta: &[f64], rule: &R) -> Result<(), TrainError> {
        let _ = (iteration, theta, rule);
        Ok(())
    }
}

/// An observer lent to the trainer (the caller keeps it: a log to flush
/// at the end, say).
impl<R: ?Sized, O: Observer<R> + ?Sized> Observer<R> for &mut O {
    fn row(&mut self, row: &Row, theta: &[f64], rule: &R) -> Result<ControlFlow<()>, TrainError> {
        (**self).row(row, theta, rule)
    }
    fn checkpoint(&mut self, iteration: usize, theta: &[f64], rule: &R) -> Result<(), TrainError> {
        (**self).checkpoint(iteration, theta, rule)
    }
}

/// A closure `FnMut(&Row, &[f64], &R) -> ControlFlow<()>` as an observer
/// of rows (what [`super::Trainer::run`] takes).
pub struct OnRow<F>(pub F);

impl<R: ?Sized, F: FnMut(&Row, &[f64], &R) -> ControlFlow<()>> Observer<R> for OnRow<F> {
    fn row(&mut self, row: &Row, theta: &[f64], rule: &R) -> Result<ControlFlow<()>, TrainError> {
        Ok((self.0)(row, theta, rule))
    }
}

/// [`OnRow`] with the closure's argument types inferred.
pub fn on_row<R: ?Sized, F: FnMut(&Row, &[f64], &R) -> ControlFlow<()>>(f: F) -> OnRow<F> {
    OnRow(f)
}

/// Two observers: `.0` first, then `.1`; the run stops if either asks.
impl<R: ?Sized, A: Observer<R>, B: Observer<R>> Observer<R> for (A, B) {
    fn row(&mut self, row: &Row, theta: &[f64], rule: &R) -> Result<ControlFlow<()>, TrainError> {
        let a = self.0.row(row, theta, rule)?;
        let b = self.1.row(row, theta, rule)?;
        Ok(if a.is_break() || b.is_break() { ControlFlow::Break(()) } else { ControlFlow::Continue(()) })
    }
    fn checkpoint(&mut self, iteration: usize, theta: &[f64], rule: &R) -> Result<(), TrainError> {
        self.0.checkpoint(iteration, theta, rule)?;
        self.1.checkpoint(iteration, theta, rule)
    }
}

/// Saves checkpoints with a function `save(iteration, theta, rule)`; sees
/// rows without acting on them.
pub struct SaveWith<F>(pub F);

impl<R: ?Sized, F: FnMut(usize, &[f64], &R) -> Result<(), TrainError>> Observer<R> for SaveWith<F> {
    fn row(&mut self, _row: &Row, _theta: &[f64], _rule: &R) -> Result<ControlFlow<()>, TrainError> {
        Ok(ControlFlow::Continue(()))
    }
    fn checkpoint(&mut self, iteration: usize, theta: &[f64], rule: &R) -> Result<(), TrainError> {
        (self.0)(iteration, theta, rule)
    }
}

/// [`SaveWith`] with the closure's argument types inferred.
pub fn save_with<R: ?Sized, F: FnMut(usize, &[f64], &R) -> Result<(), TrainError>>(save: F) -> SaveWith<F> {
    SaveWith(save)
}

/// When the trainer saves: after `every` iterations or `seconds` of wall
/// time since the last save, whichever comes first, and always when a
/// stop was asked for and after the last iteration. `Default`: only then
/// (no periodic saves).
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct CheckpointPolicy {
    /// Iterations between two saves.
    pub every: usize,
    /// Seconds between two saves.
    pub seconds: f64,
}

impl Default for CheckpointPolicy {
    fn default() -> Self {
        CheckpointPolicy { every: usize::MAX, seconds: f64::INFINITY }
    }
}

impl CheckpointPolicy {
    /// Whether a save is due after `iteration`, the last save having been
    /// after `last` at `since`.
    pub fn due(&self, iteration: usize, last: usize, since: Instant) -> bool {
        iteration.saturating_sub(last) >= self.every.max(1) || since.elapsed().as_secs_f64() >= self.seconds
    }
}

/// The training log as CSV, `iteration,loss,grad_norm,seconds`, one row
/// per iteration, appended as the run goes and flushed at every
/// checkpoint. A resumed run keeps the rows up to its checkpoint (a killed
/// run may have logged past it) and appends from there, so the log of an
/// interrupted and resumed run is the uninterrupted run's (times aside).
#[derive(Debug)]
pub struct CsvLog {
    path: PathBuf,
    out: Option<std::io::BufWriter<std::fs::File>>,
}

impl CsvLog {
    /// The header line.
    pub const HEADER: &'static str = "iteration,loss,grad_norm,seconds";

    /// The log at `path` for a run at iteration `done` (0: a fresh run):
    /// [`CsvLog::trim`], then [`CsvLog::append`].
    ///
    /// # Errors
    /// When the file cannot be read or written.
    pub fn resume(path: &Path, done: usize) -> std::io::Result<Self> {
        Self::trim(path, done)?;
        Self::append(path)
    }

    /// Keeps the header and the rows of iterations `1..=done` of the log at
    /// `path` (written atomically; a missing log becomes the header alone).
    ///
    /// # Errors
    /// When the file cannot be read or written.
    pub fn trim(path: &Path, done: usize) -> std::io::Result<()> {
        let text = if path.exists() { crate::files::read_text(path, 1 << 30, "loss log").map_err(std::io::Error::other)? } else { String::new() };
        let mut kept = vec![Self::HEADER];
        kept.extend(text.lines().skip(1).filter(|l| l.split(',').next().and_then(|i| i.parse::<usize>().ok()).is_some_and(|i| i <= done)));
        crate::files::write_atomic(path, format!("{}\n", kept.join("\n")).as_bytes())
    }

    /// The log at `path` as it is (trimmed by [`CsvLog::trim`]), rows
    /// appended. A symbolic link at `path` is refused.
    ///
    /// # Errors
    /// When the file cannot be opened for appending.
    pub fn append(path: &Path) -> std::io::Result<Self> {
        let file = std::os::unix::fs::OpenOptionsExt::custom_flags(std::fs::OpenOptions::new().append(true), libc::O_NOFOLLOW).open(path)?;
        Ok(CsvLog { path: path.to_path_buf(), out: Some(std::io::BufWriter::new(file)) })
    }

    /// A log that writes nothing (the ranks other than 0 of a distributed
    /// run).
    pub fn none() -> Self {
        CsvLog { path: PathBuf::new(), out: None }
    }

    /// The log's file.
    pub fn path(&self) -> &Path {
        &self.path
    }

    /// The CSV line of `row` (a missing gradient norm is `NaN`).
    pub fn line(row: &Row) -> String {
        format!("{},{:.9e},{:.6e},{:.4}", row.iteration, row.loss, row.grad_norm.unwrap_or(f64::NAN), row.seconds)
    }

    /// Writes out what is buffered.
    ///
    /// # Errors
    /// When the file cannot be written.
    pub fn flush(&mut self) -> std::io::Result<()> {
        match &mut self.out {
            Some(o) => o.flush(),
            None => Ok(()),
        }
    }
}

/// A log or checkpoint file that cannot be written, as the trainer's error.
fn io_error(path: &Path, e: std::io::Error) -> TrainError {
    TrainError::Observer(format!("cannot write {}: {e}", path.display()))
}

impl<R: ?Sized> Observer<R> for CsvLog {
    fn row(&mut self, row: &Row, _theta: &[f64], _rule: &R) -> Result<ControlFlow<()>, TrainError> {
        if let Some(o) = &mut self.out
            && let Err(e) = writeln!(o, "{}", Self::line(row))
        {
            return Err(io_error(&self.path, e));
        }
        Ok(ControlFlow::Continue(()))
    }
    fn checkpoint(&mut self, _iteration: usize, _theta: &[f64], _rule: &R) -> Result<(), TrainError> {
        self.flush().map_err(|e| io_error(&self.path, e))
    }
}
