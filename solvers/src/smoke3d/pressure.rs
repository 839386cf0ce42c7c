//! The 3D pressure projection: divergence over the six faces of each cell,
//! the seven-point matrix (coupling fluid cells only when there are
//! obstacles; across periodic sides; a ghost `p = 0` beyond outflow
//! sides), its solve by conjugate gradients ([`crate::cg`], preconditioned
//! by a multigrid V-cycle of [`crate::multigrid`]: the geometric one in a
//! closed box with two equal sides, the aggregation one in any other box;
//! or by MIC(0)), and the projection's adjoint (the same solve).

use super::mic::{Mic3, apply_general_matrix3};
use super::*;
use crate::cg::{CgWork, NoConvergence, Null, Stop, System};
use crate::multigrid::{AggregateMultigrid, Multigrid, apply_box_matrix};
use crate::smoke::{Preconditioner, ProjectScratch, divergence, divergence_transpose, gradient_transpose, subtract_gradient};

/// Conjugate gradients on the pressure matrix of a box (any sides), with or
/// without solid cells, preconditioned by a multigrid V-cycle, MIC(0) of
/// the matrix or not at all, with its work vectors kept between solves.
#[derive(Clone, Debug)]
pub struct PressureSolver3 {
    cfg: MacGrid<3>,
    /// The stopping rule.
    pub stop: Stop,
    precond: Precond3,
    obstacles: Option<Masked>,
    work: CgWork,
}

/// The preconditioner of a 3D solve.
#[derive(Clone, Debug)]
enum Precond3 {
    None,
    /// The V-cycle of square slabs stacked along an axis, with two buffers
    /// for the fields reordered so that axis comes last.
    Multigrid(Multigrid, usize, [Vec<f64>; 2]),
    /// The aggregation V-cycle of any box and sides.
    Aggregate(AggregateMultigrid),
    Mic(Mic3),
}

/// The axis along which a box is a stack of square slabs (the other two
/// sides equal), z first: what the multigrid needs.
pub fn slab_axis([nx, ny, nz]: [usize; 3]) -> Option<usize> {
    if nx == ny {
        Some(2)
    } else if nx == nz {
        Some(1)
    } else if ny == nz {
        Some(0)
    } else {
        None
    }
}

