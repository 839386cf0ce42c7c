//! 1D viscous Burgers on a periodic grid: first-order upwind advection and
//! central diffusion, explicit Euler in time (benchmark P1 `burgers1d`).
//!
//! One step, for every cell `i` (indices periodic), with `l = u[i-1]`,
//! `c = u[i]`, `r = u[i+1]`:
//!
//! ```text
//! adv   = c·(c − l)/dx  if c > 0,  else c·(r − c)/dx
//! dif   = ν·(r − 2c + l)/dx²
//! u'[i] = c + dt·(dif − adv)
//! ```
//!
//! The loops are branch-free (the upwind switch is a select) and the two
//! periodic boundary cells are handled outside the vectorisable interior loop.

use std::f64::consts::PI;

use crate::real::Real;

/// Grid and parameters of one Burgers step. Plain data: it is passed as a
/// constant to generated derivatives.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Burgers1d {
    /// Number of cells.
    pub n: usize,
    /// Cell width.
    pub dx: f64,
    /// Time step.
    pub dt: f64,
    /// Viscosity ν.
    pub nu: f64,
}

/// Viscosity of benchmark P1.
pub const P1_NU: f64 = 0.01;

impl Burgers1d {
    /// The P1 grid with `n` cells on [0, 2π): `dx = 2π/n`, `ν = 0.01`,
    /// `dt = min(0.25·dx, 0.25·dx²/ν)`.
    pub fn p1(n: usize) -> Self {
        let dx = 2.0 * PI / n as f64;
        let dt = (0.25 * dx).min(0.25 * dx * dx / P1_NU);
        Self { n, dx, dt, nu: P1_NU }
    }

    /// Cell positions `x_i = i·dx`.
    pub fn grid(&self) -> Vec<f64> {
        (0..self.n).map(|i| i as f64 * self.dx).collect()
    }

    /// `(dt·ν/dx², dt/dx)`: the diffusion and advection coefficients of a step.
    #[inline(always)]
    pub fn coefficients(&self) -> (f64, f64) {
        (self.dt * self.nu / (self.dx * self.dx), self.dt / self.dx)
    }
}

/// New value of one cell from its left, centre and right neighbours:
/// `c + a·(r − 2c + l) − b·c·(c − l or r − c)`, the upwind difference
/// chosen by a select (no branch), so that the loop vectorises.
#[inline(always)]
pub fn cell<R: Real>(l: R, c: R, r: R, a: R, b: R) -> R {
    let (d1, d2) = (c - l, r - c);
    let up = if c > R::zero() { d1 } else { d2 };
    c + a * (d2 - d1) - b * c * up
}

crate::simd_dispatch! {
    /// One explicit step: writes `out = step(u)` (overwrites `out`), with the
    /// widest vector instructions the CPU has (see [`crate::simd`]).
    ///
    /// # Panics
    /// If `u` and `out` do not both have `cfg.n ≥ 3` elements.
    pub fn step(cfg: &Burgers1d, u: &[f64], out: &mut [f64]) => step_body
}

/// [`step`] in baseline x86-64 instructions (no run-time dispatch).
#[inline(always)]
pub fn step_body(cfg: &Burgers1d, u: &[f64], out: &mut [f64]) {
    let n = cfg.n;
    assert!(n >= 3 && u.len() == n && out.len() == n, "burgers step: need n ≥ 3 and matching lengths");
    // Interior: three equal-length shifted views.
    step_map(cfg, &u[..n - 2], &u[1..n - 1], &u[2..], &mut out[1..n - 1]);
    let (a, b) = cfg.coefficients();
    out[0] = cell(u[n - 1], u[0], u[1], a, b);
    out[n - 1] = cell(u[n - 2], u[n - 1], u[0], a, b);
}

