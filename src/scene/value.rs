//! Single values of a scene file checked against their range, the key named
//! in the error. A leaf: the builder and the initial values both use it.

use super::SceneError;

/// `v` if it is positive and finite.
pub(super) fn positive(key: &str, v: f64) -> Result<f64, SceneError> {
    if v.is_finite() && v > 0.0 { Ok(v) } else { Err(SceneError::key(key, format!("must be a positive finite number, got {v}"))) }
}

/// `v` if it is finite.
pub(super) fn finite(key: &str, v: f64) -> Result<f64, SceneError> {
    if v.is_finite() { Ok(v) } else { Err(SceneError::key(key, format!("must be finite, got {v}"))) }
}

/// `v` as a count if it is at least 1.
pub(super) fn count(key: &str, v: i64) -> Result<usize, SceneError> {
    if v >= 1 { Ok(v as usize) } else { Err(SceneError::key(key, format!("must be at least 1, got {v}"))) }
}

/// The smallest relative tolerance a solve in double precision reaches
/// (relative residuals stall near 1e-16).
pub(super) const MIN_TOLERANCE: f64 = 1e-15;

/// `v` as a solve's relative tolerance: positive, and not below what
/// double precision reaches (an unreachable tolerance would run every solve
/// to its iteration cap).
pub(super) fn tolerance(key: &str, v: f64) -> Result<f64, SceneError> {
    let v = positive(key, v)?;
    if v < MIN_TOLERANCE {
        return Err(SceneError::key(
            key,
            format!("{v:e} is below what double precision reaches (relative residuals stall near 1e-16); use at least {MIN_TOLERANCE:e}"),
        ));
    }
    Ok(v)
}

/// `v` as the iteration cap of an iterative solve over `unknowns` values:
/// at least 1 and at most 10 per unknown plus 1000 (conjugate gradients
/// converge in at most one iteration per unknown in exact arithmetic; a
/// larger cap only lets a hopeless solve run for hours).
pub(super) fn iterations(key: &str, v: i64, unknowns: usize) -> Result<usize, SceneError> {
    let n = count(key, v)?;
    let cap = unknowns.saturating_mul(10).saturating_add(1000);
    if n > cap {
        return Err(SceneError::key(
            key,
            format!(
                "{n} iterations is more than 10 per unknown of the grid plus 1000 ({cap}); conjugate gradients need at most one per unknown in exact arithmetic"
            ),
        ));
    }
    Ok(n)
}
