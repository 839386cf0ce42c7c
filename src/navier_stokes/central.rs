//! [`CentralNavierStokes`]: incompressible Navier–Stokes on a box periodic
//! on every axis by central differences in space and a three-stage
//! Runge–Kutta step in time, in 2D and 3D: a smooth map (no interpolation,
//! no limiter, so no kinks for finite differences to straddle) whose
//! kinetic energy only the viscosity and the time step's own damping
//! remove — stable at any horizon where the traced schemes without a
//! limiter are not (docs/navier-stokes.md).
//!
//! One sub-step of `s` from a divergence-free `u` is Shu and Osher's
//! strong-stability-preserving RK3 with the projection `P` after every
//! stage (`L` the right-hand side [`MomentumRhs`]):
//!
//! ```text
//! u₁ = P(u + s·L(u))
//! u₂ = P(¾·u + ¼·(u₁ + s·L(u₁)))
//! u' = P(⅓·u + ⅔·(u₂ + s·L(u₂)))
//! ```
//!
//! `L`'s derivatives come from Enzyme; the projection (FFT) is symmetric,
//! its own adjoint; the combinations are written out.

use std::cell::Cell;

use diffsim_solvers::mac::periodic::Periodic;
use diffsim_solvers::smoke::{MacGrid, Preconditioner};

use super::MAX_SUBSTEPS;
use crate::fluids::Project;
use crate::op::{Forward, Jvp, OpError, OpMessage, Operator, Vjp, validate_forward, validate_jvp, validate_vjp};

/// The momentum equation's right-hand side `−∇·(u⊗u) + ν·∇²u` on a
/// periodic box ([`diffsim_solvers::mac::central::momentum_rhs`]): `x` the
/// packed face velocity, `p = [ν]`. Derivatives by Enzyme.
#[derive(Clone, Copy, Debug)]
pub struct MomentumRhs<const D: usize> {
    /// Cells per axis.
    pub n: [usize; D],
    /// Cell size.
    pub h: f64,
}

impl<const D: usize> Operator for MomentumRhs<D> {
    fn n_in(&self) -> usize {
        MacGrid::new(self.n).n_vel()
    }
    fn n_out(&self) -> usize {
        self.n_in()
    }
    fn n_params(&self) -> usize {
        1
    }
}

fn momentum_rhs<const D: usize>(op: &MomentumRhs<D>, x: &[f64], p: &[f64], y: &mut [f64]) {
    diffsim_solvers::mac::central::momentum_rhs(&op.n, op.h, p[0], x, y);
}

crate::differentiable!(MomentumRhs<2> => momentum_rhs::<2>);
crate::differentiable!(MomentumRhs<3> => momentum_rhs::<3>);

/// Largest `s·Σ_a max|u_a|/h` of a sub-step: the RK3 step is stable for
/// central advection up to `√3` on the imaginary axis; a margin.
pub const CENTRAL_COURANT_LIMIT: f64 = 1.5;

/// Largest `4D·ν·s/h²` (the Laplacian's largest eigenvalue times `s`) of a
/// sub-step: the RK3 step reaches −2.51 on the real axis; a margin.
pub const CENTRAL_VISCOUS_LIMIT: f64 = 2.3;

/// The weights of the three stages: stage `i` is `P(a·u + b·(v + s·L(v)))`.
const STAGES: [(f64, f64); 3] = [(0.0, 1.0), (0.75, 0.25), (1.0 / 3.0, 2.0 / 3.0)];

/// One step of incompressible Navier–Stokes on the periodic box of `flow`
/// by central differences and RK3 ([module docs](self)): `x` the packed
/// face velocity (copies included), `p = [ν, dt]`. A call takes `dt` in
/// `k` equal sub-steps, the fewest with `s·Σ_a max|u_a|/h` within
/// [`CENTRAL_COURANT_LIMIT`] and `4D·ν·s/h²` within
/// [`CENTRAL_VISCOUS_LIMIT`], `k` chosen at the start of the call. It
/// refuses, leaving the velocity as it was and saying why ([`Forward::take_error`]): `ν` or `dt`
/// negative or not finite ([`OpError::Input`]), a velocity not finite or
/// needing more than [`MAX_SUBSTEPS`] sub-steps ([`OpError::Unstable`]).
#[derive(Debug)]
pub struct CentralNavierStokes<const D: usize> {
    flow: Periodic<D>,
    rhs: MomentumRhs<D>,
    projection: Project<D>,
    error: Cell<Option<OpError>>,
}

