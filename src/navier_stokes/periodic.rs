//! [`PeriodicNavierStokes`]: the Navier–Stokes step of a box periodic on
//! every axis given by its solver's settings ([`Periodic`]: cells, cell
//! size, scheme), in 2D and 3D. It is [`NavierStokes`] on that box — the
//! same advection, explicit viscosity and sub-steps, the projection by FFT
//! (a linear map that is its own adjoint) — with the state also on the
//! cell centres ([`Centred`]: a spectral half-cell shift each way).
//! `x` the packed velocity `[u, v(, w)]` (each face array with its
//! periodic copies), `p = [ν, dt]`, or `[ν, dt, f…]` under a body force.

use diffsim_solvers::mac::periodic::Periodic;

use super::NavierStokes;
use crate::op::{Forward, Jvp, OpError, Operator, Vjp, validate_forward, validate_jvp, validate_vjp};

/// One step of incompressible Navier–Stokes on a periodic box: `x` the
/// packed velocity, `p = [ν, dt]` (the box's own `viscosity` is not used:
/// the parameter is). The step of [`NavierStokes`] on the box of `flow`
/// (its refusals and errors too: `ν` or `dt` negative or not finite, a
/// velocity not finite or needing more than [`super::MAX_SUBSTEPS`]
/// sub-steps).
#[derive(Debug)]
pub struct PeriodicNavierStokes<const D: usize> {
    flow: Periodic<D>,
    step: NavierStokes<D>,
}

impl<const D: usize> PeriodicNavierStokes<D> {
    /// The step of the box `flow` (its cells, cell size and scheme).
    ///
    /// # Panics
    /// If an axis has fewer than 2 cells or the cell size is not positive
    /// and finite.
    pub fn new(flow: Periodic<D>) -> Self {
        let step = NavierStokes::new(flow.grid, flow.h, flow.scheme).unwrap_or_else(|e| panic!("{e}"));
        Self { flow, step }
    }

    /// The step under a body force: `p = [ν, dt, f…]`, `f` one value per
    /// face in the packed velocity's layout (the copies' values unused:
    /// the step refreshes them), added over each sub-step after the
    /// viscosity; the gradient reaches `f` too.
    pub fn forced(flow: Periodic<D>) -> Self {
        let Self { flow, step } = Self::new(flow);
        Self { flow, step: step.forced() }
    }

    /// The box.
    pub fn flow(&self) -> &Periodic<D> {
        &self.flow
    }

    /// The step on the box, as an operator of any box.
    pub fn step(&self) -> &NavierStokes<D> {
        &self.step
    }
}

impl<const D: usize> Operator for PeriodicNavierStokes<D> {
    fn n_in(&self) -> usize {
        self.step.n_in()
    }
    fn n_out(&self) -> usize {
        self.step.n_out()
    }
    fn n_params(&self) -> usize {
        self.step.n_params()
    }
}

impl<const D: usize> Forward for PeriodicNavierStokes<D>
where
    NavierStokes<D>: Forward,
{
    fn forward(&self, x: &[f64], p: &[f64], y: &mut [f64]) {
        validate_forward(self, "PeriodicNavierStokes", x, p, y);
        self.step.forward(x, p, y);
    }

    fn smooth_radius(&self, x: &[f64], p: &[f64], dx: &[f64], dp: &[f64]) -> f64 {
        self.step.smooth_radius(x, p, dx, dp)
    }

    fn take_error(&self) -> Option<OpError> {
        self.step.take_error()
    }
}

impl<const D: usize> Vjp for PeriodicNavierStokes<D>
where
    NavierStokes<D>: Vjp,
{
    fn vjp(&self, x: &[f64], p: &[f64], dy: &mut [f64], dx: &mut [f64], dp: &mut [f64]) {
        validate_vjp(self, "PeriodicNavierStokes", x, p, dy, dx, dp);
        self.step.vjp(x, p, dy, dx, dp);
    }
}

