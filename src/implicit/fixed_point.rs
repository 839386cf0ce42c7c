//! The fixed-point solve: a steady state `y = G(y, x, p)` as an operator
//! `(x, p) ↦ y`, found by iterating the user's map and differentiated at
//! the fixed point, never through the iterations.
//!
//! The user writes the map as a plain function on slices (one step of a
//! relaxation, of a time-stepper run to its steady state, of a Picard
//! linearisation) and declares it with
//! [`fixed_point_system!`](crate::fixed_point_system):
//!
//! ```ignore
//! fn relax(s: &Steady, y: &[f64], x: &[f64], p: &[f64], out: &mut [f64]) { /* out = G(y, x, p) */ }
//! diffsim::fixed_point_system!(Steady => relax);
//! let solve = FixedPoint::new(Steady { .. }, FixedPointParams::default());
//! ```
//!
//! Forward, `y ← y + ω·(G(y) − y)` from [`FixedPointSystem::guess`] until
//! `‖G(y) − y‖₂ ≤ tol·‖G(y)‖₂`: it converges where `G` contracts. The
//! derivatives at the fixed point, by the implicit function theorem, each
//! an iteration of the same kind (the adjoint map contracts as `G` does):
//!
//! ```text
//! VJP:  λ = ȳ + (∂G/∂y)ᵀ·λ,   x̄ += (∂G/∂x)ᵀ·λ,   p̄ += (∂G/∂p)ᵀ·λ
//! JVP:  ẏ = (∂G/∂y)·ẏ + (∂G/∂x)·ẋ + (∂G/∂p)·ṗ
//! ```
//!
//! the products from Enzyme's derivatives of the map. Where `G` contracts
//! slowly, the same equations as a residual `y − G(y, x, p) = 0` solve
//! faster by Newton's method ([`NonlinearSolve`](super::NonlinearSolve)).

use std::sync::Mutex;
use std::sync::atomic::{AtomicUsize, Ordering};

use super::linear::{check_given, fail, keep, take};
use crate::op::{Forward, Jvp, OpError, Operator, Vjp, validate_forward, validate_jvp, validate_vjp};

/// The sizes of a user's fixed-point problem `y = G(y, x, p)`, and the
/// iteration's starting point.
pub trait FixedPointSystem {
    /// Unknowns `y` (the operator's outputs, and the map's).
    fn n(&self) -> usize;
    /// Inputs `x`.
    fn n_in(&self) -> usize;
    /// Parameters `p`.
    fn n_params(&self) -> usize {
        0
    }
    /// The iteration's start for `x` and `p` (default: zeros). Not
    /// differentiated: the fixed point does not depend on it.
    fn guess(&self, x: &[f64], p: &[f64], y: &mut [f64]) {
        let _ = (x, p);
        y.fill(0.0);
    }
}

/// A map and its derivatives, implemented by
/// [`fixed_point_system!`](crate::fixed_point_system) with Enzyme; not
/// written by hand.
#[doc(hidden)]
pub trait MapFunctions: FixedPointSystem {
    /// `out = G(y, x, p)`.
    fn map(&self, y: &[f64], x: &[f64], p: &[f64], out: &mut [f64]);
    /// `tout = (∂G/∂y)·ty + (∂G/∂x)·tx + (∂G/∂p)·tp` (and `out = G`).
    #[allow(clippy::too_many_arguments)]
    fn map_jvp(&self, y: &[f64], x: &[f64], p: &[f64], ty: &[f64], tx: &[f64], tp: &[f64], out: &mut [f64], tout: &mut [f64]);
    /// `dy += (∂G/∂y)ᵀ·w`, `dx += (∂G/∂x)ᵀ·w`, `dp += (∂G/∂p)ᵀ·w`; consumes `w`.
    #[allow(clippy::too_many_arguments)]
    fn map_vjp(&self, y: &[f64], x: &[f64], p: &[f64], w: &mut [f64], dy: &mut [f64], dx: &mut [f64], dp: &mut [f64]);
    /// `dy += (∂G/∂y)ᵀ·w` alone; consumes `w`.
    fn map_vjp_y(&self, y: &[f64], x: &[f64], p: &[f64], w: &mut [f64], dy: &mut [f64]);
}

