//! Incompressible Navier–Stokes on a box periodic on every axis, in 2D and
//! 3D, as an operator with its gradient (docs/navier-stokes.md): the state
//! is the packed MAC velocity `[u, v(, w)]` (each face array with its
//! periodic copies), the parameters `p = [ν, dt]`.
//!
//! One call takes `dt` in `k` equal sub-steps, `k` chosen at the start of
//! the call from the velocity and the parameters (the viscous number and
//! the Courant number within their limits,
//! [`Periodic::substeps`]), so that a call is one function of its input and
//! its gradient that function's. Each sub-step is three maps: the advection
//! of the velocity by itself ([`PeriodicAdvect`], the fluid operators' own
//! code), the viscosity ([`PeriodicViscosity`]), each differentiated by
//! Enzyme, and the projection by FFT, a linear map that is its own adjoint.
//! The VJP runs the sub-steps again to have their states, then goes back
//! through them.

use std::cell::{Cell, RefCell};

use diffsim_solvers::mac::fft::FftProjection;
use diffsim_solvers::mac::periodic::{COURANT_LIMIT, Periodic, viscous_limit};

use super::MAX_SUBSTEPS;
use crate::op::{Forward, Jvp, OpError, OpMessage, Operator, Vjp, validate_forward, validate_jvp, validate_vjp};

/// The advection of one sub-step: the packed velocity advected by itself
/// over `p[0]` ([`Periodic::advect`]). Derivatives by Enzyme, with respect
/// to the velocity and the time step.
#[derive(Clone, Copy, Debug)]
pub struct PeriodicAdvect<const D: usize>(pub Periodic<D>);

/// The viscosity of one sub-step, `p = [ν, dt]`: each component `u ↦ u +
/// ν·dt·Δu/h²` ([`Periodic::viscosity`]). Derivatives by Enzyme.
#[derive(Clone, Copy, Debug)]
pub struct PeriodicViscosity<const D: usize>(pub Periodic<D>);

/// A body force over one sub-step, `p = [dt, f…]` with `f` one value per
/// face (the packed velocity's layout): `u ↦ u + dt·f`. Derivatives by
/// Enzyme, with respect to the velocity, the time step and the force.
#[derive(Clone, Copy, Debug)]
pub struct PeriodicForce<const D: usize>(pub Periodic<D>);

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
sizes!(PeriodicAdvect, |f| f.n_vel(), f.n_vel(), 1);
sizes!(PeriodicViscosity, |f| f.n_vel(), f.n_vel(), 2);
sizes!(PeriodicForce, |f| f.n_vel(), f.n_vel(), 1 + f.n_vel());

/// The thin wrappers Enzyme differentiates.
fn periodic_advect<const D: usize>(op: &PeriodicAdvect<D>, x: &[f64], p: &[f64], y: &mut [f64], scratch: &mut [f64]) {
    op.0.advect(p[0], x, y, scratch)
}

fn periodic_advect_scratch<const D: usize>(op: &PeriodicAdvect<D>) -> usize {
    op.0.advect_scratch_len()
}

fn periodic_advect_radius<const D: usize>(op: &PeriodicAdvect<D>, x: &[f64], p: &[f64], dx: &[f64], dp: &[f64]) -> f64 {
    op.0.radius(p[0], x, dx, dp[0])
}

fn periodic_viscosity<const D: usize>(op: &PeriodicViscosity<D>, x: &[f64], p: &[f64], y: &mut [f64]) {
    op.0.viscosity(p[0], p[1], x, y)
}

fn periodic_force<const D: usize>(_op: &PeriodicForce<D>, x: &[f64], p: &[f64], y: &mut [f64]) {
    let (dt, f) = (p[0], &p[1..]);
    for ((y, &x), &f) in y.iter_mut().zip(x).zip(f) {
        *y = x + dt * f;
    }
}

