//! 2D incompressible smoke on a MAC grid: semi-Lagrangian, MacCormack and
//! upwind advection of a cell-centred scalar and of a staggered (MAC)
//! velocity, buoyancy, forces, inflow regions, obstacles, the boundary
//! conditions of [`crate::boundary`], and a pressure projection solved by
//! preconditioned conjugate gradients. Benchmark P2 `smoke2d` is the closed
//! box with semi-Lagrangian advection.
//!
//! Conventions (those of P2 in `benchmarks.md`, which has `Nx = Ny = N`):
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

use std::fmt;

use crate::boundary::{Boundary, Side, for_each_face};

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

/// Where a coordinate `r` (in samples) falls on an axis of `m` samples: the
/// two samples it lies between and the fraction past the first. Clamped to
/// the axis (P2's rule; the lower sample kept one short of the last) or,
/// when `WRAP`, wrapped around the period `m`.
#[inline(always)]
fn axis_position<const WRAP: bool>(m: usize, r: f64) -> (usize, usize, f64) {
    if WRAP {
        let mf = m as f64;
        let r = r - mf * (r / mf).floor();
        let k0 = (r as usize).min(m - 1);
        (k0, if k0 + 1 == m { 0 } else { k0 + 1 }, r - k0 as f64)
    } else {
        let g = r.clamp(0.0, (m - 1) as f64);
        // g ≥ 0, so truncation is the floor (one instruction, no libm call).
        let k0 = (g as usize).min(m - 2);
        (k0, k0 + 1, g - k0 as f64)
    }
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
    let inside = |wrap: bool, r: f64, m: usize| if wrap || (r >= 0.0 && r <= (m - 1) as f64) { 1.0 } else { 0.0 };
    (g * dfx * inside(WX, rx, lat.nx), g * dfy * inside(WY, ry, lat.ny))
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
        if WX { self.nx } else { self.nx + 1 }
    }

    /// Rows of y-faces that hold their own value.
    #[inline(always)]
    fn nfy(self) -> usize {
        if WY { self.ny } else { self.ny + 1 }
    }

    /// The cell (column or row) after cell `k` along a wrapping or bounded
    /// axis of `n` cells: `k + 1`, or `0` past the last cell of a wrapping
    /// axis.
    #[inline(always)]
    fn next<const WRAP: bool>(n: usize, k: usize) -> usize {
        if WRAP && k + 1 == n { 0 } else { k + 1 }
    }

    /// The two cells beside face `k` of an axis of `n` cells: wrapped, or
    /// clamped to the box (the edge-extended copy of P2).
    #[inline(always)]
    fn beside<const WRAP: bool>(n: usize, k: usize) -> (usize, usize) {
        if WRAP { (if k == 0 { n - 1 } else { k - 1 }, k) } else { (k.saturating_sub(1).min(n - 1), k.min(n - 1)) }
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
        (0.5 * (u[j * (nx + 1) + i] + u[j * (nx + 1) + Self::next::<WX>(nx, i)]), 0.5 * (v[j * nx + i] + v[Self::next::<WY>(ny, j) * nx + i]))
    }

    /// Velocity at x-face `(i, j)`: its own `u`, the four nearest `v`.
    #[inline(always)]
    fn at_u(self, u: &[f64], v: &[f64], i: usize, j: usize) -> (f64, f64) {
        let n = self.nx;
        let (a, b) = Self::beside::<WX>(n, i);
        let up = Self::next::<WY>(self.ny, j);
        (u[j * (n + 1) + i], 0.25 * (v[j * n + a] + v[j * n + b] + v[up * n + a] + v[up * n + b]))
    }

    /// Velocity at y-face `(i, j)`: the four nearest `u`, its own `v`.
    #[inline(always)]
    fn at_v(self, u: &[f64], v: &[f64], i: usize, j: usize) -> (f64, f64) {
        let nu = self.nx + 1;
        let (a, b) = Self::beside::<WY>(self.ny, j);
        let r = Self::next::<WX>(self.nx, i);
        (0.25 * (u[a * nu + i] + u[a * nu + r] + u[b * nu + i] + u[b * nu + r]), v[j * self.nx + i])
    }

    /// Adds `gᵀ·∂(at_centre)/∂(u, v)` into `(gu, gv)`.
    #[inline(always)]
    fn at_centre_adjoint(self, gu: &mut [f64], gv: &mut [f64], i: usize, j: usize, (ga, gb): (f64, f64)) {
        let n = self.nx;
        gu[j * (n + 1) + i] += 0.5 * ga;
        gu[j * (n + 1) + Self::next::<WX>(n, i)] += 0.5 * ga;
        gv[j * n + i] += 0.5 * gb;
        gv[Self::next::<WY>(self.ny, j) * n + i] += 0.5 * gb;
    }

    /// Adds `gᵀ·∂(at_u)/∂(u, v)` into `(gu, gv)`.
    #[inline(always)]
    fn at_u_adjoint(self, gu: &mut [f64], gv: &mut [f64], i: usize, j: usize, (ga, gb): (f64, f64)) {
        let n = self.nx;
        let (a, b) = Self::beside::<WX>(n, i);
        let up = Self::next::<WY>(self.ny, j);
        gu[j * (n + 1) + i] += ga;
        for c in [j * n + a, j * n + b, up * n + a, up * n + b] {
            gv[c] += 0.25 * gb;
        }
    }

    /// Adds `gᵀ·∂(at_v)/∂(u, v)` into `(gu, gv)`.
    #[inline(always)]
    fn at_v_adjoint(self, gu: &mut [f64], gv: &mut [f64], i: usize, j: usize, (ga, gb): (f64, f64)) {
        let nu = self.nx + 1;
        let (a, b) = Self::beside::<WY>(self.ny, j);
        let r = Self::next::<WX>(self.nx, i);
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

/// Advection scheme.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Scheme {
    /// One backward trace, bilinear sample (first order).
    SemiLagrangian,
    /// A backward trace, a forward trace from its result, half the
    /// difference as a correction (second order). With `limiter`, each value
    /// is clamped to the range of the four samples the backward trace blended
    /// (Selle et al. 2008): no new extrema, first order at extrema.
    MacCormack {
        /// Clamp to the local range.
        limiter: bool,
    },
}

/// Points of a lattice traced along the velocity `(u, v)`: `out[l·stride + k]
/// = f(p − sdt·vel)` for `k < kx`, `l < ly`, `p` the point of sample
/// `(k, l)` of the lattice `at` and `vel` the velocity there. (The velocity
/// is looked up by an enum, not a closure: Enzyme cannot type a closure's
/// returned pair when the closure is not inlined.)
#[inline(always)]
#[allow(clippy::too_many_arguments)]
fn trace<const WX: bool, const WY: bool>(mac: Mac<WX, WY>, at: At, (u, v): (&[f64], &[f64]), f: &[f64], sdt: f64, out: &mut [f64]) {
    let (lat, kx, ly) = mac.lattice(at);
    for l in 0..ly {
        for k in 0..kx {
            let (a, b) = mac.velocity(at, u, v, k, l);
            out[l * lat.stride + k] = sample::<WX, WY>(f, lat, k as f64 + lat.ox - sdt * a, l as f64 + lat.oy - sdt * b);
        }
    }
}

/// One field on the lattice `at` advected by `scheme`; `hat` and `tilde`
/// are scratch of `f`'s length (MacCormack only).
#[inline(always)]
#[allow(clippy::too_many_arguments)]
fn advect_field<const WX: bool, const WY: bool>(
    mac: Mac<WX, WY>,
    at: At,
    scheme: Scheme,
    dt: f64,
    uv: (&[f64], &[f64]),
    f: &[f64],
    out: &mut [f64],
    hat: &mut [f64],
    tilde: &mut [f64],
) {
    match scheme {
        Scheme::SemiLagrangian => trace(mac, at, uv, f, dt, out),
        Scheme::MacCormack { limiter } => {
            trace(mac, at, uv, f, dt, hat);
            trace(mac, at, uv, hat, -dt, tilde);
            let (lat, kx, ly) = mac.lattice(at);
            for l in 0..ly {
                for k in 0..kx {
                    let c = l * lat.stride + k;
                    let mut val = hat[c] + 0.5 * (f[c] - tilde[c]);
                    if limiter {
                        let (a, b) = mac.velocity(at, uv.0, uv.1, k, l);
                        let (lo, hi) = sample_range::<WX, WY>(f, lat, k as f64 + lat.ox - dt * a, l as f64 + lat.oy - dt * b);
                        val = val.clamp(lo, hi);
                    }
                    out[c] = val;
                }
            }
        }
    }
}