/// The step as a pointwise map over shifted views: `out[i] = cell(l[i],
/// c[i], r[i])`, where `l, c, r` are the state shifted by −1, 0, +1 (the
/// form diffsim's stencil operators differentiate). Loops over the shortest
/// of the slices; no bounds checks, vectorises.
#[inline(always)]
pub fn step_map<R: Real>(cfg: &Burgers1d, l: &[R], c: &[R], r: &[R], out: &mut [R]) {
    let (a, b) = cfg.coefficients();
    let (a, b) = (R::of(a), R::of(b));
    for (((o, &l), &c), &r) in out.iter_mut().zip(l).zip(c).zip(r) {
        *o = cell(l, c, r, a, b);
    }
}

/// Contribution of the adjoints `gl, gc, gr` of cells `j−1, j, j+1` to the
/// adjoint of `u[j]`, given the state `l, c, r` = `u[j−1], u[j], u[j+1]`.
#[inline(always)]
#[allow(clippy::too_many_arguments)]
fn cell_adjoint(l: f64, c: f64, r: f64, gl: f64, gc: f64, gr: f64, a: f64, b: f64) -> f64 {
    // ∂u'[j+1]/∂u[j] = a + b·r·[r > 0]              (u[j] is the left neighbour of j+1)
    // ∂u'[j]  /∂u[j] = 1 − 2a − b·(2c − l)          if c > 0
    //                = 1 − 2a − b·(r − 2c)          otherwise
    // ∂u'[j−1]/∂u[j] = a − b·l·[l ≤ 0]              (u[j] is the right neighbour of j−1)
    let rp = if r > 0.0 { r } else { 0.0 };
    let lm = if l > 0.0 { 0.0 } else { l };
    let dcc = if c > 0.0 { 2.0 * c - l } else { r - 2.0 * c };
    gr * (a + b * rp) + gc * (1.0 - 2.0 * a - b * dcc) + gl * (a - b * lm)
}

crate::simd_dispatch! {
    /// Hand-written adjoint of [`step`]: `du += (∂step/∂u)ᵀ·g`, evaluated at the
    /// state `u` the step was taken from (accumulates into `du`).
    ///
    /// # Panics
    /// If the slices do not all have `cfg.n ≥ 3` elements.
    pub fn step_adjoint(cfg: &Burgers1d, u: &[f64], g: &[f64], du: &mut [f64]) => step_adjoint_body
}

crate::simd_dispatch! {
    /// [`step_adjoint`] that overwrites: `du = (∂step/∂u)ᵀ·g`.
    ///
    /// # Panics
    /// If the slices do not all have `cfg.n ≥ 3` elements.
    pub fn step_adjoint_overwrite(cfg: &Burgers1d, u: &[f64], g: &[f64], du: &mut [f64]) => step_adjoint_overwrite_body
}

#[inline(always)]
fn step_adjoint_body(cfg: &Burgers1d, u: &[f64], g: &[f64], du: &mut [f64]) {
    adjoint::<true>(cfg, u, g, du)
}

#[inline(always)]
fn step_adjoint_overwrite_body(cfg: &Burgers1d, u: &[f64], g: &[f64], du: &mut [f64]) {
    adjoint::<false>(cfg, u, g, du)
}

/// The adjoint in gather form: `du[j] (+)= Σ_i g[i]·∂u'[i]/∂u[j]` over the
/// three cells `i = j−1, j, j+1`; adds when `ADD`, overwrites otherwise.
#[inline(always)]
fn adjoint<const ADD: bool>(cfg: &Burgers1d, u: &[f64], g: &[f64], du: &mut [f64]) {
    let n = cfg.n;
    assert!(n >= 3 && u.len() == n && g.len() == n && du.len() == n, "burgers adjoint: need n ≥ 3 and matching lengths");
    put::<ADD>(&mut du[0], step_adjoint_cell(cfg, u, g, 0));
    adjoint_cells::<ADD>(cfg, u, g, &mut du[1..n - 1], 1);
    put::<ADD>(&mut du[n - 1], step_adjoint_cell(cfg, u, g, n - 1));
}

