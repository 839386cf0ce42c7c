//! Steady flows around bodies by Newton's method on the discrete steady
//! equations of the cut-cell scheme, and the adjoint of a force with
//! respect to the bodies' shape parameters.
//!
//! The unknowns are the packed velocity `x` and the kinematic pressure `P`
//! per cell. The equations are exactly those a time march
//! ([`super::Stepper::with_bodies`]) reaches at its steady state, whatever
//! the step:
//!
//! - a face the boundary sets: `x_f = x_f^bc`; a face inside a body: `x_f = 0`;
//! - a fluid face: `F_f(x∘fluid) − (ν/h²)·k_f·x_f − (P_up − P_lo)/h = 0`
//!   ([`super::momentum`], `k` = [`super::Cut::wall`], `P = 0` beyond an
//!   outflow side);
//! - a cell with an open face: `Σ ± a_f·x_f / h = 0` (aperture-weighted
//!   divergence); a cell with none: `P_c = 0`.
//!
//! Newton's Jacobian is assembled exactly: `F` is quadratic in `x`, so its
//! directional derivative is the central difference `(F(x + δ) − F(x − δ))/2`
//! with no truncation error, and nine colours per component (faces `(i, j)`
//! grouped by `(i mod 3, j mod 3)`) recover every column. Each system is
//! solved by faer's sparse LU. The force's gradient is the implicit
//! (fixed-point) adjoint of the converged state: one solve with the
//! transposed Jacobian, `λ = J⁻ᵀ·∂L/∂z`, then `dL/ds = −λᵀ·∂R/∂s` with
//! `∂R/∂s` from the cut's sensitivities ([`super::CutSensitivity`]).

use super::momentum::{Pads, advanced_faces, momentum};
use super::{Convection, Cut, CutSensitivity, Flow2d, FlowError, Shape};
use crate::boundary::Side;
use crate::linalg::SparseLu;
use crate::smoke::enforce_boundary;

/// Sparse matrix entries `(row, column, value)`.
type Entries = Vec<(usize, usize, f64)>;

/// What a velocity's equation is.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
enum Row {
    /// Set by the boundary.
    Fixed,
    /// Inside a body.
    Solid,
    /// Momentum balance.
    Momentum,
}

/// When [`SteadyFlow::solve`] stops.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct NewtonParams {
    /// Stop when the largest residual falls below this.
    pub tolerance: f64,
    /// Give up after this many Newton steps.
    pub max_steps: usize,
}

/// The former name of [`NewtonParams`].
#[deprecated(note = "renamed NewtonParams")]
pub type NewtonOptions = NewtonParams;

impl Default for NewtonParams {
    fn default() -> Self {
        Self { tolerance: 1e-10, max_steps: 40 }
    }
}

/// A converged steady state and the factored Jacobian there (for adjoints
/// and tangents).
#[derive(Debug)]
pub struct SteadyState {
    /// Packed velocity.
    pub x: Vec<f64>,
    /// Kinematic pressure per cell (0 in cells with no open face).
    pub pressure: Vec<f64>,
    /// Newton steps taken.
    pub steps: usize,
    /// The last largest residual.
    pub residual: f64,
    /// The F-Jacobian entries `(row, column, value)` at the state (rows of
    /// every advanced face, columns masked by the fluid).
    jf: Entries,
    lu: SparseLu,
}

/// The steady equations of one flow around fixed bodies.
#[derive(Debug)]
pub struct SteadyFlow {
    cfg: Flow2d,
    cut: Cut,
    sens: CutSensitivity,
    rows: Vec<Row>,
    open: Vec<bool>,
    /// One open cell per group of open cells that no outflow side reaches
    /// (fluid pockets the grid cuts off): its pressure is pinned to 0 in
    /// place of its continuity equation, which the others imply.
    pinned: Vec<bool>,
    bc: Vec<f64>,
}