crate::differentiable!(PeriodicForce<2> => periodic_force::<2>);
crate::differentiable!(PeriodicForce<3> => periodic_force::<3>);
crate::differentiable!(PeriodicAdvect<2> => periodic_advect::<2>, smooth_radius = periodic_advect_radius::<2>, scratch = periodic_advect_scratch::<2>);
crate::differentiable!(PeriodicAdvect<3> => periodic_advect::<3>, smooth_radius = periodic_advect_radius::<3>, scratch = periodic_advect_scratch::<3>);
crate::differentiable!(PeriodicViscosity<2> => periodic_viscosity::<2>);
crate::differentiable!(PeriodicViscosity<3> => periodic_viscosity::<3>);

/// One step of incompressible Navier–Stokes on a periodic box: `x` the
/// packed velocity, `p = [ν, dt]` (the box's own `viscosity` is not used:
/// the parameter is). A call it refuses leaves the velocity as it was and
/// reports why ([`Forward::take_error`]): `ν` or `dt` negative or not
/// finite ([`OpError::Input`]), a velocity not finite or needing more than
/// [`MAX_SUBSTEPS`] sub-steps ([`OpError::Unstable`]).
#[derive(Debug)]
pub struct PeriodicNavierStokes<const D: usize> {
    flow: Periodic<D>,
    /// Whether a body force follows `[ν, dt]` in the parameters.
    forced: bool,
    fft: RefCell<FftProjection<D>>,
    error: Cell<Option<OpError>>,
}

impl<const D: usize> PeriodicNavierStokes<D> {
    /// The step of the box `flow` (its cells, cell size and scheme).
    pub fn new(flow: Periodic<D>) -> Self {
        Self { flow, forced: false, fft: RefCell::new(FftProjection::new(flow.n())), error: Cell::new(None) }
    }

    /// The step under a body force: `p = [ν, dt, f…]`, `f` one value per
    /// face in the packed velocity's layout (the copies' values unused:
    /// the projection refreshes them), added over each sub-step after the
    /// viscosity ([`PeriodicForce`]); the gradient reaches `f` too.
    pub fn forced(flow: Periodic<D>) -> Self {
        Self { forced: true, ..Self::new(flow) }
    }

    /// The box.
    pub fn flow(&self) -> &Periodic<D> {
        &self.flow
    }

    /// The sub-steps of a call at `(x, p)`, or the error that refuses it
    /// (checked before any generated code runs): `ν` or `dt` negative or
    /// not finite, a velocity not finite, or more than [`MAX_SUBSTEPS`].
    fn substeps(&self, x: &[f64], p: &[f64]) -> Result<usize, OpError> {
        let flow = &self.flow;
        // One test per parameter: an array of (name, value) pairs iterated
        // by value trips Enzyme's type analysis (docs/pitfalls.md).
        let refuse = |name: &str, v: f64| OpError::Input(OpMessage::new(&format!("PeriodicNavierStokes: {name} must be finite and ≥ 0, got {v}")));
        if !(p[0].is_finite() && p[0] >= 0.0) {
            return Err(refuse("the viscosity p[0]", p[0]));
        }
        if !(p[1].is_finite() && p[1] >= 0.0) {
            return Err(refuse("the time step p[1]", p[1]));
        }
        if let Some(i) = p[2..].iter().position(|f| !f.is_finite()) {
            return Err(OpError::Input(OpMessage::new(&format!("PeriodicNavierStokes: the force p[{}] is {}", i + 2, p[2 + i]))));
        }
        let k = flow.substeps(p[0], p[1], x);
        if k > MAX_SUBSTEPS || x.iter().any(|v| !v.is_finite()) {
            let speed = x.iter().fold(0.0f64, |m, v| m.max(v.abs()));
            let (courant, kappa) = (speed * p[1] / flow.h, p[0] * p[1] / (flow.h * flow.h));
            let (value, limit) = if courant.is_nan() || courant / COURANT_LIMIT >= kappa / viscous_limit(D) {
                (courant, COURANT_LIMIT * MAX_SUBSTEPS as f64)
            } else {
                (kappa, viscous_limit(D) * MAX_SUBSTEPS as f64)
            };
            return Err(OpError::Unstable { value, limit });
        }
        Ok(k)
    }

