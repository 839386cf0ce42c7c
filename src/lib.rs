//! # diffsim: differentiable physics in Rust
//!
//! A guide in six steps, from a plain solver function to a checked
//! gradient through a rollout, training through it, and what accuracy
//! costs.
//!
//! **1. A solver step is a plain function on slices.** It reads a state `x`
//! and parameters `p` and overwrites its output `y`; it knows nothing of
//! differentiation. The shipped solvers live in the `diffsim-solvers` crate
//! (built without the autodiff flag), e.g. [`diffsim_solvers::burgers::step`].
//!
//! **2. An operator gives it sizes and derivatives** ([`op`]): implement
//! [`op::Operator`] for a plain-data type and let
//! [`differentiable!`] generate [`op::Forward`], [`op::Vjp`] and
//! [`op::Jvp`] with Enzyme (or [`stencil3!`] for an explicit three-point
//! stencil written as a cell function or a pointwise map: faster; a function
//! that needs working memory takes it lent, `scratch = len`), or write
//! them by hand, or
//! take finite differences with [`op::FiniteDiff`]. Linear solves are
//! operators too: their VJP is the solve with the transposed matrix
//! ([`problems::smoke::SmokeStep`], [`fluids::DiffuseImplicit`]); a
//! user's own implicit step is its matrix-vector product and right-hand
//! side as plain functions, [`linear_system!`] and
//! [`implicit::LinearSolve`], whose derivatives follow by the implicit rule;
//! likewise a residual for Newton's method ([`nonlinear_system!`],
//! [`implicit::NonlinearSolve`]) and a right-hand side `f(u, p)` for the
//! time integrators, explicit and stiff ([`ode_system!`],
//! [`implicit::Integrator`]). `use diffsim::prelude::*` brings the names a
//! solver author writes with.
//! All three obey one contract: a VJP
//! *adds* `J_xᵀ·dy` into `dx` and consumes its seed.
//!
//! ```ignore
//! #![feature(autodiff)]
//! use diffsim::op::{Operator, OperatorExt};
//!
//! struct Square { n: usize }
//! impl Operator for Square {
//!     fn n_in(&self) -> usize { self.n }
//!     fn n_out(&self) -> usize { self.n }
//! }
//! fn square(op: &Square, x: &[f64], _p: &[f64], y: &mut [f64]) {
//!     for i in 0..op.n { y[i] = x[i] * x[i]; }
//! }
//! diffsim::differentiable!(Square => square);
//!
//! let (dx, _) = Square { n: 2 }.vjp_new(&[1.0, 3.0], &[], &[1.0, 1.0]);
//! assert_eq!(dx, vec![2.0, 6.0]);
//! ```
//!
//! (Marked `ignore`: doctests are built without fat LTO, which Enzyme
//! needs; the same code runs in `tests/user_op.rs`.)
//!
//! **3. Check the gradient** ([`check`]): `check::check_all(&op, &x, &p,
//! &Default::default())` runs finite differences over a sweep of steps, the
//! Taylor remainder test and the JVP/VJP dot-product test, and says where a
//! kink makes a check inconclusive.
//!
//! **4. Roll it out** ([`rollout`]): chain `T` steps and a loss, and get the
//! loss and its gradient by per-step VJPs over stored or checkpointed
//! states (`Store`, `Periodic`, `Binomial`), and check it through every
//! step: [`rollout::RolloutLoss`] is the map `(x_0, p) ↦ L` as an operator
//! (with respect to `x_0`, `p` or both), so [`check::check_all`] applies to
//! it; [`rollout::Repeat`] is the map `(x_0, p) ↦ x_T` of a step repeated
//! with the same parameters, its checkpointing chosen by the memory
//! budget. [`problems::burgers::P1`] and
//! [`problems::smoke::P2`] are the benchmarks built exactly this way;
//! [`fluids`] holds further operators, each for 2D and 3D (diffusion,
//! advection schemes, forces, inflow), and [`navier_stokes`] the
//! incompressible Navier–Stokes step on any box (walls, inflow, obstacles
//! and the drag on them), with a smooth central scheme for periodic ones.
//!
//! **5. Train through it** ([`nn`], [`train`]): a network is an operator
//! too (its weights are the parameters), so [`train::Coupled`] joins a
//! solver step and a network (correction, scaling, or solver parameters),
//! the rollout chains both VJPs, [`train::batch_gradient`] averages a
//! mini-batch in parallel (solvers with work buffers once per thread:
//! [`op::PerThread`]) and [`train::Optimizer`] (Adam, SGD) updates the
//! weights. The solver-in-the-loop study (`diffsim_studies::sol`, on
//! Burgers and on 2D flow past a disc) is built from these parts. Beyond
//! plain gradients: half-inverse gradients ([`train::hig`]) and
//! scale-invariant physics updates ([`train::pg`]), which use an
//! operator's [`op::LocalInverse`] (exact, regularised, a reverse-time
//! simulation as for the smoke step, or a Gauss-Newton step with
//! [`op::GaussNewton`]; sharpened by [`op::Refined`], its promise measured
//! by [`check::local_inverse`]) to give the network its target (the
//! studies `diffsim_studies::heat` and `diffsim_studies::smoke`).
//!
//! **Precision.** Operators, rollouts and training run in `f64` by default
//! and in `f32` where an operator implements `Forward<f32>` (networks, the
//! Burgers step; see [`op::Real`]); [`op::Float32`] runs an `f32` network
//! inside an `f64` rollout (mixed precision); benchmark P3
//! (`diffsim_studies::p3`) times all three.
//!
//! **6. Know what accuracy costs** (`diffsim_studies::accuracy`): the schemes against exact
//! solutions (Cole–Hopf Burgers, Taylor–Green, heat modes, translation),
//! observed orders of convergence, error versus time and memory with the
//! Pareto front (`diffsim pareto`), and the hard cases that must stay
//! stable (`diffsim stability`). Rollouts check the final state and, every
//! few steps, the adjoint, and on a NaN replay to report the pass, the
//! exact step and the operator.
//!
//! **Nothing lost.** Training writes atomic checkpoints and resumes bit for
//! bit ([`train::checkpoint`]); input files are read only when they are
//! regular files under a size limit ([`files`]); what a run will allocate
//! is estimated against a memory budget before it starts ([`memory`]), and
//! a gradient's checkpointing is chosen to fit it ([`rollout::plan`]);
//! parser messages reach users in plain words ([`words`]); every reader of
//! user input is fuzzed, and the inputs the fuzzer kept are replayed by the
//! suite (`diffsim_cli::fuzz`).
//!
//! **The workspace.** This crate is the library; the studies built on it
//! (solver-in-the-loop, SIP, HIG, accuracy) are `diffsim-studies`, the
//! command line `diffsim-cli`, the program `diffsim-bin`
//! (docs/architecture.md). A crate of one's own depends on this one alone:
//! the plain solvers are here as [`solvers`] (CG and its `System` trait,
//! BiCGStab, the grids, the fluid and flow solvers, the network kernels).
//!
//! **Your own crate.** `diffsim new PATH` writes one that builds and passes
//! out of the box (a solver, its checks, a rollout, the checks through it, a
//! fit); `docs/own-solver.md` walks through it and `docs/pitfalls.md` lists
//! the Enzyme failures known here. Everything that links generated
//! gradients is built in release with fat LTO, and `-Zautodiff=Enable` goes
//! only to the crates that declare differentiated functions and to the
//! final binaries.
#![feature(autodiff)]
#![deny(missing_docs)]

pub mod check;
pub mod distributed;
pub mod files;
pub mod fluids;
pub mod implicit;
pub mod memory;
pub mod navier_stokes;
pub mod nn;
pub mod op;
pub mod prelude;
pub mod problems;
pub mod rollout;
pub mod scene;
pub mod train;
pub mod volume;
pub mod words;

/// The plain forward solvers diffsim is built on (the `diffsim-solvers`
/// crate, compiled without the autodiff flag): what a solver author reuses,
/// so that a crate of one's own depends on `diffsim` alone.
pub use diffsim_solvers as solvers;
