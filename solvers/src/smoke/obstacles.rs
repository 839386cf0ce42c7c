//! Obstacles in the box, in any dimension: solid cells from shapes (a box,
//! a ball — a disc in 2D —, a cylinder along an axis) or from a given mask,
//! the faces they close, and the obstacle boundary condition: no smoke in a
//! solid and no flow through its faces. A cell is solid when its centre
//! lies inside a shape; the projection then couples fluid cells only.

use super::*;

/// A solid shape in cell units (x first; cell `q` has its centre at `q +
/// ½` on every axis).
#[derive(Clone, Copy, Debug, PartialEq)]
pub enum Solid<const D: usize> {
    /// The axis-aligned box `[lower, upper)`.
    Box {
        /// Lower corner.
        lower: [f64; D],
        /// Upper corner (above `lower` on every axis).
        upper: [f64; D],
    },
    /// The ball (in 2D the disc) of `radius` about `center`.
    Ball {
        /// Centre.
        center: [f64; D],
        /// Radius (> 0).
        radius: f64,
    },
    /// The points within `radius` of the line through `center` along
    /// `axis`, between `extent[0]` and `extent[1]` along it (the centre's
    /// own coordinate along the axis is not used): a circular cylinder in
    /// 3D, a strip in 2D.
    Cylinder {
        /// The cylinder's axis.
        axis: usize,
        /// A point on its centre line.
        center: [f64; D],
        /// Radius (> 0).
        radius: f64,
        /// From and to along the axis (infinite values: through the box).
        extent: [f64; 2],
    },
}

impl<const D: usize> Solid<D> {
    /// Whether the point `q` lies inside.
    pub fn contains(&self, q: [f64; D]) -> bool {
        match *self {
            Solid::Box { lower, upper } => (0..D).all(|a| q[a] >= lower[a] && q[a] < upper[a]),
            Solid::Ball { center, radius } => (0..D).map(|a| (q[a] - center[a]).powi(2)).sum::<f64>() <= radius * radius,
            Solid::Cylinder { axis, center, radius, extent } => {
                let across: f64 = (0..D).filter(|&a| a != axis).map(|a| (q[a] - center[a]).powi(2)).sum();
                across <= radius * radius && q[axis] >= extent[0] && q[axis] <= extent[1]
            }
        }
    }
}

/// The solid cells of `shapes` (a cell is solid when its centre lies in
/// any of them), flattened as the smoke.
pub fn solid_cells<const D: usize>(cfg: &MacGrid<D>, shapes: &[Solid<D>]) -> Vec<bool> {
    let cells = cfg.bounded().lattice(At::Centre);
    let mut solid = vec![false; cells.len];
    for q in cells.points() {
        let centre = q.map(|k| k as f64 + 0.5);
        solid[cells.index(q)] = shapes.iter().any(|s| s.contains(centre));
    }
    solid
}

/// The fluid indicator of a solid mask: 1 in fluid cells, 0 in solid ones.
pub fn fluid_of(solid: &[bool]) -> Vec<f64> {
    solid.iter().map(|&s| if s { 0.0 } else { 1.0 }).collect()
}

/// The open fraction of every face, packed as the velocity: 1 between two
/// fluid cells (or a fluid cell and a side of the box; across a periodic
/// side, the last cell and the first), 0 where a solid cell touches it.
pub fn open_faces<const D: usize>(cfg: &MacGrid<D>, fluid: &[f64]) -> Vec<f64> {
    let mut open = vec![0.0; cfg.n_vel()];
    for (a, o) in cfg.components_mut(&mut open).into_iter().enumerate() {
        for_each_face(cfg.n, &cfg.boundary, a, |f| {
            let w = super::open(Some(fluid), &f);
            o[f.index] = w;
            if let Some(k) = f.copy {
                o[k] = w;
            }
        });
    }
    open
}

/// The number of solid cells beside each cell (at most `2D`; across a
/// periodic side too).
pub fn solid_neighbours<const D: usize>(cfg: &MacGrid<D>, fluid: &[f64]) -> Vec<f64> {
    let mut count = vec![0.0; cfg.n_s()];
    for axis in 0..D {
        for_each_face(cfg.n, &cfg.boundary, axis, |f| {
            if let (Some(a), Some(b)) = (f.lower, f.upper) {
                count[a] += 1.0 - fluid[b];
                count[b] += 1.0 - fluid[a];
            }
        });
    }
    count
}

/// The obstacle mask in place on a packed state (or a tangent or an
/// adjoint): smoke in solid cells and the velocity on every face that
/// touches one set to zero. Linear and self-adjoint (a diagonal 0/1 mask):
/// the same call is its own transpose. `open` is [`open_faces`] of the
/// fluid indicator `fluid`.
pub fn apply_obstacle_mask<const D: usize>(cfg: &MacGrid<D>, fluid: &[f64], open: &[f64], x: &mut [f64]) {
    let (s, vel) = x.split_at_mut(cfg.n_s());
    mask_cells(fluid, s);
    mask_faces(open, vel);
}

/// The smoke part of [`apply_obstacle_mask`]: the smoke (or its tangent or
/// adjoint) in solid cells set to zero.
pub fn mask_cells(fluid: &[f64], s: &mut [f64]) {
    for (v, &f) in s.iter_mut().zip(fluid) {
        *v *= f;
    }
}

/// The velocity part of [`apply_obstacle_mask`] on a packed velocity (or
/// its tangent or adjoint): every face that touches a solid set to zero.
pub fn mask_faces(open: &[f64], vel: &mut [f64]) {
    for (v, &o) in vel.iter_mut().zip(open) {
        *v *= o;
    }
}
