//! Time integrators from a right-hand side: the user writes `f(u, p)` of
//! `du/dt = f(u, p)` as a plain function; [`Integrator`] is one step of a
//! Runge–Kutta scheme, explicit or diagonally implicit, as an operator
//! `(u_n, p) ↦ u_{n+1}` that rollouts, checkpointing, training and the
//! checks take like any other.
//!
//! ```ignore
//! fn rates(s: &Kinetics, u: &[f64], p: &[f64], du: &mut [f64]) { /* du = f(u, p) */ }
//! diffsim::ode_system!(Kinetics => rates);
//! let step = Integrator::new(Kinetics, IntegratorParams::new(Scheme::Sdirk2, 0.1));
//! ```
//!
//! A step with stages `Y_i = z_i + h·a_ii·f(Y_i)`, `z_i = u_n + h·Σ_{j<i}
//! a_ij·k_j`, `k_i = f(Y_i)`, `u_{n+1} = u_n + h·Σ b_i·k_i` solves each
//! implicit stage (`a_ii ≠ 0`) by Newton's method with the Jacobian
//! `I − h·a_ii·∂f/∂u` (its products from Enzyme's derivatives of `f`).
//! Solved directly (the default, up to 64 unknowns), the step's stages
//! share one factored Jacobian, formed at the first stage's start and
//! formed again only where Newton's steps stop contracting (simplified
//! Newton, as stiff codes do); the roots are the same to the tolerance,
//! and the adjoint solves use the exact Jacobian at each stage. The
//! derivatives are the discrete step's, exact to the Newton tolerance: in
//! reverse, stage by stage from the last,
//!
//! ```text
//! (I − h·a_ii·∂f/∂u)ᵀ·ω_i = k̄_i,   z̄_i = (∂f/∂u)ᵀ·ω_i,   p̄ += (∂f/∂p)ᵀ·ω_i,
//! ū_n += z̄_i,   k̄_j += h·a_ij·z̄_i  (j < i)
//! ```
//!
//! one transposed solve per implicit stage, one VJP of `f` per stage. For
//! stiffly accurate schemes (backward Euler, Crank–Nicolson, the SDIRKs) a
//! rollout hands the step its output, which is the last stage, so that
//! stage is not solved again in reverse.
//!
//! BDF2 is the same machinery with one stage from the base point
//! `(4·u_n − u_{n−1})/3` and both time levels in its state
//! ([`Scheme::Bdf2`]).
//!
//! The right-hand side is autonomous; a time-dependent one carries `t` as a
//! component of `u` with `dt/dt = 1`.

use std::sync::Mutex;

use super::linear::{check_given, fail, keep, same_bits, take};
use super::newton::{Equations, HeldJacobian, NewtonInfo, NewtonParams, jacobian_solve, newton, newton_held};
use crate::op::{Forward, Jvp, OpError, Operator, Vjp, validate_forward, validate_jvp, validate_vjp};

/// The size of a user's system of ordinary differential equations
/// `du/dt = f(u, p)`.
pub trait OdeSystem {
    /// Unknowns `u`.
    fn n(&self) -> usize;
    /// Parameters `p`.
    fn n_params(&self) -> usize {
        0
    }
}

/// A right-hand side and its derivatives, implemented by
/// [`ode_system!`](crate::ode_system) with Enzyme; not written by hand.
#[doc(hidden)]
pub trait RhsFunctions: OdeSystem {
    /// `out = f(u, p)`.
    fn f(&self, u: &[f64], p: &[f64], out: &mut [f64]);
    /// `tout = (∂f/∂u)·tu` (and `out = f`).
    fn f_jvp_u(&self, u: &[f64], p: &[f64], tu: &[f64], out: &mut [f64], tout: &mut [f64]);
    /// `tout = (∂f/∂u)·tu + (∂f/∂p)·tp` (and `out = f`).
    #[allow(clippy::too_many_arguments)]
    fn f_jvp(&self, u: &[f64], p: &[f64], tu: &[f64], tp: &[f64], out: &mut [f64], tout: &mut [f64]);
    /// `du += (∂f/∂u)ᵀ·w`, `dp += (∂f/∂p)ᵀ·w`; consumes `w`.
    fn f_vjp(&self, u: &[f64], p: &[f64], w: &mut [f64], du: &mut [f64], dp: &mut [f64]);
    /// The user's Jacobian `∂f/∂u` into `jac` (`n × n`, column by column),
    /// when the system names one (`ode_system!(.., jacobian = j)`); `false`
    /// (nothing written) when it does not.
    fn jacobian(&self, u: &[f64], p: &[f64], jac: &mut [f64]) -> bool {
        let _ = (u, p, jac);
        false
    }
}

