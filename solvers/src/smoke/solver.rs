//! The pressure solve of the projection, written once for 2D and 3D: the
//! pressure matrix of a box with any sides (closed, inflow, outflow,
//! periodic) and solid cells, and conjugate gradients on it
//! ([`crate::cg`]) with a choice of preconditioners.
//!
//! The matrix is `(A·p)[c] = w_c·Σ_m w_m·(p_c − p_m) + (1 − w_c)·p_c` over
//! the neighbours `m` across the faces of cell `c` that the projection
//! changes (inside the box, wrapped across a periodic side, a ghost `p = 0`
//! across an outflow side; closed and inflow sides add nothing), `w` the
//! fluid indicator (1 without obstacles): only fluid–fluid faces couple,
//! solid rows are the identity. Symmetric; without an outflow side the
//! constants on the fluid cells are its null space.
//!
//! One rule picks how it is applied, whatever the dimension:
//! - a closed box of square slabs along the last axis (P2's square, P4's
//!   cube): the fused slab product of [`crate::multigrid`] (in 2D with the
//!   product and the dot product of conjugate gradients in one pass);
//! - any other box without a periodic side: the coefficient form
//!   ([`Coefficients`]: the diagonal and one coupling per axis, `2D + 1`
//!   shifted streams, branch-free);
//! - a box with a periodic side: the stencil of
//!   [`crate::multigrid::apply_stencil`] (a 2D box is a 3D box one cell
//!   deep between closed sides).
//!
//! Preconditioners ([`Preconditioner`]): the geometric multigrid V-cycle in
//! a closed box with two equal sides (reordered so that its square slabs lie
//! along the last axis), the aggregation V-cycle in any other box; MIC(0)
//! of the matrix ([`Mic`], Bridson, *Fluid Simulation for Computer
//! Graphics*, §5); a sparse Cholesky factor (a direct solve); or none.

use std::fmt;

use super::MacGrid;
use crate::boundary::{Boundary, Side};
pub use crate::cg::NoConvergence;
use crate::cg::{CgWork, Null, Stop, System, dot};
use crate::linalg::{FactorFailed, SparseCholesky};
use crate::multigrid::{Across, AggregateMultigrid, Multigrid, across, apply_box_matrix, apply_stencil};

/// Preconditioner of the pressure solve.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Preconditioner {
    /// None: plain conjugate gradients.
    None,
    /// Modified incomplete Cholesky, MIC(0), with the usual safety factor
    /// (Bridson, *Fluid Simulation for Computer Graphics*, §5).
    Mic0,
    /// One multigrid V-cycle ([`crate::multigrid`]): geometric in a closed
    /// box with two equal sides, by aggregation in any other.
    Multigrid,
    /// A sparse Cholesky factor of the matrix ([`SparseCholesky`], computed
    /// once): a direct solve, so CG stops after one or two iterations. For
    /// boxes with obstacles and outflow, where MIC(0) needs hundreds of
    /// iterations.
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

/// A box of `D` axes as a 3D one (a 2D box is one cell deep between closed
/// sides): what the stencil and the aggregation multigrid take.
fn padded<const D: usize>(grid: &MacGrid<D>) -> ([usize; 3], Boundary<3>) {
    let mut dims = [1; 3];
    let mut b = Boundary::<3>::CLOSED;
    dims[..D].copy_from_slice(&grid.n);
    b.sides[..D].copy_from_slice(&grid.boundary.sides);
    (dims, b)
}

/// The axis along which a box is a stack of square slabs (the other two
/// sides equal), the last first: what the geometric multigrid needs. A 2D
/// box is one cell deep along z, so a square is one slab along z.
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

