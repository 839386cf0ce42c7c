//! One training loop for every study and every user: [`Trainer::run`].
//!
//! The loop owns what every training run needs, once: the iteration
//! count (starting past a checkpoint's iterations, so a resumed run repeats
//! an uninterrupted one), the learning-rate [`Schedule`], gradient clipping
//! by norm, the rule's update, the check that the ranks of a distributed
//! run still agree, and an observer called after every iteration with the
//! row of the log, the parameters and the rule (which writes the CSV log
//! and checkpoints, draws a progress bar, stops on Ctrl-C or a time budget
//! by returning [`ControlFlow::Break`]). What differs between problems is
//! the objective of each iteration: `objective_at(iteration)` builds it (a
//! batch drawn from the iteration's own seed, a rollout, a physics loss),
//! and any [`UpdateRule`] takes the step.

use std::cell::Cell;
use std::ops::ControlFlow;
use std::sync::atomic::{AtomicBool, Ordering};
use std::time::Instant;

use super::clip_by_norm;
use super::hig::{BatchJacobian, Hig};
use super::observe::{CheckpointPolicy, Observer, OnRow};
use super::pg::SipGradient;
use super::rule::{Objective, TrainError, UpdateRule};
use crate::distributed::World;

/// How the learning rate moves over the iterations.
#[derive(Clone, Copy, Debug, PartialEq)]
pub enum Schedule {
    /// The rule's own rate, untouched.
    Constant,
    /// Cosine decay from `start` to `end` over iterations `1..=over`,
    /// `end` after (Loshchilov & Hutter 2017, without restarts). The rate
    /// of an iteration depends on its number alone, so a resumed run
    /// continues the schedule.
    Cosine {
        /// The rate of iteration 1.
        start: f64,
        /// The rate at the end.
        end: f64,
        /// Iterations the decay spans.
        over: usize,
    },
    /// `start · factor^(it − 1)`: exponential decay for `factor < 1`.
    Exponential {
        /// The rate of iteration 1.
        start: f64,
        /// The factor per iteration.
        factor: f64,
    },
}

impl Schedule {
    /// The rate of iteration `it` (1-based), or `None` for the rule's own.
    pub fn at(&self, it: usize) -> Option<f64> {
        match *self {
            Schedule::Constant => None,
            Schedule::Cosine { start, end, over } => {
                let f = (it.saturating_sub(1) as f64 / over.max(1) as f64).min(1.0);
                Some(end + 0.5 * (start - end) * (1.0 + (std::f64::consts::PI * f).cos()))
            }
            Schedule::Exponential { start, factor } => Some(start * factor.powi(it.saturating_sub(1).min(i32::MAX as usize) as i32)),
        }
    }
}

/// Settings of [`Trainer`]; `Default`: from iteration 1, 100 iterations, a
/// constant rate, no clipping, ranks compared every 20 iterations,
/// checkpoints only when the run stops or ends.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct TrainerParams {
    /// The number of the first iteration (1, or one past a checkpoint's).
    pub first: usize,
    /// Iterations to run in this call.
    pub iterations: usize,
    /// The learning rate's schedule.
    pub schedule: Schedule,
    /// Gradients are scaled to at most this norm (∞: no clipping).
    pub clip: f64,
    /// The ranks compare their parameters and the rule's state this often
    /// (and after the last iteration); a difference is an error.
    pub same_state_every: usize,
    /// When the observer's [`Observer::checkpoint`] is called besides a
    /// stop and the last iteration.
    pub checkpoint: CheckpointPolicy,
}

impl Default for TrainerParams {
    fn default() -> Self {
        TrainerParams {
            first: 1,
            iterations: 100,
            schedule: Schedule::Constant,
            clip: f64::INFINITY,
            same_state_every: 20,
            checkpoint: CheckpointPolicy::default(),
        }
    }
}

/// One iteration, as the log records it.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Row {
    /// The iteration (1-based).
    pub iteration: usize,
    /// The loss before the update (the rule's: a mini-batch loss, the
    /// physics loss for SIP).
    pub loss: f64,
    /// The gradient's norm before clipping, where the rule took a gradient.
    pub grad_norm: Option<f64>,
    /// The learning rate of the update.
    pub lr: Option<f64>,
    /// Seconds since the run started.
    pub seconds: f64,
    /// Seconds of this iteration's objective and update (the observer's
    /// own time, an evaluation say, excluded).
    pub step_seconds: f64,
}

/// What a run did.
#[derive(Clone, Copy, Debug, Default, PartialEq)]
pub struct Info {
    /// The last iteration taken (`first − 1` if none).
    pub last: usize,
    /// Whether the observer stopped the run before its last iteration.
    pub stopped: bool,
    /// Wall seconds of the run.
    pub seconds: f64,
}

/// The trainer: [`TrainerParams`], the ranks it runs over, and a flag
/// that asks it to stop.
#[derive(Debug)]
pub struct Trainer<'w> {
    /// Settings.
    pub params: TrainerParams,
    /// The processes sharing each batch (one, unless under mpirun).
    pub world: &'w World,
    /// Read after every iteration: once set (on any rank), the run saves a
    /// checkpoint and stops ([`Trainer::stop_on`]).
    pub stop: Option<&'w AtomicBool>,
}