/// The open cells whose pressure is pinned: the first cell of every group
/// of open cells connected through fluid faces that reaches no outflow
/// side (its pressure is defined up to a constant).
fn pinned_cells(cfg: &Flow2d, rows: &[Row], open: &[bool]) -> Vec<bool> {
    let (nx, ny) = (cfg.nx, cfg.ny);
    let n_u = cfg.n_u();
    let cells = nx * ny;
    // Neighbours through momentum faces; "outflow" when such a face lies on a side.
    let mut label = vec![usize::MAX; cells];
    let mut pinned = vec![false; cells];
    for seed in 0..cells {
        if !open[seed] || label[seed] != usize::MAX {
            continue;
        }
        let (mut stack, mut anchored) = (vec![seed], false);
        label[seed] = seed;
        while let Some(c) = stack.pop() {
            let (i, j) = (c % nx, c / nx);
            let faces = [
                (j * (nx + 1) + i, (i > 0).then(|| c - 1)),
                (j * (nx + 1) + i + 1, (i + 1 < nx).then(|| c + 1)),
                (n_u + j * nx + i, (j > 0).then(|| c - nx)),
                (n_u + (j + 1) * nx + i, (j + 1 < ny).then(|| c + nx)),
            ];
            for (f, other) in faces {
                if rows[f] != Row::Momentum {
                    continue;
                }
                match other {
                    None => anchored = true,
                    Some(m) if open[m] && label[m] == usize::MAX => {
                        label[m] = seed;
                        stack.push(m);
                    }
                    Some(_) => {}
                }
            }
        }
        if !anchored {
            pinned[seed] = true;
        }
    }
    pinned
}

impl SteadyFlow {
    /// The steady problem of `cfg` around `shapes`, each validated first
    /// ([`Shape::validate`]; a malformed one is [`FlowError::Shape`]).
    pub fn new(cfg: Flow2d, shapes: &[Shape]) -> Result<Self, FlowError> {
        cfg.validate()?;
        for shape in shapes {
            shape.validate(&cfg).map_err(FlowError::Shape)?;
        }
        let (cut, sens) = Cut::with_sensitivity(&cfg, shapes);
        let (nx, ny) = (cfg.nx, cfg.ny);
        let n_u = cfg.n_u();
        let b = cfg.boundary;
        let (fu, fv) = (advanced_faces(b.lower(0), b.upper(0), nx), advanced_faces(b.lower(1), b.upper(1), ny));
        let rows: Vec<Row> = (0..cfg.n_vel())
            .map(|k| {
                let advanced = if k < n_u { fu.contains(&(k % (nx + 1))) } else { fv.contains(&((k - n_u) / nx)) };
                if !advanced {
                    Row::Fixed
                } else if cut.fluid[k] == 0.0 {
                    Row::Solid
                } else {
                    Row::Momentum
                }
            })
            .collect();
        // A cell is open when a face the projection moves (interior, or on
        // an outflow side) is open and in the fluid, as in the time march.
        let side = |s: Side| s == Side::Outflow;
        let open: Vec<bool> = (0..nx * ny)
            .map(|c| {
                let (i, j) = (c % nx, c / nx);
                let faces = [
                    (j * (nx + 1) + i, i > 0 || side(b.lower(0)), cut.aperture_u[j * (nx + 1) + i]),
                    (j * (nx + 1) + i + 1, i + 1 < nx || side(b.upper(0)), cut.aperture_u[j * (nx + 1) + i + 1]),
                    (n_u + j * nx + i, j > 0 || side(b.lower(1)), cut.aperture_v[j * nx + i]),
                    (n_u + (j + 1) * nx + i, j + 1 < ny || side(b.upper(1)), cut.aperture_v[(j + 1) * nx + i]),
                ];
                faces.iter().any(|&(f, moved, a)| moved && a > 0.0 && cut.fluid[f] > 0.0)
            })
            .collect();
        let pinned = pinned_cells(&cfg, &rows, &open);
        let mut bc = cfg.rest();
        enforce_boundary(&cfg.grid(), &mut bc);
        Ok(Self { cfg, cut, sens, rows, open, pinned, bc })
    }

    /// The cut of the grid.
    pub fn cut(&self) -> &Cut {
        &self.cut
    }

    /// The configuration.
    pub fn config(&self) -> &Flow2d {
        &self.cfg
    }

    /// Number of unknowns (velocities and pressures).
    pub fn n_unknowns(&self) -> usize {
        self.cfg.n_vel() + self.cfg.nx * self.cfg.ny
    }

