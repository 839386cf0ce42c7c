//! 2D buoyant smoke in a closed box (benchmark P2 `smoke2d`): semi-Lagrangian
//! advection of a cell-centred scalar and of a staggered (MAC) velocity,
//! walls, buoyancy, and a pressure projection solved by preconditioned
//! conjugate gradients.
//!
//! Conventions (those of P2 in `benchmarks.md`): N×N unit cells, x to the
//! right, y up, arrays indexed `[j][i]` (y, x) and flattened row by row.
//! - smoke `s[j][i]` at the cell centre `(i+½, j+½)`: `N·N` values, index `j·N + i`;
//! - `u[j][i]` at the x-face `(i, j+½)`, `i = 0..=N`: `N·(N+1)` values, index `j·(N+1) + i`;
//! - `v[j][i]` at the y-face `(i+½, j)`, `j = 0..=N`: `(N+1)·N` values, index `j·N + i`.
//!
//! The step is split where the gradient is split: [`advect_buoyancy`] (explicit,
//! differentiated by Enzyme in diffsim) and [`project`] (a linear solve, whose
//! adjoint is the solve with the transposed — here the same — matrix:
//! [`project_adjoint`]).

use std::fmt;

/// Grid of the smoke problem: `n × n` cells, buoyancy coefficient, time step 1.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Smoke2d {
    /// Cells per side.
    pub n: usize,
    /// Buoyancy: `v += buoyancy · (smoke averaged to the y-face)`.
    pub buoyancy: f64,
}

impl Smoke2d {
    /// The P2 setting (buoyancy 0.1).
    pub fn p2(n: usize) -> Self {
        Self { n, buoyancy: 0.1 }
    }

    /// Number of smoke values `N²`.
    pub fn n_s(&self) -> usize {
        self.n * self.n
    }

    /// Number of x-face velocities `N·(N+1)`.
    pub fn n_u(&self) -> usize {
        self.n * (self.n + 1)
    }

    /// Length of the packed state `[s, u, v]`: `N² + 2·N·(N+1)`.
    pub fn n_state(&self) -> usize {
        self.n_s() + 2 * self.n_u()
    }

    /// Splits a packed state `[s, u, v]`.
    pub fn split<'a>(&self, x: &'a [f64]) -> (&'a [f64], &'a [f64], &'a [f64]) {
        let (s, rest) = x.split_at(self.n_s());
        let (u, v) = rest.split_at(self.n_u());
        (s, u, v)
    }

    /// Splits a packed state `[s, u, v]`, mutably.
    pub fn split_mut<'a>(&self, x: &'a mut [f64]) -> (&'a mut [f64], &'a mut [f64], &'a mut [f64]) {
        let (s, rest) = x.split_at_mut(self.n_s());
        let (u, v) = rest.split_at_mut(self.n_u());
        (s, u, v)
    }
}

/// P2's rule for a point at `(rx, ry)` in lattice units of an `nx × ny`
/// lattice: clamp to the lattice, then the lower-left sample `(k0, l0)`
/// (kept one short of the last) and the fractions `(fx, fy)` past it.
#[inline(always)]
fn lattice_position(nx: usize, ny: usize, rx: f64, ry: f64) -> (usize, usize, f64, f64) {
    let gx = rx.clamp(0.0, (nx - 1) as f64);
    let gy = ry.clamp(0.0, (ny - 1) as f64);
    // gx, gy ≥ 0, so truncation is the floor (one instruction, no libm call).
    let k0 = (gx as usize).min(nx - 2);
    let l0 = (gy as usize).min(ny - 2);
    (k0, l0, gx - k0 as f64, gy - l0 as f64)
}

/// Bilinear sample of a lattice `f` of `nx × ny` samples whose sample
/// `(k, l)` sits at `(k + ox, l + oy)`, at the point `(px, py)`; positions
/// outside are clamped to the lattice's edge (P2's rule).
#[inline(always)]
#[allow(clippy::too_many_arguments)]
pub fn sample(f: &[f64], nx: usize, ny: usize, ox: f64, oy: f64, px: f64, py: f64) -> f64 {
    let (k0, l0, fx, fy) = lattice_position(nx, ny, px - ox, py - oy);
    let at = |k: usize, l: usize| f[l * nx + k];
    at(k0, l0) * (1.0 - fx) * (1.0 - fy) + at(k0 + 1, l0) * fx * (1.0 - fy) + at(k0, l0 + 1) * (1.0 - fx) * fy + at(k0 + 1, l0 + 1) * fx * fy
}

