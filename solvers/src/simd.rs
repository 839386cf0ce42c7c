//! Run-time choice of vector instructions for hot loops.
//!
//! The default build targets baseline x86-64 (SSE2, two `f64` lanes) so that
//! the binary runs anywhere. [`simd_dispatch!`](crate::simd_dispatch)
//! compiles a loop body three times — for AVX-512 (eight lanes), AVX2 (four)
//! and the baseline — and picks the widest the CPU supports when called.
//! The arithmetic is the same in all three (Rust never contracts `a*b + c`
//! into a fused multiply-add on its own), so results are bit-identical.
//!
//! [`set_max_isa`] caps the choice, so that one machine can show how a
//! processor without AVX-512 (or without AVX2) runs the same code: the
//! command line and the Python package read [`MAX_ISA_VAR`]
//! (`DIFFSIM_MAX_ISA=avx2`) at start through [`max_isa_from_env`]. Only the
//! vector width is capped this way; another processor's caches and clocks
//! are not emulated.

use std::sync::atomic::{AtomicU8, Ordering};

/// A set of vector instructions the dispatch can choose.
#[derive(Clone, Copy, Debug, PartialEq, Eq, PartialOrd, Ord)]
pub enum Isa {
    /// Baseline x86-64: SSE2, two `f64` lanes.
    Baseline,
    /// AVX2: four `f64` lanes.
    Avx2,
    /// AVX-512F: eight `f64` lanes.
    Avx512,
}

impl Isa {
    /// The name `DIFFSIM_MAX_ISA` takes: `baseline`, `avx2` or `avx512`.
    pub fn name(self) -> &'static str {
        match self {
            Isa::Baseline => "baseline",
            Isa::Avx2 => "avx2",
            Isa::Avx512 => "avx512",
        }
    }

    /// Parses [`Isa::name`] (case-insensitive).
    pub fn parse(s: &str) -> Option<Isa> {
        [Isa::Baseline, Isa::Avx2, Isa::Avx512].into_iter().find(|i| s.eq_ignore_ascii_case(i.name()))
    }
}

/// The environment variable that caps the dispatch (see [`max_isa_from_env`]).
pub const MAX_ISA_VAR: &str = "DIFFSIM_MAX_ISA";

/// An invalid [`MAX_ISA_VAR`].
#[derive(Clone, Debug, PartialEq, Eq)]
pub struct IsaError {
    /// The value found.
    pub value: String,
}

impl std::fmt::Display for IsaError {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        write!(f, "environment variable {MAX_ISA_VAR}={:?}: expected avx512, avx2 or baseline", self.value)
    }
}

impl std::error::Error for IsaError {}

/// The cap set by [`set_max_isa`], as `Isa as u8`; no cap by default.
static MAX_ISA: AtomicU8 = AtomicU8::new(Isa::Avx512 as u8);

/// Caps the vector instructions every dispatch in diffsim chooses from
/// (the widest the processor has, at most `isa`) for the rest of the
/// process. Results are the same bits at any cap; only the time changes.
pub fn set_max_isa(isa: Isa) {
    MAX_ISA.store(isa as u8, Ordering::Relaxed);
}

/// Sets the cap from [`MAX_ISA_VAR`] if it is set, and returns it; unset,
/// nothing changes.
///
/// # Errors
/// The variable holds something other than `avx512`, `avx2` or `baseline`
/// (the cap is then left as it was).
pub fn max_isa_from_env() -> Result<Option<Isa>, IsaError> {
    let Some(value) = std::env::var_os(MAX_ISA_VAR) else { return Ok(None) };
    let value = value.to_string_lossy().into_owned();
    let isa = Isa::parse(value.trim()).ok_or(IsaError { value })?;
    set_max_isa(isa);
    Ok(Some(isa))
}

/// The instructions the dispatch chooses now: the widest the processor
/// has, at most the cap of [`set_max_isa`] (the tests the dispatches make).
pub fn isa() -> Isa {
    if avx512_allowed() {
        Isa::Avx512
    } else if avx2_allowed() {
        Isa::Avx2
    } else {
        Isa::Baseline
    }
}