/// Makes `Sys` (an [`OdeSystem`], plain data) the system of an
/// [`Integrator`] from its right-hand side `fn(&Sys, u, p, du)`, a plain
/// function that writes every element of `du`. Enzyme generates the
/// derivatives the schemes and their adjoints need. With `jacobian = j`,
/// a function `fn(&Sys, u, p, jac)` writing `∂f/∂u` (`n × n`, column by
/// column: `jac[j·n + i] = ∂f_i/∂u_j`) replaces the `n` Enzyme products
/// that form the Jacobian where the stages are solved directly (up to 64
/// unknowns): Newton's steps and the adjoint solves use it, so it must be
/// exact (the checks find a wrong one). The crate that invokes it needs
/// what [`differentiable!`](crate::differentiable) needs.
#[macro_export]
macro_rules! ode_system {
    ($ty:ty => $f:path, jacobian = $jac:path) => {
        $crate::ode_system!(@functions $ty, $f, [$jac]);
    };
    ($ty:ty => $f:path) => {
        $crate::ode_system!(@functions $ty, $f, []);
    };
    (@functions $ty:ty, $f:path, [$($jac:path)?]) => {
        #[allow(clippy::too_many_arguments)]
        const _: () = {
            #[::std::autodiff::autodiff_reverse(diffsim_f_vjp, Const, Duplicated, Duplicated, Duplicated)]
            fn diffsim_f_reverse(s: &$ty, u: &[f64], p: &[f64], out: &mut [f64]) {
                $f(s, u, p, out)
            }
            #[::std::autodiff::autodiff_forward(diffsim_f_jvp, Const, Dual, Dual, Dual)]
            fn diffsim_f_forward(s: &$ty, u: &[f64], p: &[f64], out: &mut [f64]) {
                $f(s, u, p, out)
            }
            #[::std::autodiff::autodiff_forward(diffsim_f_jvp_u, Const, Dual, Const, Dual)]
            fn diffsim_f_forward_u(s: &$ty, u: &[f64], p: &[f64], out: &mut [f64]) {
                $f(s, u, p, out)
            }

            impl $crate::implicit::RhsFunctions for $ty {
                fn f(&self, u: &[f64], p: &[f64], out: &mut [f64]) {
                    $f(self, u, p, out)
                }
                #[inline(never)]
                fn f_jvp_u(&self, u: &[f64], p: &[f64], tu: &[f64], out: &mut [f64], tout: &mut [f64]) {
                    diffsim_f_jvp_u(self, u, tu, p, out, tout)
                }
                #[inline(never)]
                fn f_jvp(&self, u: &[f64], p: &[f64], tu: &[f64], tp: &[f64], out: &mut [f64], tout: &mut [f64]) {
                    diffsim_f_jvp(self, u, tu, p, tp, out, tout)
                }
                #[inline(never)]
                fn f_vjp(&self, u: &[f64], p: &[f64], w: &mut [f64], du: &mut [f64], dp: &mut [f64]) {
                    let n = $crate::implicit::OdeSystem::n(self);
                    $crate::op::with_scratch(n, |out| diffsim_f_vjp(self, u, du, p, dp, out, w));
                }
                $(
                    fn jacobian(&self, u: &[f64], p: &[f64], jac: &mut [f64]) -> bool {
                        $jac(self, u, p, jac);
                        true
                    }
                )?
            }
        };
    };
}

