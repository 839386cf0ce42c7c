//! Update rules behind one trait ([`UpdateRule`]), and what each asks of
//! the problem ([`Objective`]).
//!
//! A rule takes one update of the parameters `θ` on the objective's
//! current batch and returns the loss before it. The objective offers
//! capabilities, and a rule asks for the one it needs; an objective that
//! lacks it gives [`TrainError::Unsupported`], naming both:
//!
//! | rule | needs | reference |
//! |---|---|---|
//! | [`Sgd`], [`Adam`], [`Optimizer`] | [`Objective::loss_and_gradient`] | Kingma & Ba 2015 (Adam) |
//! | [`Lbfgs`] | the same, on a fixed (full) batch: the line search evaluates it several times | Nocedal & Wright 2006, Alg. 7.4 (argmin's) |
//! | [`Hig`] (half-inverse gradients; `Hig::gauss_newton` for Gauss–Newton) | [`Objective::jacobian`]: the outputs' Jacobian `∂y/∂θ` and `∂L/∂y` | Schnell, Holl & Thuerey, ICLR 2022 |
//! | [`Sip`] (scale-invariant physics) | [`Objective::proxy_gradient`]: the physics' local inverse | Holl, Koltun & Thuerey, NeurIPS 2022 |
//!
//! Objectives for the usual shapes are here: [`ControlBatch`] (a network
//! whose output drives the physics, HIG's setting), [`InverseBatch`] (a
//! network that inverts the physics, SIP's setting), [`RolloutBatch`] (a
//! network inside an unrolled solver, solver-in-the-loop), and
//! [`FnObjective`] (any closure giving a loss and its gradient, e.g. a
//! [`crate::rollout::RolloutLoss`] of one's own solver).

use super::hig::{BatchJacobian, ControlSample, Hig, HigError};
use super::optim::{Adam, AdamParams, Optimizer, Sgd};
use super::pg::{InverseSample, PgError, SipGradient};
use super::{Sample, batch_gradient};
use crate::distributed::World;
use crate::op::{LocalInverse, Vjp};
use crate::rollout::{Checkpointing, RolloutError};

pub use diffsim_solvers::optim::{LbfgsParams, LbfgsStep};

