//! The pressure projection: divergence and its transpose, the pressure
//! matrix of a box with walls, inflow, outflow, periodic sides and
//! obstacles, and its solve by preconditioned conjugate gradients (with the
//! adjoint, the same solve).

use super::*;
use crate::boundary::Boundary;
use std::fmt;

/// Calls `f(c, face, first)` for every cell `c` of the box with the index
/// of its lower face along `a` (the upper one a stride of the face array
/// further) and whether it is the first cell along `a`: the closed boxes'
/// plain loops.
#[inline(always)]
fn cell_faces<const D: usize>(cfg: &MacGrid<D>, a: usize, mut f: impl FnMut(usize, usize, bool)) {
    let mac = cfg.bounded();
    let (cells, faces) = (mac.lattice(At::Centre), mac.lattice(At::Face(a)));
    for k in 0..cells.n[D - 1] {
        for r in 0..cells.rows_per_slab() {
            let mut q = cells.row_start(k, r);
            for i in 0..cells.n[0] {
                q[0] = i;
                f(cells.index(q), faces.index(q), q[a] == 0);
            }
        }
    }
}

/// Divergence of a MAC velocity, `d[c] = Σ` outward flux over the faces
/// of cell `c` (overwrites `d`): `Σ_a u_a[upper face] − u_a[lower face]`
/// inside the box; a periodic axis's face `N` is not read (face `0` wraps).
/// In 2D and 3D, `vel` the components.
pub fn divergence<const D: usize>(cfg: &MacGrid<D>, vel: [&[f64]; D], d: &mut [f64]) {
    if cfg.is_closed() {
        // P2's and P4's box in plain loops.
        d.fill(0.0);
        for (a, u) in vel.into_iter().enumerate() {
            let up = cfg.face_dims(a)[..a].iter().product::<usize>();
            cell_faces(cfg, a, |c, f, _| d[c] += u[f + up] - u[f]);
        }
        return;
    }
    d.fill(0.0);
    for (axis, u) in vel.into_iter().enumerate() {
        for_each_face(cfg.n, &cfg.boundary, axis, |f| {
            let w = u[f.index];
            if let Some(c) = f.lower {
                d[c] += w;
            }
            if let Some(c) = f.upper {
                d[c] -= w;
            }
        });
    }
}

/// Transpose of [`divergence`]: `vel += Dᵀ·d` (accumulates).
pub fn divergence_transpose<const D: usize>(cfg: &MacGrid<D>, d: &[f64], vel: [&mut [f64]; D]) {
    if cfg.is_closed() {
        for (a, u) in vel.into_iter().enumerate() {
            let up = cfg.face_dims(a)[..a].iter().product::<usize>();
            cell_faces(cfg, a, |c, f, _| {
                u[f + up] += d[c];
                u[f] -= d[c];
            });
        }
        return;
    }
    for (axis, u) in vel.into_iter().enumerate() {
        for_each_face(cfg.n, &cfg.boundary, axis, |f| u[f.index] += f.lower.map_or(0.0, |c| d[c]) - f.upper.map_or(0.0, |c| d[c]));
    }
}

/// `vel −= G·p` on the faces the projection changes (interior, periodic,
/// outflow; with `fluid`, scaled by the face's openness, fluid–fluid only):
/// the pressure difference across each face, upper cell minus lower (`p = 0`
/// beyond an outflow side); periodic copies refreshed. In 2D and 3D.
pub fn subtract_gradient<const D: usize>(cfg: &MacGrid<D>, fluid: Option<&[f64]>, p: &[f64], vel: [&mut [f64]; D]) {
    if cfg.is_closed() && fluid.is_none() {
        // P2's and P4's box: the interior faces, each the lower face of a
        // cell past the first along its axis.
        for (a, u) in vel.into_iter().enumerate() {
            let down = cfg.n[..a].iter().product::<usize>();
            cell_faces(cfg, a, |c, f, first| {
                if !first {
                    u[f] -= p[c] - p[c - down];
                }
            });
        }
        return;
    }
    for (axis, u) in vel.into_iter().enumerate() {
        for_each_face(cfg.n, &cfg.boundary, axis, |f| {
            if f.projected {
                u[f.index] -= open(fluid, &f) * (f.upper.map_or(0.0, |c| p[c]) - f.lower.map_or(0.0, |c| p[c]));
                if let Some(k) = f.copy {
                    u[k] = u[f.index];
                }
            }
        });
    }
}

