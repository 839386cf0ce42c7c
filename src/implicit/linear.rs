//! The linear solve: a user's system `A(p)·y = b(x, p)` as an operator whose
//! user writes only the forward physics.
//!
//! The user's system is two plain functions on slices, the matrix-vector
//! product `A(p)·v` and the right-hand side `b(x, p)`:
//!
//! ```ignore
//! fn matvec(s: &Heat, v: &[f64], p: &[f64], out: &mut [f64]) { /* out = A(p)·v */ }
//! fn rhs(s: &Heat, x: &[f64], p: &[f64], b: &mut [f64]) { /* b = b(x, p) */ }
//! diffsim::linear_system!(Heat => matvec, rhs);
//! let step = LinearSolve::new(Heat { .. }, SolveParams::default());
//! ```
//!
//! [`LinearSolve`] is then an operator `(x, p) ↦ y` with `A(p)·y = b(x, p)`,
//! solved by CG (symmetric positive definite `A`), BiCGStab (any other) or
//! directly (a small system: assembled and factored by faer's LU),
//! and its derivatives follow from the implicit rule, never by
//! differentiating the iterations:
//!
//! ```text
//! VJP:  Aᵀ·λ = ȳ,   x̄ += (∂b/∂x)ᵀ·λ,   p̄ += (∂b/∂p)ᵀ·λ − (∂(A(p)·y)/∂p)ᵀ·λ
//! JVP:  A·ẏ = (∂b/∂x)·ẋ + (∂b/∂p)·ṗ − (∂(A(p)·y)/∂p)·ṗ
//! ```
//!
//! one more solve each.
//!
//! A matrix whose entries cost work to form from `p` (an exponential per
//! cell, a face average) can name a third function that forms its
//! coefficients `c(p)` once per solve, the product then reading `c`:
//!
//! ```ignore
//! fn conductances(s: &Heat, p: &[f64], c: &mut [f64]) { /* c = c(p) */ }
//! fn matvec(s: &Heat, v: &[f64], c: &[f64], out: &mut [f64]) { /* out = A(c)·v */ }
//! diffsim::linear_system!(Heat => matvec, rhs, coefficients = conductances);
//! ```
//!
//! (with [`LinearSystem::n_coefficients`] their number): the iterations
//! then never form them again, and `p̄` gets `(∂c/∂p)ᵀ·c̄` from Enzyme's
//! derivative of `c`. The terms in `∂/∂p`, `∂/∂x` and, for a
//! non-symmetric `A`, the transposed product `Aᵀ·λ` come from Enzyme's
//! derivatives of the user's two functions ([`linear_system!`](crate::linear_system)).
//! Differentiating through the CG iterations instead gives the derivative
//! of the truncated iteration, which lags the solution's (docs/implicit.md).
//!
//! A fourth function may precondition the iterative methods,
//! `z = M(c)⁻¹·r` from the coefficients (its diagonal, say):
//!
//! ```ignore
//! fn jacobi(s: &Heat, c: &[f64], r: &[f64], z: &mut [f64]) { /* z = M(c)⁻¹·r */ }
//! diffsim::linear_system!(Heat => matvec, rhs, coefficients = conductances, preconditioner = jacobi);
//! ```
//!
//! CG needs `M` symmetric positive definite; BiCGStab applies it on the
//! right (any non-singular `M`; its transposed solve uses the same `M`,
//! which suits a symmetric one). The preconditioner changes how fast a
//! solve converges, never its solution or derivatives, so it is not
//! differentiated.
//!
//! A system whose matrix is singular with the constant null space (a
//! Poisson matrix with Neumann sides) says so
//! ([`LinearSystem::constant_null_space`]): CG solves it for the
//! right-hand side without its mean, and returns the solution of zero mean.
//!
//! A solve that does not converge leaves the output NaN and its error in
//! [`Forward::take_error`]; a rollout stops there with that error.

use std::sync::atomic::{AtomicUsize, Ordering};
use std::sync::{Arc, Mutex};

use diffsim_solvers::cg::{CgWork, Null, Stop, System};
use diffsim_solvers::krylov::{bicgstab, bicgstab_preconditioned};

use crate::op::{Forward, Jvp, OpError, Operator, Vjp, validate_forward, validate_jvp, validate_vjp};

/// The sizes of a user's linear system `A(p)·y = b(x, p)`.
pub trait LinearSystem {
    /// Unknowns `y` (the operator's outputs).
    fn n(&self) -> usize;
    /// Inputs `x` of the right-hand side.
    fn n_in(&self) -> usize;
    /// Parameters `p` of the matrix and the right-hand side.
    fn n_params(&self) -> usize {
        0
    }
    /// Coefficients `c(p)` the matrix-vector product reads, when the
    /// system names a function that forms them
    /// ([`linear_system!`](crate::linear_system)`(.., coefficients = f)`);
    /// without one the product reads `p` itself.
    fn n_coefficients(&self) -> usize {
        self.n_params()
    }
    /// Whether `A(p)` is singular with the constant vector as its null
    /// space, for every `p` (a Poisson or conduction matrix with insulated,
    /// Neumann, sides all round): CG then solves for the right-hand side
    /// with its mean removed and returns the solution of zero mean, the
    /// adjoint solve likewise, so the derivatives are those of that
    /// solution. CG only ([`LinearSolve::new`] refuses the others).
    fn constant_null_space(&self) -> bool {
        false
    }
}

