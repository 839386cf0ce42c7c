//! 3D fluid operators beyond P4's step, on P4's grid conventions
//! ([`diffsim_solvers::smoke3d`]): buoyancy along any axis and inflow
//! regions, derivatives by Enzyme. The advection
//! ([`crate::problems::smoke3d::SmokeAdvect3`], with the hand adjoint beside
//! it) and the projection with obstacles
//! ([`crate::problems::smoke3d::Project3`]) are P4's operators.

use diffsim_solvers::smoke3d::{self, Smoke3d};

use crate::op::Operator;

/// Buoyancy over a time step `dt` along `axis` (0 x, 1 y, 2 z) with the
/// coefficient as the parameter `p = [b]`: the component of `axis` on its
/// interior faces gains `dt·b·(smoke averaged to the face)`
/// ([`smoke3d::apply_buoyancy3`]). Derivatives by Enzyme, with respect to
/// the state and `b`.
#[derive(Clone, Copy, Debug)]
pub struct Buoyancy3 {
    /// The grid.
    pub cfg: Smoke3d,
    /// Time step.
    pub dt: f64,
    /// The axis the force acts along.
    pub axis: usize,
}

impl Operator for Buoyancy3 {
    fn n_in(&self) -> usize {
        self.cfg.n_state()
    }
    fn n_out(&self) -> usize {
        self.cfg.n_state()
    }
    fn n_params(&self) -> usize {
        1
    }
}

fn buoyancy3(op: &Buoyancy3, x: &[f64], p: &[f64], y: &mut [f64]) {
    smoke3d::apply_buoyancy3(&op.cfg, op.axis, op.dt * p[0], x, y)
}

crate::differentiable!(Buoyancy3 => buoyancy3);

/// Inflow: in the cells `region = [i0, i1, j0, j1, k0, k1]` (half-open)
/// the smoke is set to `p[0]` and the velocity of the region's faces to
/// `(p[1], p[2], p[3])` every step ([`smoke3d::apply_inflow3`]).
/// Derivatives by Enzyme (with respect to the inflow values too).
#[derive(Clone, Copy, Debug)]
pub struct Inflow3 {
    /// The grid.
    pub cfg: Smoke3d,
    /// Cells `[i0, i1, j0, j1, k0, k1]`, half-open ranges.
    pub region: [usize; 6],
}

impl Operator for Inflow3 {
    fn n_in(&self) -> usize {
        self.cfg.n_state()
    }
    fn n_out(&self) -> usize {
        self.cfg.n_state()
    }
    fn n_params(&self) -> usize {
        4
    }
}

fn inflow3(op: &Inflow3, x: &[f64], p: &[f64], y: &mut [f64]) {
    smoke3d::apply_inflow3(&op.cfg, op.region, x, p, y)
}

crate::differentiable!(Inflow3 => inflow3);