/// Transpose of [`subtract_gradient`]'s `G` (with `fluid`'s openness) on
/// the faces the projection changes: `out = Gᵀ·g` (overwrites), after each
/// periodic copy's adjoint is handed to its face `0` (the copy is written
/// from it, never read).
pub fn gradient_transpose<const D: usize>(cfg: &MacGrid<D>, fluid: Option<&[f64]>, vel: [&mut [f64]; D], out: &mut [f64]) {
    out.fill(0.0);
    if cfg.is_closed() && fluid.is_none() {
        for (a, g) in vel.into_iter().enumerate() {
            let down = cfg.n[..a].iter().product::<usize>();
            cell_faces(cfg, a, |c, f, first| {
                if !first {
                    out[c] += g[f];
                    out[c - down] -= g[f];
                }
            });
        }
        return;
    }
    for (axis, g) in vel.into_iter().enumerate() {
        for_each_face(cfg.n, &cfg.boundary, axis, |f| {
            if !f.projected {
                return;
            }
            if let Some(k) = f.copy {
                g[f.index] += g[k];
                g[k] = 0.0;
            }
            let l = open(fluid, &f) * g[f.index];
            if let Some(c) = f.upper {
                out[c] += l;
            }
            if let Some(c) = f.lower {
                out[c] -= l;
            }
        });
    }
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
            across(i > 0, c.wrapping_sub(1), b.lower(0), c + n - 1);
            across(i + 1 < n, c + 1, b.upper(0), (c + 1).wrapping_sub(n));
            across(j > 0, c.wrapping_sub(n), b.lower(1), c + n * (ny - 1));
            across(j + 1 < ny, c + n, b.upper(1), i);
            out[c] = wt(c) * acc + (1.0 - wt(c)) * pc;
        }
    }
}

pub use crate::cg::NoConvergence;
use crate::cg::{CgWork, Null, Stop, System, dot};

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
    /// A sparse Cholesky factor of the matrix ([`crate::linalg::SparseCholesky`],
    /// computed once): a direct solve, so CG stops after one or two
    /// iterations. For rectangles with obstacles and outflow, where MIC(0)
    /// needs hundreds of iterations.
    Cholesky,
}

