//! The 3D pressure projection of the closed box: divergence over the six
//! faces of each cell, the seven-point matrix, its solve by conjugate
//! gradients ([`crate::cg`], preconditioned by the multigrid V-cycle of
//! [`crate::multigrid`]), and the projection's adjoint (the same solve).

use super::*;
use crate::cg::{CgWork, NoConvergence, Null, Stop, System};
use crate::multigrid::{Multigrid, apply_box_matrix};
use crate::smoke::{Preconditioner, ProjectScratch};

/// Calls `f(c, faces)` for every cell `c` with the flat indices of its six
/// faces, `[u_left, u_right, v_below, v_above, w_back, w_front]`.
#[inline(always)]
fn for_each_cell(cfg: &Smoke3d, mut f: impl FnMut(usize, [usize; 6])) {
    let [nx, ny, nz] = cfg.dims();
    for k in 0..nz {
        for j in 0..ny {
            let (ru, rv0, rv1) = ((k * ny + j) * (nx + 1), (k * (ny + 1) + j) * nx, (k * (ny + 1) + j + 1) * nx);
            let (rw0, rw1, rc) = ((k * ny + j) * nx, ((k + 1) * ny + j) * nx, (k * ny + j) * nx);
            for i in 0..nx {
                f(rc + i, [ru + i, ru + i + 1, rv0 + i, rv1 + i, rw0 + i, rw1 + i]);
            }
        }
    }
}

/// Divergence of the MAC velocity, `d[c] = Σ` outward flux over the six
/// faces of cell `c` (overwrites `d`).
pub fn divergence(cfg: &Smoke3d, [u, v, w]: [&[f64]; 3], d: &mut [f64]) {
    for_each_cell(cfg, |c, f| d[c] = (u[f[1]] - u[f[0]]) + (v[f[3]] - v[f[2]]) + (w[f[5]] - w[f[4]]));
}

/// Transpose of [`divergence`]: `(u, v, w) += Dᵀ·d` (accumulates).
pub fn divergence_transpose(cfg: &Smoke3d, d: &[f64], [u, v, w]: [&mut [f64]; 3]) {
    for_each_cell(cfg, |c, f| {
        let g = d[c];
        u[f[1]] += g;
        u[f[0]] -= g;
        v[f[3]] += g;
        v[f[2]] -= g;
        w[f[5]] += g;
        w[f[4]] -= g;
    });
}

/// `(u, v, w) −= s·G·p` on the interior faces: the pressure difference
/// across each face, upper cell minus lower, scaled by `s`.
fn subtract_gradient(cfg: &Smoke3d, scale: f64, p: &[f64], [u, v, w]: [&mut [f64]; 3]) {
    let [nx, ny, nz] = cfg.dims();
    for k in 0..nz {
        for j in 0..ny {
            let (ru, rc) = ((k * ny + j) * (nx + 1), (k * ny + j) * nx);
            for i in 1..nx {
                u[ru + i] -= scale * (p[rc + i] - p[rc + i - 1]);
            }
        }
        for j in 1..ny {
            let (rv, rc, rd) = ((k * (ny + 1) + j) * nx, (k * ny + j) * nx, (k * ny + j - 1) * nx);
            for i in 0..nx {
                v[rv + i] -= scale * (p[rc + i] - p[rd + i]);
            }
        }
    }
    let slab = nx * ny;
    for k in 1..nz {
        for c in 0..slab {
            w[k * slab + c] -= scale * (p[k * slab + c] - p[(k - 1) * slab + c]);
        }
    }
}

/// Transpose of `G` on the interior faces: `out = Gᵀ·g` (overwrites).
fn gradient_transpose(cfg: &Smoke3d, [u, v, w]: [&[f64]; 3], out: &mut [f64]) {
    out.fill(0.0);
    let [nx, ny, nz] = cfg.dims();
    for k in 0..nz {
        for j in 0..ny {
            let (ru, rc) = ((k * ny + j) * (nx + 1), (k * ny + j) * nx);
            for i in 1..nx {
                out[rc + i] += u[ru + i];
                out[rc + i - 1] -= u[ru + i];
            }
        }
        for j in 1..ny {
            let (rv, rc, rd) = ((k * (ny + 1) + j) * nx, (k * ny + j) * nx, (k * ny + j - 1) * nx);
            for i in 0..nx {
                out[rc + i] += v[rv + i];
                out[rd + i] -= v[rv + i];
            }
        }
    }
    let slab = nx * ny;
    for k in 1..nz {
        for c in 0..slab {
            out[k * slab + c] += w[k * slab + c];
            out[(k - 1) * slab + c] -= w[k * slab + c];
        }
    }
}

