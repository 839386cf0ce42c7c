//! Advection of the smoke and the velocity: semi-Lagrangian, MacCormack
//! (with or without limiter) and upwind, and the adjoint of P2's
//! semi-Lagrangian step with buoyancy. The traces are [`crate::mac`]'s,
//! shared with 3D.

use super::*;
use crate::mac::advect::{LimitedField, advect_field, trace, trace_adjoint, trace_parallel, traced};

/// Advection scheme.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Scheme {
    /// One backward trace, bilinear sample (first order).
    SemiLagrangian,
    /// A backward trace, a forward trace from its result, half the
    /// difference as a correction (second order). With `limiter`, each value
    /// is clamped to the range of the four samples the backward trace blended
    /// (Selle et al. 2008): no new extrema, first order at extrema.
    MacCormack {
        /// Clamp to the local range.
        limiter: bool,
    },
}

/// Advection over a time step `dt` of the smoke (if `smoke`) and of the
/// velocity by itself (if `velocity`), each sampled back along the velocity
/// at its own points (the other component averaged from the four nearest
/// faces); then the velocity boundary conditions. Fields not advected are
/// copied. Reads `x = [s, u, v]`, overwrites `y`. `scratch` holds
/// [`advect_scratch_len`] values (none for semi-Lagrangian).
///
/// # Panics
/// If a length is wrong or a side has fewer than 2 cells.
#[allow(clippy::too_many_arguments)]
pub fn advect(cfg: &MacGrid<2>, scheme: Scheme, dt: f64, smoke: bool, velocity: bool, x: &[f64], y: &mut [f64], scratch: &mut [f64]) {
    assert!(cfg.n[0].min(cfg.n[1]) >= 2 && x.len() == cfg.n_state() && y.len() == cfg.n_state(), "smoke: state lengths");
    assert!(scratch.len() >= advect_scratch_len(cfg, scheme), "smoke: advection scratch");
    with_mac!(cfg, mac => advect_on(mac, scheme, dt, smoke, velocity, x, y, scratch));
    if velocity {
        let (_, [u2, v2]) = cfg.split_mut(y);
        enforce_boundary(cfg, u2, v2);
    }
}

#[inline(always)]
#[allow(clippy::too_many_arguments)]
fn advect_on<W: Wraps<2>>(mac: Mac<2, W>, scheme: Scheme, dt: f64, smoke: bool, velocity: bool, x: &[f64], y: &mut [f64], scratch: &mut [f64]) {
    let [nx, ny] = mac.n;
    let (ns, nu) = (nx * ny, ny * (nx + 1));
    let (s, rest) = x.split_at(ns);
    let (u, v) = rest.split_at(nu);
    let (s2, rest) = y.split_at_mut(ns);
    let (u2, v2) = rest.split_at_mut(nu);
    // Each field's scratch: the first values of each half (none for
    // semi-Lagrangian).
    let half = scratch.len() / 2;
    let (hat, tilde) = scratch.split_at_mut(half);
    let (ks, ku, kv) = (ns.min(half), nu.min(half), v.len().min(half));
    if smoke {
        advect_field(mac, At::Centre, scheme, dt, [u, v], s, s2, &mut hat[..ks], &mut tilde[..ks]);
    } else {
        copy(s, s2);
    }
    if velocity {
        advect_field(mac, At::Face(0), scheme, dt, [u, v], u, u2, &mut hat[..ku], &mut tilde[..ku]);
        advect_field(mac, At::Face(1), scheme, dt, [u, v], v, v2, &mut hat[..kv], &mut tilde[..kv]);
    } else {
        copy(u, u2);
        copy(v, v2);
    }
}

