//! What a solver author writes with, in one import:
//! `use diffsim::prelude::*;`.
//!
//! The operator core and its macros, the implicit building blocks, the
//! checks, rollouts and the training layer's everyday names. Everything else
//! stays in its module (`diffsim::nn`, `diffsim::scene`, ...).

pub use crate::check::{CheckParams, check_all};
pub use crate::implicit::{
    FixedPoint, FixedPointParams, FixedPointSystem, Integrator, IntegratorParams, LinearSolve, LinearSystem, NewtonParams, NonlinearSolve, NonlinearSystem,
    OdeSystem, Scheme, SolveMethod, SolveParams,
};
pub use crate::op::{Forward, Jvp, OpError, Operator, OperatorExt, Vjp};
pub use crate::rollout::{AtSteps, Checkpointing, Loss, Rollout, RolloutError, RolloutLoss, Wrt};
pub use crate::train::{Adam, AdamParams, FnObjective, Lbfgs, LbfgsParams, Objective, Trainer, TrainerParams, UpdateRule};
pub use crate::{differentiable, fixed_point_system, linear_system, nonlinear_system, ode_system, stencil3};