/// Makes `Sys` (a [`FixedPointSystem`], plain data) the system of a
/// [`FixedPoint`] from its map `fn(&Sys, y, x, p, out)`, a plain function
/// that writes every element of `out`. Enzyme generates the products the
/// derivatives at the fixed point need. The crate that invokes it needs
/// what [`differentiable!`](crate::differentiable) needs.
#[macro_export]
macro_rules! fixed_point_system {
    ($ty:ty => $map:path) => {
        #[allow(clippy::too_many_arguments)]
        const _: () = {
            #[::std::autodiff::autodiff_reverse(diffsim_map_vjp, Const, Duplicated, Duplicated, Duplicated, Duplicated)]
            fn diffsim_map_reverse(s: &$ty, y: &[f64], x: &[f64], p: &[f64], out: &mut [f64]) {
                $map(s, y, x, p, out)
            }
            #[::std::autodiff::autodiff_reverse(diffsim_map_vjp_y, Const, Duplicated, Const, Const, Duplicated)]
            fn diffsim_map_reverse_y(s: &$ty, y: &[f64], x: &[f64], p: &[f64], out: &mut [f64]) {
                $map(s, y, x, p, out)
            }
            #[::std::autodiff::autodiff_forward(diffsim_map_jvp, Const, Dual, Dual, Dual, Dual)]
            fn diffsim_map_forward(s: &$ty, y: &[f64], x: &[f64], p: &[f64], out: &mut [f64]) {
                $map(s, y, x, p, out)
            }

            impl $crate::implicit::MapFunctions for $ty {
                fn map(&self, y: &[f64], x: &[f64], p: &[f64], out: &mut [f64]) {
                    $map(self, y, x, p, out)
                }
                #[inline(never)]
                fn map_jvp(&self, y: &[f64], x: &[f64], p: &[f64], ty: &[f64], tx: &[f64], tp: &[f64], out: &mut [f64], tout: &mut [f64]) {
                    diffsim_map_jvp(self, y, ty, x, tx, p, tp, out, tout)
                }
                #[inline(never)]
                fn map_vjp(&self, y: &[f64], x: &[f64], p: &[f64], w: &mut [f64], dy: &mut [f64], dx: &mut [f64], dp: &mut [f64]) {
                    let n = $crate::implicit::FixedPointSystem::n(self);
                    $crate::op::with_scratch(n, |out| diffsim_map_vjp(self, y, dy, x, dx, p, dp, out, w));
                }
                #[inline(never)]
                fn map_vjp_y(&self, y: &[f64], x: &[f64], p: &[f64], w: &mut [f64], dy: &mut [f64]) {
                    let n = $crate::implicit::FixedPointSystem::n(self);
                    $crate::op::with_scratch(n, |out| diffsim_map_vjp_y(self, y, dy, x, p, out, w));
                }
            }
        };
    };
}

/// Settings of a [`FixedPoint`]. `Default`: converged when the update is
/// 1e-10 of the iterate, at most 10,000 iterations, no relaxation.
#[derive(Clone, Copy, Debug, PartialEq, serde::Serialize, serde::Deserialize)]
pub struct FixedPointParams {
    /// Converged when `‖G(y) − y‖₂ ≤ tolerance·‖G(y)‖₂` (the derivatives'
    /// iterations alike).
    pub tolerance: f64,
    /// More iterations than this is an error.
    pub max_iterations: usize,
    /// `ω` in `y ← y + ω·(G(y) − y)`, in (0, 1]: below 1 damps a map that
    /// overshoots.
    pub relaxation: f64,
}

impl Default for FixedPointParams {
    fn default() -> Self {
        FixedPointParams { tolerance: 1e-10, max_iterations: 10_000, relaxation: 1.0 }
    }
}

/// Iterations of a [`FixedPoint`]'s solves so far.
#[derive(Debug, Default)]
pub struct FixedPointInfo {
    /// Of the forward solves (and the JVPs').
    pub forward: AtomicUsize,
    /// Of the adjoint solves.
    pub adjoint: AtomicUsize,
}

/// The operator `(x, p) ↦ y` with `y = G(y, x, p)` for a user's map `S`
/// ([`fixed_point_system!`](crate::fixed_point_system)); derivatives at the
/// fixed point (module docs).
#[derive(Debug)]
pub struct FixedPoint<S> {
    /// The user's system.
    pub system: S,
    /// How it is iterated.
    pub params: FixedPointParams,
    /// Iterations so far.
    pub info: FixedPointInfo,
    error: Mutex<Option<OpError>>,
}

impl<S: FixedPointSystem> FixedPoint<S> {
    /// The fixed point of `system`'s map, iterated by `params`.
    ///
    /// # Panics
    /// If the tolerance is not a positive number, the iteration limit 0, or
    /// the relaxation outside (0, 1].
    #[track_caller]
    pub fn new(system: S, params: FixedPointParams) -> Self {
        let FixedPointParams { tolerance, max_iterations, relaxation } = params;
        if !(tolerance.is_finite() && tolerance > 0.0) || max_iterations == 0 || !(relaxation > 0.0 && relaxation <= 1.0) {
            panic!(
                "FixedPoint: the tolerance must be a positive number, the iteration limit at least 1 and the relaxation in (0, 1], got {tolerance}, {max_iterations} and {relaxation}"
            );
        }
        FixedPoint { system, params, info: FixedPointInfo::default(), error: Mutex::new(None) }
    }