/// A perturbation `d = [ds, du, dv]` of the state carried along the
/// velocity of the state `x` over `dt` (semi-Lagrangian: each field sampled
/// at its own points traced back by `dt` times `x`'s velocity there), then
/// the linear velocity boundary conditions; overwrites `out`. Linear in
/// `d`. With `dt = −1` it runs P2's advection backwards in time along the
/// step's velocity: the approximate inverse of [`advect_buoyancy`]'s
/// transport that the smoke step's local inverse uses.
///
/// # Panics
/// If a length is wrong or a side has fewer than 2 cells.
pub fn advect_along(cfg: &MacGrid<2>, dt: f64, x: &[f64], d: &[f64], out: &mut [f64]) {
    let n = cfg.n_state();
    assert!(cfg.n[0].min(cfg.n[1]) >= 2 && x.len() == n && d.len() == n && out.len() == n, "smoke: state lengths");
    let (_, [u, v]) = cfg.split(x);
    let (ds, [du, dv]) = cfg.split(d);
    let (os, [ou, ov]) = cfg.split_mut(out);
    with_mac!(cfg, mac => {
        let all = 0..cfg.n[1];
        trace(mac, At::Centre, [u, v], ds, dt, all.clone(), os);
        trace(mac, At::Face(0), [u, v], du, dt, all.clone(), ou);
        trace(mac, At::Face(1), [u, v], dv, dt, all, ov);
    });
    let (_, [u2, v2]) = cfg.split_mut(out);
    enforce_boundary_linear(cfg, u2, v2);
}

/// The lattices advected: the centres with `smoke`, the faces with `velocity`.
fn lattices(smoke: bool, velocity: bool) -> Vec<At> {
    [(smoke, At::Centre), (velocity, At::Face(0)), (velocity, At::Face(1))].into_iter().filter(|p| p.0).map(|p| p.1).collect()
}

/// How far `x` may move along `d` before [`advect`] meets a kink: bilinear
/// sampling is smooth between lattice lines and kinks where a traced point
/// crosses one (or a clamped edge). The smallest, over the traced points
/// (the backward trace, and for MacCormack also the forward one), of the
/// distance to the nearest line over the speed at which `d` moves the
/// point; ∞ when `d` moves none. MacCormack's limiter is not counted: its
/// clamp kinks wherever it engages, which no radius of this kind bounds.
#[allow(clippy::too_many_arguments)]
pub fn advect_radius(cfg: &MacGrid<2>, scheme: Scheme, dt: f64, smoke: bool, velocity: bool, x: &[f64], d: &[f64]) -> f64 {
    let (_, [u, v]) = cfg.split(x);
    let (_, [du, dv]) = cfg.split(d);
    let steps: &[f64] = match scheme {
        Scheme::SemiLagrangian => &[dt],
        Scheme::MacCormack { .. } => &[dt, -dt],
    };
    crate::mac::advect::advect_radius(cfg.mac(), &lattices(smoke, velocity), steps, &[0.0; 2], [u, v], [du, dv], |at, q| set_by_boundary(cfg, at, q))
}

/// Whether point `q` of the lattice `at` is a face on a closed or inflow
/// side: the boundary conditions set it after the trace, so where its trace
/// lands does not matter (no kink of the step).
#[inline(always)]
fn set_by_boundary(cfg: &MacGrid<2>, at: At, [k, l]: [usize; 2]) -> bool {
    let b = &cfg.boundary;
    match at {
        At::Face(0) => (k == 0 && b.lower(0).sets_faces()) || (k == cfg.n[0] && b.upper(0).sets_faces()),
        At::Face(_) => (l == 0 && b.lower(1).sets_faces()) || (l == cfg.n[1] && b.upper(1).sets_faces()),
        At::Centre => false,
    }
}