/// `*d += v` when `ADD`, else `*d = v`.
#[inline(always)]
fn put<const ADD: bool>(d: &mut f64, v: f64) {
    if ADD { *d += v } else { *d = v }
}

/// The gather for the inside cells `s..s + du.len()` (`1 ≤ s`,
/// `s + du.len() ≤ n − 1`): three shifted views of the state and the seed.
#[inline(always)]
fn adjoint_cells<const ADD: bool>(cfg: &Burgers1d, u: &[f64], g: &[f64], du: &mut [f64], s: usize) {
    let (n, m) = (cfg.n, du.len());
    assert!(u.len() == n && g.len() == n && s >= 1 && s + m < n, "burgers adjoint cells: range {s}..{} not inside 1..{}", s + m, n - 1);
    let (a, b) = cfg.coefficients();
    let (l, c, r) = (&u[s - 1..s - 1 + m], &u[s..s + m], &u[s + 1..s + 1 + m]);
    let (gl, gc, gr) = (&g[s - 1..s - 1 + m], &g[s..s + m], &g[s + 1..s + 1 + m]);
    for (i, d) in du.iter_mut().enumerate() {
        put::<ADD>(d, cell_adjoint(l[i], c[i], r[i], gl[i], gc[i], gr[i], a, b));
    }
}

crate::simd_dispatch! {
    /// [`step_adjoint_overwrite`] for the cells `s..s + du.len()` only, all
    /// inside (`1 ≤ s`, `s + du.len() ≤ n − 1`): `du[i] = ((∂step/∂u)ᵀ·g)[s + i]`,
    /// so that a caller can split the cells over threads (the two end cells
    /// by [`step_adjoint_cell`]).
    ///
    /// # Panics
    /// If the range is not inside or `u` and `g` differ in length.
    pub fn step_adjoint_overwrite_cells(cfg: &Burgers1d, u: &[f64], g: &[f64], du: &mut [f64], s: usize) => adjoint_cells_overwrite
}

#[inline(always)]
fn adjoint_cells_overwrite(cfg: &Burgers1d, u: &[f64], g: &[f64], du: &mut [f64], s: usize) {
    adjoint_cells::<false>(cfg, u, g, du, s)
}

/// One cell of the adjoint, `((∂step/∂u)ᵀ·g)[j]`, any `j < n` (periodic).
pub fn step_adjoint_cell(cfg: &Burgers1d, u: &[f64], g: &[f64], j: usize) -> f64 {
    let n = cfg.n;
    let (a, b) = cfg.coefficients();
    let m = |k: isize| ((j as isize + k).rem_euclid(n as isize)) as usize;
    cell_adjoint(u[m(-1)], u[j], u[m(1)], g[m(-1)], g[j], g[m(1)], a, b)
}

/// Tangent-linear model of [`step`]: `out = (∂step/∂u)·t` at the state `u`
/// (overwrites `out`).
///
/// # Panics
/// If the slices do not all have `cfg.n ≥ 3` elements.
pub fn step_tangent(cfg: &Burgers1d, u: &[f64], t: &[f64], out: &mut [f64]) {
    let n = cfg.n;
    assert!(n >= 3 && u.len() == n && t.len() == n && out.len() == n, "burgers tangent: need n ≥ 3 and matching lengths");
    let (a, b) = cfg.coefficients();
    for i in 0..n {
        let (il, ir) = ((i + n - 1) % n, (i + 1) % n);
        let (l, c, r) = (u[il], u[i], u[ir]);
        let (dl, dc, dr) = if c > 0.0 { (a + b * c, 1.0 - 2.0 * a - b * (2.0 * c - l), a) } else { (a, 1.0 - 2.0 * a - b * (r - 2.0 * c), a - b * c) };
        out[i] = dl * t[il] + dc * t[i] + dr * t[ir];
    }
}

