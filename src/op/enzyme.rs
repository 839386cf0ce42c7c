//! Enzyme-generated derivatives for plain functions: the [`differentiable!`]
//! macro and the validation it runs before every generated call.
//!
//! A panic inside a generated function cannot be caught (the process
//! aborts), so every size is checked here first, with a message naming the
//! operator and the slice.

use std::cell::RefCell;

use super::Operator;

/// Makes a plain function `fn(&Op, x: &[f64], p: &[f64], y: &mut [f64])` the
/// forward of the operator type `Op`, and implements [`Forward`](crate::op::Forward),
/// [`Vjp`](crate::op::Vjp) and [`Jvp`](crate::op::Jvp) for `Op` with Enzyme.
///
/// `Op` must implement [`Operator`](crate::op::Operator) (its sizes) and be
/// plain data: numbers, arrays, nested plain structs. Boxed trait objects or
/// function pointers inside it make Enzyme's gradient silently wrong.
///
/// The function must write every element of `y` and may read `x`, `p` and
/// the fields of `Op`. Use preallocated buffers, not `Vec` growth, inside.
///
/// A piecewise-smooth operator names its [`Forward::smooth_radius`](crate::op::Forward::smooth_radius)
/// function as a second argument: `differentiable!(Op => f, smooth_radius = g)`
/// with `fn g(&Op, x, p, dx, dp) -> f64`.
///
/// The crate that invokes this macro needs `#![feature(autodiff)]`, the
/// `-Zautodiff=Enable` flag and a fat-LTO release build (see the README).
///
/// ```ignore
/// #![feature(autodiff)]
/// use diffsim::op::{Operator, OperatorExt};
///
/// struct Scale { n: usize }
/// impl Operator for Scale {
///     fn n_in(&self) -> usize { self.n }
///     fn n_out(&self) -> usize { self.n }
///     fn n_params(&self) -> usize { 1 }
/// }
/// fn scale(op: &Scale, x: &[f64], p: &[f64], y: &mut [f64]) {
///     for i in 0..op.n { y[i] = p[0] * x[i] * x[i]; }
/// }
/// diffsim::differentiable!(Scale => scale);
///
/// let op = Scale { n: 3 };
/// let (dx, dp) = op.vjp_new(&[1.0, 2.0, 3.0], &[2.0], &[1.0, 1.0, 1.0]);
/// assert_eq!(dx, vec![4.0, 8.0, 12.0]);
/// assert_eq!(dp, vec![14.0]);
/// ```
#[macro_export]
macro_rules! differentiable {
    ($ty:ty => $f:path) => {
        $crate::differentiable!($ty => $f, smooth_radius = $crate::op::always_smooth);
    };
    ($ty:ty => $f:path, smooth_radius = $radius:path) => {
        #[allow(clippy::too_many_arguments)]
        const _: () = {
            #[::std::autodiff::autodiff_reverse(diffsim_generated_vjp, Const, Duplicated, Duplicated, Duplicated)]
            fn diffsim_reverse_wrapper(op: &$ty, x: &[f64], p: &[f64], y: &mut [f64]) {
                $f(op, x, p, y)
            }

            #[::std::autodiff::autodiff_forward(diffsim_generated_jvp, Const, Dual, Dual, Dual)]
            fn diffsim_forward_wrapper(op: &$ty, x: &[f64], p: &[f64], y: &mut [f64]) {
                $f(op, x, p, y)
            }

            impl $crate::op::Forward for $ty {
                #[track_caller]
                fn forward(&self, x: &[f64], p: &[f64], y: &mut [f64]) {
                    $crate::op::validate_forward(self, ::std::stringify!($ty), x, p, y);
                    $crate::op::count::record(::std::stringify!($ty), $crate::op::count::Method::Forward);
                    $f(self, x, p, y)
                }

                fn smooth_radius(&self, x: &[f64], p: &[f64], dx: &[f64], dp: &[f64]) -> f64 {
                    $radius(self, x, p, dx, dp)
                }
            }

            impl $crate::op::Vjp for $ty {
                #[inline(never)]
                #[track_caller]
                fn vjp(&self, x: &[f64], p: &[f64], dy: &mut [f64], dx: &mut [f64], dp: &mut [f64]) {
                    $crate::op::validate_vjp(self, ::std::stringify!($ty), x, p, dy, dx, dp);
                    $crate::op::count::record(::std::stringify!($ty), $crate::op::count::Method::Vjp);
                    // The primal output goes to scratch. `Duplicated`, not
                    // `DuplicatedOnly`: with the latter, a function that reads
                    // back what it wrote to `y` got a wrong derivative (README,
                    // Enzyme notes).
                    $crate::op::with_scratch($crate::op::Operator::n_out(self), |y| {
                        diffsim_generated_vjp(self, x, dx, p, dp, y, dy);
                    });
                }
            }

            impl $crate::op::Jvp for $ty {
                #[inline(never)]
                #[track_caller]
                fn jvp(&self, x: &[f64], p: &[f64], tx: &[f64], tp: &[f64], y: &mut [f64], ty: &mut [f64]) {
                    $crate::op::validate_jvp(self, ::std::stringify!($ty), x, p, tx, tp, y, ty);
                    $crate::op::count::record(::std::stringify!($ty), $crate::op::count::Method::Jvp);
                    diffsim_generated_jvp(self, x, tx, p, tp, y, ty);
                }
            }
        };
    };
}