/// A system's functions and their derivatives, implemented by
/// [`linear_system!`](crate::linear_system) with Enzyme; not written by
/// hand.
#[doc(hidden)]
pub trait SystemFunctions: SystemCoefficients + SystemProducts {}

impl<T: SystemCoefficients + SystemProducts> SystemFunctions for T {}

/// The coefficients `c(p)` of a system's matrix and their derivatives
/// ([`linear_system!`](crate::linear_system)).
#[doc(hidden)]
pub trait SystemCoefficients: LinearSystem {
    /// `c = c(p)` (without a coefficient function: `c = p`).
    fn coefficients(&self, p: &[f64], c: &mut [f64]);
    /// `dp += (∂c/∂p)ᵀ·dc`; consumes `dc`.
    fn coefficients_vjp(&self, p: &[f64], dc: &mut [f64], dp: &mut [f64]);
    /// `c = c(p)`, `tc = (∂c/∂p)·tp`.
    fn coefficients_jvp(&self, p: &[f64], tp: &[f64], c: &mut [f64], tc: &mut [f64]);
}

/// A system's product and right-hand side and their derivatives
/// ([`linear_system!`](crate::linear_system)).
#[doc(hidden)]
pub trait SystemProducts: LinearSystem {
    /// `out = A(c)·v`.
    fn matvec(&self, v: &[f64], c: &[f64], out: &mut [f64]);
    /// `dv += A(c)ᵀ·w`, `dc += (∂(A(c)·v)/∂c)ᵀ·w`; consumes `w`.
    fn matvec_vjp(&self, v: &[f64], c: &[f64], w: &mut [f64], dv: &mut [f64], dc: &mut [f64]);
    /// `dc += (∂(A(c)·v)/∂c)ᵀ·w` alone; consumes `w`.
    fn matvec_vjp_coefficients(&self, v: &[f64], c: &[f64], w: &mut [f64], dc: &mut [f64]);
    /// `out = A(c)·v`, `tout = A(c)·tv + (∂(A(c)·v)/∂c)·tc`.
    #[allow(clippy::too_many_arguments)]
    fn matvec_jvp(&self, v: &[f64], c: &[f64], tv: &[f64], tc: &[f64], out: &mut [f64], tout: &mut [f64]);
    /// `b = b(x, p)`.
    fn rhs(&self, x: &[f64], p: &[f64], b: &mut [f64]);
    /// `dx += (∂b/∂x)ᵀ·w`, `dp += (∂b/∂p)ᵀ·w`; consumes `w`.
    fn rhs_vjp(&self, x: &[f64], p: &[f64], w: &mut [f64], dx: &mut [f64], dp: &mut [f64]);
    /// `b = b(x, p)`, `tb = (∂b/∂x)·tx + (∂b/∂p)·tp`.
    #[allow(clippy::too_many_arguments)]
    fn rhs_jvp(&self, x: &[f64], p: &[f64], tx: &[f64], tp: &[f64], b: &mut [f64], tb: &mut [f64]);
    /// Whether the system names a preconditioner
    /// ([`linear_system!`](crate::linear_system)`(.., preconditioner = m)`).
    fn has_preconditioner(&self) -> bool {
        false
    }
    /// `z = M(c)⁻¹·r` (only called when [`Self::has_preconditioner`]).
    fn precondition(&self, _c: &[f64], r: &[f64], z: &mut [f64]) {
        z.copy_from_slice(r)
    }
}

