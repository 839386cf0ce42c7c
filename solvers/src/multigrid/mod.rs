//! A geometric multigrid V-cycle for the closed-box pressure matrix, used as
//! the preconditioner of conjugate gradients: one hierarchy for the square
//! (2D, five-point matrix) and the cube (3D, seven-point matrix; a square is
//! a cube one cell deep that is never coarsened along z). Boxes with other
//! sides or whose sides all differ take the aggregation V-cycle of
//! [`AggregateMultigrid`].
//!
//! Cell-centred grids halve per level while the side stays even and ≥ 4.
//! Prolongation `P` is bilinear or trilinear (weights ¾, ¼ per axis,
//! reflected at the walls: the 2D prolongation of each slab after the slabs
//! are blended along z); restriction is its exact transpose scaled to an
//! average, `R = Pᵀ/2^d` (`d` the coarsened axes); the coarse matrix is the
//! same stencil scaled by ¼ per level (the unscaled matrix approximates
//! `−h²Δ`, and `h` doubles). Smoothing is damped Jacobi (ω = 0.8 in 2D,
//! 6/7 in 3D), as many sweeps after the coarse correction as before (one
//! each, `SWEEPS`; thirty on the coarsest grid), so that the V-cycle is a
//! symmetric positive definite operator, as conjugate gradients needs.

use crate::par::{SUM_PIECE, for_pieces, sum_pieces};
use crate::smoke::apply_pressure_matrix;

mod aggregate;

pub use aggregate::{Across, AggregateMultigrid, OVER_CORRECTION, across, apply_stencil, apply_weighted};

/// The pressure matrix of the closed box of `n × n × nz` cells (`nz = 1`:
/// the square's five-point matrix): `(A·p)[c] = Σ_{neighbours m of c inside
/// the box} (p[c] − p[m])`, overwrites `out`. Slab by slab (in parallel on
/// large boxes, [`crate::par`]): the slab's in-plane part is the vectorised
/// 2D product, then the coupling to the slabs below and above.
#[inline(always)]
pub fn apply_box_matrix(n: usize, nz: usize, p: &[f64], out: &mut [f64]) {
    let slab = n * n;
    for_pieces(&mut out[..nz * slab], slab, |k, o| box_matrix_slab(n, nz, k, p, o));
}

/// Slab `k` of [`apply_box_matrix`] into `o`.
#[inline(always)]
fn box_matrix_slab(n: usize, nz: usize, k: usize, p: &[f64], o: &mut [f64]) {
    let slab = n * n;
    let here = &p[k * slab..(k + 1) * slab];
    apply_pressure_matrix(n, n, here, o);
    let mut couple = |other: &[f64]| {
        for ((o, &h), &b) in o.iter_mut().zip(here).zip(other) {
            *o += h - b;
        }
    };
    if k > 0 {
        couple(&p[(k - 1) * slab..k * slab]);
    }
    if k + 1 < nz {
        couple(&p[(k + 1) * slab..(k + 2) * slab]);
    }
}

/// Jacobi damping: `2d/(2d + 1)` for the `(2d+1)`-point matrix in `d`
/// dimensions (the factor that damps the highest frequencies best).
fn omega(cube: bool) -> f64 {
    if cube { 6.0 / 7.0 } else { 0.8 }
}
/// Smoothing sweeps before and after the coarse-grid correction.
const SWEEPS: usize = 1;
/// Sweeps on the coarsest grid (at most 4 × 4 cells) instead of a direct solve.
const COARSEST_SWEEPS: usize = 30;

#[derive(Clone, Debug)]
struct Level {
    n: usize,
    /// Slabs along z (1 in 2D).
    nz: usize,
    /// The level's matrix is `scale · A_n`.
    scale: f64,
    /// `ω / diag` of the level's matrix.
    omega_inv_diag: Vec<f64>,
    r: Vec<f64>,
    e: Vec<f64>,
    t: Vec<f64>,
    /// The `2·nz` finer slabs restricted to (or blended from) this level's
    /// area, between the two passes of a 3D transfer.
    slabs: Vec<f64>,
}

impl Level {
    fn new(n: usize, nz: usize, scale: f64) -> Self {
        let mut omega_inv_diag = vec![0.0; n * n * nz];
        for k in 0..nz {
            for j in 0..n {
                for i in 0..n {
                    let deg = (i > 0) as usize + (i + 1 < n) as usize + (j > 0) as usize + (j + 1 < n) as usize + (k > 0) as usize + (k + 1 < nz) as usize;
                    omega_inv_diag[(k * n + j) * n + i] = omega(nz > 1) / (scale * deg as f64);
                }
            }
        }
        let z = vec![0.0; n * n * nz];
        let slabs = if nz > 1 { vec![0.0; 2 * n * n * nz] } else { Vec::new() };
        Self { n, nz, scale, omega_inv_diag, r: z.clone(), e: z.clone(), t: z, slabs }
    }

