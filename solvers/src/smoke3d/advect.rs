//! Semi-Lagrangian advection of the smoke and the velocity (trilinear), P4's
//! buoyancy and walls, and the hand-written adjoint of the three. The traces
//! are [`crate::mac`]'s, shared with 2D.

use std::ops::Range;

use super::*;
use crate::mac::advect::{trace, trace_adjoint, trace_parallel};

/// Steps 1–4 of P4: semi-Lagrangian advection of the smoke and of the
/// velocity (time step `cfg.dt`, 1 in P4; each component sampled at its own faces along
/// the velocity there), the closed walls, buoyancy along +y. Reads the
/// packed state `x = [s, u, v, w]`, overwrites `y` (the velocity not yet
/// divergence-free).
///
/// # Panics
/// If `x` or `y` is not of length [`MacGrid<3>::n_state`] or a side has fewer
/// than 2 cells.
pub fn advect_buoyancy(cfg: &MacGrid<3>, x: &[f64], y: &mut [f64]) {
    advect_buoyancy_slabs(cfg, x, 0..cfg.n[2], y);
}

/// Slabs `ks` of [`advect_buoyancy`]'s output, packed as
/// [`MacGrid<3>::slab_lens`] says (`y` of their total length): each output slab
/// depends on the whole input but on no other output slab, so that an
/// adjoint can be taken slab range by slab range (in parallel, then summed
/// in a fixed order). Over `0..nz`, [`advect_buoyancy`] itself.
///
/// # Panics
/// If `x` or `y` has the wrong length, `ks` is empty or past `nz`, or a
/// side has fewer than 2 cells.
pub fn advect_buoyancy_slabs(cfg: &MacGrid<3>, x: &[f64], ks: Range<usize>, y: &mut [f64]) {
    let (ls, [lu, lv, lw]) = cfg.slab_lens(ks.clone());
    assert!(cfg.min_cells() >= 2 && x.len() == cfg.n_state() && y.len() == ls + lu + lv + lw, "smoke3d: state lengths");
    assert!(ks.start < ks.end && ks.end <= cfg.n[2], "smoke3d: slabs {ks:?} of {}", cfg.n[2]);
    let mac = Mac::bounded(cfg.n);
    let (s, [u, v, w]) = cfg.split(x);
    let (s2, rest) = y.split_at_mut(ls);
    let (u2, rest) = rest.split_at_mut(lu);
    let (v2, w2) = rest.split_at_mut(lv);
    let vel = [u, v, w];
    trace(mac, At::Centre, vel, s, cfg.dt, ks.clone(), s2);
    trace(mac, At::Face(0), vel, u, cfg.dt, ks.clone(), u2);
    trace(mac, At::Face(1), vel, v, cfg.dt, ks.clone(), v2);
    trace(mac, At::Face(2), vel, w, cfg.dt, ks.clone(), w2);
    close_walls_slabs(cfg, ks.clone(), [u2, v2, w2]);
    add_buoyancy_slabs(cfg, cfg.buoyancy, ks.len(), s2, v2);
}

/// [`advect_buoyancy`] with the slabs of each field split over threads
/// ([`crate::par`]): the same values for any thread count. Not for
/// differentiated code (Enzyme differentiates [`advect_buoyancy`], whose
/// body this repeats: sharing it through a generic trace trips Enzyme).
///
/// # Panics
/// As [`advect_buoyancy`].
pub fn advect_buoyancy_parallel(cfg: &MacGrid<3>, x: &[f64], y: &mut [f64]) {
    assert!(cfg.n[0].min(cfg.n[1]).min(cfg.n[2]) >= 2 && x.len() == cfg.n_state() && y.len() == cfg.n_state(), "smoke3d: state lengths");
    let mac = Mac::bounded(cfg.n);
    let (s, [u, v, w]) = cfg.split(x);
    let (s2, [u2, v2, w2]) = cfg.split_mut(y);
    let vel = [u, v, w];
    trace_parallel(mac, At::Centre, vel, s, cfg.dt, s2);
    trace_parallel(mac, At::Face(0), vel, u, cfg.dt, u2);
    trace_parallel(mac, At::Face(1), vel, v, cfg.dt, v2);
    trace_parallel(mac, At::Face(2), vel, w, cfg.dt, w2);
    close_walls(cfg, [u2, v2, w2]);
    add_buoyancy(cfg, cfg.buoyancy, s2, v2);
}

