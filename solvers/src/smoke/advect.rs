//! Advection of the smoke and the velocity in any dimension:
//! semi-Lagrangian, MacCormack (with or without limiter) and upwind, P2's
//! and P4's explicit step (advection, walls, buoyancy) with its hand-written
//! adjoint, and the kink radii of the gradient checks. The traces are
//! [`crate::mac`]'s.

use super::*;
use crate::mac::advect::{LimitedField, advect_field, trace, trace_adjoint, trace_parallel, traced};

/// Advection scheme.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Scheme {
    /// One backward trace, multilinear sample (first order).
    SemiLagrangian,
    /// A backward trace, a forward trace from its result, half the
    /// difference as a correction (second order). With `limiter`, each value
    /// is clamped to the range of the samples the backward trace blended
    /// (Selle et al. 2008): no new extrema, first order at extrema.
    MacCormack {
        /// Clamp to the local range.
        limiter: bool,
    },
}

/// Advection over a time step `dt` of the smoke (if `smoke`) and of the
/// velocity by itself (if `velocity`), each field sampled back along the
/// velocity at its own points (the other components averaged from the
/// nearest faces; wrapping across periodic sides, clamped at the others);
/// then the velocity boundary conditions ([`enforce_boundary`]). Fields not
/// advected are copied. Reads the packed state `x`, overwrites `y`.
/// `scratch` holds [`advect_scratch_len`] values (none for semi-Lagrangian).
///
/// # Panics
/// If a length is wrong or an axis has fewer than 2 cells.
#[allow(clippy::too_many_arguments)]
pub fn advect<const D: usize>(cfg: &MacGrid<D>, scheme: Scheme, dt: f64, smoke: bool, velocity: bool, x: &[f64], y: &mut [f64], scratch: &mut [f64]) {
    assert!(cfg.min_cells() >= 2 && x.len() == cfg.n_state() && y.len() == cfg.n_state(), "smoke: state lengths");
    assert!(scratch.len() >= advect_scratch_len(cfg, scheme), "smoke: advection scratch");
    with_mac!(cfg, mac => advect_on(cfg, mac, scheme, dt, smoke, velocity, x, y, scratch));
    if velocity {
        enforce_boundary(cfg, &mut y[cfg.n_s()..]);
    }
}

#[inline(always)]
#[allow(clippy::too_many_arguments)]
fn advect_on<const D: usize, W: Wraps<D>>(
    cfg: &MacGrid<D>,
    mac: Mac<D, W>,
    scheme: Scheme,
    dt: f64,
    smoke: bool,
    velocity: bool,
    x: &[f64],
    y: &mut [f64],
    scratch: &mut [f64],
) {
    let (s, vel) = cfg.split(x);
    let (s2, vel2) = y.split_at_mut(cfg.n_s());
    // Each field's scratch: the first values of each half (none for
    // semi-Lagrangian).
    let half = scratch.len() / 2;
    let (hat, tilde) = scratch.split_at_mut(half);
    let ks = s.len().min(half);
    if smoke {
        advect_field(mac, At::Centre, scheme, dt, vel, s, s2, &mut hat[..ks], &mut tilde[..ks]);
    } else {
        copy(s, s2);
    }
    advect_faces(mac, scheme, dt, velocity, vel, vel, vel2, hat, tilde);
}

/// The velocity components `fields` advected along `vel` over `dt` (if
/// `velocity`; copied otherwise) into the packed `out`; `hat` and `tilde`
/// scratch of MacCormack, their first values used. `fields` is `vel`
/// itself, or the velocity when `vel` is the velocity scaled by the time
/// step ([`advect_velocity`]).
#[inline(always)]
#[allow(clippy::too_many_arguments)]
fn advect_faces<const D: usize, W: Wraps<D>>(
    mac: Mac<D, W>,
    scheme: Scheme,
    dt: f64,
    velocity: bool,
    vel: [&[f64]; D],
    fields: [&[f64]; D],
    out: &mut [f64],
    hat: &mut [f64],
    tilde: &mut [f64],
) {
    let half = hat.len().min(tilde.len());
    let mut start = 0;
    each_axis!(D, a => {
        let len = fields[a].len();
        let k = len.min(half);
        let o = &mut out[start..start + len];
        start += len;
        if velocity {
            advect_field(mac, At::Face(a), scheme, dt, vel, fields[a], o, &mut hat[..k], &mut tilde[..k]);
        } else {
            copy(fields[a], o);
        }
    });
}

