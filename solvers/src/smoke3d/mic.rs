//! The pressure matrix of any `nx × ny × nz` box and sides with solid
//! cells, and its modified incomplete Cholesky factor MIC(0), a
//! preconditioner one may pick instead of the multigrid: the 3D form of
//! the 2D solver's MIC(0) (Bridson, *Fluid Simulation for Computer
//! Graphics*, §5), with the same safety factors.

use super::MacGrid;
use crate::multigrid::{Across, across, apply_stencil3};

/// The seven-point pressure matrix of the box `cfg` (any sides) with solid
/// cells where `fluid[c] = 0` (`None`: none): `out[c] = w_c·Σ_m w_m·(p_c −
/// p_m) + (1 − w_c)·p_c` over the neighbours `m` across the cell's faces
/// that the projection changes (inside the box, wrapped across a periodic
/// side, and a ghost `p = 0` across an outflow side); closed and inflow
/// sides add nothing (Neumann). Symmetric; without an outflow side the
/// constants on the fluid cells are its null space. Slab by slab, in
/// parallel on large boxes.
pub fn apply_general_matrix3(cfg: &MacGrid<3>, fluid: Option<&[f64]>, p: &[f64], out: &mut [f64]) {
    apply_stencil3(cfg.n, &cfg.boundary, [1.0; 3], fluid, p, out);
}

/// MIC(0) of [`apply_general_matrix3`]'s matrix: `M = (D + L)·D⁻¹·(D + L)ᵀ`
/// with `L` the matrix's strictly lower part and `D` chosen so that `M`'s
/// row sums match the matrix's (modified, with the usual damping `τ =
/// 0.97` and the fallback to the diagonal below `σ = 1/4` of it). Symmetric
/// positive definite; applying it is two sequential triangular sweeps.
#[derive(Clone, Debug)]
pub struct Mic3 {
    dims: [usize; 3],
    /// `1/√d_c`.
    inv_sqrt: Vec<f64>,
    /// Couplings to the next cell along x, y and z (`A_{c, c+1}` etc.: −1
    /// between two fluid cells, 0 otherwise).
    plus: [Vec<f64>; 3],
    q: Vec<f64>,
}

impl Mic3 {
    /// The factor for the box `cfg` with solid cells where `fluid[c] = 0`
    /// (`None`: none): its diagonal counts every coupling of the matrix
    /// (periodic and outflow sides too), its off-diagonal part the
    /// couplings inside the box (those across a periodic side are left
    /// out, as in 2D).
    pub fn new(cfg: &MacGrid<3>, fluid: Option<&[f64]>) -> Self {
        const TAU: f64 = 0.97;
        const SIGMA: f64 = 0.25;
        let dims = cfg.n;
        let [nx, ny, _] = dims;
        let (slab, n) = (nx * ny, cfg.n_s());
        let w = |c: usize| fluid.map_or(1.0, |f| f[c]);
        let strides = [1, nx, slab];
        let at = |c: usize| [c % nx, (c / nx) % ny, c / slab];
        let plus: [Vec<f64>; 3] = [0, 1, 2].map(|a| (0..n).map(|c| if at(c)[a] + 1 < dims[a] { -w(c) * w(c + strides[a]) } else { 0.0 }).collect());
        let diag: Vec<f64> = (0..n)
            .map(|c| {
                let q = at(c);
                let mut s = 0.0;
                for a in 0..3 {
                    for m in across(dims, &cfg.boundary, c, q, a) {
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
        let mut inv_sqrt = vec![0.0; n];
        for c in 0..n {
            let q = at(c);
            let mut e = diag[c];
            for a in 0..3 {
                if q[a] == 0 {
                    continue;
                }
                let m = c - strides[a];
                let (coupling, pm) = (plus[a][m], inv_sqrt[m]);
                // The other two directions' couplings of the lower neighbour.
                let others: f64 = (0..3).filter(|&b| b != a).map(|b| plus[b][m]).sum();
                e -= (coupling * pm).powi(2) + TAU * coupling * others * pm * pm;
            }
            if e < SIGMA * diag[c] {
                e = diag[c];
            }
            inv_sqrt[c] = 1.0 / e.sqrt();
        }
        Self { dims, inv_sqrt, plus, q: vec![0.0; n] }
    }

    /// `z = M⁻¹·r`: the forward sweep `(D + L)·D^{-½}·q = r`, then the
    /// backward sweep with the transpose.
    pub fn apply(&mut self, r: &[f64], z: &mut [f64]) {
        let [nx, ny, _] = self.dims;
        let strides = [1, nx, nx * ny];
        let (p, plus, q) = (&self.inv_sqrt, &self.plus, &mut self.q);
        let n = p.len();
        for c in 0..n {
            let mut t = r[c];
            for a in 0..3 {
                if c >= strides[a] {
                    let m = c - strides[a];
                    t -= plus[a][m] * p[m] * q[m];
                }
            }
            q[c] = t * p[c];
        }
        for c in (0..n).rev() {
            let mut t = q[c];
            for a in 0..3 {
                let m = c + strides[a];
                if m < n {
                    t -= plus[a][c] * p[c] * z[m];
                }
            }
            z[c] = t * p[c];
        }
    }
}