impl<const D: usize> CentralNavierStokes<D> {
    /// The step on the box of `flow` (its cells and cell size; its scheme
    /// and viscosity unused).
    ///
    /// # Panics
    /// If an axis has fewer than 2 cells or the cell size is not positive
    /// and finite.
    pub fn new(flow: Periodic<D>) -> Self {
        assert!(flow.grid.min_cells() >= 2, "CentralNavierStokes: every axis needs at least 2 cells");
        assert!(flow.h.is_finite() && flow.h > 0.0, "CentralNavierStokes: the cell size must be positive, got {}", flow.h);
        let projection = Project::new(flow.grid, 1e-10, 1000, Preconditioner::Multigrid);
        Self { flow, rhs: MomentumRhs { n: flow.grid.n, h: flow.h }, projection, error: Cell::new(None) }
    }

    /// The box.
    pub fn flow(&self) -> &Periodic<D> {
        &self.flow
    }

    /// The sub-steps of a call at `(x, p)`, or the error that refuses it.
    fn substeps(&self, x: &[f64], p: &[f64]) -> Result<usize, OpError> {
        if !(p[0].is_finite() && p[0] >= 0.0) {
            return Err(OpError::Input(OpMessage::new(&format!("CentralNavierStokes: viscosity p[0] = {} not finite, ≥ 0", p[0]))));
        }
        if !(p[1].is_finite() && p[1] >= 0.0) {
            return Err(OpError::Input(OpMessage::new(&format!("CentralNavierStokes: time step p[1] = {} not finite, ≥ 0", p[1]))));
        }
        let grid = &self.flow.grid;
        let speeds: f64 = (0..D).map(|a| x[grid.face_range(a)].iter().fold(0.0f64, |m, v| m.max(v.abs()))).sum();
        let h = self.flow.h;
        let (courant, viscous) = (speeds * p[1] / h, 4.0 * D as f64 * p[0] * p[1] / (h * h));
        // Each limit on its own suffices: for a mode of wavenumber θ the
        // step's eigenvalue is −K·(1 − cos θ)/2 + i·C·sin θ, and with C ≤
        // 1.5 and K ≤ 2.3 every such curve stays where |R| ≤ 1 (R the
        // RK3 amplification; checked on a grid of C, K and θ).
        let k = (courant / CENTRAL_COURANT_LIMIT).max(viscous / CENTRAL_VISCOUS_LIMIT).ceil();
        if k.is_nan() || k > MAX_SUBSTEPS as f64 || x.iter().any(|v| !v.is_finite()) {
            // The number that asked for the sub-steps, against its limit.
            let (value, limit) = if courant.is_nan() || courant / CENTRAL_COURANT_LIMIT >= viscous / CENTRAL_VISCOUS_LIMIT {
                (courant, CENTRAL_COURANT_LIMIT)
            } else {
                (viscous, CENTRAL_VISCOUS_LIMIT)
            };
            return Err(OpError::Unstable { value, limit: limit * MAX_SUBSTEPS as f64 });
        }
        Ok((k as usize).max(1))
    }

    /// Stage `i` from the sub-step's start `u` and the stage's input `v`
    /// with `L(v)` in `l`: `P(a·u + b·(v + s·l))` into `out`.
    fn stage(&self, i: usize, s: f64, u: &[f64], v: &[f64], l: &[f64], out: &mut [f64]) {
        let (a, b) = STAGES[i];
        for (((o, &u), &v), &l) in out.iter_mut().zip(u).zip(v).zip(l) {
            *o = a * u + b * (v + s * l);
        }
        self.projection.apply_velocity(out);
    }

    /// One sub-step of `s` from `u` into `out`; each stage's input `vᵢ`
    /// (`v₀ = u`) and right-hand side `L(vᵢ)` into `stages` when given (for
    /// the adjoint).
    fn substep(&self, nu: f64, s: f64, u: &[f64], out: &mut [f64], mut stages: Option<&mut Vec<(Vec<f64>, Vec<f64>)>>)
    where
        MomentumRhs<D>: Forward,
    {
        let n = u.len();
        let (mut v, mut l) = (u.to_vec(), vec![0.0; n]);
        for i in 0..3 {
            self.rhs.forward(&v, &[nu], &mut l);
            self.stage(i, s, u, &v, &l, out);
            match stages.as_deref_mut() {
                Some(stages) => stages.push((std::mem::replace(&mut v, out.to_vec()), l.clone())),
                None => v.copy_from_slice(out),
            }
        }
    }
}

impl<const D: usize> Operator for CentralNavierStokes<D> {
    fn n_in(&self) -> usize {
        self.flow.n_vel()
    }
    fn n_out(&self) -> usize {
        self.flow.n_vel()
    }
    fn n_params(&self) -> usize {
        2
    }
}

