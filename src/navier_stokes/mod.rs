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

/// The sub-steps of a forward call, or `None` when the call is refused:
/// then the input is copied to the output and the error kept for
/// [`crate::op::Forward::take_error`] (the steps' shared refusal).
fn substeps_or_refuse(
    substeps: Result<usize, crate::op::OpError>,
    x: &[f64],
    y: &mut [f64],
    error: &std::cell::Cell<Option<crate::op::OpError>>,
) -> Option<usize> {
    match substeps {
        Ok(k) => Some(k),
        Err(e) => {
            y.copy_from_slice(x);
            error.set(Some(e));
            None
        }
    }
}

/// The VJP of a refused call (the identity): `dy` moved into `dx`.
fn refused_vjp(dy: &mut [f64], dx: &mut [f64]) {
    for (d, g) in dx.iter_mut().zip(dy.iter_mut()) {
        *d += std::mem::take(g);
    }
}

/// The JVP of a refused call (the identity).
fn refused_jvp(x: &[f64], tx: &[f64], y: &mut [f64], ty: &mut [f64]) {
    y.copy_from_slice(x);
    ty.copy_from_slice(tx);
}
