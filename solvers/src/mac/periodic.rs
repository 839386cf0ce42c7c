//! Incompressible Navier–Stokes on a box periodic on every axis, in 2D and
//! 3D from one code: the MAC velocity advected by itself (semi-Lagrangian
//! or MacCormack, [`super::advect`]), viscosity by forward Euler on each
//! component's faces, and the projection by FFT ([`super::fft`]). The
//! forward step the Navier–Stokes operator and its validation against exact
//! solutions are built on (`docs/navier-stokes.md`).
//!
//! Units: cells of size `h` on every axis (the box is `n_a·h` long), the
//! velocity in length per time, `dt` in time. A traced point moves
//! `dt·u/h` cells; the viscous number is `κ = ν·dt/h²`.
//!
//! A requested `dt` is a sampling interval, never a crash: [`Periodic::substeps`]
//! splits it into `k` equal sub-steps so that every sub-step keeps `κ` and
//! the Courant number `max|u|·dt/h` within their limits, with `k` chosen
//! once per call from the velocity it starts from (so that a call is one
//! function of its input, and its gradient that function's).

use super::advect::{advect_field, advect_radius};
use super::fft::FftProjection;
use super::{At, Mac, Wrapping};
use crate::diffusion::Grid;
use crate::smoke::Scheme;

/// Largest `κ = ν·dt/h²` of one explicit viscous sub-step in `D`
/// dimensions, with a margin: the forward Euler step of the `2D+1`-point
/// Laplacian is stable up to `1/(2D)`.
pub fn viscous_limit(d: usize) -> f64 {
    0.9 / (2 * d) as f64
}

/// Largest Courant number `max|u|·dt/h` of one sub-step (the traces stay
/// within a cell of their point, where MacCormack's correction is stable).
pub const COURANT_LIMIT: f64 = 0.9;

/// Settings of the periodic Navier–Stokes step.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Periodic<const D: usize> {
    /// Cells per axis.
    pub n: [usize; D],
    /// Cell size (every axis).
    pub h: f64,
    /// Kinematic viscosity.
    pub viscosity: f64,
    /// Advection scheme of the velocity.
    pub scheme: Scheme,
}

/// Buffers of the step.
#[derive(Debug)]
pub struct PeriodicWork<const D: usize> {
    fft: FftProjection<D>,
    next: Vec<f64>,
    scratch: Vec<f64>,
}

impl<const D: usize> Periodic<D> {
    /// The index rules of the box (every axis wraps).
    pub fn mac(&self) -> Mac<D, Wrapping> {
        Mac { n: super::axes_of(&self.n), wrap: Wrapping }
    }

    /// Length of the face array of `axis` (with the periodic copies).
    pub fn face_len(&self, axis: usize) -> usize {
        self.mac().lattice(At::Face(axis)).len
    }

    /// Buffers for [`Self::step`].
    pub fn work(&self) -> PeriodicWork<D> {
        PeriodicWork { fft: FftProjection::new(self.n), next: vec![0.0; self.n_vel()], scratch: vec![0.0; self.explicit_scratch_len()] }
    }

    /// The number of equal sub-steps a step of `dt` takes from the packed
    /// velocity `vel` with viscosity `nu`: the fewest that keep `κ` within
    /// [`viscous_limit`] and the Courant number within [`COURANT_LIMIT`].
    pub fn substeps(&self, nu: f64, dt: f64, vel: &[f64]) -> usize {
        let speed = vel.iter().fold(0.0f64, |m, u| m.max(u.abs()));
        let kappa = nu * dt / (self.h * self.h);
        let courant = speed * dt / self.h;
        let k = (kappa / viscous_limit(D)).max(courant / COURANT_LIMIT).ceil();
        (k as usize).max(1)
    }

    /// One step of `dt` in place on the packed velocity `vel` (`[u, v(,
    /// w)]`, each face array with its copies): [`Self::substeps`] sub-steps
    /// of advection, viscosity and projection. Returns the number of
    /// sub-steps.
    ///
    /// # Panics
    /// If `vel` has the wrong length.
    pub fn step(&self, dt: f64, vel: &mut [f64], work: &mut PeriodicWork<D>) -> usize {
        assert_eq!(vel.len(), self.n_vel(), "periodic step: length of the packed velocity");
        let k = self.substeps(self.viscosity, dt, vel);
        for _ in 0..k {
            self.substep(dt / k as f64, vel, work);
        }
        k
    }

    /// One sub-step of `dt` (no splitting): [`Self::explicit`], then the
    /// projection.
    pub fn substep(&self, dt: f64, vel: &mut [f64], work: &mut PeriodicWork<D>) {
        self.explicit(self.viscosity, dt, vel, &mut work.next, &mut work.scratch);
        self.project(&mut work.fft, &mut work.next);
        vel.copy_from_slice(&work.next);
    }

    /// The projection of the packed velocity `vel` by `fft`, in place.
    pub fn project(&self, fft: &mut FftProjection<D>, vel: &mut [f64]) {
        fft.project(self.components(vel));
    }

    /// The adjoint of [`Self::project`] on the packed adjoint `g`, in place.
    pub fn project_adjoint(&self, fft: &mut FftProjection<D>, g: &mut [f64]) {
        fft.project_adjoint(self.components(g));
    }