/// The pressure matrix in coefficient form: `(A·p)[c] = diag[c]·p[c] +
/// Σ_a plus[a][c]·p[c + s_a] + plus[a][c − s_a]·p[c − s_a]`, with
/// `plus[a][c] = A[c][c + s_a]` (`s_a` the stride of axis `a`; 0 on the
/// last cell along `a`). Couplings across a periodic side are not in it
/// (`wraps`: the matrix has some).
#[derive(Clone, Debug)]
pub struct Coefficients<const D: usize> {
    diag: Vec<f64>,
    plus: [Vec<f64>; D],
    strides: [usize; D],
    wraps: bool,
}

impl<const D: usize> Coefficients<D> {
    /// The matrix of the box `grid` with solid cells where `fluid[c] = 0`
    /// (`None`: none): the diagonal counts every coupling (periodic and
    /// outflow sides too), the couplings those inside the box.
    pub fn new(grid: &MacGrid<D>, fluid: Option<&[f64]>) -> Self {
        let (dims, b) = padded(grid);
        let n = grid.n_s();
        let w = |c: usize| fluid.map_or(1.0, |f| f[c]);
        let strides = strides(grid.n);
        let at = |c: usize| [c % dims[0], (c / dims[0]) % dims[1], c / (dims[0] * dims[1])];
        let plus = std::array::from_fn(|a| (0..n).map(|c| if at(c)[a] + 1 < dims[a] { -w(c) * w(c + strides[a]) } else { 0.0 }).collect());
        let diag = (0..n)
            .map(|c| {
                let mut s = 0.0;
                for a in 0..D {
                    for m in across(dims, &b, c, at(c), a) {
                        s += match m {
                            Across::Cell(m) => w(m),
                            Across::Ghost => 1.0,
                            Across::Wall => 0.0,
                        };
                    }
                }
                w(c) * s + (1.0 - w(c))
            })
            .collect();
        Self { diag, plus, strides, wraps: grid.boundary.wraps().contains(&true) }
    }

    /// The matrix of faces open by fractions (cut cells): `(A·p)[c] = Σ_f
    /// a_f·(p_c − p_m)` over the cell's faces `f` with apertures `a_f ∈ [0,
    /// 1]` (`apertures[a]` in the layout of the faces normal to axis `a`),
    /// `m` a ghost `p = 0` across an outflow side, nothing across a wall or
    /// an inflow side; cells with every face shut are identity rows. With
    /// the fluid indicator (0 on those cells).
    fn apertures(grid: &MacGrid<D>, apertures: [&[f64]; D]) -> (Self, Vec<f64>) {
        let n = grid.n;
        let cells = grid.n_s();
        let strides = strides(n);
        let b = grid.boundary;
        let ghost = |s: Side| if s == Side::Outflow { 1.0 } else { 0.0 };
        let mut k = Self { diag: vec![0.0; cells], plus: std::array::from_fn(|_| vec![0.0; cells]), strides, wraps: false };
        for c in 0..cells {
            let q: [usize; D] = std::array::from_fn(|a| (c / strides[a]) % n[a]);
            for a in 0..D {
                let faces = grid.face_dims(a);
                let (mut lower, mut stride) = (0, 1);
                for (&qx, &fx) in q.iter().zip(&faces) {
                    lower += qx * stride;
                    stride *= fx;
                }
                let face_stride: usize = faces[..a].iter().product();
                let (lo, hi) = (apertures[a][lower], apertures[a][lower + face_stride]);
                k.diag[c] += lo * if q[a] > 0 { 1.0 } else { ghost(b.lower(a)) } + hi * if q[a] + 1 < n[a] { 1.0 } else { ghost(b.upper(a)) };
                k.plus[a][c] = if q[a] + 1 < n[a] { -hi } else { 0.0 };
            }
        }
        // Cells coupled to nothing: identity rows, and not fluid (for the
        // mean removed in a closed box).
        let open: Vec<f64> = (0..cells)
            .map(|c| {
                let coupled = (0..D).any(|a| k.plus[a][c] != 0.0 || (c >= strides[a] && k.plus[a][c - strides[a]] != 0.0));
                if k.diag[c] > 0.0 || coupled { 1.0 } else { 0.0 }
            })
            .collect();
        for (d, &o) in k.diag.iter_mut().zip(&open) {
            if o == 0.0 {
                *d = 1.0;
            }
        }
        (k, open)
    }

