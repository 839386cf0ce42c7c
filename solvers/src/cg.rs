//! Preconditioned conjugate gradients on a symmetric positive
//! (semi-)definite system, written once for every pressure solve (2D and
//! 3D, any boundary, any preconditioner): the matrix and the preconditioner
//! come in through [`System`], the vectors live in [`CgWork`].
//!
//! Singular systems (a closed box: constants solve `A·p = 0`) are solved in
//! the space orthogonal to the null vector, given as [`Null`]: the
//! right-hand side is projected onto it first, to remove rounding that
//! would break the compatibility condition, and the solution returned is
//! the one without a null component (the pseudo-inverse's), whatever the
//! preconditioner added along it. The projection's adjoint sees that
//! component (through faces on walls and solids), so forward and adjoint
//! solves must agree on it.

use std::fmt;

use crate::par;

/// A solve that did not converge.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct NoConvergence {
    /// Iterations done.
    pub iterations: usize,
    /// Final true residual norm relative to `‖b‖`.
    pub relative_residual: f64,
    /// The relative tolerance asked for.
    pub tolerance: f64,
}

impl fmt::Display for NoConvergence {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        write!(
            f,
            "pressure solve did not converge: relative residual {:.3e} after {} iterations (tolerance {:.1e})",
            self.relative_residual, self.iterations, self.tolerance
        )?;
        if self.iterations == 0 && self.relative_residual.is_nan() {
            write!(f, ": its right-hand side holds a NaN or an infinity (the state before the solve is not finite)")?;
        }
        Ok(())
    }
}

impl std::error::Error for NoConvergence {}

/// The matrix `A` and the preconditioner `M⁻¹ ≈ A⁻¹` of a solve.
pub trait System {
    /// `out = A·p` (overwrites).
    fn apply(&mut self, p: &[f64], out: &mut [f64]);

    /// `q = A·d`, returning `d·q` (one pass where the matrix fuses it).
    fn apply_dot(&mut self, d: &[f64], q: &mut [f64]) -> f64 {
        self.apply(d, q);
        dot(d, q)
    }

    /// `z = M⁻¹·r`, a symmetric positive definite map; `false` when there is
    /// no preconditioner (`z` is then not written and CG runs plain).
    fn precondition(&mut self, r: &[f64], z: &mut [f64]) -> bool;

    /// The null space of `A`.
    fn null(&self) -> Null<'_>;
}

/// The null space of `A`.
#[derive(Clone, Copy, Debug)]
pub enum Null<'a> {
    /// None: `A` is definite.
    None,
    /// The constant vector on the cells where the weight is 1 (`None`: on
    /// every cell; cells of weight 0 are solid, identity rows).
    Constant(Option<&'a [f64]>),
}

/// The vectors of conjugate gradients (residual, preconditioned residual,
/// direction, matrix times direction), kept between solves.
#[derive(Clone, Debug, Default)]
pub struct CgWork {
    r: Vec<f64>,
    z: Vec<f64>,
    d: Vec<f64>,
    q: Vec<f64>,
}

impl CgWork {
    /// Vectors for systems of `n` unknowns.
    pub fn new(n: usize) -> Self {
        Self { r: vec![0.0; n], z: vec![0.0; n], d: vec![0.0; n], q: vec![0.0; n] }
    }
}

/// The stopping rule of a solve.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Stop {
    /// Relative tolerance on the true residual, `‖b − A·p‖₂ ≤ tol·‖b‖₂`.
    pub tolerance: f64,
    /// More iterations than this is an error.
    pub max_iterations: usize,
}

