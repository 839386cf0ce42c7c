//! Semi-Lagrangian and MacCormack advection of one field on one lattice of
//! the MAC grid, in any dimension, and the semi-Lagrangian adjoint: the
//! traces every 2D and 3D advection step is made of.
//!
//! The loops run slab by slab (layers along the slowest axis), row by row
//! within a slab and along x within a row, so that a range of slabs can be
//! computed alone (the parallel forward pass, and the adjoint taken over
//! slab ranges).

use std::ops::Range;

use super::*;
use crate::smoke::Scheme;

/// Points of the lattice `at` traced back along the velocity: `out[q] =
/// f(q − dt·vel(q))` for every point `q` holding its own value in slabs
/// `ks` (and the lattice's slabs past the last cell when `ks` reaches it:
/// the top faces of the slowest axis), `out` holding those slabs.
#[inline(always)]
pub(crate) fn trace<const D: usize, W: Wraps<D>>(mac: Mac<D, W>, at: At, vel: [&[f64]; D], f: &[f64], dt: f64, ks: Range<usize>, out: &mut [f64]) {
    let end = if ks.end == mac.n[D - 1] { mac.lattice(at).n[D - 1] } else { ks.end };
    trace_block(mac, at, vel, f, dt, ks.start..end, out)
}

/// [`trace`] over the whole lattice with blocks of slabs split over
/// threads (the same values). The serial trace stays unsliced: Enzyme
/// differentiates it, and slicing the output per slab there trips its
/// reverse pass (docs/enzyme.md).
pub(crate) fn trace_parallel<const D: usize, W: Wraps<D>>(mac: Mac<D, W>, at: At, vel: [&[f64]; D], f: &[f64], dt: f64, out: &mut [f64]) {
    let lat = mac.lattice(at);
    let slab = lat.stride[D - 1];
    let per = crate::par::rows_per_piece(slab);
    // One arm per kind of lattice, so that each piece's loop is compiled
    // for a known lattice, as the serial loop is where it is inlined.
    crate::par::for_pieces(&mut out[..lat.n[D - 1] * slab], per * slab, move |b, o| {
        let ks = b * per..(b * per + o.len() / slab).min(lat.n[D - 1]);
        match at {
            At::Centre => trace_block(mac, At::Centre, vel, f, dt, ks, o),
            At::Face(0) => trace_block(mac, At::Face(0), vel, f, dt, ks, o),
            At::Face(1) => trace_block(mac, At::Face(1), vel, f, dt, ks, o),
            At::Face(2) => trace_block(mac, At::Face(2), vel, f, dt, ks, o),
            At::Face(a) => trace_block(mac, At::Face(a), vel, f, dt, ks, o),
        }
    });
}

/// Lattice slabs `ks` traced into `o` (those slabs of the lattice's array):
/// the loop of [`trace`] and of each piece of [`trace_parallel`].
#[inline(always)]
fn trace_block<const D: usize, W: Wraps<D>>(mac: Mac<D, W>, at: At, vel: [&[f64]; D], f: &[f64], dt: f64, ks: Range<usize>, o: &mut [f64]) {
    let lat = mac.lattice(at);
    let base = ks.start * lat.stride[D - 1];
    for k in ks {
        for r in 0..lat.rows_per_slab() {
            let mut q = lat.row_start(k, r);
            let row = lat.index(q) - base;
            for i in 0..lat.n[0] {
                q[0] = i;
                o[row + i] = traced(mac, at, &lat, vel, f, dt, q);
            }
        }
    }
}

/// The value traced back to point `q` of the lattice `at`.
#[inline(always)]
pub(crate) fn traced<const D: usize, W: Wraps<D>>(mac: Mac<D, W>, at: At, lat: &Lattice<D>, vel: [&[f64]; D], f: &[f64], dt: f64, q: [usize; D]) -> f64 {
    let v = mac.velocity(at, vel, q);
    sample(mac.wraps(), f, lat, Mac::<D, W>::back(lat, q, v, dt))
}