/// Zeroes the velocity on the six walls (P4's step 3).
pub fn close_walls(cfg: &MacGrid<3>, vel: [&mut [f64]; 3]) {
    close_walls_slabs(cfg, 0..cfg.n[2], vel);
}

/// [`close_walls`] on slabs `ks` of the velocity (packed as
/// [`MacGrid<3>::slab_lens`] says).
fn close_walls_slabs(cfg: &MacGrid<3>, ks: Range<usize>, [u, v, w]: [&mut [f64]; 3]) {
    let [nx, ny, nz] = cfg.n;
    for k in 0..ks.len() {
        for j in 0..ny {
            let r = (k * ny + j) * (nx + 1);
            u[r] = 0.0;
            u[r + nx] = 0.0;
        }
        for i in 0..nx {
            v[(k * (ny + 1)) * nx + i] = 0.0;
            v[(k * (ny + 1) + ny) * nx + i] = 0.0;
        }
    }
    // Indexed stores, not `fill`: a fill is a memset, whose type Enzyme
    // cannot deduce here (docs/pitfalls.md).
    let (slab, last) = (nx * ny, w.len() - nx * ny);
    for c in 0..slab {
        if ks.start == 0 {
            w[c] = 0.0;
        }
        if ks.end == nz {
            w[last + c] = 0.0;
        }
    }
}

/// Buoyancy along +y, in place: `v[k][j][i] += coefficient · (s[k][j−1][i]
/// + s[k][j][i]) / 2` on the interior y-faces.
pub fn add_buoyancy(cfg: &MacGrid<3>, coefficient: f64, s: &[f64], v: &mut [f64]) {
    add_buoyancy_slabs(cfg, coefficient, cfg.n[2], s, v);
}

/// [`add_buoyancy`] on `slabs` slabs of `s` and `v`.
fn add_buoyancy_slabs(cfg: &MacGrid<3>, coefficient: f64, slabs: usize, s: &[f64], v: &mut [f64]) {
    let [nx, ny, _] = cfg.n;
    for k in 0..slabs {
        for j in 1..ny {
            for i in 0..nx {
                v[(k * (ny + 1) + j) * nx + i] += coefficient * 0.5 * (s[(k * ny + j - 1) * nx + i] + s[(k * ny + j) * nx + i]);
            }
        }
    }
}

/// Hand-written adjoint of [`advect_buoyancy`]: `gx += Jᵀ·gy` at the state
/// `x` (accumulates into `gx`; `gy` is used as scratch and left
/// unspecified). The reference for Enzyme's generated adjoint.
///
/// # Panics
/// As [`advect_buoyancy`], and if `gy` or `gx` has the wrong length.
pub fn advect_buoyancy_adjoint(cfg: &MacGrid<3>, x: &[f64], gy: &mut [f64], gx: &mut [f64]) {
    let n = cfg.n_state();
    assert!(cfg.n[0].min(cfg.n[1]).min(cfg.n[2]) >= 2 && x.len() == n && gy.len() == n && gx.len() == n, "smoke3d: state lengths");
    let mac = Mac::bounded(cfg.n);
    let [nx, ny, nz] = cfg.n;
    let (s, [u, v, w]) = cfg.split(x);
    let (gs2, [gu2, gv2, gw2]) = cfg.split_mut(gy);
    // Buoyancy, then the walls (which zero what they set).
    for k in 0..nz {
        for j in 1..ny {
            for i in 0..nx {
                let b = cfg.buoyancy * 0.5 * gv2[(k * (ny + 1) + j) * nx + i];
                gs2[(k * ny + j - 1) * nx + i] += b;
                gs2[(k * ny + j) * nx + i] += b;
            }
        }
    }
    close_walls(cfg, [&mut *gu2, &mut *gv2, &mut *gw2]);
    let (gs, [gu, gv, gw]) = cfg.split_mut(gx);
    let vel = [u, v, w];
    trace_adjoint(mac, At::Face(2), vel, w, cfg.dt, gw2, None, &mut [&mut *gu, &mut *gv, &mut *gw]);
    trace_adjoint(mac, At::Face(1), vel, v, cfg.dt, gv2, None, &mut [&mut *gu, &mut *gv, &mut *gw]);
    trace_adjoint(mac, At::Face(0), vel, u, cfg.dt, gu2, None, &mut [&mut *gu, &mut *gv, &mut *gw]);
    trace_adjoint(mac, At::Centre, vel, s, cfg.dt, gs2, Some(gs), &mut [gu, gv, gw]);
}