/// Advection over a time step `dt` of the smoke (if `smoke`) and of the
/// velocity by itself (if `velocity`), each sampled back along the velocity
/// at its own points (the other component averaged from the four nearest
/// faces); then the velocity boundary conditions. Fields not advected are
/// copied. Reads `x = [s, u, v]`, overwrites `y`. `scratch` holds
/// [`advect_scratch_len`] values (none for semi-Lagrangian).
///
/// # Panics
/// If a length is wrong or a side has fewer than 2 cells.
#[allow(clippy::too_many_arguments)]
pub fn advect(cfg: &Smoke2d, scheme: Scheme, dt: f64, smoke: bool, velocity: bool, x: &[f64], y: &mut [f64], scratch: &mut [f64]) {
    assert!(cfg.nx.min(cfg.ny) >= 2 && x.len() == cfg.n_state() && y.len() == cfg.n_state(), "smoke: state lengths");
    assert!(scratch.len() >= advect_scratch_len(cfg, scheme), "smoke: advection scratch");
    with_mac!(cfg, mac => advect_on(mac, scheme, dt, smoke, velocity, x, y, scratch));
    if velocity {
        let (_, u2, v2) = cfg.split_mut(y);
        enforce_boundary(cfg, u2, v2);
    }
}

#[inline(always)]
#[allow(clippy::too_many_arguments)]
fn advect_on<const WX: bool, const WY: bool>(
    mac: Mac<WX, WY>,
    scheme: Scheme,
    dt: f64,
    smoke: bool,
    velocity: bool,
    x: &[f64],
    y: &mut [f64],
    scratch: &mut [f64],
) {
    let (ns, nu) = (mac.nx * mac.ny, mac.ny * (mac.nx + 1));
    let (s, rest) = x.split_at(ns);
    let (u, v) = rest.split_at(nu);
    let (s2, rest) = y.split_at_mut(ns);
    let (u2, v2) = rest.split_at_mut(nu);
    // Each field's scratch: the first values of each half (none for
    // semi-Lagrangian).
    let half = scratch.len() / 2;
    let (hat, tilde) = scratch.split_at_mut(half);
    let (ks, ku, kv) = (ns.min(half), nu.min(half), v.len().min(half));
    if smoke {
        advect_field(mac, At::Centre, scheme, dt, (u, v), s, s2, &mut hat[..ks], &mut tilde[..ks]);
    } else {
        copy(s, s2);
    }
    if velocity {
        advect_field(mac, At::UFace, scheme, dt, (u, v), u, u2, &mut hat[..ku], &mut tilde[..ku]);
        advect_field(mac, At::VFace, scheme, dt, (u, v), v, v2, &mut hat[..kv], &mut tilde[..kv]);
    } else {
        copy(u, u2);
        copy(v, v2);
    }
}

/// Scratch [`advect`] needs: for MacCormack two fields of the largest
/// component's size (`2·max(n_u, n_v)`), none for semi-Lagrangian.
pub fn advect_scratch_len(cfg: &Smoke2d, scheme: Scheme) -> usize {
    match scheme {
        Scheme::SemiLagrangian => 0,
        Scheme::MacCormack { .. } => 2 * cfg.n_u().max(cfg.n_v()),
    }
}

/// Element-wise copy. An explicit loop: `copy_from_slice` into part of a
/// buffer Enzyme differentiates has given silently wrong gradients
/// (ENZYME.md).
#[inline(always)]
fn copy(from: &[f64], to: &mut [f64]) {
    for (o, &a) in to.iter_mut().zip(from) {
        *o = a;
    }
}

/// The velocity boundary conditions, in place: closed sides' faces 0,
/// inflow sides' faces the profile (inward), outflow faces as they are,
/// and on periodic axes face `N` the copy of face `0`.
pub fn enforce_boundary(cfg: &Smoke2d, u: &mut [f64], v: &mut [f64]) {
    let (nx, ny) = (cfg.nx, cfg.ny);
    let nu = nx + 1;
    let b = &cfg.boundary;
    // Position along the side, 0..1: a profile spans the whole side.
    let t = |k: usize, n: usize| (k as f64 + 0.5) / n as f64;
    for j in 0..ny {
        match b.left {
            Side::Closed => u[j * nu] = 0.0,
            Side::Inflow(p) => u[j * nu] = p.at(t(j, ny)),
            Side::Periodic | Side::Outflow => {}
        }
        match b.right {
            Side::Closed => u[j * nu + nx] = 0.0,
            Side::Inflow(p) => u[j * nu + nx] = -p.at(t(j, ny)),
            Side::Periodic => u[j * nu + nx] = u[j * nu],
            Side::Outflow => {}
        }
    }
    let top = ny * nx;
    for i in 0..nx {
        match b.bottom {
            Side::Closed => v[i] = 0.0,
            Side::Inflow(p) => v[i] = p.at(t(i, nx)),
            Side::Periodic | Side::Outflow => {}
        }
        match b.top {
            Side::Closed => v[top + i] = 0.0,
            Side::Inflow(p) => v[top + i] = -p.at(t(i, nx)),
            Side::Periodic => v[top + i] = v[i],
            Side::Outflow => {}
        }
    }
}

/// The linear part of [`enforce_boundary`] (inflow faces set to 0, not to
/// the profile), for tangents: closed and inflow faces 0, periodic copies.
pub fn enforce_boundary_linear(cfg: &Smoke2d, u: &mut [f64], v: &mut [f64]) {
    let homogeneous = |s: Side| if let Side::Inflow(_) = s { Side::Closed } else { s };
    let b = cfg.boundary;
    let linear = Boundary { left: homogeneous(b.left), right: homogeneous(b.right), bottom: homogeneous(b.bottom), top: homogeneous(b.top) };
    enforce_boundary(&cfg.with_boundary(linear), u, v);
}

/// Adjoint of [`enforce_boundary`] (of its linear part) on the velocity
/// adjoint, in place: set faces pass nothing back, copies pass theirs to the
/// original.
pub fn enforce_boundary_adjoint(cfg: &Smoke2d, gu: &mut [f64], gv: &mut [f64]) {
    let (nx, ny) = (cfg.nx, cfg.ny);
    let nu = nx + 1;
    let b = &cfg.boundary;
    for j in 0..ny {
        if let Side::Periodic = b.right {
            gu[j * nu] += gu[j * nu + nx];
            gu[j * nu + nx] = 0.0;
        }
        if let Side::Closed | Side::Inflow(_) = b.left {
            gu[j * nu] = 0.0;
        }
        if let Side::Closed | Side::Inflow(_) = b.right {
            gu[j * nu + nx] = 0.0;
        }
    }
    let top = ny * nx;
    for i in 0..nx {
        if let Side::Periodic = b.top {
            gv[i] += gv[top + i];
            gv[top + i] = 0.0;
        }
        if let Side::Closed | Side::Inflow(_) = b.bottom {
            gv[i] = 0.0;
        }
        if let Side::Closed | Side::Inflow(_) = b.top {
            gv[top + i] = 0.0;
        }
    }
}