/// Solves `A·p = b` until `‖b − A·p‖₂ ≤ tol·‖b‖₂` (true residual, `b`
/// projected off the null space first), from `p = 0` or, when `warm`, from
/// the `p` given (if finite); overwrites `p`. Returns the iterations, or the
/// residual reached when `max_iterations` pass or the iteration breaks down.
///
/// # Panics
/// If `b`, `p` and the work vectors differ in length.
pub fn solve(sys: &mut impl System, work: &mut CgWork, stop: Stop, b: &[f64], p: &mut [f64], warm: bool) -> Result<usize, NoConvergence> {
    let n = b.len();
    assert!(p.len() == n && work.r.len() == n, "cg: lengths");
    let CgWork { r, z, d, q } = work;
    // The right-hand side minus its null component.
    let mean = match sys.null() {
        Null::None => 0.0,
        Null::Constant(None) => b.iter().sum::<f64>() / n as f64,
        Null::Constant(Some(w)) => b.iter().zip(w).map(|(b, w)| b * w).sum::<f64>() / w.iter().sum::<f64>().max(1.0),
    };
    projected_rhs(sys.null(), mean, b, r);
    // ‖b‖² overflows past |b| ≈ 1e154 (and underflows below 1e-154), which
    // would read as convergence at once: the system is linear, so it is
    // solved for b scaled by a power of two (exact) and the solution scaled
    // back. A right-hand side that is not finite is an error.
    let scale = match rhs_scale(r) {
        Some(s) => s,
        None => return Err(NoConvergence { iterations: 0, relative_residual: f64::NAN, tolerance: stop.tolerance }),
    };
    if scale != 1.0 {
        r.iter_mut().for_each(|v| *v *= scale);
    }
    let bnorm = dot(r, r).sqrt();
    if bnorm == 0.0 {
        p.fill(0.0);
        return Ok(0);
    }
    if warm && p.iter().all(|v| v.is_finite()) {
        if scale != 1.0 {
            p.iter_mut().for_each(|v| *v *= scale);
        }
        sys.apply(p, q);
        for (r, &q) in r.iter_mut().zip(q.iter()) {
            *r -= q;
        }
    } else {
        p.fill(0.0);
    }
    let target = stop.tolerance * bnorm;
    let mut rz = restart(sys, r, z, d);
    let mut rr = dot(r, r);
    let mut it = 0;
    loop {
        if rr.sqrt() <= target {
            // Confirm on the true residual; restart from it if needed.
            sys.apply(p, q);
            projected_rhs(sys.null(), mean, b, r);
            for (r, &q) in r.iter_mut().zip(q.iter()) {
                *r = *r * scale - q;
            }
            rr = dot(r, r);
            if rr.sqrt() <= target {
                if let Null::Constant(w) = sys.null() {
                    remove_constant(w, p);
                }
                if scale != 1.0 {
                    p.iter_mut().for_each(|v| *v /= scale);
                }
                return Ok(it);
            }
            rz = restart(sys, r, z, d);
        }
        if it >= stop.max_iterations || !rr.is_finite() {
            return Err(NoConvergence { iterations: it, relative_residual: rr.sqrt() / bnorm, tolerance: stop.tolerance });
        }
        let dq = sys.apply_dot(d, q);
        let alpha = rz / dq;
        update(alpha, d, q, p, r, &mut rr);
        let preconditioned = sys.precondition(r, z);
        let rz_new = if preconditioned { dot(r, z) } else { rr };
        let beta = rz_new / rz;
        rz = rz_new;
        direction(beta, if preconditioned { z } else { r }, d);
        it += 1;
    }
}

/// The largest `|v_i|` (0 for an empty slice), NaN when any `v_i` is NaN:
/// unlike a fold with `f64::max`, which skips NaN, so that a NaN residual
/// is never read as a small one. Eight lanes at a time (every solve starts
/// with it: a running maximum waits on each comparison); a lane that saw
/// a value that is not finite sends the slice to the scalar loop, which
/// tells NaN from infinity.
pub fn max_abs(v: &[f64]) -> f64 {
    let (big, finite) = max_abs_dispatch(v);
    if finite { big } else { max_abs_scalar(v) }
}

crate::simd_dispatch! {
    fn max_abs_dispatch(v: &[f64]) -> (f64, bool) => max_abs_lanes
}

/// The largest `|v_i|` over eight lanes and whether every `v_i` is finite
/// (`x·0` is 0 for a finite `x`, NaN otherwise).
#[inline(always)]
fn max_abs_lanes(v: &[f64]) -> (f64, bool) {
    let (mut big, mut zero) = ([0.0f64; 8], [0.0f64; 8]);
    let chunks = v.chunks_exact(8);
    let tail = chunks.remainder();
    for x in chunks {
        for l in 0..8 {
            let a = x[l].abs();
            big[l] = if a > big[l] { a } else { big[l] };
            zero[l] += x[l] * 0.0;
        }
    }
    let mut m = big.iter().fold(0.0f64, |m, &b| if b > m { b } else { m });
    let mut z = zero.iter().sum::<f64>();
    for &x in tail {
        m = if x.abs() > m { x.abs() } else { m };
        z += x * 0.0;
    }
    (m, z == 0.0)
}

fn max_abs_scalar(v: &[f64]) -> f64 {
    let mut big = 0.0f64;
    for x in v {
        let a = x.abs();
        if a.is_nan() {
            return f64::NAN;
        }
        big = big.max(a);
    }
    big
}

