//! Training networks through solvers: a network acts between solver steps
//! ([`Coupled`]: adding a correction, scaling the state, or setting the
//! solver's parameters), the framework's rollouts chain the per-step VJPs
//! of solver and network, and [`batch_gradient`] averages over a
//! mini-batch in parallel (rayon over samples, reduced in sample order, so
//! the result does not depend on the thread count). [`optim`] updates the
//! parameters, [`hig`] and [`pg`] give the half-inverse and physical
//! (SIP) updates, [`checkpoint`] saves and resumes a run. The studies that
//! train through these parts (solver-in-the-loop, SIP, HIG, P3) are the
//! `diffsim-studies` crate.

pub mod checkpoint;
pub mod hig;
pub mod observe;
pub mod optim;
pub mod pg;
pub mod rule;
pub mod trainer;

use std::sync::atomic::{AtomicU64, Ordering};
use std::time::Instant;

use rayon::prelude::*;

use crate::distributed::World;
use crate::op::{Forward, Jvp, OpError, Operator, Real, Vjp, validate_forward, validate_jvp, validate_vjp};
use crate::rollout::{AtSteps, Checkpointing, Rollout, RolloutError};

pub use observe::{CheckpointPolicy, CsvLog, Observer, on_row, save_with};
pub use optim::{Adam, AdamParams, Optimizer, Sgd, SgdParams, clip_by_norm};
pub use rule::{ControlBatch, FnObjective, InverseBatch, Lbfgs, LbfgsParams, LbfgsStep, Objective, RolloutBatch, Sip, TrainError, UpdateRule};
pub use trainer::{Schedule, Trainer, TrainerParams};

/// How the network acts on each step.
#[derive(Clone, Copy, Debug, PartialEq, Eq, serde::Serialize, serde::Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum Coupling {
    /// `y = v + N(v; θ)` with `v = S(x)`: a learned correction.
    Add,
    /// `y = v ⊙ N(v; θ)`: a learned pointwise scaling.
    Scale,
    /// `y = S(x; N(x; θ))`: the network sets the solver's parameters
    /// (a force, a viscosity field …).
    Params,
}

/// Wall time spent inside the solver and the network, forward and backward
/// (nanoseconds, summed over threads).
#[derive(Debug, Default)]
pub struct Timers {
    /// Solver forward (including recomputation).
    pub solver_fwd: AtomicU64,
    /// Solver VJPs.
    pub solver_bwd: AtomicU64,
    /// Network forward (including recomputation).
    pub net_fwd: AtomicU64,
    /// Network VJPs.
    pub net_bwd: AtomicU64,
}

impl Timers {
    fn add(counter: &AtomicU64, since: Instant) {
        counter.fetch_add(since.elapsed().as_nanos() as u64, Ordering::Relaxed);
    }

    /// The four totals in seconds: solver forward, solver backward,
    /// network forward, network backward; resets them.
    pub fn take(&self) -> [f64; 4] {
        [&self.solver_fwd, &self.solver_bwd, &self.net_fwd, &self.net_bwd].map(|c| c.swap(0, Ordering::Relaxed) as f64 * 1e-9)
    }
}

/// Where the time of training went (seconds, summed over threads for the
/// solver and network parts).
#[derive(Clone, Copy, Debug, Default, PartialEq, serde::Serialize, serde::Deserialize)]
pub struct TimeShares {
    /// Wall time of the iterations it covers.
    pub total: f64,
    /// Solver forward (incl. recomputation), summed over threads.
    pub solver_fwd: f64,
    /// Solver VJPs.
    pub solver_bwd: f64,
    /// Network forward (incl. recomputation).
    pub net_fwd: f64,
    /// Network VJPs.
    pub net_bwd: f64,
    /// The optimizer updates (wall).
    pub optimizer: f64,
}

impl TimeShares {
    /// Adds the solver and network times of `timers` (and resets them).
    pub fn add_timers(&mut self, timers: &Timers) {
        let [a, b, c, d] = timers.take();
        self.solver_fwd += a;
        self.solver_bwd += b;
        self.net_fwd += c;
        self.net_bwd += d;
    }
}

/// A solver step `S(x; s)` and a network `N(·; θ)` as one operator with
/// parameters `θ`, coupled as [`Coupling`] says. Derivatives chain the two
/// operators' own (hand-written or generated) ones.
#[derive(Debug)]
pub struct Coupled<'a, S, N, R = f64> {
    /// The solver step (`n_in == n_out`).
    pub solver: &'a S,
    /// Its fixed parameters (unused with [`Coupling::Params`]).
    pub solver_p: &'a [R],
    /// The network.
    pub net: &'a N,
    /// How they are joined.
    pub coupling: Coupling,
    /// Time inside each part.
    pub timers: Timers,
}