/// A Runge–Kutta scheme of fixed step.
#[derive(Clone, Copy, Debug, PartialEq, Eq, serde::Serialize, serde::Deserialize)]
pub enum Scheme {
    /// Explicit, order 3, strong-stability preserving (Shu–Osher).
    SspRk3,
    /// Explicit, order 4, the classical one.
    Rk4,
    /// Implicit, order 1, L-stable.
    BackwardEuler,
    /// Implicit, order 2, A-stable (not L-stable: stiff modes ring).
    CrankNicolson,
    /// Two implicit stages, order 2, L-stable, stiffly accurate
    /// (Alexander 1977, `γ = 1 − 1/√2`).
    Sdirk2,
    /// Three implicit stages, order 3, L-stable, stiffly accurate
    /// (Alexander 1977, `γ ≈ 0.4358665`).
    Sdirk3,
    /// The two-step backward differentiation formula, order 2, L-stable:
    /// `u_{n+1} = (4·u_n − u_{n−1})/3 + (2h/3)·f(u_{n+1})`. Its state is
    /// both levels, `[u_n, u_{n−1}]` (`2n` values), and a step returns
    /// `[u_{n+1}, u_n]`. The first state `[u_1, u_0]` comes from
    /// [`Integrator::bdf2_start`] (one SDIRK2 step, so the scheme stays
    /// second order), whose VJP carries the gradient back to `u_0`.
    Bdf2,
}

impl Scheme {
    /// Every scheme, for loops over them.
    pub const ALL: [Scheme; 7] = [Scheme::SspRk3, Scheme::Rk4, Scheme::BackwardEuler, Scheme::CrankNicolson, Scheme::Sdirk2, Scheme::Sdirk3, Scheme::Bdf2];

    /// The order of accuracy.
    pub fn order(self) -> usize {
        match self {
            Scheme::BackwardEuler => 1,
            Scheme::CrankNicolson | Scheme::Sdirk2 | Scheme::Bdf2 => 2,
            Scheme::SspRk3 | Scheme::Sdirk3 => 3,
            Scheme::Rk4 => 4,
        }
    }

    /// Time levels in the state: 2 for [`Scheme::Bdf2`], 1 for the others.
    pub fn levels(self) -> usize {
        if self == Scheme::Bdf2 { 2 } else { 1 }
    }

    /// Whether a step solves equations.
    pub fn is_implicit(self) -> bool {
        !matches!(self, Scheme::SspRk3 | Scheme::Rk4)
    }

    /// The Butcher tableau: stages, `A` row-major (lower triangular), `b`.
    fn tableau(self) -> (usize, Vec<f64>, Vec<f64>) {
        match self {
            Scheme::SspRk3 => (3, vec![0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.25, 0.25, 0.0], vec![1.0 / 6.0, 1.0 / 6.0, 2.0 / 3.0]),
            Scheme::Rk4 => {
                (4, vec![0.0, 0.0, 0.0, 0.0, 0.5, 0.0, 0.0, 0.0, 0.0, 0.5, 0.0, 0.0, 0.0, 0.0, 1.0, 0.0], vec![1.0 / 6.0, 1.0 / 3.0, 1.0 / 3.0, 1.0 / 6.0])
            }
            Scheme::BackwardEuler => (1, vec![1.0], vec![1.0]),
            // One stage from the base point (4·u_n − u_{n−1})/3.
            Scheme::Bdf2 => (1, vec![2.0 / 3.0], vec![2.0 / 3.0]),
            Scheme::CrankNicolson => (2, vec![0.0, 0.0, 0.5, 0.5], vec![0.5, 0.5]),
            Scheme::Sdirk2 => {
                let g = 1.0 - std::f64::consts::FRAC_1_SQRT_2;
                (2, vec![g, 0.0, 1.0 - g, g], vec![1.0 - g, g])
            }
            Scheme::Sdirk3 => {
                // The root of 6γ³ − 18γ² + 9γ − 1 = 0 in (1/6, 1/2).
                let g = 0.435_866_521_508_459;
                let tau = (1.0 + g) / 2.0;
                let b1 = -(6.0 * g * g - 16.0 * g + 1.0) / 4.0;
                let b2 = (6.0 * g * g - 20.0 * g + 5.0) / 4.0;
                (3, vec![g, 0.0, 0.0, tau - g, g, 0.0, b1, b2, g], vec![b1, b2, g])
            }
        }
    }
}

/// Settings of an [`Integrator`].
#[derive(Clone, Copy, Debug, PartialEq, serde::Serialize, serde::Deserialize)]
pub struct IntegratorParams {
    /// The scheme.
    pub scheme: Scheme,
    /// The time step.
    pub dt: f64,
    /// The implicit stages' Newton solves (unused by explicit schemes).
    pub newton: NewtonParams,
}

