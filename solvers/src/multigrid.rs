//! A geometric multigrid V-cycle for the closed-box pressure matrix, used as
//! the preconditioner of conjugate gradients.
//!
//! Cell-centred grids halve per level while the side stays even and ≥ 4.
//! Prolongation `P` is bilinear (weights ¾, ¼ per axis, reflected at the
//! walls); restriction is its exact transpose scaled by ¼, `R = Pᵀ/4`; the
//! coarse matrix is the same stencil scaled by ¼ per level (the unscaled
//! matrix approximates `−h²Δ`, and `h` doubles). Smoothing is damped Jacobi
//! (ω = 0.8), as many sweeps after the coarse correction as before (one
//! each, `SWEEPS`; thirty on the coarsest grid), so that the V-cycle is a
//! symmetric positive definite operator, as conjugate gradients needs.

use crate::smoke::apply_pressure_matrix;

/// Jacobi damping.
const OMEGA: f64 = 0.8;
/// Smoothing sweeps before and after the coarse-grid correction.
const SWEEPS: usize = 1;
/// Sweeps on the coarsest grid (at most 4 × 4 cells) instead of a direct solve.
const COARSEST_SWEEPS: usize = 30;

#[derive(Clone, Debug)]
struct Level {
    n: usize,
    /// The level's matrix is `scale · A_n`.
    scale: f64,
    /// `ω / diag` of the level's matrix.
    omega_inv_diag: Vec<f64>,
    r: Vec<f64>,
    e: Vec<f64>,
    t: Vec<f64>,
}

impl Level {
    fn new(n: usize, scale: f64) -> Self {
        let mut omega_inv_diag = vec![0.0; n * n];
        for j in 0..n {
            for i in 0..n {
                let deg = (i > 0) as usize + (i + 1 < n) as usize + (j > 0) as usize + (j + 1 < n) as usize;
                omega_inv_diag[j * n + i] = OMEGA / (scale * deg as f64);
            }
        }
        let z = vec![0.0; n * n];
        Self { n, scale, omega_inv_diag, r: z.clone(), e: z.clone(), t: z }
    }

    #[inline(always)]
    /// `sweeps` damped-Jacobi sweeps on `scale·A·e = r`, from the current `e`.
    fn smooth(&mut self, sweeps: usize) {
        for _ in 0..sweeps {
            apply_pressure_matrix(self.n, self.n, &self.e, &mut self.t);
            for (((e, &t), &r), &w) in self.e.iter_mut().zip(&self.t).zip(&self.r).zip(&self.omega_inv_diag) {
                *e += w * (r - self.scale * t);
            }
        }
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
        let mut levels = vec![Level::new(n, 1.0)];
        let (mut m, mut scale) = (n, 1.0);
        while m % 2 == 0 && m / 2 >= 2 && m > 4 {
            m /= 2;
            scale *= 0.25;
            levels.push(Level::new(m, scale));
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
        self.levels[0].r.copy_from_slice(r);
        // Down: smooth, then restrict the residual, r_c = Pᵀ·(r − A·e) / 4.
        for k in 0..depth - 1 {
            let (fine, coarse) = self.levels.split_at_mut(k + 1);
            let (f, c) = (&mut fine[k], &mut coarse[0]);
            f.e.fill(0.0);
            f.smooth(SWEEPS);
            apply_pressure_matrix(f.n, f.n, &f.e, &mut f.t);
            for (t, &r) in f.t.iter_mut().zip(&f.r) {
                *t = r - f.scale * *t;
            }
            c.r.fill(0.0);
            restrict(c.n, &f.t, &mut c.r, &mut c.t);
            for v in c.r.iter_mut() {
                *v *= 0.25;
            }
        }
        let coarsest = &mut self.levels[depth - 1];
        coarsest.e.fill(0.0);
        coarsest.smooth(COARSEST_SWEEPS);
        // Up: e += P·e_c, then smooth.
        for k in (0..depth - 1).rev() {
            let (fine, coarse) = self.levels.split_at_mut(k + 1);
            let (f, c) = (&mut fine[k], &mut coarse[0]);
            prolong(c.n, &c.e, &mut f.e, &mut c.t);
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
