//! The other advection schemes in 3D, as in 2D: MacCormack (a backward
//! trace, a forward trace from its result, half the difference as a
//! correction; with the limiter clamped to the eight samples the backward
//! trace blended) for the smoke and/or the velocity, and first-order upwind
//! for the smoke in flux form. Plain loops that Enzyme differentiates; the
//! kinks (the clamp, the upwind switch) are declared by the radius
//! functions here.

use super::*;
use crate::mac::advect::{LimitedField, advect_field};
use crate::smoke::{Scheme, copy};

/// Scratch [`advect3`] needs: for MacCormack two fields of the largest
/// lattice, none for semi-Lagrangian.
pub fn advect3_scratch_len(cfg: &MacGrid<3>, scheme: Scheme) -> usize {
    match scheme {
        Scheme::SemiLagrangian => 0,
        Scheme::MacCormack { .. } => 2 * (0..3).map(|a| cfg.n_face(a)).max().unwrap_or(0),
    }
}

/// Advection over `cfg.dt` of the smoke (if `smoke`) and of the velocity by
/// itself (if `velocity`) in the box by `scheme`, each field sampled back
/// along the velocity at its own points (wrapping across periodic sides,
/// clamped at the others); then the boundary conditions
/// ([`enforce_boundary3`]). Fields
/// not advected are copied. Reads `x = [s, u, v, w]`, overwrites `y`;
/// `scratch` holds [`advect3_scratch_len`] values.
///
/// # Panics
/// If a length is wrong or a side has fewer than 2 cells.
#[allow(clippy::too_many_arguments)]
pub fn advect3(cfg: &MacGrid<3>, scheme: Scheme, smoke: bool, velocity: bool, x: &[f64], y: &mut [f64], scratch: &mut [f64]) {
    assert!(cfg.n[0].min(cfg.n[1]).min(cfg.n[2]) >= 2 && x.len() == cfg.n_state() && y.len() == cfg.n_state(), "smoke3d: state lengths");
    assert!(scratch.len() >= advect3_scratch_len(cfg, scheme), "smoke3d: advection scratch");
    let mac = cfg.mac();
    let (s, [u, v, w]) = cfg.split(x);
    let (s2, [u2, v2, w2]) = cfg.split_mut(y);
    let vel = [u, v, w];
    let half = scratch.len() / 2;
    let (hat, tilde) = scratch.split_at_mut(half);
    let len = |n: usize| n.min(half);
    if smoke {
        advect_field(mac, At::Centre, scheme, cfg.dt, vel, s, s2, &mut hat[..len(s.len())], &mut tilde[..len(s.len())]);
    } else {
        copy(s, s2);
    }
    if velocity {
        advect_field(mac, At::Face(0), scheme, cfg.dt, vel, u, u2, &mut hat[..len(u.len())], &mut tilde[..len(u.len())]);
        advect_field(mac, At::Face(1), scheme, cfg.dt, vel, v, v2, &mut hat[..len(v.len())], &mut tilde[..len(v.len())]);
        advect_field(mac, At::Face(2), scheme, cfg.dt, vel, w, w2, &mut hat[..len(w.len())], &mut tilde[..len(w.len())]);
        enforce_boundary3(cfg, [u2, v2, w2]);
    } else {
        copy(u, u2);
        copy(v, v2);
        copy(w, w2);
    }
}

/// The lattices advected: the centres with `smoke`, the faces with `velocity`.
fn lattices(smoke: bool, velocity: bool) -> Vec<At> {
    [(smoke, At::Centre), (velocity, At::Face(0)), (velocity, At::Face(1)), (velocity, At::Face(2))].into_iter().filter(|p| p.0).map(|p| p.1).collect()
}