/// Makes `Sys` (a [`LinearSystem`], plain data) the system of a
/// [`LinearSolve`] from its matrix-vector product `fn(&Sys, v, p, out)` and
/// right-hand side `fn(&Sys, x, p, b)`, both plain functions that write
/// every element of their output; with `coefficients = c`, a function
/// `fn(&Sys, p, c)` forms the matrix's coefficients once per solve and the
/// product reads them instead of `p` (`fn(&Sys, v, c, out)`, module docs);
/// with `preconditioner = m`, a function `fn(&Sys, c, r, z)` computes
/// `z = M⁻¹·r` for the iterative methods (not differentiated). Enzyme generates the derivatives the
/// implicit rule needs. The solves call the product through copies
/// compiled for AVX-512 and AVX2 (chosen at run time): mark it
/// `#[inline(always)]` so that each copy inlines it and vectorises it that
/// wide (the heat product of `problems::implicit_heat` does). The crate that invokes it needs what
/// [`differentiable!`](crate::differentiable) needs (the autodiff feature
/// and flag, a fat-LTO release build).
#[macro_export]
macro_rules! linear_system {
    ($ty:ty => $matvec:path, $rhs:path, coefficients = $coef:path $(, preconditioner = $pre:path)?) => {
        $crate::linear_system!(@coefficients $ty, $coef);
        $crate::linear_system!(@functions $ty, $matvec, $rhs, [$($pre)?]);
    };
    ($ty:ty => $matvec:path, $rhs:path $(, preconditioner = $pre:path)?) => {
        $crate::linear_system!(@functions $ty, $matvec, $rhs, [$($pre)?]);
        const _: () = {
            impl $crate::implicit::SystemCoefficients for $ty {
                fn coefficients(&self, p: &[f64], c: &mut [f64]) {
                    c.copy_from_slice(p)
                }
                fn coefficients_vjp(&self, _p: &[f64], dc: &mut [f64], dp: &mut [f64]) {
                    for (d, c) in dp.iter_mut().zip(dc.iter_mut()) {
                        *d += *c;
                        *c = 0.0;
                    }
                }
                fn coefficients_jvp(&self, p: &[f64], tp: &[f64], c: &mut [f64], tc: &mut [f64]) {
                    c.copy_from_slice(p);
                    tc.copy_from_slice(tp);
                }
            }
        };
    };
    (@coefficients $ty:ty, $coef:path) => {
        #[allow(clippy::too_many_arguments)]
        const _: () = {
            #[::std::autodiff::autodiff_reverse(diffsim_coefficients_vjp, Const, Duplicated, Duplicated)]
            fn diffsim_coefficients_reverse(s: &$ty, p: &[f64], c: &mut [f64]) {
                $coef(s, p, c)
            }
            #[::std::autodiff::autodiff_forward(diffsim_coefficients_jvp, Const, Dual, Dual)]
            fn diffsim_coefficients_forward(s: &$ty, p: &[f64], c: &mut [f64]) {
                $coef(s, p, c)
            }
            impl $crate::implicit::SystemCoefficients for $ty {
                fn coefficients(&self, p: &[f64], c: &mut [f64]) {
                    $coef(self, p, c)
                }
                #[inline(never)]
                fn coefficients_vjp(&self, p: &[f64], dc: &mut [f64], dp: &mut [f64]) {
                    let m = $crate::implicit::LinearSystem::n_coefficients(self);
                    $crate::op::with_scratch(m, |c| diffsim_coefficients_vjp(self, p, dp, c, dc));
                }
                #[inline(never)]
                fn coefficients_jvp(&self, p: &[f64], tp: &[f64], c: &mut [f64], tc: &mut [f64]) {
                    diffsim_coefficients_jvp(self, p, tp, c, tc)
                }
            }
        };
    };
    (@functions $ty:ty, $matvec:path, $rhs:path, [$($pre:path)?]) => {
        #[allow(clippy::too_many_arguments)]
        const _: () = {
            #[::std::autodiff::autodiff_reverse(diffsim_matvec_vjp, Const, Duplicated, Duplicated, Duplicated)]
            fn diffsim_matvec_reverse(s: &$ty, v: &[f64], c: &[f64], out: &mut [f64]) {
                $matvec(s, v, c, out)
            }
            #[::std::autodiff::autodiff_reverse(diffsim_matvec_vjp_coefficients, Const, Const, Duplicated, Duplicated)]
            fn diffsim_matvec_coefficients_reverse(s: &$ty, v: &[f64], c: &[f64], out: &mut [f64]) {
                $matvec(s, v, c, out)
            }
            #[::std::autodiff::autodiff_forward(diffsim_matvec_jvp, Const, Dual, Dual, Dual)]
            fn diffsim_matvec_forward(s: &$ty, v: &[f64], c: &[f64], out: &mut [f64]) {
                $matvec(s, v, c, out)
            }
            #[::std::autodiff::autodiff_reverse(diffsim_rhs_vjp, Const, Duplicated, Duplicated, Duplicated)]
            fn diffsim_rhs_reverse(s: &$ty, x: &[f64], p: &[f64], b: &mut [f64]) {
                $rhs(s, x, p, b)
            }
            #[::std::autodiff::autodiff_forward(diffsim_rhs_jvp, Const, Dual, Dual, Dual)]
            fn diffsim_rhs_forward(s: &$ty, x: &[f64], p: &[f64], b: &mut [f64]) {
                $rhs(s, x, p, b)
            }

            impl $crate::implicit::SystemProducts for $ty {
                fn matvec(&self, v: &[f64], c: &[f64], out: &mut [f64]) {
                    // The iterations' products, in the widest vectors the
                    // processor has (the user's function inlined into each
                    // copy when it is `#[inline]`); the derivatives below
                    // stay in the baseline instructions.
                    $crate::linear_system!(@widest $ty, $matvec, self, v, c, out)
                }
                #[inline(never)]
                fn matvec_vjp(&self, v: &[f64], c: &[f64], w: &mut [f64], dv: &mut [f64], dc: &mut [f64]) {
                    let n = $crate::implicit::LinearSystem::n(self);
                    $crate::op::with_scratch(n, |out| diffsim_matvec_vjp(self, v, dv, c, dc, out, w));
                }
                #[inline(never)]
                fn matvec_vjp_coefficients(&self, v: &[f64], c: &[f64], w: &mut [f64], dc: &mut [f64]) {
                    let n = $crate::implicit::LinearSystem::n(self);
                    $crate::op::with_scratch(n, |out| diffsim_matvec_vjp_coefficients(self, v, c, dc, out, w));
                }
                #[inline(never)]
                fn matvec_jvp(&self, v: &[f64], c: &[f64], tv: &[f64], tc: &[f64], out: &mut [f64], tout: &mut [f64]) {
                    diffsim_matvec_jvp(self, v, tv, c, tc, out, tout)
                }
                fn rhs(&self, x: &[f64], p: &[f64], b: &mut [f64]) {
                    $rhs(self, x, p, b)
                }
                #[inline(never)]
                fn rhs_vjp(&self, x: &[f64], p: &[f64], w: &mut [f64], dx: &mut [f64], dp: &mut [f64]) {
                    let n = $crate::implicit::LinearSystem::n(self);
                    $crate::op::with_scratch(n, |b| diffsim_rhs_vjp(self, x, dx, p, dp, b, w));
                }
                #[inline(never)]
                fn rhs_jvp(&self, x: &[f64], p: &[f64], tx: &[f64], tp: &[f64], b: &mut [f64], tb: &mut [f64]) {
                    diffsim_rhs_jvp(self, x, tx, p, tp, b, tb)
                }
                $(
                    fn has_preconditioner(&self) -> bool {
                        true
                    }
                    fn precondition(&self, c: &[f64], r: &[f64], z: &mut [f64]) {
                        // In the widest vectors, like the product.
                        $crate::linear_system!(@widest $ty, $pre, self, c, r, z)
                    }
                )?
            }
        };
    };
    // `f(s, a, b, out)` through copies compiled for AVX-512 and AVX2, chosen
    // at run time, else the baseline.
    (@widest $ty:ty, $f:path, $s:expr, $a:expr, $b:expr, $out:expr) => {{
        #[cfg(target_arch = "x86_64")]
        {
            #[target_feature(enable = "avx512f")]
            fn wide(s: &$ty, a: &[f64], b: &[f64], out: &mut [f64]) {
                $f(s, a, b, out)
            }
            #[target_feature(enable = "avx2")]
            fn medium(s: &$ty, a: &[f64], b: &[f64], out: &mut [f64]) {
                $f(s, a, b, out)
            }
            if $crate::solvers::simd::avx512_allowed() {
                // SAFETY: the processor has AVX-512F, checked just above.
                return unsafe { wide($s, $a, $b, $out) };
            }
            if $crate::solvers::simd::avx2_allowed() {
                // SAFETY: the processor has AVX2, checked just above.
                return unsafe { medium($s, $a, $b, $out) };
            }
        }
        $f($s, $a, $b, $out)
    }};
}

