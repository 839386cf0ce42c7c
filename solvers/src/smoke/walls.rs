//! Velocity boundary conditions on the box's sides.

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
            Side::Closed | Side::NoSlip => f[first] = 0.0,
            Side::Inflow(p) => f[first] = p.on_side(a, t),
            Side::Periodic | Side::Outflow => {}
        }
        match hi {
            Side::Closed | Side::NoSlip => f[last] = 0.0,
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
/// its adjoint to face `0`. On the packed velocity adjoint; the sides'
/// faces only.
pub fn enforce_boundary_adjoint<const D: usize>(cfg: &MacGrid<D>, vel: &mut [f64]) {
    for a in 0..D {
        let [lo, hi] = cfg.boundary.axis(a);
        let g = &mut vel[cfg.face_range(a)];
        side_faces(cfg, a, |first, last| {
            if hi == Side::Periodic {
                g[first] += g[last];
                g[last] = 0.0;
            }
            if lo.sets_faces() {
                g[first] = 0.0;
            }
            if hi.sets_faces() {
                g[last] = 0.0;
            }
        });
    }
}

/// A face an inflow side sets ([`inflow_faces`]).
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct InflowFace {
    /// Its index in the packed velocity.
    pub index: usize,
    /// The sign of the inward direction along the side's axis: `+1` on a
    /// lower side, `−1` on an upper one (the face holds `sign·speed`).
    pub sign: f64,
    /// The side's profile there: the inward speed [`enforce_boundary`] sets.
    pub speed: f64,
}

/// The faces the inflow sides of `cfg` set, in a fixed order: axis by
/// axis, the lower side before the upper, each side's points with the
/// lowest other axis fastest. The order of an inflow profile given as
/// parameters (the Navier–Stokes operator's).
pub fn inflow_faces<const D: usize>(cfg: &MacGrid<D>) -> Vec<InflowFace> {
    let mut out = Vec::new();
    for a in 0..D {
        let start = cfg.face_range(a).start;
        for (h, side) in cfg.boundary.axis(a).into_iter().enumerate() {
            let Side::Inflow(profile) = side else { continue };
            let mut lat = cfg.bounded().lattice(At::Face(a));
            let up = cfg.n[a] * lat.stride[a];
            lat.n[a] = 1;
            for q in lat.points() {
                let t: [f64; D] = std::array::from_fn(|b| (q[b] as f64 + 0.5) / cfg.n[b] as f64);
                let index = start + lat.index(q) + h * up;
                out.push(InflowFace { index, sign: if h == 0 { 1.0 } else { -1.0 }, speed: profile.on_side(a, t) });
            }
        }
    }
    out
}

/// Calls `f(first, last)` for every point of the two sides normal to `a`
/// with the indices of its face on the lower side and on the upper one in
/// the face array of `a` (for code Enzyme does not differentiate).
fn side_faces<const D: usize>(cfg: &MacGrid<D>, a: usize, mut f: impl FnMut(usize, usize)) {
    let mut side = cfg.bounded().lattice(At::Face(a));
    let up = cfg.n[a] * side.stride[a];
    // The face lattice cut to its first layer along `a`: the lower side's
    // points, indexed in the whole array.
    side.n[a] = 1;
    for q in side.points() {
        let first = side.index(q);
        f(first, first + up);
    }
}