impl IntegratorParams {
    /// `scheme` with step `dt`, Newton's default settings.
    pub fn new(scheme: Scheme, dt: f64) -> Self {
        IntegratorParams { scheme, dt, newton: NewtonParams::default() }
    }
}

/// One step `(u_n, p) ↦ u_{n+1}` of a scheme for a user's system `S`
/// ([`ode_system!`](crate::ode_system)); derivatives of the discrete step
/// (module docs). A stage whose Newton solve fails leaves the output NaN
/// and its error in [`Forward::take_error`].
#[derive(Debug)]
pub struct Integrator<S> {
    /// The user's system.
    pub system: S,
    /// The scheme, step and Newton settings.
    pub params: IntegratorParams,
    /// Newton's work so far.
    pub info: NewtonInfo,
    stages: usize,
    a: Vec<f64>,
    b: Vec<f64>,
    /// Time levels in the input and the output (BDF2's state holds two).
    levels_in: usize,
    levels_out: usize,
    error: Mutex<Option<OpError>>,
    /// A step's vectors, kept between calls.
    work: Mutex<StepWork>,
    /// Stage values of recent forward steps, for their VJPs.
    cache: Mutex<StageCache>,
}

/// The stage values of recent forward steps of an implicit scheme, kept
/// for their VJPs: a rollout's backward pass reverses the steps its
/// forward pass took, and a step found here (the same `x` and `p`, bit for
/// bit) is not solved again. At most [`STAGE_CACHE_VALUES`] values; when
/// full it starts again empty, so memory stays bounded whatever the
/// checkpointing (a step not found is solved again, as without it).
#[derive(Debug, Default)]
struct StageCache {
    /// By a hash of `(x, p)`: `x`, `p`, the stage values, the slopes.
    entries: std::collections::HashMap<u64, Vec<f64>>,
    values: usize,
}

/// The stage cache's capacity in values (8 MB).
const STAGE_CACHE_VALUES: usize = 1 << 20;

/// A hash of the bits of `x` and `p`.
fn stage_key(x: &[f64], p: &[f64]) -> u64 {
    x.iter().chain(p).fold(0xcbf2_9ce4_8422_2325u64, |h, v| (h ^ v.to_bits()).wrapping_mul(0x0000_0100_0000_01b3).rotate_left(29))
}

/// A step's vectors, kept between calls so that a step allocates nothing
/// (a busy set, on another thread, is passed by for a fresh one).
#[derive(Debug, Default)]
struct StepWork {
    st: Stages,
    z: Vec<f64>,
    base: Vec<f64>,
    /// The stages' Jacobian, when they are solved directly.
    held: Option<HeldJacobian>,
    /// The reverse sweep's vectors.
    kbar: Vec<f64>,
    dbase: Vec<f64>,
    omega: Vec<f64>,
    zbar: Vec<f64>,
    zero: Vec<f64>,
}

impl<S: OdeSystem> Integrator<S> {
    /// A step of `params.scheme` for `system`.
    ///
    /// # Panics
    /// If the time step is not a positive finite number, or a Newton
    /// setting is out of range (named).
    #[track_caller]
    pub fn new(system: S, params: IntegratorParams) -> Self {
        if !(params.dt.is_finite() && params.dt > 0.0) {
            panic!("Integrator: the time step must be a positive number, got {}", params.dt);
        }
        if let Some(e) = params.newton.invalid() {
            panic!("Integrator: {e}");
        }
        let (stages, a, b) = params.scheme.tableau();
        let levels = params.scheme.levels();
        Integrator {
            system,
            params,
            info: NewtonInfo::default(),
            stages,
            a,
            b,
            levels_in: levels,
            levels_out: levels,
            error: Mutex::new(None),
            work: Mutex::new(StepWork::default()),
            cache: Mutex::new(StageCache::default()),
        }
    }

