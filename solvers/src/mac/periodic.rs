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

use super::Mac;
use super::fft::FftProjection;
use crate::boundary::{Boundary, Side};
use crate::diffusion::Grid;
use crate::smoke::{MacGrid, Scheme, advect_velocity, advect_velocity_radius};

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
    /// The grid: its cells, every side periodic. The velocity is advected
    /// by the fluid operators' own code ([`crate::smoke::advect_velocity`]).
    pub grid: MacGrid<D>,
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
    /// The box of `n` cells of size `h` on every axis, every side periodic.
    pub fn new(n: [usize; D], h: f64, viscosity: f64, scheme: Scheme) -> Self {
        Self { grid: MacGrid::new(n).with_boundary(Boundary::all(Side::Periodic)), h, viscosity, scheme }
    }

    /// Cells per axis.
    pub fn n(&self) -> [usize; D] {
        self.grid.n
    }

    /// The index rules of the box (every axis wraps).
    pub fn mac(&self) -> Mac<D, [bool; D]> {
        self.grid.mac()
    }

    /// Length of the face array of `axis` (with the periodic copies).
    pub fn face_len(&self, axis: usize) -> usize {
        self.grid.n_face(axis)
    }

    /// Buffers for [`Self::step`].
    pub fn work(&self) -> PeriodicWork<D> {
        PeriodicWork { fft: FftProjection::new(self.grid.n), next: vec![0.0; self.n_vel()], scratch: vec![0.0; self.explicit_scratch_len()] }
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

    /// Steps the packed velocity `vel` from time 0 to `t` in the fewest
    /// equal steps of at most `max_dt` (each split into stable sub-steps by
    /// [`Self::step`]); returns the number of steps.
    pub fn run(&self, t: f64, max_dt: f64, vel: &mut [f64]) -> usize {
        let mut work = self.work();
        let steps = (t / max_dt).ceil() as usize;
        for _ in 0..steps {
            self.step(t / steps as f64, vel, &mut work);
        }
        steps
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
        fft.project(self.grid.components_mut(vel));
    }

    /// The adjoint of [`Self::project`] on the packed adjoint `g`, in place.
    pub fn project_adjoint(&self, fft: &mut FftProjection<D>, g: &mut [f64]) {
        fft.project_adjoint(self.grid.components_mut(g));
    }
}

impl<const D: usize> Periodic<D> {
    /// Length of the packed velocity `[u, v(, w)]` (each face array with
    /// its copies).
    pub fn n_vel(&self) -> usize {
        self.grid.n_vel()
    }

    /// Scratch [`Self::explicit`] needs: the advected velocity and
    /// [`Self::advect_scratch_len`].
    pub fn explicit_scratch_len(&self) -> usize {
        self.n_vel() + self.advect_scratch_len()
    }

    /// The explicit part of one sub-step on the packed velocity `x`:
    /// [`Self::advect`] over `dt`, then [`Self::viscosity`] `nu`, written
    /// to `y` (the projection follows, outside). `nu` and `dt` are
    /// arguments so that a gradient reaches them; the operator
    /// differentiates the two parts apart (Enzyme gave a wrong 3D gradient
    /// for the two in one function, each alone is right: docs/pitfalls.md).
    ///
    /// # Panics
    /// If a length is wrong.
    pub fn explicit(&self, nu: f64, dt: f64, x: &[f64], y: &mut [f64], scratch: &mut [f64]) {
        let n_vel = self.n_vel();
        assert!(x.len() == n_vel && y.len() == n_vel && scratch.len() >= self.explicit_scratch_len(), "periodic step: packed lengths");
        let (advected, rest) = scratch.split_at_mut(n_vel);
        self.advect(dt, x, advected, rest);
        self.viscosity(nu, dt, advected, y);
    }

    /// The advection of one sub-step: the packed velocity `x` advected by
    /// itself over `dt` by the box's scheme into `y` (the fluid operators'
    /// [`advect_velocity`], or [`crate::smoke::advect_velocity_near`] where
    /// it applies), the periodic copies refreshed; `scratch` holds
    /// [`Self::advect_scratch_len`] values.
    #[inline(always)]
    pub fn advect(&self, dt: f64, x: &[f64], y: &mut [f64], scratch: &mut [f64]) {
        let dt = dt / self.h;
        if crate::smoke::near_applies(&self.grid, self.scheme, dt, x) {
            return crate::smoke::advect_velocity_near_widest(&self.grid, self.scheme, dt, x, y, scratch);
        }
        advect_velocity(&self.grid, self.scheme, dt, x, y, scratch);
        refresh_periodic_copies(&self.grid, y);
    }

