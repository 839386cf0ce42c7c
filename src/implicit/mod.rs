//! Implicit steps as ordinary Rust: the user writes only the forward
//! physics, diffsim solves it and differentiates the solution by the
//! implicit rule, never through the iterations.
//!
//! Four building blocks, each a plain function declared by a macro that
//! has Enzyme generate the derivatives the rule needs:
//!
//! | block | the user writes | declared by | operator |
//! |---|---|---|---|
//! | linear solve `A(p)·y = b(x, p)` | `A(p)·v` and `b(x, p)` | [`linear_system!`](crate::linear_system) | [`LinearSolve`] (CG, BiCGStab, direct) |
//! | nonlinear solve `F(y, x, p) = 0` | `F` | [`nonlinear_system!`](crate::nonlinear_system) | [`NonlinearSolve`] (Newton, line search) |
//! | steady state `y = G(y, x, p)` | `G` | [`fixed_point_system!`](crate::fixed_point_system) | [`FixedPoint`] (relaxed iteration) |
//! | time step of `du/dt = f(u, p)` | `f` | [`ode_system!`](crate::ode_system) | [`Integrator`] (RK4, SSP-RK3, backward Euler, Crank–Nicolson, SDIRK2/3, BDF2) |
//!
//! Each is an [`Operator`](crate::op::Operator) with forward, VJP and JVP,
//! so rollouts, checkpointing, training and the checks take it like any
//! other; each declares its solver tolerance
//! ([`Forward::solve_tolerance`](crate::op::Forward::solve_tolerance)) so
//! the checks judge at that level; each hands a solve that fails to
//! [`Forward::take_error`](crate::op::Forward::take_error) (the output
//! NaN), so a rollout stops with the error. Through a rollout the VJP
//! receives the step's output (`Vjp::vjp_overwrite_given`), so the
//! solution is not computed again. docs/implicit.md shows them at work and
//! measured.

mod fixed_point;
mod linear;
mod newton;
mod ode;

pub use fixed_point::{FixedPoint, FixedPointInfo, FixedPointParams, FixedPointSystem, MapFunctions};
pub use linear::{LinearSolve, LinearSystem, SolveInfo, SolveMethod, SolveParams, Start, SystemCoefficients, SystemFunctions, SystemProducts};
pub use newton::{NewtonInfo, NewtonParams, NonlinearSolve, NonlinearSystem, ResidualFunctions};
pub use ode::{Integrator, IntegratorParams, OdeSystem, RhsFunctions, Scheme};