/// How a [`LinearSolve`] solves.
#[derive(Clone, Copy, Debug, PartialEq, Eq, serde::Serialize, serde::Deserialize)]
pub enum SolveMethod {
    /// Conjugate gradients: `A(p)` symmetric positive definite (the
    /// adjoint solve is then the same solve).
    Cg,
    /// BiCGStab: any non-singular `A(p)` (the adjoint solves with `Aᵀ`,
    /// its product from Enzyme's derivative of the matrix-vector product).
    BiCgStab,
    /// A direct solve, for small systems: `A(p)` assembled by `n` products
    /// with the unit vectors and factored by faer's LU with partial
    /// pivoting, dense up to 64 unknowns, sparse (its nonzero entries kept)
    /// above; the adjoint solves with the transposed factors. Exact to
    /// rounding (the tolerance is not used); a singular matrix is an error.
    Direct,
}

/// Settings of a [`LinearSolve`]; `Default`: CG to a relative residual of
/// 1e-10, at most 10,000 iterations.
#[derive(Clone, Copy, Debug, PartialEq, serde::Serialize, serde::Deserialize)]
pub struct SolveParams {
    /// The method.
    pub method: SolveMethod,
    /// Relative tolerance on the true residual, `‖b − A·y‖₂ ≤ tol·‖b‖₂`
    /// (the iterative methods).
    pub tolerance: f64,
    /// More iterations (BiCGStab: matrix products) than this is an error.
    pub max_iterations: usize,
    /// Where the iterative methods start.
    #[serde(default)]
    pub start: Start,
}

/// The first iterate of an iterative solve.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq, serde::Serialize, serde::Deserialize)]
pub enum Start {
    /// Zero.
    #[default]
    Zero,
    /// The right-hand side: close to the solution when the matrix is close
    /// to the identity, as in a time step `(I + dt·A)·y = x` (and its
    /// adjoint). Deterministic, like `Zero`: the same solve gives the same
    /// bits whatever was solved before.
    Rhs,
}