    /// Scratch of [`Self::advect`] (either path's).
    pub fn advect_scratch_len(&self) -> usize {
        crate::smoke::advect_velocity_scratch_len(&self.grid, self.scheme).max(crate::smoke::advect_velocity_near_scratch_len(&self.grid))
    }

    /// The viscosity of one sub-step: `y = x + ν·dt·Δx/h²` on each
    /// component of the packed velocity `x` ([`diffuse`]). Linear in `x`.
    #[inline(always)]
    pub fn viscosity(&self, nu: f64, dt: f64, x: &[f64], y: &mut [f64]) {
        assert!(x.len() == self.n_vel() && y.len() == self.n_vel(), "periodic viscosity: packed lengths");
        let n = self.grid.cells();
        let kappa = nu * dt / (self.h * self.h);
        // Each component through its range of the packed arrays.
        let mut start = 0;
        each_axis!(D, a => {
            let len = self.grid.n_face(a);
            let r = start..start + len;
            diffuse(n, a, kappa, &x[r.clone()], &mut y[r]);
            start += len;
        });
    }

    /// How far the packed velocity `x` and the time step `dt` may move along
    /// `(dx, ddt)` before a trace of one sub-step crosses a lattice plane,
    /// where multilinear sampling kinks (for MacCormack, the forward trace
    /// too, and with its limiter where the clamp switches): the fluid
    /// operators' [`advect_velocity_radius`]. Over the first sub-step only.
    pub fn radius(&self, dt: f64, x: &[f64], dx: &[f64], ddt: f64) -> f64 {
        advect_velocity_radius(&self.grid, self.scheme, dt / self.h, ddt / self.h, x, dx)
    }
}

impl<const D: usize> Periodic<D> {
    /// The packed face velocity `vel` on the cell centres: each component
    /// moved half a cell along its own axis by the Fourier shift theorem
    /// ([`super::fft::shift_along`]), exact for a band-limited field (no
    /// `cos²(πk/n)` damping, as a linear average has); returns the `D`
    /// components, each on the `Π n` cells (x fastest), one after another.
    ///
    /// # Panics
    /// If `vel` has the wrong length.
    pub fn faces_to_centres(&self, vel: &[f64]) -> Vec<f64> {
        assert_eq!(vel.len(), self.n_vel(), "faces_to_centres: length of the packed velocity");
        let n = self.n();
        let mut out = Vec::with_capacity(D * self.grid.n_s());
        for a in 0..D {
            let mut own = own_faces(n, a, &vel[self.grid.face_range(a)]);
            super::fft::shift_along(&n, a, 0.5, &mut own);
            out.extend_from_slice(&own);
        }
        out
    }

    /// The inverse of [`Self::faces_to_centres`] (and its transpose): the
    /// `D` centred components moved back half a cell along their axes onto
    /// the faces, the periodic copies filled. A round trip returns a
    /// band-limited field to rounding (measured in docs/navier-stokes.md).
    ///
    /// # Panics
    /// If `centred` does not have `D` values per cell.
    pub fn centres_to_faces(&self, centred: &[f64]) -> Vec<f64> {
        let cells = self.grid.n_s();
        assert_eq!(centred.len(), D * cells, "centres_to_faces: D values per cell");
        let n = self.n();
        let mut out = Vec::with_capacity(self.n_vel());
        for a in 0..D {
            let mut own = centred[a * cells..(a + 1) * cells].to_vec();
            super::fft::shift_along(&n, a, -0.5, &mut own);
            out.extend(with_copies(n, a, &own));
        }
        out
    }

    /// The transpose of [`Self::faces_to_centres`]: centred adjoints `g`
    /// onto the faces (the copies, which the conversion does not read, get
    /// zero).
    pub fn faces_to_centres_transpose(&self, g: &[f64]) -> Vec<f64> {
        let mut out = self.centres_to_faces(g);
        for a in 0..D {
            let faces = &mut out[self.grid.face_range(a)];
            super::fft::for_copies(self.n(), a, |_, copy| faces[copy] = 0.0);
        }
        out
    }

    /// The transpose of [`Self::centres_to_faces`]: face adjoints `g`, each
    /// copy's added to the face it copies, then [`Self::faces_to_centres`]
    /// (which reads no copy).
    pub fn centres_to_faces_transpose(&self, g: &[f64]) -> Vec<f64> {
        assert_eq!(g.len(), self.n_vel(), "centres_to_faces_transpose: length of the packed adjoint");
        let mut folded = g.to_vec();
        for a in 0..D {
            let faces = &mut folded[self.grid.face_range(a)];
            super::fft::for_copies(self.n(), a, |face, copy| faces[face] += faces[copy]);
        }
        self.faces_to_centres(&folded)
    }
}