/// The processor has AVX-512F and the cap allows it: the test the
/// dispatches make before calling their AVX-512 copy.
#[inline]
pub fn avx512_allowed() -> bool {
    #[cfg(target_arch = "x86_64")]
    {
        MAX_ISA.load(Ordering::Relaxed) >= Isa::Avx512 as u8 && ::std::is_x86_feature_detected!("avx512f")
    }
    #[cfg(not(target_arch = "x86_64"))]
    false
}

/// The processor has AVX2 and the cap allows it (as [`avx512_allowed`]).
#[inline]
pub fn avx2_allowed() -> bool {
    #[cfg(target_arch = "x86_64")]
    {
        MAX_ISA.load(Ordering::Relaxed) >= Isa::Avx2 as u8 && ::std::is_x86_feature_detected!("avx2")
    }
    #[cfg(not(target_arch = "x86_64"))]
    false
}

/// Defines `fn $name(args) [-> ret]` that calls `$body(args)` compiled for the widest
/// of AVX-512F, AVX2 and baseline x86-64 that the CPU supports (at most the
/// cap of [`set_max_isa`]). `$body` should
/// be `#[inline(always)]` so that it is compiled inside each variant.
#[macro_export]
macro_rules! simd_dispatch {
    ($(#[$m:meta])* $vis:vis fn $name:ident($($arg:ident: $ty:ty),* $(,)?) => $body:path) => {
        $crate::simd_dispatch! { $(#[$m])* $vis fn $name($($arg: $ty),*) -> () => $body }
    };
    ($(#[$m:meta])* $vis:vis fn $name:ident($($arg:ident: $ty:ty),* $(,)?) -> $ret:ty => $body:path) => {
        $(#[$m])*
        #[inline]
        $vis fn $name($($arg: $ty),*) -> $ret {
            #[cfg(target_arch = "x86_64")]
            {
                #[target_feature(enable = "avx512f")]
                fn wide($($arg: $ty),*) -> $ret {
                    $body($($arg),*)
                }
                #[target_feature(enable = "avx2")]
                fn medium($($arg: $ty),*) -> $ret {
                    $body($($arg),*)
                }
                if $crate::simd::avx512_allowed() {
                    // SAFETY: the CPU supports AVX-512F, checked just above.
                    return unsafe { wide($($arg),*) };
                }
                if $crate::simd::avx2_allowed() {
                    // SAFETY: the CPU supports AVX2, checked just above.
                    return unsafe { medium($($arg),*) };
                }
            }
            $body($($arg),*)
        }
    };
}

#[cfg(test)]
mod tests {
    use super::*;

    /// The cap limits the choice and the dispatched kernels give the same
    /// bits under every cap (the only test that sets it; restored after).
    #[test]
    fn the_cap_limits_the_choice_and_not_the_values() {
        let n = 1003;
        let a: Vec<f64> = (0..n).map(|i| ((i * 37 % 101) as f64 - 50.0) / 7.0).collect();
        let b: Vec<f64> = (0..n).map(|i| ((i * 53 % 97) as f64).sqrt() - 3.1).collect();
        let uncapped = isa();
        let mut seen = Vec::new();
        for cap in [Isa::Avx512, Isa::Avx2, Isa::Baseline] {
            set_max_isa(cap);
            assert!(isa() <= cap && isa() <= uncapped, "{:?} under the cap {cap:?}", isa());
            seen.push((crate::cg::dot(&a, &b).to_bits(), crate::cg::max_abs(&a).to_bits()));
        }
        set_max_isa(Isa::Avx512);
        assert_eq!(isa(), uncapped);
        assert!(seen.windows(2).all(|w| w[0] == w[1]), "{seen:?}");
        assert_eq!(Isa::parse("AVX2"), Some(Isa::Avx2));
        assert_eq!(Isa::parse(" avx2"), None);
        let e = IsaError { value: "sse9".into() };
        assert_eq!(e.to_string(), "environment variable DIFFSIM_MAX_ISA=\"sse9\": expected avx512, avx2 or baseline");
    }
}