/// Reorders a field of the box `dims` so that `axis` comes last (slabs
/// along it), or back (`back`). Along z it is a copy.
fn reorder(dims: [usize; 3], axis: usize, from: &[f64], to: &mut [f64], back: bool) {
    let [nx, ny, nz] = dims;
    for k in 0..nz {
        for j in 0..ny {
            for i in 0..nx {
                let c = (k * ny + j) * nx + i;
                let r = match axis {
                    2 => c,
                    1 => (j * nz + k) * nx + i,
                    _ => (i * nz + k) * ny + j,
                };
                if back {
                    to[c] = from[r];
                } else {
                    to[r] = from[c];
                }
            }
        }
    }
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
    /// The relative tolerance its solves stop at.
    pub fn tolerance(&self) -> f64 {
        self.stop.tolerance
    }

    /// A solver for the box `cfg` (any sides): relative `tolerance` on the true
    /// residual, more than `max_iterations` an error, preconditioned by
    /// [`Preconditioner::Multigrid`] (a closed box with two equal sides: the
    /// geometric V-cycle of a stack of square slabs, reordered so that they
    /// lie along z when they do not; any other box: the aggregation V-cycle
    /// of [`AggregateMultigrid`]), [`Preconditioner::Mic0`] or
    /// [`Preconditioner::None`].
    ///
    /// # Panics
    /// For the Cholesky preconditioner (2D only).
    pub fn new(cfg: &MacGrid<3>, tolerance: f64, max_iterations: usize, precond: Preconditioner) -> Self {
        Self::build(cfg, tolerance, max_iterations, precond, None)
    }

    /// A solver for the box `cfg` with solid cells where `fluid[c] =
    /// 0`: the matrix `W·(A_box·W − S) + (I − W)`, which couples fluid cells
    /// across their shared faces only (`S` counts the solid cells beside
    /// each cell) and keeps solid rows as the identity; symmetric, the
    /// constants on the fluid cells its null space (with no outflow side).
    /// The multigrid preconditioner is the box's V-cycle on the fluid cells,
    /// `W·M·W + (I − W)`: symmetric and positive, blind to the obstacles'
    /// walls (they cost iterations, not accuracy); MIC(0) is built for the
    /// matrix itself.
    ///
    /// # Panics
    /// As [`PressureSolver3::new`], or if `fluid` does not have a value per cell.
    pub fn with_obstacles(cfg: &MacGrid<3>, tolerance: f64, max_iterations: usize, precond: Preconditioner, fluid: Vec<f64>) -> Self {
        assert_eq!(fluid.len(), cfg.n_s(), "fluid mask length");
        Self::build(cfg, tolerance, max_iterations, precond, Some(fluid))
    }

    fn build(cfg: &MacGrid<3>, tolerance: f64, max_iterations: usize, precond: Preconditioner, fluid: Option<Vec<f64>>) -> Self {
        let dims = cfg.n;
        let precond = match (precond, slab_axis(dims)) {
            (Preconditioner::Multigrid, Some(axis)) if cfg.is_closed() => {
                let side = dims[(axis + 1) % 3];
                let buffers = if axis == 2 { [Vec::new(), Vec::new()] } else { [vec![0.0; cfg.n_s()], vec![0.0; cfg.n_s()]] };
                Precond3::Multigrid(Multigrid::slabs(side, dims[axis]), axis, buffers)
            }
            (Preconditioner::Multigrid, _) => Precond3::Aggregate(AggregateMultigrid::new(dims, cfg.boundary)),
            (Preconditioner::Mic0, _) => Precond3::Mic(Mic3::new(cfg, fluid.as_deref())),
            (Preconditioner::None, _) => Precond3::None,
            (other, _) => panic!("3D pressure solves take multigrid, MIC(0) or no preconditioner, not {other}"),
        };
        let obstacles = fluid.map(|fluid| Masked { buf: vec![0.0; fluid.len()], solid_beside: crate::smoke::solid_neighbours(cfg, &fluid), fluid });
        Self { cfg: *cfg, stop: Stop { tolerance, max_iterations }, precond, obstacles, work: CgWork::new(cfg.n_s()) }
    }

    /// The fluid mask (1 fluid, 0 solid) when there are obstacles.
    pub fn fluid(&self) -> Option<&[f64]> {
        self.obstacles.as_ref().map(|m| &m.fluid[..])
    }

    /// The preconditioner in use.
    pub fn preconditioner(&self) -> Preconditioner {
        match self.precond {
            Precond3::None => Preconditioner::None,
            Precond3::Multigrid(..) | Precond3::Aggregate(_) => Preconditioner::Multigrid,
            Precond3::Mic(_) => Preconditioner::Mic0,
        }
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
        let [nx, ny, nz] = self.cfg.n;
        let square = nx == ny && self.cfg.is_closed();
        match &mut self.obstacles {
            // The square slabs' fast product.
            None if square => apply_box_matrix(nx, nz, p, out),
            None => apply_general_matrix3(&self.cfg, None, p, out),
            Some(m) if square => {
                // W·(A_box·(W·p) − S·p) + (I − W)·p.
                for ((b, &p), &w) in m.buf.iter_mut().zip(p).zip(&m.fluid) {
                    *b = w * p;
                }
                apply_box_matrix(nx, nz, &m.buf, out);
                for (((o, &p), &w), &s) in out.iter_mut().zip(p).zip(&m.fluid).zip(&m.solid_beside) {
                    *o = w * (*o - s * p) + (1.0 - w) * p;
                }
            }
            Some(m) => apply_general_matrix3(&self.cfg, Some(&m.fluid), p, out),
        }
    }

    /// Constants (on the fluid cells) unless a side is an outflow.
    fn null(&self) -> Null<'_> {
        if self.cfg.boundary.has_outflow() { Null::None } else { Null::Constant(self.fluid()) }
    }

    fn precondition(&mut self, r: &[f64], z: &mut [f64]) -> bool {
        let dims = self.cfg.n;
        // The V-cycle of the slabs along `axis`.
        let cycle = |mg: &mut Multigrid, axis: usize, [a, b]: &mut [Vec<f64>; 2], r: &[f64], z: &mut [f64]| {
            if axis == 2 {
                return mg.apply(r, z);
            }
            reorder(dims, axis, r, a, false);
            mg.apply(a, b);
            reorder(dims, axis, b, z, true);
        };
        match (&mut self.precond, &mut self.obstacles) {
            (Precond3::None, _) => return false,
            (Precond3::Mic(mic), _) => mic.apply(r, z),
            (Precond3::Multigrid(mg, axis, bufs), None) => cycle(mg, *axis, bufs, r, z),
            (Precond3::Aggregate(mg), None) => mg.apply(r, z),
            (Precond3::Aggregate(mg), Some(m)) => {
                // W·M·(W·r) + (I − W)·r, as for the geometric V-cycle.
                for ((b, &r), &w) in m.buf.iter_mut().zip(r).zip(&m.fluid) {
                    *b = w * r;
                }
                mg.apply(&m.buf, z);
                for ((z, &r), &w) in z.iter_mut().zip(r).zip(&m.fluid) {
                    *z = w * *z + (1.0 - w) * r;
                }
            }
            (Precond3::Multigrid(mg, axis, bufs), Some(m)) => {
                // W·M·(W·r) + (I − W)·r.
                for ((b, &r), &w) in m.buf.iter_mut().zip(r).zip(&m.fluid) {
                    *b = w * r;
                }
                cycle(mg, *axis, bufs, &m.buf, z);
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
/// ([`apply_obstacle_mask`](crate::smoke::apply_obstacle_mask)): the gradient
/// across a face beside a solid cell is then dropped, and the result is
/// divergence-free in every fluid cell.
pub fn project(cfg: &MacGrid<3>, y: &mut [f64], solver: &mut PressureSolver3, scratch: &mut ProjectScratch) -> Result<usize, NoConvergence> {
    let (_, [u, v, w]) = cfg.split_mut(y);
    divergence(cfg, [u, v, w], &mut scratch.d);
    for d in scratch.d.iter_mut() {
        *d = -*d;
    }
    let it = solver.solve(&scratch.d, &mut scratch.p)?;
    subtract_gradient(cfg, None, &scratch.p, [u, v, w]);
    Ok(it)
}

/// Adjoint of [`project`] (a linear map), in place on the velocity part of
/// the adjoint `g`: `λ_p = −Gᵀ·λ`, the solve `A·μ = λ_p` (the transposed —
/// here the same — system to the same tolerance), `λ += −Dᵀ·μ`. Returns
/// the CG iterations.
pub fn project_adjoint(cfg: &MacGrid<3>, g: &mut [f64], solver: &mut PressureSolver3, scratch: &mut ProjectScratch) -> Result<usize, NoConvergence> {
    let (_, [gu, gv, gw]) = cfg.split_mut(g);
    gradient_transpose(cfg, None, [&mut *gu, &mut *gv, &mut *gw], &mut scratch.d);
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
