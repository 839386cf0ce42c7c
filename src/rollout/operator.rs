//! Whole rollouts as operators, so that the gradient checks of
//! [`crate::check`] apply to them:
//!
//! - [`RolloutLoss`]: `(x_0, p) ↦ L`, the loss of a rollout (terms at any
//!   steps) as a function of the initial state, the parameters, or both
//!   ([`Wrt`]). Its VJP is [`Rollout::value_and_grad`]; its JVP chains the
//!   per-step JVPs and the loss terms' gradients, an independent forward-mode
//!   computation for the dot-product test.
//! - [`RolloutOperator`]: `x_0 ↦ x_T`, the final state as a function of the
//!   initial one (the parameters held fixed).
//! - [`Repeat`]: `(x_0, p) ↦ x_T`, an owned operator of the initial state
//!   and the parameters shared by every step, its checkpointing chosen by
//!   the memory budget.
//!
//! ```ignore
//! use diffsim::check::{CheckParams, check_all};
//! use diffsim::rollout::{AtSteps, Checkpointing, Rollout, RolloutLoss, Wrt};
//!
//! let loss = AtSteps { steps: vec![10, 20], f: |_t: usize, x: &[f64], g: &mut [f64]| {
//!     g.copy_from_slice(x);
//!     0.5 * x.iter().map(|v| v * v).sum::<f64>()
//! } };
//! let rollout = Rollout::new(&op, &p, 20)?;
//! let as_op = RolloutLoss::new(rollout, &x0, &loss, Checkpointing::periodic_sqrt(20), Wrt::Both)?;
//! let (x, p) = as_op.point();
//! let report = check_all(&as_op, x, p, &CheckParams::default()); // ∂L/∂x0 and ∂L/∂p
//! ```

use super::checkpoint::{self, Checkpointing, Workspace};
use super::{Loss, Rollout, RolloutError};
use crate::op::{Forward, Jvp, Operator, Vjp};

/// Which inputs of a rollout a [`RolloutLoss`] takes: the others are held
/// at the values it was built with.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Wrt {
    /// The initial state `x_0` is the operator's state input; `p` is fixed
    /// (the operator has no parameters).
    X0,
    /// The parameters `p` (per step if the rollout's are) are the
    /// operator's parameters; `x_0` is fixed (its state input is empty).
    P,
    /// Both: state input `x_0`, parameters `p`.
    Both,
}

impl Wrt {
    fn x0(self) -> bool {
        matches!(self, Wrt::X0 | Wrt::Both)
    }
    fn p(self) -> bool {
        matches!(self, Wrt::P | Wrt::Both)
    }
}

/// The loss of a whole rollout as an operator `(x_0, p) ↦ L` with one
/// output, so that [`check_all`](crate::check::check_all) checks `∂L/∂x_0`
/// and `∂L/∂p` through every step, with loss terms at any steps
/// ([`AtSteps`](super::AtSteps)).
///
/// The operator's state input is `x_0` when [`Wrt`] includes it (else
/// empty), its parameters are `p` when [`Wrt`] includes them (else none);
/// [`RolloutLoss::point`] gives the matching `(x, p)` to check at.
///
/// - Forward: the loss, [`Rollout::loss`].
/// - VJP: `dx += dy·∂L/∂x_0`, `dp += dy·∂L/∂p` from
///   [`Rollout::value_and_grad`] under the chosen checkpointing (consumes
///   `dy`).
/// - JVP: the tangent carried forward through the per-step JVPs,
///   `L̇ = Σ_t ⟨∇ℓ_t(x_t), ẋ_t⟩`: forward mode, independent of the VJP.
///
/// # Panics
/// The operator methods panic with the rollout's error (a non-finite
/// value, a failed solve) since they return nothing; a check that hits one
/// is not a check of the gradient.
#[derive(Debug)]
pub struct RolloutLoss<'a, O, L> {
    rollout: Rollout<'a, O>,
    x0: &'a [f64],
    loss: &'a L,
    mode: Checkpointing,
    wrt: Wrt,
}