/// Buoyancy, in place: `v += coefficient · (smoke averaged to the y-face)`
/// on the interior y-faces and, when y wraps, on face row `0` (whose copy,
/// row `Ny`, follows).
pub fn add_buoyancy(cfg: &Smoke2d, coefficient: f64, s: &[f64], v: &mut [f64]) {
    let (n, ny) = (cfg.nx, cfg.ny);
    for j in 1..ny {
        for i in 0..n {
            v[j * n + i] += coefficient * 0.5 * (s[(j - 1) * n + i] + s[j * n + i]);
        }
    }
    if cfg.boundary.periodic_y() {
        for i in 0..n {
            v[i] += coefficient * 0.5 * (s[(ny - 1) * n + i] + s[i]);
            v[ny * n + i] = v[i];
        }
    }
}

/// [`add_buoyancy`] as a map of packed states: `y = x` with
/// `v += coefficient · (smoke averaged to the y-face)`.
pub fn apply_buoyancy(cfg: &Smoke2d, coefficient: f64, x: &[f64], y: &mut [f64]) {
    assert!(x.len() == cfg.n_state() && y.len() == cfg.n_state(), "smoke: state lengths");
    copy(x, y);
    let (s, _, _) = cfg.split(x);
    let (_, _, v2) = cfg.split_mut(y);
    add_buoyancy(cfg, coefficient, s, v2);
}

/// Steps 1–4 of P2, for any boundary: semi-Lagrangian advection of smoke and
/// velocity (unit time step), buoyancy, the velocity boundary conditions.
/// Reads the packed state `x = [s, u, v]`, overwrites `y = [s', u', v']`
/// (the velocity not yet divergence-free).
///
/// # Panics
/// If `x` or `y` is not of length [`Smoke2d::n_state`] or a side has fewer
/// than 2 cells.
pub fn advect_buoyancy(cfg: &Smoke2d, x: &[f64], y: &mut [f64]) {
    advect(cfg, Scheme::SemiLagrangian, 1.0, true, true, x, y, &mut []);
    // Buoyancy touches no closed, inflow or outflow face and refreshes its
    // own periodic copies, so the boundary conditions of `advect` still hold.
    let (s2, _, v2) = cfg.split_mut(y);
    add_buoyancy(cfg, cfg.buoyancy, s2, v2);
}

/// Hand-written adjoint of [`advect_buoyancy`]: `gx += Jᵀ·gy` at the state
/// `x` (accumulates into `gx`; `gy` is used as scratch and left
/// unspecified). The reference for Enzyme's generated adjoint.
pub fn advect_buoyancy_adjoint(cfg: &Smoke2d, x: &[f64], gy: &mut [f64], gx: &mut [f64]) {
    let (n, ny) = (cfg.nx, cfg.ny);
    assert!(n.min(ny) >= 2 && x.len() == cfg.n_state() && gy.len() == cfg.n_state() && gx.len() == cfg.n_state(), "smoke: state lengths");
    let (s, u, v) = cfg.split(x);
    let (gs2, gu2, gv2) = cfg.split_mut(gy);
    let (gs, gu, gv) = cfg.split_mut(gx);
    // Buoyancy (its own periodic copy came after its addition).
    if cfg.boundary.periodic_y() {
        for i in 0..n {
            gv2[i] += gv2[ny * n + i];
            gv2[ny * n + i] = 0.0;
            let b = cfg.buoyancy * 0.5 * gv2[i];
            gs2[(ny - 1) * n + i] += b;
            gs2[i] += b;
        }
    }
    for j in 1..ny {
        for i in 0..n {
            let b = cfg.buoyancy * 0.5 * gv2[j * n + i];
            gs2[(j - 1) * n + i] += b;
            gs2[j * n + i] += b;
        }
    }
    enforce_boundary_adjoint(cfg, gu2, gv2);
    with_mac!(cfg, mac => semi_lagrangian_adjoint(mac, s, u, v, gs2, gu2, gv2, gs, gu, gv));
}

/// Adjoint of the semi-Lagrangian advection of smoke and velocity (unit
/// time step): adds `Jᵀ·g₂` into `(gs, gu, gv)`.
#[allow(clippy::too_many_arguments)]
fn semi_lagrangian_adjoint<const WX: bool, const WY: bool>(
    mac: Mac<WX, WY>,
    s: &[f64],
    u: &[f64],
    v: &[f64],
    gs2: &[f64],
    gu2: &[f64],
    gv2: &[f64],
    gs: &mut [f64],
    gu: &mut [f64],
    gv: &mut [f64],
) {
    let (n, ny) = (mac.nx, mac.ny);
    for j in 0..mac.nfy() {
        for i in 0..n {
            let (ub, vv) = mac.at_v(u, v, i, j);
            let (dpx, dpy) = sample_adjoint::<WX, WY>(v, gv, mac.v(), i as f64 + 0.5 - ub, j as f64 - vv, gv2[j * n + i]);
            mac.at_v_adjoint(gu, gv, i, j, (-dpx, -dpy));
        }
    }
    for j in 0..ny {
        for i in 0..mac.nfx() {
            let (uu, vb) = mac.at_u(u, v, i, j);
            let (dpx, dpy) = sample_adjoint::<WX, WY>(u, gu, mac.u(), i as f64 - uu, j as f64 + 0.5 - vb, gu2[j * (n + 1) + i]);
            mac.at_u_adjoint(gu, gv, i, j, (-dpx, -dpy));
        }
    }
    for j in 0..ny {
        for i in 0..n {
            let (uc, vc) = mac.at_centre(u, v, i, j);
            let (dpx, dpy) = sample_adjoint::<WX, WY>(s, gs, mac.smoke(), i as f64 + 0.5 - uc, j as f64 + 0.5 - vc, gs2[j * n + i]);
            mac.at_centre_adjoint(gu, gv, i, j, (-dpx, -dpy));
        }
    }
}

/// Divergence of a MAC velocity, `d[c] = Σ` outward flux over the faces
/// of cell `c` (overwrites `d`): `u[j][i+1] − u[j][i] + v[j+1][i] − v[j][i]`
/// inside the box; a periodic axis's face `N` is not read (face `0` wraps).
pub fn divergence(cfg: &Smoke2d, u: &[f64], v: &[f64], d: &mut [f64]) {
    d.fill(0.0);
    for (axis, vel) in [u, v].into_iter().enumerate() {
        for_each_face(cfg.nx, cfg.ny, &cfg.boundary, axis, |f| {
            let w = vel[f.index];
            if let Some(c) = f.lower {
                d[c] += w;
            }
            if let Some(c) = f.upper {
                d[c] -= w;
            }
        });
    }
}

/// Transpose of [`divergence`]: `(u, v) += Dᵀ·d` (accumulates).
pub fn divergence_transpose(cfg: &Smoke2d, d: &[f64], u: &mut [f64], v: &mut [f64]) {
    for (axis, vel) in [u, v].into_iter().enumerate() {
        for_each_face(cfg.nx, cfg.ny, &cfg.boundary, axis, |f| vel[f.index] += f.lower.map_or(0.0, |c| d[c]) - f.upper.map_or(0.0, |c| d[c]));
    }
}

/// Whether a face lets fluid through: the product of the fluid indicators
/// of the cells beside it (1 without obstacles).
#[inline]
fn open(fluid: Option<&[f64]>, f: &crate::boundary::Face) -> f64 {
    fluid.map_or(1.0, |w| f.lower.map_or(1.0, |c| w[c]) * f.upper.map_or(1.0, |c| w[c]))
}