/// The packed velocity `vel` advected by itself over `dt` cells per unit
/// speed by `scheme` (the velocity part of [`advect`]); overwrites `out`.
/// The velocity boundary conditions are the caller's: the faces they set
/// (walls, inflow) hold traced values, the periodic copies traced values
/// or none (the caller refreshes them). `scratch` holds
/// [`advect_velocity_scratch_len`] values. The Navier–Stokes step's
/// advection ([`crate::mac::periodic`]); where [`near_applies`] holds,
/// [`advect_velocity_near`] gives the same values faster.
///
/// The traces run along `dt·vel`, kept in `scratch`, with a unit step: a
/// time step Enzyme differentiates (the Navier–Stokes gradient with
/// respect to `dt`) reaches the traces only through that scaled velocity.
/// With `dt` inside the traces, Enzyme's 3D derivative with respect to it
/// was wrong; so was the whole 3D gradient when this function called
/// [`enforce_boundary`], which [`advect`] calls too (docs/pitfalls.md).
///
/// # Panics
/// If a length is wrong or an axis has fewer than 2 cells.
#[inline(always)]
pub fn advect_velocity<const D: usize>(cfg: &MacGrid<D>, scheme: Scheme, dt: f64, vel: &[f64], out: &mut [f64], scratch: &mut [f64]) {
    let n = cfg.n_vel();
    assert!(cfg.min_cells() >= 2 && vel.len() == n && out.len() == n, "advect_velocity: packed velocity lengths");
    assert!(scratch.len() >= advect_velocity_scratch_len(cfg, scheme), "advect_velocity: scratch");
    let (scaled, rest) = scratch.split_at_mut(n);
    for (s, &v) in scaled.iter_mut().zip(vel) {
        *s = dt * v;
    }
    let half = rest.len() / 2;
    let (hat, tilde) = rest.split_at_mut(half);
    if cfg.boundary.wraps().iter().all(|&w| w) {
        // A box periodic on every axis (the Navier–Stokes step's): the
        // wrapping known when compiling, so the index rules carry no test
        // of the axis and the generated adjoint keeps less.
        let mac = Mac { n: cfg.cells(), wrap: crate::mac::Wrapping };
        return advect_faces(mac, scheme, 1.0, true, cfg.components(scaled), cfg.components(vel), out, hat, tilde);
    }
    with_mac!(cfg, mac => advect_faces(mac, scheme, 1.0, true, cfg.components(scaled), cfg.components(vel), out, hat, tilde));
}

/// Scratch of [`advect_velocity`]: the scaled velocity and
/// [`advect_scratch_len`].
pub fn advect_velocity_scratch_len<const D: usize>(cfg: &MacGrid<D>, scheme: Scheme) -> usize {
    cfg.n_vel() + advect_scratch_len(cfg, scheme)
}

/// Whether [`advect_velocity_near`] applies: a box periodic on every axis,
/// semi-Lagrangian or MacCormack without the limiter, and every face of
/// `dt·vel` below one cell (the Navier–Stokes step's sub-steps keep them
/// at 0.9 or less). False for NaN.
#[inline(always)]
pub fn near_applies<const D: usize>(cfg: &MacGrid<D>, scheme: Scheme, dt: f64, vel: &[f64]) -> bool {
    cfg.boundary.wraps().iter().all(|&w| w) && scheme != (Scheme::MacCormack { limiter: true }) && crate::mac::near::below_a_cell(dt, vel)
}

/// [`advect_velocity`] by the traces shorter than a cell
/// (`mac::near`) where [`near_applies`], the periodic copies
/// refreshed: the same values to rounding, several times faster
/// (docs/navier-stokes.md). Differentiated by Enzyme on its own, apart
/// from [`advect_velocity`]. `scratch` holds
/// [`advect_velocity_near_scratch_len`] values.
///
/// # Panics
/// If a length is wrong or [`near_applies`] does not hold.
#[inline(always)]
pub fn advect_velocity_near<const D: usize>(cfg: &MacGrid<D>, scheme: Scheme, dt: f64, vel: &[f64], out: &mut [f64], scratch: &mut [f64]) {
    let n = cfg.n_vel();
    assert!(cfg.min_cells() >= 2 && vel.len() == n && out.len() == n, "advect_velocity_near: packed velocity lengths");
    assert!(near_applies(cfg, scheme, dt, vel), "advect_velocity_near: a periodic box, no limiter, below a cell");
    let mac = Mac { n: cfg.cells(), wrap: crate::mac::Wrapping };
    let mut strides = [[0; D]; D];
    each_axis!(D, a => {
        strides[a] = mac.lattice(At::Face(a)).stride;
    });
    let maccormack = scheme != Scheme::SemiLagrangian;
    crate::mac::near::advect_velocity(cfg.cells(), strides, maccormack, dt, cfg.components(vel), cfg.components_mut(out), scratch);
    crate::mac::periodic::refresh_periodic_copies(cfg, out);
}