/// Distance to the nearest upwind switch along `d`: the largest `s` such
/// that no `u[i] + σ·d[i]`, `|σ| ≤ s`, changes sign (`∞` when `d = 0`).
pub fn smooth_radius<R: Real>(u: &[R], d: &[R]) -> f64 {
    u.iter().zip(d).filter(|(_, d)| !d.is_zero()).map(|(u, d)| (u.as_f64() / d.as_f64()).abs()).fold(f64::INFINITY, f64::min)
}

/// Initial state of P1: `u0_i = sin(x_i) + 0.5·sin(2·x_i + 0.3)`.
pub fn p1_initial(cfg: &Burgers1d) -> Vec<f64> {
    cfg.grid().iter().map(|&x| x.sin() + 0.5 * (2.0 * x + 0.3).sin()).collect()
}

/// Target of P1: `u*_i = 0.8·sin(x_i − 0.4)`.
pub fn p1_target(cfg: &Burgers1d) -> Vec<f64> {
    cfg.grid().iter().map(|&x| 0.8 * (x - 0.4).sin()).collect()
}

/// P1 loss `L = 0.5·dx·Σ (u_i − u*_i)²`; writes `∂L/∂u = dx·(u − u*)` into
/// `grad` (overwrites).
pub fn p1_loss(cfg: &Burgers1d, u: &[f64], target: &[f64], grad: &mut [f64]) -> f64 {
    let mut sum = 0.0;
    for ((g, &ui), &ti) in grad.iter_mut().zip(u).zip(target) {
        let d = ui - ti;
        sum += d * d;
        *g = cfg.dx * d;
    }
    0.5 * cfg.dx * sum
}

/// Reference values of one P1 size (float64, from `docs/benchmarks.md`).
#[derive(Clone, Copy, Debug)]
pub struct P1Reference {
    /// Size name (S, M, L).
    pub name: char,
    /// Cells.
    pub n: usize,
    /// Steps.
    pub steps: usize,
    /// Loss.
    pub loss: f64,
    /// ‖∇L‖₂.
    pub grad_l2: f64,
    /// ∂L/∂u0 at index 0.
    pub grad_0: f64,
    /// ∂L/∂u0 at index N/2.
    pub grad_n2: f64,
}

/// The three P1 sizes with their reference values.
pub const P1_SIZES: [P1Reference; 3] = [
    P1Reference { name: 'S', n: 256, steps: 256, loss: 0.5368372669763, grad_l2: 0.18125045729660, grad_0: 6.633665977490e-3, grad_n2: -1.2198946630625e-2 },
    P1Reference { name: 'M', n: 2048, steps: 2048, loss: 0.5078725528708, grad_l2: 0.05414400159445, grad_0: 1.237753013381e-3, grad_n2: -3.574446469229e-4 },
    P1Reference { name: 'L', n: 16384, steps: 1000, loss: 0.6520170921227, grad_l2: 0.02234454159575, grad_0: 1.759639889846e-4, grad_n2: -6.266553176260e-5 },
];

/// Advection schemes of the operator-split Burgers step ([`advect_line`]),
/// for accuracy studies beside P1's fused scheme.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Advection1d {
    /// First-order upwind differences (P1's advection).
    Upwind,
    /// One backward trace along `u`, linear interpolation (first order).
    SemiLagrangian,
    /// A backward trace, a forward trace from its result, half the
    /// difference as a correction (second order on smooth solutions).
    MacCormack,
}

/// Linear interpolation of the periodic samples `f` at position `r` (in
/// cells).
#[inline(always)]
fn interp_periodic(f: &[f64], r: f64) -> f64 {
    let n = f.len();
    let nf = n as f64;
    let r = r - nf * (r / nf).floor();
    let k0 = (r as usize).min(n - 1);
    let k1 = if k0 + 1 == n { 0 } else { k0 + 1 };
    let w = r - k0 as f64;
    f[k0] + w * (f[k1] - f[k0])
}