/// The pressure matrix of the closed `nx × ny` box (`nx ≥ 2`): `(A·p)[c] =
/// Σ_{neighbours m of c inside the box} (p[c] − p[m])` (overwrites `out`).
/// Symmetric positive semi-definite, constants in its null space. Row by
/// row, branch-free inside each row, so that it vectorises.
#[inline(always)]
pub fn apply_pressure_matrix(nx: usize, ny: usize, p: &[f64], out: &mut [f64]) {
    let n = nx;
    for j in 0..ny {
        let row = &p[j * n..(j + 1) * n];
        let dn = (j > 0).then(|| &p[(j - 1) * n..j * n]);
        let up = (j + 1 < ny).then(|| &p[(j + 1) * n..(j + 2) * n]);
        let o = &mut out[j * n..(j + 1) * n];
        // The two end cells, with their neighbour count.
        for i in [0, n - 1] {
            let mut acc = 0.0;
            if i > 0 {
                acc += row[i] - row[i - 1];
            }
            if i + 1 < n {
                acc += row[i] - row[i + 1];
            }
            if let Some(d) = dn {
                acc += row[i] - d[i];
            }
            if let Some(u) = up {
                acc += row[i] - u[i];
            }
            o[i] = acc;
        }
        // The rest of the row in one pass over five streams.
        let (l, c, r) = (&row[..n - 2], &row[1..n - 1], &row[2..]);
        let o = &mut o[1..n - 1];
        match (dn, up) {
            (Some(d), Some(u)) => {
                for (((((o, &l), &c), &r), &d), &u) in o.iter_mut().zip(l).zip(c).zip(r).zip(&d[1..n - 1]).zip(&u[1..n - 1]) {
                    *o = 4.0 * c - l - r - d - u;
                }
            }
            (Some(v), None) | (None, Some(v)) => {
                for ((((o, &l), &c), &r), &v) in o.iter_mut().zip(l).zip(c).zip(r).zip(&v[1..n - 1]) {
                    *o = 3.0 * c - l - r - v;
                }
            }
            (None, None) => {
                for (((o, &l), &c), &r) in o.iter_mut().zip(l).zip(c).zip(r) {
                    *o = 2.0 * c - l - r;
                }
            }
        }
    }
}

/// The pressure matrix for any [`Boundary`] and solid cells (`w[c] = 0`;
/// `None`: no solids): `out[c] = w_c·Σ_m w_m·(p_c − p_m) + (1 − w_c)·p_c`
/// over the neighbours `m` across the cell's faces that the projection
/// changes (interior, wrapped across a periodic side, and a ghost `p = 0`
/// across an outflow side); closed and inflow sides add nothing (Neumann).
/// Only fluid–fluid faces couple; solid rows are the identity. Symmetric.
pub fn apply_boundary_matrix(nx: usize, ny: usize, b: &Boundary, w: Option<&[f64]>, p: &[f64], out: &mut [f64]) {
    let wt = |c: usize| w.map_or(1.0, |w| w[c]);
    let n = nx;
    for j in 0..ny {
        for i in 0..n {
            let c = j * n + i;
            let pc = p[c];
            let mut acc = 0.0;
            // Each direction: the neighbour inside, or what the side does.
            let mut across = |inside: bool, m: usize, side: Side, wrapped: usize| {
                if inside {
                    acc += wt(m) * (pc - p[m]);
                } else {
                    match side {
                        Side::Periodic => acc += wt(wrapped) * (pc - p[wrapped]),
                        Side::Outflow => acc += pc,
                        Side::Closed | Side::Inflow(_) => {}
                    }
                }
            };
            across(i > 0, c.wrapping_sub(1), b.left, c + n - 1);
            across(i + 1 < n, c + 1, b.right, (c + 1).wrapping_sub(n));
            across(j > 0, c.wrapping_sub(n), b.bottom, c + n * (ny - 1));
            across(j + 1 < ny, c + n, b.top, i);
            out[c] = wt(c) * acc + (1.0 - wt(c)) * pc;
        }
    }
}

/// Zeroes the smoke in solid cells and the velocity on every face that
/// touches a solid cell, in place on a packed state: the obstacle boundary
/// condition. Linear and self-adjoint (a diagonal 0/1 mask), so the same
/// call is its own VJP.
pub fn apply_obstacle_mask(cfg: &Smoke2d, fluid: &[f64], x: &mut [f64]) {
    let (s, u, v) = cfg.split_mut(x);
    for (sv, &w) in s.iter_mut().zip(fluid) {
        *sv *= w;
    }
    for (axis, vel) in [u, v].into_iter().enumerate() {
        for_each_face(cfg.nx, cfg.ny, &cfg.boundary, axis, |f| {
            let o = open(Some(fluid), &f);
            vel[f.index] *= o;
            if let Some(k) = f.copy {
                vel[k] *= o;
            }
        });
    }
}

/// A pressure solve that did not converge.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct NoConvergence {
    /// Iterations done.
    pub iterations: usize,
    /// Final true residual norm relative to `‖b‖`.
    pub relative_residual: f64,
    /// The relative tolerance asked for.
    pub tolerance: f64,
}

impl fmt::Display for NoConvergence {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        write!(
            f,
            "pressure solve did not converge: relative residual {:.3e} after {} iterations (tolerance {:.1e})",
            self.relative_residual, self.iterations, self.tolerance
        )
    }
}

impl std::error::Error for NoConvergence {}

/// Preconditioner of the pressure solve.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Preconditioner {
    /// None: plain conjugate gradients.
    None,
    /// Modified incomplete Cholesky, MIC(0), with the usual safety factor
    /// (Bridson, *Fluid Simulation for Computer Graphics*, §5).
    Mic0,
    /// One geometric multigrid V-cycle ([`crate::multigrid`]).
    Multigrid,
}

impl fmt::Display for Preconditioner {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        f.write_str(match self {
            Preconditioner::None => "none",
            Preconditioner::Mic0 => "mic0",
            Preconditioner::Multigrid => "multigrid",
        })
    }
}

/// Conjugate gradients on the pressure matrix of an `nx × ny` box, with
/// reusable work buffers and the preconditioner factor computed once. The
/// closed square box without obstacles (P2, [`PressureSolver::new`]) has a
/// fused, vectorised matrix product and a choice of preconditioners; other
/// boundaries, obstacles and rectangles ([`PressureSolver::general`]) use
/// the general matrix [`apply_boundary_matrix`] with MIC(0) built for it.
#[derive(Clone, Debug)]
pub struct PressureSolver {
    nx: usize,
    ny: usize,
    /// Relative tolerance on the true residual, `‖b − A·p‖ ≤ tol·‖b‖`.
    pub tolerance: f64,
    /// More iterations than this is an error.
    pub max_iterations: usize,
    precond: Preconditioner,
    /// MIC(0) inverse diagonal.
    inv_diag: Vec<f64>,
    /// The general matrix's coefficients (`None` for the closed square
    /// box's special path).
    coeffs: Option<Coefficients>,
    mg: Option<crate::multigrid::Multigrid>,
    /// Fluid indicator per cell (1 fluid, 0 solid) when there are obstacles.
    fluid: Option<Vec<f64>>,
    boundary: Boundary,
    r: Vec<f64>,
    z: Vec<f64>,
    d: Vec<f64>,
    q: Vec<f64>,
}

impl PressureSolver {
    /// A solver for the `n × n` box with tolerance `tolerance`, at most
    /// `max_iterations` iterations, and the given preconditioner.
    pub fn new(n: usize, tolerance: f64, max_iterations: usize, precond: Preconditioner) -> Self {
        let mut inv_diag = vec![0.0; n * n];
        if precond == Preconditioner::Mic0 {
            // Bridson's MIC(0) for the 5-point matrix with unit off-diagonals.
            const TAU: f64 = 0.97;
            const SIGMA: f64 = 0.25;
            let diag = |i: usize, j: usize| ((i > 0) as usize + (i + 1 < n) as usize + (j > 0) as usize + (j + 1 < n) as usize) as f64;
            for j in 0..n {
                for i in 0..n {
                    let c = j * n + i;
                    let mut e = diag(i, j);
                    if i > 0 {
                        let (a, pc) = (-1.0, inv_diag[c - 1]);
                        let ay_left = if j + 1 < n { -1.0 } else { 0.0 };
                        e -= (a * pc) * (a * pc) + TAU * (a * ay_left * pc * pc);
                    }
                    if j > 0 {
                        let (a, pc) = (-1.0, inv_diag[c - n]);
                        let ax_below = if i + 1 < n { -1.0 } else { 0.0 };
                        e -= (a * pc) * (a * pc) + TAU * (a * ax_below * pc * pc);
                    }
                    if e < SIGMA * diag(i, j) {
                        e = diag(i, j);
                    }
                    inv_diag[c] = 1.0 / e.sqrt();
                }
            }
        }
        let z = vec![0.0; n * n];
        let mg = (precond == Preconditioner::Multigrid).then(|| crate::multigrid::Multigrid::new(n));
        Self {
            nx: n,
            ny: n,
            tolerance,
            max_iterations,
            precond,
            inv_diag,
            coeffs: None,
            mg,
            fluid: None,
            boundary: Boundary::CLOSED,
            r: z.clone(),
            z: z.clone(),
            d: z.clone(),
            q: z,
        }
    }