impl SolveParams {
    /// The relative error the solves leave: the tolerance of the iterative
    /// methods, 0 for the direct solve (exact to rounding).
    pub fn solve_tolerance(&self) -> f64 {
        if self.method == SolveMethod::Direct { 0.0 } else { self.tolerance }
    }
}

impl Default for SolveParams {
    fn default() -> Self {
        SolveParams { method: SolveMethod::Cg, tolerance: 1e-10, max_iterations: 10_000, start: Start::Zero }
    }
}

/// Iterations of a [`LinearSolve`]'s solves so far.
#[derive(Debug, Default)]
pub struct SolveInfo {
    /// Of the forward solves (and the JVPs').
    pub forward: AtomicUsize,
    /// Of the adjoint solves.
    pub adjoint: AtomicUsize,
}

/// The operator `(x, p) ↦ y` with `A(p)·y = b(x, p)` for a user's system
/// `S` ([`linear_system!`](crate::linear_system)); derivatives by the
/// implicit rule (module docs).
#[derive(Debug)]
pub struct LinearSolve<S> {
    /// The user's system.
    pub system: S,
    /// How it is solved.
    pub params: SolveParams,
    /// Iterations so far.
    pub info: SolveInfo,
    error: Mutex<Option<OpError>>,
    /// The last parameters and their coefficients `c(p)`: a rollout solves
    /// with the same `p` at every step, forward and backward.
    cache: Mutex<(Vec<f64>, Arc<Vec<f64>>)>,
    /// CG's vectors.
    work: Mutex<CgWork>,
}

impl<S: LinearSystem> LinearSolve<S> {
    /// The solve of `system` with `params`.
    ///
    /// # Panics
    /// If the tolerance is not a positive finite number, the iteration
    /// limit is 0, or the system has a constant null space and the method
    /// is not CG.
    #[track_caller]
    pub fn new(system: S, params: SolveParams) -> Self {
        if !(params.tolerance.is_finite() && params.tolerance > 0.0) || params.max_iterations == 0 {
            panic!(
                "LinearSolve: the tolerance must be a positive number and the iteration limit at least 1, got {} and {}",
                params.tolerance, params.max_iterations
            );
        }
        if system.constant_null_space() && params.method != SolveMethod::Cg {
            panic!("LinearSolve: a system with a constant null space is solved by SolveMethod::Cg, got {:?}", params.method);
        }
        let work = Mutex::new(CgWork::new(if params.method == SolveMethod::Cg { system.n() } else { 0 }));
        LinearSolve { system, params, info: SolveInfo::default(), error: Mutex::new(None), cache: Mutex::new((Vec::new(), Arc::new(Vec::new()))), work }
    }
}

/// A preconditioner, `z = M⁻¹·r`.
pub(crate) type Precondition<'a> = &'a dyn Fn(&[f64], &mut [f64]);

/// A matrix given by its product (and perhaps a preconditioner), as CG's
/// [`System`].
struct Product<'a, F> {
    apply: F,
    precondition: Option<Precondition<'a>>,
    constant_null: bool,
}

impl<F: FnMut(&[f64], &mut [f64])> System for Product<'_, F> {
    fn apply(&mut self, v: &[f64], out: &mut [f64]) {
        (self.apply)(v, out);
    }
    fn precondition(&mut self, r: &[f64], z: &mut [f64]) -> bool {
        match self.precondition {
            Some(m) => {
                m(r, z);
                true
            }
            None => false,
        }
    }
    fn null(&self) -> Null<'_> {
        if self.constant_null { Null::Constant(None) } else { Null::None }
    }
}

/// How [`solve_system`] may help its iterations: a preconditioner
/// `z = M⁻¹·r` (CG and BiCGStab, on the right, the same `M` for the
/// transposed solve; the direct solve ignores it), and whether `A` has the
/// constant null space (CG).
#[derive(Clone, Copy, Default)]
pub(crate) struct Aids<'a> {
    pub precondition: Option<Precondition<'a>>,
    pub constant_null: bool,
}