/// How far `x` may move along `d` before [`advect_buoyancy`] meets a kink:
/// trilinear sampling is smooth between lattice planes and kinks where a
/// traced point crosses one (or a clamped edge). The smallest, over the
/// traced points of the four lattices (the walls' own faces left out: the
/// walls set them), of the distance to the nearest plane over the speed at
/// which `d` moves the point; ∞ when `d` moves none.
pub fn advect_radius(cfg: &MacGrid<3>, x: &[f64], d: &[f64]) -> f64 {
    advect3_radius(cfg, crate::smoke::Scheme::SemiLagrangian, true, true, x, d)
}

/// Hand-written adjoint of [`advect3`] with the semi-Lagrangian scheme, in
/// any box: `gx += Jᵀ·gy` at the state `x` (accumulates into `gx`; `gy` is
/// used as scratch and left unspecified). The reference for Enzyme's
/// generated adjoint of [`advect3`] under every boundary
/// kind (P4's closed step has its own, [`advect_buoyancy_adjoint`]).
///
/// # Panics
/// As [`advect3`], and if `gy` or `gx` has the wrong length.
pub fn advect3_adjoint(cfg: &MacGrid<3>, smoke: bool, velocity: bool, x: &[f64], gy: &mut [f64], gx: &mut [f64]) {
    let n = cfg.n_state();
    assert!(cfg.n[0].min(cfg.n[1]).min(cfg.n[2]) >= 2 && x.len() == n && gy.len() == n && gx.len() == n, "smoke3d: state lengths");
    let mac = cfg.mac();
    let (s, [u, v, w]) = cfg.split(x);
    let (gs2, [gu2, gv2, gw2]) = cfg.split_mut(gy);
    let (gs, [gu, gv, gw]) = cfg.split_mut(gx);
    let vel = [u, v, w];
    if velocity {
        // The boundary conditions came last: set faces pass nothing back,
        // periodic copies hand theirs to face 0.
        enforce_boundary3_adjoint(cfg, [&mut *gu2, &mut *gv2, &mut *gw2]);
        trace_adjoint(mac, At::Face(2), vel, w, cfg.dt, gw2, None, &mut [&mut *gu, &mut *gv, &mut *gw]);
        trace_adjoint(mac, At::Face(1), vel, v, cfg.dt, gv2, None, &mut [&mut *gu, &mut *gv, &mut *gw]);
        trace_adjoint(mac, At::Face(0), vel, u, cfg.dt, gu2, None, &mut [&mut *gu, &mut *gv, &mut *gw]);
    } else {
        for (g, g2) in [(&mut *gu, &*gu2), (&mut *gv, &*gv2), (&mut *gw, &*gw2)] {
            for (g, &g2) in g.iter_mut().zip(g2) {
                *g += g2;
            }
        }
    }
    if smoke {
        trace_adjoint(mac, At::Centre, vel, s, cfg.dt, gs2, Some(gs), &mut [gu, gv, gw]);
    } else {
        for (g, &g2) in gs.iter_mut().zip(&*gs2) {
            *g += g2;
        }
    }
}