/// Steps 1–4 of P2: semi-Lagrangian advection of smoke and velocity, closed
/// walls, buoyancy. Reads the packed state `x = [s, u, v]`, overwrites
/// `y = [s', u', v']` (the velocity not yet divergence-free).
///
/// # Panics
/// If `x` or `y` is not of length [`Smoke2d::n_state`] or `n < 2`.
pub fn advect_buoyancy(cfg: &Smoke2d, x: &[f64], y: &mut [f64]) {
    let n = cfg.n;
    assert!(n >= 2 && x.len() == cfg.n_state() && y.len() == cfg.n_state(), "smoke: state lengths");
    let (s, u, v) = cfg.split(x);
    let (s2, u2, v2) = cfg.split_mut(y);
    let (nu, clamp) = (n + 1, |k: isize| k.clamp(0, n as isize - 1) as usize);
    // 1. Smoke, sampled back along the velocity at the cell centre.
    for j in 0..n {
        for i in 0..n {
            let uc = 0.5 * (u[j * nu + i] + u[j * nu + i + 1]);
            let vc = 0.5 * (v[j * n + i] + v[(j + 1) * n + i]);
            s2[j * n + i] = sample(s, n, n, 0.5, 0.5, i as f64 + 0.5 - uc, j as f64 + 0.5 - vc);
        }
    }
    // 2. Velocity: each component sampled back along the full velocity at
    //    its face; the other component averaged from the four nearest faces
    //    of an edge-extended copy.
    for j in 0..n {
        for i in 0..=n {
            let (a, b) = (clamp(i as isize - 1), clamp(i as isize));
            let vbar = 0.25 * (v[j * n + a] + v[j * n + b] + v[(j + 1) * n + a] + v[(j + 1) * n + b]);
            let uu = u[j * nu + i];
            u2[j * nu + i] = sample(u, n + 1, n, 0.0, 0.5, i as f64 - uu, j as f64 + 0.5 - vbar);
        }
    }
    for j in 0..=n {
        for i in 0..n {
            let (a, b) = (clamp(j as isize - 1), clamp(j as isize));
            let ubar = 0.25 * (u[a * nu + i] + u[a * nu + i + 1] + u[b * nu + i] + u[b * nu + i + 1]);
            let vv = v[j * n + i];
            v2[j * n + i] = sample(v, n, n + 1, 0.5, 0.0, i as f64 + 0.5 - ubar, j as f64 - vv);
        }
    }
    // 3. Closed walls.
    for j in 0..n {
        u2[j * nu] = 0.0;
        u2[j * nu + n] = 0.0;
    }
    for i in 0..n {
        v2[i] = 0.0;
        v2[n * n + i] = 0.0;
    }
    // 4. Buoyancy on the interior y-faces.
    for j in 1..n {
        for i in 0..n {
            v2[j * n + i] += cfg.buoyancy * 0.5 * (s2[(j - 1) * n + i] + s2[j * n + i]);
        }
    }
}

/// Adjoint of [`sample`]: adds `g·∂value/∂f` into `gf` and returns
/// `(g·∂value/∂px, g·∂value/∂py)`. The clamp passes derivatives where the
/// position is inside the lattice's range (edges included), as Enzyme's
/// derivative of `f64::clamp` does.
#[inline(always)]
#[allow(clippy::too_many_arguments)]
pub fn sample_adjoint(f: &[f64], gf: &mut [f64], nx: usize, ny: usize, ox: f64, oy: f64, px: f64, py: f64, g: f64) -> (f64, f64) {
    let (rx, ry) = (px - ox, py - oy);
    let (hx, hy) = ((nx - 1) as f64, (ny - 1) as f64);
    let (k0, l0, fx, fy) = lattice_position(nx, ny, rx, ry);
    let (c00, c10, c01, c11) = (l0 * nx + k0, l0 * nx + k0 + 1, (l0 + 1) * nx + k0, (l0 + 1) * nx + k0 + 1);
    gf[c00] += g * (1.0 - fx) * (1.0 - fy);
    gf[c10] += g * fx * (1.0 - fy);
    gf[c01] += g * (1.0 - fx) * fy;
    gf[c11] += g * fx * fy;
    let dfx = (f[c10] - f[c00]) * (1.0 - fy) + (f[c11] - f[c01]) * fy;
    let dfy = (f[c01] - f[c00]) * (1.0 - fx) + (f[c11] - f[c10]) * fx;
    let inside = |r: f64, h: f64| if r < 0.0 || r > h { 0.0 } else { 1.0 };
    (g * dfx * inside(rx, hx), g * dfy * inside(ry, hy))
}

