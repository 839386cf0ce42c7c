//! Run-time choice of vector instructions for hot loops.
//!
//! The default build targets baseline x86-64 (SSE2, two `f64` lanes) so that
//! the binary runs anywhere. [`simd_dispatch!`](crate::simd_dispatch)
//! compiles a loop body three times — for AVX-512 (eight lanes), AVX2 (four)
//! and the baseline — and picks the widest the CPU supports when called.
//! The arithmetic is the same in all three (Rust never contracts `a*b + c`
//! into a fused multiply-add on its own), so results are bit-identical.

/// Defines `fn $name(args) [-> ret]` that calls `$body(args)` compiled for the widest
/// of AVX-512F, AVX2 and baseline x86-64 that the CPU supports. `$body` should
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
                if ::std::is_x86_feature_detected!("avx512f") {
                    // SAFETY: the CPU supports AVX-512F, checked just above.
                    return unsafe { wide($($arg),*) };
                }
                if ::std::is_x86_feature_detected!("avx2") {
                    // SAFETY: the CPU supports AVX2, checked just above.
                    return unsafe { medium($($arg),*) };
                }
            }
            $body($($arg),*)
        }
    };
}