impl<const D: usize> Forward for CentralNavierStokes<D>
where
    MomentumRhs<D>: Forward,
{
    fn forward(&self, x: &[f64], p: &[f64], y: &mut [f64]) {
        validate_forward(self, "CentralNavierStokes", x, p, y);
        let Some(k) = super::substeps_or_refuse(self.substeps(x, p), x, y, &self.error) else { return };
        let s = p[1] / k as f64;
        let mut cur = x.to_vec();
        for _ in 0..k {
            self.substep(p[0], s, &cur, y, None);
            cur.copy_from_slice(y);
        }
    }

    fn take_error(&self) -> Option<OpError> {
        self.error.take().or(self.projection.take_error())
    }
}

impl<const D: usize> Vjp for CentralNavierStokes<D>
where
    MomentumRhs<D>: Forward + Vjp,
{
    fn vjp(&self, x: &[f64], p: &[f64], dy: &mut [f64], dx: &mut [f64], dp: &mut [f64]) {
        validate_vjp(self, "CentralNavierStokes", x, p, dy, dx, dp);
        let Ok(k) = self.substeps(x, p) else { return super::refused_vjp(dy, dx) };
        let (nu, s, n) = (p[0], p[1] / k as f64, x.len());
        // Every stage's input and right-hand side, sub-step after sub-step.
        let mut substeps: Vec<Vec<(Vec<f64>, Vec<f64>)>> = Vec::with_capacity(k);
        let (mut cur, mut next) = (x.to_vec(), vec![0.0; n]);
        for _ in 0..k {
            let mut stages = Vec::with_capacity(3);
            self.substep(nu, s, &cur, &mut next, Some(&mut stages));
            substeps.push(stages);
            std::mem::swap(&mut cur, &mut next);
        }
        let mut g = dy.to_vec();
        dy.fill(0.0);
        let (mut g_nu, mut g_s) = (0.0, 0.0);
        for stages in substeps.iter().rev() {
            // `g` is the adjoint of the sub-step's result; `gu` collects the
            // adjoint of its start `u = v₀`.
            let mut gu = vec![0.0; n];
            for i in (0..3).rev() {
                let (a, b) = STAGES[i];
                self.projection.apply_adjoint_velocity(&mut g);
                // out = a·u + b·v + b·s·L(v)
                let (v, l) = &stages[i];
                g_s += b * g.iter().zip(l).map(|(g, l)| g * l).sum::<f64>();
                let mut gl: Vec<f64> = g.iter().map(|g| b * s * g).collect();
                let mut gv: Vec<f64> = g.iter().map(|g| b * g).collect();
                let mut gnu = [0.0];
                self.rhs.vjp(v, &[nu], &mut gl, &mut gv, &mut gnu);
                g_nu += gnu[0];
                for (gu, g) in gu.iter_mut().zip(&g) {
                    *gu += a * g;
                }
                // The stage's input is the previous stage's output (stage 0's is u).
                if i == 0 {
                    for (gu, gv) in gu.iter_mut().zip(&gv) {
                        *gu += gv;
                    }
                } else {
                    g = gv;
                }
            }
            g = gu;
        }
        dp[0] += g_nu;
        dp[1] += g_s / k as f64;
        for (d, g) in dx.iter_mut().zip(&g) {
            *d += g;
        }
    }
}

impl<const D: usize> Jvp for CentralNavierStokes<D>
where
    MomentumRhs<D>: Forward + Jvp,
{
    fn jvp(&self, x: &[f64], p: &[f64], tx: &[f64], tp: &[f64], y: &mut [f64], ty: &mut [f64]) {
        validate_jvp(self, "CentralNavierStokes", x, p, tx, tp, y, ty);
        let Ok(k) = self.substeps(x, p) else { return super::refused_jvp(x, tx, y, ty) };
        let (nu, s, ts, n) = (p[0], p[1] / k as f64, tp[1] / k as f64, x.len());
        let (mut u, mut tu) = (x.to_vec(), tx.to_vec());
        let (mut l, mut tl) = (vec![0.0; n], vec![0.0; n]);
        for _ in 0..k {
            let (mut v, mut tv) = (u.clone(), tu.clone());
            for (i, &(a, b)) in STAGES.iter().enumerate() {
                self.rhs.jvp(&v, &[nu], &tv, &[tp[0]], &mut l, &mut tl);
                for j in 0..n {
                    y[j] = a * u[j] + b * (v[j] + s * l[j]);
                    ty[j] = a * tu[j] + b * (tv[j] + s * tl[j] + ts * l[j]);
                }
                self.projection.apply_velocity(y);
                self.projection.apply_velocity(ty);
                if i < 2 {
                    v.copy_from_slice(y);
                    tv.copy_from_slice(ty);
                }
            }
            u.copy_from_slice(y);
            tu.copy_from_slice(ty);
        }
    }
}