/// Hand-written adjoint of [`advect_buoyancy`]: `gx += Jᵀ·gy` at the state
/// `x` (accumulates into `gx`; `gy` is used as scratch and left
/// unspecified). The reference for Enzyme's generated adjoint.
pub fn advect_buoyancy_adjoint(cfg: &Smoke2d, x: &[f64], gy: &mut [f64], gx: &mut [f64]) {
    let n = cfg.n;
    assert!(n >= 2 && x.len() == cfg.n_state() && gy.len() == cfg.n_state() && gx.len() == cfg.n_state(), "smoke: state lengths");
    let (s, u, v) = cfg.split(x);
    let (gs2, gu2, gv2) = cfg.split_mut(gy);
    let (gs, gu, gv) = cfg.split_mut(gx);
    let (nu, clamp) = (n + 1, |k: isize| k.clamp(0, n as isize - 1) as usize);
    // 4. Buoyancy.
    for j in 1..n {
        for i in 0..n {
            let b = cfg.buoyancy * 0.5 * gv2[j * n + i];
            gs2[(j - 1) * n + i] += b;
            gs2[j * n + i] += b;
        }
    }
    // 3. Walls: the wall faces were overwritten with zeros.
    for j in 0..n {
        gu2[j * nu] = 0.0;
        gu2[j * nu + n] = 0.0;
    }
    for i in 0..n {
        gv2[i] = 0.0;
        gv2[n * n + i] = 0.0;
    }
    // 2. Velocity advection.
    for j in 0..=n {
        for i in 0..n {
            let (a, b) = (clamp(j as isize - 1), clamp(j as isize));
            let ubar = 0.25 * (u[a * nu + i] + u[a * nu + i + 1] + u[b * nu + i] + u[b * nu + i + 1]);
            let vv = v[j * n + i];
            let (dpx, dpy) = sample_adjoint(v, gv, n, n + 1, 0.5, 0.0, i as f64 + 0.5 - ubar, j as f64 - vv, gv2[j * n + i]);
            gv[j * n + i] -= dpy;
            for c in [a * nu + i, a * nu + i + 1, b * nu + i, b * nu + i + 1] {
                gu[c] -= 0.25 * dpx;
            }
        }
    }
    for j in 0..n {
        for i in 0..=n {
            let (a, b) = (clamp(i as isize - 1), clamp(i as isize));
            let vbar = 0.25 * (v[j * n + a] + v[j * n + b] + v[(j + 1) * n + a] + v[(j + 1) * n + b]);
            let uu = u[j * nu + i];
            let (dpx, dpy) = sample_adjoint(u, gu, n + 1, n, 0.0, 0.5, i as f64 - uu, j as f64 + 0.5 - vbar, gu2[j * nu + i]);
            gu[j * nu + i] -= dpx;
            for c in [j * n + a, j * n + b, (j + 1) * n + a, (j + 1) * n + b] {
                gv[c] -= 0.25 * dpy;
            }
        }
    }
    // 1. Smoke.
    for j in 0..n {
        for i in 0..n {
            let uc = 0.5 * (u[j * nu + i] + u[j * nu + i + 1]);
            let vc = 0.5 * (v[j * n + i] + v[(j + 1) * n + i]);
            let (dpx, dpy) = sample_adjoint(s, gs, n, n, 0.5, 0.5, i as f64 + 0.5 - uc, j as f64 + 0.5 - vc, gs2[j * n + i]);
            gu[j * nu + i] -= 0.5 * dpx;
            gu[j * nu + i + 1] -= 0.5 * dpx;
            gv[j * n + i] -= 0.5 * dpy;
            gv[(j + 1) * n + i] -= 0.5 * dpy;
        }
    }
}

/// Divergence of a MAC velocity: `d[j][i] = u[j][i+1] − u[j][i] + v[j+1][i] − v[j][i]`
/// (overwrites `d`).
pub fn divergence(n: usize, u: &[f64], v: &[f64], d: &mut [f64]) {
    let nu = n + 1;
    for j in 0..n {
        for i in 0..n {
            d[j * n + i] = u[j * nu + i + 1] - u[j * nu + i] + v[(j + 1) * n + i] - v[j * n + i];
        }
    }
}

/// Transpose of [`divergence`]: `u += Dₓᵀ·d`, `v += D_yᵀ·d` (accumulates).
pub fn divergence_transpose(n: usize, d: &[f64], u: &mut [f64], v: &mut [f64]) {
    let nu = n + 1;
    for j in 0..n {
        for i in 0..n {
            let dv = d[j * n + i];
            u[j * nu + i + 1] += dv;
            u[j * nu + i] -= dv;
            v[(j + 1) * n + i] += dv;
            v[j * n + i] -= dv;
        }
    }
}

/// The pressure matrix of the closed box: `(A·p)[c] = Σ_{neighbours m of c
/// inside the box} (p[c] − p[m])` (overwrites `out`). Symmetric positive
/// semi-definite, constants in its null space. Row by row, branch-free
/// inside each row, so that it vectorises.
#[inline(always)]
pub fn apply_pressure_matrix(n: usize, p: &[f64], out: &mut [f64]) {
    for j in 0..n {
        let row = &p[j * n..(j + 1) * n];
        let dn = (j > 0).then(|| &p[(j - 1) * n..j * n]);
        let up = (j + 1 < n).then(|| &p[(j + 1) * n..(j + 2) * n]);
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

/// The pressure matrix with solid cells (`w[c] = 0`):
/// `out[c] = w_c·Σ_{m in box} w_m·(p_c − p_m) + (1 − w_c)·p_c`: only
/// fluid–fluid faces couple, solid rows are the identity. Symmetric.
pub fn apply_masked_matrix(n: usize, w: &[f64], p: &[f64], out: &mut [f64]) {
    for j in 0..n {
        for i in 0..n {
            let c = j * n + i;
            let pc = p[c];
            let mut acc = 0.0;
            if i > 0 {
                acc += w[c - 1] * (pc - p[c - 1]);
            }
            if i + 1 < n {
                acc += w[c + 1] * (pc - p[c + 1]);
            }
            if j > 0 {
                acc += w[c - n] * (pc - p[c - n]);
            }
            if j + 1 < n {
                acc += w[c + n] * (pc - p[c + n]);
            }
            out[c] = w[c] * acc + (1.0 - w[c]) * pc;
        }
    }
}

/// Zeroes the smoke in solid cells and the velocity on every face that
/// touches a solid cell (or a wall), in place on a packed state: the
/// obstacle boundary condition. Linear and self-adjoint (a diagonal 0/1
/// mask), so the same call is its own VJP.
pub fn apply_obstacle_mask(cfg: &Smoke2d, fluid: &[f64], x: &mut [f64]) {
    let n = cfg.n;
    let nu = n + 1;
    let (s, u, v) = cfg.split_mut(x);
    for (sv, &w) in s.iter_mut().zip(fluid) {
        *sv *= w;
    }
    for j in 0..n {
        for i in 0..=n {
            let open = if i == 0 || i == n { 0.0 } else { fluid[j * n + i - 1] * fluid[j * n + i] };
            u[j * nu + i] *= open;
        }
    }
    for j in 0..=n {
        for i in 0..n {
            let open = if j == 0 || j == n { 0.0 } else { fluid[(j - 1) * n + i] * fluid[j * n + i] };
            v[j * n + i] *= open;
        }
    }
}

/// A pressure solve that did not converge.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct NoConvergence {
    /// Iterations done.
    pub iterations: usize,
    /// Final true residual norm relative to `‖b‖`.
    pub relative_residual: f64,
    /// The relative tolerance asked for.
    pub tolerance: f64,
}

impl fmt::Display for NoConvergence {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        write!(
            f,
            "pressure solve did not converge: relative residual {:.3e} after {} iterations (tolerance {:.1e})",
            self.relative_residual, self.iterations, self.tolerance
        )
    }
}