/// The power of two that brings the largest `|r_i|` into `[1, 2)` when it
/// lies outside `[2⁻³⁰⁰, 2³⁰⁰]` (where sums of squares could overflow or
/// underflow), else 1; `None` when `r` holds a NaN or an infinity.
pub fn rhs_scale(r: &[f64]) -> Option<f64> {
    let big = max_abs(r);
    if !big.is_finite() {
        return None;
    }
    if big == 0.0 || (big >= 2f64.powi(-300) && big <= 2f64.powi(300)) {
        return Some(1.0);
    }
    Some(2f64.powi((-big.log2().floor() as i32).clamp(-1000, 1000)))
}

/// `r = b − mean·w`: the right-hand side with its null component (`mean`
/// along the null vector `w`) removed.
fn projected_rhs(null: Null<'_>, mean: f64, b: &[f64], r: &mut [f64]) {
    let weights = match null {
        Null::Constant(w) => w,
        Null::None => None,
    };
    for (c, (r, &bv)) in r.iter_mut().zip(b).enumerate() {
        *r = bv - mean * weights.map_or(1.0, |w| w[c]);
    }
}

/// A fresh search direction, `d = M⁻¹·r` (or `r` without a
/// preconditioner); returns `r·M⁻¹·r`.
fn restart(sys: &mut impl System, r: &[f64], z: &mut [f64], d: &mut [f64]) -> f64 {
    if sys.precondition(r, z) {
        d.copy_from_slice(z);
        dot(r, z)
    } else {
        d.copy_from_slice(r);
        dot(r, r)
    }
}

/// Removes the component of `p` along the constant vector on the cells of
/// weight 1 (`None`: every cell).
pub fn remove_constant(weights: Option<&[f64]>, p: &mut [f64]) {
    match weights {
        None => {
            let mean = p.iter().sum::<f64>() / p.len().max(1) as f64;
            p.iter_mut().for_each(|v| *v -= mean);
        }
        Some(w) => {
            let count = w.iter().sum::<f64>().max(1.0);
            let mean = p.iter().zip(w).map(|(p, w)| p * w).sum::<f64>() / count;
            p.iter_mut().zip(w).for_each(|(v, w)| *v -= mean * w);
        }
    }
}

/// `p += α·d`, `r −= α·q`, `*rr = r·r` in one pass (in pieces, [`crate::par`]).
fn update(alpha: f64, d: &[f64], q: &[f64], p: &mut [f64], r: &mut [f64], rr: &mut f64) {
    *rr = par::sum_pieces_mut(p, r, |k, p, r| {
        let o = k * par::SUM_PIECE..k * par::SUM_PIECE + p.len();
        let mut acc = 0.0;
        update_piece(alpha, &d[o.clone()], &q[o], p, r, &mut acc);
        acc
    });
}

crate::simd_dispatch! {
    fn update_piece(alpha: f64, d: &[f64], q: &[f64], p: &mut [f64], r: &mut [f64], rr: &mut f64) => update_body
}

#[inline(always)]
fn update_body(alpha: f64, d: &[f64], q: &[f64], p: &mut [f64], r: &mut [f64], rr: &mut f64) {
    let mut acc = [0.0f64; 8];
    let mut tail = 0.0;
    let (mut pc, mut rc) = (p.chunks_exact_mut(8), r.chunks_exact_mut(8));
    let (mut dc, mut qc) = (d.chunks_exact(8), q.chunks_exact(8));
    for (((pv, rv), dv), qv) in (&mut pc).zip(&mut rc).zip(&mut dc).zip(&mut qc) {
        for l in 0..8 {
            pv[l] += alpha * dv[l];
            rv[l] -= alpha * qv[l];
            acc[l] += rv[l] * rv[l];
        }
    }
    for (((pv, rv), dv), qv) in pc.into_remainder().iter_mut().zip(rc.into_remainder().iter_mut()).zip(dc.remainder()).zip(qc.remainder()) {
        *pv += alpha * dv;
        *rv -= alpha * qv;
        tail += *rv * *rv;
    }
    *rr = acc.iter().sum::<f64>() + tail;
}

/// `d = z + β·d` (in pieces).
fn direction(beta: f64, z: &[f64], d: &mut [f64]) {
    par::for_pieces(d, par::SUM_PIECE, |k, d| direction_piece(beta, &z[k * par::SUM_PIECE..k * par::SUM_PIECE + d.len()], d));
}

crate::simd_dispatch! {
    fn direction_piece(beta: f64, z: &[f64], d: &mut [f64]) => direction_body
}

#[inline(always)]
fn direction_body(beta: f64, z: &[f64], d: &mut [f64]) {
    for (dv, &zv) in d.iter_mut().zip(z) {
        *dv = zv + beta * *dv;
    }
}

/// `a·b`: the partial sums of pieces of [`par::SUM_PIECE`] values (each with
/// eight lanes, which vectorise) added in order, so that results depend on
/// neither the machine nor the thread count.
#[inline]
pub fn dot(a: &[f64], b: &[f64]) -> f64 {
    par::sum_pieces(a, b, dot_dispatch)
}

