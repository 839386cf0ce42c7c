//! The 3D pressure projection of the closed box: divergence over the six
//! faces of each cell, the seven-point matrix (coupling fluid cells only
//! when there are obstacles), its solve by conjugate gradients
//! ([`crate::cg`], preconditioned by the multigrid V-cycle of
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
    obstacles: Option<Masked>,
    work: CgWork,
}

/// What the matrix with solid cells needs: the fluid mask `W`, the count of
/// solid cells beside each cell `S`, and a buffer.
#[derive(Clone, Debug)]
struct Masked {
    fluid: Vec<f64>,
    solid_beside: Vec<f64>,
    buf: Vec<f64>,
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
        Self { n, stop: Stop { tolerance, max_iterations }, mg, obstacles: None, work: CgWork::new(n * n * n) }
    }

    /// A solver for the `n × n × n` closed box with solid cells where
    /// `fluid[c] = 0`: the matrix `W·(A_box·W − S) + (I − W)`, which couples
    /// fluid cells across their shared faces only (`S` counts the solid
    /// cells beside each cell) and keeps solid rows as the identity;
    /// symmetric, the constants on the fluid cells its null space. The
    /// multigrid preconditioner is the closed box's V-cycle on the fluid
    /// cells, `W·M·W + (I − W)`: symmetric and positive, blind to the
    /// obstacles' walls (they cost iterations, not accuracy).
    ///
    /// # Panics
    /// As [`PressureSolver3::new`], or if `fluid` does not have `n³` values.
    pub fn with_obstacles(n: usize, tolerance: f64, max_iterations: usize, precond: Preconditioner, fluid: Vec<f64>) -> Self {
        assert_eq!(fluid.len(), n * n * n, "fluid mask length");
        let solid_beside = super::solid_neighbours(&Smoke3d::new(n, n, n, 1.0), &fluid);
        let obstacles = Some(Masked { buf: vec![0.0; fluid.len()], fluid, solid_beside });
        Self { obstacles, ..Self::new(n, tolerance, max_iterations, precond) }
    }

    /// The fluid mask (1 fluid, 0 solid) when there are obstacles.
    pub fn fluid(&self) -> Option<&[f64]> {
        self.obstacles.as_ref().map(|m| &m.fluid[..])
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
        let Some(m) = &mut self.obstacles else {
            return apply_box_matrix(self.n, self.n, p, out);
        };
        // W·(A_box·(W·p) − S·p) + (I − W)·p.
        for ((b, &p), &w) in m.buf.iter_mut().zip(p).zip(&m.fluid) {
            *b = w * p;
        }
        apply_box_matrix(self.n, self.n, &m.buf, out);
        for (((o, &p), &w), &s) in out.iter_mut().zip(p).zip(&m.fluid).zip(&m.solid_beside) {
            *o = w * (*o - s * p) + (1.0 - w) * p;
        }
    }

    /// Constants (on the fluid cells): the box is closed.
    fn null(&self) -> Null<'_> {
        Null::Constant(self.fluid())
    }

    fn precondition(&mut self, r: &[f64], z: &mut [f64]) -> bool {
        let Some(mg) = &mut self.mg else {
            return false;
        };
        match &mut self.obstacles {
            None => mg.apply(r, z),
            Some(m) => {
                // W·M·(W·r) + (I − W)·r.
                for ((b, &r), &w) in m.buf.iter_mut().zip(r).zip(&m.fluid) {
                    *b = w * r;
                }
                mg.apply(&m.buf, z);
                for ((z, &r), &w) in z.iter_mut().zip(r).zip(&m.fluid) {
                    *z = w * *z + (1.0 - w) * r;
                }
            }
        }
        true
    }
}

/// P4's step 5 in place on the velocity part of the packed state `y`: the
/// solve `A·p = −D·(u, v, w)`, then `(u, v, w) −= G·p` on the interior
/// faces. Returns the CG iterations. With obstacles, the velocity must
/// hold no flow through the faces of solid cells before (then `D·(u, v,
/// w)` is zero in them) and be masked again after
/// ([`apply_obstacle_mask3`](super::apply_obstacle_mask3)): the gradient
/// across a face beside a solid cell is then dropped, and the result is
/// divergence-free in every fluid cell.
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