impl<const D: usize> Jvp for PeriodicNavierStokes<D>
where
    NavierStokes<D>: Jvp,
{
    fn jvp(&self, x: &[f64], p: &[f64], tx: &[f64], tp: &[f64], y: &mut [f64], ty: &mut [f64]) {
        validate_jvp(self, "PeriodicNavierStokes", x, p, tx, tp, y, ty);
        self.step.jvp(x, p, tx, tp, y, ty);
    }
}

/// The sizes of an operator on a box `$f` (the operator's `Periodic`).
macro_rules! sizes {
    ($t:ident, |$f:ident| $in:expr, $out:expr, $params:expr) => {
        impl<const D: usize> Operator for $t<D> {
            fn n_in(&self) -> usize {
                let $f = &self.0;
                $in
            }
            fn n_out(&self) -> usize {
                let $f = &self.0;
                $out
            }
            fn n_params(&self) -> usize {
                let $f = &self.0;
                let _ = $f;
                $params
            }
        }
    };
}
/// The packed face velocity of a periodic box on its cell centres
/// ([`Periodic::faces_to_centres`]: a spectral half-cell shift per
/// component, exact for band-limited fields); `D` values per cell out. A
/// linear map; its VJP is its transpose.
#[derive(Clone, Copy, Debug)]
pub struct FacesToCentres<const D: usize>(pub Periodic<D>);

/// The way back: `D` centred values per cell onto the faces, the periodic
/// copies filled ([`Periodic::centres_to_faces`]).
#[derive(Clone, Copy, Debug)]
pub struct CentresToFaces<const D: usize>(pub Periodic<D>);

sizes!(FacesToCentres, |f| f.n_vel(), D * f.grid.n_s(), 0);
sizes!(CentresToFaces, |f| D * f.grid.n_s(), f.n_vel(), 0);

/// Forward, VJP (the transpose, accumulated) and JVP (the map itself) of a
/// linear conversion.
macro_rules! linear_conversion {
    ($t:ident, $map:ident, $transpose:ident) => {
        impl<const D: usize> Forward for $t<D> {
            fn forward(&self, x: &[f64], p: &[f64], y: &mut [f64]) {
                validate_forward(self, stringify!($t), x, p, y);
                y.copy_from_slice(&self.0.$map(x));
            }
        }
        impl<const D: usize> Vjp for $t<D> {
            fn vjp(&self, x: &[f64], p: &[f64], dy: &mut [f64], dx: &mut [f64], dp: &mut [f64]) {
                validate_vjp(self, stringify!($t), x, p, dy, dx, dp);
                for (d, g) in dx.iter_mut().zip(self.0.$transpose(dy)) {
                    *d += g;
                }
                dy.fill(0.0);
            }
        }
        impl<const D: usize> Jvp for $t<D> {
            fn jvp(&self, x: &[f64], p: &[f64], tx: &[f64], tp: &[f64], y: &mut [f64], ty: &mut [f64]) {
                validate_jvp(self, stringify!($t), x, p, tx, tp, y, ty);
                y.copy_from_slice(&self.0.$map(x));
                ty.copy_from_slice(&self.0.$map(tx));
            }
        }
    };
}
linear_conversion!(FacesToCentres, faces_to_centres, faces_to_centres_transpose);
linear_conversion!(CentresToFaces, centres_to_faces, centres_to_faces_transpose);

impl<const D: usize> PeriodicNavierStokes<D> {
    /// This step with its velocity in and out on the cell centres (`D`
    /// values per cell, component after component, x fastest): the
    /// conversions [`CentresToFaces`] and [`FacesToCentres`] around it
    /// ([`Centred`]); the parameters are the step's.
    pub fn centred(self) -> Centred<D> {
        Centred::around(self.flow, self)
    }
}

