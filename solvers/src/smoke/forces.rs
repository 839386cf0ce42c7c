//! Buoyancy, external forces on the faces, and inflow regions, in any
//! dimension: plain loops over the packed state that Enzyme differentiates
//! (with respect to the state and the coefficients), each array walked
//! slab by slab and row by row through its [`Lattice`] as the traces are
//! (constant-bound axis loops only: Enzyme cannot type an index into a
//! small array that a loop of unknown trip count computes, docs/pitfalls.md).

use super::*;
use crate::mac::Lattice;

/// The lattice of every face normal to `axis` (periodic copies included)
/// and that of the cells.
#[inline(always)]
fn lattices_of<const D: usize>(cfg: &MacGrid<D>, axis: usize) -> (Lattice<D>, Lattice<D>) {
    let mac = cfg.bounded();
    (mac.lattice(At::Face(axis)), mac.lattice(At::Centre))
}

/// Buoyancy along `axis`, in place: the velocity component `f` of that axis
/// raised by `coefficient · (smoke averaged to the face)` on its faces
/// between two cells (interior, and across a periodic side: the last cell
/// and the first, the copy refreshed).
pub fn add_buoyancy<const D: usize>(cfg: &MacGrid<D>, axis: usize, coefficient: f64, s: &[f64], f: &mut [f64]) {
    // The axis a constant in each arm (see `each_axis`).
    on_axis!(axis, axis => {
        let (faces, cells) = lattices_of(cfg, axis);
        let m = cfg.n[axis];
        let wrap = cfg.boundary.wraps()[axis];
        let (down, copy) = (cells.stride[axis], m * faces.stride[axis]);
        for k in 0..faces.n[D - 1] {
            for r in 0..faces.rows_per_slab() {
                let mut q = faces.row_start(k, r);
                for i in 0..faces.n[0] {
                    q[0] = i;
                    let along = q[axis];
                    let face = faces.index(q);
                    if along > 0 && along < m {
                        let c = cells.index(q);
                        f[face] += coefficient * 0.5 * (s[c - down] + s[c]);
                    } else if wrap && along == 0 {
                        let c = cells.index(q);
                        f[face] += coefficient * 0.5 * (s[c + (m - 1) * down] + s[c]);
                        f[face + copy] = f[face];
                    }
                }
            }
        }
    })
}

/// [`add_buoyancy`] as a map of packed states: `y = x` with the component
/// of `axis` (0 x, 1 y, 2 z; a negative coefficient pushes the other way)
/// raised by `coefficient · (smoke averaged to the face)`.
///
/// # Panics
/// If `x` or `y` is not a packed state or `axis ≥ D`.
pub fn apply_buoyancy<const D: usize>(cfg: &MacGrid<D>, axis: usize, coefficient: f64, x: &[f64], y: &mut [f64]) {
    assert!(x.len() == cfg.n_state() && y.len() == cfg.n_state() && axis < D, "smoke: buoyancy lengths");
    copy(x, y);
    let (s, _) = cfg.split(x);
    let r = cfg.face_range(axis);
    let ns = cfg.n_s();
    add_buoyancy(cfg, axis, coefficient, s, &mut y[ns + r.start..ns + r.end]);
}

/// An external force over a time step `dt`: `[s, u₀, …] ↦ [s, u₀ + dt·f₀,
/// …]` on the interior faces and those that wrap across a periodic side
/// (copies refreshed), with the force `f` given per face (the velocity
/// layout, [`MacGrid::n_vel`] values); the faces on the other sides keep
/// their velocity.
///
/// # Panics
/// If the lengths are wrong.
pub fn apply_force<const D: usize>(cfg: &MacGrid<D>, dt: f64, x: &[f64], f: &[f64], y: &mut [f64]) {
    assert!(x.len() == cfg.n_state() && y.len() == cfg.n_state() && f.len() == cfg.n_vel(), "smoke: force lengths");
    copy(x, y);
    let wraps = cfg.boundary.wraps();
    let ns = cfg.n_s();
    each_axis!(D, axis => {
        let start = ns + cfg.face_range(axis).start;
        let (faces, _) = lattices_of(cfg, axis);
        let m = cfg.n[axis];
        let first = 1 - wraps[axis] as usize;
        let copy = m * faces.stride[axis];
        for k in 0..faces.n[D - 1] {
            for r in 0..faces.rows_per_slab() {
                let mut q = faces.row_start(k, r);
                for i in 0..faces.n[0] {
                    q[0] = i;
                    let along = q[axis];
                    if along >= first && along < m {
                        let face = start + faces.index(q);
                        y[face] += dt * f[face - ns];
                        if along == 0 {
                            y[face + copy] = y[face];
                        }
                    }
                }
            }
        }
    });
}

/// Inflow: in the cells `region[a][0]..region[a][1]` along each axis `a`
/// the smoke set to `p[0]` and the velocity on the faces of those cells
/// (the box's sides excepted) to `(p[1], …, p[D])`; everything else passes
/// through.
///
/// # Panics
/// If the lengths are wrong or the region is empty or leaves the box.
pub fn apply_inflow<const D: usize>(cfg: &MacGrid<D>, region: [[usize; 2]; D], x: &[f64], p: &[f64], y: &mut [f64]) {
    let n = cfg.cells();
    assert!(x.len() == cfg.n_state() && y.len() == cfg.n_state() && p.len() == D + 1, "smoke: inflow lengths");
    assert!((0..D).all(|a| region[a][0] < region[a][1] && region[a][1] <= n[a]), "smoke: inflow region");
    copy(x, y);
    let ns = cfg.n_s();
    each_axis!(D, axis => {
        let start = ns + cfg.face_range(axis).start;
        let (faces, cells) = lattices_of(cfg, axis);
        for k in 0..faces.n[D - 1] {
            for r in 0..faces.rows_per_slab() {
                let mut q = faces.row_start(k, r);
                for i in 0..faces.n[0] {
                    q[0] = i;
                    // The region's cells (once, with the first axis), and
                    // each axis's faces of them off the box's sides.
                    let (mut cell, mut face) = (axis == 0, true);
                    for a in 0..D {
                        let [lo, hi] = region[a];
                        cell &= q[a] >= lo && q[a] < hi;
                        face &= if a == axis { q[a] >= lo.max(1) && q[a] <= hi.min(n[a] - 1) } else { q[a] >= lo && q[a] < hi };
                    }
                    if cell && q[0] < n[0] {
                        y[cells.index(q)] = p[0];
                    }
                    if face {
                        y[start + faces.index(q)] = p[1 + axis];
                    }
                }
            }
        }
    });
}