impl<O, L> Clone for RolloutLoss<'_, O, L> {
    fn clone(&self) -> Self {
        *self
    }
}

impl<O, L> Copy for RolloutLoss<'_, O, L> {}

impl<'a, O: Jvp, L: Loss> RolloutLoss<'a, O, L> {
    /// The loss of `rollout` from `x0` as an operator of the inputs `wrt`
    /// names; the rollout's `p` and `x0` are the values of the inputs held
    /// fixed and the point [`RolloutLoss::point`] returns. `mode` is the
    /// checkpointing of the VJP (a default for `T` steps:
    /// `Checkpointing::periodic_sqrt(T)`).
    ///
    /// # Errors
    /// [`RolloutError::Length`] if `x0` is not a state of the operator.
    pub fn new(rollout: Rollout<'a, O>, x0: &'a [f64], loss: &'a L, mode: Checkpointing, wrt: Wrt) -> Result<Self, RolloutError> {
        rollout.check_state(x0)?;
        Ok(Self { rollout, x0, loss, mode: mode.resolve(rollout.steps), wrt })
    }

    /// The point `(x, p)` at which to check: `x_0` (or nothing) and `p` (or
    /// nothing), as [`Wrt`] says.
    pub fn point(&self) -> (&'a [f64], &'a [f64]) {
        (if self.wrt.x0() { self.x0 } else { &[] }, if self.wrt.p() { self.rollout.p } else { &[] })
    }

    /// The rollout at the operator's inputs `(x, p)`: `(x_0, rollout)`.
    #[track_caller]
    fn at<'b>(&'b self, x: &'b [f64], p: &'b [f64]) -> (&'b [f64], Rollout<'b, O>) {
        crate::op::check_lengths(self, "RolloutLoss (`point()` gives the inputs)", x, p, None);
        let x0 = if self.wrt.x0() { x } else { self.x0 };
        let mut r = self.rollout;
        if self.wrt.p() {
            r.p = p;
        }
        (x0, r)
    }
}

impl<O: Forward, L: Loss> Operator for RolloutLoss<'_, O, L> {
    fn n_in(&self) -> usize {
        if self.wrt.x0() { self.rollout.op.n_in() } else { 0 }
    }
    fn n_out(&self) -> usize {
        1
    }
    fn n_params(&self) -> usize {
        if self.wrt.p() { self.rollout.p.len() } else { 0 }
    }
}

impl<O: Jvp, L: Loss> Forward for RolloutLoss<'_, O, L> {
    /// `y[0] = L(x_0, p)`.
    #[track_caller]
    fn forward(&self, x: &[f64], p: &[f64], y: &mut [f64]) {
        let (x0, r) = self.at(x, p);
        y[0] = r.loss(x0, self.loss).unwrap_or_else(|e| panic!("RolloutLoss: {e}"));
    }

    /// The step's solve tolerance times the number of steps.
    fn solve_tolerance(&self) -> f64 {
        self.rollout.op.solve_tolerance() * self.rollout.steps as f64
    }

    /// The smallest radius of the steps, each at its state along the
    /// tangent the JVPs carry to it (first order, as [`crate::op::Chain`]'s).
    fn smooth_radius(&self, x: &[f64], p: &[f64], dx: &[f64], dp: &[f64]) -> f64 {
        let (x0, r) = self.at(x, p);
        let zero = vec![0.0; x0.len()];
        let tx = if self.wrt.x0() { dx } else { &zero[..] };
        let zero_tp = vec![0.0; r.op.n_params()];
        rollout_radius(&r, x0, tx, |t| if self.wrt.p() { &dp[r.block(t)] } else { &zero_tp[..] })
    }
}

/// The smallest kink radius over the steps of `r` from `x0` along the
/// tangent `tx` (and `tp(t)` for step `t`'s parameters), each step's radius
/// taken at its state along the tangent its predecessors' JVPs carry to it.
fn rollout_radius<'b, O: Jvp>(r: &Rollout<'_, O>, x0: &[f64], tx: &[f64], tp: impl Fn(usize) -> &'b [f64]) -> f64 {
    let mut radius = f64::INFINITY;
    carry_tangent(r, x0, tx, tp, |t, x, tx, tp| radius = radius.min(r.op.smooth_radius(x, r.p_at(t), tx, tp)), |_, _, _| {});
    // Errors are the forward pass's to report.
    let _ = r.op.take_error();
    radius
}