/// Solves `A·y = b` (`transposed`: `Aᵀ·y = b`) by `params`, the matrix
/// given by its product `apply` and transposed product `apply_t` (called
/// only by BiCGStab's transposed solve), helped by `aids`, and returns the
/// iterations (0 for the direct solve). CG takes `A` symmetric, so its
/// transposed solve is the same solve. On failure `y` is left unspecified.
/// Shared by the linear solve, Newton's method and the integrators.
#[allow(clippy::too_many_arguments)]
pub(crate) fn solve_system(
    params: &SolveParams,
    mut apply: impl FnMut(&[f64], &mut [f64]),
    apply_t: impl FnMut(&[f64], &mut [f64]),
    aids: Aids<'_>,
    b: &[f64],
    y: &mut [f64],
    transposed: bool,
    work: Option<&mut CgWork>,
) -> Result<usize, OpError> {
    let stop = Stop { tolerance: params.tolerance, max_iterations: params.max_iterations };
    let n = b.len();
    let warm = params.start == Start::Rhs && params.method != SolveMethod::Direct;
    if warm {
        y.copy_from_slice(b);
    }
    let iterations = match params.method {
        SolveMethod::Cg => {
            let mut system = Product { apply, precondition: aids.precondition, constant_null: aids.constant_null };
            match work {
                Some(work) => diffsim_solvers::cg::solve(&mut system, work, stop, b, y, warm)?,
                None => diffsim_solvers::cg::solve(&mut system, &mut CgWork::new(n), stop, b, y, warm)?,
            }
        }
        SolveMethod::BiCgStab => match (aids.precondition, transposed) {
            (Some(m), true) => bicgstab_preconditioned(apply_t, m, stop, b, y, warm)?,
            (Some(m), false) => bicgstab_preconditioned(apply, m, stop, b, y, warm)?,
            (None, true) => bicgstab(apply_t, stop, b, y, warm)?,
            (None, false) => bicgstab(apply, stop, b, y, warm)?,
        },
        SolveMethod::Direct => {
            let lu = factor(n, &mut apply)?;
            y.copy_from_slice(b);
            lu.solve(y, transposed);
            if !y.iter().all(|v| v.is_finite()) {
                return Err(singular());
            }
            0
        }
    };
    Ok(iterations)
}

/// Whether `a` and `b` hold the same bits; without an early exit, so that
/// the compare vectorises.
pub(crate) fn same_bits(a: &[f64], b: &[f64]) -> bool {
    a.len() == b.len() && a.iter().zip(b).fold(0, |d, (a, b)| d | (a.to_bits() ^ b.to_bits())) == 0
}

/// The error of a direct solve whose matrix is singular.
pub(crate) fn singular() -> OpError {
    OpError::Input(crate::op::OpMessage::new("a direct solve: the matrix is singular"))
}

/// Systems up to this size are factored dense (faer's dense LU), larger
/// ones sparse: for a few unknowns (an ODE's state) setting up a sparse
/// factorisation costs many times the arithmetic (`bench robertson`).
const DENSE_UP_TO: usize = diffsim_solvers::linalg::DENSE_SOLVE_MAX;

/// The factors of a direct solve (the sparse variant stays inline: a boxed
/// faer type is one more thing for rustc's type trees in this flagged
/// crate): the dense matrix (factored with each
/// solve, [`diffsim_solvers::linalg::dense_solve`]; a direct solve solves
/// once per assembly) or a sparse LU.
#[allow(clippy::large_enum_variant)]
enum Factors {
    Dense(usize, Vec<f64>),
    Sparse(diffsim_solvers::linalg::SparseLu),
}

impl Factors {
    /// `b = A⁻¹·b` (`transposed`: `A⁻ᵀ·b`); once (the dense matrix is
    /// factored in place).
    fn solve(mut self, b: &mut [f64], transposed: bool) {
        match &mut self {
            Factors::Dense(n, a) => diffsim_solvers::linalg::dense_solve(*n, a, b, transposed),
            Factors::Sparse(lu) if transposed => lu.solve_transpose_in_place(b),
            Factors::Sparse(lu) => lu.solve_in_place(b),
        }
    }
}

/// [`SolveMethod::Direct`]: the matrix assembled column by column from its
/// products with the unit vectors (dense up to [`DENSE_UP_TO`] unknowns,
/// else its nonzero entries kept), and its LU.
fn factor(n: usize, apply: &mut impl FnMut(&[f64], &mut [f64])) -> Result<Factors, OpError> {
    let not_finite = || OpError::Input(crate::op::OpMessage::new("a direct solve: the matrix holds a NaN or an infinity"));
    let (mut unit, mut column) = (vec![0.0; n], vec![0.0; n]);
    if n <= DENSE_UP_TO {
        let mut a = vec![0.0; n * n];
        for (j, col) in a.chunks_exact_mut(n.max(1)).enumerate() {
            unit[j] = 1.0;
            apply(&unit, col);
            unit[j] = 0.0;
        }
        if !a.iter().all(|v| v.is_finite()) {
            return Err(not_finite());
        }
        return Ok(Factors::Dense(n, a));
    }
    let mut entries = Vec::new();
    for j in 0..n {
        unit[j] = 1.0;
        apply(&unit, &mut column);
        unit[j] = 0.0;
        entries.extend(column.iter().enumerate().filter(|(_, v)| **v != 0.0).map(|(i, &v)| (i, j, v)));
    }
    if entries.iter().any(|(_, _, v)| !v.is_finite()) {
        return Err(not_finite());
    }
    diffsim_solvers::linalg::SparseLu::new(n, &entries).map(Factors::Sparse).map_err(|_| singular())
}

/// Keeps the first failure in `kept` (for [`Forward::take_error`]).
pub(crate) fn keep(kept: &Mutex<Option<OpError>>, e: OpError) {
    let mut kept = kept.lock().unwrap_or_else(|poisoned| poisoned.into_inner());
    kept.get_or_insert(e);
}