    /// The cells below and above face `k` (packed), `None` beyond a side.
    fn cells_of(&self, k: usize) -> (Option<usize>, Option<usize>) {
        let (nx, ny) = (self.cfg.nx, self.cfg.ny);
        let n_u = self.cfg.n_u();
        if k < n_u {
            let (j, i) = (k / (nx + 1), k % (nx + 1));
            ((i > 0).then(|| j * nx + i - 1), (i < nx).then(|| j * nx + i))
        } else {
            let (j, i) = ((k - n_u) / nx, (k - n_u) % nx);
            ((j > 0).then(|| (j - 1) * nx + i), (j < ny).then(|| j * nx + i))
        }
    }

    /// The four faces of cell `c` with the sign of their outward flux.
    fn faces_of(&self, c: usize) -> [(usize, f64); 4] {
        let nx = self.cfg.nx;
        let n_u = self.cfg.n_u();
        let (i, j) = (c % nx, c / nx);
        [(j * (nx + 1) + i, -1.0), (j * (nx + 1) + i + 1, 1.0), (n_u + j * nx + i, -1.0), (n_u + (j + 1) * nx + i, 1.0)]
    }

    /// Whether cell `c`'s equation is its continuity (else `P_c = 0`).
    fn continuity(&self, c: usize) -> bool {
        self.open[c] && !self.pinned[c]
    }

    fn aperture(&self, k: usize) -> f64 {
        let n_u = self.cfg.n_u();
        if k < n_u { self.cut.aperture_u[k] } else { self.cut.aperture_v[k - n_u] }
    }

    /// `F(x∘fluid)` into `out`.
    fn momentum_masked(&self, x: &[f64], pads: &mut Pads, masked: &mut [f64], out: &mut [f64]) {
        for ((m, &v), &w) in masked.iter_mut().zip(x).zip(&self.cut.fluid) {
            *m = v * w;
        }
        momentum(&self.cfg, masked, pads, out);
    }

    /// The residual of the steady equations at `z = [x, P]`.
    pub fn residual(&self, z: &[f64], out: &mut [f64]) {
        let n = self.cfg.n_vel();
        let (x, p) = z.split_at(n);
        let mut pads = Pads::new(&self.cfg);
        let mut masked = vec![0.0; n];
        let (ro, rp) = out.split_at_mut(n);
        self.momentum_masked(x, &mut pads, &mut masked, ro);
        let (h, c) = (self.cfg.h, self.cfg.nu / (self.cfg.h * self.cfg.h));
        for k in 0..n {
            ro[k] = match self.rows[k] {
                Row::Fixed => x[k] - self.bc[k],
                Row::Solid => x[k],
                Row::Momentum => {
                    let (lo, up) = self.cells_of(k);
                    let grad = (up.map_or(0.0, |c| p[c]) - lo.map_or(0.0, |c| p[c])) / h;
                    ro[k] - c * self.cut.wall[k] * x[k] - grad
                }
            };
        }
        for (cell, r) in rp.iter_mut().enumerate() {
            *r = if self.continuity(cell) { self.faces_of(cell).iter().map(|&(f, s)| s * self.aperture(f) * x[f]).sum::<f64>() / h } else { p[cell] };
        }
    }