/// How far `x` may move along `d` before MacCormack's limiter switches: the
/// clamp of each value to the range of the four samples its backward trace
/// blended kinks where the unclamped value crosses a bound, and where the
/// bound passes from one sample to another. First order: the rates of the
/// unclamped values come from a step of `1e-7` relative along `d` (exact
/// for the bounds, which are samples of the field); within the sampling
/// radius of [`advect_radius`], which the caller takes too.
pub fn limiter_radius(cfg: &MacGrid<2>, dt: f64, smoke: bool, velocity: bool, x: &[f64], d: &[f64]) -> f64 {
    let dmax = d.iter().fold(0.0f64, |m, v| m.max(v.abs()));
    if dmax == 0.0 {
        return f64::INFINITY;
    }
    let eps = 1e-7 * (1.0 + x.iter().fold(0.0f64, |m, v| m.max(v.abs()))) / dmax;
    let xe: Vec<f64> = x.iter().zip(d).map(|(a, b)| a + eps * b).collect();
    let (fx, fd, fe) = (cfg.split(x), cfg.split(d), cfg.split(&xe));
    let mut fields = Vec::new();
    if smoke {
        fields.push(LimitedField { at: At::Centre, f: fx.0, df: fd.0, fe: fe.0 });
    }
    if velocity {
        for a in 0..2 {
            fields.push(LimitedField { at: At::Face(a), f: fx.1[a], df: fd.1[a], fe: fe.1[a] });
        }
    }
    crate::mac::advect::limiter_radius(cfg.mac(), &fields, dt, [fx.1, fe.1], eps, |at, q| set_by_boundary(cfg, at, q))
}

/// Scratch [`advect()`] needs: for MacCormack two fields of the largest
/// component's size (`2·max(n_u, n_v)`), none for semi-Lagrangian.
pub fn advect_scratch_len(cfg: &MacGrid<2>, scheme: Scheme) -> usize {
    match scheme {
        Scheme::SemiLagrangian => 0,
        Scheme::MacCormack { .. } => 2 * cfg.n_face(0).max(cfg.n_face(1)),
    }
}

/// Steps 1–4 of P2, for any boundary: semi-Lagrangian advection of smoke and
/// velocity (unit time step), buoyancy, the velocity boundary conditions.
/// Reads the packed state `x = [s, u, v]`, overwrites `y = [s', u', v']`
/// (the velocity not yet divergence-free).
///
/// # Panics
/// If `x` or `y` is not of length [`MacGrid<2>::n_state`] or a side has fewer
/// than 2 cells.
pub fn advect_buoyancy(cfg: &MacGrid<2>, x: &[f64], y: &mut [f64]) {
    advect(cfg, Scheme::SemiLagrangian, 1.0, true, true, x, y, &mut []);
    // Buoyancy touches no closed, inflow or outflow face and refreshes its
    // own periodic copies, so the boundary conditions of `advect` still hold.
    let (s2, [_, v2]) = cfg.split_mut(y);
    add_buoyancy(cfg, cfg.buoyancy, s2, v2);
}

/// Rows `js` of [`advect_buoyancy`]'s output in the closed box (P2),
/// packed as [`MacGrid::slab_lens`] says (`y` of their total length): each output row
/// depends on the whole input but on no other output row (the buoyancy of
/// a range's first y-face traces the smoke row below it again), so that an
/// adjoint can be taken row range by row range in parallel, then summed in
/// a fixed order. The same values as [`advect_buoyancy`], operation for
/// operation.
///
/// # Panics
/// If the box is not closed, a length is wrong, or `js` is empty or past
/// `ny`.
pub fn advect_buoyancy_rows(cfg: &MacGrid<2>, x: &[f64], js: std::ops::Range<usize>, y: &mut [f64]) {
    let (n, ny) = (cfg.n[0], cfg.n[1]);
    let (ls, [lu, _]) = cfg.slab_lens(js.clone());
    assert!(cfg.is_closed() && n.min(ny) >= 2 && x.len() == cfg.n_state() && y.len() == cfg.slabs_len(js.clone()), "smoke: rows of the closed box's step");
    assert!(js.start < js.end && js.end <= ny, "smoke: rows {js:?} of {ny}");
    let mac = Mac::bounded([n, ny]);
    let (s, [u, v]) = cfg.split(x);
    let (s2, rest) = y.split_at_mut(ls);
    let (u2, v2) = rest.split_at_mut(lu);
    let j0 = js.start;
    // One call per field (a loop over an array of (lattice, slice) pairs
    // trips Enzyme, docs/pitfalls.md).
    trace(mac, At::Centre, [u, v], s, 1.0, js.clone(), s2);
    trace(mac, At::Face(0), [u, v], u, 1.0, js.clone(), u2);
    trace(mac, At::Face(1), [u, v], v, 1.0, js.clone(), v2);
    // The closed walls (indexed stores: a fill is a memset Enzyme cannot type).
    for r in 0..js.len() {
        u2[r * (n + 1)] = 0.0;
        u2[r * (n + 1) + n] = 0.0;
    }
    for i in 0..n {
        if j0 == 0 {
            v2[i] = 0.0;
        }
        if js.end == ny {
            v2[js.len() * n + i] = 0.0;
        }
    }
    // Buoyancy on the interior y-faces of the range.
    let centre = mac.lattice(At::Centre);
    for l in j0.max(1)..js.end {
        for i in 0..n {
            let below = if l > j0 { s2[(l - 1 - j0) * n + i] } else { traced(mac, At::Centre, &centre, [u, v], s, 1.0, [i, l - 1]) };
            v2[(l - j0) * n + i] += cfg.buoyancy * 0.5 * (below + s2[(l - j0) * n + i]);
        }
    }
}

