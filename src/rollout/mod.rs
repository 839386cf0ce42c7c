//! Rollouts: `T` steps of an operator `x_{t+1} = f(x_t, p_t)`, a loss on
//! the final state or on any listed steps, and its gradient by per-step
//! VJPs chained backwards. The parameters are the same at every step
//! ([`Rollout::new`]) or given per step ([`Rollout::per_step`], e.g. a
//! time-varying control), with the gradient in the same shape.
//!
//! The backward pass needs every state `x_t` in reverse order. How they are
//! kept is a [`Checkpointing`] mode:
//!
//! | mode | states held | step evaluations |
//! |------|-------------|------------------|
//! | [`Checkpointing::Store`] | `T` | `T` |
//! | [`Checkpointing::Periodic`]`{ every: k }` | `⌈T/k⌉ + k` | `≈ 2T` |
//! | [`Checkpointing::Binomial`]`{ snapshots: s }` | `s + 2` | `≈ r·T`, `r` the smallest with `C(s+r, s) ≥ T` |
//!
//! All modes compute the same floating-point operations on the same states,
//! so their gradients agree to rounding (in practice bit for bit).
//!
//! With two or more rayon threads and a `Sync` operator and loss,
//! [`Rollout::value_and_grad_pipelined_in`] runs the periodic backward pass
//! on two threads: each recomputes a segment and then reverses it, while
//! the other does the same with the next one (same result, bit for bit;
//! one more segment of `k − 1` states held; P1's hand gradient at 16384
//! cells, with its steps also split over the two threads: 18 ms instead of
//! 26 ms in one run).
//! [`RolloutStats`] reports what each run held and recomputed.

mod checkpoint;
mod operator;
pub mod plan;

use thiserror::Error;

use crate::op::{Forward, Real, Vjp};

pub use checkpoint::{Checkpointing, Workspace};
pub use operator::{Repeat, RolloutLoss, RolloutOperator, Wrt};

/// Errors of a rollout.
///
/// Deliberately free of pointers (no `String`, no `&str`): a `Result` whose
/// `Ok` holds `Vec<f64>` and whose `Err` holds a string crashes rustc's
/// Enzyme type-tree emission in crates built with `-Zautodiff=Enable`
/// (docs/pitfalls.md).
#[derive(Debug, Error, Clone, Copy, PartialEq)]
pub enum RolloutError {
    /// The operator does not map a state to a state of the same size.
    #[error("a rollout needs an operator with n_in == n_out (got n_in = {n_in}, n_out = {n_out})")]
    NotAStateMap {
        /// Input size.
        n_in: usize,
        /// Output size.
        n_out: usize,
    },
    /// A slice given to the rollout has the wrong length.
    #[error("`{what}` has length {got}, expected {expected}")]
    Length {
        /// Which argument.
        what: Argument,
        /// Its length.
        got: usize,
        /// The length the operator needs.
        expected: usize,
    },
    /// The operator failed (e.g. its linear solve did not converge).
    #[error("in the {pass} pass: {error}")]
    Operator {
        /// Which pass.
        pass: Pass,
        /// What failed.
        error: crate::op::OpError,
    },
    /// Every state is finite but the loss is not (a term overflowed, or
    /// the loss function returned NaN).
    #[error(
        "the loss is not finite ({value}) though every state of the rollout is: a loss term overflowed or is NaN (values too large to square and sum in f64?)"
    )]
    LossNotFinite {
        /// The loss.
        value: f64,
    },
    /// A non-finite value appeared in the forward or backward pass.
    #[error("non-finite value (NaN or infinity) in the {pass} pass at step {step} (operator {operator})")]
    NonFinite {
        /// Which pass.
        pass: Pass,
        /// Forward: the operator (or the part of a composite one) whose
        /// output held it; backward: the rollout's step operator.
        operator: crate::op::OpName,
        /// Forward: the step whose output held it (0-based). Backward: the
        /// step `t` whose adjoint `∂L/∂x_t` held it first (checked once per
        /// step, from the last); `t = T` means the loss gradient itself.
        step: usize,
    },
}

/// The arguments of a rollout, for error messages.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Argument {
    /// The initial state.
    X0,
    /// The parameters.
    P,
    /// The number of steps.
    Steps,
}

impl std::fmt::Display for Argument {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.write_str(match self {
            Argument::X0 => "x0",
            Argument::P => "p",
            Argument::Steps => "steps",
        })
    }
}