    /// The start of a [`Scheme::Bdf2`] rollout, `(u_0, p) ↦ [u_1, u_0]`
    /// with `u_1` one SDIRK2 step (order 2, L-stable) of `params.dt`: apply
    /// it to the initial state, roll out the BDF2 step from its output, and
    /// pass the rollout's gradient with respect to its initial state through
    /// this operator's VJP to get the gradient with respect to `u_0` (and
    /// the start's share of `p`'s).
    ///
    /// # Panics
    /// As [`Integrator::new`], and if `params.scheme` is not BDF2.
    #[track_caller]
    pub fn bdf2_start(system: S, params: IntegratorParams) -> Self {
        if params.scheme != Scheme::Bdf2 {
            panic!("Integrator::bdf2_start: the scheme is {:?}, not Bdf2", params.scheme);
        }
        let mut start = Integrator::new(system, IntegratorParams { scheme: Scheme::Sdirk2, ..params });
        start.params.scheme = Scheme::Bdf2;
        (start.levels_in, start.levels_out) = (1, 2);
        start
    }

    /// The last stage is the step's output (`b` is `A`'s last row).
    fn stiffly_accurate(&self) -> bool {
        let s = self.stages;
        self.a[(s - 1) * s..] == self.b[..]
    }
}

/// An implicit stage's equation `G(Y) = Y − z − h·γ·f(Y, p)`.
struct Stage<'a, S> {
    system: &'a S,
    p: &'a [f64],
    z: &'a [f64],
    hg: f64,
}

impl<S: RhsFunctions> Equations for Stage<'_, S> {
    fn residual(&self, y: &[f64], r: &mut [f64]) {
        self.system.f(y, self.p, r);
        for ((r, y), z) in r.iter_mut().zip(y).zip(self.z) {
            *r = y - z - self.hg * *r;
        }
    }
    /// `I − h·γ·∂f/∂u` from the user's Jacobian, when there is one.
    fn jacobian_matrix(&self, y: &[f64], m: &mut [f64]) -> bool {
        if !self.system.jacobian(y, self.p, m) {
            return false;
        }
        let n = y.len();
        for (k, v) in m.iter_mut().enumerate() {
            *v = if k % (n + 1) == 0 { 1.0 } else { 0.0 } - self.hg * *v;
        }
        true
    }
    fn jacobian_product(&self, y: &[f64], v: &[f64], out: &mut [f64]) {
        // f itself is not needed: into the thread's scratch (a direct
        // solve calls this n times per Newton iteration).
        crate::op::with_scratch(y.len(), |f| self.system.f_jvp_u(y, self.p, v, f, out));
        for (o, v) in out.iter_mut().zip(v) {
            *o = v - self.hg * *o;
        }
    }
    fn jacobian_transpose_product(&self, y: &[f64], w: &[f64], out: &mut [f64]) {
        let (mut seed, mut dp) = (w.to_vec(), vec![0.0; self.p.len()]);
        out.fill(0.0);
        self.system.f_vjp(y, self.p, &mut seed, out, &mut dp);
        for (o, w) in out.iter_mut().zip(w) {
            *o = w - self.hg * *o;
        }
    }
}

impl StepWork {
    /// Makes `held` the stages' Jacobian for `n` unknowns solved by
    /// `params` (none when they are not solved directly).
    fn hold_jacobian(&mut self, n: usize, params: &NewtonParams) {
        if self.held.as_ref().is_none_or(|held| held.n() != n) {
            self.held = HeldJacobian::for_params(n, params);
        }
    }
}

/// A step's stage values `Y_i` and slopes `k_i`, each `stages·n` long.
#[derive(Debug, Default)]
struct Stages {
    y: Vec<f64>,
    k: Vec<f64>,
}

impl<S: RhsFunctions> Integrator<S> {
    /// Runs `f` with the kept step vectors (a fresh set when they are busy).
    fn with_work<R>(&self, f: impl FnOnce(&mut StepWork) -> R) -> R {
        match self.work.try_lock() {
            Ok(mut w) => f(&mut w),
            Err(_) => f(&mut StepWork::default()),
        }
    }