    /// A solver for an `nx × ny` box with any boundary and solid cells
    /// where `fluid[c] = 0` (`None`: no solids): the matrix of
    /// [`apply_boundary_matrix`], CG preconditioned by MIC(0) of that
    /// matrix (couplings across a periodic side left out of the factor).
    pub fn general(nx: usize, ny: usize, boundary: Boundary, tolerance: f64, max_iterations: usize, fluid: Option<Vec<f64>>) -> Self {
        let nn = nx * ny;
        if let Some(w) = &fluid {
            assert_eq!(w.len(), nn, "fluid mask length");
        }
        let z = vec![0.0; nn];
        let mut s = Self {
            nx,
            ny,
            tolerance,
            max_iterations,
            precond: Preconditioner::Mic0,
            inv_diag: z.clone(),
            coeffs: None,
            mg: None,
            fluid,
            boundary,
            r: z.clone(),
            z: z.clone(),
            d: z.clone(),
            q: z,
        };
        s.factor_general();
        s
    }

    /// MIC(0) of the general matrix (Bridson, §5, with its couplings):
    /// diagonal and couplings read off [`apply_boundary_matrix`] applied to
    /// unit vectors' closed forms.
    fn factor_general(&mut self) {
        const TAU: f64 = 0.97;
        const SIGMA: f64 = 0.25;
        let (nx, ny, b) = (self.nx, self.ny, self.boundary);
        let w = |c: usize| self.fluid.as_ref().map_or(1.0, |w| w[c]);
        let mut k = Coefficients { diag: vec![0.0; nx * ny], ax: vec![0.0; nx * ny], ay: vec![0.0; nx * ny], wraps: b.periodic_x() || b.periodic_y() };
        for j in 0..ny {
            for i in 0..nx {
                let c = j * nx + i;
                // What each side adds to the diagonal: a neighbour's fluid
                // weight, 1 for the ghost of an outflow side, 0 for a wall.
                let side = |inside: bool, m: usize, s: Side, wrapped: usize| {
                    if inside {
                        w(m)
                    } else {
                        match s {
                            Side::Periodic => w(wrapped),
                            Side::Outflow => 1.0,
                            Side::Closed | Side::Inflow(_) => 0.0,
                        }
                    }
                };
                let sum = side(i > 0, c.wrapping_sub(1), b.left, c + nx - 1)
                    + side(i + 1 < nx, c + 1, b.right, (c + 1).wrapping_sub(nx))
                    + side(j > 0, c.wrapping_sub(nx), b.bottom, c + nx * (ny - 1))
                    + side(j + 1 < ny, c + nx, b.top, i);
                k.diag[c] = w(c) * sum + (1.0 - w(c));
                k.ax[c] = if i + 1 < nx { -w(c) * w(c + 1) } else { 0.0 };
                k.ay[c] = if j + 1 < ny { -w(c) * w(c + nx) } else { 0.0 };
            }
        }
        let pc = &mut self.inv_diag;
        for c in 0..nx * ny {
            let mut e = k.diag[c];
            // `ax` is 0 at the end of a row, so the left neighbour of a
            // row's first cell contributes nothing.
            if c > 0 {
                let (ax, ay, p) = (k.ax[c - 1], k.ay[c - 1], pc[c - 1]);
                e -= (ax * p) * (ax * p) + TAU * ax * ay * p * p;
            }
            if c >= nx {
                let (ay, ax, p) = (k.ay[c - nx], k.ax[c - nx], pc[c - nx]);
                e -= (ay * p) * (ay * p) + TAU * ay * ax * p * p;
            }
            if e < SIGMA * k.diag[c] {
                e = k.diag[c];
            }
            // A cell coupled to nothing (walled in): leave its residual as is.
            pc[c] = if e > 0.0 { 1.0 / e.sqrt() } else { 1.0 };
        }
        self.coeffs = Some(k);
    }

    /// `out = A·p` with the general matrix: the coefficient form when no
    /// side wraps, else [`apply_boundary_matrix`].
    fn apply_general(&self, p: &[f64], out: &mut [f64]) {
        match &self.coeffs {
            Some(k) if !k.wraps => apply_coefficients(self.nx, &k.diag, &k.ax, &k.ay, p, out),
            _ => apply_boundary_matrix(self.nx, self.ny, &self.boundary, self.fluid.as_deref(), p, out),
        }
    }

    /// The fluid indicator, when there are obstacles.
    pub fn fluid(&self) -> Option<&[f64]> {
        self.fluid.as_deref()
    }

    /// The preconditioner in use.
    pub fn preconditioner(&self) -> Preconditioner {
        self.precond
    }

    /// `z = M⁻¹·r` (MIC(0): forward then backward substitution).
    fn precondition(&mut self) {
        let n = self.nx;
        match self.precond {
            Preconditioner::None => self.z.copy_from_slice(&self.r),
            Preconditioner::Mic0 if self.coeffs.is_some() => {
                let k = self.coeffs.as_ref().expect("coefficients");
                mic0_general(self.nx, &k.ax, &k.ay, &self.inv_diag, &self.r, &mut self.z)
            }
            Preconditioner::Mic0 => mic0_apply(n, &self.inv_diag, &self.r, &mut self.z),
            Preconditioner::Multigrid => self.mg.as_mut().expect("multigrid hierarchy").apply(&self.r, &mut self.z),
        }
    }

    /// Solves `A·p = b` from `p = 0` until `‖b − A·p‖₂ ≤ tol·‖b‖₂` (true
    /// residual); overwrites `p`. Without an outflow side the matrix is
    /// singular and `b` must sum to zero over the fluid (the compatibility
    /// condition); it is projected onto that space to remove rounding, and
    /// the solution returned is the one with zero mean on the fluid.
    /// Returns the number of iterations.
    pub fn solve(&mut self, b: &[f64], p: &mut [f64]) -> Result<usize, NoConvergence> {
        let (nx, ny) = (self.nx, self.ny);
        let nn = nx * ny;
        // Remove the component along the null vector (constant on the fluid).
        let (total, count) = match &self.fluid {
            None => (b.iter().sum::<f64>(), nn as f64),
            Some(w) => (b.iter().zip(w).map(|(b, w)| b * w).sum::<f64>(), w.iter().sum::<f64>()),
        };
        let mean = if self.boundary.has_outflow() { 0.0 } else { total / count.max(1.0) };
        let special = self.fluid.is_none() && self.boundary == Boundary::CLOSED && nx >= 2;
        // The right-hand side minus its mean on the fluid cells.
        let fluid_mean = |c: usize, fluid: &Option<Vec<f64>>| mean * fluid.as_ref().map_or(1.0, |w| w[c]);
        for (c, (r, &bv)) in self.r.iter_mut().zip(b).enumerate() {
            *r = bv - fluid_mean(c, &self.fluid);
        }
        p.fill(0.0);
        let bnorm = dot(&self.r, &self.r).sqrt();
        if bnorm == 0.0 {
            return Ok(0);
        }
        let target = self.tolerance * bnorm;
        let plain = self.precond == Preconditioner::None;
        let mut rz = self.restart();
        let mut rr = dot(&self.r, &self.r);
        let mut it = 0;
        loop {
            if rr.sqrt() <= target {
                // Confirm on the true residual; restart from it if needed.
                if special {
                    apply_pressure_matrix(nx, ny, p, &mut self.q);
                } else {
                    let mut q = std::mem::take(&mut self.q);
                    self.apply_general(p, &mut q);
                    self.q = q;
                }
                for (c, ((q, &bv), r)) in self.q.iter().zip(b).zip(self.r.iter_mut()).enumerate() {
                    *r = bv - fluid_mean(c, &self.fluid) - q;
                }
                rr = dot(&self.r, &self.r);
                if rr.sqrt() <= target {
                    if !self.boundary.has_outflow() {
                        self.remove_null_component(p);
                    }
                    return Ok(it);
                }
                rz = self.restart();
            }
            if it >= self.max_iterations || !rr.is_finite() {
                return Err(NoConvergence { iterations: it, relative_residual: rr.sqrt() / bnorm, tolerance: self.tolerance });
            }
            let mut dq = 0.0;
            if special {
                matvec_dot(nx, ny, &self.d, &mut self.q, &mut dq);
            } else {
                let mut q = std::mem::take(&mut self.q);
                self.apply_general(&self.d, &mut q);
                self.q = q;
                dq = dot(&self.d, &self.q);
            }
            let alpha = rz / dq;
            update(alpha, &self.d, &self.q, p, &mut self.r, &mut rr);
            let rz_new = if plain {
                rr
            } else {
                self.precondition();
                dot(&self.r, &self.z)
            };
            let beta = rz_new / rz;
            rz = rz_new;
            direction(beta, if plain { &self.r } else { &self.z }, &mut self.d);
            it += 1;
        }
    }