/// Adjoint of [`trace`] over the whole lattice at time step `dt`: adds
/// `Jᵀ·g` into the velocity's adjoint `gvel` and the traced field's: `gs`
/// for the centres, else the component's own entry of `gvel` (a velocity
/// component is both the field sampled and one of the velocities that
/// trace it).
#[inline(always)]
#[allow(clippy::too_many_arguments)]
pub(crate) fn trace_adjoint<const D: usize, W: Wraps<D>>(
    mac: Mac<D, W>,
    at: At,
    vel: [&[f64]; D],
    f: &[f64],
    dt: f64,
    g: &[f64],
    mut gs: Option<&mut [f64]>,
    gvel: &mut [&mut [f64]; D],
) {
    let lat = mac.lattice(at);
    for k in 0..lat.n[D - 1] {
        for r in 0..lat.rows_per_slab() {
            let mut q = lat.row_start(k, r);
            for i in 0..lat.n[0] {
                q[0] = i;
                let v = mac.velocity(at, vel, q);
                let p = Mac::<D, W>::back(&lat, q, v, dt);
                let gq = g[lat.index(q)];
                let gf: &mut [f64] = match at {
                    At::Centre => gs.as_deref_mut().expect("the centres' adjoint"),
                    At::Face(b) => &mut *gvel[b],
                };
                let dp = sample_adjoint(mac.wraps(), f, gf, &lat, p, gq);
                mac.velocity_adjoint(at, gvel, q, dp.map(|d| -dt * d));
            }
        }
    }
}

/// One field on the lattice `at` advected by `scheme` over `dt`; `hat` and
/// `tilde` are scratch of `f`'s length (MacCormack only). MacCormack: a
/// backward trace, a forward trace from its result, half the difference as
/// a correction; with the limiter each value clamped to the range of the
/// samples the backward trace blended.
#[inline(always)]
#[allow(clippy::too_many_arguments)]
pub(crate) fn advect_field<const D: usize, W: Wraps<D>>(
    mac: Mac<D, W>,
    at: At,
    scheme: Scheme,
    dt: f64,
    vel: [&[f64]; D],
    f: &[f64],
    out: &mut [f64],
    hat: &mut [f64],
    tilde: &mut [f64],
) {
    let all = 0..mac.n[D - 1];
    match scheme {
        Scheme::SemiLagrangian => trace(mac, at, vel, f, dt, all, out),
        Scheme::MacCormack { limiter } => {
            trace(mac, at, vel, f, dt, all.clone(), hat);
            trace(mac, at, vel, hat, -dt, all, tilde);
            let lat = mac.lattice(at);
            for k in 0..lat.n[D - 1] {
                for r in 0..lat.rows_per_slab() {
                    let mut q = lat.row_start(k, r);
                    for i in 0..lat.n[0] {
                        q[0] = i;
                        let c = lat.index(q);
                        let mut val = hat[c] + 0.5 * (f[c] - tilde[c]);
                        if limiter {
                            let p = Mac::<D, W>::back(&lat, q, mac.velocity(at, vel, q), dt);
                            let (lo, hi) = sample_range(mac.wraps(), f, &lat, p);
                            // Comparisons, not `f64::clamp` (its assertion's
                            // branch and selects left a phi Enzyme could not
                            // type in 3D: docs/pitfalls.md).
                            if val < lo {
                                val = lo;
                            }
                            if val > hi {
                                val = hi;
                            }
                        }
                        out[c] = val;
                    }
                }
            }
        }
    }
}

/// MacCormack's value before the limiter at every point of the lattice `at`.
pub(crate) fn unclamped<const D: usize, W: Wraps<D>>(mac: Mac<D, W>, at: At, dt: f64, vel: [&[f64]; D], f: &[f64]) -> Vec<f64> {
    let (mut hat, mut tilde) = (vec![0.0; f.len()], vec![0.0; f.len()]);
    trace(mac, at, vel, f, dt, 0..mac.n[D - 1], &mut hat);
    trace(mac, at, vel, &hat, -dt, 0..mac.n[D - 1], &mut tilde);
    hat.iter().zip(f).zip(&tilde).map(|((h, f), t)| h + 0.5 * (f - t)).collect()
}