/// [`advect_velocity_near`] compiled for the widest of AVX-512F, AVX2 and
/// baseline x86-64 that the processor has (as [`crate::simd_dispatch!`]):
/// the same values bit for bit, for forward passes (Enzyme differentiates
/// the baseline [`advect_velocity_near`]).
///
/// # Panics
/// As [`advect_velocity_near`].
pub fn advect_velocity_near_widest<const D: usize>(cfg: &MacGrid<D>, scheme: Scheme, dt: f64, vel: &[f64], out: &mut [f64], scratch: &mut [f64]) {
    #[cfg(target_arch = "x86_64")]
    {
        #[target_feature(enable = "avx512f")]
        fn wide<const D: usize>(cfg: &MacGrid<D>, scheme: Scheme, dt: f64, vel: &[f64], out: &mut [f64], scratch: &mut [f64]) {
            advect_velocity_near(cfg, scheme, dt, vel, out, scratch)
        }
        #[target_feature(enable = "avx2")]
        fn medium<const D: usize>(cfg: &MacGrid<D>, scheme: Scheme, dt: f64, vel: &[f64], out: &mut [f64], scratch: &mut [f64]) {
            advect_velocity_near(cfg, scheme, dt, vel, out, scratch)
        }
        if crate::simd::avx512_allowed() {
            // SAFETY: the processor has AVX-512F, checked just above.
            return unsafe { wide(cfg, scheme, dt, vel, out, scratch) };
        }
        if crate::simd::avx2_allowed() {
            // SAFETY: the processor has AVX2, checked just above.
            return unsafe { medium(cfg, scheme, dt, vel, out, scratch) };
        }
    }
    advect_velocity_near(cfg, scheme, dt, vel, out, scratch)
}

/// Scratch of [`advect_velocity_near`].
pub fn advect_velocity_near_scratch_len<const D: usize>(cfg: &MacGrid<D>) -> usize {
    crate::mac::near::scratch_len(cfg.cells())
}

/// Adjoint of [`advect_velocity_near`], hand-written (the reference for
/// Enzyme's): adds `Jᵀ·g` into `gvel` (`g` and `gvel` packed velocities;
/// the copies of `g` count for the faces they copy, those of `gvel` get
/// nothing: the step reads only own faces) and returns the derivative with
/// respect to `dt`.
///
/// # Panics
/// If a length is wrong or [`near_applies`] does not hold.
pub fn advect_velocity_near_adjoint<const D: usize>(cfg: &MacGrid<D>, scheme: Scheme, dt: f64, vel: &[f64], g: &[f64], gvel: &mut [f64]) -> f64 {
    let n = cfg.n_vel();
    assert!(vel.len() == n && g.len() == n && gvel.len() == n, "advect_velocity_near_adjoint: packed velocity lengths");
    assert!(near_applies(cfg, scheme, dt, vel), "advect_velocity_near_adjoint: a periodic box, no limiter, below a cell");
    let mut folded = g.to_vec();
    crate::mac::periodic::refresh_periodic_copies_adjoint(cfg, &mut folded);
    let mac = Mac { n: cfg.cells(), wrap: crate::mac::Wrapping };
    let strides: [[usize; D]; D] = std::array::from_fn(|a| mac.lattice(At::Face(a)).stride);
    let maccormack = scheme != Scheme::SemiLagrangian;
    crate::mac::near::advect_velocity_adjoint(cfg.cells(), strides, maccormack, dt, cfg.components(vel), cfg.components(&folded), cfg.components_mut(gvel))
}