/// How far `x` may move along `d` before [`advect3`] meets a sampling kink
/// (a traced point crossing a lattice plane): over the backward trace, and
/// for MacCormack also the forward one. MacCormack's limiter is
/// [`limiter3_radius`].
pub fn advect3_radius(cfg: &MacGrid<3>, scheme: Scheme, smoke: bool, velocity: bool, x: &[f64], d: &[f64]) -> f64 {
    let (_, [u, v, w]) = cfg.split(x);
    let (_, [du, dv, dw]) = cfg.split(d);
    let steps: &[f64] = match scheme {
        Scheme::SemiLagrangian => &[cfg.dt],
        Scheme::MacCormack { .. } => &[cfg.dt, -cfg.dt],
    };
    // A face on a wall is set by the walls after the trace (when the
    // velocity is advected, as it is on its lattices).
    crate::mac::advect::advect_radius(cfg.mac(), &lattices(smoke, velocity), steps, &[0.0; 2], [u, v, w], [du, dv, dw], |at, q| set_by_boundary(cfg, at, q))
}

/// How far `x` may move along `d` before MacCormack's limiter switches (the
/// 3D [`crate::smoke::limiter_radius`]): where an unclamped value crosses
/// the smallest or largest of its eight samples, or the bound passes from
/// one sample to another. First order, rates from a step of `1e-7`
/// relative along `d`; within [`advect3_radius`], which the caller takes too.
pub fn limiter3_radius(cfg: &MacGrid<3>, smoke: bool, velocity: bool, x: &[f64], d: &[f64]) -> f64 {
    let dmax = d.iter().fold(0.0f64, |m, v| m.max(v.abs()));
    if dmax == 0.0 {
        return f64::INFINITY;
    }
    let eps = 1e-7 * (1.0 + x.iter().fold(0.0f64, |m, v| m.max(v.abs()))) / dmax;
    let xe: Vec<f64> = x.iter().zip(d).map(|(a, b)| a + eps * b).collect();
    let (fx, fd, fe) = (cfg.split(x), cfg.split(d), cfg.split(&xe));
    let fields: Vec<LimitedField<'_>> = lattices(smoke, velocity)
        .into_iter()
        .map(|at| match at {
            At::Centre => LimitedField { at, f: fx.0, df: fd.0, fe: fe.0 },
            At::Face(a) => LimitedField { at, f: fx.1[a], df: fd.1[a], fe: fe.1[a] },
        })
        .collect();
    let vel = [fx.1, fe.1];
    crate::mac::advect::limiter_radius(cfg.mac(), &fields, cfg.dt, vel, eps, |at, q| set_by_boundary(cfg, at, q))
}

/// First-order upwind advection of the smoke by the MAC velocity over
/// `cfg.dt`, in flux form through every face between two cells (across
/// periodic sides too; none through the other sides): smoke is conserved. Reads `x = [s, u, v, w]`, writes
/// `y = [s', u, v, w]`.
///
/// # Panics
/// If a length is wrong.
pub fn advect_upwind3(cfg: &MacGrid<3>, x: &[f64], y: &mut [f64]) {
    assert!(x.len() == cfg.n_state() && y.len() == cfg.n_state(), "smoke3d: state lengths");
    copy(x, y);
    let dt = cfg.dt;
    for axis in 0..3 {
        // The component's faces in the packed state.
        let start = cfg.slab_starts(0).1[axis];
        let e = cfg.face_dims(axis);
        for k in 0..e[2] {
            for j in 0..e[1] {
                for i in 0..e[0] {
                    if let Some((lo, hi)) = cells_beside(cfg, axis, [i, j, k]) {
                        let c = dt * x[start + (k * e[1] + j) * e[0] + i];
                        let flux = c * if c > 0.0 { x[lo] } else { x[hi] };
                        y[lo] -= flux;
                        y[hi] += flux;
                    }
                }
            }
        }
    }
}

/// Distance to the nearest upwind switch of [`advect_upwind3`] along `d`:
/// the smallest `|vel_f / d_f|` over the interior faces.
pub fn upwind3_radius(cfg: &MacGrid<3>, x: &[f64], d: &[f64]) -> f64 {
    let (_, [u, v, w]) = cfg.split(x);
    let (_, [du, dv, dw]) = cfg.split(d);
    let mut r = f64::INFINITY;
    for (axis, (vel, dvel)) in [(u, du), (v, dv), (w, dw)].into_iter().enumerate() {
        for_each_face3(cfg, axis, |f| {
            if f.lower.is_some() && f.upper.is_some() && dvel[f.index] != 0.0 {
                r = r.min((vel[f.index] / dvel[f.index]).abs());
            }
        });
    }
    r
}
