//! # diffsim's studies
//!
//! Published setups reproduced through the `diffsim` library, one module
//! each; the command line (`diffsim experiment …`, `diffsim train`,
//! `diffsim pareto`, `diffsim stability`, `diffsim bench p3`) runs them and
//! writes their files. Nothing here is needed to use the library: a study
//! is an example of its parts at work, and its result is checked against a
//! published figure.
//!
//! - [`sol`]: solver-in-the-loop (Um et al. 2020) on Burgers ([`burgers`],
//!   configured by [`config`] for `diffsim train`) and on 2D flow past a
//!   disc ([`wake`]).
//! - [`oscillators`]: half-inverse gradients against Adam and Gauss–Newton
//!   on coupled oscillators (Schnell et al. 2022).
//! - [`heat`] and [`smoke`]: scale-invariant physics (SIP) updates against
//!   Adam (Holl et al. 2022).
//! - [`cavity`]: the lid-driven cavity against Ghia, Ghia & Shin (1982).
//! - [`cylinder`]: the flow around a cylinder against Schäfer & Turek (1996).
//! - [`drag_shape`]: the minimum-drag body at fixed area, by L-BFGS through
//!   the steady solver's adjoint.
//! - [`shape_net`]: a network from the Reynolds number to the minimum-drag
//!   shape, trained through the steady solver.
//! - [`p3`]: benchmark P3, one training iteration (docs/benchmarks.md).
//! - [`accuracy`]: the schemes against exact solutions, error against time
//!   and memory, and the hard cases that must stay stable.
#![deny(missing_docs)]

pub mod accuracy;
pub mod burgers;
pub mod cavity;
pub mod config;
pub mod cylinder;
pub mod drag_shape;
pub mod heat;
pub mod measure;
pub mod oscillators;
pub mod p3;
pub mod shape_net;
pub mod smoke;
pub mod sol;
pub mod wake;

use diffsim::distributed::World;
use diffsim::train::checkpoint::{CheckpointError, Parts};

/// A study that failed.
#[derive(Debug, thiserror::Error)]
pub enum StudyError {
    /// Training failed (a non-finite loss or gradient, with where).
    #[error("training: {0}")]
    Train(#[from] diffsim::train::TrainError),
    /// A saved part cannot be written or used.
    #[error(transparent)]
    Part(#[from] CheckpointError),
    /// Stopped by a signal; the variant in progress is checkpointed.
    #[error("interrupted in variant {variant} after iteration {done} of {of}; the finished variants and its progress are saved")]
    Interrupted {
        /// The variant in progress.
        variant: String,
        /// Its iterations done.
        done: usize,
        /// Its iterations in all.
        of: usize,
    },
    /// A viscous flow could not be simulated or did not settle.
    #[error(transparent)]
    Flow(#[from] diffsim_solvers::flow::FlowError),
    /// A figure of the result is wrong (not finite, or a flow at rest):
    /// the result is not reported.
    #[error("{what}: {reason}; no result is reported")]
    NotReported {
        /// The run.
        what: String,
        /// The figure and what is wrong with it.
        reason: String,
    },
    /// A rollout or its gradient failed.
    #[error(transparent)]
    Rollout(#[from] diffsim::rollout::RolloutError),
    /// An evaluation rollout blew up.
    #[error("evaluation: {0}")]
    Eval(#[from] sol::EvalError),
}

/// A study's part (one optimizer's run, one problem): read back from
/// `parts` when an earlier, interrupted run finished it, else run and
/// saved there. Over the ranks of `world` rank 0 reads and sends what it
/// read, every rank runs, rank 0 saves. Without `parts`, just `run`.
///
/// # Errors
/// `run`'s, or a part that cannot be read or saved.
pub fn part<T, E>(world: &World, parts: Option<&Parts>, name: &str, run: impl FnOnce() -> Result<T, E>) -> Result<T, E>
where
    T: serde::Serialize + serde::de::DeserializeOwned,
    E: From<CheckpointError>,
{
    let Some(parts) = parts else { return run() };
    if let Some(done) = world.from_root(|| parts.finished(name))? {
        return Ok(done);
    }
    let value = run()?;
    if world.is_root() {
        parts.finish(name, &value)?;
    }
    Ok(value)
}

/// `Ok` when every figure is finite, else [`StudyError::NotReported`]
/// naming the first that is not.
///
/// # Errors
/// The first figure that is NaN or infinite.
pub fn finite_figures(what: &str, figures: &[(&str, f64)]) -> Result<(), StudyError> {
    match figures.iter().find(|(_, v)| !v.is_finite()) {
        Some((name, v)) => Err(StudyError::NotReported { what: what.to_string(), reason: format!("{name} came out {v}") }),
        None => Ok(()),
    }
}