/// A perturbation `d` of the state carried along the velocity of the
/// state `x` over `dt` (semi-Lagrangian: each field sampled at its own
/// points traced back by `dt` times `x`'s velocity there), then the linear
/// velocity boundary conditions; overwrites `out`. Linear in `d`. With
/// `dt = −1` it runs P2's advection backwards in time along the step's
/// velocity: the approximate inverse of [`advect_buoyancy`]'s transport
/// that the smoke step's local inverse uses.
///
/// # Panics
/// If a length is wrong or an axis has fewer than 2 cells.
pub fn advect_along<const D: usize>(cfg: &MacGrid<D>, dt: f64, x: &[f64], d: &[f64], out: &mut [f64]) {
    let n = cfg.n_state();
    assert!(cfg.min_cells() >= 2 && x.len() == n && d.len() == n && out.len() == n, "smoke: state lengths");
    let (_, vel) = cfg.split(x);
    let (ds, dvel) = cfg.split(d);
    let (os, ovel) = out.split_at_mut(cfg.n_s());
    with_mac!(cfg, mac => {
        let all = 0..cfg.n[D - 1];
        trace(mac, At::Centre, vel, ds, dt, all.clone(), os);
        each_axis!(D, a => {
            trace(mac, At::Face(a), vel, dvel[a], dt, all.clone(), &mut ovel[cfg.face_range(a)]);
        });
    });
    enforce_boundary_linear(cfg, ovel);
}

/// The lattices advected: the centres with `smoke`, the faces with `velocity`.
fn lattices<const D: usize>(smoke: bool, velocity: bool) -> Vec<At> {
    let mut l = Vec::new();
    if smoke {
        l.push(At::Centre);
    }
    if velocity {
        l.extend((0..D).map(At::Face));
    }
    l
}

/// How far `x` may move along `d` before [`advect`] meets a kink:
/// multilinear sampling is smooth between lattice planes and kinks where a
/// traced point crosses one (or a clamped edge). The smallest, over the
/// traced points (the backward trace, and for MacCormack also the forward
/// one; under semi-Lagrangian advection the faces the boundary sets after
/// the trace left out), of the
/// distance to the nearest plane over the speed at which `d` moves the
/// point; ∞ when `d` moves none. MacCormack's limiter is
/// [`limiter_radius`].
#[allow(clippy::too_many_arguments)]
pub fn advect_radius<const D: usize>(cfg: &MacGrid<D>, scheme: Scheme, dt: f64, smoke: bool, velocity: bool, x: &[f64], d: &[f64]) -> f64 {
    let (_, vel) = cfg.split(x);
    let (_, dvel) = cfg.split(d);
    let steps: &[f64] = match scheme {
        Scheme::SemiLagrangian => &[dt],
        Scheme::MacCormack { .. } => &[dt, -dt],
    };
    crate::mac::advect::advect_radius(cfg.mac(), &lattices::<D>(smoke, velocity), steps, &[0.0; 2], vel, dvel, |at, q| traced_for_nothing(cfg, scheme, at, q))
}

/// Whether the trace of point `q` of the lattice `at` leaves no mark on
/// the step: a face the boundary sets after the trace, under
/// semi-Lagrangian advection. Under MacCormack the first trace's value at
/// such a face is sampled by its neighbours' second trace, so every point
/// counts.
#[inline(always)]
fn traced_for_nothing<const D: usize>(cfg: &MacGrid<D>, scheme: Scheme, at: At, q: [usize; D]) -> bool {
    scheme == Scheme::SemiLagrangian && set_by_boundary(cfg, at, q)
}

/// [`advect_radius`] of the packed velocity `vel` advected by itself alone
/// ([`advect_velocity`]) over `dt` cells, the perturbation moving the
/// velocity along `dvel` and the time step at the rate `ddt` (the
/// Navier–Stokes step's gradient with respect to its time step); with
/// MacCormack's limiter also [`limiter_radius`] (of the velocity's
/// perturbation).
pub fn advect_velocity_radius<const D: usize>(cfg: &MacGrid<D>, scheme: Scheme, dt: f64, ddt: f64, vel: &[f64], dvel: &[f64]) -> f64 {
    let (steps, rates): (&[f64], &[f64]) = match scheme {
        Scheme::SemiLagrangian => (&[dt], &[ddt]),
        Scheme::MacCormack { .. } => (&[dt, -dt], &[ddt, -ddt]),
    };
    let (v, dv) = (cfg.components(vel), cfg.components(dvel));
    let r = crate::mac::advect::advect_radius(cfg.mac(), &lattices::<D>(false, true), steps, rates, v, dv, |at, q| traced_for_nothing(cfg, scheme, at, q));
    if scheme != (Scheme::MacCormack { limiter: true }) {
        return r;
    }
    let state = |v: &[f64]| {
        let mut s = vec![0.0; cfg.n_state()];
        s[cfg.n_s()..].copy_from_slice(v);
        s
    };
    r.min(limiter_radius(cfg, dt, false, true, &state(vel), &state(dvel)))
}

