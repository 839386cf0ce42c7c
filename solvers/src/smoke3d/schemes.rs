//! The other advection schemes in 3D, as in 2D: MacCormack (a backward
//! trace, a forward trace from its result, half the difference as a
//! correction; with the limiter clamped to the eight samples the backward
//! trace blended) for the smoke and/or the velocity, and first-order upwind
//! for the smoke in flux form. Plain loops that Enzyme differentiates; the
//! kinks (the clamp, the upwind switch) are declared by the radius
//! functions here.

use super::*;
use crate::smoke::{Scheme, copy};

/// Scratch [`advect3`] needs: for MacCormack two fields of the largest
/// lattice, none for semi-Lagrangian.
pub fn advect3_scratch_len(cfg: &Smoke3d, scheme: Scheme) -> usize {
    match scheme {
        Scheme::SemiLagrangian => 0,
        Scheme::MacCormack { .. } => 2 * (0..3).map(|a| cfg.n_face(a)).max().unwrap_or(0),
    }
}

/// One field on the lattice `at` advected by `scheme` over `dt`; `hat` and
/// `tilde` are scratch of `f`'s length (MacCormack only).
#[inline(always)]
#[allow(clippy::too_many_arguments)]
fn advect_field3(mac: Mac3<[bool; 3]>, at: At3, scheme: Scheme, dt: f64, vel: [&[f64]; 3], f: &[f64], out: &mut [f64], hat: &mut [f64], tilde: &mut [f64]) {
    let nz = mac.n[2];
    match scheme {
        Scheme::SemiLagrangian => trace(mac, at, vel, f, dt, 0..nz, out),
        Scheme::MacCormack { limiter } => {
            trace(mac, at, vel, f, dt, 0..nz, hat);
            trace(mac, at, vel, hat, -dt, 0..nz, tilde);
            let lat = mac.lattice(at);
            for k in 0..lat.n[2] {
                for j in 0..lat.n[1] {
                    for i in 0..lat.n[0] {
                        let c = (k * lat.sy + j) * lat.sx + i;
                        let mut val = hat[c] + 0.5 * (f[c] - tilde[c]);
                        if limiter {
                            let [a, b, d] = mac.velocity(at, vel, [i, j, k]);
                            let p = [i as f64 + lat.o[0] - dt * a, j as f64 + lat.o[1] - dt * b, k as f64 + lat.o[2] - dt * d];
                            let (lo, hi) = sample3_range(mac.wraps(), f, lat, p);
                            val = val.clamp(lo, hi);
                        }
                        out[c] = val;
                    }
                }
            }
        }
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
pub fn advect3(cfg: &Smoke3d, scheme: Scheme, smoke: bool, velocity: bool, x: &[f64], y: &mut [f64], scratch: &mut [f64]) {
    assert!(cfg.nx.min(cfg.ny).min(cfg.nz) >= 2 && x.len() == cfg.n_state() && y.len() == cfg.n_state(), "smoke3d: state lengths");
    assert!(scratch.len() >= advect3_scratch_len(cfg, scheme), "smoke3d: advection scratch");
    let mac = cfg.mac();
    let [s, u, v, w] = cfg.split(x);
    let [s2, u2, v2, w2] = cfg.split_mut(y);
    let vel = [u, v, w];
    let half = scratch.len() / 2;
    let (hat, tilde) = scratch.split_at_mut(half);
    let len = |n: usize| n.min(half);
    if smoke {
        advect_field3(mac, At3::Centre, scheme, cfg.dt, vel, s, s2, &mut hat[..len(s.len())], &mut tilde[..len(s.len())]);
    } else {
        copy(s, s2);
    }
    if velocity {
        advect_field3(mac, At3::U, scheme, cfg.dt, vel, u, u2, &mut hat[..len(u.len())], &mut tilde[..len(u.len())]);
        advect_field3(mac, At3::V, scheme, cfg.dt, vel, v, v2, &mut hat[..len(v.len())], &mut tilde[..len(v.len())]);
        advect_field3(mac, At3::W, scheme, cfg.dt, vel, w, w2, &mut hat[..len(w.len())], &mut tilde[..len(w.len())]);
        enforce_boundary3(cfg, [u2, v2, w2]);
    } else {
        copy(u, u2);
        copy(v, v2);
        copy(w, w2);
    }
}

/// The lattices a scheme samples, with whether each is advected.
fn lattices(smoke: bool, velocity: bool) -> [(bool, At3); 4] {
    [(smoke, At3::Centre), (velocity, At3::U), (velocity, At3::V), (velocity, At3::W)]
}

/// How far `x` may move along `d` before [`advect3`] meets a sampling kink
/// (a traced point crossing a lattice plane): over the backward trace, and
/// for MacCormack also the forward one. MacCormack's limiter is
/// [`limiter3_radius`].
pub fn advect3_radius(cfg: &Smoke3d, scheme: Scheme, smoke: bool, velocity: bool, x: &[f64], d: &[f64]) -> f64 {
    let mac = cfg.mac();
    let [_, u, v, w] = cfg.split(x);
    let [_, du, dv, dw] = cfg.split(d);
    let steps: &[f64] = match scheme {
        Scheme::SemiLagrangian => &[1.0],
        Scheme::MacCormack { .. } => &[1.0, -1.0],
    };
    let mut r = f64::INFINITY;
    for &(on, at) in lattices(smoke, velocity).iter() {
        if !on {
            continue;
        }
        let lat = mac.lattice(at);
        for k in 0..lat.n[2] {
            for j in 0..lat.n[1] {
                for i in 0..lat.n[0] {
                    let q = [i, j, k];
                    // A face on a wall is set by the walls after the trace
                    // (when the velocity is advected, as it is on its lattices).
                    if set_by_boundary(cfg, at, q) {
                        continue;
                    }
                    let vel = mac.velocity(at, [u, v, w], q);
                    let dvel = mac.velocity(at, [du, dv, dw], q);
                    for &sign in steps {
                        let sdt = sign * cfg.dt;
                        for a in 0..3 {
                            r = r.min(lattice_gap(q[a] as f64 - sdt * vel[a], sdt * dvel[a]));
                        }
                    }
                }
            }
        }
    }
    r
}

/// MacCormack's value before the limiter at every point of the lattice `at`.
fn unclamped3(mac: Mac3<[bool; 3]>, at: At3, dt: f64, vel: [&[f64]; 3], f: &[f64]) -> Vec<f64> {
    let (mut hat, mut tilde) = (vec![0.0; f.len()], vec![0.0; f.len()]);
    trace(mac, at, vel, f, dt, 0..mac.n[2], &mut hat);
    trace(mac, at, vel, &hat, -dt, 0..mac.n[2], &mut tilde);
    hat.iter().zip(f).zip(&tilde).map(|((h, f), t)| h + 0.5 * (f - t)).collect()
}

/// How far `x` may move along `d` before MacCormack's limiter switches (the
/// 3D [`crate::smoke::limiter_radius`]): where an unclamped value crosses
/// the smallest or largest of its eight samples, or the bound passes from
/// one sample to another. First order, rates from a step of `1e-7`
/// relative along `d`; within [`advect3_radius`], which the caller takes too.
pub fn limiter3_radius(cfg: &Smoke3d, smoke: bool, velocity: bool, x: &[f64], d: &[f64]) -> f64 {
    let dmax = d.iter().fold(0.0f64, |m, v| m.max(v.abs()));
    if dmax == 0.0 {
        return f64::INFINITY;
    }
    let eps = 1e-7 * (1.0 + x.iter().fold(0.0f64, |m, v| m.max(v.abs()))) / dmax;
    let xe: Vec<f64> = x.iter().zip(d).map(|(a, b)| a + eps * b).collect();
    let mac = cfg.mac();
    let (fx, fd, fe) = (cfg.split(x), cfg.split(d), cfg.split(&xe));
    let (vel, vele) = ([fx[1], fx[2], fx[3]], [fe[1], fe[2], fe[3]]);
    let mut r = f64::INFINITY;
    for (field, &(on, at)) in lattices(smoke, velocity).iter().enumerate() {
        if !on {
            continue;
        }
        let (f, df) = (fx[field], fd[field]);
        let lat = mac.lattice(at);
        let val = unclamped3(mac, at, cfg.dt, vel, f);
        let vale = unclamped3(mac, at, cfg.dt, vele, fe[field]);
        for k in 0..lat.n[2] {
            for j in 0..lat.n[1] {
                for i in 0..lat.n[0] {
                    let c = (k * lat.sy + j) * lat.sx + i;
                    if set_by_boundary(cfg, at, [i, j, k]) {
                        continue;
                    }
                    let [a, b, e] = mac.velocity(at, vel, [i, j, k]);
                    let p = [i as f64 + lat.o[0] - cfg.dt * a, j as f64 + lat.o[1] - cfg.dt * b, k as f64 + lat.o[2] - cfg.dt * e];
                    let mut order = sample3_corners(mac.wraps(), lat, p);
                    order.sort_by(|&m, &n| f[m].total_cmp(&f[n]));
                    let (lo, lo2, hi2, hi) = (order[0], order[1], order[6], order[7]);
                    let rate = (vale[c] - val[c]) / eps;
                    r = r
                        .min(crate::smoke::crossing(val[c] - f[lo], rate - df[lo]))
                        .min(crate::smoke::crossing(f[hi] - val[c], df[hi] - rate))
                        .min(crate::smoke::crossing(f[lo2] - f[lo], df[lo2] - df[lo]))
                        .min(crate::smoke::crossing(f[hi] - f[hi2], df[hi] - df[hi2]));
                }
            }
        }
    }
    r
}

/// First-order upwind advection of the smoke by the MAC velocity over
/// `cfg.dt`, in flux form through every face between two cells (across
/// periodic sides too; none through the other sides): smoke is conserved. Reads `x = [s, u, v, w]`, writes
/// `y = [s', u, v, w]`.
///
/// # Panics
/// If a length is wrong.
pub fn advect_upwind3(cfg: &Smoke3d, x: &[f64], y: &mut [f64]) {
    assert!(x.len() == cfg.n_state() && y.len() == cfg.n_state(), "smoke3d: state lengths");
    copy(x, y);
    let dt = cfg.dt;
    for axis in 0..3 {
        // The component's faces in the packed state.
        let start = cfg.slab_starts(0)[1 + axis];
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
pub fn upwind3_radius(cfg: &Smoke3d, x: &[f64], d: &[f64]) -> f64 {
    let [_, u, v, w] = cfg.split(x);
    let [_, du, dv, dw] = cfg.split(d);
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