/// [`advect_buoyancy`] with each lattice's rows split over threads
/// ([`crate::par`]): the same values for any thread count. Not for
/// differentiated code (Enzyme differentiates [`advect_buoyancy`]).
///
/// # Panics
/// As [`advect_buoyancy`].
pub fn advect_buoyancy_parallel(cfg: &MacGrid<2>, x: &[f64], y: &mut [f64]) {
    assert!(cfg.n[0].min(cfg.n[1]) >= 2 && x.len() == cfg.n_state() && y.len() == cfg.n_state(), "smoke: state lengths");
    with_mac!(cfg, mac => {
        let (s, [u, v]) = cfg.split(x);
        let (s2, [u2, v2]) = cfg.split_mut(y);
        trace_parallel(mac, At::Centre, [u, v], s, 1.0, s2);
        trace_parallel(mac, At::Face(0), [u, v], u, 1.0, u2);
        trace_parallel(mac, At::Face(1), [u, v], v, 1.0, v2);
    });
    let (_, [u2, v2]) = cfg.split_mut(y);
    enforce_boundary(cfg, u2, v2);
    let (s2, [_, v2]) = cfg.split_mut(y);
    add_buoyancy(cfg, cfg.buoyancy, s2, v2);
}

/// Hand-written adjoint of [`advect_buoyancy`]: `gx += Jᵀ·gy` at the state
/// `x` (accumulates into `gx`; `gy` is used as scratch and left
/// unspecified). The reference for Enzyme's generated adjoint.
pub fn advect_buoyancy_adjoint(cfg: &MacGrid<2>, x: &[f64], gy: &mut [f64], gx: &mut [f64]) {
    let (n, ny) = (cfg.n[0], cfg.n[1]);
    assert!(n.min(ny) >= 2 && x.len() == cfg.n_state() && gy.len() == cfg.n_state() && gx.len() == cfg.n_state(), "smoke: state lengths");
    let (s, [u, v]) = cfg.split(x);
    let (gs2, [gu2, gv2]) = cfg.split_mut(gy);
    let (gs, [gu, gv]) = cfg.split_mut(gx);
    // Buoyancy (its own periodic copy came after its addition).
    if cfg.boundary.periodic(1) {
        for i in 0..n {
            gv2[i] += gv2[ny * n + i];
            gv2[ny * n + i] = 0.0;
            let b = cfg.buoyancy * 0.5 * gv2[i];
            gs2[(ny - 1) * n + i] += b;
            gs2[i] += b;
        }
    }
    for j in 1..ny {
        for i in 0..n {
            let b = cfg.buoyancy * 0.5 * gv2[j * n + i];
            gs2[(j - 1) * n + i] += b;
            gs2[j * n + i] += b;
        }
    }
    enforce_boundary_adjoint(cfg, gu2, gv2);
    // The traces in reverse: y-faces, x-faces, centres.
    with_mac!(cfg, mac => {
        let mut gvel = [&mut *gu, &mut *gv];
        trace_adjoint(mac, At::Face(1), [u, v], v, 1.0, gv2, None, &mut gvel);
        trace_adjoint(mac, At::Face(0), [u, v], u, 1.0, gu2, None, &mut gvel);
        trace_adjoint(mac, At::Centre, [u, v], s, 1.0, gs2, Some(&mut *gs), &mut gvel);
    });
}