/// An update that could not be made.
#[derive(Clone, Debug, PartialEq, thiserror::Error)]
pub enum TrainError {
    /// The rule needs something the objective does not provide.
    #[error("{rule} needs {needs}, which this objective does not provide")]
    Unsupported {
        /// The rule.
        rule: &'static str,
        /// What it needs.
        needs: &'static str,
    },
    /// The loss or the gradient is not finite.
    #[error("the {what} is not finite ({value})")]
    NonFinite {
        /// Loss or gradient.
        what: &'static str,
        /// The offending value.
        value: f64,
    },
    /// A HIG or Gauss–Newton step failed.
    #[error("{0}")]
    Hig(#[from] HigError),
    /// A physical-gradient step failed.
    #[error("{0}")]
    Pg(#[from] PgError),
    /// A rollout failed (a NaN state, a solver that did not converge).
    #[error("{0}")]
    Rollout(String),
    /// L-BFGS could not make an iteration (its line search found no
    /// decrease, or a trial point's loss was not finite).
    #[error("L-BFGS: {0}")]
    Lbfgs(String),
    /// The objective's own failure.
    #[error("{0}")]
    Objective(String),
    /// The ranks of a distributed run no longer agree.
    #[error("{0}")]
    Distributed(String),
    /// An observer could not do its part (a log or a checkpoint that
    /// cannot be written), in its words.
    #[error("{0}")]
    Observer(String),
}

impl From<RolloutError> for TrainError {
    fn from(e: RolloutError) -> Self {
        TrainError::Rollout(e.to_string())
    }
}

/// What a rule may ask of the problem, at the current batch.
pub trait Objective {
    /// The number of parameters.
    fn n_params(&self) -> usize;

    /// The loss at `θ` and its gradient `∂L/∂θ`.
    fn loss_and_gradient(&mut self, theta: &[f64]) -> Result<(f64, Vec<f64>), TrainError>;

    /// The outputs' Jacobian `∂y/∂θ` (rows: batch × outputs), `∂L/∂y` and
    /// the loss, within `memory_budget` bytes. For [`Hig`].
    fn jacobian(&mut self, theta: &[f64], memory_budget: usize) -> Result<BatchJacobian, TrainError> {
        let _ = (theta, memory_budget);
        Err(TrainError::Unsupported { rule: "HIG / Gauss–Newton", needs: "the outputs' Jacobian (Objective::jacobian)" })
    }

    /// The loss and the update `J^{−power}·∂L/∂y` of `hig` (before its step
    /// size). The default decomposes [`Objective::jacobian`] here; an
    /// objective over several ranks gathers the Jacobian, decomposes it
    /// once and shares the update ([`ControlBatch::over`]).
    fn pseudo_inverse_update(&mut self, theta: &[f64], hig: &Hig) -> Result<(f64, Vec<f64>), TrainError> {
        let j = self.jacobian(theta, hig.memory_budget)?;
        let update = super::hig::update_of(&j, hig)?;
        Ok((j.loss, update))
    }

    /// The physics loss and the gradient of the proxy loss towards the
    /// physics' local inverse with step `eta`. For [`Sip`].
    fn proxy_gradient(&mut self, theta: &[f64], eta: f64) -> Result<SipGradient, TrainError> {
        let _ = (theta, eta);
        Err(TrainError::Unsupported { rule: "SIP", needs: "a local inverse of the physics (Objective::proxy_gradient)" })
    }
}

/// One update rule: SGD, Adam, L-BFGS, HIG, Gauss–Newton, SIP, or one's
/// own.
pub trait UpdateRule {
    /// The rule's name, for logs and messages.
    fn name(&self) -> &'static str;

    /// One update of `theta` on `objective`; returns the loss at `theta`
    /// before the update. On an error `theta` is unchanged.
    fn step(&mut self, objective: &mut dyn Objective, theta: &mut [f64]) -> Result<f64, TrainError>;

    /// The step size, where the rule has one (for schedules).
    fn learning_rate(&self) -> Option<f64> {
        None
    }

    /// Sets the step size (for schedules); rules without one ignore it.
    fn set_learning_rate(&mut self, lr: f64) {
        let _ = lr;
    }

    /// Every number of the rule's state (for the check that the ranks of
    /// a distributed run agree); empty for a rule without state.
    fn state_values(&self) -> Vec<f64> {
        Vec::new()
    }
}

/// The loss and gradient, checked finite.
fn gradient(objective: &mut dyn Objective, theta: &[f64]) -> Result<(f64, Vec<f64>), TrainError> {
    let (loss, g) = objective.loss_and_gradient(theta)?;
    finite(loss, &g)?;
    Ok((loss, g))
}

fn finite(loss: f64, g: &[f64]) -> Result<(), TrainError> {
    if !loss.is_finite() {
        return Err(TrainError::NonFinite { what: "loss", value: loss });
    }
    match g.iter().find(|v| !v.is_finite()) {
        Some(v) => Err(TrainError::NonFinite { what: "gradient", value: *v }),
        None => Ok(()),
    }
}

/// The rule of a gradient optimizer with `update(θ, g)`, `state()` and
/// `params.lr` (SGD, Adam).
macro_rules! gradient_rule {
    ($t:ty, $name:literal) => {
        impl UpdateRule for $t {
            fn name(&self) -> &'static str {
                $name
            }
            fn step(&mut self, objective: &mut dyn Objective, theta: &mut [f64]) -> Result<f64, TrainError> {
                let (loss, g) = gradient(objective, theta)?;
                self.update(theta, &g);
                Ok(loss)
            }
            fn learning_rate(&self) -> Option<f64> {
                Some(self.params.lr)
            }
            fn set_learning_rate(&mut self, lr: f64) {
                self.params.lr = lr;
            }
            fn state_values(&self) -> Vec<f64> {
                self.state()
            }
        }
    };
}

gradient_rule!(Sgd, "SGD");
gradient_rule!(Adam, "Adam");

impl UpdateRule for Optimizer {
    fn name(&self) -> &'static str {
        match self {
            Optimizer::Sgd(s) => s.name(),
            Optimizer::Adam(a) => a.name(),
        }
    }
    fn step(&mut self, objective: &mut dyn Objective, theta: &mut [f64]) -> Result<f64, TrainError> {
        match self {
            Optimizer::Sgd(s) => UpdateRule::step(s, objective, theta),
            Optimizer::Adam(a) => UpdateRule::step(a, objective, theta),
        }
    }
    fn learning_rate(&self) -> Option<f64> {
        Some(self.lr())
    }
    fn set_learning_rate(&mut self, lr: f64) {
        self.set_lr(lr);
    }
    fn state_values(&self) -> Vec<f64> {
        self.state()
    }
}

