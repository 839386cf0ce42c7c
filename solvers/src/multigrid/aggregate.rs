//! A multigrid V-cycle for the 3D pressure matrix of any box and any sides
//! (closed, periodic, inflow, outflow), the preconditioner where the
//! geometric V-cycle of the closed box ([`super::Multigrid`]) does not
//! apply: boxes with periodic or outflow sides, and boxes whose sides all
//! differ.
//!
//! Cells are aggregated in pairs along every axis whose count is even and
//! at least 4 (semi-coarsening where an axis is odd), level after level.
//! Prolongation `P` copies each coarse value to its cells, restriction is
//! `Pᵀ` (sums over the cells), and the coarse matrix is Galerkin's `Pᵀ·A·P`:
//! again the seven-point stencil of the same sides, its coupling along an
//! axis weighted by the number of fine faces between two coarse cells (the
//! product of the other axes' aggregation factors), which
//! [`apply_weighted`] applies. Damped Jacobi smooths (ω = 6/7, one sweep
//! before and after the correction, thirty on the coarsest level), the
//! coarse correction is scaled by [`OVER_CORRECTION`] (piecewise-constant
//! prolongation under-corrects smooth errors); pre- and post-smoothing
//! mirror each other, so the V-cycle is a symmetric positive definite map,
//! as conjugate gradients needs.

use crate::boundary::{Boundary, Side};
use crate::par::{SUM_PIECE, for_pieces, sum_pieces};

/// Jacobi damping for the seven-point stencil.
const OMEGA: f64 = 6.0 / 7.0;
/// Sweeps on the coarsest level.
const COARSEST_SWEEPS: usize = 30;
/// Scale of the coarse correction: piecewise-constant prolongation leaves
/// smooth errors under-corrected, and scaling the correction up (below 2,
/// where the V-cycle stays positive definite) cut the pressure time of
/// `scenes/duct3d.toml` (30 steps) from 2.94 s at 1 to 2.21 s at 1.6 (2.25
/// at 1.5, 2.2–2.5 at 1.7, 2.33 at 2; one run each).
pub const OVER_CORRECTION: f64 = 1.6;

/// What lies across one face of a cell, along one direction of an axis.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Across {
    /// Another cell (inside the box, or wrapped across a periodic side).
    Cell(usize),
    /// The outside of an outflow side, where `p = 0`.
    Ghost,
    /// Nothing: a closed or inflow side (no flux).
    Wall,
}

/// The two neighbours of cell `c` at `q` along `axis` (down, then up) in a
/// box of `dims` cells with sides `b`: the rule of the 3D pressure matrix,
/// written once for the matrices and the preconditioners.
#[inline(always)]
pub fn across(dims: [usize; 3], b: &Boundary<3>, c: usize, q: [usize; 3], axis: usize) -> [Across; 2] {
    let stride = [1, dims[0], dims[0] * dims[1]][axis];
    let span = (dims[axis] - 1) * stride;
    let [lo, hi] = b.axis(axis);
    let beyond = |side: Side, wrapped: usize| match side {
        Side::Periodic => Across::Cell(wrapped),
        Side::Outflow => Across::Ghost,
        Side::Closed | Side::NoSlip | Side::Inflow(_) => Across::Wall,
    };
    let down = if q[axis] > 0 { Across::Cell(c - stride) } else { beyond(lo, c + span) };
    let up = if q[axis] + 1 < dims[axis] { Across::Cell(c + stride) } else { beyond(hi, c - span) };
    [down, up]
}

/// The seven-point matrix of a box of `dims` cells with sides `b`, its
/// coupling along axis `a` weighted by `w[a]`: `out[c] = Σ_a w_a·Σ (p_c −
/// p_m)` over the neighbours [`across`] gives (`p_m = 0` for a ghost,
/// nothing at a wall). Overwrites `out`; slab by slab, in parallel on large
/// boxes.
pub fn apply_weighted(dims: [usize; 3], b: &Boundary<3>, w: [f64; 3], p: &[f64], out: &mut [f64]) {
    apply_stencil(dims, b, w, None, p, out);
}

/// The seven-point matrix of [`apply_weighted`] with solid cells where
/// `fluid[c] = 0` (`None`: none): `out[c] = f_c·Σ_a w_a·Σ_m f_m·(p_c − p_m)
/// + (1 − f_c)·p_c` (a ghost counts `p_c`), which couples fluid cells only
/// and keeps solid rows as the identity. The one loop behind both 3D
/// pressure matrices (this one's and [`crate::smoke::PressureSolver`]'s on a periodic box).
pub fn apply_stencil(dims: [usize; 3], b: &Boundary<3>, w: [f64; 3], fluid: Option<&[f64]>, p: &[f64], out: &mut [f64]) {
    let [nx, ny, nz] = dims;
    let slab = nx * ny;
    let f = |c: usize| fluid.map_or(1.0, |f| f[c]);
    for_pieces(&mut out[..slab * nz], slab, |k, o| {
        for j in 0..ny {
            for i in 0..nx {
                let c = (k * ny + j) * nx + i;
                let (pc, fc) = (p[c], f(c));
                let mut acc = 0.0;
                for (a, &wa) in w.iter().enumerate() {
                    for m in across(dims, b, c, [i, j, k], a) {
                        acc += wa
                            * match m {
                                Across::Cell(m) => f(m) * (pc - p[m]),
                                Across::Ghost => pc,
                                Across::Wall => 0.0,
                            };
                    }
                }
                o[j * nx + i] = fc * acc + (1.0 - fc) * pc;
            }
        }
    });
}