    /// The F-Jacobian at `x` (masked by the fluid): entries for every
    /// advanced face's row, by colouring (exact: `F` is quadratic).
    fn momentum_jacobian(&self, x: &[f64]) -> Entries {
        let cfg = &self.cfg;
        let (nx, ny) = (cfg.nx, cfg.ny);
        let n = cfg.n_vel();
        let n_u = cfg.n_u();
        let mut pads = Pads::new(cfg);
        let (mut xm, mut plus, mut minus) = (vec![0.0; n], vec![0.0; n], vec![0.0; n]);
        for ((m, &v), &w) in xm.iter_mut().zip(x).zip(&self.cut.fluid) {
            *m = v * w;
        }
        let mut entries = Vec::with_capacity(14 * n);
        let mut shifted = vec![0.0; n];
        let position = |k: usize| if k < n_u { (k % (nx + 1), k / (nx + 1)) } else { ((k - n_u) % nx, (k - n_u) / nx) };
        // How far a row reads its own component (`reach`), and the other
        // component's block: second order reads ±1 and a 2 × 2 block, the
        // fourth-order interpolation ±2 and a 2 × 4 block. Columns of one
        // colour lie `period` apart, so that no row reads two of them.
        let (reach, wide): (isize, bool) = match cfg.convection {
            Convection::Second => (1, false),
            Convection::Fourth => (2, true),
        };
        let period = (2 * reach + 1) as usize;
        let per_component = period * period;
        for colour in 0..2 * per_component {
            let is_u = colour < per_component;
            let (ci, cj) = ((colour % per_component) / period, colour % period);
            let columns: Vec<usize> = (0..n)
                .filter(|&k| {
                    let (i, j) = position(k);
                    (k < n_u) == is_u && i % period == ci && j % period == cj && self.cut.fluid[k] > 0.0
                })
                .collect();
            if columns.is_empty() {
                continue;
            }
            for sign in [1.0, -1.0] {
                shifted.copy_from_slice(&xm);
                for &k in &columns {
                    shifted[k] += sign;
                }
                momentum(cfg, &shifted, &mut pads, if sign > 0.0 { &mut plus } else { &mut minus });
            }
            for &g in &columns {
                let (i, j) = position(g);
                let (i, j) = (i as isize, j as isize);
                // Rows that read column g: same component within ±reach,
                // the other component in its block.
                let mut rows: Vec<usize> = Vec::with_capacity(33);
                let (same_w, same_h, other_w, other_h, other_off) = if is_u { (nx + 1, ny, nx, ny + 1, n_u) } else { (nx, ny + 1, nx + 1, ny, 0) };
                let same_off = if is_u { 0 } else { n_u };
                for dj in -reach..=reach {
                    for di in -reach..=reach {
                        let (a, b) = (i + di, j + dj);
                        if a >= 0 && b >= 0 && (a as usize) < same_w && (b as usize) < same_h {
                            rows.push(same_off + b as usize * same_w + a as usize);
                        }
                    }
                }
                // A v-row (a, b) reads u in columns a, a + 1 and rows
                // b − 1, b (b − 2 … b + 1 when wide); a u-row (a, b) reads v
                // in rows b, b + 1 and columns a − 1, a (a − 2 … a + 1 when
                // wide). So column g is read from these offsets.
                let spread: &[isize] = if wide { &[-1, 0, 1, 2] } else { &[0, 1] };
                let (di_range, dj_range): (&[isize], &[isize]) = if is_u { (&[-1, 0], spread) } else { (spread, &[-1, 0]) };
                for &dj in dj_range {
                    for &di in di_range {
                        let (a, b) = (i + di, j + dj);
                        if a >= 0 && b >= 0 && (a as usize) < other_w && (b as usize) < other_h {
                            rows.push(other_off + b as usize * other_w + a as usize);
                        }
                    }
                }
                for f in rows {
                    let d = 0.5 * (plus[f] - minus[f]);
                    if d != 0.0 && self.rows[f] != Row::Fixed {
                        entries.push((f, g, d));
                    }
                }
            }
        }
        entries
    }

    /// The Jacobian of [`SteadyFlow::residual`] at `z` (given the
    /// F-Jacobian there).
    fn jacobian(&self, jf: &[(usize, usize, f64)]) -> Entries {
        let n = self.cfg.n_vel();
        let (h, c) = (self.cfg.h, self.cfg.nu / (self.cfg.h * self.cfg.h));
        let mut t: Entries = jf.iter().filter(|e| self.rows[e.0] == Row::Momentum).copied().collect();
        for k in 0..n {
            match self.rows[k] {
                Row::Fixed | Row::Solid => t.push((k, k, 1.0)),
                Row::Momentum => {
                    t.push((k, k, -c * self.cut.wall[k]));
                    let (lo, up) = self.cells_of(k);
                    if let Some(u) = up {
                        t.push((k, n + u, -1.0 / h));
                    }
                    if let Some(l) = lo {
                        t.push((k, n + l, 1.0 / h));
                    }
                }
            }
        }
        for cell in 0..self.cfg.nx * self.cfg.ny {
            if self.continuity(cell) {
                for (f, s) in self.faces_of(cell) {
                    let a = self.aperture(f);
                    if a != 0.0 {
                        t.push((n + cell, f, s * a / h));
                    }
                }
            } else {
                t.push((n + cell, n + cell, 1.0));
            }
        }
        t
    }

    fn factor(&self, z: &[f64]) -> Result<(Entries, SparseLu), FlowError> {
        let jf = self.momentum_jacobian(&z[..self.cfg.n_vel()]);
        let lu = SparseLu::new(self.n_unknowns(), &self.jacobian(&jf)).map_err(|_| FlowError::Factor)?;
        Ok((jf, lu))
    }

