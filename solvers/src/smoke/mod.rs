//! Incompressible smoke on a MAC grid, written once for 2D and 3D
//! ([`MacGrid<D>`]): semi-Lagrangian, MacCormack and upwind advection of a
//! cell-centred scalar and of a staggered (MAC) velocity, buoyancy, forces,
//! inflow regions, obstacles, the boundary conditions of
//! [`crate::boundary`], and a pressure projection solved by preconditioned
//! conjugate gradients. Benchmark P2 `smoke2d` is the closed square with
//! semi-Lagrangian advection, P4 `smoke3d` the closed cube.
//!
//! Conventions (those of P2 and P4 in `docs/benchmarks.md`): unit cells, x
//! to the right, y up, z towards the viewer; every array x fastest and its
//! slowest axis last. In 2D:
//! - smoke `s[j][i]` at the cell centre `(i+½, j+½)`: `Nx·Ny` values, index `j·Nx + i`;
//! - `u[j][i]` at the x-face `(i, j+½)`, `i = 0..=Nx`: `Ny·(Nx+1)` values, index `j·(Nx+1) + i`;
//! - `v[j][i]` at the y-face `(i+½, j)`, `j = 0..=Ny`: `(Ny+1)·Nx` values, index `j·Nx + i`;
//!
//! and in 3D the same with a third index `k` slowest (`w` on the z-faces,
//! `k = 0..=Nz`).
//!
//! On a periodic axis face `Nx` (`Ny`, `Nz`) is a copy of face `0`:
//! operators never read it and write it as the copy, so the state keeps one
//! layout whatever the boundary.
//!
//! The step is split where the gradient is split: [`advect_buoyancy`] (explicit,
//! differentiated by Enzyme in diffsim) and [`project`] (a linear solve, whose
//! adjoint is the solve with the transposed — here the same — matrix:
//! [`project_adjoint`]).
//!
//! The lattices, their bilinear and trilinear sampling and the MAC grid's
//! index rules are [`crate::mac`]'s. The module in files: `grid` the grid
//! ([`MacGrid<D>`]); `advect` the advection schemes and their adjoints,
//! `forces` buoyancy, external forces and inflow, `walls` the velocity
//! boundary conditions, `obstacles` solid cells, `pressure` the divergence,
//! the gradient and the projection, `solver` the pressure matrix and its
//! conjugate-gradient solve ([`PressureSolver<D>`]), `benchmarks` P2's and
//! P4's set-up and reference values.

use crate::boundary::{Side, for_each_face};
use crate::mac::{At, Mac, Wraps, each_axis, on_axis};

/// Calls `$body` with `$mac` bound to the [`Mac`] of the configuration:
/// [`crate::mac::Bounded`] when no axis wraps (P2's closed box: its loops carry no
/// test), else with the wrapping axes known at run time.
macro_rules! with_mac {
    ($cfg:expr, $mac:ident => $body:expr) => {
        if $cfg.boundary.wraps().contains(&true) {
            let $mac = $cfg.mac();
            $body
        } else {
            let $mac = $cfg.bounded();
            $body
        }
    };
}

/// Element-wise copy. An explicit loop: `copy_from_slice` into part of a
/// buffer Enzyme differentiates has given silently wrong gradients
/// (ENZYME.md).
#[inline(always)]
pub(crate) fn copy(from: &[f64], to: &mut [f64]) {
    for (o, &a) in to.iter_mut().zip(from) {
        *o = a;
    }
}

/// Whether a face lets fluid through: the product of the fluid indicators
/// of the cells beside it (1 without obstacles).
#[inline]
fn open(fluid: Option<&[f64]>, f: &crate::boundary::Face) -> f64 {
    fluid.map_or(1.0, |w| f.lower.map_or(1.0, |c| w[c]) * f.upper.map_or(1.0, |c| w[c]))
}

mod advect;
mod benchmarks;
mod forces;
mod grid;
mod obstacles;
mod pressure;
mod solver;
mod walls;

pub use advect::*;
pub use benchmarks::*;
pub use forces::*;
pub use grid::*;
pub use obstacles::*;
pub use pressure::*;
pub use solver::*;
pub use walls::*;
