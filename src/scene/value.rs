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