/// Carries `(x_0, tx)` through the steps of `r` by their JVPs (step `t`
/// with the parameter tangent `tp(t)`): `before(t, x_t, t_t, tp(t))` sees
/// each step's input, `after(t + 1, x_{t+1}, t_{t+1})` its output.
/// Returns `(x_T, t_T)`.
fn carry_tangent<'b, O: Jvp>(
    r: &Rollout<'_, O>,
    x0: &[f64],
    tx: &[f64],
    tp: impl Fn(usize) -> &'b [f64],
    mut before: impl FnMut(usize, &[f64], &[f64], &[f64]),
    mut after: impl FnMut(usize, &[f64], &[f64]),
) -> (Vec<f64>, Vec<f64>) {
    let n = x0.len();
    let (mut xc, mut tc) = (x0.to_vec(), tx.to_vec());
    let (mut xn, mut tn) = (vec![0.0; n], vec![0.0; n]);
    for t in 0..r.steps {
        let tp_t = tp(t);
        before(t, &xc, &tc, tp_t);
        r.op.jvp(&xc, r.p_at(t), &tc, tp_t, &mut xn, &mut tn);
        std::mem::swap(&mut xc, &mut xn);
        std::mem::swap(&mut tc, &mut tn);
        after(t + 1, &xc, &tc);
    }
    (xc, tc)
}

impl<O: Vjp + Jvp, L: Loss> Vjp for RolloutLoss<'_, O, L> {
    #[track_caller]
    fn vjp(&self, x: &[f64], p: &[f64], dy: &mut [f64], dx: &mut [f64], dp: &mut [f64]) {
        let (x0, r) = self.at(x, p);
        let g = r.value_and_grad(x0, self.loss, self.mode).unwrap_or_else(|e| panic!("RolloutLoss: {e}"));
        let s = dy[0];
        if self.wrt.x0() {
            dx.iter_mut().zip(&g.dx0).for_each(|(d, v)| *d += s * v);
        }
        if self.wrt.p() {
            dp.iter_mut().zip(&g.dp).for_each(|(d, v)| *d += s * v);
        }
        dy[0] = 0.0;
    }
}

impl<O: Jvp, L: Loss> Jvp for RolloutLoss<'_, O, L> {
    #[track_caller]
    fn jvp(&self, x: &[f64], p: &[f64], tx: &[f64], tp: &[f64], y: &mut [f64], ty: &mut [f64]) {
        let (x0, r) = self.at(x, p);
        let n = x0.len();
        let (zero_tp, zero_tx) = (vec![0.0; r.op.n_params()], vec![0.0; n]);
        let tx0 = if self.wrt.x0() { tx } else { &zero_tx[..] };
        let mut g = vec![0.0; n];
        let (mut value, mut slope) = (0.0, 0.0);
        let mut term = |t: usize, x: &[f64], tx: &[f64]| {
            if self.loss.has_term(t, r.steps) {
                value += self.loss.term(t, x, &mut g);
                slope += g.iter().zip(tx).map(|(a, b)| a * b).sum::<f64>();
            }
        };
        if r.steps == 0 {
            term(0, x0, tx0);
        }
        // The tangent of the step from x_t: its block of tp (or zero).
        let tp_at = |t: usize| if self.wrt.p() { &tp[r.block(t)] } else { &zero_tp[..] };
        carry_tangent(&r, x0, tx0, tp_at, |_, _, _, _| {}, &mut term);
        if let Some(e) = r.op.take_error() {
            panic!("RolloutLoss: in the forward pass: {e}");
        }
        assert!(value.is_finite() && slope.is_finite(), "RolloutLoss: the JVP through {} steps of {} is not finite", r.steps, r.op.name());
        y[0] = value;
        ty[0] = slope;
    }
}