    /// Removes the component of `p` along the null vector (constant on the
    /// fluid): the solution becomes the pseudo-inverse's, whatever the
    /// preconditioner added along the null space. The velocity does not
    /// see the constant, but the projection's adjoint does (through faces
    /// on walls and solids), so forward and adjoint must agree on it.
    fn remove_null_component(&self, p: &mut [f64]) {
        match &self.fluid {
            None => {
                let mean = p.iter().sum::<f64>() / p.len().max(1) as f64;
                p.iter_mut().for_each(|v| *v -= mean);
            }
            Some(w) => {
                let count = w.iter().sum::<f64>().max(1.0);
                let mean = p.iter().zip(w).map(|(p, w)| p * w).sum::<f64>() / count;
                p.iter_mut().zip(w).for_each(|(v, w)| *v -= mean * w);
            }
        }
    }

    /// `d = M⁻¹·r`; returns `r·M⁻¹·r`.
    fn restart(&mut self) -> f64 {
        self.precondition();
        self.d.copy_from_slice(&self.z);
        dot(&self.r, &self.z)
    }
}

crate::simd_dispatch! {
    /// `q = A·d` and `*dq = d·q` in one pass.
    fn matvec_dot(nx: usize, ny: usize, d: &[f64], q: &mut [f64], dq: &mut f64) => matvec_dot_body
}

#[inline(always)]
fn matvec_dot_body(nx: usize, ny: usize, d: &[f64], q: &mut [f64], dq: &mut f64) {
    apply_pressure_matrix(nx, ny, d, q);
    *dq = dot(d, q);
}

crate::simd_dispatch! {
    /// `p += α·d`, `r −= α·q`, `*rr = r·r` in one pass.
    fn update(alpha: f64, d: &[f64], q: &[f64], p: &mut [f64], r: &mut [f64], rr: &mut f64) => update_body
}

#[inline(always)]
fn update_body(alpha: f64, d: &[f64], q: &[f64], p: &mut [f64], r: &mut [f64], rr: &mut f64) {
    let mut acc = [0.0f64; 8];
    let mut tail = 0.0;
    let (mut pc, mut rc) = (p.chunks_exact_mut(8), r.chunks_exact_mut(8));
    let (mut dc, mut qc) = (d.chunks_exact(8), q.chunks_exact(8));
    for (((pv, rv), dv), qv) in (&mut pc).zip(&mut rc).zip(&mut dc).zip(&mut qc) {
        for l in 0..8 {
            pv[l] += alpha * dv[l];
            rv[l] -= alpha * qv[l];
            acc[l] += rv[l] * rv[l];
        }
    }
    for (((pv, rv), dv), qv) in pc.into_remainder().iter_mut().zip(rc.into_remainder().iter_mut()).zip(dc.remainder()).zip(qc.remainder()) {
        *pv += alpha * dv;
        *rv -= alpha * qv;
        tail += *rv * *rv;
    }
    *rr = acc.iter().sum::<f64>() + tail;
}

crate::simd_dispatch! {
    /// `d = z + β·d`.
    fn direction(beta: f64, z: &[f64], d: &mut [f64]) => direction_body
}

#[inline(always)]
fn direction_body(beta: f64, z: &[f64], d: &mut [f64]) {
    for (dv, &zv) in d.iter_mut().zip(z) {
        *dv = zv + beta * *dv;
    }
}

/// `z = (L·Lᵀ)⁻¹·r` for the MIC(0) factor `L` with inverse diagonal `pc`:
/// forward then backward substitution. Each cell depends on its left and
/// lower (right and upper) neighbour, so the sweeps run along anti-diagonals
/// `i + j = k`, whose cells are independent of each other: no dependency
/// chain between consecutive operations, unlike the row-by-row order.
fn mic0_apply(n: usize, pc: &[f64], r: &[f64], z: &mut [f64]) {
    for k in 0..2 * n - 1 {
        for i in k.saturating_sub(n - 1)..=k.min(n - 1) {
            let c = (k - i) * n + i;
            let mut t = r[c];
            if i > 0 {
                t += z[c - 1] * pc[c - 1];
            }
            if k - i > 0 {
                t += z[c - n] * pc[c - n];
            }
            z[c] = t * pc[c];
        }
    }
    for k in (0..2 * n - 1).rev() {
        for i in k.saturating_sub(n - 1)..=k.min(n - 1) {
            let c = (k - i) * n + i;
            let mut t = z[c];
            if i + 1 < n {
                t += z[c + 1] * pc[c];
            }
            if k - i + 1 < n {
                t += z[c + n] * pc[c];
            }
            z[c] = t * pc[c];
        }
    }
}

/// The general pressure matrix in coefficient form: `(A·p)[c] =
/// diag[c]·p[c] + ax[c]·p[c+1] + ax[c−1]·p[c−1] + ay[c]·p[c+nx] +
/// ay[c−nx]·p[c−nx]`, with `ax[c] = A[c][c+1]` (0 at the end of a row) and
/// `ay[c] = A[c][c+nx]` (0 on the top row). Couplings across a periodic side
/// are not in it (`wraps`: the matrix has some).
#[derive(Clone, Debug)]
struct Coefficients {
    diag: Vec<f64>,
    ax: Vec<f64>,
    ay: Vec<f64>,
    wraps: bool,
}

crate::simd_dispatch! {
    /// `out = A·p` from the coefficients: five shifted streams, each a
    /// branch-free loop.
    fn apply_coefficients(nx: usize, diag: &[f64], ax: &[f64], ay: &[f64], p: &[f64], out: &mut [f64]) => apply_coefficients_body
}

#[inline(always)]
fn apply_coefficients_body(nx: usize, diag: &[f64], ax: &[f64], ay: &[f64], p: &[f64], out: &mut [f64]) {
    let n = p.len();
    for ((o, &d), &v) in out.iter_mut().zip(diag).zip(p) {
        *o = d * v;
    }
    let m = n.saturating_sub(1);
    for ((o, &a), &v) in out[..m].iter_mut().zip(&ax[..m]).zip(&p[1..]) {
        *o += a * v;
    }
    for ((o, &a), &v) in out[1..].iter_mut().zip(&ax[..m]).zip(&p[..m]) {
        *o += a * v;
    }
    let m = n.saturating_sub(nx);
    for ((o, &a), &v) in out[..m].iter_mut().zip(&ay[..m]).zip(&p[nx..]) {
        *o += a * v;
    }
    for ((o, &a), &v) in out[nx..].iter_mut().zip(&ay[..m]).zip(&p[..m]) {
        *o += a * v;
    }
}