/// Self-advection `u_t + u·u_x = 0` of a periodic line over one step, with
/// `c = dt/dx`: writes `out` (overwrites). `scratch` holds `u.len()` values
/// (MacCormack only; may be empty otherwise).
///
/// # Panics
/// If `u.len() < 3`, `out` has another length, or MacCormack's scratch is
/// short.
pub fn advect_line(scheme: Advection1d, c: f64, u: &[f64], out: &mut [f64], scratch: &mut [f64]) {
    let n = u.len();
    assert!(n >= 3 && out.len() == n, "advect_line: need n ≥ 3 and matching lengths");
    match scheme {
        Advection1d::Upwind => {
            for i in 0..n {
                let (l, r) = (u[(i + n - 1) % n], u[(i + 1) % n]);
                out[i] = cell(l, u[i], r, 0.0, c);
            }
        }
        Advection1d::SemiLagrangian => {
            for i in 0..n {
                out[i] = interp_periodic(u, i as f64 - c * u[i]);
            }
        }
        Advection1d::MacCormack => {
            assert!(scratch.len() >= n, "advect_line: MacCormack needs n scratch values");
            let hat = &mut scratch[..n];
            for i in 0..n {
                hat[i] = interp_periodic(u, i as f64 - c * u[i]);
            }
            for i in 0..n {
                let tilde = interp_periodic(hat, i as f64 + c * u[i]);
                out[i] = hat[i] + 0.5 * (u[i] - tilde);
            }
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn state(n: usize) -> Vec<f64> {
        (0..n).map(|i| (0.7 * i as f64).sin() + 0.3 * (1.9 * i as f64).cos()).collect()
    }

    /// The step is the upwind cell formula at every cell, the ends wrapped.
    #[test]
    fn the_step_is_the_cell_formula_with_periodic_ends() {
        let cfg = Burgers1d::p1(16);
        let u = state(16);
        let mut out = vec![0.0; 16];
        step(&cfg, &u, &mut out);
        let (a, b) = cfg.coefficients();
        for i in 0..16 {
            let (l, r) = (u[(i + 15) % 16], u[(i + 1) % 16]);
            let c = u[i];
            let up = if c > 0.0 { c - l } else { r - c };
            assert_eq!(out[i], c + a * ((r - c) - (c - l)) - b * c * up, "cell {i}");
        }
    }

    /// The tangent matches central differences of the step (away from
    /// upwind switches), and the adjoint is its transpose: `⟨g, J·t⟩ =
    /// ⟨Jᵀ·g, t⟩`.
    #[test]
    fn tangent_and_adjoint_are_the_steps_derivative_and_its_transpose() {
        let cfg = Burgers1d::p1(24);
        let u = state(24);
        let t: Vec<f64> = (0..24).map(|i| (0.31 * i as f64).cos()).collect();
        let g: Vec<f64> = (0..24).map(|i| (0.53 * i as f64 + 0.2).sin()).collect();
        let mut jt = vec![0.0; 24];
        step_tangent(&cfg, &u, &t, &mut jt);
        let h = 1e-7 * smooth_radius(&u, &t).min(1.0);
        let (mut plus, mut minus) = (vec![0.0; 24], vec![0.0; 24]);
        let shifted = |s: f64| u.iter().zip(&t).map(|(a, b)| a + s * b).collect::<Vec<f64>>();
        step(&cfg, &shifted(h), &mut plus);
        step(&cfg, &shifted(-h), &mut minus);
        for i in 0..24 {
            let fd = (plus[i] - minus[i]) / (2.0 * h);
            assert!((fd - jt[i]).abs() < 1e-6 * (1.0 + jt[i].abs()), "cell {i}: {fd} vs {}", jt[i]);
        }
        let gjt: f64 = g.iter().zip(&jt).map(|(a, b)| a * b).sum();
        let jtg_t: f64 = (0..24).map(|j| step_adjoint_cell(&cfg, &u, &g, j) * t[j]).sum();
        assert!((gjt - jtg_t).abs() < 1e-13 * gjt.abs().max(1.0), "{gjt} vs {jtg_t}");
    }
}