/// How far the state may move along a tangent before the traces of
/// `lattices` meet a kink: multilinear sampling is smooth between lattice
/// planes and kinks where a traced point crosses one (or a clamped edge).
/// The smallest, over the points traced back by each of `steps` (the time
/// steps of the traces, in cells per unit speed: `[dt]`, or `[dt, −dt]`
/// for MacCormack; each moving at its entry of `rates`, 0 when the step is
/// fixed) with the velocity `vel` moving at `dvel`, of the distance to the
/// nearest plane over the speed at which the point moves; ∞ when none
/// moves. Points for which `set(at, q)` holds are skipped (faces the
/// boundary conditions set after the trace: where their trace lands does
/// not matter).
#[allow(clippy::too_many_arguments)]
pub(crate) fn advect_radius<const D: usize, W: Wraps<D>>(
    mac: Mac<D, W>,
    lattices: &[At],
    steps: &[f64],
    rates: &[f64],
    vel: [&[f64]; D],
    dvel: [&[f64]; D],
    set: impl Fn(At, [usize; D]) -> bool,
) -> f64 {
    let mut r = f64::INFINITY;
    for &at in lattices {
        let lat = mac.lattice(at);
        for q in lat.points().filter(|&q| !set(at, q)) {
            let (v, dv) = (mac.velocity(at, vel, q), mac.velocity(at, dvel, q));
            for (&sdt, &rate) in steps.iter().zip(rates) {
                for a in 0..D {
                    r = r.min(crate::grid::lattice_gap(q[a] as f64 - sdt * v[a], sdt * dv[a] + rate * v[a]));
                }
            }
        }
    }
    r
}

/// One advected field for [`limiter_radius`]: its lattice, its values at
/// the state `x`, its tangent, and its values at `x + eps·d`.
pub(crate) struct LimitedField<'a> {
    pub at: At,
    pub f: &'a [f64],
    pub df: &'a [f64],
    pub fe: &'a [f64],
}

/// How far the state may move along a tangent before MacCormack's limiter
/// switches: the clamp of each value to the range of the samples its
/// backward trace blended kinks where the unclamped value crosses a bound,
/// and where the bound passes from one sample to another. First order: the
/// rates of the unclamped values come from the state moved by `eps` along
/// the tangent (`vele` its velocity; exact for the bounds, which are samples
/// of the field). Points for which `set(at, q)` holds are skipped.
pub(crate) fn limiter_radius<const D: usize, W: Wraps<D>>(
    mac: Mac<D, W>,
    fields: &[LimitedField<'_>],
    dt: f64,
    [vel, vele]: [[&[f64]; D]; 2],
    eps: f64,
    set: impl Fn(At, [usize; D]) -> bool,
) -> f64 {
    let mut r = f64::INFINITY;
    for fld in fields {
        let (at, f, df) = (fld.at, fld.f, fld.df);
        let lat = mac.lattice(at);
        let val = unclamped(mac, at, dt, vel, f);
        let vale = unclamped(mac, at, dt, vele, fld.fe);
        let m = 1 << D;
        for q in lat.points().filter(|&q| !set(at, q)) {
            let c = lat.index(q);
            let p = Mac::<D, W>::back(&lat, q, mac.velocity(at, vel, q), dt);
            let (mut order, _) = corners(mac.wraps(), &lat, p);
            let order = &mut order[..m];
            order.sort_by(|&a, &b| f[a].total_cmp(&f[b]));
            // The bounds: the smallest and largest sample, and the runner-up of each.
            let (lo, lo2, hi2, hi) = (order[0], order[1], order[m - 2], order[m - 1]);
            let rate = (vale[c] - val[c]) / eps;
            r = r
                .min(crossing(val[c] - f[lo], rate - df[lo]))
                .min(crossing(f[hi] - val[c], df[hi] - rate))
                .min(crossing(f[lo2] - f[lo], df[lo2] - df[lo]))
                .min(crossing(f[hi] - f[hi2], df[hi] - df[hi2]));
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
