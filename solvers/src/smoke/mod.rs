//! 2D incompressible smoke on a MAC grid: semi-Lagrangian, MacCormack and
//! upwind advection of a cell-centred scalar and of a staggered (MAC)
//! velocity, buoyancy, forces, inflow regions, obstacles, the boundary
//! conditions of [`crate::boundary`], and a pressure projection solved by
//! preconditioned conjugate gradients. Benchmark P2 `smoke2d` is the closed
//! box with semi-Lagrangian advection.
//!
//! Conventions (those of P2 in `docs/benchmarks.md`, which has `Nx = Ny = N`):
//! `Nx × Ny` unit cells, x to the right, y up, arrays indexed `[j][i]` (y, x)
//! and flattened row by row.
//! - smoke `s[j][i]` at the cell centre `(i+½, j+½)`: `Nx·Ny` values, index `j·Nx + i`;
//! - `u[j][i]` at the x-face `(i, j+½)`, `i = 0..=Nx`: `Ny·(Nx+1)` values, index `j·(Nx+1) + i`;
//! - `v[j][i]` at the y-face `(i+½, j)`, `j = 0..=Ny`: `(Ny+1)·Nx` values, index `j·Nx + i`.
//!
//! On a periodic axis face `Nx` (`Ny`) is a copy of face `0`: operators never
//! read it and write it as the copy, so the state keeps one layout whatever
//! the boundary.
//!
//! The step is split where the gradient is split: [`advect_buoyancy`] (explicit,
//! differentiated by Enzyme in diffsim) and [`project`] (a linear solve, whose
//! adjoint is the solve with the transposed — here the same — matrix:
//! [`project_adjoint`]).
//!
//! The module in files: this one holds the grid ([`Smoke2d`]), the bilinear
//! sampling of lattices and the MAC grid's index rules that the others share;
//! `advect` the advection schemes and their adjoints, `forces` buoyancy,
//! external forces and inflow, `walls` the velocity boundary conditions and
//! obstacles, `pressure` the divergence, the pressure matrices and the
//! projection's conjugate-gradient solve, `p2` benchmark P2's set-up and
//! reference values.

use crate::boundary::{Boundary, Side, for_each_face};
use crate::grid::{axis_passes, axis_position, beside, lattice_gap, next, own_faces};

/// Grid of the smoke problem: `nx × ny` unit cells, buoyancy coefficient,
/// and the boundary conditions.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Smoke2d {
    /// Cells along x (columns).
    pub nx: usize,
    /// Cells along y (rows).
    pub ny: usize,
    /// Buoyancy: `v += buoyancy · (smoke averaged to the y-face)`.
    pub buoyancy: f64,
    /// The four sides (closed for P2). Check with [`Boundary::validate`]
    /// before simulating.
    pub boundary: Boundary,
}

impl Smoke2d {
    /// The P2 setting (buoyancy 0.1, closed box).
    pub fn p2(n: usize) -> Self {
        Self { nx: n, ny: n, buoyancy: 0.1, boundary: Boundary::CLOSED }
    }

    /// A closed box of `nx × ny` cells without buoyancy.
    pub fn new(nx: usize, ny: usize) -> Self {
        Self { nx, ny, buoyancy: 0.0, boundary: Boundary::CLOSED }
    }

    /// Whether the box is square (`nx = ny`).
    pub fn is_square(&self) -> bool {
        self.nx == self.ny
    }

    /// The same grid with other boundary conditions.
    pub fn with_boundary(self, boundary: Boundary) -> Self {
        Self { boundary, ..self }
    }

    /// Number of smoke values (cells) `Nx·Ny`.
    pub fn n_s(&self) -> usize {
        self.nx * self.ny
    }

    /// Number of x-face velocities `Ny·(Nx+1)`.
    pub fn n_u(&self) -> usize {
        self.ny * (self.nx + 1)
    }

    /// Number of y-face velocities `(Ny+1)·Nx`.
    pub fn n_v(&self) -> usize {
        (self.ny + 1) * self.nx
    }

    /// Number of velocities `n_u + n_v`.
    pub fn n_vel(&self) -> usize {
        self.n_u() + self.n_v()
    }