impl std::error::Error for NoConvergence {}

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
}

impl fmt::Display for Preconditioner {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        f.write_str(match self {
            Preconditioner::None => "none",
            Preconditioner::Mic0 => "mic0",
            Preconditioner::Multigrid => "multigrid",
        })
    }
}

/// Conjugate gradients on the pressure matrix of an `n × n` closed box, with
/// reusable work buffers and the preconditioner factor computed once.
#[derive(Clone, Debug)]
pub struct PressureSolver {
    n: usize,
    /// Relative tolerance on the true residual, `‖b − A·p‖ ≤ tol·‖b‖`.
    pub tolerance: f64,
    /// More iterations than this is an error.
    pub max_iterations: usize,
    precond: Preconditioner,
    /// MIC(0) inverse diagonal.
    inv_diag: Vec<f64>,
    mg: Option<crate::multigrid::Multigrid>,
    /// Fluid indicator per cell (1 fluid, 0 solid) when there are obstacles.
    fluid: Option<Vec<f64>>,
    r: Vec<f64>,
    z: Vec<f64>,
    d: Vec<f64>,
    q: Vec<f64>,
}

impl PressureSolver {
    /// A solver for the `n × n` box with tolerance `tolerance`, at most
    /// `max_iterations` iterations, and the given preconditioner.
    pub fn new(n: usize, tolerance: f64, max_iterations: usize, precond: Preconditioner) -> Self {
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
        Self { n, tolerance, max_iterations, precond, inv_diag, mg, fluid: None, r: z.clone(), z: z.clone(), d: z.clone(), q: z }
    }

    /// A solver for the box with solid cells (`fluid[c] = 0`): the matrix
    /// couples only fluid cells (no flow through solid faces) and is the
    /// identity on solid cells. Unpreconditioned: the preconditioners here
    /// do not know the mask yet.
    pub fn with_obstacles(n: usize, tolerance: f64, max_iterations: usize, fluid: Vec<f64>) -> Self {
        assert_eq!(fluid.len(), n * n, "fluid mask length");
        let mut s = Self::new(n, tolerance, max_iterations, Preconditioner::None);
        s.fluid = Some(fluid);
        s
    }

    /// The fluid indicator, when there are obstacles.
    pub fn fluid(&self) -> Option<&[f64]> {
        self.fluid.as_deref()
    }

    /// The preconditioner in use.
    pub fn preconditioner(&self) -> Preconditioner {
        self.precond
    }

    /// `z = M⁻¹·r` (MIC(0): forward then backward substitution).
    fn precondition(&mut self) {
        let n = self.n;
        match self.precond {
            Preconditioner::None => self.z.copy_from_slice(&self.r),
            Preconditioner::Mic0 => mic0_apply(n, &self.inv_diag, &self.r, &mut self.z),
            Preconditioner::Multigrid => self.mg.as_mut().expect("multigrid hierarchy").apply(&self.r, &mut self.z),
        }
    }