/// A whole rollout `x_0 ↦ x_T` as an operator, so that the gradient checks
/// apply to it: its VJP is the chained per-step VJP (under the chosen
/// checkpointing), its JVP the chained per-step JVPs. The parameters are
/// held fixed; [`RolloutLoss`] takes them (and a loss at several steps) as
/// inputs too.
#[derive(Debug)]
pub struct RolloutOperator<'a, O> {
    /// The rollout.
    pub rollout: Rollout<'a, O>,
    /// How the VJP keeps states.
    pub mode: Checkpointing,
}

impl<O> Clone for RolloutOperator<'_, O> {
    fn clone(&self) -> Self {
        *self
    }
}

impl<O> Copy for RolloutOperator<'_, O> {}

impl<O: Forward> Operator for RolloutOperator<'_, O> {
    fn n_in(&self) -> usize {
        self.rollout.op.n_in()
    }
    fn n_out(&self) -> usize {
        self.rollout.op.n_out()
    }
}

impl<O: Jvp> Forward for RolloutOperator<'_, O> {
    /// `y = x_T` from `x_0 = x` (the rollout's own parameters are used; the
    /// operator has no parameter input of its own).
    #[track_caller]
    fn forward(&self, x: &[f64], _p: &[f64], y: &mut [f64]) {
        self.rollout.check_state(x).unwrap_or_else(|e| panic!("RolloutOperator: {e}"));
        let xt = self.rollout.final_state_unchecked(x);
        y.copy_from_slice(&xt);
    }

    /// The step's solve tolerance times the number of steps.
    fn solve_tolerance(&self) -> f64 {
        self.rollout.op.solve_tolerance() * self.rollout.steps as f64
    }

    /// The smallest radius of the steps along the tangent the JVPs carry
    /// (see [`RolloutLoss`]'s).
    fn smooth_radius(&self, x: &[f64], _p: &[f64], dx: &[f64], _dp: &[f64]) -> f64 {
        let tp = vec![0.0; self.rollout.op.n_params()];
        rollout_radius(&self.rollout, x, dx, |_| &tp[..])
    }
}

impl<O: Vjp + Jvp> Vjp for RolloutOperator<'_, O> {
    #[track_caller]
    fn vjp(&self, x: &[f64], _p: &[f64], dy: &mut [f64], dx: &mut [f64], _dp: &mut [f64]) {
        let seed = dy.to_vec();
        let linear = |y: &[f64], g: &mut [f64]| -> f64 {
            g.copy_from_slice(&seed);
            y.iter().zip(&seed).map(|(a, b)| a * b).sum()
        };
        self.rollout.check_state(x).unwrap_or_else(|e| panic!("RolloutOperator: {e}"));
        let g = checkpoint::run(&self.rollout, &mut Workspace::new(), x, &linear, self.mode, checkpoint::CHECK_EVERY, None)
            .unwrap_or_else(|e| panic!("RolloutOperator: {e}"));
        for (d, v) in dx.iter_mut().zip(&g.dx0) {
            *d += v;
        }
        dy.fill(0.0);
    }
}

impl<O: Jvp> Jvp for RolloutOperator<'_, O> {
    #[track_caller]
    fn jvp(&self, x: &[f64], _p: &[f64], tx: &[f64], _tp: &[f64], y: &mut [f64], ty: &mut [f64]) {
        let tp = vec![0.0; self.rollout.op.n_params()];
        let (xt, tt) = carry_tangent(&self.rollout, x, tx, |_| &tp[..], |_, _, _, _| {}, |_, _, _| {});
        y.copy_from_slice(&xt);
        ty.copy_from_slice(&tt);
    }
}

