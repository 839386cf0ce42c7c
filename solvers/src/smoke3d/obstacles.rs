//! Obstacles in the 3D box: solid cells from shapes (box, sphere, cylinder
//! along an axis) or from a given mask, and the obstacle boundary
//! condition, no smoke in a solid and no flow through its faces.
//!
//! As in 2D, a cell is solid when its centre lies inside a shape; the
//! projection then couples fluid cells only ([`PressureSolver3::with_obstacles`](super::PressureSolver3::with_obstacles)).

use super::MacGrid;
use crate::boundary::for_each_face;

/// A solid shape in cell units (x first; cell `(i, j, k)` has its centre at
/// `(i + ½, j + ½, k + ½)`).
#[derive(Clone, Copy, Debug, PartialEq)]
pub enum Solid3 {
    /// The axis-aligned box `[lower, upper)`.
    Box {
        /// Lower corner.
        lower: [f64; 3],
        /// Upper corner (above `lower` on every axis).
        upper: [f64; 3],
    },
    /// The ball of `radius` about `center`.
    Sphere {
        /// Centre.
        center: [f64; 3],
        /// Radius (> 0).
        radius: f64,
    },
    /// A circular cylinder along `axis` (0 x, 1 y, 2 z): the points within
    /// `radius` of the line through `center` along the axis, between
    /// `extent[0]` and `extent[1]` along it (the centre's own coordinate
    /// along the axis is not used).
    Cylinder {
        /// The cylinder's axis.
        axis: usize,
        /// A point on its centre line.
        center: [f64; 3],
        /// Radius (> 0).
        radius: f64,
        /// From and to along the axis (infinite values: through the box).
        extent: [f64; 2],
    },
}

impl Solid3 {
    /// Whether the point `q` lies inside.
    pub fn contains(&self, q: [f64; 3]) -> bool {
        match *self {
            Solid3::Box { lower, upper } => (0..3).all(|a| q[a] >= lower[a] && q[a] < upper[a]),
            Solid3::Sphere { center, radius } => (0..3).map(|a| (q[a] - center[a]).powi(2)).sum::<f64>() <= radius * radius,
            Solid3::Cylinder { axis, center, radius, extent } => {
                let across: f64 = (0..3).filter(|&a| a != axis).map(|a| (q[a] - center[a]).powi(2)).sum();
                across <= radius * radius && q[axis] >= extent[0] && q[axis] <= extent[1]
            }
        }
    }
}

/// The solid cells of `shapes` (a cell is solid when its centre lies in
/// any of them), `[k][j][i]` flattened as the smoke.
pub fn solid_cells(cfg: &MacGrid<3>, shapes: &[Solid3]) -> Vec<bool> {
    let [nx, ny, _] = cfg.n;
    (0..cfg.n_s())
        .map(|c| {
            let q = [(c % nx) as f64 + 0.5, ((c / nx) % ny) as f64 + 0.5, (c / (nx * ny)) as f64 + 0.5];
            shapes.iter().any(|s| s.contains(q))
        })
        .collect()
}

/// The open fraction of every face of each axis: 1 between two fluid cells
/// (or a fluid cell and a side of the box; across a periodic side, the
/// last cell and the first), 0 where a solid cell touches it.
pub fn open_faces(cfg: &MacGrid<3>, fluid: &[f64]) -> [Vec<f64>; 3] {
    [0, 1, 2].map(|axis| {
        let mut open = vec![0.0; cfg.n_face(axis)];
        for_each_face(cfg.n, &cfg.boundary, axis, |f| {
            let o = f.lower.map_or(1.0, |c| fluid[c]) * f.upper.map_or(1.0, |c| fluid[c]);
            open[f.index] = o;
            if let Some(k) = f.copy {
                open[k] = o;
            }
        });
        open
    })
}

/// The number of solid cells beside each cell (at most six; across a
/// periodic side too).
pub fn solid_neighbours(cfg: &MacGrid<3>, fluid: &[f64]) -> Vec<f64> {
    let mut count = vec![0.0; cfg.n_s()];
    for axis in 0..3 {
        for_each_face(cfg.n, &cfg.boundary, axis, |f| {
            if let (Some(a), Some(b)) = (f.lower, f.upper) {
                count[a] += 1.0 - fluid[b];
                count[b] += 1.0 - fluid[a];
            }
        });
    }
    count
}

/// The obstacle mask in place on a packed state `[s, u, v, w]` (or a
/// tangent or an adjoint): smoke in solid cells and the velocity on every
/// face that touches one set to zero. Linear and self-adjoint (a diagonal
/// 0/1 mask): the same call is its own transpose. `open` is
/// [`open_faces`] of the fluid mask.
pub fn apply_obstacle_mask3(cfg: &MacGrid<3>, fluid: &[f64], open: &[Vec<f64>; 3], x: &mut [f64]) {
    let (s, [u, v, w]) = cfg.split_mut(x);
    for (sv, &f) in s.iter_mut().zip(fluid) {
        *sv *= f;
    }
    for (vel, o) in [u, v, w].into_iter().zip(open) {
        for (x, &o) in vel.iter_mut().zip(o) {
            *x *= o;
        }
    }
}
