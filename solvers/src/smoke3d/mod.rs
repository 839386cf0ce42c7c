//! 3D incompressible smoke on a MAC grid: semi-Lagrangian advection of a
//! cell-centred scalar and of a staggered velocity by trilinear sampling,
//! buoyancy, walls, and the pressure projection solved by conjugate
//! gradients with a multigrid preconditioner. Benchmark P4 `smoke3d` is
//! P2 in three dimensions (`docs/benchmarks.md`).
//!
//! Conventions (those of P4): `nx × ny × nz` unit cells, x to the right, y
//! up, z towards the viewer; arrays indexed `[k][j][i]` (z, y, x) and
//! flattened as `(k·ny + j)·nx + i` with the extent of each array's own axes:
//! - smoke `s[k][j][i]` at the cell centre `(i+½, j+½, k+½)`: `nx·ny·nz` values;
//! - `u[k][j][i]` at the x-face `(i, j+½, k+½)`, `i = 0..=nx`: `nz·ny·(nx+1)`;
//! - `v[k][j][i]` at the y-face `(i+½, j, k+½)`, `j = 0..=ny`: `nz·(ny+1)·nx`;
//! - `w[k][j][i]` at the z-face `(i+½, j+½, k)`, `k = 0..=nz`: `(nz+1)·ny·nx`.
//!
//! The lattices, their trilinear sampling and the velocity at each point
//! ([`Mac::taps`]) are [`crate::mac`]'s, the same code as in 2D: one rule
//! for the forward step and its adjoint.
//!
//! The step is split where the gradient is split, as in 2D:
//! [`advect_buoyancy`] (explicit, differentiated by Enzyme in diffsim, with
//! the hand-written [`advect_buoyancy_adjoint`] beside it) and [`project`]
//! (a linear solve; its adjoint [`project_adjoint`] is the same solve).

use std::ops::Range;

use crate::boundary::{Boundary, Side};
use crate::mac::{At, Mac};

/// Grid of the 3D smoke problem: `nx × ny × nz` unit cells, the buoyancy
/// coefficient (along +y) of P4's step, the time step and the six sides.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Smoke3d {
    /// Cells along x.
    pub nx: usize,
    /// Cells along y (up).
    pub ny: usize,
    /// Cells along z.
    pub nz: usize,
    /// Buoyancy of the explicit step: `v += buoyancy · (smoke averaged to
    /// the y-face)` (0: none; a scene adds buoyancy as its own effect).
    pub buoyancy: f64,
    /// Time step of the advection, in cells per unit speed (P4: 1).
    pub dt: f64,
    /// The six sides (closed for P4). Check with [`Boundary::<3>::validate`]
    /// before simulating.
    pub boundary: Boundary<3>,
}

impl Smoke3d {
    /// The P4 setting: an `n³` closed box, buoyancy 0.1, unit time step.
    pub fn p4(n: usize) -> Self {
        Self { nx: n, ny: n, nz: n, buoyancy: 0.1, dt: 1.0, boundary: Boundary::<3>::CLOSED }
    }

    /// A closed `nx × ny × nz` box advected with time step `dt`, without
    /// buoyancy in the explicit step.
    pub fn new(nx: usize, ny: usize, nz: usize, dt: f64) -> Self {
        Self { nx, ny, nz, buoyancy: 0.0, dt, boundary: Boundary::<3>::CLOSED }
    }

    /// The same grid with other sides.
    pub fn with_boundary(self, boundary: Boundary<3>) -> Self {
        Self { boundary, ..self }
    }

    /// Whether every side is closed (P4's box).
    pub fn is_closed(&self) -> bool {
        self.boundary == Boundary::<3>::CLOSED
    }

    /// The index rules of this grid's MAC lattices, its axes wrapping where
    /// the sides are periodic.
    pub fn mac(&self) -> Mac<3, [bool; 3]> {
        Mac { n: self.dims(), wrap: self.boundary.wraps() }
    }

    /// Cells along each axis `[nx, ny, nz]`.
    pub fn dims(&self) -> [usize; 3] {
        [self.nx, self.ny, self.nz]
    }

    /// Number of smoke values (cells).
    pub fn n_s(&self) -> usize {
        self.nx * self.ny * self.nz
    }

    /// Extents `[x, y, z]` of the array of faces normal to `axis` (0 x, 1 y,
    /// 2 z): the cells with one more along that axis.
    pub fn face_dims(&self, axis: usize) -> [usize; 3] {
        let d = self.dims();
        [0, 1, 2].map(|a| d[a] + (a == axis) as usize)
    }

    /// Number of faces normal to `axis`.
    pub fn n_face(&self, axis: usize) -> usize {
        self.face_dims(axis).iter().product()
    }

    /// Number of velocities `n_u + n_v + n_w`.
    pub fn n_vel(&self) -> usize {
        self.n_face(0) + self.n_face(1) + self.n_face(2)
    }

    /// Length of the packed state `[s, u, v, w]`.
    pub fn n_state(&self) -> usize {
        self.n_s() + self.n_vel()
    }

    /// Splits a packed state `[s, u, v, w]`.
    pub fn split<'a>(&self, x: &'a [f64]) -> [&'a [f64]; 4] {
        let (s, rest) = x.split_at(self.n_s());
        let (u, rest) = rest.split_at(self.n_face(0));
        let (v, w) = rest.split_at(self.n_face(1));
        [s, u, v, w]
    }

    /// Lengths of slabs `ks` (along z) of `[s, u, v, w]`: `ks.len()` slabs
    /// of each field, and for `w` also its last face slab when `ks` reaches
    /// the top (`ks.end == nz`). Over `0..nz`, the packed state.
    pub fn slab_lens(&self, ks: Range<usize>) -> [usize; 4] {
        let [nx, ny, nz] = self.dims();
        let m = ks.end - ks.start;
        [m * ny * nx, m * ny * (nx + 1), m * (ny + 1) * nx, (m + (ks.end == nz) as usize) * ny * nx]
    }

    /// Where slab `k` of each field starts in the packed state.
    pub fn slab_starts(&self, k: usize) -> [usize; 4] {
        let [nx, ny, _] = self.dims();
        let (ns, nu, nv) = (self.n_s(), self.n_face(0), self.n_face(1));
        [k * ny * nx, ns + k * ny * (nx + 1), ns + nu + k * (ny + 1) * nx, ns + nu + nv + k * ny * nx]
    }

    /// Splits a packed state `[s, u, v, w]`, mutably.
    pub fn split_mut<'a>(&self, x: &'a mut [f64]) -> [&'a mut [f64]; 4] {
        let (s, rest) = x.split_at_mut(self.n_s());
        let (u, rest) = rest.split_at_mut(self.n_face(0));
        let (v, w) = rest.split_at_mut(self.n_face(1));
        [s, u, v, w]
    }
}

mod advect;
mod forces;
mod mic;
mod obstacles;
mod p4;
mod pressure;
mod schemes;
mod sides;

pub use advect::*;
pub use forces::*;
pub use mic::*;
pub use obstacles::*;
pub use p4::*;
pub use pressure::*;
pub use schemes::*;
pub use sides::*;