/// L-BFGS (argmin's, with the More–Thuente line search) for a
/// deterministic objective: a full batch, or one batch held fixed. Its
/// history is forgotten when `θ` is changed between steps by anyone else.
#[derive(Debug)]
pub struct Lbfgs(diffsim_solvers::optim::Lbfgs);

impl Lbfgs {
    /// L-BFGS with `params` (`LbfgsParams::default()`: 10 pairs).
    ///
    /// # Errors
    /// A setting out of range, named.
    pub fn new(params: LbfgsParams) -> Result<Self, TrainError> {
        diffsim_solvers::optim::Lbfgs::new(params).map(Lbfgs).map_err(TrainError::Lbfgs)
    }

    /// One iteration, with what it did (moved, and how far the loss fell,
    /// or converged).
    pub fn iterate(&mut self, objective: &mut dyn Objective, theta: &mut [f64]) -> Result<LbfgsStep, TrainError> {
        // The objective's own error, kept whole (the line search sees a
        // message).
        let mut failure = None;
        let mut f = |x: &[f64]| match objective.loss_and_gradient(x) {
            Ok(v) => Ok(v),
            Err(e) => {
                let m = e.to_string();
                failure = Some(e);
                Err(m)
            }
        };
        let r = self.0.step(&mut f, theta);
        match (r, failure) {
            (Ok(s), _) => Ok(s),
            (Err(_), Some(e)) => Err(e),
            (Err(m), None) => Err(TrainError::Lbfgs(m)),
        }
    }
}

impl UpdateRule for Lbfgs {
    fn name(&self) -> &'static str {
        "L-BFGS"
    }
    fn step(&mut self, objective: &mut dyn Objective, theta: &mut [f64]) -> Result<f64, TrainError> {
        match self.iterate(objective, theta)? {
            LbfgsStep::Moved { loss_before, .. } => Ok(loss_before),
            LbfgsStep::Converged { loss } => Ok(loss),
        }
    }
}

impl UpdateRule for Hig {
    fn name(&self) -> &'static str {
        if self.power == 1.0 { "Gauss–Newton" } else { "HIG" }
    }
    fn step(&mut self, objective: &mut dyn Objective, theta: &mut [f64]) -> Result<f64, TrainError> {
        let (loss, update) = objective.pseudo_inverse_update(theta, self)?;
        for (t, d) in theta.iter_mut().zip(&update) {
            *t -= self.lr * d;
        }
        Ok(loss)
    }
    fn learning_rate(&self) -> Option<f64> {
        Some(self.lr)
    }
    fn set_learning_rate(&mut self, lr: f64) {
        self.lr = lr;
    }
}