/// An operator on the face velocities of the periodic box `flow` (a
/// [`PeriodicNavierStokes`] step by default, or a whole rollout of them,
/// [`crate::rollout::Repeat`]) with its velocity on the cell centres:
/// `x ↦ F(op(C(x), p))` with `C` the way onto the faces and `F` the way
/// back, both linear (their transposes in the VJP). Around a rollout the
/// conversions are made once, not at every step. Plain data and its own
/// type (not a [`crate::op::Chain`]) so that batches run it per thread.
#[derive(Debug)]
pub struct Centred<const D: usize, O = PeriodicNavierStokes<D>> {
    flow: Periodic<D>,
    op: O,
}

impl<const D: usize, O: Operator> Centred<D, O> {
    /// `op` (velocity on the faces of `flow`, in and out) on the centres.
    ///
    /// # Panics
    /// If `op` does not map `flow`'s face velocity to itself.
    pub fn around(flow: Periodic<D>, op: O) -> Self {
        assert!(
            op.n_in() == flow.n_vel() && op.n_out() == flow.n_vel(),
            "Centred: the operator maps {} values to {}; the box has {} face velocities",
            op.n_in(),
            op.n_out(),
            flow.n_vel()
        );
        Self { flow, op }
    }

    /// The operator on the faces.
    pub fn inner(&self) -> &O {
        &self.op
    }
}

impl<const D: usize, O: Operator> Operator for Centred<D, O> {
    fn n_in(&self) -> usize {
        D * self.flow.grid.n_s()
    }
    fn n_out(&self) -> usize {
        D * self.flow.grid.n_s()
    }
    fn n_params(&self) -> usize {
        self.op.n_params()
    }
}

impl<const D: usize, O: Forward> Forward for Centred<D, O> {
    fn forward(&self, x: &[f64], p: &[f64], y: &mut [f64]) {
        validate_forward(self, "Centred", x, p, y);
        let flow = &self.flow;
        let mut faces = vec![0.0; flow.n_vel()];
        self.op.forward(&flow.centres_to_faces(x), p, &mut faces);
        y.copy_from_slice(&flow.faces_to_centres(&faces));
    }

    fn smooth_radius(&self, x: &[f64], p: &[f64], dx: &[f64], dp: &[f64]) -> f64 {
        let flow = &self.flow;
        self.op.smooth_radius(&flow.centres_to_faces(x), p, &flow.centres_to_faces(dx), dp)
    }

    fn solve_tolerance(&self) -> f64 {
        self.op.solve_tolerance()
    }

    fn take_error(&self) -> Option<OpError> {
        self.op.take_error()
    }
}

impl<const D: usize, O: Vjp> Vjp for Centred<D, O> {
    fn vjp(&self, x: &[f64], p: &[f64], dy: &mut [f64], dx: &mut [f64], dp: &mut [f64]) {
        validate_vjp(self, "Centred", x, p, dy, dx, dp);
        let flow = &self.flow;
        let mut g = flow.faces_to_centres_transpose(dy);
        dy.fill(0.0);
        let mut gfaces = vec![0.0; flow.n_vel()];
        self.op.vjp(&flow.centres_to_faces(x), p, &mut g, &mut gfaces, dp);
        for (d, g) in dx.iter_mut().zip(flow.centres_to_faces_transpose(&gfaces)) {
            *d += g;
        }
    }
}

impl<const D: usize, O: Jvp> Jvp for Centred<D, O> {
    fn jvp(&self, x: &[f64], p: &[f64], tx: &[f64], tp: &[f64], y: &mut [f64], ty: &mut [f64]) {
        validate_jvp(self, "Centred", x, p, tx, tp, y, ty);
        let flow = &self.flow;
        let (mut yf, mut tyf) = (vec![0.0; flow.n_vel()], vec![0.0; flow.n_vel()]);
        self.op.jvp(&flow.centres_to_faces(x), p, &flow.centres_to_faces(tx), tp, &mut yf, &mut tyf);
        y.copy_from_slice(&flow.faces_to_centres(&yf));
        ty.copy_from_slice(&flow.faces_to_centres(&tyf));
    }
}