/// Whether point `q` of the lattice `at` is a face the boundary sets after
/// the trace (on a closed or inflow side), so that where its trace lands
/// does not matter (no kink of the step).
#[inline(always)]
fn set_by_boundary<const D: usize>(cfg: &MacGrid<D>, at: At, q: [usize; D]) -> bool {
    let a = at.axis();
    if a >= D {
        return false;
    }
    let [lo, hi] = cfg.boundary.axis(a);
    (q[a] == 0 && lo.sets_faces()) || (q[a] == cfg.n[a] && hi.sets_faces())
}

/// How far `x` may move along `d` before MacCormack's limiter switches: the
/// clamp of each value to the range of the samples its backward trace
/// blended kinks where the unclamped value crosses a bound, and where the
/// bound passes from one sample to another. First order: the rates of the
/// unclamped values come from a step of `1e-7` relative along `d` (exact
/// for the bounds, which are samples of the field); within the sampling
/// radius of [`advect_radius`], which the caller takes too.
pub fn limiter_radius<const D: usize>(cfg: &MacGrid<D>, dt: f64, smoke: bool, velocity: bool, x: &[f64], d: &[f64]) -> f64 {
    let dmax = d.iter().fold(0.0f64, |m, v| m.max(v.abs()));
    if dmax == 0.0 {
        return f64::INFINITY;
    }
    let eps = 1e-7 * (1.0 + x.iter().fold(0.0f64, |m, v| m.max(v.abs()))) / dmax;
    let xe: Vec<f64> = x.iter().zip(d).map(|(a, b)| a + eps * b).collect();
    let (fx, fd, fe) = (cfg.split(x), cfg.split(d), cfg.split(&xe));
    let fields: Vec<LimitedField<'_>> = lattices::<D>(smoke, velocity)
        .into_iter()
        .map(|at| match at {
            At::Centre => LimitedField { at, f: fx.0, df: fd.0, fe: fe.0 },
            At::Face(a) => LimitedField { at, f: fx.1[a], df: fd.1[a], fe: fe.1[a] },
        })
        .collect();
    crate::mac::advect::limiter_radius(cfg.mac(), &fields, dt, [fx.1, fe.1], eps, |at, q| set_by_boundary(cfg, at, q))
}

/// Scratch [`advect()`] needs: for MacCormack two fields of the largest
/// lattice, none for semi-Lagrangian.
pub fn advect_scratch_len<const D: usize>(cfg: &MacGrid<D>, scheme: Scheme) -> usize {
    match scheme {
        Scheme::SemiLagrangian => 0,
        Scheme::MacCormack { .. } => 2 * (0..D).map(|a| cfg.n_face(a)).max().unwrap_or(0),
    }
}

/// Steps 1–4 of P2 and P4, for any boundary: semi-Lagrangian advection of
/// the smoke and the velocity over `cfg.dt` (1 in P2 and P4), the velocity
/// boundary conditions, buoyancy along +y (`cfg.buoyancy`). Reads the
/// packed state `x`, overwrites `y` (the velocity not yet divergence-free).
///
/// # Panics
/// If `x` or `y` is not of length [`MacGrid::n_state`] or an axis has
/// fewer than 2 cells.
pub fn advect_buoyancy<const D: usize>(cfg: &MacGrid<D>, x: &[f64], y: &mut [f64]) {
    advect(cfg, Scheme::SemiLagrangian, cfg.dt, true, true, x, y, &mut []);
    // Buoyancy touches no closed, inflow or outflow face and refreshes its
    // own periodic copies, so the boundary conditions of `advect` still hold.
    let (s2, vel2) = y.split_at_mut(cfg.n_s());
    add_buoyancy(cfg, 1, cfg.buoyancy, s2, &mut vel2[cfg.face_range(1)]);
}