    /// The force's parameters over a sub-step of `sub`: `[sub, f…]`.
    fn force_params(p: &[f64], sub: f64) -> Vec<f64> {
        std::iter::once(sub).chain(p[2..].iter().copied()).collect()
    }

    /// One sub-step from `x` (`sub` its time step): the advected velocity
    /// into `advected`, the velocity after the viscosity into `viscous`
    /// (with a force; else straight into `y`), the result into `y`.
    fn substep(&self, x: &[f64], p: &[f64], sub: f64, advected: &mut [f64], viscous: &mut [f64], y: &mut [f64])
    where
        PeriodicAdvect<D>: Forward,
        PeriodicViscosity<D>: Forward,
        PeriodicForce<D>: Forward,
    {
        PeriodicAdvect(self.flow).forward(x, &[sub], advected);
        if self.forced {
            PeriodicViscosity(self.flow).forward(advected, &[p[0], sub], viscous);
            PeriodicForce(self.flow).forward(viscous, &Self::force_params(p, sub), y);
        } else {
            PeriodicViscosity(self.flow).forward(advected, &[p[0], sub], y);
        }
        self.flow.project(&mut self.fft.borrow_mut(), y);
    }
}

impl<const D: usize> Operator for PeriodicNavierStokes<D> {
    fn n_in(&self) -> usize {
        self.flow.n_vel()
    }
    fn n_out(&self) -> usize {
        self.flow.n_vel()
    }
    fn n_params(&self) -> usize {
        if self.forced { 2 + self.flow.n_vel() } else { 2 }
    }
}

impl<const D: usize> Forward for PeriodicNavierStokes<D>
where
    PeriodicAdvect<D>: Forward,
    PeriodicViscosity<D>: Forward,
    PeriodicForce<D>: Forward,
{
    fn forward(&self, x: &[f64], p: &[f64], y: &mut [f64]) {
        validate_forward(self, "PeriodicNavierStokes", x, p, y);
        let k = match self.substeps(x, p) {
            Ok(k) => k,
            Err(e) => {
                y.copy_from_slice(x);
                self.error.set(Some(e));
                return;
            }
        };
        let sub = p[1] / k as f64;
        // The velocity after the viscosity is kept apart only under a force.
        let viscous_len = if self.forced { x.len() } else { 0 };
        let (mut cur, mut advected, mut viscous) = (x.to_vec(), vec![0.0; x.len()], vec![0.0; viscous_len]);
        for _ in 0..k {
            self.substep(&cur, p, sub, &mut advected, &mut viscous, y);
            cur.copy_from_slice(y);
        }
    }

    fn smooth_radius(&self, x: &[f64], p: &[f64], dx: &[f64], dp: &[f64]) -> f64 {
        match self.substeps(x, p) {
            Ok(k) => self.flow.radius(p[1] / k as f64, x, dx, dp[1] / k as f64),
            Err(_) => 0.0,
        }
    }

    fn take_error(&self) -> Option<OpError> {
        self.error.take()
    }
}

