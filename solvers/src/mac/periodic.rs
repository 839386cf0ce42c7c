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

use super::advect::advect_field;
use super::fft::FftProjection;
use super::{At, Mac, Wrapping};
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
    advected: Vec<Vec<f64>>,
    hat: Vec<f64>,
    tilde: Vec<f64>,
}

impl<const D: usize> Periodic<D> {
    /// The index rules of the box (every axis wraps).
    pub fn mac(&self) -> Mac<D, Wrapping> {
        Mac { n: self.n, wrap: Wrapping }
    }

    /// Length of the face array of `axis` (with the periodic copies).
    pub fn face_len(&self, axis: usize) -> usize {
        self.mac().lattice(At::Face(axis)).len
    }

    /// Buffers for [`Self::step`].
    pub fn work(&self) -> PeriodicWork<D> {
        let longest = (0..D).map(|a| self.face_len(a)).max().unwrap_or(0);
        PeriodicWork {
            fft: FftProjection::new(self.n),
            advected: (0..D).map(|a| vec![0.0; self.face_len(a)]).collect(),
            hat: vec![0.0; longest],
            tilde: vec![0.0; longest],
        }
    }

    /// The number of equal sub-steps a step of `dt` takes from the velocity
    /// `vel`: the fewest that keep `κ` within [`viscous_limit`] and the
    /// Courant number within [`COURANT_LIMIT`].
    pub fn substeps(&self, dt: f64, vel: &[&[f64]; D]) -> usize {
        let speed = vel.iter().flat_map(|v| v.iter()).fold(0.0f64, |m, u| m.max(u.abs()));
        let kappa = self.viscosity * dt / (self.h * self.h);
        let courant = speed * dt / self.h;
        let k = (kappa / viscous_limit(D)).max(courant / COURANT_LIMIT).ceil();
        (k as usize).max(1)
    }

    /// One step of `dt` in place on the velocity `vel` (the face arrays of
    /// each axis): [`Self::substeps`] sub-steps of advection, viscosity and
    /// projection. Returns the number of sub-steps.
    ///
    /// # Panics
    /// If an array has the wrong length.
    pub fn step(&self, dt: f64, vel: &mut [Vec<f64>], work: &mut PeriodicWork<D>) -> usize {
        assert_eq!(vel.len(), D, "periodic step: one face array per axis");
        for (a, v) in vel.iter().enumerate() {
            assert_eq!(v.len(), self.face_len(a), "periodic step: length of the velocity of axis {a}");
        }
        let k = self.substeps(dt, &std::array::from_fn(|a| vel[a].as_slice()));
        let sdt = dt / k as f64;
        for _ in 0..k {
            self.substep(sdt, vel, work);
        }
        k
    }

    /// One sub-step of `dt` (no splitting).
    pub fn substep(&self, dt: f64, vel: &mut [Vec<f64>], work: &mut PeriodicWork<D>) {
        let mac = self.mac();
        {
            let v: [&[f64]; D] = std::array::from_fn(|a| vel[a].as_slice());
            for a in 0..D {
                let len = v[a].len();
                let (hat, tilde) = (&mut work.hat[..len], &mut work.tilde[..len]);
                advect_field(mac, At::Face(a), self.scheme, dt / self.h, v, v[a], &mut work.advected[a], hat, tilde);
            }
        }
        let kappa = self.viscosity * dt / (self.h * self.h);
        for a in 0..D {
            let lat = mac.lattice(At::Face(a));
            diffuse(&lat, a, kappa, &work.advected[a], &mut vel[a]);
        }
        let arrays: Vec<&mut [f64]> = vel.iter_mut().map(|v| v.as_mut_slice()).collect();
        work.fft.project(arrays.try_into().expect("one face array per axis"));
    }
}

/// `out = s + κ·Δs` on the own samples of the periodic face lattice `lat`
/// of `axis` (the `2D+1`-point Laplacian, wrapping on every axis), its
/// copies (face `n` along `axis`) refreshed.
pub fn diffuse<const D: usize>(lat: &super::Lattice<D>, axis: usize, kappa: f64, s: &[f64], out: &mut [f64]) {
    let m = lat.n[0];
    for k in 0..lat.n[D - 1] {
        for r in 0..lat.rows_per_slab() {
            let q = lat.row_start(k, r);
            let row = lat.index(q);
            // The rows beside this one along the other axes (wrapped): the
            // same for every sample of the row.
            let mut beside = [(row, row); 3];
            for a in 1..D {
                let (st, n) = (lat.stride[a], lat.n[a]);
                let down = if q[a] == 0 { row + (n - 1) * st } else { row - st };
                let up = if q[a] + 1 == n { row - (n - 1) * st } else { row + st };
                beside[a] = (down, up);
            }
            for i in 0..m {
                let (left, right) = (if i == 0 { m - 1 } else { i - 1 }, if i + 1 == m { 0 } else { i + 1 });
                let c = s[row + i];
                let mut lap = s[row + left] + s[row + right] - 2.0 * c;
                for &(down, up) in &beside[1..D] {
                    lap += s[down + i] + s[up + i] - 2.0 * c;
                }
                out[row + i] = c + kappa * lap;
            }
        }
    }
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