    /// Iterates `v ← v + ω·(step(v) − v)` from `v` to convergence, counting
    /// into `counter`.
    fn iterate(&self, v: &mut [f64], counter: &AtomicUsize, mut step: impl FnMut(&[f64], &mut [f64])) -> Result<(), OpError> {
        let FixedPointParams { tolerance, max_iterations, relaxation } = self.params;
        let mut next = vec![0.0; v.len()];
        let mut relative = f64::NAN;
        for it in 1..=max_iterations {
            step(v, &mut next);
            let (mut change, mut size) = (0.0, 0.0);
            for (a, b) in v.iter_mut().zip(&next) {
                change += (b - *a) * (b - *a);
                size += b * b;
                *a += relaxation * (b - *a);
            }
            relative = change.sqrt() / size.sqrt().max(f64::MIN_POSITIVE);
            if !relative.is_finite() && change != 0.0 {
                counter.fetch_add(it, Ordering::Relaxed);
                return Err(OpError::NoConvergence { iterations: it, relative_residual: f64::NAN, tolerance });
            }
            if change == 0.0 || relative <= tolerance {
                counter.fetch_add(it, Ordering::Relaxed);
                return Ok(());
            }
        }
        counter.fetch_add(max_iterations, Ordering::Relaxed);
        Err(OpError::NoConvergence { iterations: max_iterations, relative_residual: relative, tolerance })
    }
}

impl<S: FixedPointSystem> Operator for FixedPoint<S> {
    fn n_in(&self) -> usize {
        self.system.n_in()
    }
    fn n_out(&self) -> usize {
        self.system.n()
    }
    fn n_params(&self) -> usize {
        self.system.n_params()
    }
}

impl<S: MapFunctions> Forward for FixedPoint<S> {
    #[track_caller]
    fn forward(&self, x: &[f64], p: &[f64], y: &mut [f64]) {
        validate_forward(self, "FixedPoint", x, p, y);
        self.system.guess(x, p, y);
        if let Err(e) = self.iterate(y, &self.info.forward, |v, out| self.system.map(v, x, p, out)) {
            fail(&self.error, y, e);
        }
    }

    fn solve_tolerance(&self) -> f64 {
        self.params.tolerance
    }

    fn take_error(&self) -> Option<OpError> {
        take(&self.error)
    }
}

impl<S: MapFunctions> FixedPoint<S> {
    /// The VJP at the fixed point `y`: `λ = ȳ + (∂G/∂y)ᵀ·λ` iterated, then
    /// `x̄`, `p̄`; consumes `ȳ`.
    fn vjp_at(&self, x: &[f64], p: &[f64], y: &[f64], dy: &mut [f64], dx: &mut [f64], dp: &mut [f64]) {
        let n = self.system.n();
        let mut lambda = dy.to_vec();
        let mut w = vec![0.0; n];
        let result = self.iterate(&mut lambda, &self.info.adjoint, |l, out| {
            out.copy_from_slice(dy);
            w.copy_from_slice(l);
            self.system.map_vjp_y(y, x, p, &mut w, out);
        });
        if let Err(e) = result {
            // The gradient is not a number: NaN where it would go.
            keep(&self.error, e);
            lambda.fill(f64::NAN);
        }
        let mut unused = vec![0.0; n];
        self.system.map_vjp(y, x, p, &mut lambda, &mut unused, dx, dp);
        dy.fill(0.0);
    }
}

impl<S: MapFunctions> Vjp for FixedPoint<S> {
    #[track_caller]
    fn vjp(&self, x: &[f64], p: &[f64], dy: &mut [f64], dx: &mut [f64], dp: &mut [f64]) {
        validate_vjp(self, "FixedPoint", x, p, dy, dx, dp);
        let mut y = vec![0.0; self.system.n()];
        self.forward(x, p, &mut y);
        self.vjp_at(x, p, &y, dy, dx, dp);
    }

    /// The fixed point is the rollout's next state: no forward iteration.
    #[track_caller]
    fn vjp_overwrite_given(&self, x: &[f64], p: &[f64], y: &[f64], dy: &mut [f64], dx: &mut [f64], dp: &mut [f64]) {
        validate_vjp(self, "FixedPoint", x, p, dy, dx, dp);
        check_given("FixedPoint", y, self.system.n());
        dx.fill(0.0);
        self.vjp_at(x, p, y, dy, dx, dp);
    }
}

impl<S: MapFunctions> Jvp for FixedPoint<S> {
    #[track_caller]
    fn jvp(&self, x: &[f64], p: &[f64], tx: &[f64], tp: &[f64], y: &mut [f64], ty: &mut [f64]) {
        validate_jvp(self, "FixedPoint", x, p, tx, tp, y, ty);
        self.forward(x, p, y);
        let n = self.system.n();
        // c = (∂G/∂x)·ẋ + (∂G/∂p)·ṗ, then ẏ = c + (∂G/∂y)·ẏ iterated.
        let (zero_y, zero_x, zero_p) = (vec![0.0; n], vec![0.0; tx.len()], vec![0.0; tp.len()]);
        let (mut g, mut c) = (vec![0.0; n], vec![0.0; n]);
        self.system.map_jvp(y, x, p, &zero_y, tx, tp, &mut g, &mut c);
        ty.copy_from_slice(&c);
        let y: &[f64] = y;
        let result = self.iterate(ty, &self.info.forward, |t, out| {
            self.system.map_jvp(y, x, p, t, &zero_x, &zero_p, &mut g, out);
            for (o, c) in out.iter_mut().zip(&c) {
                *o += c;
            }
        });
        if let Err(e) = result {
            fail(&self.error, ty, e);
        }
    }
}
