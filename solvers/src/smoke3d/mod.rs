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
//! The per-axis rules (where a sample falls, which cells lie beside a
//! face) are [`crate::grid`]'s, shared with 2D: trilinear weights are the
//! product of three axes' linear weights, as bilinear ones are of two.
//! Every velocity a trace needs is the mean of four faces of one component
//! ([`Mac3::taps`]): one rule for the forward step and its adjoint.
//!
//! The step is split where the gradient is split, as in 2D:
//! [`advect_buoyancy`] (explicit, differentiated by Enzyme in diffsim, with
//! the hand-written [`advect_buoyancy_adjoint`] beside it) and [`project`]
//! (a linear solve; its adjoint [`project_adjoint`] is the same solve).

use std::ops::Range;

use crate::boundary::{Boundary3, Side};
use crate::grid::{beside, lattice_gap, next, own_faces, passes, position};

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
    /// The six sides (closed for P4). Check with [`Boundary3::validate`]
    /// before simulating.
    pub boundary: Boundary3,
}

impl Smoke3d {
    /// The P4 setting: an `n³` closed box, buoyancy 0.1, unit time step.
    pub fn p4(n: usize) -> Self {
        Self { nx: n, ny: n, nz: n, buoyancy: 0.1, dt: 1.0, boundary: Boundary3::CLOSED }
    }

    /// A closed `nx × ny × nz` box advected with time step `dt`, without
    /// buoyancy in the explicit step.
    pub fn new(nx: usize, ny: usize, nz: usize, dt: f64) -> Self {
        Self { nx, ny, nz, buoyancy: 0.0, dt, boundary: Boundary3::CLOSED }
    }

    /// The same grid with other sides.
    pub fn with_boundary(self, boundary: Boundary3) -> Self {
        Self { boundary, ..self }
    }

    /// Whether every side is closed (P4's box).
    pub fn is_closed(&self) -> bool {
        self.boundary == Boundary3::CLOSED
    }