    /// `sweeps ≥ 1` damped-Jacobi sweeps on `scale·A·e = r` from `e = 0`:
    /// the first is `e = ω·D⁻¹·r` (no product needed).
    #[inline(always)]
    fn smooth_from_zero(&mut self, sweeps: usize) {
        let (r, w, len) = (&self.r, &self.omega_inv_diag, self.n * self.n);
        if self.nz == 1 {
            // One slab: straight here, so that it is compiled with the
            // caller's vector instructions (a closure handed to the
            // parallel pass is compiled apart, without them).
            first_sweep_piece(0, len, r, w, &mut self.e);
        } else {
            for_pieces(&mut self.e, len, |k, e| first_sweep_piece(k, len, r, w, e));
        }
        self.smooth(sweeps - 1);
    }

    #[inline(always)]
    /// `sweeps` damped-Jacobi sweeps on `scale·A·e = r`, from the current `e`.
    fn smooth(&mut self, sweeps: usize) {
        for _ in 0..sweeps {
            self.sweep();
        }
    }

    /// One damped-Jacobi sweep, `e ← e + ω·D⁻¹·(r − scale·A·e)`, written
    /// slab by slab into `t` (the product and the update in one pass), then
    /// swapped into `e`.
    #[inline(always)]
    fn sweep(&mut self) {
        let (n, nz, scale) = (self.n, self.nz, self.scale);
        let (e, r, w) = (&self.e, &self.r, &self.omega_inv_diag);
        if nz == 1 {
            sweep_slab(n, nz, scale, 0, e, r, w, &mut self.t);
        } else {
            for_pieces(&mut self.t[..n * n * nz], n * n, |k, t| sweep_slab(n, nz, scale, k, e, r, w, t));
        }
        std::mem::swap(&mut self.e, &mut self.t);
    }

    /// `t = r − scale·A·e`, the residual of the level's equation.
    #[inline(always)]
    fn residual(&mut self) {
        let (n, nz, scale) = (self.n, self.nz, self.scale);
        let (e, r) = (&self.e, &self.r);
        if nz == 1 {
            residual_slab(n, nz, scale, 0, e, r, &mut self.t);
        } else {
            for_pieces(&mut self.t[..n * n * nz], n * n, |k, t| residual_slab(n, nz, scale, k, e, r, t));
        }
    }
}

/// Piece `k` (of `len` values) of the first sweep from zero, `e = ω·D⁻¹·r`.
#[inline(always)]
fn first_sweep_piece(k: usize, len: usize, r: &[f64], w: &[f64], e: &mut [f64]) {
    let o = k * len..k * len + e.len();
    for ((e, &r), &w) in e.iter_mut().zip(&r[o.clone()]).zip(&w[o]) {
        *e = w * r;
    }
}

/// Slab `k` of a damped-Jacobi sweep into `t`.
#[inline(always)]
#[allow(clippy::too_many_arguments)]
fn sweep_slab(n: usize, nz: usize, scale: f64, k: usize, e: &[f64], r: &[f64], w: &[f64], t: &mut [f64]) {
    box_matrix_slab(n, nz, k, e, t);
    let o = k * n * n..(k + 1) * n * n;
    for (((t, &e), &r), &w) in t.iter_mut().zip(&e[o.clone()]).zip(&r[o.clone()]).zip(&w[o]) {
        *t = e + w * (r - scale * *t);
    }
}

/// Slab `k` of the residual `t = r − scale·A·e`.
#[inline(always)]
fn residual_slab(n: usize, nz: usize, scale: f64, k: usize, e: &[f64], r: &[f64], t: &mut [f64]) {
    box_matrix_slab(n, nz, k, e, t);
    for (t, &r) in t.iter_mut().zip(&r[k * n * n..(k + 1) * n * n]) {
        *t = r - scale * *t;
    }
}

/// The multigrid hierarchy and its work buffers.
#[derive(Clone, Debug)]
pub struct Multigrid {
    levels: Vec<Level>,
}

impl Multigrid {
    /// The hierarchy for an `n × n` box.
    pub fn new(n: usize) -> Self {
        Self::hierarchy(n, 0)
    }