    /// Computes the stages at `(x, p)` into `w.st`; `last` is the output
    /// when the scheme is stiffly accurate and it is known (a rollout's
    /// next state).
    fn stages(&self, x: &[f64], p: &[f64], last: Option<&[f64]>, w: &mut StepWork) -> Result<(), OpError> {
        let (n, s, h) = (self.system.n(), self.stages, self.params.dt);
        w.st.y.resize(s * n, 0.0);
        w.st.k.resize(s * n, 0.0);
        w.z.resize(n, 0.0);
        w.base.resize(n, 0.0);
        w.hold_jacobian(n, &self.params.newton);
        let StepWork { st, z, base, held, .. } = w;
        self.base(x, base);
        // One Jacobian for the step's implicit stages (they share h·γ in
        // every scheme here), formed at the first stage's start and formed
        // again only where Newton's steps stop contracting; nothing held
        // from an earlier step, so a step's result depends on its inputs
        // alone.
        if let Some(held) = held.as_mut() {
            held.invalidate();
        }
        let mut held_hg = f64::NAN;
        for i in 0..s {
            z.copy_from_slice(base);
            for j in 0..i {
                let a = h * self.a[i * s + j];
                if a != 0.0 {
                    for (z, k) in z.iter_mut().zip(&st.k[j * n..(j + 1) * n]) {
                        *z += a * k;
                    }
                }
            }
            let gamma = self.a[i * s + i];
            let y = &mut st.y[i * n..(i + 1) * n];
            match last {
                Some(given) if i == s - 1 && gamma != 0.0 => y.copy_from_slice(&given[..n]),
                _ => {
                    y.copy_from_slice(z);
                    if gamma != 0.0 {
                        let stage = Stage { system: &self.system, p, z, hg: h * gamma };
                        match held.as_mut() {
                            Some(held) => {
                                if held_hg != h * gamma {
                                    held.invalidate();
                                    held_hg = h * gamma;
                                }
                                newton_held(&stage, &self.params.newton, &self.info, held, y)?
                            }
                            None => newton(&stage, &self.params.newton, &self.info, y)?,
                        }
                    }
                }
            }
            self.system.f(&st.y[i * n..(i + 1) * n], p, &mut st.k[i * n..(i + 1) * n]);
        }
        Ok(())
    }

    /// The point the stages start from: `u_n`, or BDF2's `(4·u_n − u_{n−1})/3`.
    fn base(&self, x: &[f64], base: &mut [f64]) {
        let n = base.len();
        if self.levels_in == 2 {
            for (i, b) in base.iter_mut().enumerate() {
                *b = (4.0 * x[i] - x[n + i]) / 3.0;
            }
        } else {
            base.copy_from_slice(x);
        }
    }

    /// `y = base(x) + h·Σ b_i·k_i` (BDF2: and `u_n` as the older level).
    /// Linear in `x` and `k`, so the JVP's tangents combine the same way.
    fn combine(&self, x: &[f64], k: &[f64], y: &mut [f64]) {
        let (n, h) = (self.system.n(), self.params.dt);
        self.base(x, &mut y[..n]);
        for (i, b) in self.b.iter().enumerate() {
            for (y, k) in y[..n].iter_mut().zip(&k[i * n..(i + 1) * n]) {
                *y += h * b * k;
            }
        }
        if self.levels_out == 2 {
            y[n..].copy_from_slice(&x[..n]);
        }
    }