/// Slabs `ks` (layers along the slowest axis: rows in 2D) of
/// [`advect_buoyancy`]'s output in the closed box (P2, P4), packed as
/// [`MacGrid::slab_lens`] says (`y` of their total length): each output
/// slab depends on the whole input but on no other output slab (in 2D the
/// buoyancy of a range's first y-face traces the smoke row below it again),
/// so that an adjoint can be taken slab range by slab range in parallel,
/// then summed in a fixed order. The same values as [`advect_buoyancy`],
/// operation for operation.
///
/// # Panics
/// If the box is not closed, a length is wrong, or `ks` is empty or past
/// the last slab.
pub fn advect_buoyancy_slabs<const D: usize>(cfg: &MacGrid<D>, x: &[f64], ks: std::ops::Range<usize>, y: &mut [f64]) {
    let n = cfg.cells();
    let last = n[D - 1];
    assert!(
        cfg.is_closed() && cfg.min_cells() >= 2 && x.len() == cfg.n_state() && y.len() == cfg.slabs_len(ks.clone()),
        "smoke: slabs of the closed box's step"
    );
    assert!(ks.start < ks.end && ks.end <= last, "smoke: slabs {ks:?} of {last}");
    let mac = cfg.bounded();
    let (s, vel) = cfg.split(x);
    // The output's pieces: the smoke's slabs, then each component's
    // (`at[a]..at[a + 1]` of the velocity part).
    let (ls, lf) = cfg.slab_lens(ks.clone());
    let (s2, vel2) = y.split_at_mut(ls);
    trace(mac, At::Centre, vel, s, cfg.dt, ks.clone(), s2);
    // Each component's slabs in turn, then its walls.
    let mut start = 0;
    each_axis!(D, a => {
        let out = &mut vel2[start..start + lf[a]];
        trace(mac, At::Face(a), vel, vel[a], cfg.dt, ks.clone(), out);
        close_walls(cfg, ks.clone(), a, out);
        start += lf[a];
    });
    let v2 = &mut vel2[lf[0]..lf[0] + lf[1]];
    // Buoyancy on the interior y-faces of the slabs (in 2D the first y-face
    // of a range has its lower cell in the row before the range: traced
    // again).
    let (centre, faces) = (mac.lattice(At::Centre), mac.lattice(At::Face(1)));
    let (cbase, fbase) = (ks.start * centre.stride[D - 1], ks.start * faces.stride[D - 1]);
    let coefficient = cfg.buoyancy * 0.5;
    for k in ks.clone() {
        for r in 0..faces.rows_per_slab() {
            let q = faces.row_start(k, r);
            if q[1] == 0 || q[1] >= n[1] {
                continue;
            }
            // The row's first face and the first cells above and below it
            // (rows of the same length: x fastest in both arrays).
            let mut below = q;
            below[1] -= 1;
            let (f0, c0) = (faces.index(q) - fbase, centre.index(q) - cbase);
            if D == 2 && q[1] == ks.start {
                for i in 0..n[0] {
                    below[0] = i;
                    let lower = traced(mac, At::Centre, &centre, vel, s, cfg.dt, below);
                    v2[f0 + i] += coefficient * (lower + s2[c0 + i]);
                }
            } else {
                let b0 = centre.index(below) - cbase;
                for i in 0..n[0] {
                    v2[f0 + i] += coefficient * (s2[b0 + i] + s2[c0 + i]);
                }
            }
        }
    }
}

/// The closed walls of slabs `ks` of the faces normal to `a` (`f` those
/// slabs, as [`MacGrid::slab_lens`] packs them): every face on a side set
/// to 0.
#[inline(always)]
fn close_walls<const D: usize>(cfg: &MacGrid<D>, ks: std::ops::Range<usize>, a: usize, f: &mut [f64]) {
    let n = cfg.cells();
    let faces = cfg.bounded().lattice(At::Face(a));
    // This lattice's slabs: those of `ks`, and its last face slab when `ks`
    // reaches the end.
    let end = if ks.end == n[D - 1] { faces.n[D - 1] } else { ks.end };
    let base = ks.start * faces.stride[D - 1];
    // Row by row: along x the row's two end faces; along another axis the
    // whole row when it lies on a wall (indexed stores: a fill is a memset
    // Enzyme cannot type).
    for k in ks.start..end {
        for r in 0..faces.rows_per_slab() {
            let q = faces.row_start(k, r);
            let row = faces.index(q) - base;
            if a == 0 {
                f[row] = 0.0;
                f[row + n[0]] = 0.0;
            } else if q[a] == 0 || q[a] == n[a] {
                for i in 0..n[0] {
                    f[row + i] = 0.0;
                }
            }
        }
    }
}