    /// Newton's method from the velocity `x0` (its boundary values are
    /// set here; the pressure starts at 0), with a backtracking line search
    /// on the largest residual. Not converging within the steps is
    /// [`FlowError::NotSteady`] (its `rate` is the residual).
    pub fn solve(&self, x0: &[f64], opts: &NewtonParams) -> Result<SteadyState, FlowError> {
        let n = self.cfg.n_vel();
        assert_eq!(x0.len(), n, "steady flow: initial velocity length");
        let mut z = vec![0.0; self.n_unknowns()];
        z[..n].copy_from_slice(x0);
        let mut r = vec![0.0; z.len()];
        // NaN-propagating: a NaN residual is not a converged one.
        let norm = crate::cg::max_abs;
        self.residual(&z, &mut r);
        let mut res = norm(&r);
        let mut trial = z.clone();
        for step in 0..=opts.max_steps {
            if !res.is_finite() {
                return Err(FlowError::NotFinite { step });
            }
            if res <= opts.tolerance {
                let (jf, lu) = self.factor(&z)?;
                let pressure = z[n..].to_vec();
                z.truncate(n);
                return Ok(SteadyState { x: z, pressure, steps: step, residual: res, jf, lu });
            }
            if step == opts.max_steps {
                break;
            }
            let (_, lu) = self.factor(&z)?;
            let mut dz: Vec<f64> = r.iter().map(|v| -v).collect();
            lu.solve_in_place(&mut dz);
            let mut alpha = 1.0;
            loop {
                for ((t, &zv), &d) in trial.iter_mut().zip(&z).zip(&dz) {
                    *t = zv + alpha * d;
                }
                self.residual(&trial, &mut r);
                let new = norm(&r);
                if new < res || alpha < 1e-3 {
                    res = new;
                    std::mem::swap(&mut z, &mut trial);
                    break;
                }
                alpha *= 0.5;
            }
        }
        Err(FlowError::NotSteady { steps: opts.max_steps, rate: res, tolerance: opts.tolerance })
    }

    /// The force on whatever lies inside the box of cells `[i0, i1) ×
    /// [j0, j1)` at a steady state (the momentum balance of
    /// [`super::Stepper::force_in_box`]), per unit depth, density 1.
    pub fn force(&self, state: &SteadyState, cells: [usize; 4]) -> [f64; 2] {
        let n = self.cfg.n_vel();
        let mut pads = Pads::new(&self.cfg);
        let (mut masked, mut f) = (vec![0.0; n], vec![0.0; n]);
        self.momentum_masked(&state.x, &mut pads, &mut masked, &mut f);
        let mut out = [0.0; 2];
        for (k, w) in self.box_faces(cells) {
            let (lo, up) = self.cells_of(k);
            let p = &state.pressure;
            let grad = (up.map_or(0.0, |c| p[c]) - lo.map_or(0.0, |c| p[c])) / self.cfg.h;
            out[w] += (f[k] - grad) * self.cfg.h * self.cfg.h;
        }
        out
    }

    /// The faces strictly inside the box with their axis (0: x, 1: y).
    fn box_faces(&self, [i0, i1, j0, j1]: [usize; 4]) -> Vec<(usize, usize)> {
        let nx = self.cfg.nx;
        let n_u = self.cfg.n_u();
        let mut faces = Vec::new();
        for j in j0..j1 {
            for i in i0 + 1..i1 {
                faces.push((j * (nx + 1) + i, 0));
            }
        }
        for j in j0 + 1..j1 {
            for i in i0..i1 {
                faces.push((n_u + j * nx + i, 1));
            }
        }
        faces
    }

    /// `∂L/∂z` for `L = weights · force(cells)`.
    fn force_seed(&self, cells: [usize; 4], weights: [f64; 2]) -> Vec<f64> {
        let n = self.cfg.n_vel();
        let h = self.cfg.h;
        let mut g = vec![0.0; self.n_unknowns()];
        for (k, axis) in self.box_faces(cells) {
            let w = weights[axis];
            // The weight of F_k (mapped to ∂L/∂x through the F-Jacobian by
            // the callers) and the pressure part.
            g[k] += w * h * h;
            let (lo, up) = self.cells_of(k);
            if let Some(u) = up {
                g[n + u] -= w * h;
            }
            if let Some(l) = lo {
                g[n + l] += w * h;
            }
        }
        g
    }