    /// The reverse sweep through the stages in `w.st` (module docs).
    fn vjp_stages(&self, p: &[f64], w: &mut StepWork, dy: &mut [f64], dx: &mut [f64], dp: &mut [f64]) {
        let (n, s, h) = (self.system.n(), self.stages, self.params.dt);
        let StepWork { st, held, kbar, dbase, omega, zbar, zero, .. } = w;
        kbar.resize(s * n, 0.0);
        for (i, b) in self.b.iter().enumerate() {
            for (kb, d) in kbar[i * n..(i + 1) * n].iter_mut().zip(dy.iter()) {
                *kb = h * b * d;
            }
        }
        // The adjoint of the base point.
        dbase.clear();
        dbase.extend_from_slice(&dy[..n]);
        omega.resize(n, 0.0);
        zbar.resize(n, 0.0);
        // z_i only sets a stage equation's constant, not its Jacobian.
        zero.clear();
        zero.resize(n, 0.0);
        for i in (0..s).rev() {
            let gamma = self.a[i * s + i];
            let yi = &st.y[i * n..(i + 1) * n];
            let kb = &kbar[i * n..(i + 1) * n];
            if gamma == 0.0 {
                omega.copy_from_slice(kb);
            } else {
                let stage = Stage { system: &self.system, p, z: zero, hg: h * gamma };
                // The exact Jacobian at the stage: held factors when the
                // stages are solved directly, else the linear method.
                let solved = match held.as_mut() {
                    Some(held) => {
                        self.info.adjoint_solves.fetch_add(1, std::sync::atomic::Ordering::Relaxed);
                        held.solve_at(&stage, yi, kb, omega, true)
                    }
                    None => jacobian_solve(&stage, &self.params.newton, &self.info, yi, kb, omega, true),
                };
                if let Err(e) = solved {
                    fail(&self.error, omega, e);
                }
            }
            zbar.fill(0.0);
            self.system.f_vjp(yi, p, omega, zbar, dp);
            for (d, zb) in dbase.iter_mut().zip(zbar.iter()) {
                *d += zb;
            }
            for j in 0..i {
                let a = h * self.a[i * s + j];
                if a != 0.0 {
                    for (kb, zb) in kbar[j * n..(j + 1) * n].iter_mut().zip(zbar.iter()) {
                        *kb += a * zb;
                    }
                }
            }
        }
        if self.levels_in == 2 {
            for i in 0..n {
                dx[i] += 4.0 / 3.0 * dbase[i];
                dx[n + i] -= dbase[i] / 3.0;
            }
        } else {
            for (dx, d) in dx.iter_mut().zip(dbase.iter()) {
                *dx += d;
            }
        }
        if self.levels_out == 2 {
            for i in 0..n {
                dx[i] += dy[n + i];
            }
        }
        dy.fill(0.0);
    }
}

impl<S: OdeSystem> Operator for Integrator<S> {
    fn n_in(&self) -> usize {
        self.system.n() * self.levels_in
    }
    fn n_out(&self) -> usize {
        self.system.n() * self.levels_out
    }
    fn n_params(&self) -> usize {
        self.system.n_params()
    }
}

impl<S: RhsFunctions> Forward for Integrator<S> {
    #[track_caller]
    fn forward(&self, x: &[f64], p: &[f64], y: &mut [f64]) {
        validate_forward(self, "Integrator", x, p, y);
        self.with_work(|w| match self.stages(x, p, None, w) {
            Ok(()) => {
                self.combine(x, &w.st.k, y);
                self.keep_stages(x, p, &w.st);
            }
            Err(e) => fail(&self.error, y, e),
        })
    }

    /// The Newton tolerance of an implicit scheme; 0 for an explicit one.
    fn solve_tolerance(&self) -> f64 {
        if self.params.scheme.is_implicit() { self.params.newton.solve_tolerance() } else { 0.0 }
    }

    fn take_error(&self) -> Option<OpError> {
        take(&self.error)
    }
}

impl<S: RhsFunctions> Integrator<S> {
    /// Keeps an implicit step's stages for its VJP ([`StageCache`]).
    fn keep_stages(&self, x: &[f64], p: &[f64], st: &Stages) {
        if !self.params.scheme.is_implicit() {
            return;
        }
        let Ok(mut cache) = self.cache.try_lock() else { return };
        let len = x.len() + p.len() + st.y.len() + st.k.len();
        if cache.values + len > STAGE_CACHE_VALUES {
            cache.entries.clear();
            cache.values = 0;
        }
        let entry: Vec<f64> = x.iter().chain(p).chain(&st.y).chain(&st.k).copied().collect();
        if let Some(old) = cache.entries.insert(stage_key(x, p), entry) {
            cache.values -= old.len();
        }
        cache.values += len;
    }

    /// The stages a forward step at `(x, p)` kept, into `st` (and out of
    /// the cache); `false` when there are none.
    fn kept_stages(&self, x: &[f64], p: &[f64], st: &mut Stages) -> bool {
        if !self.params.scheme.is_implicit() {
            return false;
        }
        let Ok(mut cache) = self.cache.try_lock() else { return false };
        let Some(entry) = cache.entries.remove(&stage_key(x, p)) else { return false };
        cache.values -= entry.len();
        let (kx, rest) = entry.split_at(x.len());
        let (kp, rest) = rest.split_at(p.len());
        if !(same_bits(kx, x) && same_bits(kp, p)) {
            return false;
        }
        let (y, k) = rest.split_at(rest.len() / 2);
        st.y.clear();
        st.y.extend_from_slice(y);
        st.k.clear();
        st.k.extend_from_slice(k);
        true
    }

