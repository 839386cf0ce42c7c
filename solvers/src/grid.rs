//! Index rules of one axis of a cell grid, shared by every dimension.
//!
//! A 2D or 3D grid is a product of axes, and each of its rules (where a
//! traced point falls, which cell follows another, which cells lie beside a
//! face) acts on one axis at a time: bilinear and trilinear sampling
//! multiply the per-axis weights of [`axis_position`], and the MAC grids of
//! [`crate::smoke`] (2D and 3D) average velocities over
//! the cells of [`next`] and [`beside`]. An axis either wraps (periodic) or
//! is bounded (every other boundary kind: samples clamp to it).

/// Where a coordinate `r` (in samples) falls on an axis of `m ≥ 2` samples:
/// the two samples it lies between and the fraction past the first. Clamped
/// to the axis (P2's rule; the lower sample kept one short of the last) or,
/// when `WRAP`, wrapped around the period `m`.
#[inline(always)]
pub fn axis_position<const WRAP: bool>(m: usize, r: f64) -> (usize, usize, f64) {
    if WRAP {
        // The floor by truncation (no libm call: `f64::floor` is one on the
        // baseline x86-64 target), then the cell wrapped into the period,
        // by one addition or subtraction for a point within a period of the
        // box (any trace of a stable step) and by a division otherwise.
        let t = r as i64;
        let fl = t - (r < t as f64) as i64;
        let mi = m as i64;
        let k = if fl < 0 && fl >= -mi {
            fl + mi
        } else if fl >= mi && fl < 2 * mi {
            fl - mi
        } else {
            fl.rem_euclid(mi)
        };
        let k0 = k as usize;
        (k0, if k0 + 1 == m { 0 } else { k0 + 1 }, r - fl as f64)
    } else {
        let g = r.clamp(0.0, (m - 1) as f64);
        // g ≥ 0, so truncation is the floor (one instruction, no libm call).
        let k0 = (g as usize).min(m - 2);
        (k0, k0 + 1, g - k0 as f64)
    }
}

/// Whether a sample position `r` moves the clamped sample of an axis of `m`
/// samples (inside the range, edges included, or on a wrapping axis): the
/// factor, 1 or 0, by which the adjoint of sampling passes `∂/∂r`, as
/// Enzyme's derivative of `f64::clamp` does.
#[inline(always)]
pub fn axis_passes<const WRAP: bool>(m: usize, r: f64) -> f64 {
    if WRAP || (r >= 0.0 && r <= (m - 1) as f64) { 1.0 } else { 0.0 }
}

/// The cell after cell `k` along an axis of `n` cells: `k + 1`, or `0` past
/// the last cell of a wrapping axis.
#[inline(always)]
pub fn next<const WRAP: bool>(n: usize, k: usize) -> usize {
    if WRAP && k + 1 == n { 0 } else { k + 1 }
}

/// The two cells beside face `k` of an axis of `n` cells: wrapped, or
/// clamped to the box (the edge-extended copy of P2 and P4).
#[inline(always)]
pub fn beside<const WRAP: bool>(n: usize, k: usize) -> (usize, usize) {
    if WRAP { (if k == 0 { n - 1 } else { k - 1 }, k) } else { (k.saturating_sub(1).min(n - 1), k.min(n - 1)) }
}

/// Faces of an axis of `n` cells that hold their own value: `n + 1`, or `n`
/// when the axis wraps (face `n` is a copy of face `0`).
#[inline(always)]
pub fn own_faces<const WRAP: bool>(n: usize) -> usize {
    if WRAP { n } else { n + 1 }
}

/// How far a sample position `pos` (in samples) may move at `speed` before
/// it crosses a lattice line, where linear sampling kinks: its distance to
/// the nearest whole number over `|speed|` (∞ when the speed is 0).
#[inline(always)]
pub fn lattice_gap(pos: f64, speed: f64) -> f64 {
    if speed == 0.0 { f64::INFINITY } else { (pos - pos.round()).abs() / speed.abs() }
}

/// [`axis_position`] for an axis that wraps when `wrap` (a value known at
/// run time, or folded away where it is a constant).
#[inline(always)]
pub fn position(wrap: bool, m: usize, r: f64) -> (usize, usize, f64) {
    if wrap { axis_position::<true>(m, r) } else { axis_position::<false>(m, r) }
}

/// [`axis_passes`] for an axis that wraps when `wrap`.
#[inline(always)]
pub fn passes(wrap: bool, m: usize, r: f64) -> f64 {
    if wrap { axis_passes::<true>(m, r) } else { axis_passes::<false>(m, r) }
}