/// `(x_0, p) ↦ x_T`: `steps` steps of `op` with the same parameters `p` at
/// every step, as an operator of the initial state **and** the parameters
/// (JAX-CFD's `repeated`, with gradients): its VJP is one backward pass
/// over the rollout ([`super::checkpoint`], `∂x_T/∂p` summed over the
/// steps), under a checkpointing chosen by the memory budget
/// ([`super::plan::choose`], once per operator) unless one is set; its
/// JVP carries the tangents of `x_0` and `p` through the per-step JVPs.
///
/// A failure of any step (a solve that does not converge, a state that is
/// not finite) is kept: [`Repeat::take_rollout_error`] gives it in full,
/// [`Forward::take_error`] as the step's own error.
#[derive(Debug)]
pub struct Repeat<O> {
    op: O,
    steps: usize,
    /// Set by [`Repeat::with_checkpointing`].
    mode: Option<Checkpointing>,
    /// Chosen by the memory budget on the first VJP that needed a choice.
    chosen: std::sync::Mutex<Option<Checkpointing>>,
    error: std::sync::Mutex<Option<RolloutError>>,
}

impl<O: Forward> Repeat<O> {
    /// `steps ≥ 1` steps of `op`.
    ///
    /// # Errors
    /// `op` does not map a state to a state of the same size, or `steps` is
    /// zero.
    pub fn new(op: O, steps: usize) -> Result<Self, RolloutError> {
        if op.n_in() != op.n_out() {
            return Err(RolloutError::NotAStateMap { n_in: op.n_in(), n_out: op.n_out() });
        }
        if steps == 0 {
            return Err(RolloutError::Length { what: super::Argument::Steps, got: 0, expected: 1 });
        }
        Ok(Self { op, steps, mode: None, chosen: std::sync::Mutex::new(None), error: std::sync::Mutex::new(None) })
    }

    /// The VJP keeps its states as `mode` says instead of choosing by the
    /// memory budget.
    pub fn with_checkpointing(mut self, mode: Checkpointing) -> Self {
        self.mode = Some(mode.resolve(self.steps));
        self
    }

    /// The step operator.
    pub fn op(&self) -> &O {
        &self.op
    }

    /// Number of steps.
    pub fn steps(&self) -> usize {
        self.steps
    }

    /// The failure of the last call, if one failed (taken: a second call
    /// returns `None`).
    pub fn take_rollout_error(&self) -> Option<RolloutError> {
        self.error.lock().unwrap_or_else(|e| e.into_inner()).take()
    }

    fn record(&self, e: RolloutError) {
        *self.error.lock().unwrap_or_else(|e| e.into_inner()) = Some(e);
    }

    /// The checkpointing of a VJP from `x`: the one set; else storing
    /// every state when they all fit in cache ([`super::plan::CACHE`]:
    /// nothing is faster); else the fastest that fits the memory budget by
    /// the cost model, with one step timed (chosen once per operator).
    fn mode(&self, x: &[f64], p: &[f64]) -> Result<Checkpointing, RolloutError> {
        if let Some(m) = self.mode {
            return Ok(m);
        }
        let states = 8 * x.len() as u64 * (self.steps as u64 + 2);
        if states <= super::plan::CACHE && states.saturating_add(crate::memory::BASE) <= crate::memory::budget() {
            return Ok(Checkpointing::Store);
        }
        let mut chosen = self.chosen.lock().unwrap_or_else(|e| e.into_inner());
        if let Some(m) = *chosen {
            return Ok(m);
        }
        let mut y = vec![0.0; x.len()];
        let start = std::time::Instant::now();
        self.op.forward(x, p, &mut y);
        let forward_s = start.elapsed().as_secs_f64();
        if let Some(error) = self.op.take_error() {
            return Err(RolloutError::Operator { pass: super::Pass::Forward, error });
        }
        let job = super::plan::Job { steps: self.steps, state_bytes: 8 * x.len() as u64, copies: 1, forward_s };
        // None fits: refused (the error is pointer-free, so the estimate
        // stays out of it; `plan::choose` says how much would be needed).
        let plan = super::plan::choose(&job, 0, crate::memory::budget(), "the gradient of a repeated step").map_err(|_| RolloutError::Operator {
            pass: super::Pass::Backward,
            error: crate::op::OpError::Input(crate::op::OpMessage::new("no checkpointing fits the memory budget")),
        })?;
        *chosen = Some(plan.mode);
        Ok(plan.mode)
    }
}