    /// The index rules of this grid's MAC lattices, its axes wrapping where
    /// the sides are periodic.
    pub fn mac(&self) -> Mac3<[bool; 3]> {
        Mac3 { n: self.dims(), wrap: self.boundary.wraps() }
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

/// A 3D lattice of samples `f[(l·sy + m)·sx + k]`, sample `(k, m, l)` at the
/// point `(k + o[0], m + o[1], l + o[2])`; `n` samples per axis hold their
/// own value (on a wrapping axis: per period).
#[derive(Clone, Copy, Debug)]
pub struct Lattice3 {
    /// Samples per row in the array.
    pub sx: usize,
    /// Rows per slab in the array.
    pub sy: usize,
    /// Samples per axis.
    pub n: [usize; 3],
    /// Position of sample `(0, 0, 0)`.
    pub o: [f64; 3],
}

/// The eight samples around `p` (x fastest) and the fractions along each axis.
#[inline(always)]
fn corners3(wrap: [bool; 3], lat: Lattice3, p: [f64; 3]) -> ([usize; 8], [f64; 3]) {
    let (i0, i1, fx) = position(wrap[0], lat.n[0], p[0] - lat.o[0]);
    let (j0, j1, fy) = position(wrap[1], lat.n[1], p[1] - lat.o[1]);
    let (k0, k1, fz) = position(wrap[2], lat.n[2], p[2] - lat.o[2]);
    let (sx, sy) = (lat.sx, lat.sy);
    let (r00, r10, r01, r11) = ((k0 * sy + j0) * sx, (k0 * sy + j1) * sx, (k1 * sy + j0) * sx, (k1 * sy + j1) * sx);
    ([r00 + i0, r00 + i1, r10 + i0, r10 + i1, r01 + i0, r01 + i1, r11 + i0, r11 + i1], [fx, fy, fz])
}

/// Trilinear sample of the lattice `f` at `p`; outside it, positions are
/// clamped to its edge per axis (P4's rule) or wrap on the axes marked in
/// `wrap` (x, y, z).
#[inline(always)]
pub fn sample3(wrap: [bool; 3], f: &[f64], lat: Lattice3, p: [f64; 3]) -> f64 {
    let (c, [fx, fy, fz]) = corners3(wrap, lat, p);
    let (gx, gy, gz) = (1.0 - fx, 1.0 - fy, 1.0 - fz);
    let lo = (f[c[0]] * gx + f[c[1]] * fx) * gy + (f[c[2]] * gx + f[c[3]] * fx) * fy;
    let hi = (f[c[4]] * gx + f[c[5]] * fx) * gy + (f[c[6]] * gx + f[c[7]] * fx) * fy;
    lo * gz + hi * fz
}

/// The smallest and largest of the eight samples [`sample3`] blends at `p`
/// (MacCormack's limiter clamps to them).
#[inline(always)]
pub fn sample3_range(wrap: [bool; 3], f: &[f64], lat: Lattice3, p: [f64; 3]) -> (f64, f64) {
    let (c, _) = corners3(wrap, lat, p);
    let mut lo = f[c[0]];
    let mut hi = lo;
    for &k in &c[1..] {
        lo = lo.min(f[k]);
        hi = hi.max(f[k]);
    }
    (lo, hi)
}

/// The eight samples [`sample3`] blends at `p`, x fastest.
#[inline(always)]
pub fn sample3_corners(wrap: [bool; 3], lat: Lattice3, p: [f64; 3]) -> [usize; 8] {
    corners3(wrap, lat, p).0
}

/// Adjoint of [`sample3`]: adds `g·∂value/∂f` into `gf` and returns
/// `g·∂value/∂p`; the clamp passes derivatives as
/// [`crate::grid::axis_passes`] says.
#[inline(always)]
pub fn sample3_adjoint(wrap: [bool; 3], f: &[f64], gf: &mut [f64], lat: Lattice3, p: [f64; 3], g: f64) -> [f64; 3] {
    let (c, [fx, fy, fz]) = corners3(wrap, lat, p);
    let (gx, gy, gz) = (1.0 - fx, 1.0 - fy, 1.0 - fz);
    let w = [gx * gy * gz, fx * gy * gz, gx * fy * gz, fx * fy * gz, gx * gy * fz, fx * gy * fz, gx * fy * fz, fx * fy * fz];
    for (&c, &w) in c.iter().zip(&w) {
        gf[c] += g * w;
    }
    let v = c.map(|c| f[c]);
    // Differences along each axis, blended over the other two.
    let dx = ((v[1] - v[0]) * gy + (v[3] - v[2]) * fy) * gz + ((v[5] - v[4]) * gy + (v[7] - v[6]) * fy) * fz;
    let dy = ((v[2] - v[0]) * gx + (v[3] - v[1]) * fx) * gz + ((v[6] - v[4]) * gx + (v[7] - v[5]) * fx) * fz;
    let dz = ((v[4] - v[0]) * gx + (v[5] - v[1]) * fx) * gy + ((v[6] - v[2]) * gx + (v[7] - v[3]) * fx) * fy;
    [
        g * dx * passes(wrap[0], lat.n[0], p[0] - lat.o[0]),
        g * dy * passes(wrap[1], lat.n[1], p[1] - lat.o[1]),
        g * dz * passes(wrap[2], lat.n[2], p[2] - lat.o[2]),
    ]
}

/// The four lattices of the 3D MAC grid: cell centres, and the faces
/// normal to x, y and z.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum At3 {
    /// Cell centres (smoke).
    Centre,
    /// x-faces (`u`).
    U,
    /// y-faces (`v`).
    V,
    /// z-faces (`w`).
    W,
}

impl At3 {
    /// The axis the lattice's faces are normal to (3 for the centres).
    #[inline(always)]
    fn axis(self) -> usize {
        match self {
            At3::U => 0,
            At3::V => 1,
            At3::W => 2,
            At3::Centre => 3,
        }
    }
}

/// Which axes of a 3D grid wrap: [`Bounded`] (none, known when compiling:
/// P4's closed box, whose loops then carry no test) or `[bool; 3]` (known
/// at run time: any boundary).
pub trait Wraps: Copy + Send + Sync {
    /// Whether x, y and z wrap.
    fn wraps(self) -> [bool; 3];
}

/// No axis wraps (every side bounded).
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq)]
pub struct Bounded;

impl Wraps for Bounded {
    #[inline(always)]
    fn wraps(self) -> [bool; 3] {
        [false; 3]
    }
}

impl Wraps for [bool; 3] {
    #[inline(always)]
    fn wraps(self) -> [bool; 3] {
        self
    }
}

/// Index rules of the MAC grid of an `nx × ny × nz` box whose axes wrap
/// as `wrap` says, written once for the forward operators and their
/// adjoints.
#[derive(Clone, Copy, Debug)]
pub struct Mac3<W: Wraps = Bounded> {
    /// Cells per axis.
    pub n: [usize; 3],
    /// The axes that wrap.
    pub wrap: W,
}