    /// `out = A·p` (the couplings inside the box only).
    pub fn apply(&self, p: &[f64], out: &mut [f64]) {
        apply_coefficients(&self.strides, &self.diag, &self.plus, p, out)
    }

    /// The lower triangle of the matrix, `(row, column, value)`, with the
    /// couplings across periodic sides of the box `grid` (fluid indicator
    /// `fluid`); a singular matrix (no outflow side) gets 1 added to its
    /// first fluid cell's diagonal, which makes it definite (the solve
    /// removes the null component itself).
    fn lower_triplets(&self, grid: &MacGrid<D>, fluid: Option<&[f64]>) -> Vec<(usize, usize, f64)> {
        let (n, b) = (grid.n, grid.boundary);
        let w = |c: usize| fluid.map_or(1.0, |w| w[c]);
        let cells = self.diag.len();
        let mut t = Vec::with_capacity((D + 1) * cells);
        let pinned = (!b.has_outflow()).then(|| (0..cells).find(|&c| w(c) > 0.0)).flatten();
        for c in 0..cells {
            t.push((c, c, self.diag[c] + if Some(c) == pinned { 1.0 } else { 0.0 }));
            for a in 0..D {
                if self.plus[a][c] != 0.0 {
                    t.push((c + self.strides[a], c, self.plus[a][c]));
                }
            }
        }
        // Wrapped couplings: the last cell along a periodic axis with the first.
        for a in (0..D).filter(|&a| b.periodic(a) && n[a] > 2) {
            let span = (n[a] - 1) * self.strides[a];
            for first in (0..cells).filter(|&c| (c / self.strides[a]).is_multiple_of(n[a])) {
                t.push((first + span, first, -w(first) * w(first + span)));
            }
        }
        t
    }
}

/// The strides of a box's cells (x fastest).
fn strides<const D: usize>(n: [usize; D]) -> [usize; D] {
    std::array::from_fn(|a| n[..a].iter().product())
}

crate::simd_dispatch! {
    /// `out = A·p` from the coefficients: `2D + 1` shifted streams, each a
    /// branch-free loop.
    fn apply_coefficients(strides: &[usize], diag: &[f64], plus: &[Vec<f64>], p: &[f64], out: &mut [f64]) => apply_coefficients_body
}

#[inline(always)]
fn apply_coefficients_body(strides: &[usize], diag: &[f64], plus: &[Vec<f64>], p: &[f64], out: &mut [f64]) {
    let n = p.len();
    for ((o, &d), &v) in out.iter_mut().zip(diag).zip(p) {
        *o = d * v;
    }
    for (&s, a) in strides.iter().zip(plus) {
        let m = n.saturating_sub(s);
        for ((o, &a), &v) in out[..m].iter_mut().zip(&a[..m]).zip(&p[s..]) {
            *o += a * v;
        }
        for ((o, &a), &v) in out[s..].iter_mut().zip(&a[..m]).zip(&p[..m]) {
            *o += a * v;
        }
    }
}

/// MIC(0) of a matrix in [`Coefficients`] form: `M = (D + L)·D⁻¹·(D +
/// L)ᵀ` with `L` the strictly lower part and `D` chosen so that `M`'s row
/// sums match the matrix's (modified, with the usual damping `τ = 0.97` and
/// the fallback to the diagonal below `σ = 1/4` of it; couplings across a
/// periodic side are left out). Symmetric positive definite; applying it is
/// two sequential triangular sweeps.
#[derive(Clone, Debug)]
pub struct Mic<const D: usize> {
    /// `1/√d_c`.
    inv_sqrt: Vec<f64>,
    /// The couplings to the next cell along each axis times the cell's
    /// `1/√d_c`.
    scaled: [Vec<f64>; D],
    strides: [usize; D],
    /// The closed square's factor, swept along anti-diagonals.
    square: Option<usize>,
}