impl<O: Forward> Operator for Repeat<O> {
    fn n_in(&self) -> usize {
        self.op.n_in()
    }
    fn n_out(&self) -> usize {
        self.op.n_out()
    }
    fn n_params(&self) -> usize {
        self.op.n_params()
    }
}

impl<O: Jvp> Forward for Repeat<O> {
    #[track_caller]
    fn forward(&self, x: &[f64], p: &[f64], y: &mut [f64]) {
        crate::op::validate_forward(self, "Repeat", x, p, y);
        match Rollout::new(&self.op, p, self.steps).and_then(|r| r.final_state(x)) {
            Ok(xt) => y.copy_from_slice(&xt),
            Err(e) => {
                y.fill(f64::NAN);
                self.record(e);
            }
        }
    }

    /// The step's solve tolerance times the number of steps.
    fn solve_tolerance(&self) -> f64 {
        self.op.solve_tolerance() * self.steps as f64
    }

    /// The smallest radius of the steps along the tangent the JVPs carry
    /// (a parameter's own limit, a time step that must stay positive, among
    /// them), as [`RolloutLoss`]'s.
    fn smooth_radius(&self, x: &[f64], p: &[f64], dx: &[f64], dp: &[f64]) -> f64 {
        match Rollout::new(&self.op, p, self.steps) {
            Ok(r) => rollout_radius(&r, x, dx, |_| dp),
            Err(_) => f64::INFINITY,
        }
    }

    fn take_error(&self) -> Option<crate::op::OpError> {
        self.take_rollout_error().map(|e| match e {
            RolloutError::Operator { error, .. } => error,
            other => crate::op::OpError::Input(crate::op::OpMessage::new(&other.to_string())),
        })
    }
}

impl<O: Vjp + Jvp> Vjp for Repeat<O> {
    #[track_caller]
    fn vjp(&self, x: &[f64], p: &[f64], dy: &mut [f64], dx: &mut [f64], dp: &mut [f64]) {
        crate::op::validate_vjp(self, "Repeat", x, p, dy, dx, dp);
        let seed = dy.to_vec();
        let linear = |y: &[f64], g: &mut [f64]| -> f64 {
            g.copy_from_slice(&seed);
            y.iter().zip(&seed).map(|(a, b)| a * b).sum()
        };
        let run = || {
            let mode = self.mode(x, p)?;
            let rollout = Rollout::new(&self.op, p, self.steps)?;
            checkpoint::run(&rollout, &mut Workspace::new(), x, &linear, mode, checkpoint::CHECK_EVERY, None)
        };
        match run() {
            Ok(g) => {
                dx.iter_mut().zip(&g.dx0).for_each(|(d, v)| *d += v);
                dp.iter_mut().zip(&g.dp).for_each(|(d, v)| *d += v);
            }
            Err(e) => {
                dx.fill(f64::NAN);
                dp.fill(f64::NAN);
                self.record(e);
            }
        }
        dy.fill(0.0);
    }
}

impl<O: Jvp> Jvp for Repeat<O> {
    #[track_caller]
    fn jvp(&self, x: &[f64], p: &[f64], tx: &[f64], tp: &[f64], y: &mut [f64], ty: &mut [f64]) {
        crate::op::validate_jvp(self, "Repeat", x, p, tx, tp, y, ty);
        let (mut xs, mut ts) = (x.to_vec(), tx.to_vec());
        for t in 0..self.steps {
            self.op.jvp(&xs, p, &ts, tp, y, ty);
            if let Some(error) = self.op.take_error() {
                y.fill(f64::NAN);
                ty.fill(f64::NAN);
                return self.record(RolloutError::Operator { pass: super::Pass::Forward, error });
            }
            if !crate::op::all_finite(y) || !crate::op::all_finite(ty) {
                y.fill(f64::NAN);
                ty.fill(f64::NAN);
                let operator = self.op.locate_non_finite(&xs, p);
                return self.record(RolloutError::NonFinite { pass: super::Pass::Forward, step: t, operator });
            }
            xs.copy_from_slice(y);
            ts.copy_from_slice(ty);
        }
    }
}