impl fmt::Display for Preconditioner {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        f.write_str(match self {
            Preconditioner::None => "none",
            Preconditioner::Mic0 => "mic0",
            Preconditioner::Multigrid => "multigrid",
            Preconditioner::Cholesky => "cholesky",
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
    /// The sparse Cholesky factor (of the matrix with one cell pinned when
    /// it is singular).
    chol: Option<crate::linalg::SparseCholesky>,
    /// Fluid indicator per cell (1 fluid, 0 solid) when there are obstacles.
    fluid: Option<Vec<f64>>,
    boundary: Boundary,
    work: CgWork,
}

impl PressureSolver {
    /// The relative tolerance its solves stop at.
    pub fn tolerance(&self) -> f64 {
        self.tolerance
    }

    /// A solver for the `n × n` box with tolerance `tolerance`, at most
    /// `max_iterations` iterations, and the given preconditioner.
    pub fn new(n: usize, tolerance: f64, max_iterations: usize, precond: Preconditioner) -> Self {
        if precond == Preconditioner::Cholesky {
            // The closed box's matrix with one cell pinned is definite: only
            // running out of memory can fail.
            return Self::general_direct(n, n, Boundary::CLOSED, tolerance, max_iterations, None).expect("sparse Cholesky of the closed box's pressure matrix");
        }
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
            chol: None,
            fluid: None,
            boundary: Boundary::CLOSED,
            work: CgWork::new(z.len()),
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
            chol: None,
            fluid,
            boundary,
            work: CgWork::new(z.len()),
        };
        s.factor_general();
        s
    }

    /// [`PressureSolver::general`] with the sparse Cholesky factor of the
    /// matrix as the preconditioner ([`Preconditioner::Cholesky`]): a direct
    /// solve, for large rectangles with obstacles and outflow.
    pub fn general_direct(
        nx: usize,
        ny: usize,
        boundary: Boundary,
        tolerance: f64,
        max_iterations: usize,
        fluid: Option<Vec<f64>>,
    ) -> Result<Self, crate::linalg::FactorFailed> {
        let mut s = Self::general(nx, ny, boundary, tolerance, max_iterations, fluid);
        s.chol = Some(crate::linalg::SparseCholesky::new(nx * ny, &s.lower_triplets())?);
        s.precond = Preconditioner::Cholesky;
        Ok(s)
    }

    /// A direct solver ([`Preconditioner::Cholesky`]) for the matrix of
    /// faces open by fractions: `(A·p)[c] = Σ_f a_f·(p_c − p_m)` over the
    /// cell's faces `f` with apertures `a_f ∈ [0, 1]` (`aperture_u` in the
    /// x-face layout, `aperture_v` in the y-face layout), the neighbour `m`
    /// a ghost `p = 0` across an outflow side, nothing across a wall or an
    /// inflow side: the projection onto velocities whose aperture-weighted
    /// flux balances in every cell (cut cells). Cells with every face shut
    /// are identity rows. Periodic sides are not supported here.
    ///
    /// # Panics
    /// If a side is periodic or an aperture array has the wrong length.
    pub fn with_apertures(
        nx: usize,
        ny: usize,
        boundary: Boundary,
        tolerance: f64,
        max_iterations: usize,
        aperture_u: &[f64],
        aperture_v: &[f64],
    ) -> Result<Self, crate::linalg::FactorFailed> {
        assert!(!boundary.periodic(0) && !boundary.periodic(1), "apertures with periodic sides");
        assert_eq!(aperture_u.len(), ny * (nx + 1), "x-face apertures");
        assert_eq!(aperture_v.len(), (ny + 1) * nx, "y-face apertures");
        let mut k = Coefficients { diag: vec![0.0; nx * ny], ax: vec![0.0; nx * ny], ay: vec![0.0; nx * ny], wraps: false };
        let side = |s: Side| if s == Side::Outflow { 1.0 } else { 0.0 };
        for j in 0..ny {
            for i in 0..nx {
                let c = j * nx + i;
                let (l, r) = (aperture_u[j * (nx + 1) + i], aperture_u[j * (nx + 1) + i + 1]);
                let (d, u) = (aperture_v[j * nx + i], aperture_v[(j + 1) * nx + i]);
                let sum = l * if i > 0 { 1.0 } else { side(boundary.lower(0)) }
                    + r * if i + 1 < nx { 1.0 } else { side(boundary.upper(0)) }
                    + d * if j > 0 { 1.0 } else { side(boundary.lower(1)) }
                    + u * if j + 1 < ny { 1.0 } else { side(boundary.upper(1)) };
                k.diag[c] = sum;
                k.ax[c] = if i + 1 < nx { -r } else { 0.0 };
                k.ay[c] = if j + 1 < ny { -u } else { 0.0 };
            }
        }
        // Cells coupled to nothing: identity rows, and not fluid (for the
        // mean removed in a closed box).
        let open: Vec<f64> = (0..nx * ny)
            .map(|c| {
                if k.diag[c] > 0.0 || k.ax[c] != 0.0 || k.ay[c] != 0.0 || (c > 0 && k.ax[c - 1] != 0.0) || (c >= nx && k.ay[c - nx] != 0.0) { 1.0 } else { 0.0 }
            })
            .collect();
        for (d, &o) in k.diag.iter_mut().zip(&open) {
            if o == 0.0 {
                *d = 1.0;
            }
        }
        let z = vec![0.0; nx * ny];
        let mut s = Self {
            nx,
            ny,
            tolerance,
            max_iterations,
            precond: Preconditioner::Cholesky,
            inv_diag: z.clone(),
            coeffs: None,
            mg: None,
            chol: None,
            fluid: Some(open),
            boundary,
            work: CgWork::new(z.len()),
        };
        s.factor_mic0(k);
        s.chol = Some(crate::linalg::SparseCholesky::new(nx * ny, &s.lower_triplets())?);
        Ok(s)
    }

    /// The lower triangle of the general matrix, `(row, column, value)`,
    /// with the couplings across periodic sides; a singular matrix (no
    /// outflow side) gets 1 added to its first fluid cell's diagonal, which
    /// makes it definite (the solve removes the null component itself).
    fn lower_triplets(&self) -> Vec<(usize, usize, f64)> {
        let (nx, ny, b) = (self.nx, self.ny, self.boundary);
        let k = self.coeffs.as_ref().expect("coefficients of the general matrix");
        let w = |c: usize| self.fluid.as_ref().map_or(1.0, |w| w[c]);
        let mut t = Vec::with_capacity(3 * nx * ny);
        let pinned = (!b.has_outflow()).then(|| (0..nx * ny).find(|&c| w(c) > 0.0)).flatten();
        for c in 0..nx * ny {
            t.push((c, c, k.diag[c] + if Some(c) == pinned { 1.0 } else { 0.0 }));
            if k.ax[c] != 0.0 {
                t.push((c + 1, c, k.ax[c]));
            }
            if k.ay[c] != 0.0 {
                t.push((c + nx, c, k.ay[c]));
            }
        }
        // Wrapped couplings: the last column with the first, the top row with the bottom.
        if b.periodic(0) && nx > 2 {
            for j in 0..ny {
                let (first, last) = (j * nx, j * nx + nx - 1);
                t.push((last, first, -w(first) * w(last)));
            }
        }
        if b.periodic(1) && ny > 2 {
            for i in 0..nx {
                let (bottom, top) = (i, (ny - 1) * nx + i);
                t.push((top, bottom, -w(bottom) * w(top)));
            }
        }
        t
    }

    /// MIC(0) of the general matrix (Bridson, §5, with its couplings):
    /// diagonal and couplings read off [`apply_boundary_matrix`] applied to
    /// unit vectors' closed forms.
    fn factor_general(&mut self) {
        let k = self.coefficients_general();
        self.factor_mic0(k);
    }

    /// The general matrix's coefficients from the cells' fluid weights.
    fn coefficients_general(&self) -> Coefficients {
        let (nx, ny, b) = (self.nx, self.ny, self.boundary);
        let w = |c: usize| self.fluid.as_ref().map_or(1.0, |w| w[c]);
        let mut k = Coefficients { diag: vec![0.0; nx * ny], ax: vec![0.0; nx * ny], ay: vec![0.0; nx * ny], wraps: b.periodic(0) || b.periodic(1) };
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
                let sum = side(i > 0, c.wrapping_sub(1), b.lower(0), c + nx - 1)
                    + side(i + 1 < nx, c + 1, b.upper(0), (c + 1).wrapping_sub(nx))
                    + side(j > 0, c.wrapping_sub(nx), b.lower(1), c + nx * (ny - 1))
                    + side(j + 1 < ny, c + nx, b.upper(1), i);
                k.diag[c] = w(c) * sum + (1.0 - w(c));
                k.ax[c] = if i + 1 < nx { -w(c) * w(c + 1) } else { 0.0 };
                k.ay[c] = if j + 1 < ny { -w(c) * w(c + nx) } else { 0.0 };
            }
        }
        k
    }

    /// MIC(0) of the matrix with coefficients `k`, which it keeps.
    fn factor_mic0(&mut self, k: Coefficients) {
        const TAU: f64 = 0.97;
        const SIGMA: f64 = 0.25;
        let (nx, n) = (self.nx, self.nx * self.ny);
        let pc = &mut self.inv_diag;
        for c in 0..n {
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

    /// Solves `A·p = b` from `p = 0` until `‖b − A·p‖₂ ≤ tol·‖b‖₂` (true
    /// residual); overwrites `p`. Without an outflow side the matrix is
    /// singular and `b` must sum to zero over the fluid (the compatibility
    /// condition); it is projected onto that space to remove rounding, and
    /// the solution returned is the one with zero mean on the fluid.
    /// Returns the number of iterations.
    pub fn solve(&mut self, b: &[f64], p: &mut [f64]) -> Result<usize, NoConvergence> {
        self.solve_impl(b, p, false)
    }

    /// [`PressureSolver::solve`] starting from the `p` given instead of
    /// zero: the same tolerance relative to `‖b‖`, fewer iterations when `p`
    /// is already close.
    pub fn solve_from(&mut self, b: &[f64], p: &mut [f64]) -> Result<usize, NoConvergence> {
        self.solve_impl(b, p, true)
    }

    fn solve_impl(&mut self, b: &[f64], p: &mut [f64], warm: bool) -> Result<usize, NoConvergence> {
        let stop = Stop { tolerance: self.tolerance, max_iterations: self.max_iterations };
        let mut work = std::mem::take(&mut self.work);
        let result = crate::cg::solve(self, &mut work, stop, b, p, warm);
        self.work = work;
        result
    }

    /// Whether the closed square box's fused product applies.
    fn special(&self) -> bool {
        self.fluid.is_none() && self.boundary == Boundary::CLOSED && self.nx >= 2
    }
}

impl System for PressureSolver {
    fn apply(&mut self, p: &[f64], out: &mut [f64]) {
        if self.special() {
            apply_pressure_matrix(self.nx, self.ny, p, out);
        } else {
            self.apply_general(p, out);
        }
    }

    fn apply_dot(&mut self, d: &[f64], q: &mut [f64]) -> f64 {
        if self.special() {
            let mut dq = 0.0;
            matvec_dot(self.nx, self.ny, d, q, &mut dq);
            dq
        } else {
            self.apply_general(d, q);
            dot(d, q)
        }
    }

    /// Constants on the fluid cells, unless a side lets fluid out.
    fn null(&self) -> Null<'_> {
        if self.boundary.has_outflow() { Null::None } else { Null::Constant(self.fluid.as_deref()) }
    }

    /// `z = M⁻¹·r` (MIC(0): forward then backward substitution).
    fn precondition(&mut self, r: &[f64], z: &mut [f64]) -> bool {
        match self.precond {
            Preconditioner::None => return false,
            Preconditioner::Mic0 if self.coeffs.is_some() => {
                let k = self.coeffs.as_ref().expect("coefficients");
                mic0_general(self.nx, &k.ax, &k.ay, &self.inv_diag, r, z)
            }
            Preconditioner::Mic0 => mic0_apply(self.nx, &self.inv_diag, r, z),
            Preconditioner::Multigrid => self.mg.as_mut().expect("multigrid hierarchy").apply(r, z),
            Preconditioner::Cholesky => {
                z.copy_from_slice(r);
                self.chol.as_ref().expect("Cholesky factor").solve_in_place(z);
            }
        }
        true
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

/// Scratch of the projection (2D and 3D): divergence and pressure.
#[derive(Clone, Debug)]
pub struct ProjectScratch {
    pub(crate) d: Vec<f64>,
    pub(crate) p: Vec<f64>,
}

impl ProjectScratch {
    /// Scratch for a box of `cells` cells.
    pub fn new(cells: usize) -> Self {
        Self { d: vec![0.0; cells], p: vec![0.0; cells] }
    }

    /// The pressure of the last projection, in the projection's units: the
    /// velocity changed by its unit-spaced differences (`u −= p[c+1] − p[c]`).
    pub fn pressure(&self) -> &[f64] {
        &self.p
    }

    /// Multiplies the kept pressure by `r` (a warm start for a projection
    /// whose step is `r` times the last one's).
    pub fn scale_pressure(&mut self, r: f64) {
        self.p.iter_mut().for_each(|p| *p *= r);
    }
}

/// Step 5 of P2, for any boundary, in place on the velocity part of the
/// packed state `y`: `d = D·(u, v)`, solve `A·p = −W·d` (`W` the fluid
/// mask), `(u, v) −= G·p` on the faces the projection changes (interior,
/// periodic, outflow; fluid–fluid only), periodic copies refreshed. The
/// solver must be built for `cfg`'s boundary. Returns the CG iterations.
pub fn project(cfg: &MacGrid<2>, y: &mut [f64], solver: &mut PressureSolver, scratch: &mut ProjectScratch) -> Result<usize, NoConvergence> {
    let (_, [u, v]) = cfg.split_mut(y);
    project_velocity(cfg, u, v, None, None, solver, scratch, false)
}

/// [`project`] on separate velocity arrays. With `warm`, the solve starts
/// from the pressure left in `scratch` by the previous call (fewer
/// iterations when consecutive projections are alike, as in a march to a
/// steady state) instead of from zero; either way it ends at the same
/// tolerance. The pressure stays in `scratch` ([`ProjectScratch::pressure`]).
///
/// With `apertures` (x-faces, y-faces), the divergence weighs each face's
/// flux by its open fraction and every face open by any fraction takes the
/// pressure gradient (cut cells), scaled per face by `grad_scale` (packed
/// `[u, v]`; 1 without): the projection `y − M·G·p` with `D_a·M·G·p = D_a·y`,
/// whose solver [`PressureSolver::with_apertures`] builds from the products
/// `a_f·M_f`.
#[allow(clippy::too_many_arguments)]
pub fn project_velocity(
    cfg: &MacGrid<2>,
    u: &mut [f64],
    v: &mut [f64],
    apertures: Option<(&[f64], &[f64])>,
    grad_scale: Option<&[f64]>,
    solver: &mut PressureSolver,
    scratch: &mut ProjectScratch,
    warm: bool,
) -> Result<usize, NoConvergence> {
    debug_assert_eq!(solver.boundary, cfg.boundary, "pressure solver built for another boundary");
    let weight = |axis: usize, k: usize| apertures.map_or(1.0, |(au, av)| if axis == 0 { au[k] } else { av[k] });
    match apertures {
        None => divergence(cfg, [u, v], &mut scratch.d),
        Some(_) => {
            let d = &mut scratch.d;
            d.fill(0.0);
            for (axis, vel) in [&*u, &*v].into_iter().enumerate() {
                for_each_face(cfg.n, &cfg.boundary, axis, |f| {
                    let w = weight(axis, f.index) * vel[f.index];
                    if let Some(c) = f.lower {
                        d[c] += w;
                    }
                    if let Some(c) = f.upper {
                        d[c] -= w;
                    }
                });
            }
        }
    }
    for d in scratch.d.iter_mut() {
        *d = -*d;
    }
    if let Some(w) = solver.fluid() {
        for (d, &wv) in scratch.d.iter_mut().zip(w) {
            *d *= wv;
        }
    }
    let iterations = if warm { solver.solve_from(&scratch.d, &mut scratch.p)? } else { solver.solve(&scratch.d, &mut scratch.p)? };
    let (p, fluid) = (&scratch.p, solver.fluid());
    let Some(_) = apertures else {
        debug_assert!(grad_scale.is_none(), "a gradient scale goes with apertures");
        subtract_gradient(cfg, fluid, p, [u, v]);
        return Ok(iterations);
    };
    // Cut cells: every face open by any fraction takes the gradient, scaled.
    for (axis, vel) in [u, v].into_iter().enumerate() {
        for_each_face(cfg.n, &cfg.boundary, axis, |f| {
            if f.projected {
                let grad = f.upper.map_or(0.0, |c| p[c]) - f.lower.map_or(0.0, |c| p[c]);
                let open =
                    (weight(axis, f.index) > 0.0) as u8 as f64 * grad_scale.map_or(1.0, |m| m[if axis == 0 { f.index } else { cfg.n_face(0) + f.index }]);
                vel[f.index] -= open * grad;
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
pub fn project_adjoint(cfg: &MacGrid<2>, g: &mut [f64], solver: &mut PressureSolver, scratch: &mut ProjectScratch) -> Result<usize, NoConvergence> {
    let (_, [gu, gv]) = cfg.split_mut(g);
    let lp = &mut scratch.d;
    gradient_transpose(cfg, solver.fluid(), [&mut *gu, &mut *gv], lp);
    for l in lp.iter_mut() {
        *l = -*l;
    }
    let iterations = solver.solve(lp, &mut scratch.p)?;
    for (c, m) in scratch.p.iter_mut().enumerate() {
        *m = -*m * solver.fluid().map_or(1.0, |w| w[c]);
    }
    divergence_transpose(cfg, &scratch.p, [gu, gv]);
    Ok(iterations)
}