impl<const D: usize> Mic<D> {
    /// The factor of the matrix `k`.
    pub fn new(k: &Coefficients<D>) -> Self {
        const TAU: f64 = 0.97;
        const SIGMA: f64 = 0.25;
        let n = k.diag.len();
        let mut inv_sqrt = vec![0.0; n];
        for c in 0..n {
            let mut e = k.diag[c];
            for a in 0..D {
                // The coupling to the lower neighbour along `a` (0 when `c`
                // is first along `a`), with that neighbour's other couplings.
                let Some(m) = c.checked_sub(k.strides[a]) else { continue };
                let (coupling, pm) = (k.plus[a][m], inv_sqrt[m]);
                let others: f64 = (0..D).filter(|&b| b != a).map(|b| k.plus[b][m]).sum();
                e -= (coupling * pm) * (coupling * pm) + TAU * coupling * others * pm * pm;
            }
            if e < SIGMA * k.diag[c] {
                e = k.diag[c];
            }
            // A cell coupled to nothing (walled in): leave its residual as is.
            inv_sqrt[c] = if e > 0.0 { 1.0 / e.sqrt() } else { 1.0 };
        }
        let scaled = std::array::from_fn(|a| k.plus[a].iter().zip(&inv_sqrt).map(|(k, p)| k * p).collect());
        Self { inv_sqrt, scaled, strides: k.strides, square: None }
    }

    /// `z = M⁻¹·r`: the forward sweep `(D + L)·D^{-½}·q = r`, then the
    /// backward sweep with the transpose.
    pub fn apply(&mut self, r: &[f64], z: &mut [f64]) {
        if let Some(n) = self.square {
            return mic0_square(n, &self.inv_sqrt, r, z);
        }
        // Both sweeps in place in `z`: row order, each cell after its lower
        // (upper) neighbours; the couplings scaled by the inverse diagonal
        // once (`scaled`), off the sweeps' dependency chain.
        let (p, scaled, strides) = (&self.inv_sqrt, &self.scaled, self.strides);
        let n = p.len();
        let (r, z) = (&r[..n], &mut z[..n]);
        for c in 0..n {
            let mut t = r[c];
            for a in 0..D {
                if c >= strides[a] {
                    let m = c - strides[a];
                    t -= scaled[a][m] * z[m];
                }
            }
            z[c] = t * p[c];
        }
        for c in (0..n).rev() {
            let mut t = z[c];
            for a in 0..D {
                if c + strides[a] < n {
                    t -= scaled[a][c] * z[c + strides[a]];
                }
            }
            z[c] = t * p[c];
        }
    }
}