/// Forward or backward pass, for error messages.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Pass {
    /// The forward pass (states).
    Forward,
    /// The backward pass (adjoints).
    Backward,
}

impl std::fmt::Display for Pass {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.write_str(match self {
            Pass::Forward => "forward",
            Pass::Backward => "backward",
        })
    }
}

/// A loss on the states of a rollout: `L = Σ_t ℓ_t(x_t)` over the steps
/// `t ∈ 1..=T` that have a term.
///
/// A closure `Fn(&[f64], &mut [f64]) -> f64` is a loss on the final state
/// only; [`AtSteps`] puts terms at listed steps. States may be `f32`
/// (`Loss<f32>`); the loss value is always `f64`.
pub trait Loss<R = f64> {
    /// Whether step `t` (of `steps`) has a term.
    fn has_term(&self, t: usize, steps: usize) -> bool;
    /// `ℓ_t(x)`, writing `∂ℓ_t/∂x` into `grad` (overwrites); called only
    /// for steps that [`Loss::has_term`].
    fn term(&self, t: usize, x: &[R], grad: &mut [R]) -> f64;
}

impl<R: Real, F: Fn(&[R], &mut [R]) -> f64> Loss<R> for F {
    fn has_term(&self, t: usize, steps: usize) -> bool {
        t == steps
    }
    fn term(&self, _t: usize, y: &[R], grad: &mut [R]) -> f64 {
        self(y, grad)
    }
}

/// A loss with terms at listed steps: `L = Σ_{t ∈ steps} f(t, x_t)`, where
/// `f(t, x, grad)` returns `ℓ_t(x)` and writes its gradient (overwrites).
#[derive(Clone, Debug)]
pub struct AtSteps<F> {
    /// The steps (1-based; `T` is the last state) with a term.
    pub steps: Vec<usize>,
    /// The term.
    pub f: F,
}

impl<R: Real, F: Fn(usize, &[R], &mut [R]) -> f64> Loss<R> for AtSteps<F> {
    fn has_term(&self, t: usize, _steps: usize) -> bool {
        self.steps.contains(&t)
    }
    fn term(&self, t: usize, x: &[R], grad: &mut [R]) -> f64 {
        (self.f)(t, x, grad)
    }
}

/// What a gradient computation held in memory and recomputed.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq)]
pub struct RolloutStats {
    /// Steps of the rollout.
    pub steps: usize,
    /// Step evaluations, the forward pass and all recomputation included.
    pub step_evaluations: usize,
    /// Largest number of state vectors held at once (checkpoints and
    /// working buffers, adjoint buffers excluded).
    pub peak_states: usize,
    /// `peak_states` in bytes.
    pub peak_state_bytes: usize,
}

/// Loss and gradient of a rollout.
#[derive(Clone, Debug)]
pub struct Gradient<R = f64> {
    /// `L`.
    pub loss: f64,
    /// `∂L/∂x_0`.
    pub dx0: Vec<R>,
    /// `∂L/∂p`, shaped like the rollout's `p` (per step if it is).
    pub dp: Vec<R>,
    /// Memory and recomputation of this run.
    pub stats: RolloutStats,
}

/// A rollout of `steps` steps of `op` with parameters `p`, on values of
/// type `R` (`f64` unless said otherwise). It holds references only, so it
/// is `Copy` whatever the operator.
#[derive(Debug)]
pub struct Rollout<'a, O, R = f64> {
    /// The step operator.
    pub op: &'a O,
    /// Its parameters: the same at every step, or `steps` blocks of
    /// `op.n_params()`, block `t` used by the step from `x_t`.
    pub p: &'a [R],
    /// Number of steps `T`.
    pub steps: usize,
    /// Whether `p` holds one block per step.
    pub per_step: bool,
}

impl<O, R> Clone for Rollout<'_, O, R> {
    fn clone(&self) -> Self {
        *self
    }
}

impl<O, R> Copy for Rollout<'_, O, R> {}

impl<'a, R: Real, O: Forward<R>> Rollout<'a, O, R> {
    /// A rollout of `steps` steps; checks that `op` maps states to states and
    /// that `p` has the operator's parameter length.
    pub fn new(op: &'a O, p: &'a [R], steps: usize) -> Result<Self, RolloutError> {
        if op.n_in() != op.n_out() {
            return Err(RolloutError::NotAStateMap { n_in: op.n_in(), n_out: op.n_out() });
        }
        if p.len() != op.n_params() {
            return Err(RolloutError::Length { what: Argument::P, got: p.len(), expected: op.n_params() });
        }
        Ok(Self { op, p, steps, per_step: false })
    }