    /// The hierarchy for an `n × n × n` box.
    pub fn cube(n: usize) -> Self {
        Self::hierarchy(n, n)
    }

    /// The hierarchy for a box of `nz` square slabs of `n × n` cells (`nz =
    /// n`: the cube); both are halved together while both are even.
    /// One slab is the square ([`Multigrid::new`]).
    pub fn slabs(n: usize, nz: usize) -> Self {
        Self::hierarchy(n, if nz == 1 { 0 } else { nz })
    }

    /// `nz = 0`: the square (one slab, never coarsened along z).
    fn hierarchy(n: usize, nz: usize) -> Self {
        let square = nz == 0;
        let mut levels = vec![Level::new(n, nz.max(1), 1.0)];
        let (mut m, mut mz, mut scale) = (n, nz, 1.0);
        while m % 2 == 0 && m / 2 >= 2 && m > 4 && (square || (mz % 2 == 0 && mz / 2 >= 2)) {
            m /= 2;
            mz /= 2;
            scale *= 0.25;
            levels.push(Level::new(m, mz.max(1), scale));
        }
        Self { levels }
    }

    /// Number of levels.
    pub fn depth(&self) -> usize {
        self.levels.len()
    }

    /// `z = V·r`: one V-cycle from a zero guess (a fixed symmetric linear
    /// map), with the constant mode removed from `z`; compiled for the
    /// widest vector instructions the CPU has.
    pub fn apply(&mut self, r: &[f64], z: &mut [f64]) {
        apply_dispatch(self, r, z)
    }

    #[inline(always)]
    fn apply_body(&mut self, r: &[f64], z: &mut [f64]) {
        let depth = self.levels.len();
        // Restriction averages the 8 (cube) or 4 (square) fine cells of a coarse one.
        let average = if self.levels[0].nz > 1 { 0.125 } else { 0.25 };
        // Small grids straight here (with the vector instructions of the
        // dispatch), large ones in pieces over threads.
        let small = r.len() < crate::par::MIN_PARALLEL;
        if small {
            self.levels[0].r.copy_from_slice(r);
        } else {
            for_pieces(&mut self.levels[0].r, SUM_PIECE, |k, piece| piece.copy_from_slice(&r[k * SUM_PIECE..k * SUM_PIECE + piece.len()]));
        }
        // Down: smooth, then restrict the residual, r_c = Pᵀ·(r − A·e) / 2^d.
        for k in 0..depth - 1 {
            let (fine, coarse) = self.levels.split_at_mut(k + 1);
            let (f, c) = (&mut fine[k], &mut coarse[0]);
            f.smooth_from_zero(SWEEPS);
            f.residual();
            restrict_box(c, &f.t, average);
        }
        self.levels[depth - 1].smooth_from_zero(COARSEST_SWEEPS);
        // Up: e += P·e_c, then smooth.
        for k in (0..depth - 1).rev() {
            let (fine, coarse) = self.levels.split_at_mut(k + 1);
            let (f, c) = (&mut fine[k], &mut coarse[0]);
            prolong_box(c, &mut f.e);
            f.smooth(SWEEPS);
        }
        let e = &self.levels[0].e;
        let mean = sum_pieces(e, e, |a, _| crate::cg::sum_piece(a)) / z.len() as f64;
        if small {
            for (z, &e) in z.iter_mut().zip(e) {
                *z = e - mean;
            }
        } else {
            for_pieces(z, SUM_PIECE, |k, z| {
                for (z, &e) in z.iter_mut().zip(&e[k * SUM_PIECE..]) {
                    *z = e - mean;
                }
            });
        }
    }
}

crate::simd_dispatch! {
    fn apply_dispatch(mg: &mut Multigrid, r: &[f64], z: &mut [f64]) => apply_body_free
}

#[inline(always)]
fn apply_body_free(mg: &mut Multigrid, r: &[f64], z: &mut [f64]) {
    mg.apply_body(r, z)
}

/// The two coarse taps of fine index `a` along one axis: `(own, ¾)` and
/// `(neighbour, ¼)`, the neighbour reflected at the walls.
#[inline(always)]
fn taps(a: usize, nc: usize) -> (usize, usize) {
    let ic = a / 2;
    let other = if a % 2 == 0 { ic.saturating_sub(1) } else { (ic + 1).min(nc - 1) };
    (ic, other)
}