/// First-order upwind advection of the smoke by the MAC velocity, in
/// conservative (flux) form over one time step `dt`: through every interior
/// face, across periodic sides, and through inflow and outflow sides (with
/// smoke-free fluid outside); none through closed sides. Reads
/// `x = [s, u, v]`, writes `y = [s', u, v]`.
pub fn advect_upwind(cfg: &MacGrid<2>, dt: f64, x: &[f64], y: &mut [f64]) {
    let (n, ny) = (cfg.n[0], cfg.n[1]);
    assert!(n.min(ny) >= 2 && x.len() == cfg.n_state() && y.len() == cfg.n_state(), "smoke: state lengths");
    let (s, [u, v]) = cfg.split(x);
    let nu = n + 1;
    let (s2, rest) = y.split_at_mut(cfg.n_s());
    copy(s, s2);
    // Interior x-faces: flux from cell (i−1, j) to (i, j).
    for j in 0..ny {
        for i in 1..n {
            upwind_flux(s, s2, dt * u[j * nu + i], Some(j * n + i - 1), Some(j * n + i));
        }
    }
    // Interior y-faces: flux from cell (i, j−1) to (i, j).
    for j in 1..ny {
        for i in 0..n {
            upwind_flux(s, s2, dt * v[j * n + i], Some((j - 1) * n + i), Some(j * n + i));
        }
    }
    // The sides: wrap, or exchange with the smoke-free outside.
    let b = &cfg.boundary;
    for k in 0..ny {
        match b.lower(0) {
            Side::Periodic => upwind_flux(s, s2, dt * u[k * nu], Some(k * n + n - 1), Some(k * n)),
            Side::Inflow(_) | Side::Outflow => upwind_flux(s, s2, dt * u[k * nu], None, Some(k * n)),
            Side::Closed => {}
        }
        if let Side::Inflow(_) | Side::Outflow = b.upper(0) {
            upwind_flux(s, s2, dt * u[k * nu + n], Some(k * n + n - 1), None);
        }
    }
    for k in 0..n {
        match b.lower(1) {
            Side::Periodic => upwind_flux(s, s2, dt * v[k], Some((ny - 1) * n + k), Some(k)),
            Side::Inflow(_) | Side::Outflow => upwind_flux(s, s2, dt * v[k], None, Some(k)),
            Side::Closed => {}
        }
        if let Side::Inflow(_) | Side::Outflow = b.upper(1) {
            upwind_flux(s, s2, dt * v[ny * n + k], Some((ny - 1) * n + k), None);
        }
    }
    copy(&x[cfg.n_s()..], rest);
}

/// The upwind flux `c·s_upwind` (`c` = velocity·dt) from cell `lower` to
/// cell `upper` (`None`: outside, where the smoke is 0).
#[inline(always)]
fn upwind_flux(s: &[f64], s2: &mut [f64], c: f64, lower: Option<usize>, upper: Option<usize>) {
    let from = if c > 0.0 { lower } else { upper };
    let f = c * from.map_or(0.0, |k| s[k]);
    if let Some(k) = lower {
        s2[k] -= f;
    }
    if let Some(k) = upper {
        s2[k] += f;
    }
}

/// Distance to the nearest upwind switch of [`advect_upwind`] along `d`: the
/// smallest `|u_f / d_f|` over the faces that carry flux.
pub fn upwind_radius(cfg: &MacGrid<2>, x: &[f64], d: &[f64]) -> f64 {
    let (_, [u, v]) = cfg.split(x);
    let (_, [du, dv]) = cfg.split(d);
    let mut r = f64::INFINITY;
    for (axis, (vel, dvel)) in [(u, du), (v, dv)].into_iter().enumerate() {
        for_each_face(cfg.n[0], cfg.n[1], &cfg.boundary, axis, |f| {
            if f.side != Some(Side::Closed) && dvel[f.index] != 0.0 {
                r = r.min((vel[f.index] / dvel[f.index]).abs());
            }
        });
    }
    r
}
