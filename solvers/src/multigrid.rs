//! A geometric multigrid V-cycle for the closed-box pressure matrix, used as
//! the preconditioner of conjugate gradients: one hierarchy for the square
//! (2D, five-point matrix) and the cube (3D, seven-point matrix; a square is
//! a cube one cell deep that is never coarsened along z).
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

use crate::smoke::apply_pressure_matrix;

/// The pressure matrix of the closed box of `n × n × nz` cells (`nz = 1`:
/// the square's five-point matrix): `(A·p)[c] = Σ_{neighbours m of c inside
/// the box} (p[c] − p[m])`, overwrites `out`. Each slab's in-plane part is
/// the vectorised 2D product; the coupling across slabs is a pass over
/// pairs of slabs.
#[inline(always)]
pub fn apply_box_matrix(n: usize, nz: usize, p: &[f64], out: &mut [f64]) {
    let slab = n * n;
    for k in 0..nz {
        apply_pressure_matrix(n, n, &p[k * slab..(k + 1) * slab], &mut out[k * slab..(k + 1) * slab]);
    }
    for k in 1..nz {
        let (lo, hi) = out.split_at_mut(k * slab);
        let (below, here) = (&p[(k - 1) * slab..k * slab], &p[k * slab..(k + 1) * slab]);
        for (((ol, oh), &b), &h) in lo[(k - 1) * slab..].iter_mut().zip(&mut hi[..slab]).zip(below).zip(here) {
            *ol += b - h;
            *oh += h - b;
        }
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
        Self { n, nz, scale, omega_inv_diag, r: z.clone(), e: z.clone(), t: z }
    }

    /// `sweeps ≥ 1` damped-Jacobi sweeps on `scale·A·e = r` from `e = 0`:
    /// the first is `e = ω·D⁻¹·r` (no product needed).
    #[inline(always)]
    fn smooth_from_zero(&mut self, sweeps: usize) {
        for ((e, &r), &w) in self.e.iter_mut().zip(&self.r).zip(&self.omega_inv_diag) {
            *e = w * r;
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

    /// One damped-Jacobi sweep, `e += ω·D⁻¹·(r − scale·A·e)`.
    #[inline(always)]
    fn sweep(&mut self) {
        apply_box_matrix(self.n, self.nz, &self.e, &mut self.t);
        for (((e, &t), &r), &w) in self.e.iter_mut().zip(&self.t).zip(&self.r).zip(&self.omega_inv_diag) {
            *e += w * (r - self.scale * t);
        }
    }
}

/// The multigrid hierarchy and its work buffers.
#[derive(Clone, Debug)]
pub struct Multigrid {
    levels: Vec<Level>,
    /// One coarse slab (blending along z).
    slab: Vec<f64>,
}

impl Multigrid {
    /// The hierarchy for an `n × n` box.
    pub fn new(n: usize) -> Self {
        Self::hierarchy(n, false)
    }

    /// The hierarchy for an `n × n × n` box.
    pub fn cube(n: usize) -> Self {
        Self::hierarchy(n, true)
    }

    fn hierarchy(n: usize, cube: bool) -> Self {
        let depth = |m: usize| if cube { m } else { 1 };
        let mut levels = vec![Level::new(n, depth(n), 1.0)];
        let (mut m, mut scale) = (n, 1.0);
        while m % 2 == 0 && m / 2 >= 2 && m > 4 {
            m /= 2;
            scale *= 0.25;
            levels.push(Level::new(m, depth(m), scale));
        }
        Self { levels, slab: vec![0.0; (n / 2).max(1).pow(2)] }
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
        self.levels[0].r.copy_from_slice(r);
        // Down: smooth, then restrict the residual, r_c = Pᵀ·(r − A·e) / 2^d.
        for k in 0..depth - 1 {
            let (fine, coarse) = self.levels.split_at_mut(k + 1);
            let (f, c) = (&mut fine[k], &mut coarse[0]);
            f.smooth_from_zero(SWEEPS);
            apply_box_matrix(f.n, f.nz, &f.e, &mut f.t);
            for (t, &r) in f.t.iter_mut().zip(&f.r) {
                *t = r - f.scale * *t;
            }
            c.r.fill(0.0);
            restrict_box(c, &f.t, &mut self.slab);
            for v in c.r.iter_mut() {
                *v *= average;
            }
        }
        self.levels[depth - 1].smooth_from_zero(COARSEST_SWEEPS);
        // Up: e += P·e_c, then smooth.
        for k in (0..depth - 1).rev() {
            let (fine, coarse) = self.levels.split_at_mut(k + 1);
            let (f, c) = (&mut fine[k], &mut coarse[0]);
            prolong_box(c, &mut f.e, &mut self.slab);
            f.smooth(SWEEPS);
        }
        z.copy_from_slice(&self.levels[0].e);
        let mean = z.iter().sum::<f64>() / z.len() as f64;
        for v in z.iter_mut() {
            *v -= mean;
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

/// `fine += P·coarse` from the level `c`: each fine slab from the two
/// coarse slabs beside it along z (¾, ¼) blended into `slab`, then the 2D
/// prolongation; a level one slab deep is prolonged in the plane only.
#[inline(always)]
fn prolong_box(c: &mut Level, fine: &mut [f64], slab: &mut [f64]) {
    let (nc, area) = (c.n, c.n * c.n);
    if c.nz == 1 {
        return prolong(nc, &c.e, fine, &mut c.t);
    }
    let fine_area = 4 * area;
    for kf in 0..2 * c.nz {
        let (kc, ko) = taps(kf, c.nz);
        let (a, b) = (&c.e[kc * area..(kc + 1) * area], &c.e[ko * area..(ko + 1) * area]);
        for ((s, &a), &b) in slab[..area].iter_mut().zip(a).zip(b) {
            *s = 0.75 * a + 0.25 * b;
        }
        prolong(nc, &slab[..area], &mut fine[kf * fine_area..(kf + 1) * fine_area], &mut c.t);
    }
}

/// `c.r += Pᵀ·fine`, the exact transpose of [`prolong_box`]: each fine
/// slab restricted in the plane into `slab`, then spread to the two coarse
/// slabs beside it along z.
#[inline(always)]
fn restrict_box(c: &mut Level, fine: &[f64], slab: &mut [f64]) {
    let (nc, area) = (c.n, c.n * c.n);
    if c.nz == 1 {
        return restrict(nc, fine, &mut c.r, &mut c.t);
    }
    let fine_area = 4 * area;
    for kf in 0..2 * c.nz {
        let (kc, ko) = taps(kf, c.nz);
        let s = &mut slab[..area];
        s.fill(0.0);
        restrict(nc, &fine[kf * fine_area..(kf + 1) * fine_area], s, &mut c.t);
        for (r, &v) in c.r[kc * area..(kc + 1) * area].iter_mut().zip(s.iter()) {
            *r += 0.75 * v;
        }
        for (r, &v) in c.r[ko * area..(ko + 1) * area].iter_mut().zip(s.iter()) {
            *r += 0.25 * v;
        }
    }
}

/// `fine += P·coarse`: bilinear cell-centred prolongation from `nc × nc` to
/// `2nc × 2nc` (rows blended first, then each coarse value spread to its
/// two fine cells along x).
#[inline(always)]
fn prolong(nc: usize, coarse: &[f64], fine: &mut [f64], row: &mut [f64]) {
    let nf = 2 * nc;
    for jf in 0..nf {
        let (jc, jo) = taps(jf, nc);
        for ((r, &a), &b) in row.iter_mut().zip(&coarse[jc * nc..(jc + 1) * nc]).zip(&coarse[jo * nc..(jo + 1) * nc]) {
            *r = 0.75 * a + 0.25 * b;
        }
        let f = &mut fine[jf * nf..(jf + 1) * nf];
        for ic in 0..nc {
            let (left, right) = (row[ic.saturating_sub(1)], row[(ic + 1).min(nc - 1)]);
            f[2 * ic] += 0.75 * row[ic] + 0.25 * left;
            f[2 * ic + 1] += 0.75 * row[ic] + 0.25 * right;
        }
    }
}

/// `coarse += Pᵀ·fine`: the exact transpose of [`prolong`], as gathers.
#[inline(always)]
fn restrict(nc: usize, fine: &[f64], coarse: &mut [f64], row: &mut [f64]) {
    let nf = 2 * nc;
    for jf in 0..nf {
        let (jc, jo) = taps(jf, nc);
        let f = &fine[jf * nf..(jf + 1) * nf];
        for (ic, r) in row[..nc].iter_mut().enumerate() {
            // Fine 2ic and 2ic+1 weigh ¾; fine 2ic−1 and 2ic+2 weigh ¼, and
            // at the walls the reflected fine 0 and nf−1.
            let left = if ic > 0 { f[2 * ic - 1] } else { f[0] };
            let right = if ic + 1 < nc { f[2 * ic + 2] } else { f[nf - 1] };
            *r = 0.75 * (f[2 * ic] + f[2 * ic + 1]) + 0.25 * (left + right);
        }
        for (c, &r) in coarse[jc * nc..(jc + 1) * nc].iter_mut().zip(row.iter()) {
            *c += 0.75 * r;
        }
        for (c, &r) in coarse[jo * nc..(jo + 1) * nc].iter_mut().zip(row.iter()) {
            *c += 0.25 * r;
        }
    }
}
