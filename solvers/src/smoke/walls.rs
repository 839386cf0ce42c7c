//! Velocity boundary conditions on the box's sides, and obstacles (solid
//! cells whose faces are held at zero).

use super::*;

/// The velocity boundary conditions, in place: a closed side's faces 0,
/// an inflow side's the profile (inward, [`crate::boundary::Profile::on_side`]),
/// an outflow side's as they are, and on a periodic axis face `N` the copy
/// of face `0`. On the packed velocity `vel` ([`MacGrid::n_vel`] values).
pub fn enforce_boundary<const D: usize>(cfg: &MacGrid<D>, vel: &mut [f64]) {
    // Component by component, each a slice of the packed velocity (an array
    // of slices iterated by value lost the periodic copies' derivatives in
    // Enzyme, docs/pitfalls.md).
    each_axis!(D, a => {
        set_sides(cfg, a, &mut vel[cfg.face_range(a)]);
    });
}

/// [`enforce_boundary`] on the faces `f` normal to `a`: over the points of
/// the side (every axis but `a`, x fastest), its first and last face.
#[inline(always)]
fn set_sides<const D: usize>(cfg: &MacGrid<D>, a: usize, f: &mut [f64]) {
    let n = cfg.cells();
    let [lo, hi] = cfg.boundary.axis(a);
    let e = cfg.face_dims(a);
    // Strides of the face array; the side's points counted across it.
    let mut stride = e;
    let (mut step, mut points) = (1, 1);
    each_axis!(D, b => {
        stride[b] = step;
        step *= e[b];
        if b != a {
            points *= n[b];
        }
    });
    for m in 0..points {
        // The point's position on the other axes, and across the side.
        let (mut first, mut rest) = (0, m);
        let mut t = [0.5; D];
        each_axis!(D, b => {
            if b != a {
                let q = rest % n[b];
                rest /= n[b];
                first += q * stride[b];
                t[b] = (q as f64 + 0.5) / n[b] as f64;
            }
        });
        let last = first + n[a] * stride[a];
        match lo {
            Side::Closed => f[first] = 0.0,
            Side::Inflow(p) => f[first] = p.on_side(a, t),
            Side::Periodic | Side::Outflow => {}
        }
        match hi {
            Side::Closed => f[last] = 0.0,
            Side::Inflow(p) => f[last] = -p.on_side(a, t),
            Side::Periodic => f[last] = f[first],
            Side::Outflow => {}
        }
    }
}

/// The linear part of [`enforce_boundary`] (inflow faces set to 0, not to
/// the profile), for tangents: closed and inflow faces 0, periodic copies.
/// (A separate boundary, not a flag: a flag choosing between the profile
/// and 0 leaves Enzyme a value it cannot type, docs/pitfalls.md.)
pub fn enforce_boundary_linear<const D: usize>(cfg: &MacGrid<D>, vel: &mut [f64]) {
    enforce_boundary(&cfg.with_boundary(cfg.boundary.homogeneous()), vel);
}

/// Adjoint of [`enforce_boundary`] (of its linear part) on the velocity
/// adjoint, in place: set faces pass nothing back, a periodic copy passes
/// its adjoint to face `0`. On the packed velocity adjoint.
pub fn enforce_boundary_adjoint<const D: usize>(cfg: &MacGrid<D>, vel: &mut [f64]) {
    for (a, g) in cfg.components_mut(vel).into_iter().enumerate() {
        for_each_face(cfg.n, &cfg.boundary, a, |f| {
            if let Some(k) = f.copy {
                g[f.index] += g[k];
                g[k] = 0.0;
            }
            if f.side.is_some_and(Side::sets_faces) {
                g[f.index] = 0.0;
            }
        });
    }
}

/// Zeroes the smoke in solid cells and the velocity on every face that
/// touches a solid cell, in place on a packed state: the obstacle boundary
/// condition. Linear and self-adjoint (a diagonal 0/1 mask), so the same
/// call is its own VJP.
pub fn apply_obstacle_mask(cfg: &MacGrid<2>, fluid: &[f64], x: &mut [f64]) {
    let (s, [u, v]) = cfg.split_mut(x);
    for (sv, &w) in s.iter_mut().zip(fluid) {
        *sv *= w;
    }
    for (axis, vel) in [u, v].into_iter().enumerate() {
        for_each_face(cfg.n, &cfg.boundary, axis, |f| {
            let o = open(Some(fluid), &f);
            vel[f.index] *= o;
            if let Some(k) = f.copy {
                vel[k] *= o;
            }
        });
    }
}

/// Solid cells of an axis-aligned box `[lower, upper)` in cell units (x
/// first), for the fluid operators and, complemented, as the fluid mask of
/// [`PressureSolver::general`]: a cell is solid when its centre lies inside. The box is clipped to the
/// domain; `None` when no cell centre lies inside (a box wholly outside).
pub fn obstacle_box(cfg: &MacGrid<2>, lower: [f64; 2], upper: [f64; 2]) -> Option<Vec<bool>> {
    obstacle(cfg, |x, y| x >= lower[0] && x < upper[0] && y >= lower[1] && y < upper[1])
}

/// Solid cells of a disc (centre in cell units, x first): a cell is solid
/// when its centre lies within `radius`. `None` when no cell is covered.
pub fn obstacle_disc(cfg: &MacGrid<2>, center: [f64; 2], radius: f64) -> Option<Vec<bool>> {
    obstacle(cfg, |x, y| (x - center[0]).powi(2) + (y - center[1]).powi(2) <= radius * radius)
}

fn obstacle(cfg: &MacGrid<2>, inside: impl Fn(f64, f64) -> bool) -> Option<Vec<bool>> {
    let n = cfg.n[0];
    let solid: Vec<bool> = (0..cfg.n_s()).map(|c| inside((c % n) as f64 + 0.5, (c / n) as f64 + 0.5)).collect();
    solid.iter().any(|&s| s).then_some(solid)
}