    fn vjp_at(&self, x: &[f64], p: &[f64], given: Option<&[f64]>, dy: &mut [f64], dx: &mut [f64], dp: &mut [f64]) {
        self.with_work(|w| {
            w.hold_jacobian(self.system.n(), &self.params.newton);
            if self.kept_stages(x, p, &mut w.st) {
                self.vjp_stages(p, w, dy, dx, dp);
                return;
            }
            self.vjp_solved(x, p, given, w, dy, dx, dp)
        })
    }

    /// The VJP with the stages solved again.
    #[allow(clippy::too_many_arguments)]
    fn vjp_solved(&self, x: &[f64], p: &[f64], given: Option<&[f64]>, w: &mut StepWork, dy: &mut [f64], dx: &mut [f64], dp: &mut [f64]) {
        match self.stages(x, p, given.filter(|_| self.stiffly_accurate()), w) {
            Ok(()) => self.vjp_stages(p, w, dy, dx, dp),
            Err(e) => {
                keep(&self.error, e);
                dx.fill(f64::NAN);
                dp.fill(f64::NAN);
                dy.fill(0.0);
            }
        }
    }
}

impl<S: RhsFunctions> Vjp for Integrator<S> {
    #[track_caller]
    fn vjp(&self, x: &[f64], p: &[f64], dy: &mut [f64], dx: &mut [f64], dp: &mut [f64]) {
        validate_vjp(self, "Integrator", x, p, dy, dx, dp);
        self.vjp_at(x, p, None, dy, dx, dp);
    }

    /// A stiffly accurate scheme's last stage is the given output: it is not
    /// solved again.
    #[track_caller]
    fn vjp_overwrite_given(&self, x: &[f64], p: &[f64], y: &[f64], dy: &mut [f64], dx: &mut [f64], dp: &mut [f64]) {
        validate_vjp(self, "Integrator", x, p, dy, dx, dp);
        check_given("Integrator", y, self.n_out());
        dx.fill(0.0);
        self.vjp_at(x, p, Some(y), dy, dx, dp);
    }
}

impl<S: RhsFunctions> Jvp for Integrator<S> {
    #[track_caller]
    fn jvp(&self, x: &[f64], p: &[f64], tx: &[f64], tp: &[f64], y: &mut [f64], ty: &mut [f64]) {
        validate_jvp(self, "Integrator", x, p, tx, tp, y, ty);
        let (n, s, h) = (self.system.n(), self.stages, self.params.dt);
        // The JVP keeps its own stages (it is not on a rollout's hot path).
        let mut w = StepWork::default();
        if let Err(e) = self.stages(x, p, None, &mut w) {
            fail(&self.error, y, e);
            ty.fill(f64::NAN);
            return;
        }
        let st = &w.st;
        self.combine(x, &st.k, y);
        // k̇_i: (I − h·γ·∂f/∂u)·k̇_i = (∂f/∂u)·ż_i + (∂f/∂p)·ṗ, ż_i = ẋ + h·Σ a_ij·k̇_j.
        let mut tk = vec![0.0; s * n];
        let (mut tz, mut q, mut f, mut tbase) = (vec![0.0; n], vec![0.0; n], vec![0.0; n], vec![0.0; n]);
        self.base(tx, &mut tbase);
        for i in 0..s {
            tz.copy_from_slice(&tbase);
            for j in 0..i {
                let a = h * self.a[i * s + j];
                if a != 0.0 {
                    for (t, k) in tz.iter_mut().zip(&tk[j * n..(j + 1) * n]) {
                        *t += a * k;
                    }
                }
            }
            let yi = &st.y[i * n..(i + 1) * n];
            self.system.f_jvp(yi, p, &tz, tp, &mut f, &mut q);
            let gamma = self.a[i * s + i];
            let out = &mut tk[i * n..(i + 1) * n];
            if gamma == 0.0 {
                out.copy_from_slice(&q);
            } else {
                let stage = Stage { system: &self.system, p, z: &tz, hg: h * gamma };
                if let Err(e) = jacobian_solve(&stage, &self.params.newton, &self.info, yi, &q, out, false) {
                    fail(&self.error, out, e);
                }
            }
        }
        self.combine(tx, &tk, ty);
    }
}