    /// A rollout whose parameters change from step to step: `p` holds
    /// `steps` blocks of `op.n_params()` values, block `t` for the step
    /// `x_t → x_{t+1}`.
    pub fn per_step(op: &'a O, p: &'a [R], steps: usize) -> Result<Self, RolloutError> {
        let mut r = Self::new(op, &p[..op.n_params().min(p.len())], steps)?;
        if p.len() != steps * op.n_params() {
            return Err(RolloutError::Length { what: Argument::P, got: p.len(), expected: steps * op.n_params() });
        }
        r.p = p;
        r.per_step = true;
        Ok(r)
    }

    /// The parameters of the step from `x_t`.
    pub fn p_at(&self, t: usize) -> &'a [R] {
        &self.p[self.block(t)]
    }

    /// Where the step from `x_t` finds its part of a vector shaped like `p`
    /// (the parameters, or a tangent or gradient of them): block `t` when
    /// the parameters are per step, else all of it.
    fn block(&self, t: usize) -> std::ops::Range<usize> {
        let np = self.op.n_params();
        if self.per_step { t * np..(t + 1) * np } else { 0..self.p.len() }
    }

    fn check_state(&self, x0: &[R]) -> Result<(), RolloutError> {
        if x0.len() != self.op.n_in() {
            return Err(RolloutError::Length { what: Argument::X0, got: x0.len(), expected: self.op.n_in() });
        }
        Ok(())
    }

    fn final_state_unchecked(&self, x0: &[R]) -> Vec<R> {
        self.run_unchecked(x0, |_, _| {})
    }

    /// Runs all steps, calling `visit(t, x_t)` for `t = 1..=T`.
    fn run_unchecked(&self, x0: &[R], mut visit: impl FnMut(usize, &[R])) -> Vec<R> {
        let mut x = x0.to_vec();
        let mut y = vec![R::zero(); x.len()];
        for t in 0..self.steps {
            self.op.forward(&x, self.p_at(t), &mut y);
            std::mem::swap(&mut x, &mut y);
            visit(t + 1, &x);
        }
        x
    }

    /// The final state `x_T` (two state buffers, nothing stored).
    pub fn final_state(&self, x0: &[R]) -> Result<Vec<R>, RolloutError> {
        self.check_state(x0)?;
        let x = self.final_state_unchecked(x0);
        if let Some(error) = Forward::<R>::take_error(self.op) {
            return Err(RolloutError::Operator { pass: Pass::Forward, error });
        }
        if !all_finite(&x) {
            return Err(self.non_finite_forward(x0, 0.0));
        }
        Ok(x)
    }

    /// The loss without gradient.
    pub fn loss(&self, x0: &[R], loss: &impl Loss<R>) -> Result<f64, RolloutError> {
        self.check_state(x0)?;
        let mut g = vec![R::zero(); x0.len()];
        let mut value = if self.steps == 0 && loss.has_term(0, 0) { loss.term(0, x0, &mut g) } else { 0.0 };
        let x = self.run_unchecked(x0, |t, x| {
            if loss.has_term(t, self.steps) {
                value += loss.term(t, x, &mut g);
            }
        });
        if let Some(error) = Forward::<R>::take_error(self.op) {
            return Err(RolloutError::Operator { pass: Pass::Forward, error });
        }
        if !all_finite(&x) || !value.is_finite() {
            return Err(self.non_finite_forward(x0, value));
        }
        Ok(value)
    }

    /// Replays the rollout to find the first step whose output is not
    /// finite and the operator that produced it (only called once something
    /// already went wrong); step `T` if every state is finite (the loss is
    /// not: [`RolloutError::LossNotFinite`] with `loss`).
    fn non_finite_forward(&self, x0: &[R], loss: f64) -> RolloutError {
        let mut x = x0.to_vec();
        let mut y = vec![R::zero(); x.len()];
        for t in 0..self.steps {
            self.op.forward(&x, self.p_at(t), &mut y);
            if !all_finite(&y) {
                return RolloutError::NonFinite { pass: Pass::Forward, step: t, operator: Forward::<R>::locate_non_finite(self.op, &x, self.p_at(t)) };
            }
            std::mem::swap(&mut x, &mut y);
        }
        RolloutError::LossNotFinite { value: loss }
    }
}

