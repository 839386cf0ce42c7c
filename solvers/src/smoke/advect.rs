//! Advection of the smoke and the velocity: semi-Lagrangian, MacCormack
//! (with or without limiter) and upwind, and the adjoint of P2's
//! semi-Lagrangian step with buoyancy.

use super::*;

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

/// Points of a lattice traced along the velocity `(u, v)`: `out[l·stride + k]
/// = f(p − sdt·vel)` for `k < kx`, `l < ly`, `p` the point of sample
/// `(k, l)` of the lattice `at` and `vel` the velocity there. (The velocity
/// is looked up by an enum, not a closure: Enzyme cannot type a closure's
/// returned pair when the closure is not inlined.)
#[inline(always)]
#[allow(clippy::too_many_arguments)]
fn trace<const WX: bool, const WY: bool>(mac: Mac<WX, WY>, at: At, uv: (&[f64], &[f64]), f: &[f64], sdt: f64, out: &mut [f64]) {
    let (lat, kx, ly) = mac.lattice(at);
    for l in 0..ly {
        for k in 0..kx {
            out[l * lat.stride + k] = traced(mac, at, lat, uv, f, sdt, k, l);
        }
    }
}

/// [`trace`] with blocks of rows split over threads (the same values). The
/// serial loop stays as it is: Enzyme differentiates it.
fn trace_parallel<const WX: bool, const WY: bool>(mac: Mac<WX, WY>, at: At, uv: (&[f64], &[f64]), f: &[f64], sdt: f64, out: &mut [f64]) {
    let (lat, kx, ly) = mac.lattice(at);
    let rows = crate::par::rows_per_piece(lat.stride);
    crate::par::for_pieces(out, rows * lat.stride, |b, o| {
        let l0 = b * rows;
        for l in l0..(l0 + o.len() / lat.stride).min(ly) {
            for k in 0..kx {
                o[(l - l0) * lat.stride + k] = traced(mac, at, lat, uv, f, sdt, k, l);
            }
        }
    });
}

/// The value traced back to sample `(k, l)` of the lattice `at`.
#[inline(always)]
#[allow(clippy::too_many_arguments)]
fn traced<const WX: bool, const WY: bool>(mac: Mac<WX, WY>, at: At, lat: Lattice, (u, v): (&[f64], &[f64]), f: &[f64], sdt: f64, k: usize, l: usize) -> f64 {
    let (a, b) = mac.velocity(at, u, v, k, l);
    sample::<WX, WY>(f, lat, k as f64 + lat.ox - sdt * a, l as f64 + lat.oy - sdt * b)
}