impl<const D: usize> Vjp for PeriodicNavierStokes<D>
where
    PeriodicAdvect<D>: Vjp,
    PeriodicViscosity<D>: Vjp,
    PeriodicForce<D>: Vjp,
{
    fn vjp(&self, x: &[f64], p: &[f64], dy: &mut [f64], dx: &mut [f64], dp: &mut [f64]) {
        validate_vjp(self, "PeriodicNavierStokes", x, p, dy, dx, dp);
        let Ok(k) = self.substeps(x, p) else {
            // The forward left the velocity as it was (and reported why).
            for (d, g) in dx.iter_mut().zip(dy.iter_mut()) {
                *d += std::mem::take(g);
            }
            return;
        };
        let (sub, nu, n) = (p[1] / k as f64, p[0], x.len());
        // Each sub-step's starting state, advected velocity and (with a
        // force) velocity after the viscosity.
        let mut states = vec![x.to_vec()];
        let (mut advected, mut viscous) = (Vec::with_capacity(k), Vec::with_capacity(k));
        for i in 0..k {
            let (mut a, mut v, mut next) = (vec![0.0; n], vec![0.0; if self.forced { n } else { 0 }], vec![0.0; n]);
            self.substep(&states[i], p, sub, &mut a, &mut v, &mut next);
            advected.push(a);
            viscous.push(v);
            if i + 1 < k {
                states.push(next);
            }
        }
        let (advect, viscosity, force) = (PeriodicAdvect(self.flow), PeriodicViscosity(self.flow), PeriodicForce(self.flow));
        let fp = if self.forced { Self::force_params(p, sub) } else { Vec::new() };
        let mut gf = vec![0.0; fp.len()];
        let mut g = dy.to_vec();
        dy.fill(0.0);
        let (mut ga, mut gw) = (vec![0.0; n], vec![0.0; n]);
        for ((state, a), v) in states.iter().zip(&advected).zip(&viscous).rev() {
            self.flow.project_adjoint(&mut self.fft.borrow_mut(), &mut g);
            if self.forced {
                gw.fill(0.0);
                force.vjp(v, &fp, &mut g, &mut gw, &mut gf);
                std::mem::swap(&mut g, &mut gw);
            }
            let (mut gv, mut gx) = ([0.0; 2], vec![0.0; n]);
            ga.fill(0.0);
            viscosity.vjp(a, &[nu, sub], &mut g, &mut ga, &mut gv);
            let mut gt = [0.0];
            advect.vjp(state, &[sub], &mut ga, &mut gx, &mut gt);
            dp[0] += gv[0];
            dp[1] += (gv[1] + gt[0]) / k as f64;
            g = gx;
        }
        if self.forced {
            // The force's time step is the sub-step's: dt/k.
            dp[1] += gf[0] / k as f64;
            for (d, g) in dp[2..].iter_mut().zip(&gf[1..]) {
                *d += g;
            }
        }
        for (d, g) in dx.iter_mut().zip(&g) {
            *d += g;
        }
    }
}

impl<const D: usize> Jvp for PeriodicNavierStokes<D>
where
    PeriodicAdvect<D>: Jvp,
    PeriodicViscosity<D>: Jvp,
    PeriodicForce<D>: Jvp,
{
    fn jvp(&self, x: &[f64], p: &[f64], tx: &[f64], tp: &[f64], y: &mut [f64], ty: &mut [f64]) {
        validate_jvp(self, "PeriodicNavierStokes", x, p, tx, tp, y, ty);
        let Ok(k) = self.substeps(x, p) else {
            y.copy_from_slice(x);
            ty.copy_from_slice(tx);
            return;
        };
        let (sub, tsub, n) = (p[1] / k as f64, tp[1] / k as f64, x.len());
        let (advect, viscosity, force) = (PeriodicAdvect(self.flow), PeriodicViscosity(self.flow), PeriodicForce(self.flow));
        let (fp, tfp) = if self.forced { (Self::force_params(p, sub), Self::force_params(tp, tsub)) } else { (Vec::new(), Vec::new()) };
        let (mut cur, mut tcur) = (x.to_vec(), tx.to_vec());
        let (mut a, mut ta, mut v, mut tv) = (vec![0.0; n], vec![0.0; n], vec![0.0; n], vec![0.0; n]);
        for _ in 0..k {
            advect.jvp(&cur, &[sub], &tcur, &[tsub], &mut a, &mut ta);
            if self.forced {
                viscosity.jvp(&a, &[p[0], sub], &ta, &[tp[0], tsub], &mut v, &mut tv);
                force.jvp(&v, &fp, &tv, &tfp, y, ty);
            } else {
                viscosity.jvp(&a, &[p[0], sub], &ta, &[tp[0], tsub], y, ty);
            }
            self.flow.project(&mut self.fft.borrow_mut(), y);
            self.flow.project(&mut self.fft.borrow_mut(), ty);
            cur.copy_from_slice(y);
            tcur.copy_from_slice(ty);
        }
    }
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
        Centred(self)
    }
}

