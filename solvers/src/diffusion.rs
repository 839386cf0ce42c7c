//! Diffusion of a field sampled on a lattice ([`Grid`]: the cell centres of
//! the box, or one velocity component's faces), unit spacing, no flux
//! through the lattice's edges or wrapping around a periodic axis: explicit
//! (forward Euler) and implicit (backward Euler, solved by conjugate
//! gradients). Smoke diffusion and viscosity are both this.
//!
//! With `A` the lattice's matrix of [`laplacian`] (`A ≈ −Δ` on unit
//! spacing; for the closed box of cells that of
//! [`crate::smoke::apply_pressure_matrix`]) and `κ = ν·dt`:
//! - explicit: `s' = s − κ·A·s`, stable for `κ ≤ 1/4` (the largest eigenvalue
//!   of `A` is below 8);
//! - implicit: `(I + κ·A)·s' = s`, stable for every `κ ≥ 0`. The matrix is
//!   symmetric positive definite, so its adjoint is the same solve.

use crate::boundary::Side;
use crate::smoke::{MacGrid, NoConvergence, apply_pressure_matrix};

/// A lattice of `nx × ny × nz` samples at `f[m·slab + l·stride + k]` in a
/// slice of [`Grid::len`] values (a line or a plane: `nz = 1`); on a
/// wrapping axis the lattice is periodic, on the others no flux leaves it
/// (the value beyond an edge is the edge's own) unless the edge is marked
/// in [`Grid::fixed`]: there the value beyond it is the negative of the
/// edge's, so that the field is zero half a sample beyond the edge (a
/// no-slip wall for a velocity component tangential to it). Entries of the
/// slice that are not samples (a periodic velocity's copy column or row)
/// do not diffuse.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct Grid {
    /// Distance between rows in the slice.
    pub stride: usize,
    /// Samples per row.
    pub nx: usize,
    /// Rows per slab.
    pub ny: usize,
    /// Slabs (1 on a line or a plane).
    pub nz: usize,
    /// The x axis wraps.
    pub wrap_x: bool,
    /// The y axis wraps.
    pub wrap_y: bool,
    /// The z axis wraps.
    pub wrap_z: bool,
    /// Rows per slab in the slice (`ny`, or one more where a periodic y
    /// axis keeps its copy row inside each slab).
    pub rows: usize,
    /// The edges where the field is held at zero half a sample beyond the
    /// last sample: bit `2a` the lower edge of axis `a` (0 x, 1 y, 2 z),
    /// bit `2a + 1` the upper one; 0 for none. (Bits, not an array of
    /// flags: a plain integer is what Enzyme types surely in the explicit
    /// step it differentiates.)
    pub fixed: u32,
}

impl Grid {
    /// A plane of `nx × ny` samples, rows `stride` apart.
    pub fn plane(stride: usize, nx: usize, ny: usize, wrap_x: bool, wrap_y: bool) -> Self {
        Self { stride, nx, ny, nz: 1, wrap_x, wrap_y, wrap_z: false, rows: ny, fixed: 0 }
    }

    /// A line of `n` samples, periodic or closed.
    pub fn line(n: usize, periodic: bool) -> Self {
        Self::plane(n, n, 1, periodic, false)
    }

    /// The cells of the closed `n × n` box.
    pub fn square(n: usize) -> Self {
        Self::plane(n, n, n, false, false)
    }

    /// The lattices of a state `[s, u₀, …]` for `cfg`'s sides, in 2D or
    /// 3D: the cell centres, then the faces normal to each axis (each over
    /// its whole array; a periodic axis's copy faces are not samples). A
    /// face lattice's edges along a no-slip side ([`Side::NoSlip`]) of
    /// another axis are [fixed](Grid::fixed): the component tangential to
    /// the wall is zero on it.
    pub fn of_state<const D: usize>(cfg: &MacGrid<D>) -> Vec<Grid> {
        let w = cfg.boundary.wraps();
        let mut grids = Vec::with_capacity(D + 1);
        for l in 0..=D {
            // The array's extents, the samples (own faces) and the wrapping
            // per axis, padded to three axes.
            let (mut ext, mut own, mut wraps, mut fixed) = ([1usize; 3], [1usize; 3], [false; 3], 0);
            for a in 0..D {
                ext[a] = cfg.n[a] + usize::from(l == a + 1);
                own[a] = ext[a] - usize::from(l == a + 1 && w[a]);
                wraps[a] = w[a];
                for (h, side) in cfg.boundary.axis(a).into_iter().enumerate() {
                    if l >= 1 && l != a + 1 && side == Side::NoSlip {
                        fixed |= 1 << (2 * a + h);
                    }
                }
            }
            grids.push(Grid { stride: ext[0], nx: own[0], ny: own[1], nz: own[2], wrap_x: wraps[0], wrap_y: wraps[1], wrap_z: wraps[2], rows: ext[1], fixed });
        }
        grids
    }