/// An objective whose gradients are clipped, their norm before clipping
/// recorded.
struct Clipped<'a> {
    inner: &'a mut dyn Objective,
    max: f64,
    norm: Cell<Option<f64>>,
}

impl Objective for Clipped<'_> {
    fn n_params(&self) -> usize {
        self.inner.n_params()
    }
    fn loss_and_gradient(&mut self, theta: &[f64]) -> Result<(f64, Vec<f64>), TrainError> {
        let (loss, mut g) = self.inner.loss_and_gradient(theta)?;
        self.norm.set(Some(clip_by_norm(&mut g, self.max)));
        Ok((loss, g))
    }
    fn jacobian(&mut self, theta: &[f64], memory_budget: usize) -> Result<BatchJacobian, TrainError> {
        self.inner.jacobian(theta, memory_budget)
    }
    fn pseudo_inverse_update(&mut self, theta: &[f64], hig: &Hig) -> Result<(f64, Vec<f64>), TrainError> {
        self.inner.pseudo_inverse_update(theta, hig)
    }
    fn proxy_gradient(&mut self, theta: &[f64], eta: f64) -> Result<SipGradient, TrainError> {
        let mut s = self.inner.proxy_gradient(theta, eta)?;
        self.norm.set(Some(clip_by_norm(&mut s.grad, self.max)));
        Ok(s)
    }
}

impl<'w> Trainer<'w> {
    /// A trainer with `params` over `world`.
    pub fn new(params: TrainerParams, world: &'w World) -> Self {
        Trainer { params, world, stop: None }
    }

    /// The same trainer, stopping (after a checkpoint) once `flag` is set:
    /// a Ctrl-C handler sets it, a test or a time budget may too.
    pub fn stop_on(self, flag: &'w AtomicBool) -> Self {
        Trainer { stop: Some(flag), ..self }
    }

    /// [`Trainer::run_observed`] with a closure observing the rows:
    /// `observe(row, theta, rule)` after every iteration, which may stop
    /// the run.
    ///
    /// # Errors
    /// As [`Trainer::run_observed`].
    pub fn run<R, O>(
        &self,
        rule: &mut R,
        theta: &mut [f64],
        objective_at: impl FnMut(usize) -> Result<O, TrainError>,
        observe: impl FnMut(&Row, &[f64], &R) -> ControlFlow<()>,
    ) -> Result<Info, TrainError>
    where
        R: UpdateRule + ?Sized,
        O: Objective,
    {
        self.run_observed(rule, theta, objective_at, OnRow(observe))
    }

    /// Runs iterations `first ..= first + iterations − 1`: builds the
    /// iteration's objective, sets the scheduled rate, takes the rule's
    /// step on `theta` (clipped gradients), compares the ranks, and shows
    /// the row to `observer`. The observer's checkpoint is called when the
    /// [`CheckpointPolicy`] is due, after the last iteration, and when the
    /// run stops (the observer asked, or the stop flag was set on any rank:
    /// every rank stops after the same iteration).
    ///
    /// # Errors
    /// The objective's or the rule's error (a non-finite loss or gradient,
    /// a failed rollout, a rule the objective cannot serve), the observer's
    /// (a log or checkpoint that cannot be written), or ranks that no
    /// longer agree; `theta` keeps the last completed update.
    pub fn run_observed<R, O>(
        &self,
        rule: &mut R,
        theta: &mut [f64],
        mut objective_at: impl FnMut(usize) -> Result<O, TrainError>,
        mut observer: impl Observer<R>,
    ) -> Result<Info, TrainError>
    where
        R: UpdateRule + ?Sized,
        O: Objective,
    {
        let p = &self.params;
        let start = Instant::now();
        let mut info = Info { last: p.first.saturating_sub(1), ..Info::default() };
        let last = p.first + p.iterations.saturating_sub(1);
        let (mut saved, mut saved_at) = (info.last, Instant::now());
        for it in p.first..p.first + p.iterations {
            let step_start = Instant::now();
            let mut objective = objective_at(it)?;
            if let Some(lr) = p.schedule.at(it) {
                rule.set_learning_rate(lr);
            }
            let lr = rule.learning_rate();
            let mut clipped = Clipped { inner: &mut objective, max: p.clip, norm: Cell::new(None) };
            let loss = rule.step(&mut clipped, theta)?;
            let step_seconds = step_start.elapsed().as_secs_f64();
            info.last = it;
            if it % p.same_state_every.max(1) == 0 || it == last {
                self.world
                    .check_same("parameters and optimizer state", || format!("iteration {it}"), &[theta, &rule.state_values()])
                    .map_err(|e| TrainError::Distributed(e.to_string()))?;
            }
            let row = Row { iteration: it, loss, grad_norm: clipped.norm.get(), lr, seconds: start.elapsed().as_secs_f64(), step_seconds };
            let asked = observer.row(&row, theta, rule)?.is_break() || self.stop.is_some_and(|f| f.load(Ordering::SeqCst));
            let stop = self.world.any(asked);
            if stop || it == last || p.checkpoint.due(it, saved, saved_at) {
                observer.checkpoint(it, theta, rule)?;
                (saved, saved_at) = (it, Instant::now());
            }
            if stop {
                info.stopped = it < last;
                break;
            }
        }
        info.seconds = start.elapsed().as_secs_f64();
        Ok(info)
    }
}