/// A [`PeriodicNavierStokes`] step with its velocity on the cell centres:
/// `x ↦ F(step(C(x), p))` with `C` the way onto the faces and `F` the way
/// back, both linear (their transposes in the VJP). Plain data and its own
/// type (not a [`crate::op::Chain`]) so that batches run it per thread.
#[derive(Debug)]
pub struct Centred<const D: usize>(pub PeriodicNavierStokes<D>);

impl<const D: usize> Operator for Centred<D> {
    fn n_in(&self) -> usize {
        D * self.0.flow.grid.n_s()
    }
    fn n_out(&self) -> usize {
        D * self.0.flow.grid.n_s()
    }
    fn n_params(&self) -> usize {
        self.0.n_params()
    }
}

impl<const D: usize> Forward for Centred<D>
where
    PeriodicNavierStokes<D>: Forward,
{
    fn forward(&self, x: &[f64], p: &[f64], y: &mut [f64]) {
        validate_forward(self, "Centred", x, p, y);
        let flow = &self.0.flow;
        let mut faces = vec![0.0; flow.n_vel()];
        self.0.forward(&flow.centres_to_faces(x), p, &mut faces);
        y.copy_from_slice(&flow.faces_to_centres(&faces));
    }

    fn smooth_radius(&self, x: &[f64], p: &[f64], dx: &[f64], dp: &[f64]) -> f64 {
        let flow = &self.0.flow;
        self.0.smooth_radius(&flow.centres_to_faces(x), p, &flow.centres_to_faces(dx), dp)
    }

    fn take_error(&self) -> Option<OpError> {
        self.0.take_error()
    }
}

impl<const D: usize> Vjp for Centred<D>
where
    PeriodicNavierStokes<D>: Vjp,
{
    fn vjp(&self, x: &[f64], p: &[f64], dy: &mut [f64], dx: &mut [f64], dp: &mut [f64]) {
        validate_vjp(self, "Centred", x, p, dy, dx, dp);
        let flow = &self.0.flow;
        let mut g = flow.faces_to_centres_transpose(dy);
        dy.fill(0.0);
        let mut gfaces = vec![0.0; flow.n_vel()];
        self.0.vjp(&flow.centres_to_faces(x), p, &mut g, &mut gfaces, dp);
        for (d, g) in dx.iter_mut().zip(flow.centres_to_faces_transpose(&gfaces)) {
            *d += g;
        }
    }
}

impl<const D: usize> Jvp for Centred<D>
where
    PeriodicNavierStokes<D>: Jvp,
{
    fn jvp(&self, x: &[f64], p: &[f64], tx: &[f64], tp: &[f64], y: &mut [f64], ty: &mut [f64]) {
        validate_jvp(self, "Centred", x, p, tx, tp, y, ty);
        let flow = &self.0.flow;
        let (mut yf, mut tyf) = (vec![0.0; flow.n_vel()], vec![0.0; flow.n_vel()]);
        self.0.jvp(&flow.centres_to_faces(x), p, &flow.centres_to_faces(tx), tp, &mut yf, &mut tyf);
        y.copy_from_slice(&flow.faces_to_centres(&yf));
        ty.copy_from_slice(&flow.faces_to_centres(&tyf));
    }
}