/// One field on the lattice `at` advected by `scheme`; `hat` and `tilde`
/// are scratch of `f`'s length (MacCormack only).
#[inline(always)]
#[allow(clippy::too_many_arguments)]
fn advect_field<const WX: bool, const WY: bool>(
    mac: Mac<WX, WY>,
    at: At,
    scheme: Scheme,
    dt: f64,
    uv: (&[f64], &[f64]),
    f: &[f64],
    out: &mut [f64],
    hat: &mut [f64],
    tilde: &mut [f64],
) {
    match scheme {
        Scheme::SemiLagrangian => trace(mac, at, uv, f, dt, out),
        Scheme::MacCormack { limiter } => {
            trace(mac, at, uv, f, dt, hat);
            trace(mac, at, uv, hat, -dt, tilde);
            let (lat, kx, ly) = mac.lattice(at);
            for l in 0..ly {
                for k in 0..kx {
                    let c = l * lat.stride + k;
                    let mut val = hat[c] + 0.5 * (f[c] - tilde[c]);
                    if limiter {
                        let (a, b) = mac.velocity(at, uv.0, uv.1, k, l);
                        let (lo, hi) = sample_range::<WX, WY>(f, lat, k as f64 + lat.ox - dt * a, l as f64 + lat.oy - dt * b);
                        val = val.clamp(lo, hi);
                    }
                    out[c] = val;
                }
            }
        }
    }
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
pub fn advect(cfg: &Smoke2d, scheme: Scheme, dt: f64, smoke: bool, velocity: bool, x: &[f64], y: &mut [f64], scratch: &mut [f64]) {
    assert!(cfg.nx.min(cfg.ny) >= 2 && x.len() == cfg.n_state() && y.len() == cfg.n_state(), "smoke: state lengths");
    assert!(scratch.len() >= advect_scratch_len(cfg, scheme), "smoke: advection scratch");
    with_mac!(cfg, mac => advect_on(mac, scheme, dt, smoke, velocity, x, y, scratch));
    if velocity {
        let (_, u2, v2) = cfg.split_mut(y);
        enforce_boundary(cfg, u2, v2);
    }
}

#[inline(always)]
#[allow(clippy::too_many_arguments)]
fn advect_on<const WX: bool, const WY: bool>(
    mac: Mac<WX, WY>,
    scheme: Scheme,
    dt: f64,
    smoke: bool,
    velocity: bool,
    x: &[f64],
    y: &mut [f64],
    scratch: &mut [f64],
) {
    let (ns, nu) = (mac.nx * mac.ny, mac.ny * (mac.nx + 1));
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
        advect_field(mac, At::Centre, scheme, dt, (u, v), s, s2, &mut hat[..ks], &mut tilde[..ks]);
    } else {
        copy(s, s2);
    }
    if velocity {
        advect_field(mac, At::UFace, scheme, dt, (u, v), u, u2, &mut hat[..ku], &mut tilde[..ku]);
        advect_field(mac, At::VFace, scheme, dt, (u, v), v, v2, &mut hat[..kv], &mut tilde[..kv]);
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
pub fn advect_along(cfg: &Smoke2d, dt: f64, x: &[f64], d: &[f64], out: &mut [f64]) {
    let n = cfg.n_state();
    assert!(cfg.nx.min(cfg.ny) >= 2 && x.len() == n && d.len() == n && out.len() == n, "smoke: state lengths");
    with_mac!(cfg, mac => advect_along_on(mac, dt, x, d, out));
    let (_, u2, v2) = cfg.split_mut(out);
    enforce_boundary_linear(cfg, u2, v2);
}

fn advect_along_on<const WX: bool, const WY: bool>(mac: Mac<WX, WY>, dt: f64, x: &[f64], d: &[f64], out: &mut [f64]) {
    let (ns, nu) = (mac.nx * mac.ny, mac.ny * (mac.nx + 1));
    let (u, v) = x[ns..].split_at(nu);
    let (ds, rest) = d.split_at(ns);
    let (du, dv) = rest.split_at(nu);
    let (os, rest) = out.split_at_mut(ns);
    let (ou, ov) = rest.split_at_mut(nu);
    trace(mac, At::Centre, (u, v), ds, dt, os);
    trace(mac, At::UFace, (u, v), du, dt, ou);
    trace(mac, At::VFace, (u, v), dv, dt, ov);
}

/// How far `x` may move along `d` before [`advect`] meets a kink: bilinear
/// sampling is smooth between lattice lines and kinks where a traced point
/// crosses one (or a clamped edge). The smallest, over the traced points
/// (the backward trace, and for MacCormack also the forward one), of the
/// distance to the nearest line over the speed at which `d` moves the
/// point; ∞ when `d` moves none. MacCormack's limiter is not counted: its
/// clamp kinks wherever it engages, which no radius of this kind bounds.
#[allow(clippy::too_many_arguments)]
pub fn advect_radius(cfg: &Smoke2d, scheme: Scheme, dt: f64, smoke: bool, velocity: bool, x: &[f64], d: &[f64]) -> f64 {
    let (_, u, v) = cfg.split(x);
    let (_, du, dv) = cfg.split(d);
    with_mac!(cfg, mac => {
        let mut r = f64::INFINITY;
        let steps: &[f64] = match scheme {
            Scheme::SemiLagrangian => &[dt],
            Scheme::MacCormack { .. } => &[dt, -dt],
        };
        let lattices = [(smoke, At::Centre), (velocity, At::UFace), (velocity, At::VFace)];
        for &(on, at) in lattices.iter() {
            if !on {
                continue;
            }
            let (_, kx, ly) = mac.lattice(at);
            for l in 0..ly {
                for k in 0..kx {
                    if set_by_boundary(cfg, at, k, l) {
                        continue;
                    }
                    let (a, b) = mac.velocity(at, u, v, k, l);
                    let (da, db) = mac.velocity(at, du, dv, k, l);
                    for &sdt in steps {
                        r = r.min(lattice_gap(k as f64 - sdt * a, sdt * da)).min(lattice_gap(l as f64 - sdt * b, sdt * db));
                    }
                }
            }
        }
        r
    })
}

/// Whether sample `(k, l)` of the lattice `at` is a face on a closed or
/// inflow side: the boundary conditions set it after the trace, so where
/// its trace lands does not matter (no kink of the step).
#[inline(always)]
fn set_by_boundary(cfg: &Smoke2d, at: At, k: usize, l: usize) -> bool {
    let b = &cfg.boundary;
    match at {
        At::UFace => (k == 0 && b.left.sets_faces()) || (k == cfg.nx && b.right.sets_faces()),
        At::VFace => (l == 0 && b.bottom.sets_faces()) || (l == cfg.ny && b.top.sets_faces()),
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
pub fn limiter_radius(cfg: &Smoke2d, dt: f64, smoke: bool, velocity: bool, x: &[f64], d: &[f64]) -> f64 {
    let dmax = d.iter().fold(0.0f64, |m, v| m.max(v.abs()));
    if dmax == 0.0 {
        return f64::INFINITY;
    }
    let eps = 1e-7 * (1.0 + x.iter().fold(0.0f64, |m, v| m.max(v.abs()))) / dmax;
    let xe: Vec<f64> = x.iter().zip(d).map(|(a, b)| a + eps * b).collect();
    with_mac!(cfg, mac => limiter_on(cfg, mac, dt, smoke, velocity, [cfg.split(x), cfg.split(d), cfg.split(&xe)], eps))
}

type Fields<'a> = (&'a [f64], &'a [f64], &'a [f64]);

/// [`limiter_radius`] on one MAC grid: `[x, d, x + eps·d]` split.
#[allow(clippy::too_many_arguments)]
fn limiter_on<const WX: bool, const WY: bool>(
    cfg: &Smoke2d,
    mac: Mac<WX, WY>,
    dt: f64,
    smoke: bool,
    velocity: bool,
    [x, d, xe]: [Fields<'_>; 3],
    eps: f64,
) -> f64 {
    let mut r = f64::INFINITY;
    // (One lattice at a time: the fields and their tangents by match, not a table.)
    for at in [At::Centre, At::UFace, At::VFace] {
        let (f, df, fe) = match at {
            At::Centre if smoke => (x.0, d.0, xe.0),
            At::UFace if velocity => (x.1, d.1, xe.1),
            At::VFace if velocity => (x.2, d.2, xe.2),
            _ => continue,
        };
        let (lat, kx, ly) = mac.lattice(at);
        let val = unclamped(mac, at, dt, (x.1, x.2), f);
        let vale = unclamped(mac, at, dt, (xe.1, xe.2), fe);
        for l in 0..ly {
            for k in 0..kx {
                if set_by_boundary(cfg, at, k, l) {
                    continue;
                }
                let c = l * lat.stride + k;
                let (a, b) = mac.velocity(at, x.1, x.2, k, l);
                let (idx, _, _) = corners::<WX, WY>(lat, k as f64 + lat.ox - dt * a, l as f64 + lat.oy - dt * b);
                let rate = (vale[c] - val[c]) / eps;
                // The bounds: the smallest and largest sample, and the runner-up of each.
                let mut order = idx;
                order.sort_by(|&i, &j| f[i].total_cmp(&f[j]));
                let (lo, lo2, hi2, hi) = (order[0], order[1], order[2], order[3]);
                r = r
                    .min(crossing(val[c] - f[lo], rate - df[lo]))
                    .min(crossing(f[hi] - val[c], df[hi] - rate))
                    .min(crossing(f[lo2] - f[lo], df[lo2] - df[lo]))
                    .min(crossing(f[hi] - f[hi2], df[hi] - df[hi2]));
            }
        }
    }
    r
}

/// When a gap closing at `speed` reaches zero (∞ when it opens or stays;
/// 0 when it is closed and about to open).
pub(crate) fn crossing(gap: f64, speed: f64) -> f64 {
    if gap == 0.0 {
        if speed == 0.0 { f64::INFINITY } else { 0.0 }
    } else if gap * speed < 0.0 {
        gap.abs() / speed.abs()
    } else {
        f64::INFINITY
    }
}

/// MacCormack's value before the limiter at every point of the lattice `at`.
#[inline(always)]
fn unclamped<const WX: bool, const WY: bool>(mac: Mac<WX, WY>, at: At, dt: f64, uv: (&[f64], &[f64]), f: &[f64]) -> Vec<f64> {
    let (mut hat, mut tilde) = (vec![0.0; f.len()], vec![0.0; f.len()]);
    trace(mac, at, uv, f, dt, &mut hat);
    trace(mac, at, uv, &hat, -dt, &mut tilde);
    hat.iter().zip(f).zip(&tilde).map(|((h, f), t)| h + 0.5 * (f - t)).collect()
}

/// Scratch [`advect()`] needs: for MacCormack two fields of the largest
/// component's size (`2·max(n_u, n_v)`), none for semi-Lagrangian.
pub fn advect_scratch_len(cfg: &Smoke2d, scheme: Scheme) -> usize {
    match scheme {
        Scheme::SemiLagrangian => 0,
        Scheme::MacCormack { .. } => 2 * cfg.n_u().max(cfg.n_v()),
    }
}

/// Steps 1–4 of P2, for any boundary: semi-Lagrangian advection of smoke and
/// velocity (unit time step), buoyancy, the velocity boundary conditions.
/// Reads the packed state `x = [s, u, v]`, overwrites `y = [s', u', v']`
/// (the velocity not yet divergence-free).
///
/// # Panics
/// If `x` or `y` is not of length [`Smoke2d::n_state`] or a side has fewer
/// than 2 cells.
pub fn advect_buoyancy(cfg: &Smoke2d, x: &[f64], y: &mut [f64]) {
    advect(cfg, Scheme::SemiLagrangian, 1.0, true, true, x, y, &mut []);
    // Buoyancy touches no closed, inflow or outflow face and refreshes its
    // own periodic copies, so the boundary conditions of `advect` still hold.
    let (s2, _, v2) = cfg.split_mut(y);
    add_buoyancy(cfg, cfg.buoyancy, s2, v2);
}

/// Rows `rows` of the lattice `at` traced back over a unit step into `out`,
/// whose first row is row `j0`.
#[inline(always)]
#[allow(clippy::too_many_arguments)]
fn trace_rows(mac: Mac<false, false>, at: At, uv: (&[f64], &[f64]), f: &[f64], rows: std::ops::Range<usize>, j0: usize, out: &mut [f64]) {
    let (lat, kx, _) = mac.lattice(at);
    for l in rows {
        for k in 0..kx {
            out[(l - j0) * lat.stride + k] = traced(mac, at, lat, uv, f, 1.0, k, l);
        }
    }
}

/// Lengths of rows `js` of `[s, u, v]` in the closed box (P2): `js.len()`
/// rows of each field, and for `v` also its top row when `js` reaches it.
/// Over `0..ny`, the packed state.
pub fn row_lens(cfg: &Smoke2d, js: std::ops::Range<usize>) -> [usize; 3] {
    let (n, m) = (cfg.nx, js.len());
    [m * n, m * (n + 1), (m + (js.end == cfg.ny) as usize) * n]
}

/// Where row `j` of each field starts in the packed state.
pub fn row_starts(cfg: &Smoke2d, j: usize) -> [usize; 3] {
    let n = cfg.nx;
    [j * n, cfg.n_s() + j * (n + 1), cfg.n_s() + cfg.n_u() + j * n]
}

/// Rows `js` of [`advect_buoyancy`]'s output in the closed box (P2),
/// packed as [`row_lens`] says (`y` of their total length): each output row
/// depends on the whole input but on no other output row (the buoyancy of
/// a range's first y-face traces the smoke row below it again), so that an
/// adjoint can be taken row range by row range in parallel, then summed in
/// a fixed order. The same values as [`advect_buoyancy`], operation for
/// operation.
///
/// # Panics
/// If the box is not closed, a length is wrong, or `js` is empty or past
/// `ny`.
pub fn advect_buoyancy_rows(cfg: &Smoke2d, x: &[f64], js: std::ops::Range<usize>, y: &mut [f64]) {
    let (n, ny) = (cfg.nx, cfg.ny);
    let lens = row_lens(cfg, js.clone());
    assert!(
        cfg.boundary == Boundary::CLOSED && n.min(ny) >= 2 && x.len() == cfg.n_state() && y.len() == lens.iter().sum::<usize>(),
        "smoke: rows of the closed box's step"
    );
    assert!(js.start < js.end && js.end <= ny, "smoke: rows {js:?} of {ny}");
    let mac = Mac::<false, false> { nx: n, ny };
    let (s, u, v) = cfg.split(x);
    let (s2, rest) = y.split_at_mut(lens[0]);
    let (u2, v2) = rest.split_at_mut(lens[1]);
    let uv = (u, v);
    let j0 = js.start;
    let v_end = js.end + (js.end == ny) as usize;
    // One call per field (a loop over an array of (lattice, slice) pairs
    // trips Enzyme, docs/pitfalls.md).
    trace_rows(mac, At::Centre, uv, s, j0..js.end, j0, s2);
    trace_rows(mac, At::UFace, uv, u, j0..js.end, j0, u2);
    trace_rows(mac, At::VFace, uv, v, j0..v_end, j0, v2);
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
    let (centre, _, _) = mac.lattice(At::Centre);
    for l in j0.max(1)..js.end {
        for i in 0..n {
            let below = if l > j0 { s2[(l - 1 - j0) * n + i] } else { traced(mac, At::Centre, centre, uv, s, 1.0, i, l - 1) };
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
pub fn advect_buoyancy_parallel(cfg: &Smoke2d, x: &[f64], y: &mut [f64]) {
    assert!(cfg.nx.min(cfg.ny) >= 2 && x.len() == cfg.n_state() && y.len() == cfg.n_state(), "smoke: state lengths");
    with_mac!(cfg, mac => {
        let (s, u, v) = cfg.split(x);
        let (s2, u2, v2) = cfg.split_mut(y);
        trace_parallel(mac, At::Centre, (u, v), s, 1.0, s2);
        trace_parallel(mac, At::UFace, (u, v), u, 1.0, u2);
        trace_parallel(mac, At::VFace, (u, v), v, 1.0, v2);
    });
    let (_, u2, v2) = cfg.split_mut(y);
    enforce_boundary(cfg, u2, v2);
    let (s2, _, v2) = cfg.split_mut(y);
    add_buoyancy(cfg, cfg.buoyancy, s2, v2);
}

/// Hand-written adjoint of [`advect_buoyancy`]: `gx += Jᵀ·gy` at the state
/// `x` (accumulates into `gx`; `gy` is used as scratch and left
/// unspecified). The reference for Enzyme's generated adjoint.
pub fn advect_buoyancy_adjoint(cfg: &Smoke2d, x: &[f64], gy: &mut [f64], gx: &mut [f64]) {
    let (n, ny) = (cfg.nx, cfg.ny);
    assert!(n.min(ny) >= 2 && x.len() == cfg.n_state() && gy.len() == cfg.n_state() && gx.len() == cfg.n_state(), "smoke: state lengths");
    let (s, u, v) = cfg.split(x);
    let (gs2, gu2, gv2) = cfg.split_mut(gy);
    let (gs, gu, gv) = cfg.split_mut(gx);
    // Buoyancy (its own periodic copy came after its addition).
    if cfg.boundary.periodic_y() {
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
    with_mac!(cfg, mac => semi_lagrangian_adjoint(mac, s, u, v, gs2, gu2, gv2, gs, gu, gv));
}

/// Adjoint of the semi-Lagrangian advection of smoke and velocity (unit
/// time step): adds `Jᵀ·g₂` into `(gs, gu, gv)`.
#[allow(clippy::too_many_arguments)]
fn semi_lagrangian_adjoint<const WX: bool, const WY: bool>(
    mac: Mac<WX, WY>,
    s: &[f64],
    u: &[f64],
    v: &[f64],
    gs2: &[f64],
    gu2: &[f64],
    gv2: &[f64],
    gs: &mut [f64],
    gu: &mut [f64],
    gv: &mut [f64],
) {
    let (n, ny) = (mac.nx, mac.ny);
    for j in 0..mac.nfy() {
        for i in 0..n {
            let (ub, vv) = mac.at_v(u, v, i, j);
            let (dpx, dpy) = sample_adjoint::<WX, WY>(v, gv, mac.v(), i as f64 + 0.5 - ub, j as f64 - vv, gv2[j * n + i]);
            mac.at_v_adjoint(gu, gv, i, j, (-dpx, -dpy));
        }
    }
    for j in 0..ny {
        for i in 0..mac.nfx() {
            let (uu, vb) = mac.at_u(u, v, i, j);
            let (dpx, dpy) = sample_adjoint::<WX, WY>(u, gu, mac.u(), i as f64 - uu, j as f64 + 0.5 - vb, gu2[j * (n + 1) + i]);
            mac.at_u_adjoint(gu, gv, i, j, (-dpx, -dpy));
        }
    }
    for j in 0..ny {
        for i in 0..n {
            let (uc, vc) = mac.at_centre(u, v, i, j);
            let (dpx, dpy) = sample_adjoint::<WX, WY>(s, gs, mac.smoke(), i as f64 + 0.5 - uc, j as f64 + 0.5 - vc, gs2[j * n + i]);
            mac.at_centre_adjoint(gu, gv, i, j, (-dpx, -dpy));
        }
    }
}

/// First-order upwind advection of the smoke by the MAC velocity, in
/// conservative (flux) form over one time step `dt`: through every interior
/// face, across periodic sides, and through inflow and outflow sides (with
/// smoke-free fluid outside); none through closed sides. Reads
/// `x = [s, u, v]`, writes `y = [s', u, v]`.
pub fn advect_upwind(cfg: &Smoke2d, dt: f64, x: &[f64], y: &mut [f64]) {
    let (n, ny) = (cfg.nx, cfg.ny);
    assert!(n.min(ny) >= 2 && x.len() == cfg.n_state() && y.len() == cfg.n_state(), "smoke: state lengths");
    let (s, u, v) = cfg.split(x);
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
        match b.left {
            Side::Periodic => upwind_flux(s, s2, dt * u[k * nu], Some(k * n + n - 1), Some(k * n)),
            Side::Inflow(_) | Side::Outflow => upwind_flux(s, s2, dt * u[k * nu], None, Some(k * n)),
            Side::Closed => {}
        }
        if let Side::Inflow(_) | Side::Outflow = b.right {
            upwind_flux(s, s2, dt * u[k * nu + n], Some(k * n + n - 1), None);
        }
    }
    for k in 0..n {
        match b.bottom {
            Side::Periodic => upwind_flux(s, s2, dt * v[k], Some((ny - 1) * n + k), Some(k)),
            Side::Inflow(_) | Side::Outflow => upwind_flux(s, s2, dt * v[k], None, Some(k)),
            Side::Closed => {}
        }
        if let Side::Inflow(_) | Side::Outflow = b.top {
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
pub fn upwind_radius(cfg: &Smoke2d, x: &[f64], d: &[f64]) -> f64 {
    let (_, u, v) = cfg.split(x);
    let (_, du, dv) = cfg.split(d);
    let mut r = f64::INFINITY;
    for (axis, (vel, dvel)) in [(u, du), (v, dv)].into_iter().enumerate() {
        for_each_face(cfg.nx, cfg.ny, &cfg.boundary, axis, |f| {
            if f.side != Some(Side::Closed) && dvel[f.index] != 0.0 {
                r = r.min((vel[f.index] / dvel[f.index]).abs());
            }
        });
    }
    r
}