    /// The packed velocity's components.
    fn parts<'a>(&self, vel: &'a [f64]) -> [&'a [f64]; D] {
        // One constant index at a time (docs/pitfalls.md).
        let mut parts = [vel; D];
        let mut start = 0;
        each_axis!(D, a => {
            parts[a] = &vel[start..start + self.face_len(a)];
            start += self.face_len(a);
        });
        parts
    }

    /// The packed velocity cut into its components, mutably.
    fn components<'a>(&self, vel: &'a mut [f64]) -> [&'a mut [f64]; D] {
        let mut parts = Vec::with_capacity(D);
        let mut rest = vel;
        for a in 0..D {
            let (head, tail) = rest.split_at_mut(self.face_len(a));
            parts.push(head);
            rest = tail;
        }
        parts.try_into().expect("one face array per axis")
    }
}

impl<const D: usize> Periodic<D> {
    /// Length of the packed velocity `[u, v(, w)]` (each face array with
    /// its copies).
    pub fn n_vel(&self) -> usize {
        (0..D).map(|a| self.face_len(a)).sum()
    }

    /// Scratch [`Self::explicit`] needs: the advected velocity and, for
    /// MacCormack, two fields of the longest component.
    pub fn explicit_scratch_len(&self) -> usize {
        let longest = (0..D).map(|a| self.face_len(a)).max().unwrap_or(0);
        self.n_vel() + 2 * longest
    }

    /// The explicit part of one sub-step on the packed velocity `x`:
    /// advection over `dt`, then viscosity `nu`, written to `y` (the
    /// projection follows, outside). `nu` and `dt` are arguments so that a
    /// gradient reaches them. Plain loops on slices, one call per component
    /// (Enzyme differentiates this).
    ///
    /// # Panics
    /// If a length is wrong.
    pub fn explicit(&self, nu: f64, dt: f64, x: &[f64], y: &mut [f64], scratch: &mut [f64]) {
        let n_vel = self.n_vel();
        assert!(x.len() == n_vel && y.len() == n_vel && scratch.len() >= self.explicit_scratch_len(), "periodic step: packed lengths");
        let mac = self.mac();
        let longest = (0..D).map(|a| self.face_len(a)).max().unwrap_or(0);
        let (advected, rest) = scratch.split_at_mut(n_vel);
        let half = (rest.len() / 2).min(longest);
        let (hat, rest) = rest.split_at_mut(half);
        let tilde = &mut rest[..half];
        let vel = self.parts(x);
        let cells = dt / self.h;
        let kappa = nu * dt / (self.h * self.h);
        // Each component through its range of the packed arrays.
        let mut start = 0;
        each_axis!(D, a => {
            let len = vel[a].len();
            let r = start..start + len;
            advect_field(mac, At::Face(a), self.scheme, cells, vel, vel[a], &mut advected[r.clone()], &mut hat[..len], &mut tilde[..len]);
            diffuse(&mac.lattice(At::Face(a)), a, kappa, &advected[r.clone()], &mut y[r]);
            start += len;
        });
    }

    /// How far the packed velocity `x` and the time step `dt` may move along
    /// `(dx, ddt)` before a trace of one sub-step crosses a lattice plane,
    /// where multilinear sampling kinks (for MacCormack, the forward trace
    /// too; its limiter is not counted). Over the first sub-step only.
    pub fn radius(&self, dt: f64, x: &[f64], dx: &[f64], ddt: f64) -> f64 {
        let (cells, rate) = (dt / self.h, ddt / self.h);
        let (steps, rates): (&[f64], &[f64]) = match self.scheme {
            Scheme::SemiLagrangian => (&[cells], &[rate]),
            Scheme::MacCormack { .. } => (&[cells, -cells], &[rate, -rate]),
        };
        let lattices: Vec<At> = (0..D).map(At::Face).collect();
        advect_radius(self.mac(), &lattices, steps, rates, self.parts(x), self.parts(dx), |_, _| false)
    }
}

/// `out = s + κ·Δs` on the own samples of the periodic face lattice `lat`
/// of `axis` (the `2D+1`-point Laplacian, wrapping on every axis:
/// [`crate::diffusion::explicit`] on the lattice's [`Grid`]), its copies
/// (face `n` along `axis`) refreshed.
pub fn diffuse<const D: usize>(lat: &super::Lattice<D>, axis: usize, kappa: f64, s: &[f64], out: &mut [f64]) {
    // Rows per slab in the array (one more along `axis` when it is y).
    let rows = if D == 3 { lat.stride[2] / lat.stride[1] } else { lat.len / lat.stride[1] };
    let grid =
        Grid { stride: lat.stride[1], nx: lat.n[0], ny: lat.n[1], nz: if D == 3 { lat.n[2] } else { 1 }, wrap_x: true, wrap_y: true, wrap_z: D == 3, rows };
    crate::diffusion::explicit(&grid, kappa, s, out);
    refresh_copies(lat, axis, out);
}

/// On the face lattice of `axis`, face `n` (the copy) set to face 0.
pub fn refresh_copies<const D: usize>(lat: &super::Lattice<D>, axis: usize, f: &mut [f64]) {
    let (st, shift) = (lat.stride[axis], lat.n[axis] * lat.stride[axis]);
    // Layers along `axis`: `st` values inside each, `len / (st·(n + 1))` of them.
    for outer in 0..lat.len / (st * (lat.n[axis] + 1)) {
        let base = outer * st * (lat.n[axis] + 1);
        for c in base..base + st {
            f[c + shift] = f[c];
        }
    }
}