crate::simd_dispatch! {
    fn dot_dispatch(a: &[f64], b: &[f64]) -> f64 => dot_piece
}

/// `Σ a` with eight independent partial sums (a single running sum waits
/// on each addition; this one vectorises).
#[inline(always)]
pub fn sum_piece(a: &[f64]) -> f64 {
    let mut acc = [0.0f64; 8];
    let ca = a.chunks_exact(8);
    let tail: f64 = ca.remainder().iter().sum();
    for x in ca {
        for k in 0..8 {
            acc[k] += x[k];
        }
    }
    acc.iter().sum::<f64>() + tail
}

/// `a·b` with eight independent partial sums.
#[inline(always)]
pub fn dot_piece(a: &[f64], b: &[f64]) -> f64 {
    let mut acc = [0.0f64; 8];
    let (ca, cb) = (a.chunks_exact(8), b.chunks_exact(8));
    let tail: f64 = ca.remainder().iter().zip(cb.remainder()).map(|(x, y)| x * y).sum();
    for (x, y) in ca.zip(cb) {
        for k in 0..8 {
            acc[k] += x[k] * y[k];
        }
    }
    acc.iter().sum::<f64>() + tail
}

#[cfg(test)]
mod tests {
    use super::*;

    /// `tridiag(−1, 2 + s, −1)`: symmetric positive definite.
    struct Tridiagonal(f64);

    impl System for Tridiagonal {
        fn apply(&mut self, p: &[f64], out: &mut [f64]) {
            let n = p.len();
            for i in 0..n {
                let l = if i > 0 { p[i - 1] } else { 0.0 };
                let r = if i + 1 < n { p[i + 1] } else { 0.0 };
                out[i] = (2.0 + self.0) * p[i] - l - r;
            }
        }
        fn precondition(&mut self, _r: &[f64], _z: &mut [f64]) -> bool {
            false
        }
        fn null(&self) -> Null<'_> {
            Null::None
        }
    }

    /// The eight-lane maximum agrees with a plain fold on every length and
    /// position, and a NaN or an infinity anywhere (a lane or the tail)
    /// comes out as the scalar loop says: NaN for NaN, infinity otherwise.
    #[test]
    fn max_abs_finds_the_largest_and_never_skips_a_nan() {
        assert_eq!(max_abs(&[]), 0.0);
        for len in [1usize, 7, 8, 9, 23, 64, 4097] {
            let v: Vec<f64> = (0..len).map(|i| ((i * 37 % 101) as f64 - 50.0) * 0.1).collect();
            let fold = v.iter().fold(0.0f64, |m, x| m.max(x.abs()));
            assert_eq!(max_abs(&v), fold, "length {len}");
            for at in [0, len / 2, len - 1] {
                let mut w = v.clone();
                w[at] = f64::NAN;
                assert!(max_abs(&w).is_nan(), "NaN at {at} of {len}");
                w[at] = f64::NEG_INFINITY;
                assert_eq!(max_abs(&w), f64::INFINITY, "infinity at {at} of {len}");
                w[at] = -1e300;
                assert_eq!(max_abs(&w), 1e300, "-1e300 at {at} of {len}");
            }
        }
    }

    /// CG recovers a known solution to its tolerance, warm starts from a
    /// solution in no iterations, and too few iterations are an error with
    /// the residual reached.
    #[test]
    fn cg_solves_a_definite_system_and_reports_what_it_could_not() {
        let n = 50;
        let truth: Vec<f64> = (0..n).map(|i| (0.2 * i as f64).sin()).collect();
        let mut sys = Tridiagonal(0.01);
        let mut b = vec![0.0; n];
        sys.apply(&truth, &mut b);
        let mut work = CgWork::new(n);
        let mut p = vec![0.0; n];
        let stop = Stop { tolerance: 1e-12, max_iterations: 500 };
        let its = solve(&mut sys, &mut work, stop, &b, &mut p, false).unwrap();
        assert!(its > 0 && its <= n + 5, "{its} iterations");
        let err = p.iter().zip(&truth).map(|(a, b)| (a - b).abs()).fold(0.0, f64::max);
        assert!(err < 1e-8, "{err}");
        assert_eq!(solve(&mut sys, &mut work, stop, &b, &mut p, true).unwrap(), 0);
        let short = Stop { tolerance: 1e-12, max_iterations: 3 };
        let e = solve(&mut sys, &mut work, short, &b, &mut vec![0.0; n], false).unwrap_err();
        assert!(e.relative_residual > 1e-12 && e.relative_residual.is_finite(), "{e}");
    }
}