    /// Length of the packed state `[s, u, v]`: `Nx·Ny + Ny·(Nx+1) + (Ny+1)·Nx`.
    pub fn n_state(&self) -> usize {
        self.n_s() + self.n_vel()
    }

    /// Splits a packed state `[s, u, v]`.
    pub fn split<'a>(&self, x: &'a [f64]) -> (&'a [f64], &'a [f64], &'a [f64]) {
        let (s, rest) = x.split_at(self.n_s());
        let (u, v) = rest.split_at(self.n_u());
        (s, u, v)
    }

    /// Splits a packed state `[s, u, v]`, mutably.
    pub fn split_mut<'a>(&self, x: &'a mut [f64]) -> (&'a mut [f64], &'a mut [f64], &'a mut [f64]) {
        let (s, rest) = x.split_at_mut(self.n_s());
        let (u, v) = rest.split_at_mut(self.n_u());
        (s, u, v)
    }
}

/// A lattice of samples `f[l·stride + k]`, `k < nx`, `l < ny`, sample
/// `(k, l)` at the point `(k + ox, l + oy)`.
#[derive(Clone, Copy, Debug)]
pub struct Lattice {
    /// Distance between rows in the array.
    pub stride: usize,
    /// Samples per row (on a wrapping axis: per period).
    pub nx: usize,
    /// Rows (on a wrapping axis: per period).
    pub ny: usize,
    /// x of sample `(0, 0)`.
    pub ox: f64,
    /// y of sample `(0, 0)`.
    pub oy: f64,
}

/// The four samples around `(px, py)` (row-major corners `c00, c10, c01,
/// c11`) and the fractions `(fx, fy)`.
#[inline(always)]
fn corners<const WX: bool, const WY: bool>(lat: Lattice, px: f64, py: f64) -> ([usize; 4], f64, f64) {
    let (k0, k1, fx) = axis_position::<WX>(lat.nx, px - lat.ox);
    let (l0, l1, fy) = axis_position::<WY>(lat.ny, py - lat.oy);
    let s = lat.stride;
    ([l0 * s + k0, l0 * s + k1, l1 * s + k0, l1 * s + k1], fx, fy)
}

/// Bilinear sample of the lattice `f` at the point `(px, py)`; outside it,
/// positions are clamped to its edge (P2's rule) or wrap on the axes marked
/// `WX`, `WY`.
#[inline(always)]
pub fn sample<const WX: bool, const WY: bool>(f: &[f64], lat: Lattice, px: f64, py: f64) -> f64 {
    let ([c00, c10, c01, c11], fx, fy) = corners::<WX, WY>(lat, px, py);
    f[c00] * (1.0 - fx) * (1.0 - fy) + f[c10] * fx * (1.0 - fy) + f[c01] * (1.0 - fx) * fy + f[c11] * fx * fy
}

/// Adjoint of [`sample`]: adds `g·∂value/∂f` into `gf` and returns
/// `(g·∂value/∂px, g·∂value/∂py)`. The clamp passes derivatives where the
/// position is inside the lattice's range (edges included), as Enzyme's
/// derivative of `f64::clamp` does; a wrap always passes them.
#[inline(always)]
pub fn sample_adjoint<const WX: bool, const WY: bool>(f: &[f64], gf: &mut [f64], lat: Lattice, px: f64, py: f64, g: f64) -> (f64, f64) {
    let (rx, ry) = (px - lat.ox, py - lat.oy);
    let ([c00, c10, c01, c11], fx, fy) = corners::<WX, WY>(lat, px, py);
    gf[c00] += g * (1.0 - fx) * (1.0 - fy);
    gf[c10] += g * fx * (1.0 - fy);
    gf[c01] += g * (1.0 - fx) * fy;
    gf[c11] += g * fx * fy;
    let dfx = (f[c10] - f[c00]) * (1.0 - fy) + (f[c11] - f[c01]) * fy;
    let dfy = (f[c01] - f[c00]) * (1.0 - fx) + (f[c11] - f[c10]) * fx;
    (g * dfx * axis_passes::<WX>(lat.nx, rx), g * dfy * axis_passes::<WY>(lat.ny, ry))
}