/// Scale-invariant physics (SIP): the network is trained by Adam on the
/// proxy loss towards `x + P⁻¹(η·(y* − y); x)`; `eta` is the physics step
/// (1 in the published runs).
#[derive(Clone, Debug, PartialEq)]
pub struct Sip {
    /// The physics step size η.
    pub eta: f64,
    /// The optimizer of the proxy loss.
    pub adam: Adam,
}

impl Sip {
    /// SIP with physics step `eta` and Adam on the proxy at `adam`.
    pub fn new(eta: f64, adam: AdamParams) -> Self {
        Sip { eta, adam: Adam::new(adam) }
    }
}

impl UpdateRule for Sip {
    fn state_values(&self) -> Vec<f64> {
        self.adam.state()
    }
    fn name(&self) -> &'static str {
        "SIP"
    }
    /// Returns the physics loss before the update.
    fn step(&mut self, objective: &mut dyn Objective, theta: &mut [f64]) -> Result<f64, TrainError> {
        let s = objective.proxy_gradient(theta, self.eta)?;
        finite(s.physics_loss, &s.grad)?;
        self.adam.update(theta, &s.grad);
        Ok(s.physics_loss)
    }
    fn learning_rate(&self) -> Option<f64> {
        Some(self.adam.params.lr)
    }
    fn set_learning_rate(&mut self, lr: f64) {
        self.adam.params.lr = lr;
    }
}

/// A network `N(·; θ)` whose output drives the physics `P`, on a batch of
/// [`ControlSample`]s (HIG's setting): loss `(1/B)·Σ‖P(x₀, N(y*)) − y*‖²`.
/// Over the ranks of an mpirun ([`ControlBatch::over`]) each rank holds its
/// share of the batch; gradients are reduced and HIG's Jacobian decomposed
/// once, on rank 0, for all.
pub struct ControlBatch<'a, P, N> {
    physics: &'a P,
    net: &'a N,
    batch: &'a [ControlSample],
    world: Option<(&'a World, usize)>,
}

impl<'a, P, N> ControlBatch<'a, P, N> {
    /// The whole batch in this process.
    pub fn new(physics: &'a P, net: &'a N, batch: &'a [ControlSample]) -> Self {
        ControlBatch { physics, net, batch, world: None }
    }

    /// This rank's share `batch` of a batch of `batch_len` samples shared
    /// among the ranks of `world` ([`World::share`]).
    pub fn over(mut self, world: &'a World, batch_len: usize) -> Self {
        self.world = Some((world, batch_len));
        self
    }
}

impl<P: Vjp + Sync, N: Vjp + Sync> Objective for ControlBatch<'_, P, N> {
    fn n_params(&self) -> usize {
        self.net.n_params()
    }
    fn loss_and_gradient(&mut self, theta: &[f64]) -> Result<(f64, Vec<f64>), TrainError> {
        Ok(match self.world {
            None => super::hig::loss_and_gradient(self.physics, self.net, theta, self.batch),
            Some((world, len)) => super::hig::loss_and_gradient_over(world, self.physics, self.net, theta, self.batch, len),
        })
    }
    fn jacobian(&mut self, theta: &[f64], memory_budget: usize) -> Result<BatchJacobian, TrainError> {
        if self.world.is_some_and(|(w, _)| w.size() > 1) {
            return Err(TrainError::Unsupported { rule: "a Jacobian over several ranks", needs: "one process (HIG's step decomposes it on rank 0)" });
        }
        Ok(super::hig::batch_jacobian(self.physics, self.net, theta, self.batch, memory_budget)?)
    }
    fn pseudo_inverse_update(&mut self, theta: &[f64], hig: &Hig) -> Result<(f64, Vec<f64>), TrainError> {
        let single = World::single();
        let (world, len) = self.world.unwrap_or((&single, self.batch.len()));
        Ok(super::hig::update_over(world, self.physics, self.net, theta, self.batch, len, hig)?)
    }
}