/// A coupling whose sizes do not fit.
#[derive(Clone, Copy, Debug, PartialEq, Eq, thiserror::Error)]
pub enum CouplingError {
    /// The solver does not map a state to a state.
    #[error("the solver maps {n_in} values to {n_out}; it must keep the state size")]
    Solver {
        /// Input size.
        n_in: usize,
        /// Output size.
        n_out: usize,
    },
    /// The network's sizes do not fit the coupling.
    #[error("the network maps {n_in} → {n_out} values; this coupling needs {want_in} → {want_out}")]
    Net {
        /// Its input size.
        n_in: usize,
        /// Its output size.
        n_out: usize,
        /// The input size needed.
        want_in: usize,
        /// The output size needed.
        want_out: usize,
    },
    /// The solver's fixed parameters have the wrong length.
    #[error("the solver takes {expected} parameters, got {got}")]
    SolverParams {
        /// Given.
        got: usize,
        /// Needed.
        expected: usize,
    },
}

impl<'a, R: Real, S: Vjp<R> + Jvp<R>, N: Vjp<R> + Jvp<R>> Coupled<'a, S, N, R> {
    /// Couples `solver` (with parameters `solver_p`) and `net`, checking sizes.
    pub fn new(solver: &'a S, solver_p: &'a [R], net: &'a N, coupling: Coupling) -> Result<Self, CouplingError> {
        let n = solver.n_in();
        if solver.n_out() != n {
            return Err(CouplingError::Solver { n_in: n, n_out: solver.n_out() });
        }
        let (want_in, want_out) = match coupling {
            Coupling::Add | Coupling::Scale => (n, n),
            Coupling::Params => (n, solver.n_params()),
        };
        if net.n_in() != want_in || net.n_out() != want_out {
            return Err(CouplingError::Net { n_in: net.n_in(), n_out: net.n_out(), want_in, want_out });
        }
        if coupling != Coupling::Params && solver_p.len() != solver.n_params() {
            return Err(CouplingError::SolverParams { got: solver_p.len(), expected: solver.n_params() });
        }
        Ok(Self { solver, solver_p, net, coupling, timers: Timers::default() })
    }

    fn solve(&self, x: &[R], s: &[R], y: &mut [R]) {
        let t = Instant::now();
        self.solver.forward(x, s, y);
        Timers::add(&self.timers.solver_fwd, t);
    }

    fn apply_net(&self, x: &[R], theta: &[R], y: &mut [R]) {
        let t = Instant::now();
        self.net.forward(x, theta, y);
        Timers::add(&self.timers.net_fwd, t);
    }
}

impl<S: Operator, N: Operator, R> Operator for Coupled<'_, S, N, R> {
    fn n_in(&self) -> usize {
        self.solver.n_in()
    }
    fn n_out(&self) -> usize {
        self.solver.n_out()
    }
    fn n_params(&self) -> usize {
        self.net.n_params()
    }
}

impl<R: Real, S: Vjp<R> + Jvp<R>, N: Vjp<R> + Jvp<R>> Forward<R> for Coupled<'_, S, N, R> {
    fn forward(&self, x: &[R], p: &[R], y: &mut [R]) {
        validate_forward(self, "Coupled", x, p, y);
        match self.coupling {
            Coupling::Add | Coupling::Scale => {
                let mut v = vec![R::zero(); x.len()];
                self.solve(x, self.solver_p, &mut v);
                self.apply_net(&v, p, y);
                for (y, v) in y.iter_mut().zip(&v) {
                    *y = if self.coupling == Coupling::Add { *y + *v } else { *y * *v };
                }
            }
            Coupling::Params => {
                let mut q = vec![R::zero(); self.net.n_out()];
                self.apply_net(x, p, &mut q);
                self.solve(x, &q, y);
            }
        }
    }

    fn smooth_radius(&self, x: &[R], p: &[R], dx: &[R], dp: &[R]) -> f64 {
        let n = x.len();
        match self.coupling {
            Coupling::Add | Coupling::Scale => {
                let zero = vec![R::zero(); self.solver_p.len()];
                let r = self.solver.smooth_radius(x, self.solver_p, dx, &zero);
                let (mut v, mut tv) = (vec![R::zero(); n], vec![R::zero(); n]);
                self.solver.jvp(x, self.solver_p, dx, &zero, &mut v, &mut tv);
                r.min(self.net.smooth_radius(&v, p, &tv, dp))
            }
            Coupling::Params => {
                let r = self.net.smooth_radius(x, p, dx, dp);
                let (mut q, mut tq) = (vec![R::zero(); self.net.n_out()], vec![R::zero(); self.net.n_out()]);
                self.net.jvp(x, p, dx, dp, &mut q, &mut tq);
                r.min(self.solver.smooth_radius(x, &q, dx, &tq))
            }
        }
    }

    /// The solver or the network, whichever first produced the non-finite value.
    fn locate_non_finite(&self, x: &[R], p: &[R]) -> crate::op::OpName {
        let finite = crate::rollout::all_finite;
        match self.coupling {
            Coupling::Add | Coupling::Scale => {
                let mut v = vec![R::zero(); x.len()];
                self.solver.forward(x, self.solver_p, &mut v);
                if !finite(&v) {
                    return self.solver.locate_non_finite(x, self.solver_p);
                }
                let mut y = vec![R::zero(); self.net.n_out()];
                self.net.forward(&v, p, &mut y);
                if !finite(&y) { self.net.locate_non_finite(&v, p) } else { self.name() }
            }
            Coupling::Params => {
                let mut q = vec![R::zero(); self.net.n_out()];
                self.net.forward(x, p, &mut q);
                if !finite(&q) { self.net.locate_non_finite(x, p) } else { self.solver.locate_non_finite(x, &q) }
            }
        }
    }

    fn take_error(&self) -> Option<OpError> {
        self.solver.take_error().or_else(|| self.net.take_error())
    }
}