/// [`advect_buoyancy`] with each lattice's slabs split over threads
/// ([`crate::par`]): the same values for any thread count. Not for
/// differentiated code (Enzyme differentiates [`advect_buoyancy`]).
///
/// # Panics
/// As [`advect_buoyancy`].
pub fn advect_buoyancy_parallel<const D: usize>(cfg: &MacGrid<D>, x: &[f64], y: &mut [f64]) {
    assert!(cfg.min_cells() >= 2 && x.len() == cfg.n_state() && y.len() == cfg.n_state(), "smoke: state lengths");
    with_mac!(cfg, mac => {
        let (s, vel) = cfg.split(x);
        let (s2, vel2) = cfg.split_mut(y);
        trace_parallel(mac, At::Centre, vel, s, cfg.dt, s2);
        for a in 0..D {
            trace_parallel(mac, At::Face(a), vel, vel[a], cfg.dt, &mut *vel2[a]);
        }
    });
    let (s2, vel2) = y.split_at_mut(cfg.n_s());
    enforce_boundary(cfg, vel2);
    add_buoyancy(cfg, 1, cfg.buoyancy, s2, &mut vel2[cfg.face_range(1)]);
}

/// Hand-written adjoint of [`advect_buoyancy`]: `gx += Jᵀ·gy` at the state
/// `x` (accumulates into `gx`; `gy` is used as scratch and left
/// unspecified). The reference for Enzyme's generated adjoint.
///
/// # Panics
/// As [`advect_buoyancy`], and if `gy` or `gx` has the wrong length.
pub fn advect_buoyancy_adjoint<const D: usize>(cfg: &MacGrid<D>, x: &[f64], gy: &mut [f64], gx: &mut [f64]) {
    let n = cfg.n_state();
    assert!(cfg.min_cells() >= 2 && x.len() == n && gy.len() == n && gx.len() == n, "smoke: state lengths");
    let (gs2, gvel2) = gy.split_at_mut(cfg.n_s());
    add_buoyancy_adjoint(cfg, 1, cfg.buoyancy, &mut gvel2[cfg.face_range(1)], gs2);
    advect_adjoint(cfg, cfg.dt, true, true, x, gy, gx);
}

/// Adjoint of [`add_buoyancy`] along `axis`: the face adjoint `gf` passes
/// `coefficient / 2` of itself to each cell beside the face (`gs +=`); a
/// periodic copy first hands its adjoint to face `0`.
fn add_buoyancy_adjoint<const D: usize>(cfg: &MacGrid<D>, axis: usize, coefficient: f64, gf: &mut [f64], gs: &mut [f64]) {
    let mac = cfg.bounded();
    let (faces, cells) = (mac.lattice(At::Face(axis)), mac.lattice(At::Centre));
    let m = cfg.n[axis];
    let wrap = cfg.boundary.periodic(axis);
    let (down, copy) = (cells.stride[axis], m * faces.stride[axis]);
    for q in faces.points() {
        let (along, face) = (q[axis], faces.index(q));
        let lower = if along > 0 && along < m {
            cells.index(q) - down
        } else if wrap && along == 0 {
            gf[face] += gf[face + copy];
            gf[face + copy] = 0.0;
            cells.index(q) + (m - 1) * down
        } else {
            continue;
        };
        let b = coefficient * 0.5 * gf[face];
        gs[lower] += b;
        gs[cells.index(q)] += b;
    }
}