/// Leaves `y` NaN and keeps the first failure in `kept`.
pub(crate) fn fail(kept: &Mutex<Option<OpError>>, y: &mut [f64], e: OpError) {
    y.fill(f64::NAN);
    keep(kept, e);
}

/// Panics, naming the operator, when the output a rollout hands to
/// `vjp_overwrite_given` is not `n_out` long.
#[track_caller]
pub(crate) fn check_given(name: &str, given: &[f64], n_out: usize) {
    if given.len() != n_out {
        panic!("{name}: the given output has length {}, the operator's output {n_out}", given.len());
    }
}

/// Takes the kept failure.
pub(crate) fn take(kept: &Mutex<Option<OpError>>) -> Option<OpError> {
    let mut kept = kept.lock().unwrap_or_else(|poisoned| poisoned.into_inner());
    kept.take()
}

impl<S: SystemFunctions> LinearSolve<S> {
    /// Solves `A(p)·y = b` (the adjoint solve: `A(p)ᵀ·y = b`) into `y`; a
    /// failure leaves `y` NaN and is kept for [`Forward::take_error`].
    fn solve(&self, c: &[f64], b: &[f64], y: &mut [f64], adjoint: bool) {
        let (n, m) = (self.system.n(), self.system.n_coefficients());
        let (mut w, mut dp) = (Vec::new(), Vec::new());
        let transposed_product = |v: &[f64], out: &mut [f64]| {
            // Aᵀ·v: the VJP of u ↦ A(p)·u, at any u (it is linear).
            w.clear();
            w.extend_from_slice(v);
            dp.resize(m, 0.0);
            out.fill(0.0);
            self.system.matvec_vjp(v, c, &mut w, out, &mut dp);
        };
        // CG's vectors, kept between solves (a busy set is passed by).
        let mut kept = self.work.try_lock();
        let work = kept.as_deref_mut().ok().filter(|_| self.params.method == SolveMethod::Cg);
        let precondition = |r: &[f64], z: &mut [f64]| self.system.precondition(c, r, z);
        let precondition = self.system.has_preconditioner().then_some(&precondition as &dyn Fn(&[f64], &mut [f64]));
        let aids = Aids { precondition, constant_null: self.system.constant_null_space() };
        let result = solve_system(&self.params, |v, out| self.system.matvec(v, c, out), transposed_product, aids, b, y, adjoint, work);
        debug_assert_eq!(y.len(), n);
        let counter = if adjoint { &self.info.adjoint } else { &self.info.forward };
        match result {
            Ok(it) => {
                counter.fetch_add(it, Ordering::Relaxed);
            }
            Err(e) => {
                if let OpError::NoConvergence { iterations, .. } = e {
                    counter.fetch_add(iterations, Ordering::Relaxed);
                }
                fail(&self.error, y, e);
            }
        }
    }
}

impl<S: LinearSystem> Operator for LinearSolve<S> {
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

impl<S: SystemFunctions> Forward for LinearSolve<S> {
    #[track_caller]
    fn forward(&self, x: &[f64], p: &[f64], y: &mut [f64]) {
        validate_forward(self, "LinearSolve", x, p, y);
        let mut b = vec![0.0; self.system.n()];
        self.system.rhs(x, p, &mut b);
        let c = self.coefficients(p);
        self.solve(&c, &b, y, false);
    }

    /// The iterative methods' tolerance; 0 for the direct solve.
    fn solve_tolerance(&self) -> f64 {
        self.params.solve_tolerance()
    }

    fn take_error(&self) -> Option<OpError> {
        take(&self.error)
    }
}

impl<S: SystemFunctions> Vjp for LinearSolve<S> {
    #[track_caller]
    fn vjp(&self, x: &[f64], p: &[f64], dy: &mut [f64], dx: &mut [f64], dp: &mut [f64]) {
        validate_vjp(self, "LinearSolve", x, p, dy, dx, dp);
        // The solution (the forward solve again), then the rule.
        let mut y = vec![0.0; self.system.n()];
        self.forward(x, p, &mut y);
        self.vjp_from_solution(x, p, &y, dy, dx, dp);
    }

    /// The solution is the rollout's next state: no forward solve.
    #[track_caller]
    fn vjp_overwrite_given(&self, x: &[f64], p: &[f64], y: &[f64], dy: &mut [f64], dx: &mut [f64], dp: &mut [f64]) {
        validate_vjp(self, "LinearSolve", x, p, dy, dx, dp);
        check_given("LinearSolve", y, self.system.n());
        dx.fill(0.0);
        self.vjp_from_solution(x, p, y, dy, dx, dp);
    }

    /// The coefficients' cotangent `c̄`, then the right-hand side's `p̄`.
    fn n_deferred(&self) -> usize {
        self.system.n_coefficients() + self.system.n_params()
    }