impl<R: Real, O: Vjp<R>> Rollout<'_, O, R> {
    /// The loss and its gradients with respect to `x_0` and `p`, by
    /// per-step VJPs over states kept as `mode` says.
    pub fn value_and_grad(&self, x0: &[R], loss: &impl Loss<R>, mode: Checkpointing) -> Result<Gradient<R>, RolloutError> {
        self.value_and_grad_in(&mut Workspace::new(), x0, loss, mode)
    }

    /// [`Rollout::value_and_grad`] reusing the buffers of `ws` (for repeated
    /// gradients, as in training).
    pub fn value_and_grad_in(&self, ws: &mut Workspace<R>, x0: &[R], loss: &impl Loss<R>, mode: Checkpointing) -> Result<Gradient<R>, RolloutError> {
        self.grad_with(ws, x0, loss, mode, None)
    }

    /// [`Rollout::value_and_grad_in`] on two threads of the current rayon
    /// pool: under periodic checkpointing each thread in turn recomputes a
    /// segment's states and reverses them, so that one thread's
    /// recomputation overlaps the other's reversal and each reads the
    /// states from its own cache (the adjoint passes between the threads
    /// once per segment). Same floating-point operations on the same states
    /// as the one-thread version, so the same result bit for bit; needs an
    /// operator and a loss that can be shared between threads (`Sync`) and
    /// one more segment of memory. A panic on either thread reaches the
    /// caller. With one thread in the pool, or in the other modes, it is
    /// [`Rollout::value_and_grad_in`].
    pub fn value_and_grad_pipelined_in<L: Loss<R> + Sync>(
        &self,
        ws: &mut Workspace<R>,
        x0: &[R],
        loss: &L,
        mode: Checkpointing,
    ) -> Result<Gradient<R>, RolloutError>
    where
        O: Sync,
    {
        if rayon::current_num_threads() < 2 {
            return self.grad_with(ws, x0, loss, mode, None);
        }
        self.grad_with(ws, x0, loss, mode, Some(checkpoint::reverse_two_threads::<R, O, L>))
    }

    fn grad_with<L: Loss<R>>(
        &self,
        ws: &mut Workspace<R>,
        x0: &[R],
        loss: &L,
        mode: Checkpointing,
        two_threads: Option<checkpoint::TwoThreads<O, L, R>>,
    ) -> Result<Gradient<R>, RolloutError> {
        self.check_state(x0)?;
        Forward::<R>::take_error(self.op);
        let g = match checkpoint::run(self, ws, x0, loss, mode, checkpoint::CHECK_EVERY, two_threads) {
            Err(RolloutError::NonFinite { pass: Pass::Backward, .. }) => {
                // A failed solve or a NaN in the forward pass is the cause.
                if let Some(error) = Forward::<R>::take_error(self.op) {
                    return Err(RolloutError::Operator { pass: Pass::Backward, error });
                }
                if let e @ RolloutError::NonFinite { .. } = self.non_finite_forward(x0, 0.0) {
                    return Err(e);
                }
                // Found at a periodic check: run again checking every step
                // to name the step where it entered the adjoint.
                let step = match checkpoint::run(self, ws, x0, loss, mode, 1, None) {
                    Err(RolloutError::NonFinite { pass: Pass::Backward, step, .. }) => step,
                    _ => 0,
                };
                return Err(RolloutError::NonFinite { pass: Pass::Backward, step, operator: Forward::<R>::name(self.op) });
            }
            g => g?,
        };
        if let Some(error) = Forward::<R>::take_error(self.op) {
            return Err(RolloutError::Operator { pass: Pass::Backward, error });
        }
        if !g.loss.is_finite() {
            return Err(self.non_finite_forward(x0, g.loss));
        }
        if !all_finite(&g.dx0) || !all_finite(&g.dp) {
            return Err(RolloutError::NonFinite { pass: Pass::Backward, step: 0, operator: Forward::<R>::name(self.op) });
        }
        Ok(g)
    }
}

/// Whether every value is finite (no NaN, no infinity); the operator core's
/// [`crate::op::all_finite`], re-exported where rollouts use it.
pub use crate::op::all_finite;