/// A network that inverts the physics, on a batch of [`InverseSample`]s
/// (SIP's setting): loss `(1/B)·Σ ½‖P(N(y*)) − y*‖²`. The batch is
/// borrowed or owned (drawn afresh for the iteration).
pub struct InverseBatch<'a, P, N> {
    physics: &'a P,
    net: &'a N,
    batch: std::borrow::Cow<'a, [InverseSample]>,
}

impl<'a, P, N> InverseBatch<'a, P, N> {
    /// The objective of `net` through `physics` on `batch`.
    pub fn new(physics: &'a P, net: &'a N, batch: impl Into<std::borrow::Cow<'a, [InverseSample]>>) -> Self {
        InverseBatch { physics, net, batch: batch.into() }
    }
}

impl<P: LocalInverse + Vjp + Sync, N: Vjp + Sync> Objective for InverseBatch<'_, P, N> {
    fn n_params(&self) -> usize {
        self.net.n_params()
    }
    fn loss_and_gradient(&mut self, theta: &[f64]) -> Result<(f64, Vec<f64>), TrainError> {
        Ok(super::pg::physics_loss_and_gradient(self.physics, self.net, theta, &self.batch)?)
    }
    fn proxy_gradient(&mut self, theta: &[f64], eta: f64) -> Result<SipGradient, TrainError> {
        Ok(super::pg::sip_gradient(self.physics, self.net, theta, &self.batch, eta)?)
    }
}

/// Unrolled rollouts of `op` (a solver step with a network inside, e.g.
/// [`super::Coupled`]) from each sample's start, the loss at `loss_steps`
/// (solver-in-the-loop's setting; [`batch_gradient`]). Over the ranks of
/// an mpirun ([`RolloutBatch::over`]) each rank unrolls its share and the
/// sums run in sample order ([`super::batch_gradient_over`]).
pub struct RolloutBatch<'a, O> {
    op: &'a O,
    unroll: usize,
    loss_steps: &'a [usize],
    batch: &'a [Sample],
    mode: Checkpointing,
    world: Option<(&'a World, usize)>,
}

impl<'a, O> RolloutBatch<'a, O> {
    /// `op` (the network's weights its parameters) unrolled `unroll` steps
    /// from every sample of `batch`, the loss at `loss_steps`, the states
    /// kept as `mode` says; the whole batch in this process.
    pub fn new(op: &'a O, unroll: usize, loss_steps: &'a [usize], batch: &'a [Sample], mode: Checkpointing) -> Self {
        RolloutBatch { op, unroll, loss_steps, batch, mode, world: None }
    }

    /// This rank's share `batch` of a batch of `batch_len` samples shared
    /// among the ranks of `world` ([`World::share`]).
    pub fn over(mut self, world: &'a World, batch_len: usize) -> Self {
        self.world = Some((world, batch_len));
        self
    }
}

impl<O: Vjp + Sync> Objective for RolloutBatch<'_, O> {
    fn n_params(&self) -> usize {
        self.op.n_params()
    }
    fn loss_and_gradient(&mut self, theta: &[f64]) -> Result<(f64, Vec<f64>), TrainError> {
        let r = match self.world {
            None => batch_gradient(self.op, theta, self.unroll, self.loss_steps, self.batch, self.mode),
            Some((world, len)) => super::batch_gradient_over(world, self.op, theta, self.unroll, self.loss_steps, self.batch, len, self.mode),
        };
        Ok(r?)
    }
}

/// Any closure giving the loss and its gradient at `θ`, with `n` parameters.
pub struct FnObjective<F> {
    /// The number of parameters.
    pub n: usize,
    /// The loss and its gradient.
    pub f: F,
}

impl<F: FnMut(&[f64]) -> Result<(f64, Vec<f64>), TrainError>> Objective for FnObjective<F> {
    fn n_params(&self) -> usize {
        self.n
    }
    fn loss_and_gradient(&mut self, theta: &[f64]) -> Result<(f64, Vec<f64>), TrainError> {
        (self.f)(theta)
    }
}