/// `fine += P·coarse` from the level `c`: the two coarse slabs beside each
/// fine slab along z blended (¾, ¼) into `c.slabs`, then each fine slab
/// prolonged in the plane (both passes slab by slab, in parallel on large
/// boxes); a level one slab deep is prolonged in the plane only.
#[inline(always)]
fn prolong_box(c: &mut Level, fine: &mut [f64]) {
    let (nc, area) = (c.n, c.n * c.n);
    if c.nz == 1 {
        return prolong(nc, &c.e, fine);
    }
    let (e, nz) = (&c.e, c.nz);
    for_pieces(&mut c.slabs, area, |kf, s| {
        let (kc, ko) = taps(kf, nz);
        for ((s, &a), &b) in s.iter_mut().zip(&e[kc * area..(kc + 1) * area]).zip(&e[ko * area..(ko + 1) * area]) {
            *s = 0.75 * a + 0.25 * b;
        }
    });
    let slabs = &c.slabs;
    for_pieces(&mut fine[..8 * area * nz], 4 * area, |kf, f| prolong(nc, &slabs[kf * area..(kf + 1) * area], f));
}

/// `c.r = average · Pᵀ·fine`, the transpose of [`prolong_box`] scaled:
/// each fine slab restricted in the plane into `c.slabs`, then each coarse
/// slab gathered from the fine slabs beside it along z (both passes in
/// parallel on large boxes).
#[inline(always)]
fn restrict_box(c: &mut Level, fine: &[f64], average: f64) {
    let (nc, area) = (c.n, c.n * c.n);
    if c.nz == 1 {
        c.r.fill(0.0);
        restrict(nc, fine, &mut c.r);
        c.r.iter_mut().for_each(|v| *v *= average);
        return;
    }
    let nz = c.nz;
    for_pieces(&mut c.slabs, area, |kf, s| {
        s.fill(0.0);
        restrict(nc, &fine[kf * 4 * area..(kf + 1) * 4 * area], s);
    });
    let slabs = &c.slabs;
    for_pieces(&mut c.r, area, |kc, r| {
        r.fill(0.0);
        // Fine slabs 2kc and 2kc+1 weigh ¾, 2kc−1 and 2kc+2 ¼ (at the walls
        // the reflected end slab), added in the order of the fine slabs.
        for kf in (2 * kc).saturating_sub(1)..(2 * kc + 3).min(2 * nz) {
            let (own, other) = taps(kf, nz);
            let s = &slabs[kf * area..(kf + 1) * area];
            for (weight, tap) in [(0.75, own), (0.25, other)] {
                if tap == kc {
                    for (r, &v) in r.iter_mut().zip(s) {
                        *r += weight * v;
                    }
                }
            }
        }
        r.iter_mut().for_each(|v| *v *= average);
    });
}

/// `fine += P·coarse`: bilinear cell-centred prolongation from `nc × nc` to
/// `2nc × 2nc` (rows blended, then each coarse value spread to its two fine
/// cells along x).
#[inline(always)]
fn prolong(nc: usize, coarse: &[f64], fine: &mut [f64]) {
    let nf = 2 * nc;
    for jf in 0..nf {
        let (jc, jo) = taps(jf, nc);
        let (a, b) = (&coarse[jc * nc..(jc + 1) * nc], &coarse[jo * nc..(jo + 1) * nc]);
        let row = |i: usize| 0.75 * a[i] + 0.25 * b[i];
        let f = &mut fine[jf * nf..(jf + 1) * nf];
        for ic in 0..nc {
            let (here, left, right) = (row(ic), row(ic.saturating_sub(1)), row((ic + 1).min(nc - 1)));
            f[2 * ic] += 0.75 * here + 0.25 * left;
            f[2 * ic + 1] += 0.75 * here + 0.25 * right;
        }
    }
}

/// `coarse += Pᵀ·fine`: the exact transpose of [`prolong`], as gathers.
#[inline(always)]
fn restrict(nc: usize, fine: &[f64], coarse: &mut [f64]) {
    let nf = 2 * nc;
    for jf in 0..nf {
        let (jc, jo) = taps(jf, nc);
        let f = &fine[jf * nf..(jf + 1) * nf];
        for ic in 0..nc {
            // Fine 2ic and 2ic+1 weigh ¾; fine 2ic−1 and 2ic+2 weigh ¼, and
            // at the walls the reflected fine 0 and nf−1.
            let left = if ic > 0 { f[2 * ic - 1] } else { f[0] };
            let right = if ic + 1 < nc { f[2 * ic + 2] } else { f[nf - 1] };
            let r = 0.75 * (f[2 * ic] + f[2 * ic + 1]) + 0.25 * (left + right);
            coarse[jc * nc + ic] += 0.75 * r;
            coarse[jo * nc + ic] += 0.25 * r;
        }
    }
}