/// The faces normal to `axis` that hold their own value (the copies along
/// `axis` left out), as a field of `Π n` samples.
pub(crate) fn own_faces<const D: usize>(n: [usize; D], axis: usize, faces: &[f64]) -> Vec<f64> {
    let inner: usize = n[..axis].iter().product();
    let na = n[axis];
    let mut out = Vec::with_capacity(n.iter().product());
    for layer in faces.chunks(inner * (na + 1)) {
        out.extend_from_slice(&layer[..inner * na]);
    }
    out
}

/// The inverse of [`own_faces`]: the face array of `axis` with its copies.
fn with_copies<const D: usize>(n: [usize; D], axis: usize, own: &[f64]) -> Vec<f64> {
    let inner: usize = n[..axis].iter().product();
    let mut out = Vec::with_capacity(own.len() / n[axis] * (n[axis] + 1));
    for layer in own.chunks(inner * n[axis]) {
        out.extend_from_slice(layer);
        out.extend_from_slice(&layer[..inner]);
    }
    out
}

/// `out = s + κ·Δs` on the own samples of the faces normal to `axis` of a
/// periodic box of `n` cells (the `2D+1`-point Laplacian, wrapping on every
/// axis: [`crate::diffusion::explicit`] on the face array's [`Grid`]), the
/// copies (face `n` along `axis`) refreshed.
///
/// Integers in, no [`super::Lattice`]: a lattice struct (integers, then
/// its origin's `f64`s) built here and handed on reached Enzyme mistyped,
/// and the 3D gradient came out wrong (docs/pitfalls.md).
#[inline(always)]
pub fn diffuse<const D: usize>(n: [usize; D], axis: usize, kappa: f64, s: &[f64], out: &mut [f64]) {
    // The face array: one more face along `axis` (the copy).
    let len = |b: usize| n[b] + usize::from(b == axis);
    let grid =
        Grid { stride: len(0), nx: n[0], ny: n[1], nz: if D == 3 { n[D - 1] } else { 1 }, wrap_x: true, wrap_y: true, wrap_z: D == 3, rows: len(1), fixed: 0 };
    crate::diffusion::explicit(&grid, kappa, s, out);
    refresh_copies(n, axis, out);
}

/// On the packed velocity `vel` of `grid`, the periodic copies (face `n`
/// along each wrapping axis, of the component normal to it) set to face 0,
/// by this module's own loop: the Navier–Stokes advection's last part,
/// inside the function Enzyme differentiates (so that every output is
/// defined and every seed consumed; calling the walls'
/// [`crate::smoke::enforce_boundary`] there gave a wrong 3D gradient,
/// docs/pitfalls.md).
#[inline(always)]
pub fn refresh_periodic_copies<const D: usize>(grid: &MacGrid<D>, vel: &mut [f64]) {
    let (n, wraps) = (grid.cells(), grid.boundary.wraps());
    let mut start = 0;
    each_axis!(D, a => {
        let len = grid.n_face(a);
        if wraps[a] {
            refresh_copies(n, a, &mut vel[start..start + len]);
        }
        start += len;
    });
}

/// On the faces normal to `axis` of a periodic box of `n` cells (the array
/// with the copies), face `n` (the copy) set to face 0.
#[inline(always)]
pub fn refresh_copies<const D: usize>(n: [usize; D], axis: usize, f: &mut [f64]) {
    // Values inside one layer along `axis`, and layers of `n + 1` faces.
    let mut st = 1;
    let mut total = 1;
    each_axis!(D, b => {
        let m = n[b] + usize::from(b == axis);
        if b < axis {
            st *= m;
        }
        total *= m;
    });
    let (na, shift) = (n[axis], n[axis] * st);
    for outer in 0..total / (st * (na + 1)) {
        let base = outer * st * (na + 1);
        for c in base..base + st {
            f[c + shift] = f[c];
        }
    }
}

/// Adjoint of [`refresh_periodic_copies`]: each copy's adjoint added into
/// its face's and zeroed.
pub fn refresh_periodic_copies_adjoint<const D: usize>(grid: &MacGrid<D>, g: &mut [f64]) {
    let (n, wraps) = (grid.cells(), grid.boundary.wraps());
    let mut start = 0;
    for a in 0..D {
        let len = grid.n_face(a);
        if wraps[a] {
            let f = &mut g[start..start + len];
            let st: usize = (0..a).map(|b| n[b]).product();
            let (na, shift) = (n[a], n[a] * st);
            for outer in 0..len / (st * (na + 1)) {
                let base = outer * st * (na + 1);
                for c in base..base + st {
                    f[c] += std::mem::take(&mut f[c + shift]);
                }
            }
        }
        start += len;
    }
}