impl<R: Real, S: Vjp<R> + Jvp<R>, N: Vjp<R> + Jvp<R>> Vjp<R> for Coupled<'_, S, N, R> {
    fn vjp(&self, x: &[R], p: &[R], dy: &mut [R], dx: &mut [R], dp: &mut [R]) {
        validate_vjp(self, "Coupled", x, p, dy, dx, dp);
        let n = x.len();
        match self.coupling {
            Coupling::Add | Coupling::Scale => {
                let mut v = vec![R::zero(); n];
                self.solve(x, self.solver_p, &mut v);
                // gv = ∂y/∂v ᵀ·dy: the identity (Add) or the network's output (Scale), plus the network's VJP.
                let mut gv = vec![R::zero(); n];
                let mut seed = dy.to_vec();
                if self.coupling == Coupling::Scale {
                    let mut out = vec![R::zero(); n];
                    self.apply_net(&v, p, &mut out);
                    for ((g, s), (o, vv)) in gv.iter_mut().zip(seed.iter_mut()).zip(out.iter().zip(&v)) {
                        *g = *s * *o;
                        *s *= *vv;
                    }
                } else {
                    gv.copy_from_slice(dy);
                }
                let t = Instant::now();
                self.net.vjp(&v, p, &mut seed, &mut gv, dp);
                Timers::add(&self.timers.net_bwd, t);
                let mut ds = vec![R::zero(); self.solver.n_params()];
                let t = Instant::now();
                self.solver.vjp(x, self.solver_p, &mut gv, dx, &mut ds);
                Timers::add(&self.timers.solver_bwd, t);
            }
            Coupling::Params => {
                let mut q = vec![R::zero(); self.net.n_out()];
                self.apply_net(x, p, &mut q);
                let mut gq = vec![R::zero(); q.len()];
                let t = Instant::now();
                self.solver.vjp(x, &q, dy, dx, &mut gq);
                Timers::add(&self.timers.solver_bwd, t);
                let t = Instant::now();
                self.net.vjp(x, p, &mut gq, dx, dp);
                Timers::add(&self.timers.net_bwd, t);
            }
        }
        dy.fill(R::zero());
    }
}

impl<R: Real, S: Vjp<R> + Jvp<R>, N: Vjp<R> + Jvp<R>> Jvp<R> for Coupled<'_, S, N, R> {
    fn jvp(&self, x: &[R], p: &[R], tx: &[R], tp: &[R], y: &mut [R], ty: &mut [R]) {
        validate_jvp(self, "Coupled", x, p, tx, tp, y, ty);
        let n = x.len();
        match self.coupling {
            Coupling::Add | Coupling::Scale => {
                let zero = vec![R::zero(); self.solver_p.len()];
                let (mut v, mut tv) = (vec![R::zero(); n], vec![R::zero(); n]);
                self.solver.jvp(x, self.solver_p, tx, &zero, &mut v, &mut tv);
                self.net.jvp(&v, p, &tv, tp, y, ty);
                for ((y, ty), (v, tv)) in y.iter_mut().zip(ty.iter_mut()).zip(v.iter().zip(&tv)) {
                    if self.coupling == Coupling::Add {
                        *y += *v;
                        *ty += *tv;
                    } else {
                        *ty = *ty * *v + *y * *tv;
                        *y *= *v;
                    }
                }
            }
            Coupling::Params => {
                let (mut q, mut tq) = (vec![R::zero(); self.net.n_out()], vec![R::zero(); self.net.n_out()]);
                self.net.jvp(x, p, tx, tp, &mut q, &mut tq);
                self.solver.jvp(x, &q, tx, &tq, y, ty);
            }
        }
    }
}