/// Conjugate gradients on the pressure matrix of the closed `n³` box,
/// preconditioned by a multigrid V-cycle or not at all, with its work
/// vectors kept between solves.
#[derive(Clone, Debug)]
pub struct PressureSolver3 {
    n: usize,
    /// The stopping rule.
    pub stop: Stop,
    mg: Option<Multigrid>,
    work: CgWork,
}

impl PressureSolver3 {
    /// A solver for the `n × n × n` closed box: relative `tolerance` on the
    /// true residual, more than `max_iterations` an error, preconditioned by
    /// [`Preconditioner::Multigrid`] or [`Preconditioner::None`].
    ///
    /// # Panics
    /// For another preconditioner (MIC(0) and Cholesky are 2D only).
    pub fn new(n: usize, tolerance: f64, max_iterations: usize, precond: Preconditioner) -> Self {
        let mg = match precond {
            Preconditioner::Multigrid => Some(Multigrid::cube(n)),
            Preconditioner::None => None,
            other => panic!("3D pressure solves take the multigrid preconditioner or none, not {other}"),
        };
        Self { n, stop: Stop { tolerance, max_iterations }, mg, work: CgWork::new(n * n * n) }
    }

    /// The preconditioner in use.
    pub fn preconditioner(&self) -> Preconditioner {
        if self.mg.is_some() { Preconditioner::Multigrid } else { Preconditioner::None }
    }

    /// Solves `A·p = b` from `p = 0` to the tolerance (the matrix is
    /// singular: `b` is projected onto sums of zero, the solution has zero
    /// mean). Returns the iterations.
    pub fn solve(&mut self, b: &[f64], p: &mut [f64]) -> Result<usize, NoConvergence> {
        let mut work = std::mem::take(&mut self.work);
        let stop = self.stop;
        let r = crate::cg::solve(self, &mut work, stop, b, p, false);
        self.work = work;
        r
    }
}

impl System for PressureSolver3 {
    fn apply(&mut self, p: &[f64], out: &mut [f64]) {
        apply_box_matrix(self.n, self.n, p, out);
    }

    /// Constants: the box is closed.
    fn null(&self) -> Null<'_> {
        Null::Constant(None)
    }

    fn precondition(&mut self, r: &[f64], z: &mut [f64]) -> bool {
        match &mut self.mg {
            Some(mg) => {
                mg.apply(r, z);
                true
            }
            None => false,
        }
    }
}

/// P4's step 5 in place on the velocity part of the packed state `y`: the
/// solve `A·p = −D·(u, v, w)`, then `(u, v, w) −= G·p` on the interior
/// faces. Returns the CG iterations.
pub fn project(cfg: &Smoke3d, y: &mut [f64], solver: &mut PressureSolver3, scratch: &mut ProjectScratch) -> Result<usize, NoConvergence> {
    let [_, u, v, w] = cfg.split_mut(y);
    divergence(cfg, [u, v, w], &mut scratch.d);
    for d in scratch.d.iter_mut() {
        *d = -*d;
    }
    let it = solver.solve(&scratch.d, &mut scratch.p)?;
    subtract_gradient(cfg, 1.0, &scratch.p, [u, v, w]);
    Ok(it)
}

/// Adjoint of [`project`] (a linear map), in place on the velocity part of
/// the adjoint `g`: `λ_p = −Gᵀ·λ`, the solve `A·μ = λ_p` (the transposed —
/// here the same — system to the same tolerance), `λ += −Dᵀ·μ`. Returns
/// the CG iterations.
pub fn project_adjoint(cfg: &Smoke3d, g: &mut [f64], solver: &mut PressureSolver3, scratch: &mut ProjectScratch) -> Result<usize, NoConvergence> {
    let [_, gu, gv, gw] = cfg.split_mut(g);
    gradient_transpose(cfg, [gu, gv, gw], &mut scratch.d);
    for d in scratch.d.iter_mut() {
        *d = -*d;
    }
    let it = solver.solve(&scratch.d, &mut scratch.p)?;
    for p in scratch.p.iter_mut() {
        *p = -*p;
    }
    divergence_transpose(cfg, &scratch.p, [gu, gv, gw]);
    Ok(it)
}