    /// The rule without the coefficients' VJP: `c̄` gathered over the
    /// backward pass, `(∂c/∂p)ᵀ·c̄` formed once by `finish_deferred`.
    #[track_caller]
    fn vjp_deferred(&self, x: &[f64], p: &[f64], y: Option<&[f64]>, dy: &mut [f64], dx: &mut [f64], acc: &mut [f64]) {
        if acc.len() != self.n_deferred() {
            panic!("LinearSolve: the deferred cotangent has length {}, the operator's {}", acc.len(), self.n_deferred());
        }
        validate_vjp(self, "LinearSolve", x, p, dy, dx, &acc[self.system.n_coefficients()..]);
        let solved;
        let y = match y {
            Some(y) => {
                check_given("LinearSolve", y, self.system.n());
                y
            }
            None => {
                let mut own = vec![0.0; self.system.n()];
                self.forward(x, p, &mut own);
                solved = own;
                &solved
            }
        };
        dx.fill(0.0);
        let (dc, dp) = acc.split_at_mut(self.system.n_coefficients());
        self.rule(x, p, y, dy, dx, dc, dp);
    }

    fn finish_deferred(&self, p: &[f64], acc: &mut [f64], dp: &mut [f64]) {
        let (dc, direct) = acc.split_at_mut(self.system.n_coefficients());
        self.system.coefficients_vjp(p, dc, dp);
        for (d, a) in dp.iter_mut().zip(direct.iter_mut()) {
            *d += *a;
            *a = 0.0;
        }
    }
}

impl<S: SystemFunctions> LinearSolve<S> {
    /// The matrix's coefficients `c(p)`, from the cache when `p` is the
    /// last one's (bit for bit; a busy cache is passed by).
    fn coefficients(&self, p: &[f64]) -> Arc<Vec<f64>> {
        if let Ok(cache) = self.cache.try_lock()
            && same_bits(&cache.0, p)
        {
            return Arc::clone(&cache.1);
        }
        let mut c = vec![0.0; self.system.n_coefficients()];
        self.system.coefficients(p, &mut c);
        let c = Arc::new(c);
        if let Ok(mut cache) = self.cache.try_lock() {
            cache.0.clear();
            cache.0.extend_from_slice(p);
            cache.1 = Arc::clone(&c);
        }
        c
    }

    /// The implicit rule at the solution `y`: one adjoint solve, then the
    /// derivatives of the user's functions.
    fn vjp_from_solution(&self, x: &[f64], p: &[f64], y: &[f64], dy: &mut [f64], dx: &mut [f64], dp: &mut [f64]) {
        let mut dc = vec![0.0; self.system.n_coefficients()];
        self.rule(x, p, y, dy, dx, &mut dc, dp);
        self.system.coefficients_vjp(p, &mut dc, dp);
    }

    /// The rule up to the coefficients' VJP: `λ` from `Aᵀ·λ = ȳ`, then
    /// `c̄ −= (∂(A(c)·y)/∂c)ᵀ·λ`, `x̄ += (∂b/∂x)ᵀ·λ`, `p̄ += (∂b/∂p)ᵀ·λ`;
    /// consumes `ȳ`.
    #[allow(clippy::too_many_arguments)]
    fn rule(&self, x: &[f64], p: &[f64], y: &[f64], dy: &mut [f64], dx: &mut [f64], dc: &mut [f64], dp: &mut [f64]) {
        let n = self.system.n();
        let c = self.coefficients(p);
        let mut lambda = vec![0.0; n];
        self.solve(&c, dy, &mut lambda, true);
        let mut w: Vec<f64> = lambda.iter().map(|l| -l).collect();
        self.system.matvec_vjp_coefficients(y, &c, &mut w, dc);
        self.system.rhs_vjp(x, p, &mut lambda, dx, dp);
        dy.fill(0.0);
    }
}

impl<S: SystemFunctions> Jvp for LinearSolve<S> {
    #[track_caller]
    fn jvp(&self, x: &[f64], p: &[f64], tx: &[f64], tp: &[f64], y: &mut [f64], ty: &mut [f64]) {
        validate_jvp(self, "LinearSolve", x, p, tx, tp, y, ty);
        let n = self.system.n();
        let (mut b, mut tb) = (vec![0.0; n], vec![0.0; n]);
        self.system.rhs_jvp(x, p, tx, tp, &mut b, &mut tb);
        let m = self.system.n_coefficients();
        let (mut c, mut tc) = (vec![0.0; m], vec![0.0; m]);
        self.system.coefficients_jvp(p, tp, &mut c, &mut tc);
        self.solve(&c, &b, y, false);
        // ẏ solves A·ẏ = ḃ − (∂(A(c)·y)/∂c)·ċ.
        let (mut ay, mut tay, zero) = (vec![0.0; n], vec![0.0; n], vec![0.0; n]);
        self.system.matvec_jvp(y, &c, &zero, &tc, &mut ay, &mut tay);
        for (t, a) in tb.iter_mut().zip(&tay) {
            *t -= a;
        }
        self.solve(&c, &tb, ty, false);
    }
}
