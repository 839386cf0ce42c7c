//! Incompressible Navier–Stokes as operators with their gradients, in 2D
//! and 3D from one code (docs/navier-stokes.md). The state is the packed
//! MAC velocity `[u, v(, w)]` of a [`diffsim_solvers::smoke::MacGrid`]
//! (each component on its own faces), the parameters start with `[ν, dt]`.
//!
//! - [`NavierStokes`]: any box — periodic, free-slip (closed), no-slip,
//!   inflow and outflow sides, obstacles — with explicit or implicit
//!   viscosity, the projection by conjugate gradients (by FFT when every
//!   side is periodic), an inflow profile and a body force as parameters;
//!   the force on its obstacles along x carried in the state
//!   ([`SurfaceDrag`], Mosaic's surface sums, its gradient included).
//! - [`PeriodicNavierStokes`]: that operator on the box periodic on every
//!   axis of a [`diffsim_solvers::mac::periodic::Periodic`], with values on
//!   the cell centres as well ([`Centred`]).
//! - [`CentralNavierStokes`]: the periodic box by central differences and
//!   a three-stage Runge–Kutta step: a smooth map, stable at any horizon
//!   without a limiter.
//!
//! Both split a requested `dt` into `k` equal sub-steps chosen at the start
//! of the call (the viscous number and the Courant number within their
//! limits, [`diffsim_solvers::mac::periodic::Periodic::substeps`]), so that
//! `dt` is a sampling interval and never a crash, and a call is one
//! function of its input whose gradient is that function's. The explicit
//! parts get their derivatives from Enzyme; the solves (the projection,
//! implicit viscosity) from the implicit rule.

mod central;
mod drag;
mod periodic;
mod step;

pub use central::*;
pub use drag::SurfaceDrag;
pub use periodic::*;
pub use step::*;

/// More sub-steps than this in one call is refused (recorded as
/// [`crate::op::OpError::Unstable`], the velocity left as it was): the
/// velocity has blown up or `dt` is far beyond the flow's time scale.
pub const MAX_SUBSTEPS: usize = 4096;