    /// Whether edge `bit` ([`Grid::fixed`]'s numbering) is fixed: `1.0` or `0.0`.
    #[inline(always)]
    fn fixed_at(&self, bit: u32) -> f64 {
        ((self.fixed >> bit) & 1) as f64
    }

    /// Distance between slabs in the slice.
    pub fn slab(&self) -> usize {
        self.stride * self.rows
    }

    /// Length of the slice holding the field.
    pub fn len(&self) -> usize {
        self.slab() * self.nz
    }

    /// Largest stable `κ = ν·dt` of the explicit scheme on this lattice:
    /// `1/(2·d)` with `d` the number of axes with more than one sample
    /// (1/6 in a 3D box, 1/4 in a plane, 1/2 on a line).
    pub fn explicit_limit(&self) -> f64 {
        let axes = usize::from(self.nx > 1) + usize::from(self.ny > 1) + usize::from(self.nz > 1);
        0.5 / axes.max(1) as f64
    }

    /// Whether the lattice has no samples.
    pub fn is_empty(&self) -> bool {
        self.nx == 0 || self.ny == 0 || self.nz == 0
    }
}

/// `out = A·s` for the lattice `g` (overwrites `out`): `(A·s)_c = Σ_m (s_c −
/// s_m)` over the neighbours `m` of sample `c` on the lattice (wrapped on a
/// periodic axis); zero at slice entries that are not samples. Symmetric
/// positive semi-definite.
pub fn laplacian(g: &Grid, s: &[f64], out: &mut [f64]) {
    if !g.wrap_x && !g.wrap_y && g.fixed == 0 && g.stride == g.nx && g.nx >= 2 && g.nz == 1 && g.rows == g.ny {
        return apply_pressure_matrix(g.nx, g.ny, s, out);
    }
    for o in out.iter_mut() {
        *o = 0.0;
    }
    let (nx, ny, nz, st, slab) = (g.nx, g.ny, g.nz, g.stride, g.slab());
    for m in 0..nz {
        for l in 0..ny {
            for k in 0..nx {
                let c = m * slab + l * st + k;
                let mut acc = plane_terms(g, s, c, k, l, m * slab);
                if m > 0 {
                    acc += s[c] - s[c - slab];
                } else if g.wrap_z {
                    acc += s[c] - s[c + (nz - 1) * slab];
                } else {
                    acc += 2.0 * g.fixed_at(4) * s[c];
                }
                if m + 1 < nz {
                    acc += s[c] - s[c + slab];
                } else if g.wrap_z {
                    acc += s[c] - s[c - (nz - 1) * slab];
                } else {
                    acc += 2.0 * g.fixed_at(5) * s[c];
                }
                out[c] = acc;
            }
        }
    }
}

/// The in-plane terms of [`laplacian`] at sample `c` = `(k, l)` of the slab
/// starting at `base`.
#[inline(always)]
fn plane_terms(g: &Grid, s: &[f64], c: usize, k: usize, l: usize, base: usize) -> f64 {
    let (nx, ny, st) = (g.nx, g.ny, g.stride);
    let sc = s[c];
    let mut acc = 0.0;
    // Beyond an edge: the wrapped sample, the edge's own value (no flux)
    // or its negative (fixed: `2·s` in the sum).
    if k > 0 {
        acc += sc - s[c - 1];
    } else if g.wrap_x {
        acc += sc - s[c + nx - 1];
    } else {
        acc += 2.0 * g.fixed_at(0) * sc;
    }
    if k + 1 < nx {
        acc += sc - s[c + 1];
    } else if g.wrap_x {
        acc += sc - s[base + l * st];
    } else {
        acc += 2.0 * g.fixed_at(1) * sc;
    }
    if l > 0 {
        acc += sc - s[c - st];
    } else if g.wrap_y {
        acc += sc - s[base + (ny - 1) * st + k];
    } else {
        acc += 2.0 * g.fixed_at(2) * sc;
    }
    if l + 1 < ny {
        acc += sc - s[c + st];
    } else if g.wrap_y {
        acc += sc - s[base + k];
    } else {
        acc += 2.0 * g.fixed_at(3) * sc;
    }
    acc
}

