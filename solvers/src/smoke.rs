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

/// Bilinear sample of a lattice `f` of `nx × ny` samples whose sample
/// `(k, l)` sits at `(k + ox, l + oy)`, at the point `(px, py)`; positions
/// outside are clamped to the lattice's edge (P2's rule).
#[inline(always)]
#[allow(clippy::too_many_arguments)]
pub fn sample(f: &[f64], nx: usize, ny: usize, ox: f64, oy: f64, px: f64, py: f64) -> f64 {
    let gx = (px - ox).clamp(0.0, (nx - 1) as f64);
    let gy = (py - oy).clamp(0.0, (ny - 1) as f64);
    let k0 = (gx.floor() as usize).min(nx - 2);
    let l0 = (gy.floor() as usize).min(ny - 2);
    let fx = gx - k0 as f64;
    let fy = gy - l0 as f64;
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
/// semi-definite, constants in its null space.
pub fn apply_pressure_matrix(n: usize, p: &[f64], out: &mut [f64]) {
    for j in 0..n {
        for i in 0..n {
            let c = j * n + i;
            let pc = p[c];
            let mut acc = 0.0;
            if i > 0 {
                acc += pc - p[c - 1];
            }
            if i + 1 < n {
                acc += pc - p[c + 1];
            }
            if j > 0 {
                acc += pc - p[c - n];
            }
            if j + 1 < n {
                acc += pc - p[c + n];
            }
            out[c] = acc;
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
}

impl fmt::Display for Preconditioner {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        f.write_str(match self {
            Preconditioner::None => "none",
            Preconditioner::Mic0 => "mic0",
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
        Self { n, tolerance, max_iterations, precond, inv_diag, r: z.clone(), z: z.clone(), d: z.clone(), q: z }
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
            Preconditioner::Mic0 => {
                let (r, z, pc) = (&self.r, &mut self.z, &self.inv_diag);
                // Solve L·q = r (q stored in z).
                for j in 0..n {
                    for i in 0..n {
                        let c = j * n + i;
                        let mut t = r[c];
                        if i > 0 {
                            t += z[c - 1] * pc[c - 1];
                        }
                        if j > 0 {
                            t += z[c - n] * pc[c - n];
                        }
                        z[c] = t * pc[c];
                    }
                }
                // Solve Lᵀ·z = q.
                for j in (0..n).rev() {
                    for i in (0..n).rev() {
                        let c = j * n + i;
                        let mut t = z[c];
                        if i + 1 < n {
                            t += z[c + 1] * pc[c];
                        }
                        if j + 1 < n {
                            t += z[c + n] * pc[c];
                        }
                        z[c] = t * pc[c];
                    }
                }
            }
        }
    }

    /// Solves `A·p = b` from `p = 0` until `‖b − A·p‖₂ ≤ tol·‖b‖₂` (true
    /// residual); overwrites `p`. `b` must sum to zero (the closed box's
    /// compatibility condition); it is projected onto that space to remove
    /// rounding. Returns the number of iterations.
    pub fn solve(&mut self, b: &[f64], p: &mut [f64]) -> Result<usize, NoConvergence> {
        let nn = self.n * self.n;
        let mean = b.iter().sum::<f64>() / nn as f64;
        for (r, &bv) in self.r.iter_mut().zip(b) {
            *r = bv - mean;
        }
        p.fill(0.0);
        let bnorm = dot(&self.r, &self.r).sqrt();
        if bnorm == 0.0 {
            return Ok(0);
        }
        let target = self.tolerance * bnorm;
        self.precondition();
        self.d.copy_from_slice(&self.z);
        let mut rz = dot(&self.r, &self.z);
        let mut it = 0;
        loop {
            let rnorm = dot(&self.r, &self.r).sqrt();
            if rnorm <= target {
                // Confirm on the true residual.
                apply_pressure_matrix(self.n, p, &mut self.q);
                let mut t = 0.0;
                for ((q, &bv), r) in self.q.iter().zip(b).zip(self.r.iter_mut()) {
                    *r = bv - mean - q;
                    t += *r * *r;
                }
                if t.sqrt() <= target {
                    return Ok(it);
                }
                // Restart from the true residual.
                self.precondition();
                self.d.copy_from_slice(&self.z);
                rz = dot(&self.r, &self.z);
            }
            if it >= self.max_iterations || !rnorm.is_finite() {
                return Err(NoConvergence { iterations: it, relative_residual: rnorm / bnorm, tolerance: self.tolerance });
            }
            apply_pressure_matrix(self.n, &self.d, &mut self.q);
            let alpha = rz / dot(&self.d, &self.q);
            for ((pv, &dv), (r, &qv)) in p.iter_mut().zip(&self.d).zip(self.r.iter_mut().zip(&self.q)) {
                *pv += alpha * dv;
                *r -= alpha * qv;
            }
            self.precondition();
            let rz_new = dot(&self.r, &self.z);
            let beta = rz_new / rz;
            rz = rz_new;
            for (dv, &zv) in self.d.iter_mut().zip(&self.z) {
                *dv = zv + beta * *dv;
            }
            it += 1;
        }
    }
}

fn dot(a: &[f64], b: &[f64]) -> f64 {
    a.iter().zip(b).map(|(a, b)| a * b).sum()
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
    let iterations = solver.solve(&scratch.d, &mut scratch.p)?;
    subtract_gradient(n, &scratch.p, u, v);
    Ok(iterations)
}

/// `u[j][i] −= p[j][i] − p[j][i−1]` (i = 1..N−1), `v[j][i] −= p[j][i] − p[j−1][i]` (j = 1..N−1).
fn subtract_gradient(n: usize, p: &[f64], u: &mut [f64], v: &mut [f64]) {
    let nu = n + 1;
    for j in 0..n {
        for i in 1..n {
            u[j * nu + i] -= p[j * n + i] - p[j * n + i - 1];
        }
    }
    for j in 1..n {
        for i in 0..n {
            v[j * n + i] -= p[j * n + i] - p[(j - 1) * n + i];
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
    // λ_p[c] = ∂/∂p of Σ λ·(u − G·p) = −(Gᵀ·λ)[c].
    let lp = &mut scratch.d;
    lp.fill(0.0);
    for j in 0..n {
        for i in 1..n {
            let l = gu[j * nu + i];
            lp[j * n + i] -= l;
            lp[j * n + i - 1] += l;
        }
    }
    for j in 1..n {
        for i in 0..n {
            let l = gv[j * n + i];
            lp[j * n + i] -= l;
            lp[(j - 1) * n + i] += l;
        }
    }
    // p = A⁻¹·b with b = −d: λ_b = A⁻ᵀ·λ_p = μ, λ_d = −μ, λ_(u,v) += Dᵀ·λ_d.
    let iterations = solver.solve(lp, &mut scratch.p)?;
    for m in scratch.p.iter_mut() {
        *m = -*m;
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