/// The sums over a batch shared among the ranks of `world`: `rows` holds
/// this rank's samples in order, each as `[loss, gradient (n values)]`;
/// every rank receives every rank's rows ([`World::all_gather`], rank
/// order: the whole batch in sample order) and adds them in that order, the
/// loss in `f64`, the gradient in `R`: one process's sums, bit for bit.
pub(crate) fn sum_in_sample_order<R: Real>(world: &World, rows: &[f64], n: usize) -> (f64, Vec<R>) {
    let all = world.all_gather(rows);
    let mut grad = vec![R::zero(); n];
    let mut total = 0.0;
    for row in all.chunks_exact(1 + n) {
        total += row[0];
        for (a, &b) in grad.iter_mut().zip(&row[1..]) {
            *a += R::of(b);
        }
    }
    (total, grad)
}

/// One training sample: an initial state and the targets at the loss steps.
#[derive(Clone, Debug)]
pub struct Sample<R = f64> {
    /// The state the unroll starts from.
    pub x0: Vec<R>,
    /// One target per loss step, in the order of the steps.
    pub targets: Vec<Vec<R>>,
}

/// The mean loss and its gradient over a mini-batch: each sample is
/// unrolled `unroll` steps of `op` from its `x0`, with the loss
/// `mean over loss_steps and values of (x_t − target_t)²`, and the batch
/// mean is taken. Samples run in parallel (rayon); the sum runs in sample
/// order, so the result is the same for any number of threads. In `f32`
/// the loss is summed in `f64`, the gradient in `f32`.
pub fn batch_gradient<R: Real, O: Vjp<R> + Sync>(
    op: &O,
    theta: &[R],
    unroll: usize,
    loss_steps: &[usize],
    batch: &[Sample<R>],
    mode: Checkpointing,
) -> Result<(f64, Vec<R>), RolloutError> {
    batch_gradient_over(&World::single(), op, theta, unroll, loss_steps, batch, batch.len(), mode)
}

/// [`batch_gradient`] of a batch of `batch_len` samples shared among the
/// ranks of `world`: this rank unrolls `mine`, the samples
/// [`World::share`]`(batch_len)`, and every rank receives every sample's
/// loss and gradient ([`World::all_gather`], in sample order) and sums them
/// in sample order as one process does. The result is the same, bit for
/// bit, for any number of ranks and threads; the exchange is
/// `batch_len × (parameters + 1)` numbers.
#[allow(clippy::too_many_arguments)]
pub fn batch_gradient_over<R: Real, O: Vjp<R> + Sync>(
    world: &World,
    op: &O,
    theta: &[R],
    unroll: usize,
    loss_steps: &[usize],
    mine: &[Sample<R>],
    batch_len: usize,
    mode: Checkpointing,
) -> Result<(f64, Vec<R>), RolloutError> {
    debug_assert_eq!(mine.len(), world.share(batch_len).len());
    let rollout = Rollout::new(op, theta, unroll)?;
    let scale = 1.0 / (loss_steps.len() * op.n_out()) as f64;
    let per_sample: Vec<_> = mine
        .par_iter()
        .map(|s| {
            let loss = AtSteps {
                steps: loss_steps.to_vec(),
                f: |t: usize, x: &[R], g: &mut [R]| {
                    let i = loss_steps.iter().position(|&k| k == t).expect("a listed step");
                    let mut v = 0.0;
                    let two_scale = R::of(2.0 * scale);
                    for ((g, &x), &r) in g.iter_mut().zip(x).zip(&s.targets[i]) {
                        let d = x - r;
                        *g = two_scale * d;
                        v += scale * (d * d).as_f64();
                    }
                    v
                },
            };
            rollout.value_and_grad(&s.x0, &loss, mode)
        })
        .collect();
    let mut rows = Vec::with_capacity(mine.len() * (1 + theta.len()));
    for g in per_sample {
        let g = g?;
        rows.push(g.loss);
        rows.extend(g.dp.iter().map(|v| v.as_f64()));
    }
    let (total, mut grad) = sum_in_sample_order::<R>(world, &rows, theta.len());
    let b = batch_len.max(1) as f64;
    let inv = R::of(1.0 / b);
    for a in &mut grad {
        *a *= inv;
    }
    Ok((total / b, grad))
}