/// `z = (L·Lᵀ)⁻¹·r` for the general MIC(0) factor (couplings `ax`, `ay` of
/// [`Coefficients`], inverse diagonal `pc`): forward then backward
/// substitution in row order (`ax` is 0 at the end of a row, so no test for
/// the row's edge is needed). Anti-diagonal order (as in [`mic0_apply`]) and
/// bands of rows in a skewed wavefront measured slower at 256 × 128.
fn mic0_general(nx: usize, ax: &[f64], ay: &[f64], pc: &[f64], r: &[f64], z: &mut [f64]) {
    let n = r.len();
    for c in 0..n {
        let mut t = r[c];
        if c > 0 {
            t -= ax[c - 1] * pc[c - 1] * z[c - 1];
        }
        if c >= nx {
            t -= ay[c - nx] * pc[c - nx] * z[c - nx];
        }
        z[c] = t * pc[c];
    }
    for c in (0..n).rev() {
        let mut t = z[c];
        if c + 1 < n {
            t -= ax[c] * pc[c] * z[c + 1];
        }
        if c + nx < n {
            t -= ay[c] * pc[c] * z[c + nx];
        }
        z[c] = t * pc[c];
    }
}

/// Dot product with eight independent partial sums (vectorises; a fixed
/// summation order, so results do not depend on the machine).
#[inline(always)]
fn dot(a: &[f64], b: &[f64]) -> f64 {
    let mut acc = [0.0f64; 8];
    let (ca, cb) = (a.chunks_exact(8), b.chunks_exact(8));
    let tail: f64 = ca.remainder().iter().zip(cb.remainder()).map(|(x, y)| x * y).sum();
    for (x, y) in ca.zip(cb) {
        for k in 0..8 {
            acc[k] += x[k] * y[k];
        }
    }
    acc.iter().sum::<f64>() + tail
}

/// Scratch of the projection: divergence and pressure.
#[derive(Clone, Debug)]
pub struct ProjectScratch {
    d: Vec<f64>,
    p: Vec<f64>,
}

impl ProjectScratch {
    /// Scratch for a box of `cells` cells.
    pub fn new(cells: usize) -> Self {
        Self { d: vec![0.0; cells], p: vec![0.0; cells] }
    }
}

/// Step 5 of P2, for any boundary, in place on the velocity part of the
/// packed state `y`: `d = D·(u, v)`, solve `A·p = −W·d` (`W` the fluid
/// mask), `(u, v) −= G·p` on the faces the projection changes (interior,
/// periodic, outflow; fluid–fluid only), periodic copies refreshed. The
/// solver must be built for `cfg`'s boundary. Returns the CG iterations.
pub fn project(cfg: &Smoke2d, y: &mut [f64], solver: &mut PressureSolver, scratch: &mut ProjectScratch) -> Result<usize, NoConvergence> {
    debug_assert_eq!(solver.boundary, cfg.boundary, "pressure solver built for another boundary");
    let (_, u, v) = cfg.split_mut(y);
    divergence(cfg, u, v, &mut scratch.d);
    for d in scratch.d.iter_mut() {
        *d = -*d;
    }
    if let Some(w) = solver.fluid() {
        for (d, &wv) in scratch.d.iter_mut().zip(w) {
            *d *= wv;
        }
    }
    let iterations = solver.solve(&scratch.d, &mut scratch.p)?;
    let (p, fluid) = (&scratch.p, solver.fluid());
    for (axis, vel) in [u, v].into_iter().enumerate() {
        for_each_face(cfg.nx, cfg.ny, &cfg.boundary, axis, |f| {
            if f.projected {
                let grad = f.upper.map_or(0.0, |c| p[c]) - f.lower.map_or(0.0, |c| p[c]);
                vel[f.index] -= open(fluid, &f) * grad;
                if let Some(k) = f.copy {
                    vel[k] = vel[f.index];
                }
            }
        });
    }
    Ok(iterations)
}

/// Adjoint of [`project`] (a linear map), in place on the velocity part of
/// the adjoint `g`: periodic copies handed to their originals;
/// `λ_p = −Gᵀ·λ`; solve `A·μ = λ_p` (the transposed system — `A` is
/// symmetric — to the same tolerance; never a backward pass through the
/// iterations); since the solve's right-hand side was `−W·D·(u, v)`,
/// `λ_(u,v) += −Dᵀ·W·μ`. Returns the CG iterations.
pub fn project_adjoint(cfg: &Smoke2d, g: &mut [f64], solver: &mut PressureSolver, scratch: &mut ProjectScratch) -> Result<usize, NoConvergence> {
    let (_, gu, gv) = cfg.split_mut(g);
    let lp = &mut scratch.d;
    lp.fill(0.0);
    for (axis, gvel) in [&mut *gu, &mut *gv].into_iter().enumerate() {
        for_each_face(cfg.nx, cfg.ny, &cfg.boundary, axis, |f| {
            if !f.projected {
                return;
            }
            if let Some(k) = f.copy {
                gvel[f.index] += gvel[k];
                gvel[k] = 0.0;
            }
            let l = open(solver.fluid(), &f) * gvel[f.index];
            if let Some(c) = f.upper {
                lp[c] -= l;
            }
            if let Some(c) = f.lower {
                lp[c] += l;
            }
        });
    }
    let iterations = solver.solve(lp, &mut scratch.p)?;
    for (c, m) in scratch.p.iter_mut().enumerate() {
        *m = -*m * solver.fluid().map_or(1.0, |w| w[c]);
    }
    divergence_transpose(cfg, &scratch.p, gu, gv);
    Ok(iterations)
}

/// P2's initial state: zero velocity, smoke 1 in every cell whose centre lies
/// within `N/8` of `(N/2, N/4)`, packed as `[s, u, v]`.
pub fn p2_initial(cfg: &Smoke2d) -> Vec<f64> {
    let mut x = vec![0.0; cfg.n_state()];
    x[..cfg.n_s()].copy_from_slice(&disc(cfg.nx, 0.25));
    x
}

/// P2's target smoke: the same disc centred at `(N/2, 3N/4)`.
pub fn p2_target(cfg: &Smoke2d) -> Vec<f64> {
    disc(cfg.nx, 0.75)
}

fn disc(n: usize, cy: f64) -> Vec<f64> {
    let nf = n as f64;
    let mut s = vec![0.0; n * n];
    for j in 0..n {
        for i in 0..n {
            let (dx, dy) = (i as f64 + 0.5 - nf / 2.0, j as f64 + 0.5 - cy * nf);
            if dx * dx + dy * dy <= (nf / 8.0) * (nf / 8.0) {
                s[j * n + i] = 1.0;
            }
        }
    }
    s
}

/// P2 loss `L = ½·Σ (s_T − s*)²` on the smoke part of the packed state;
/// writes `∂L/∂x` (zero on the velocity part) into `grad` (overwrites).
pub fn p2_loss(cfg: &Smoke2d, x: &[f64], target: &[f64], grad: &mut [f64]) -> f64 {
    grad.fill(0.0);
    let mut sum = 0.0;
    for ((g, &s), &t) in grad.iter_mut().zip(&x[..cfg.n_s()]).zip(target) {
        let d = s - t;
        sum += d * d;
        *g = d;
    }
    0.5 * sum
}

/// Reference values of one P2 size (JAX, float64; `benchmarks.md`).
#[derive(Clone, Copy, Debug)]
pub struct P2Reference {
    /// Cells per side.
    pub n: usize,
    /// Steps.
    pub steps: usize,
    /// Loss.
    pub loss: f64,
    /// ‖∇L‖₂.
    pub grad_l2: f64,
    /// ∂L/∂s at flat index 0.
    pub grad_0: f64,
    /// ∂L/∂s at flat index N²/2.
    pub grad_n2: f64,
}

/// The two P2 sizes with their reference values.
pub const P2_SIZES: [P2Reference; 2] = [
    P2Reference { n: 64, steps: 20, loss: 183.8917448743, grad_l2: 18.18088488397, grad_0: 1.37382956e-4, grad_n2: -3.78117637e-3 },
    P2Reference { n: 128, steps: 20, loss: 768.1330262886, grad_l2: 38.36607301311, grad_0: 1.88809603e-5, grad_n2: -1.54349595e-3 },
];