/// The smoothness radius of a smooth operator: `∞`.
#[doc(hidden)]
pub fn always_smooth<O: ?Sized, T>(_: &O, _: &[T], _: &[T], _: &[T], _: &[T]) -> f64 {
    f64::INFINITY
}

thread_local! {
    static SCRATCH: RefCell<Vec<f64>> = const { RefCell::new(Vec::new()) };
}

/// Runs `f` with a per-thread scratch buffer of length `n` (contents
/// unspecified). Generated reverse passes write their primal output there.
#[doc(hidden)]
pub fn with_scratch<R>(n: usize, f: impl FnOnce(&mut [f64]) -> R) -> R {
    SCRATCH.with(|cell| match cell.try_borrow_mut() {
        Ok(mut buf) => {
            if buf.len() < n {
                buf.resize(n, 0.0);
            }
            f(&mut buf[..n])
        }
        // Re-entrant use (an operator whose forward calls another generated
        // adjoint): fall back to a fresh buffer.
        Err(_) => f(&mut vec![0.0; n]),
    })
}

#[track_caller]
fn check_len(op: &str, what: &str, got: usize, want: usize) {
    if got != want {
        panic!("{op}: `{what}` has length {got}, the operator expects {want}");
    }
}

/// Checks the slice lengths of a forward call.
#[doc(hidden)]
#[track_caller]
pub fn validate_forward<O: Operator + ?Sized, T>(op: &O, name: &str, x: &[T], p: &[T], y: &[T]) {
    check_len(name, "x", x.len(), op.n_in());
    check_len(name, "p", p.len(), op.n_params());
    check_len(name, "y", y.len(), op.n_out());
}

/// Checks the slice lengths of a VJP call.
#[doc(hidden)]
#[track_caller]
pub fn validate_vjp<O: Operator + ?Sized, T>(op: &O, name: &str, x: &[T], p: &[T], dy: &[T], dx: &[T], dp: &[T]) {
    check_len(name, "x", x.len(), op.n_in());
    check_len(name, "p", p.len(), op.n_params());
    check_len(name, "dy", dy.len(), op.n_out());
    check_len(name, "dx", dx.len(), op.n_in());
    check_len(name, "dp", dp.len(), op.n_params());
}

/// Checks the slice lengths of a JVP call.
#[doc(hidden)]
#[track_caller]
#[allow(clippy::too_many_arguments)]
pub fn validate_jvp<O: Operator + ?Sized, T>(op: &O, name: &str, x: &[T], p: &[T], tx: &[T], tp: &[T], y: &[T], ty: &[T]) {
    check_len(name, "x", x.len(), op.n_in());
    check_len(name, "p", p.len(), op.n_params());
    check_len(name, "tx", tx.len(), op.n_in());
    check_len(name, "tp", tp.len(), op.n_params());
    check_len(name, "y", y.len(), op.n_out());
    check_len(name, "ty", ty.len(), op.n_out());
}