/// The smallest and largest of the four lattice values [`sample`] blends
/// at this point.
#[inline(always)]
fn sample_range<const WX: bool, const WY: bool>(f: &[f64], lat: Lattice, px: f64, py: f64) -> (f64, f64) {
    let ([c00, c10, c01, c11], _, _) = corners::<WX, WY>(lat, px, py);
    let a = [f[c00], f[c10], f[c01], f[c11]];
    (a[0].min(a[1]).min(a[2].min(a[3])), a[0].max(a[1]).max(a[2].max(a[3])))
}

/// Index rules of the MAC grid of an `nx × ny` box whose x (y) axis wraps
/// when `WX` (`WY`), written once for the forward operators and their
/// adjoints.
#[derive(Clone, Copy, Debug)]
struct Mac<const WX: bool, const WY: bool> {
    nx: usize,
    ny: usize,
}

impl<const WX: bool, const WY: bool> Mac<WX, WY> {
    /// x-faces per row that hold their own value (`N` when x wraps: face
    /// `N` is a copy).
    #[inline(always)]
    fn nfx(self) -> usize {
        own_faces::<WX>(self.nx)
    }

    /// Rows of y-faces that hold their own value.
    #[inline(always)]
    fn nfy(self) -> usize {
        own_faces::<WY>(self.ny)
    }

    /// The lattice of `at` and the samples per row and rows that hold their
    /// own value.
    #[inline(always)]
    fn lattice(self, at: At) -> (Lattice, usize, usize) {
        match at {
            At::Centre => (self.smoke(), self.nx, self.ny),
            At::UFace => (self.u(), self.nfx(), self.ny),
            At::VFace => (self.v(), self.nx, self.nfy()),
        }
    }

    #[inline(always)]
    fn smoke(self) -> Lattice {
        Lattice { stride: self.nx, nx: self.nx, ny: self.ny, ox: 0.5, oy: 0.5 }
    }

    #[inline(always)]
    fn u(self) -> Lattice {
        Lattice { stride: self.nx + 1, nx: self.nfx(), ny: self.ny, ox: 0.0, oy: 0.5 }
    }

    #[inline(always)]
    fn v(self) -> Lattice {
        Lattice { stride: self.nx, nx: self.nx, ny: self.nfy(), ox: 0.5, oy: 0.0 }
    }

    /// Velocity at the point `(i, j)` of the lattice `at`.
    #[inline(always)]
    fn velocity(self, at: At, u: &[f64], v: &[f64], i: usize, j: usize) -> (f64, f64) {
        match at {
            At::Centre => self.at_centre(u, v, i, j),
            At::UFace => self.at_u(u, v, i, j),
            At::VFace => self.at_v(u, v, i, j),
        }
    }

    /// Velocity at the centre of cell `(i, j)`.
    #[inline(always)]
    fn at_centre(self, u: &[f64], v: &[f64], i: usize, j: usize) -> (f64, f64) {
        let (nx, ny) = (self.nx, self.ny);
        (0.5 * (u[j * (nx + 1) + i] + u[j * (nx + 1) + next::<WX>(nx, i)]), 0.5 * (v[j * nx + i] + v[next::<WY>(ny, j) * nx + i]))
    }

    /// Velocity at x-face `(i, j)`: its own `u`, the four nearest `v`.
    #[inline(always)]
    fn at_u(self, u: &[f64], v: &[f64], i: usize, j: usize) -> (f64, f64) {
        let n = self.nx;
        let (a, b) = beside::<WX>(n, i);
        let up = next::<WY>(self.ny, j);
        (u[j * (n + 1) + i], 0.25 * (v[j * n + a] + v[j * n + b] + v[up * n + a] + v[up * n + b]))
    }

    /// Velocity at y-face `(i, j)`: the four nearest `u`, its own `v`.
    #[inline(always)]
    fn at_v(self, u: &[f64], v: &[f64], i: usize, j: usize) -> (f64, f64) {
        let nu = self.nx + 1;
        let (a, b) = beside::<WY>(self.ny, j);
        let r = next::<WX>(self.nx, i);
        (0.25 * (u[a * nu + i] + u[a * nu + r] + u[b * nu + i] + u[b * nu + r]), v[j * self.nx + i])
    }