/// First-order upwind advection of the smoke by the MAC velocity, in
/// conservative (flux) form over one time step `dt`: through every interior
/// face, across periodic sides, and through inflow and outflow sides (with
/// smoke-free fluid outside); none through closed sides. Reads
/// `x = [s, u, v]`, writes `y = [s', u, v]`.
pub fn advect_upwind(cfg: &Smoke2d, dt: f64, x: &[f64], y: &mut [f64]) {
    let (n, ny) = (cfg.nx, cfg.ny);
    assert!(n.min(ny) >= 2 && x.len() == cfg.n_state() && y.len() == cfg.n_state(), "smoke: state lengths");
    let (s, u, v) = cfg.split(x);
    let nu = n + 1;
    let (s2, rest) = y.split_at_mut(cfg.n_s());
    copy(s, s2);
    // Interior x-faces: flux from cell (i−1, j) to (i, j).
    for j in 0..ny {
        for i in 1..n {
            upwind_flux(s, s2, dt * u[j * nu + i], Some(j * n + i - 1), Some(j * n + i));
        }
    }
    // Interior y-faces: flux from cell (i, j−1) to (i, j).
    for j in 1..ny {
        for i in 0..n {
            upwind_flux(s, s2, dt * v[j * n + i], Some((j - 1) * n + i), Some(j * n + i));
        }
    }
    // The sides: wrap, or exchange with the smoke-free outside.
    let b = &cfg.boundary;
    for k in 0..ny {
        match b.left {
            Side::Periodic => upwind_flux(s, s2, dt * u[k * nu], Some(k * n + n - 1), Some(k * n)),
            Side::Inflow(_) | Side::Outflow => upwind_flux(s, s2, dt * u[k * nu], None, Some(k * n)),
            Side::Closed => {}
        }
        if let Side::Inflow(_) | Side::Outflow = b.right {
            upwind_flux(s, s2, dt * u[k * nu + n], Some(k * n + n - 1), None);
        }
    }
    for k in 0..n {
        match b.bottom {
            Side::Periodic => upwind_flux(s, s2, dt * v[k], Some((ny - 1) * n + k), Some(k)),
            Side::Inflow(_) | Side::Outflow => upwind_flux(s, s2, dt * v[k], None, Some(k)),
            Side::Closed => {}
        }
        if let Side::Inflow(_) | Side::Outflow = b.top {
            upwind_flux(s, s2, dt * v[ny * n + k], Some((ny - 1) * n + k), None);
        }
    }
    copy(&x[cfg.n_s()..], rest);
}

/// The upwind flux `c·s_upwind` (`c` = velocity·dt) from cell `lower` to
/// cell `upper` (`None`: outside, where the smoke is 0).
#[inline(always)]
fn upwind_flux(s: &[f64], s2: &mut [f64], c: f64, lower: Option<usize>, upper: Option<usize>) {
    let from = if c > 0.0 { lower } else { upper };
    let f = c * from.map_or(0.0, |k| s[k]);
    if let Some(k) = lower {
        s2[k] -= f;
    }
    if let Some(k) = upper {
        s2[k] += f;
    }
}

/// Distance to the nearest upwind switch of [`advect_upwind`] along `d`: the
/// smallest `|u_f / d_f|` over the faces that carry flux.
pub fn upwind_radius(cfg: &Smoke2d, x: &[f64], d: &[f64]) -> f64 {
    let (_, u, v) = cfg.split(x);
    let (_, du, dv) = cfg.split(d);
    let mut r = f64::INFINITY;
    for (axis, (vel, dvel)) in [(u, du), (v, dv)].into_iter().enumerate() {
        for_each_face(cfg.nx, cfg.ny, &cfg.boundary, axis, |f| {
            if f.side != Some(Side::Closed) && dvel[f.index] != 0.0 {
                r = r.min((vel[f.index] / dvel[f.index]).abs());
            }
        });
    }
    r
}

/// An external force over a time step `dt`: `[s, u, v] ↦ [s, u + dt·fu,
/// v + dt·fv]`, with the force `f = [fu, fv]` given per face (the velocity
/// layout, [`Smoke2d::n_vel`] values), on the interior faces and the faces
/// that wrap across a periodic side (copies refreshed); the faces on other
/// sides keep their velocity.
pub fn apply_force(cfg: &Smoke2d, dt: f64, x: &[f64], f: &[f64], y: &mut [f64]) {
    let (n, ny) = (cfg.nx, cfg.ny);
    assert!(x.len() == cfg.n_state() && y.len() == cfg.n_state() && f.len() == cfg.n_vel(), "smoke: force lengths");
    let nu = n + 1;
    copy(x, y);
    let (fu, fv) = f.split_at(cfg.n_u());
    let (_, u2, v2) = cfg.split_mut(y);
    let (wx, wy) = (cfg.boundary.periodic_x() as usize, cfg.boundary.periodic_y() as usize);
    for j in 0..ny {
        for i in 1 - wx..n {
            u2[j * nu + i] += dt * fu[j * nu + i];
        }
    }
    for j in 1 - wy..ny {
        for i in 0..n {
            v2[j * n + i] += dt * fv[j * n + i];
        }
    }
    for j in 0..ny * wx {
        u2[j * nu + n] = u2[j * nu];
    }
    for i in 0..n * wy {
        v2[ny * n + i] = v2[i];
    }
}

/// Inflow: in the cells `i0..i1 × j0..j1` set the smoke to `p[0]` and the
/// velocity on the faces of those cells (walls excepted) to `(p[1], p[2])`;
/// everything else passes through.
pub fn apply_inflow(cfg: &Smoke2d, region: [usize; 4], x: &[f64], p: &[f64], y: &mut [f64]) {
    let (n, ny) = (cfg.nx, cfg.ny);
    let [i0, i1, j0, j1] = region;
    assert!(x.len() == cfg.n_state() && y.len() == cfg.n_state() && p.len() == 3 && i0 < i1 && i1 <= n && j0 < j1 && j1 <= ny, "smoke: inflow");
    let nu = n + 1;
    for (o, &a) in y.iter_mut().zip(x) {
        *o = a;
    }
    let (s2, u2, v2) = cfg.split_mut(y);
    for j in j0..j1 {
        for i in i0..i1 {
            s2[j * n + i] = p[0];
        }
        for i in i0.max(1)..=i1.min(n - 1) {
            u2[j * nu + i] = p[1];
        }
    }
    for j in j0.max(1)..=j1.min(ny - 1) {
        for i in i0..i1 {
            v2[j * n + i] = p[2];
        }
    }
}

/// Solid cells of an axis-aligned box `[lower, upper)` in cell units (x
/// first), for the fluid operators and, complemented, as the fluid mask of
/// [`PressureSolver::general`]: a cell is solid when its centre lies inside. The box is clipped to the
/// domain; `None` when no cell centre lies inside (a box wholly outside).
pub fn obstacle_box(cfg: &Smoke2d, lower: [f64; 2], upper: [f64; 2]) -> Option<Vec<bool>> {
    obstacle(cfg, |x, y| x >= lower[0] && x < upper[0] && y >= lower[1] && y < upper[1])
}

/// Solid cells of a disc (centre in cell units, x first): a cell is solid
/// when its centre lies within `radius`. `None` when no cell is covered.
pub fn obstacle_disc(cfg: &Smoke2d, center: [f64; 2], radius: f64) -> Option<Vec<bool>> {
    obstacle(cfg, |x, y| (x - center[0]).powi(2) + (y - center[1]).powi(2) <= radius * radius)
}

fn obstacle(cfg: &Smoke2d, inside: impl Fn(f64, f64) -> bool) -> Option<Vec<bool>> {
    let n = cfg.nx;
    let solid: Vec<bool> = (0..cfg.n_s()).map(|c| inside((c % n) as f64 + 0.5, (c / n) as f64 + 0.5)).collect();
    solid.iter().any(|&s| s).then_some(solid)
}