impl Mac3<Bounded> {
    /// The closed box of `n` cells per axis.
    pub fn bounded(n: [usize; 3]) -> Self {
        Self { n, wrap: Bounded }
    }
}

impl<W: Wraps> Mac3<W> {
    /// Which axes wrap.
    #[inline(always)]
    pub fn wraps(self) -> [bool; 3] {
        self.wrap.wraps()
    }

    /// The cell after `k` along `axis`.
    #[inline(always)]
    fn next(self, axis: usize, k: usize) -> usize {
        if self.wraps()[axis] { next::<true>(self.n[axis], k) } else { next::<false>(self.n[axis], k) }
    }

    /// The two cells beside face `k` of `axis`.
    #[inline(always)]
    fn beside(self, axis: usize, k: usize) -> (usize, usize) {
        if self.wraps()[axis] { beside::<true>(self.n[axis], k) } else { beside::<false>(self.n[axis], k) }
    }

    /// The lattice of `at`: array extents, own samples and origin.
    #[inline(always)]
    pub fn lattice(self, at: At3) -> Lattice3 {
        let a = at.axis();
        let w = self.wraps();
        let own = [0, 1, 2].map(|b| if w[b] { own_faces::<true>(self.n[b]) } else { own_faces::<false>(self.n[b]) });
        let ext = |b: usize| self.n[b] + (a == b) as usize;
        let pick = |b: usize| if a == b { own[b] } else { self.n[b] };
        let org = |b: usize| if a == b { 0.0 } else { 0.5 };
        Lattice3 { sx: ext(0), sy: ext(1), n: [pick(0), pick(1), pick(2)], o: [org(0), org(1), org(2)] }
    }

    /// Flat index of `(i, j, k)` in the array of component `b` (0 u, 1 v, 2 w).
    #[inline(always)]
    fn index(self, b: usize, [i, j, k]: [usize; 3]) -> usize {
        let (sx, sy) = (self.n[0] + (b == 0) as usize, self.n[1] + (b == 1) as usize);
        (k * sy + j) * sx + i
    }

    /// The four faces of component `b` whose mean is the velocity `b` at
    /// point `q` of the lattice `at`: at a centre, the two faces of the cell
    /// along `b` (each twice); on faces of axis `b`, the face itself (four
    /// times); on faces of another axis `a`, the faces of the two cells
    /// beside `q` along `a` (the edge-extended copy on a bounded axis) at
    /// `q` and the next position along `b` (P4's four nearest faces).
    #[inline(always)]
    pub fn taps(self, at: At3, b: usize, q: [usize; 3]) -> [usize; 4] {
        let a = at.axis();
        if a == b {
            let c = self.index(b, q);
            return [c; 4];
        }
        let (b0, b1) = (q[b], self.next(b, q[b]));
        // The other varying axis: `a` on a face lattice; any third axis (left
        // fixed) at a centre.
        let (axis, (a0, a1)) = if a < 3 { (a, self.beside(a, q[a])) } else { ((b + 1) % 3, (q[(b + 1) % 3], q[(b + 1) % 3])) };
        let at_ = |x: usize, y: usize| {
            let mut p = q;
            p[axis] = x;
            p[b] = y;
            self.index(b, p)
        };
        [at_(a0, b0), at_(a1, b0), at_(a0, b1), at_(a1, b1)]
    }

    /// The velocity at point `q` of the lattice `at`.
    #[inline(always)]
    pub fn velocity(self, at: At3, [u, v, w]: [&[f64]; 3], q: [usize; 3]) -> [f64; 3] {
        let mean = |f: &[f64], t: [usize; 4]| 0.25 * ((f[t[0]] + f[t[1]]) + (f[t[2]] + f[t[3]]));
        [mean(u, self.taps(at, 0, q)), mean(v, self.taps(at, 1, q)), mean(w, self.taps(at, 2, q))]
    }

    /// Adds `gᵀ·∂(velocity)/∂(u, v, w)` into `(gu, gv, gw)`.
    #[inline(always)]
    pub fn velocity_adjoint(self, at: At3, [gu, gv, gw]: [&mut [f64]; 3], q: [usize; 3], g: [f64; 3]) {
        for t in self.taps(at, 0, q) {
            gu[t] += 0.25 * g[0];
        }
        for t in self.taps(at, 1, q) {
            gv[t] += 0.25 * g[1];
        }
        for t in self.taps(at, 2, q) {
            gw[t] += 0.25 * g[2];
        }
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
