//! The six sides of the 3D box ([`crate::boundary::Boundary<3>`]): the
//! velocity boundary conditions on the sides' faces, the faces of each axis
//! with the cells beside them (across periodic sides too), and which faces
//! the boundary sets after an advection.

use super::*;
use crate::boundary::{Face, axis_face};

/// The boundary conditions on the velocity, in place: a closed side's
/// faces 0, an inflow side's the profile (inward, [`crate::boundary::Profile::across`]),
/// an outflow side's as they are, and on a periodic axis face `N` the copy
/// of face `0`. For P4's closed box, [`close_walls`].
pub fn enforce_boundary3(cfg: &MacGrid<3>, [u, v, w]: [&mut [f64]; 3]) {
    // One call per component: a loop over the three slices in an array
    // lost the periodic copies' derivatives in Enzyme (docs/pitfalls.md).
    set_sides(cfg, 0, u);
    set_sides(cfg, 1, v);
    set_sides(cfg, 2, w);
}

/// [`enforce_boundary3`] on the faces `f` normal to `a`.
#[inline(always)]
fn set_sides(cfg: &MacGrid<3>, a: usize, f: &mut [f64]) {
    let n = cfg.n;
    let [lo, hi] = cfg.boundary.axis(a);
    let e = cfg.face_dims(a);
    // The side's two axes, in x, y, z order.
    let (b, c) = match a {
        0 => (1, 2),
        1 => (0, 2),
        _ => (0, 1),
    };
    for qc in 0..n[c] {
        for qb in 0..n[b] {
            let index = |k: usize| {
                let mut q = [0; 3];
                q[a] = k;
                q[b] = qb;
                q[c] = qc;
                (q[2] * e[1] + q[1]) * e[0] + q[0]
            };
            let (t1, t2) = ((qb as f64 + 0.5) / n[b] as f64, (qc as f64 + 0.5) / n[c] as f64);
            let (first, last) = (index(0), index(n[a]));
            match lo {
                Side::Closed => f[first] = 0.0,
                Side::Inflow(p) => f[first] = p.across(t1, t2),
                Side::Periodic | Side::Outflow => {}
            }
            match hi {
                Side::Closed => f[last] = 0.0,
                Side::Inflow(p) => f[last] = -p.across(t1, t2),
                Side::Periodic => f[last] = f[first],
                Side::Outflow => {}
            }
        }
    }
}

/// The linear part of [`enforce_boundary3`] (inflow faces set to 0, as
/// closed ones), for tangents. (A separate boundary, not a flag: a flag
/// choosing between the profile and 0 leaves Enzyme a value it cannot
/// type, docs/pitfalls.md.)
pub fn enforce_boundary3_linear(cfg: &MacGrid<3>, vel: [&mut [f64]; 3]) {
    enforce_boundary3(&cfg.with_boundary(cfg.boundary.homogeneous()), vel);
}

/// Adjoint of [`enforce_boundary3`] (of its linear part) on the velocity
/// adjoint, in place: set faces pass nothing back, a periodic copy passes
/// its adjoint to face `0`.
pub fn enforce_boundary3_adjoint(cfg: &MacGrid<3>, vel: [&mut [f64]; 3]) {
    for (a, g) in vel.into_iter().enumerate() {
        for_each_face3(cfg, a, |f| {
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

/// The two cells beside face `q` normal to `axis` when it lies between two
/// cells (inside the box, or across a periodic side: the last cell and the
/// first), `None` on the other sides and for a periodic copy. Plain
/// integers, for differentiated loops ([`for_each_face3`] builds a
/// [`Face`], whose integer fields Enzyme warns about there).
#[inline(always)]
pub(crate) fn cells_beside(cfg: &MacGrid<3>, axis: usize, q: [usize; 3]) -> Option<(usize, usize)> {
    let n = cfg.n;
    let stride = [1, n[0], n[0] * n[1]][axis];
    let cell = (q[2] * n[1] + q[1]) * n[0] + q[0];
    let k = q[axis];
    if k > 0 && k < n[axis] {
        Some((cell - stride, cell))
    } else if k == 0 && cfg.boundary.wraps()[axis] {
        Some((cell + (n[axis] - 1) * stride, cell))
    } else {
        None
    }
}

/// Calls `visit` for each face normal to `axis` that holds its own value,
/// in memory order (`[k][j][i]` of the face array), with the cells beside it
/// (across a periodic side: the last cell and the first) and what the
/// projection does with it ([`Face`]); a periodic axis's duplicate last
/// faces are left out (each is `copy` of its face `0`).
#[inline]
pub fn for_each_face3(cfg: &MacGrid<3>, axis: usize, mut visit: impl FnMut(Face)) {
    let n = cfg.n;
    let [nx, ny, _] = n;
    let [lo, hi] = cfg.boundary.axis(axis);
    let e = cfg.face_dims(axis);
    let cell = |q: [usize; 3]| (q[2] * ny + q[1]) * nx + q[0];
    let mut index = 0;
    for k in 0..e[2] {
        for j in 0..e[1] {
            for i in 0..e[0] {
                let q = [i, j, k];
                if let Some(f) = axis_face(q[axis], n[axis], lo, hi) {
                    let at = |along: usize| {
                        let mut p = q;
                        p[axis] = along;
                        p
                    };
                    let face = |along: usize| {
                        let p = at(along);
                        (p[2] * e[1] + p[1]) * e[0] + p[0]
                    };
                    visit(Face {
                        index,
                        lower: f.lower.map(|l| cell(at(l))),
                        upper: f.upper.map(|u| cell(at(u))),
                        projected: f.projected,
                        side: f.side,
                        copy: f.copy.map(face),
                    });
                }
                index += 1;
            }
        }
    }
}

/// Whether point `q` of the lattice `at` is a face the boundary sets after
/// the trace (on a closed or inflow side), so that where its trace lands
/// does not matter (no kink of the step).
#[inline(always)]
pub(crate) fn set_by_boundary(cfg: &MacGrid<3>, at: At, q: [usize; 3]) -> bool {
    let a = at.axis();
    if a >= 3 {
        return false;
    }
    let [lo, hi] = cfg.boundary.axis(a);
    (q[a] == 0 && lo.sets_faces()) || (q[a] == cfg.n[a] && hi.sets_faces())
}