/// `z = (L·Lᵀ)⁻¹·r` for the MIC(0) factor of the closed `n × n` square
/// (every coupling −1, inverse diagonal `pc`): forward then backward
/// substitution. Each cell depends on its left and lower (right and upper)
/// neighbour, so the sweeps run along anti-diagonals `i + j = k`, whose
/// cells are independent of each other: no dependency chain between
/// consecutive operations, unlike the row-by-row order.
fn mic0_square(n: usize, pc: &[f64], r: &[f64], z: &mut [f64]) {
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

crate::simd_dispatch! {
    /// `q = A·d` and `*dq = d·q` in one pass (the closed square).
    fn matvec_dot(nx: usize, ny: usize, d: &[f64], q: &mut [f64], dq: &mut f64) => matvec_dot_body
}

#[inline(always)]
fn matvec_dot_body(nx: usize, ny: usize, d: &[f64], q: &mut [f64], dq: &mut f64) {
    apply_pressure_matrix(nx, ny, d, q);
    *dq = dot(d, q);
}

/// How the matrix is applied (the rule in the module's documentation).
#[derive(Clone, Debug)]
enum Product<const D: usize> {
    /// A closed box of `slabs` square slabs of `n × n` cells along the last
    /// axis (2D: one slab), with what the solid cells need: the count of
    /// solid cells beside each cell and a buffer.
    Slabs { n: usize, slabs: usize, solid_beside: Vec<f64> },
    /// The coefficient form (no periodic side).
    Coefficients(Coefficients<D>),
    /// The stencil of the box as a 3D one (a periodic side).
    Stencil([usize; 3], Boundary<3>),
}

/// The preconditioner of a solve.
#[derive(Clone, Debug)]
enum Precond<const D: usize> {
    None,
    /// The geometric V-cycle of square slabs stacked along an axis, with
    /// two buffers for the fields reordered so that axis comes last.
    Multigrid(Multigrid, [usize; 3], usize, [Vec<f64>; 2]),
    /// The aggregation V-cycle of any box and sides.
    Aggregate(AggregateMultigrid),
    Mic(Mic<D>),
    Cholesky(SparseCholesky),
}

/// Conjugate gradients on the pressure matrix of a box of `D` axes (2 or
/// 3) with any sides and solid cells, preconditioned by
/// [`Preconditioner`]'s choice, with its work vectors kept between solves.
/// The rule that picks the product and the preconditioner's form is in the
/// module's documentation.
#[derive(Clone, Debug)]
pub struct PressureSolver<const D: usize> {
    grid: MacGrid<D>,
    /// The stopping rule.
    pub stop: Stop,
    product: Product<D>,
    precond: Precond<D>,
    /// Fluid indicator per cell (1 fluid, 0 solid) when there are obstacles.
    fluid: Option<Vec<f64>>,
    /// A buffer for the masked product and the masked V-cycle (with obstacles).
    buf: Vec<f64>,
    work: CgWork,
}

impl<const D: usize> PressureSolver<D> {
    /// A solver for the box `grid` (any sides): relative `tolerance` on the
    /// true residual, more than `max_iterations` an error, preconditioned by
    /// `precond`.
    ///
    /// # Panics
    /// For [`Preconditioner::Cholesky`], if the factor cannot be computed
    /// (out of memory); [`PressureSolver::direct`] returns the error instead.
    pub fn new(grid: &MacGrid<D>, tolerance: f64, max_iterations: usize, precond: Preconditioner) -> Self {
        Self::build(grid, Stop { tolerance, max_iterations }, precond, None, None).expect("sparse Cholesky of the pressure matrix")
    }

    /// A solver for the box `grid` with solid cells where `fluid[c] = 0`:
    /// the matrix couples fluid cells across their shared faces only and
    /// keeps solid rows as the identity; symmetric, the constants on the
    /// fluid cells its null space (with no outflow side). A multigrid
    /// preconditioner is the box's V-cycle on the fluid cells, `W·M·W + (I
    /// − W)`: symmetric and positive, blind to the obstacles' walls (they
    /// cost iterations, not accuracy); MIC(0) and Cholesky are built for
    /// the matrix itself.
    ///
    /// # Panics
    /// As [`PressureSolver::new`], or if `fluid` does not have a value per cell.
    pub fn with_obstacles(grid: &MacGrid<D>, tolerance: f64, max_iterations: usize, precond: Preconditioner, fluid: Vec<f64>) -> Self {
        assert_eq!(fluid.len(), grid.n_s(), "fluid mask length");
        Self::build(grid, Stop { tolerance, max_iterations }, precond, Some(fluid), None).expect("sparse Cholesky of the pressure matrix")
    }

    /// A direct solver ([`Preconditioner::Cholesky`]) for the box `grid`
    /// with solid cells where `fluid[c] = 0` (`None`: none).
    pub fn direct(grid: &MacGrid<D>, tolerance: f64, max_iterations: usize, fluid: Option<Vec<f64>>) -> Result<Self, FactorFailed> {
        if let Some(f) = &fluid {
            assert_eq!(f.len(), grid.n_s(), "fluid mask length");
        }
        Self::build(grid, Stop { tolerance, max_iterations }, Preconditioner::Cholesky, fluid, None)
    }

    /// A direct solver ([`Preconditioner::Cholesky`]) for the matrix of
    /// faces open by fractions ([`Coefficients`] of the apertures,
    /// `apertures[a]` in the layout of the faces normal to axis `a`): the
    /// projection onto velocities whose aperture-weighted flux balances in
    /// every cell (cut cells). Cells with every face shut are identity
    /// rows, and not fluid.
    ///
    /// # Panics
    /// If a side is periodic or an aperture array has the wrong length.
    pub fn with_apertures(grid: &MacGrid<D>, tolerance: f64, max_iterations: usize, apertures: [&[f64]; D]) -> Result<Self, FactorFailed> {
        assert!(!grid.boundary.wraps().contains(&true), "apertures with periodic sides");
        for (a, ap) in apertures.iter().enumerate() {
            assert_eq!(ap.len(), grid.n_face(a), "apertures of the faces normal to axis {a}");
        }
        let (k, open) = Coefficients::apertures(grid, apertures);
        Self::build(grid, Stop { tolerance, max_iterations }, Preconditioner::Cholesky, Some(open), Some(k))
    }

    fn build(
        grid: &MacGrid<D>,
        stop: Stop,
        precond: Preconditioner,
        fluid: Option<Vec<f64>>,
        coefficients: Option<Coefficients<D>>,
    ) -> Result<Self, FactorFailed> {
        let (dims, b) = padded(grid);
        let cells = grid.n_s();
        let given = coefficients.is_some();
        let k = coefficients.unwrap_or_else(|| Coefficients::new(grid, fluid.as_deref()));
        let slabs = !given && grid.is_closed() && dims[0] == dims[1] && dims[0] >= 2;
        let precond = match precond {
            Preconditioner::None => Precond::None,
            Preconditioner::Mic0 => {
                let mut mic = Mic::new(&k);
                if D == 2 && slabs && fluid.is_none() {
                    mic.square = Some(dims[0]);
                }
                Precond::Mic(mic)
            }
            Preconditioner::Multigrid => match slab_axis(dims) {
                Some(axis) if grid.is_closed() => {
                    let side = dims[(axis + 1) % 3];
                    let buffers = if axis == 2 { [Vec::new(), Vec::new()] } else { [vec![0.0; cells], vec![0.0; cells]] };
                    Precond::Multigrid(Multigrid::slabs(side, dims[axis]), dims, axis, buffers)
                }
                _ => Precond::Aggregate(AggregateMultigrid::new(dims, b)),
            },
            Preconditioner::Cholesky => Precond::Cholesky(SparseCholesky::new(cells, &k.lower_triplets(grid, fluid.as_deref()))?),
        };
        let product = if slabs {
            let solid_beside = fluid.as_deref().map_or_else(Vec::new, |f| crate::smoke::solid_neighbours(grid, f));
            Product::Slabs { n: dims[0], slabs: dims[2], solid_beside }
        } else if !k.wraps {
            Product::Coefficients(k)
        } else {
            Product::Stencil(dims, b)
        };
        // The masked product and the masked V-cycle use it in turn.
        let buf = if fluid.is_some() { vec![0.0; cells] } else { Vec::new() };
        Ok(Self { grid: *grid, stop, product, precond, fluid, buf, work: CgWork::new(cells) })
    }

    /// The relative tolerance its solves stop at.
    pub fn tolerance(&self) -> f64 {
        self.stop.tolerance
    }

    /// The box it solves on.
    pub fn grid(&self) -> &MacGrid<D> {
        &self.grid
    }

    /// The fluid indicator (1 fluid, 0 solid) when there are obstacles.
    pub fn fluid(&self) -> Option<&[f64]> {
        self.fluid.as_deref()
    }

    /// The preconditioner in use.
    pub fn preconditioner(&self) -> Preconditioner {
        match self.precond {
            Precond::None => Preconditioner::None,
            Precond::Multigrid(..) | Precond::Aggregate(_) => Preconditioner::Multigrid,
            Precond::Mic(_) => Preconditioner::Mic0,
            Precond::Cholesky(_) => Preconditioner::Cholesky,
        }
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
        let mut work = std::mem::take(&mut self.work);
        let stop = self.stop;
        let result = crate::cg::solve(self, &mut work, stop, b, p, warm);
        self.work = work;
        result
    }
}

impl<const D: usize> System for PressureSolver<D> {
    fn apply(&mut self, p: &[f64], out: &mut [f64]) {
        match (&mut self.product, &self.fluid) {
            // The square's product straight here (vectorised by the caller).
            (Product::Slabs { n, slabs: 1, .. }, None) => apply_pressure_matrix(*n, *n, p, out),
            (Product::Slabs { n, slabs, .. }, None) => apply_box_matrix(*n, *slabs, p, out),
            (Product::Slabs { n, slabs, solid_beside }, Some(fluid)) => {
                // W·(A_box·(W·p) − S·p) + (I − W)·p.
                for ((b, &p), &w) in self.buf.iter_mut().zip(p).zip(fluid) {
                    *b = w * p;
                }
                apply_box_matrix(*n, *slabs, &self.buf, out);
                for (((o, &p), &w), &s) in out.iter_mut().zip(p).zip(fluid).zip(&*solid_beside) {
                    *o = w * (*o - s * p) + (1.0 - w) * p;
                }
            }
            (Product::Coefficients(k), _) => k.apply(p, out),
            (Product::Stencil(dims, b), fluid) => apply_stencil(*dims, b, [1.0; 3], fluid.as_deref(), p, out),
        }
    }

    fn apply_dot(&mut self, d: &[f64], q: &mut [f64]) -> f64 {
        if let (Product::Slabs { n, slabs: 1, .. }, None) = (&self.product, &self.fluid) {
            let mut dq = 0.0;
            matvec_dot(*n, *n, d, q, &mut dq);
            return dq;
        }
        self.apply(d, q);
        dot(d, q)
    }

    /// Constants on the fluid cells, unless a side lets fluid out.
    fn null(&self) -> Null<'_> {
        if self.grid.boundary.has_outflow() { Null::None } else { Null::Constant(self.fluid()) }
    }

    fn precondition(&mut self, r: &[f64], z: &mut [f64]) -> bool {
        // The V-cycle of the slabs along `axis`.
        let cycle = |mg: &mut Multigrid, dims: [usize; 3], axis: usize, [a, b]: &mut [Vec<f64>; 2], r: &[f64], z: &mut [f64]| {
            if axis == 2 {
                return mg.apply(r, z);
            }
            reorder(dims, axis, r, a, false);
            mg.apply(a, b);
            reorder(dims, axis, b, z, true);
        };
        let multigrid = |precond: &mut Precond<D>, r: &[f64], z: &mut [f64]| match precond {
            Precond::Multigrid(mg, dims, axis, bufs) => cycle(mg, *dims, *axis, bufs, r, z),
            Precond::Aggregate(mg) => mg.apply(r, z),
            _ => unreachable!("a multigrid preconditioner"),
        };
        match (&mut self.precond, &self.fluid) {
            (Precond::None, _) => return false,
            (Precond::Mic(mic), _) => mic.apply(r, z),
            (Precond::Cholesky(chol), _) => {
                z.copy_from_slice(r);
                chol.solve_in_place(z);
            }
            (precond, None) => multigrid(precond, r, z),
            (precond, Some(fluid)) => {
                // W·M·(W·r) + (I − W)·r.
                for ((b, &r), &w) in self.buf.iter_mut().zip(r).zip(fluid) {
                    *b = w * r;
                }
                multigrid(precond, &self.buf, z);
                for ((z, &r), &w) in z.iter_mut().zip(r).zip(fluid) {
                    *z = w * *z + (1.0 - w) * r;
                }
            }
        }
        true
    }
}
