//! 3D incompressible smoke on a MAC grid: semi-Lagrangian advection of a
//! cell-centred scalar and of a staggered velocity by trilinear sampling,
//! buoyancy, walls, and the pressure projection solved by conjugate
//! gradients with a multigrid preconditioner. Benchmark P4 `smoke3d` is
//! P2 in three dimensions (`docs/benchmarks.md`).
//!
//! Conventions (those of P4): `nx × ny × nz` unit cells, x to the right, y
//! up, z towards the viewer; arrays indexed `[k][j][i]` (z, y, x) and
//! flattened as `(k·ny + j)·nx + i` with the extent of each array's own axes:
//! - smoke `s[k][j][i]` at the cell centre `(i+½, j+½, k+½)`: `nx·ny·nz` values;
//! - `u[k][j][i]` at the x-face `(i, j+½, k+½)`, `i = 0..=nx`: `nz·ny·(nx+1)`;
//! - `v[k][j][i]` at the y-face `(i+½, j, k+½)`, `j = 0..=ny`: `nz·(ny+1)·nx`;
//! - `w[k][j][i]` at the z-face `(i+½, j+½, k)`, `k = 0..=nz`: `(nz+1)·ny·nx`.
//!
//! The lattices, their trilinear sampling and the velocity at each point
//! ([`Mac::taps`]) are [`crate::mac`]'s, the same code as in 2D: one rule
//! for the forward step and its adjoint.
//!
//! The step is split where the gradient is split, as in 2D:
//! [`advect_buoyancy`] (explicit, differentiated by Enzyme in diffsim, with
//! the hand-written [`advect_buoyancy_adjoint`] beside it) and [`project`]
//! (a linear solve; its adjoint [`project_adjoint`] is the same solve).

use crate::smoke::MacGrid;

mod mic;
mod pressure;

pub use mic::*;
pub use pressure::*;