/// One level: its box, stencil weights, aggregation factors to the next
/// coarser level, `ω/diag`, and its vectors.
#[derive(Clone, Debug)]
struct Level {
    dims: [usize; 3],
    w: [f64; 3],
    /// 2 along the axes the next level halves, else 1.
    factor: [usize; 3],
    omega_inv_diag: Vec<f64>,
    r: Vec<f64>,
    e: Vec<f64>,
    t: Vec<f64>,
}

impl Level {
    fn new(dims: [usize; 3], b: &Boundary<3>, w: [f64; 3]) -> Self {
        let n = dims.iter().product();
        let [nx, ny, _] = dims;
        let omega_inv_diag = (0..n)
            .map(|c| {
                let q = [c % nx, (c / nx) % ny, c / (nx * ny)];
                let diag: f64 = (0..3).map(|a| w[a] * across(dims, b, c, q, a).iter().filter(|m| **m != Across::Wall).count() as f64).sum();
                OMEGA / diag
            })
            .collect();
        let factor = dims.map(|d| if d % 2 == 0 && d >= 4 { 2 } else { 1 });
        Self { dims, w, factor, omega_inv_diag, r: vec![0.0; n], e: vec![0.0; n], t: vec![0.0; n] }
    }

    fn cells(&self) -> usize {
        self.r.len()
    }

    /// `e = ω·D⁻¹·r`, then `sweeps − 1` more sweeps.
    fn smooth_from_zero(&mut self, b: &Boundary<3>, sweeps: usize) {
        for ((e, &r), &d) in self.e.iter_mut().zip(&self.r).zip(&self.omega_inv_diag) {
            *e = d * r;
        }
        for _ in 1..sweeps {
            self.sweep(b);
        }
    }

    /// One damped-Jacobi sweep `e ← e + ω·D⁻¹·(r − A·e)`.
    fn sweep(&mut self, b: &Boundary<3>) {
        self.residual(b);
        for ((e, &t), &d) in self.e.iter_mut().zip(&self.t).zip(&self.omega_inv_diag) {
            *e += d * t;
        }
    }

    /// `t = r − A·e`.
    fn residual(&mut self, b: &Boundary<3>) {
        apply_weighted(self.dims, b, self.w, &self.e, &mut self.t);
        for (t, &r) in self.t.iter_mut().zip(&self.r) {
            *t = r - *t;
        }
    }

    /// The coarse cell of fine cell `c`.
    #[inline(always)]
    fn parent(&self, c: usize, coarse: [usize; 3]) -> usize {
        let [nx, ny, _] = self.dims;
        let q = [c % nx, (c / nx) % ny, c / (nx * ny)];
        let p = [0, 1, 2].map(|a| q[a] / self.factor[a]);
        (p[2] * coarse[1] + p[1]) * coarse[0] + p[0]
    }
}

/// The aggregation hierarchy of a box and its sides, with work buffers.
#[derive(Clone, Debug)]
pub struct AggregateMultigrid {
    boundary: Boundary<3>,
    levels: Vec<Level>,
    /// The coarse cell of each fine cell, per level but the coarsest.
    parents: Vec<Vec<u32>>,
}

impl AggregateMultigrid {
    /// The hierarchy for a box of `dims` cells (x and y at least 2; a 2D box
    /// is one cell deep along z between closed sides) with sides
    /// `boundary`: levels until no axis can be halved.
    pub fn new(dims: [usize; 3], boundary: Boundary<3>) -> Self {
        let mut levels = vec![Level::new(dims, &boundary, [1.0; 3])];
        let mut parents = Vec::new();
        loop {
            let fine = levels.last().expect("a level");
            if fine.factor == [1; 3] {
                break;
            }
            let coarse = [0, 1, 2].map(|a| fine.dims[a] / fine.factor[a]);
            // Faces between two coarse cells along a: the other axes' factors.
            let w = [0, 1, 2].map(|a| fine.w[a] * (0..3).filter(|&o| o != a).map(|o| fine.factor[o] as f64).product::<f64>());
            parents.push((0..fine.cells()).map(|c| fine.parent(c, coarse) as u32).collect());
            levels.push(Level::new(coarse, &boundary, w));
        }
        Self { boundary, levels, parents }
    }

    /// Number of levels.
    pub fn depth(&self) -> usize {
        self.levels.len()
    }

    /// `z = V·r`: one V-cycle from a zero guess (a fixed symmetric linear
    /// map); without an outflow side the constant mode is removed from `z`.
    pub fn apply(&mut self, r: &[f64], z: &mut [f64]) {
        let b = self.boundary;
        let depth = self.levels.len();
        self.levels[0].r.copy_from_slice(r);
        for k in 0..depth - 1 {
            let (fine, coarse) = self.levels.split_at_mut(k + 1);
            let (f, c) = (&mut fine[k], &mut coarse[0]);
            f.smooth_from_zero(&b, 1);
            f.residual(&b);
            c.r.fill(0.0);
            for (&t, &p) in f.t.iter().zip(&self.parents[k]) {
                c.r[p as usize] += t;
            }
        }
        self.levels[depth - 1].smooth_from_zero(&b, COARSEST_SWEEPS);
        for k in (0..depth - 1).rev() {
            let (fine, coarse) = self.levels.split_at_mut(k + 1);
            let (f, c) = (&mut fine[k], &coarse[0]);
            for (e, &p) in f.e.iter_mut().zip(&self.parents[k]) {
                *e += OVER_CORRECTION * c.e[p as usize];
            }
            f.sweep(&b);
        }
        let e = &self.levels[0].e;
        let mean = if b.has_outflow() { 0.0 } else { sum_pieces(e, e, |a, _| crate::cg::sum_piece(a)) / z.len() as f64 };
        for_pieces(z, SUM_PIECE, |k, z| {
            for (z, &e) in z.iter_mut().zip(&e[k * SUM_PIECE..]) {
                *z = e - mean;
            }
        });
    }
}