    /// Solves `A·p = b` from `p = 0` until `‖b − A·p‖₂ ≤ tol·‖b‖₂` (true
    /// residual); overwrites `p`. `b` must sum to zero (the closed box's
    /// compatibility condition); it is projected onto that space to remove
    /// rounding. Returns the number of iterations.
    pub fn solve(&mut self, b: &[f64], p: &mut [f64]) -> Result<usize, NoConvergence> {
        let n = self.n;
        let nn = n * n;
        // Remove the component along the null vector (constant on the fluid).
        let (total, count) = match &self.fluid {
            None => (b.iter().sum::<f64>(), nn as f64),
            Some(w) => (b.iter().zip(w).map(|(b, w)| b * w).sum::<f64>(), w.iter().sum::<f64>()),
        };
        let mean = total / count.max(1.0);
        // The right-hand side minus its mean on the fluid cells.
        let fluid_mean = |c: usize, fluid: &Option<Vec<f64>>| mean * fluid.as_ref().map_or(1.0, |w| w[c]);
        for (c, (r, &bv)) in self.r.iter_mut().zip(b).enumerate() {
            *r = bv - fluid_mean(c, &self.fluid);
        }
        p.fill(0.0);
        let bnorm = dot(&self.r, &self.r).sqrt();
        if bnorm == 0.0 {
            return Ok(0);
        }
        let target = self.tolerance * bnorm;
        let plain = self.precond == Preconditioner::None;
        let mut rz = self.restart();
        let mut rr = dot(&self.r, &self.r);
        let mut it = 0;
        loop {
            if rr.sqrt() <= target {
                // Confirm on the true residual; restart from it if needed.
                match &self.fluid {
                    None => apply_pressure_matrix(n, p, &mut self.q),
                    Some(w) => apply_masked_matrix(n, w, p, &mut self.q),
                }
                for (c, ((q, &bv), r)) in self.q.iter().zip(b).zip(self.r.iter_mut()).enumerate() {
                    *r = bv - fluid_mean(c, &self.fluid) - q;
                }
                rr = dot(&self.r, &self.r);
                if rr.sqrt() <= target {
                    return Ok(it);
                }
                rz = self.restart();
            }
            if it >= self.max_iterations || !rr.is_finite() {
                return Err(NoConvergence { iterations: it, relative_residual: rr.sqrt() / bnorm, tolerance: self.tolerance });
            }
            let mut dq = 0.0;
            match &self.fluid {
                None => matvec_dot(n, &self.d, &mut self.q, &mut dq),
                Some(w) => {
                    apply_masked_matrix(n, w, &self.d, &mut self.q);
                    dq = dot(&self.d, &self.q);
                }
            }
            let alpha = rz / dq;
            update(alpha, &self.d, &self.q, p, &mut self.r, &mut rr);
            let rz_new = if plain {
                rr
            } else {
                self.precondition();
                dot(&self.r, &self.z)
            };
            let beta = rz_new / rz;
            rz = rz_new;
            direction(beta, if plain { &self.r } else { &self.z }, &mut self.d);
            it += 1;
        }
    }

    /// `d = M⁻¹·r`; returns `r·M⁻¹·r`.
    fn restart(&mut self) -> f64 {
        self.precondition();
        self.d.copy_from_slice(&self.z);
        dot(&self.r, &self.z)
    }
}

crate::simd_dispatch! {
    /// `q = A·d` and `*dq = d·q` in one pass.
    fn matvec_dot(n: usize, d: &[f64], q: &mut [f64], dq: &mut f64) => matvec_dot_body
}

#[inline(always)]
fn matvec_dot_body(n: usize, d: &[f64], q: &mut [f64], dq: &mut f64) {
    apply_pressure_matrix(n, d, q);
    *dq = dot(d, q);
}

crate::simd_dispatch! {
    /// `p += α·d`, `r −= α·q`, `*rr = r·r` in one pass.
    fn update(alpha: f64, d: &[f64], q: &[f64], p: &mut [f64], r: &mut [f64], rr: &mut f64) => update_body
}

#[inline(always)]
fn update_body(alpha: f64, d: &[f64], q: &[f64], p: &mut [f64], r: &mut [f64], rr: &mut f64) {
    let mut acc = [0.0f64; 8];
    let mut tail = 0.0;
    let (mut pc, mut rc) = (p.chunks_exact_mut(8), r.chunks_exact_mut(8));
    let (mut dc, mut qc) = (d.chunks_exact(8), q.chunks_exact(8));
    for (((pv, rv), dv), qv) in (&mut pc).zip(&mut rc).zip(&mut dc).zip(&mut qc) {
        for l in 0..8 {
            pv[l] += alpha * dv[l];
            rv[l] -= alpha * qv[l];
            acc[l] += rv[l] * rv[l];
        }
    }
    for (((pv, rv), dv), qv) in pc.into_remainder().iter_mut().zip(rc.into_remainder().iter_mut()).zip(dc.remainder()).zip(qc.remainder()) {
        *pv += alpha * dv;
        *rv -= alpha * qv;
        tail += *rv * *rv;
    }
    *rr = acc.iter().sum::<f64>() + tail;
}

crate::simd_dispatch! {
    /// `d = z + β·d`.
    fn direction(beta: f64, z: &[f64], d: &mut [f64]) => direction_body
}