    /// Adds `gᵀ·∂(at_centre)/∂(u, v)` into `(gu, gv)`.
    #[inline(always)]
    fn at_centre_adjoint(self, gu: &mut [f64], gv: &mut [f64], i: usize, j: usize, (ga, gb): (f64, f64)) {
        let n = self.nx;
        gu[j * (n + 1) + i] += 0.5 * ga;
        gu[j * (n + 1) + next::<WX>(n, i)] += 0.5 * ga;
        gv[j * n + i] += 0.5 * gb;
        gv[next::<WY>(self.ny, j) * n + i] += 0.5 * gb;
    }

    /// Adds `gᵀ·∂(at_u)/∂(u, v)` into `(gu, gv)`.
    #[inline(always)]
    fn at_u_adjoint(self, gu: &mut [f64], gv: &mut [f64], i: usize, j: usize, (ga, gb): (f64, f64)) {
        let n = self.nx;
        let (a, b) = beside::<WX>(n, i);
        let up = next::<WY>(self.ny, j);
        gu[j * (n + 1) + i] += ga;
        for c in [j * n + a, j * n + b, up * n + a, up * n + b] {
            gv[c] += 0.25 * gb;
        }
    }

    /// Adds `gᵀ·∂(at_v)/∂(u, v)` into `(gu, gv)`.
    #[inline(always)]
    fn at_v_adjoint(self, gu: &mut [f64], gv: &mut [f64], i: usize, j: usize, (ga, gb): (f64, f64)) {
        let nu = self.nx + 1;
        let (a, b) = beside::<WY>(self.ny, j);
        let r = next::<WX>(self.nx, i);
        for c in [a * nu + i, a * nu + r, b * nu + i, b * nu + r] {
            gu[c] += 0.25 * ga;
        }
        gv[j * self.nx + i] += gb;
    }
}

/// The three lattices of the MAC grid.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
enum At {
    /// Cell centres (smoke).
    Centre,
    /// x-faces.
    UFace,
    /// y-faces.
    VFace,
}

/// Calls `$body` with `$mac` bound to the [`Mac`] of the configuration's
/// wrapping axes (four instantiations, one chosen at run time).
macro_rules! with_mac {
    ($cfg:expr, $mac:ident => $body:expr) => {
        match ($cfg.boundary.periodic_x(), $cfg.boundary.periodic_y()) {
            (false, false) => {
                let $mac = Mac::<false, false> { nx: $cfg.nx, ny: $cfg.ny };
                $body
            }
            (true, false) => {
                let $mac = Mac::<true, false> { nx: $cfg.nx, ny: $cfg.ny };
                $body
            }
            (false, true) => {
                let $mac = Mac::<false, true> { nx: $cfg.nx, ny: $cfg.ny };
                $body
            }
            (true, true) => {
                let $mac = Mac::<true, true> { nx: $cfg.nx, ny: $cfg.ny };
                $body
            }
        }
    };
}

/// Element-wise copy. An explicit loop: `copy_from_slice` into part of a
/// buffer Enzyme differentiates has given silently wrong gradients
/// (ENZYME.md).
#[inline(always)]
pub(crate) fn copy(from: &[f64], to: &mut [f64]) {
    for (o, &a) in to.iter_mut().zip(from) {
        *o = a;
    }
}

/// Whether a face lets fluid through: the product of the fluid indicators
/// of the cells beside it (1 without obstacles).
#[inline]
fn open(fluid: Option<&[f64]>, f: &crate::boundary::Face) -> f64 {
    fluid.map_or(1.0, |w| f.lower.map_or(1.0, |c| w[c]) * f.upper.map_or(1.0, |c| w[c]))
}

mod advect;
mod forces;
mod p2;
mod pressure;
mod walls;

pub use advect::*;
pub use forces::*;
pub use p2::*;
pub use pressure::*;
pub use walls::*;