/// Largest stable `κ = ν·dt` of the explicit scheme on unit cells.
pub const EXPLICIT_LIMIT: f64 = 0.25;

/// `out = s − κ·A·s` (overwrites `out`). It writes `A·s` into `out` and
/// rescales in place; Enzyme differentiates this correctly with the output
/// declared `Duplicated`, as diffsim's macros do (tests/user_op.rs keeps
/// that shape under the checks).
pub fn explicit(g: &Grid, kappa: f64, s: &[f64], out: &mut [f64]) {
    laplacian(g, s, out);
    for (o, &v) in out.iter_mut().zip(s) {
        *o = v - kappa * *o;
    }
}

/// Conjugate gradients for `(I + κ·A)·x = b` with reusable buffers.
#[derive(Clone, Debug)]
pub struct ImplicitSolver {
    grid: Grid,
    /// Relative tolerance on the true residual.
    pub tolerance: f64,
    /// More iterations than this is an error.
    pub max_iterations: usize,
    r: Vec<f64>,
    d: Vec<f64>,
    q: Vec<f64>,
}

impl ImplicitSolver {
    /// A solver for the lattice `grid`.
    pub fn new(grid: Grid, tolerance: f64, max_iterations: usize) -> Self {
        let z = vec![0.0; grid.len()];
        Self { grid, tolerance, max_iterations, r: z.clone(), d: z.clone(), q: z }
    }

    /// `out = (I + κ·A)·x`: the explicit step with `−κ`.
    fn apply(g: &Grid, kappa: f64, x: &[f64], out: &mut [f64]) {
        explicit(g, -kappa, x, out)
    }

    /// Solves `(I + κ·A)·x = b`, starting from `x = b` (a good guess for
    /// small `κ`), until `‖b − M·x‖ ≤ tol·‖b‖` on the true residual;
    /// overwrites `x`. Returns the iterations.
    pub fn solve(&mut self, kappa: f64, b: &[f64], x: &mut [f64]) -> Result<usize, NoConvergence> {
        let g = self.grid;
        let dot = |a: &[f64], b: &[f64]| a.iter().zip(b).map(|(a, b)| a * b).sum::<f64>();
        // Solved for b scaled by a power of two where ‖b‖² would overflow or
        // underflow (crate::cg::rhs_scale), the solution scaled back.
        let scale = crate::cg::rhs_scale(b).ok_or(NoConvergence { iterations: 0, relative_residual: f64::NAN, tolerance: self.tolerance })?;
        let scaled: Vec<f64>;
        let b = if scale == 1.0 {
            b
        } else {
            scaled = b.iter().map(|v| v * scale).collect();
            &scaled
        };
        let bnorm = dot(b, b).sqrt();
        x.copy_from_slice(b);
        if bnorm == 0.0 {
            return Ok(0);
        }
        let target = self.tolerance * bnorm;
        let residual = |x: &[f64], r: &mut [f64], q: &mut [f64]| {
            Self::apply(&g, kappa, x, q);
            for ((r, &bv), &qv) in r.iter_mut().zip(b).zip(q.iter()) {
                *r = bv - qv;
            }
        };
        residual(x, &mut self.r, &mut self.q);
        self.d.copy_from_slice(&self.r);
        let mut rr = dot(&self.r, &self.r);
        let mut it = 0;
        loop {
            if rr.sqrt() <= target {
                residual(x, &mut self.r, &mut self.q);
                rr = dot(&self.r, &self.r);
                if rr.sqrt() <= target {
                    if scale != 1.0 {
                        x.iter_mut().for_each(|v| *v /= scale);
                    }
                    return Ok(it);
                }
                self.d.copy_from_slice(&self.r);
            }
            if it >= self.max_iterations || !rr.is_finite() {
                return Err(NoConvergence { iterations: it, relative_residual: rr.sqrt() / bnorm, tolerance: self.tolerance });
            }
            Self::apply(&g, kappa, &self.d, &mut self.q);
            let alpha = rr / dot(&self.d, &self.q);
            for ((xv, &dv), (r, &qv)) in x.iter_mut().zip(&self.d).zip(self.r.iter_mut().zip(&self.q)) {
                *xv += alpha * dv;
                *r -= alpha * qv;
            }
            let rr_new = dot(&self.r, &self.r);
            let beta = rr_new / rr;
            rr = rr_new;
            for (dv, &rv) in self.d.iter_mut().zip(&self.r) {
                *dv = rv + beta * *dv;
            }
            it += 1;
        }
    }
}