    /// The gradient of `L = weights · force(cells)` with respect to the
    /// shapes' parameters (all shapes' [`Shape::params`] concatenated), by
    /// the adjoint of the steady equations.
    pub fn force_gradient(&self, state: &SteadyState, cells: [usize; 4], weights: [f64; 2]) -> Vec<f64> {
        let n = self.cfg.n_vel();
        let seed = self.force_seed(cells, weights);
        // ∂L/∂x = J_Fᵀ·(seed on the faces) ; ∂L/∂P as in the seed.
        let mut g = vec![0.0; self.n_unknowns()];
        for &(f, col, v) in &state.jf {
            g[col] += v * seed[f];
        }
        g[n..].copy_from_slice(&seed[n..]);
        state.lu.solve_transpose_in_place(&mut g);
        // dL/ds = −λᵀ·∂R/∂s.
        let mut grad = vec![0.0; self.sens.n_params];
        self.add_residual_sensitivity_t(state, &g, -1.0, &mut grad);
        grad
    }

    /// The derivative of `L = weights · force(cells)` along the parameter
    /// direction `ds` by the tangent (forward sensitivity) equations:
    /// `dz = −J⁻¹·∂R/∂s·ds`, independent of the adjoint.
    pub fn force_tangent(&self, state: &SteadyState, cells: [usize; 4], weights: [f64; 2], ds: &[f64]) -> f64 {
        let n = self.cfg.n_vel();
        assert_eq!(ds.len(), self.sens.n_params, "force_tangent: direction length");
        let mut dz = vec![0.0; self.n_unknowns()];
        self.add_residual_sensitivity(state, ds, -1.0, &mut dz);
        state.lu.solve_in_place(&mut dz);
        let seed = self.force_seed(cells, weights);
        // dL = Σ_f seed_f·(J_F·dx)_f + seed_P·dP.
        let mut jdx = vec![0.0; n];
        for &(f, col, v) in &state.jf {
            jdx[f] += v * dz[col];
        }
        (0..n).map(|k| seed[k] * jdx[k]).sum::<f64>() + seed[n..].iter().zip(&dz[n..]).map(|(a, b)| a * b).sum::<f64>()
    }

    /// `out += scale·∂R/∂s·ds`.
    fn add_residual_sensitivity(&self, state: &SteadyState, ds: &[f64], scale: f64, out: &mut [f64]) {
        let (n, h, c) = (self.cfg.n_vel(), self.cfg.h, self.cfg.nu / (self.cfg.h * self.cfg.h));
        let dot = |row: &[f64]| row.iter().zip(ds).map(|(a, b)| a * b).sum::<f64>();
        for (k, row) in &self.sens.wall {
            if self.rows[*k] == Row::Momentum {
                out[*k] += scale * (-c * state.x[*k] * dot(row));
            }
        }
        for (f, row) in &self.sens.aperture {
            let d = dot(row) * state.x[*f] / h;
            let (lo, up) = self.cells_of(*f);
            // Outward flux: + for the cell below (lo), − for the one above.
            if let Some(l) = lo.filter(|&l| self.continuity(l)) {
                out[n + l] += scale * d;
            }
            if let Some(u) = up.filter(|&u| self.continuity(u)) {
                out[n + u] -= scale * d;
            }
        }
    }

    /// `grad += scale·(∂R/∂s)ᵀ·lambda`.
    fn add_residual_sensitivity_t(&self, state: &SteadyState, lambda: &[f64], scale: f64, grad: &mut [f64]) {
        let (n, h, c) = (self.cfg.n_vel(), self.cfg.h, self.cfg.nu / (self.cfg.h * self.cfg.h));
        for (k, row) in &self.sens.wall {
            if self.rows[*k] == Row::Momentum {
                let w = scale * lambda[*k] * (-c * state.x[*k]);
                for (g, d) in grad.iter_mut().zip(row) {
                    *g += w * d;
                }
            }
        }
        for (f, row) in &self.sens.aperture {
            let (lo, up) = self.cells_of(*f);
            let mut w = 0.0;
            if let Some(l) = lo.filter(|&l| self.continuity(l)) {
                w += lambda[n + l];
            }
            if let Some(u) = up.filter(|&u| self.continuity(u)) {
                w -= lambda[n + u];
            }
            let w = scale * w * state.x[*f] / h;
            for (g, d) in grad.iter_mut().zip(row) {
                *g += w * d;
            }
        }
    }
}