/// Hand-written adjoint of [`advect`] with the semi-Lagrangian scheme over
/// `dt`, in any box: `gx += Jᵀ·gy` at the state `x` (accumulates into `gx`;
/// `gy` is used as scratch and left unspecified). The reference for
/// Enzyme's generated adjoint under every boundary kind.
///
/// # Panics
/// As [`advect`], and if `gy` or `gx` has the wrong length.
pub fn advect_adjoint<const D: usize>(cfg: &MacGrid<D>, dt: f64, smoke: bool, velocity: bool, x: &[f64], gy: &mut [f64], gx: &mut [f64]) {
    let n = cfg.n_state();
    assert!(cfg.min_cells() >= 2 && x.len() == n && gy.len() == n && gx.len() == n, "smoke: state lengths");
    let (s, vel) = cfg.split(x);
    if velocity {
        // The boundary conditions came last: set faces pass nothing back,
        // periodic copies hand theirs to face 0.
        enforce_boundary_adjoint(cfg, &mut gy[cfg.n_s()..]);
    }
    let (gs2, gvel2) = cfg.split_mut(gy);
    let (gs, mut gvel) = cfg.split_mut(gx);
    if velocity {
        with_mac!(cfg, mac => {
            // The lattice a constant in each call (a run-time one costs a
            // branch per point).
            for a in (0..D).rev() {
                on_axis!(a, b => {
                    trace_adjoint(mac, At::Face(b), vel, vel[b], dt, &*gvel2[b], None, &mut gvel);
                });
            }
        });
    } else {
        for a in 0..D {
            for (g, &g2) in gvel[a].iter_mut().zip(&*gvel2[a]) {
                *g += g2;
            }
        }
    }
    if smoke {
        with_mac!(cfg, mac => trace_adjoint(mac, At::Centre, vel, s, dt, gs2, Some(&mut *gs), &mut gvel));
    } else {
        for (g, &g2) in gs.iter_mut().zip(&*gs2) {
            *g += g2;
        }
    }
}

/// First-order upwind advection of the smoke by the MAC velocity, in
/// conservative (flux) form over one time step `dt`: through every face
/// between two cells (across periodic sides too), and through inflow and
/// outflow sides (with smoke-free fluid outside); none through closed
/// sides. Reads the packed state `x`, writes `y` (the velocity passes
/// through).
///
/// # Panics
/// If a length is wrong.
pub fn advect_upwind<const D: usize>(cfg: &MacGrid<D>, dt: f64, x: &[f64], y: &mut [f64]) {
    assert!(cfg.min_cells() >= 2 && x.len() == cfg.n_state() && y.len() == cfg.n_state(), "smoke: state lengths");
    copy(x, y);
    let n = cfg.cells();
    let mac = cfg.bounded();
    let cells = mac.lattice(At::Centre);
    each_axis!(D, axis => {
        let start = cfg.n_s() + cfg.face_range(axis).start;
        let faces = mac.lattice(At::Face(axis));
        let [lo, hi] = cfg.boundary.axis(axis);
        let wrap = lo == Side::Periodic;
        let (m, down) = (n[axis], cells.stride[axis]);
        for k in 0..faces.n[D - 1] {
            for r in 0..faces.rows_per_slab() {
                let mut q = faces.row_start(k, r);
                for i in 0..faces.n[0] {
                    q[0] = i;
                    let along = q[axis];
                    // The cells beside the face (`None`: outside the box),
                    // and whether fluid passes.
                    let (lower, upper, passes) = if along > 0 && along < m {
                        let c = cells.index(q);
                        (Some(c - down), Some(c), true)
                    } else if along == 0 {
                        let c = cells.index(q);
                        (wrap.then(|| c + (m - 1) * down), Some(c), wrap || lo.lets_through())
                    } else {
                        (Some(cells.index(q) - down), None, hi.lets_through())
                    };
                    if passes {
                        let c = dt * x[start + faces.index(q)];
                        let from = if c > 0.0 { lower } else { upper };
                        let f = c * from.map_or(0.0, |l| x[l]);
                        if let Some(l) = lower {
                            y[l] -= f;
                        }
                        if let Some(u) = upper {
                            y[u] += f;
                        }
                    }
                }
            }
        }
    });
}

/// Distance to the nearest upwind switch of [`advect_upwind`] along `d`:
/// the smallest `|u_f / d_f|` over the faces that carry flux.
pub fn upwind_radius<const D: usize>(cfg: &MacGrid<D>, x: &[f64], d: &[f64]) -> f64 {
    let (_, vel) = cfg.split(x);
    let (_, dvel) = cfg.split(d);
    let mut r = f64::INFINITY;
    for a in 0..D {
        for_each_face(cfg.n, &cfg.boundary, a, |f| {
            if !f.side.is_some_and(Side::is_wall) && dvel[a][f.index] != 0.0 {
                r = r.min((vel[a][f.index] / dvel[a][f.index]).abs());
            }
        });
    }
    r
}