#[inline(always)]
fn direction_body(beta: f64, z: &[f64], d: &mut [f64]) {
    for (dv, &zv) in d.iter_mut().zip(z) {
        *dv = zv + beta * *dv;
    }
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

/// Dot product with eight independent partial sums (vectorises; a fixed
/// summation order, so results do not depend on the machine).
#[inline(always)]
fn dot(a: &[f64], b: &[f64]) -> f64 {
    let mut acc = [0.0f64; 8];
    let (ca, cb) = (a.chunks_exact(8), b.chunks_exact(8));
    let tail: f64 = ca.remainder().iter().zip(cb.remainder()).map(|(x, y)| x * y).sum();
    for (x, y) in ca.zip(cb) {
        for k in 0..8 {
            acc[k] += x[k] * y[k];
        }
    }
    acc.iter().sum::<f64>() + tail
}

/// Scratch of the projection: divergence and pressure.
#[derive(Clone, Debug)]
pub struct ProjectScratch {
    d: Vec<f64>,
    p: Vec<f64>,
}

impl ProjectScratch {
    /// Scratch for an `n × n` box.
    pub fn new(n: usize) -> Self {
        Self { d: vec![0.0; n * n], p: vec![0.0; n * n] }
    }
}

/// Step 5 of P2, in place on the velocity part of the packed state `y`:
/// `d = D·(u, v)`, solve `A·p = −d`, `u −= Gₓ·p`, `v −= G_y·p` on the
/// interior faces. Returns the CG iterations.
pub fn project(cfg: &Smoke2d, y: &mut [f64], solver: &mut PressureSolver, scratch: &mut ProjectScratch) -> Result<usize, NoConvergence> {
    let n = cfg.n;
    let (_, u, v) = cfg.split_mut(y);
    divergence(n, u, v, &mut scratch.d);
    for d in scratch.d.iter_mut() {
        *d = -*d;
    }
    if let Some(w) = solver.fluid() {
        for (d, &wv) in scratch.d.iter_mut().zip(w) {
            *d *= wv;
        }
    }
    let iterations = solver.solve(&scratch.d, &mut scratch.p)?;
    subtract_gradient(n, &scratch.p, solver.fluid(), u, v);
    Ok(iterations)
}

/// `u[j][i] −= p[j][i] − p[j][i−1]` (i = 1..N−1), `v[j][i] −= p[j][i] − p[j−1][i]` (j = 1..N−1),
/// on fluid–fluid faces only when there is a mask.
fn subtract_gradient(n: usize, p: &[f64], fluid: Option<&[f64]>, u: &mut [f64], v: &mut [f64]) {
    let nu = n + 1;
    let open = |a: usize, b: usize| fluid.map_or(1.0, |w| w[a] * w[b]);
    for j in 0..n {
        for i in 1..n {
            let (a, b) = (j * n + i, j * n + i - 1);
            u[j * nu + i] -= open(a, b) * (p[a] - p[b]);
        }
    }
    for j in 1..n {
        for i in 0..n {
            let (a, b) = (j * n + i, (j - 1) * n + i);
            v[j * n + i] -= open(a, b) * (p[a] - p[b]);
        }
    }
}

/// Adjoint of [`project`] (a linear map), in place on the velocity part of
/// the adjoint `g`: `λ_p = −Gᵀ·λ`; solve `A·μ = λ_p` (the transposed
/// system — `A` is symmetric — to the same tolerance; never a backward pass
/// through the iterations); since the solve's right-hand side was `−D·(u, v)`,
/// `λ_(u,v) += −Dᵀ·μ`. Returns the CG iterations.
pub fn project_adjoint(cfg: &Smoke2d, g: &mut [f64], solver: &mut PressureSolver, scratch: &mut ProjectScratch) -> Result<usize, NoConvergence> {
    let n = cfg.n;
    let nu = n + 1;
    let (_, gu, gv) = cfg.split_mut(g);
    let fluid = solver.fluid().map(<[f64]>::to_vec);
    let open = |a: usize, b: usize| fluid.as_ref().map_or(1.0, |w| w[a] * w[b]);
    // λ_p[c] = ∂/∂p of Σ λ·(u − G·p) = −(Gᵀ·λ)[c] (fluid–fluid faces only
    // when there is a mask).
    let lp = &mut scratch.d;
    lp.fill(0.0);
    for j in 0..n {
        for i in 1..n {
            let l = open(j * n + i, j * n + i - 1) * gu[j * nu + i];
            lp[j * n + i] -= l;
            lp[j * n + i - 1] += l;
        }
    }
    for j in 1..n {
        for i in 0..n {
            let l = open(j * n + i, (j - 1) * n + i) * gv[j * n + i];
            lp[j * n + i] -= l;
            lp[(j - 1) * n + i] += l;
        }
    }
    // p = A⁻¹·b with b = −W·D·u: λ_b = A⁻ᵀ·λ_p = μ, λ_(u,v) += Dᵀ·(−W·μ).
    let iterations = solver.solve(lp, &mut scratch.p)?;
    for (c, m) in scratch.p.iter_mut().enumerate() {
        *m = -*m * fluid.as_ref().map_or(1.0, |w| w[c]);
    }
    divergence_transpose(n, &scratch.p, gu, gv);
    Ok(iterations)
}

/// P2's initial state: zero velocity, smoke 1 in every cell whose centre lies
/// within `N/8` of `(N/2, N/4)`, packed as `[s, u, v]`.
pub fn p2_initial(cfg: &Smoke2d) -> Vec<f64> {
    let mut x = vec![0.0; cfg.n_state()];
    x[..cfg.n_s()].copy_from_slice(&disc(cfg.n, 0.25));
    x
}

/// P2's target smoke: the same disc centred at `(N/2, 3N/4)`.
pub fn p2_target(cfg: &Smoke2d) -> Vec<f64> {
    disc(cfg.n, 0.75)
}

fn disc(n: usize, cy: f64) -> Vec<f64> {
    let nf = n as f64;
    let mut s = vec![0.0; n * n];
    for j in 0..n {
        for i in 0..n {
            let (dx, dy) = (i as f64 + 0.5 - nf / 2.0, j as f64 + 0.5 - cy * nf);
            if dx * dx + dy * dy <= (nf / 8.0) * (nf / 8.0) {
                s[j * n + i] = 1.0;
            }
        }
    }
    s
}

/// P2 loss `L = ½·Σ (s_T − s*)²` on the smoke part of the packed state;
/// writes `∂L/∂x` (zero on the velocity part) into `grad` (overwrites).
pub fn p2_loss(cfg: &Smoke2d, x: &[f64], target: &[f64], grad: &mut [f64]) -> f64 {
    grad.fill(0.0);
    let mut sum = 0.0;
    for ((g, &s), &t) in grad.iter_mut().zip(&x[..cfg.n_s()]).zip(target) {
        let d = s - t;
        sum += d * d;
        *g = d;
    }
    0.5 * sum
}

/// Reference values of one P2 size (JAX, float64; `benchmarks.md`).
#[derive(Clone, Copy, Debug)]
pub struct P2Reference {
    /// Cells per side.
    pub n: usize,
    /// Steps.
    pub steps: usize,
    /// Loss.
    pub loss: f64,
    /// ‖∇L‖₂.
    pub grad_l2: f64,
    /// ∂L/∂s at flat index 0.
    pub grad_0: f64,
    /// ∂L/∂s at flat index N²/2.
    pub grad_n2: f64,
}

/// The two P2 sizes with their reference values.
pub const P2_SIZES: [P2Reference; 2] = [
    P2Reference { n: 64, steps: 20, loss: 183.8917448743, grad_l2: 18.18088488397, grad_0: 1.37382956e-4, grad_n2: -3.78117637e-3 },
    P2Reference { n: 128, steps: 20, loss: 768.1330262886, grad_l2: 38.36607301311, grad_0: 1.88809603e-5, grad_n2: -1.54349595e-3 },
];

/// First-order upwind advection of the smoke by the MAC velocity, in
/// conservative (flux) form over one time step `dt`, closed walls (no flux
/// through the box's sides): reads `x = [s, u, v]`, writes `y = [s', u, v]`.
pub fn advect_upwind(cfg: &Smoke2d, dt: f64, x: &[f64], y: &mut [f64]) {
    let n = cfg.n;
    assert!(n >= 2 && x.len() == cfg.n_state() && y.len() == cfg.n_state(), "smoke: state lengths");
    let (s, u, v) = cfg.split(x);
    let nu = n + 1;
    let (s2, rest) = y.split_at_mut(cfg.n_s());
    // Explicit copy loops: `copy_from_slice` into part of a buffer Enzyme
    // differentiates has given silently wrong gradients (ENZYME.md).
    for (o, &a) in s2.iter_mut().zip(s) {
        *o = a;
    }
    // Interior x-faces: flux from cell (i−1, j) to (i, j).
    for j in 0..n {
        for i in 1..n {
            let uf = u[j * nu + i];
            let up = if uf > 0.0 { s[j * n + i - 1] } else { s[j * n + i] };
            let f = dt * uf * up;
            s2[j * n + i - 1] -= f;
            s2[j * n + i] += f;
        }
    }
    // Interior y-faces: flux from cell (i, j−1) to (i, j).
    for j in 1..n {
        for i in 0..n {
            let vf = v[j * n + i];
            let up = if vf > 0.0 { s[(j - 1) * n + i] } else { s[j * n + i] };
            let f = dt * vf * up;
            s2[(j - 1) * n + i] -= f;
            s2[j * n + i] += f;
        }
    }
    for (o, &a) in rest.iter_mut().zip(&x[cfg.n_s()..]) {
        *o = a;
    }
}

/// Distance to the nearest upwind switch of [`advect_upwind`] along `d`: the
/// smallest `|u_f / d_f|` over the interior faces whose velocity moves.
pub fn upwind_radius(cfg: &Smoke2d, x: &[f64], d: &[f64]) -> f64 {
    let n = cfg.n;
    let (_, u, v) = cfg.split(x);
    let (_, du, dv) = cfg.split(d);
    let mut r = f64::INFINITY;
    for j in 0..n {
        for i in 1..n {
            let k = j * (n + 1) + i;
            if du[k] != 0.0 {
                r = r.min((u[k] / du[k]).abs());
            }
        }
    }
    for j in 1..n {
        for i in 0..n {
            let k = j * n + i;
            if dv[k] != 0.0 {
                r = r.min((v[k] / dv[k]).abs());
            }
        }
    }
    r
}

/// MacCormack advection of the smoke (second order): a semi-Lagrangian step
/// back along the velocity, one forward from its result, and half the
/// difference as a correction, `s' = ŝ + (s − s̃)/2`. With `limiter`, each
/// corrected value is clamped to the range of the four samples the first
/// step interpolated from (Selle et al. 2008), which keeps the scheme free
/// of new extrema; without it the scheme is second order also at extrema.
/// Reads `x = [s, u, v]`, writes `y = [s', u, v]`; `scratch` holds `ŝ` and
/// `s̃` (`2·N²` values).
pub fn advect_maccormack(cfg: &Smoke2d, limiter: bool, x: &[f64], y: &mut [f64], scratch: &mut [f64]) {
    let n = cfg.n;
    assert!(n >= 2 && x.len() == cfg.n_state() && y.len() == cfg.n_state() && scratch.len() == 2 * cfg.n_s(), "smoke: state lengths");
    let (s, u, v) = cfg.split(x);
    let (hat, tilde) = scratch.split_at_mut(cfg.n_s());
    let nu = n + 1;
    let vel = |i: usize, j: usize| (0.5 * (u[j * nu + i] + u[j * nu + i + 1]), 0.5 * (v[j * n + i] + v[(j + 1) * n + i]));
    for j in 0..n {
        for i in 0..n {
            let (uc, vc) = vel(i, j);
            hat[j * n + i] = sample(s, n, n, 0.5, 0.5, i as f64 + 0.5 - uc, j as f64 + 0.5 - vc);
        }
    }
    for j in 0..n {
        for i in 0..n {
            let (uc, vc) = vel(i, j);
            tilde[j * n + i] = sample(hat, n, n, 0.5, 0.5, i as f64 + 0.5 + uc, j as f64 + 0.5 + vc);
        }
    }
    let (s2, rest) = y.split_at_mut(cfg.n_s());
    for j in 0..n {
        for i in 0..n {
            let c = j * n + i;
            let mut val = hat[c] + 0.5 * (s[c] - tilde[c]);
            if limiter {
                let (uc, vc) = vel(i, j);
                let (lo, hi) = sample_range(s, n, n, 0.5, 0.5, i as f64 + 0.5 - uc, j as f64 + 0.5 - vc);
                val = val.clamp(lo, hi);
            }
            s2[c] = val;
        }
    }
    // Explicit copy loop (see `advect_upwind`).
    for (o, &a) in rest.iter_mut().zip(&x[cfg.n_s()..]) {
        *o = a;
    }
}

/// The smallest and largest of the four lattice values [`sample`] blends
/// at this point.
#[inline(always)]
#[allow(clippy::too_many_arguments)]
fn sample_range(f: &[f64], nx: usize, ny: usize, ox: f64, oy: f64, px: f64, py: f64) -> (f64, f64) {
    let (k0, l0, _, _) = lattice_position(nx, ny, px - ox, py - oy);
    let a = [f[l0 * nx + k0], f[l0 * nx + k0 + 1], f[(l0 + 1) * nx + k0], f[(l0 + 1) * nx + k0 + 1]];
    (a[0].min(a[1]).min(a[2].min(a[3])), a[0].max(a[1]).max(a[2].max(a[3])))
}

/// An external force on the interior faces over a time step `dt`:
/// `[s, u, v] ↦ [s, u + dt·fu, v + dt·fv]`, with the force `f = [fu, fv]`
/// given per face (`N·(N+1)` values each, the velocity layout); the wall
/// faces keep their velocity.
pub fn apply_force(cfg: &Smoke2d, dt: f64, x: &[f64], f: &[f64], y: &mut [f64]) {
    let n = cfg.n;
    assert!(x.len() == cfg.n_state() && y.len() == cfg.n_state() && f.len() == 2 * cfg.n_u(), "smoke: force lengths");
    let nu = n + 1;
    for (o, &a) in y.iter_mut().zip(x) {
        *o = a;
    }
    let (fu, fv) = f.split_at(cfg.n_u());
    let (_, u2, v2) = cfg.split_mut(y);
    for j in 0..n {
        for i in 1..n {
            u2[j * nu + i] += dt * fu[j * nu + i];
        }
    }
    for j in 1..n {
        for i in 0..n {
            v2[j * n + i] += dt * fv[j * n + i];
        }
    }
}

/// Inflow: in the cells `i0..i1 × j0..j1` set the smoke to `p[0]` and the
/// velocity on the faces of those cells (walls excepted) to `(p[1], p[2])`;
/// everything else passes through.
pub fn apply_inflow(cfg: &Smoke2d, region: [usize; 4], x: &[f64], p: &[f64], y: &mut [f64]) {
    let n = cfg.n;
    let [i0, i1, j0, j1] = region;
    assert!(x.len() == cfg.n_state() && y.len() == cfg.n_state() && p.len() == 3 && i0 < i1 && i1 <= n && j0 < j1 && j1 <= n, "smoke: inflow");
    let nu = n + 1;
    for (o, &a) in y.iter_mut().zip(x) {
        *o = a;
    }
    let (s2, u2, v2) = cfg.split_mut(y);
    for j in j0..j1 {
        for i in i0..i1 {
            s2[j * n + i] = p[0];
        }
        for i in i0.max(1)..=i1.min(n - 1) {
            u2[j * nu + i] = p[1];
        }
    }
    for j in j0.max(1)..=j1.min(n - 1) {
        for i in i0..i1 {
            v2[j * n + i] = p[2];
        }
    }
}

/// Solid cells of an axis-aligned box `[lower, upper)` in cell units (x
/// first), for [`PressureSolver::with_obstacles`] and the fluid operators: a
/// cell is solid when its centre lies inside. The box is clipped to the
/// domain; `None` when no cell centre lies inside (a box wholly outside).
pub fn obstacle_box(n: usize, lower: [f64; 2], upper: [f64; 2]) -> Option<Vec<bool>> {
    obstacle(n, |x, y| x >= lower[0] && x < upper[0] && y >= lower[1] && y < upper[1])
}

/// Solid cells of a disc (centre in cell units, x first): a cell is solid
/// when its centre lies within `radius`. `None` when no cell is covered.
pub fn obstacle_disc(n: usize, center: [f64; 2], radius: f64) -> Option<Vec<bool>> {
    obstacle(n, |x, y| (x - center[0]).powi(2) + (y - center[1]).powi(2) <= radius * radius)
}

fn obstacle(n: usize, inside: impl Fn(f64, f64) -> bool) -> Option<Vec<bool>> {
    let solid: Vec<bool> = (0..n * n).map(|c| inside((c % n) as f64 + 0.5, (c / n) as f64 + 0.5)).collect();
    solid.iter().any(|&s| s).then_some(solid)
}
