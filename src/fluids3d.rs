//! 3D fluid operators beyond P4's step, on P4's grid conventions
//! ([`diffsim_solvers::smoke3d`]): buoyancy along any axis, inflow regions
//! and a general force, derivatives by Enzyme (diffusion is
//! [`crate::fluids::Diffuse::in_box_3d`], on the lattices shared with 2D). The advection
//! ([`crate::problems::smoke3d::SmokeAdvect3`], with the hand adjoint beside
//! it) and the projection with obstacles
//! ([`crate::problems::smoke3d::Project3`]) are P4's operators.

use diffsim_solvers::smoke::MacGrid;
use diffsim_solvers::smoke::Scheme;
use diffsim_solvers::smoke3d;

/// Buoyancy over a time step `dt` along `axis` (0 x, 1 y, 2 z) with the
/// coefficient as the parameter `p = [b]`: the component of `axis` on its
/// interior faces gains `dt·b·(smoke averaged to the face)`
/// ([`smoke3d::apply_buoyancy3`]). Derivatives by Enzyme, with respect to
/// the state and `b`.
#[derive(Clone, Copy, Debug)]
pub struct Buoyancy3 {
    /// The grid.
    pub cfg: MacGrid<3>,
    /// Time step.
    pub dt: f64,
    /// The axis the force acts along.
    pub axis: usize,
}

crate::fluids::state_sizes!(Buoyancy3, |_op| 1);

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
    pub cfg: MacGrid<3>,
    /// Cells `[i0, i1, j0, j1, k0, k1]`, half-open ranges.
    pub region: [usize; 6],
}

crate::fluids::state_sizes!(Inflow3, |_op| 4);

fn inflow3(op: &Inflow3, x: &[f64], p: &[f64], y: &mut [f64]) {
    smoke3d::apply_inflow3(&op.cfg, op.region, x, p, y)
}

crate::differentiable!(Inflow3 => inflow3);

/// An external force over a time step `dt`, given per velocity face as the
/// parameters (`p`: [`MacGrid<3>::n_vel`] values, the velocity's layout):
/// `vel += dt·p` on the interior faces ([`smoke3d::apply_force3`]).
/// Derivatives by Enzyme, with respect to the state and the force.
#[derive(Clone, Copy, Debug)]
pub struct Force3 {
    /// The grid.
    pub cfg: MacGrid<3>,
    /// Time step.
    pub dt: f64,
}

crate::fluids::state_sizes!(Force3, |op| op.cfg.n_vel());

fn force3(op: &Force3, x: &[f64], p: &[f64], y: &mut [f64]) {
    smoke3d::apply_force3(&op.cfg, op.dt, x, p, y)
}

crate::differentiable!(Force3 => force3);

/// Advection of the smoke and/or the velocity of the closed 3D box over
/// `cfg.dt` by `scheme` (semi-Lagrangian or MacCormack, with or without
/// limiter; [`smoke3d::advect3`]), the walls closed after. Derivatives by
/// Enzyme; the sampling kinks and the limiter's switches are declared
/// through [`crate::op::Forward::smooth_radius`]. P4's own step is
/// [`crate::problems::smoke3d::SmokeAdvect3`] (both fields, with buoyancy,
/// parallel, with a hand adjoint beside it).
#[derive(Clone, Copy, Debug)]
pub struct Advect3 {
    /// The grid (its `dt` is the time step).
    pub cfg: MacGrid<3>,
    /// The scheme.
    pub scheme: Scheme,
    /// Whether the smoke is advected.
    pub smoke: bool,
    /// Whether the velocity is advected.
    pub velocity: bool,
}

crate::fluids::state_sizes!(Advect3);

fn advect3(op: &Advect3, x: &[f64], _p: &[f64], y: &mut [f64], scratch: &mut [f64]) {
    smoke3d::advect3(&op.cfg, op.scheme, op.smoke, op.velocity, x, y, scratch)
}

/// MacCormack's intermediate fields.
fn advect3_scratch(op: &Advect3) -> usize {
    smoke3d::advect3_scratch_len(&op.cfg, op.scheme)
}

/// Where the trilinear samples stay between lattice planes, and with
/// MacCormack's limiter also where its clamp switches.
fn advect3_radius(op: &Advect3, x: &[f64], _p: &[f64], dx: &[f64], _dp: &[f64]) -> f64 {
    let sampling = smoke3d::advect3_radius(&op.cfg, op.scheme, op.smoke, op.velocity, x, dx);
    match op.scheme {
        Scheme::MacCormack { limiter: true } => sampling.min(smoke3d::limiter3_radius(&op.cfg, op.smoke, op.velocity, x, dx)),
        _ => sampling,
    }
}

crate::differentiable!(Advect3 => advect3, smooth_radius = advect3_radius, scratch = advect3_scratch);

/// First-order upwind advection of the smoke of the closed 3D box over
/// `cfg.dt`, in flux form ([`smoke3d::advect_upwind3`]; the velocity passes
/// through). Derivatives by Enzyme; the upwind switch is declared through
/// [`crate::op::Forward::smooth_radius`].
#[derive(Clone, Copy, Debug)]
pub struct AdvectUpwind3 {
    /// The grid (its `dt` is the time step).
    pub cfg: MacGrid<3>,
}

crate::fluids::state_sizes!(AdvectUpwind3);

fn advect_upwind3(op: &AdvectUpwind3, x: &[f64], _p: &[f64], y: &mut [f64]) {
    smoke3d::advect_upwind3(&op.cfg, x, y)
}

fn upwind3_radius(op: &AdvectUpwind3, x: &[f64], _p: &[f64], dx: &[f64], _dp: &[f64]) -> f64 {
    smoke3d::upwind3_radius(&op.cfg, x, dx)
}

crate::differentiable!(AdvectUpwind3 => advect_upwind3, smooth_radius = upwind3_radius);
