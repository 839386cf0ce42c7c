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
/// function: `differentiable!(Op => f, smooth_radius = g)` with
/// `fn g(&Op, x, p, dx, dp) -> f64`.
///
/// A function that needs working memory for intermediate fields takes it as
/// a fifth argument, `fn f(&Op, x, p, y, scratch: &mut [f64])`, and names the
/// length it needs: `differentiable!(Op => f, scratch = len)` with
/// `fn len(&Op) -> usize` (after `smooth_radius = g` when both are given).
/// The framework lends a per-thread buffer of that length (contents
/// unspecified: `f` writes an element before reading it) and, for the
/// derivatives, its zeroed shadow. An allocation inside the differentiated
/// function works too, but Enzyme then differentiates the allocator calls
/// (it warns `freeing without malloc` for `vec![0.0; n]`).
///
/// An ensemble of small systems, each sample with its own parameters (a
/// control per sample), gains from running [`LANES`](crate::op::LANES)
/// samples side by side: `differentiable!(Op => f, lanes = g)` with the lane
/// form `fn g(&Op, x, p, y)` on `LANES` samples at once, value `c` of lane
/// `l` at `c·LANES + l` (usually `f`'s body inside `for l in 0..LANES`).
/// Enzyme differentiates `g` too, and [`Forward::forward_each`](crate::op::Forward::forward_each)
/// and [`Vjp::vjp_each`](crate::op::Vjp::vjp_each) run it compiled for the
/// CPU's widest vector instructions ([`crate::op::lanes`]). `g` must give
/// each lane what `f` gives its sample (tested by
/// `user_op::lane_forms_match_their_per_sample_operator`).
///
/// The crate that invokes this macro needs `#![feature(autodiff)]`, the
/// `-Zautodiff=Enable` flag and a fat-LTO release build (docs/own-solver.md).
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
        $crate::differentiable!(@impl $ty => $f, $crate::op::always_smooth, plain, $crate::op::no_scratch, none);
    };
    ($ty:ty => $f:path, lanes = $g:path) => {
        $crate::differentiable!(@impl $ty => $f, $crate::op::always_smooth, plain, $crate::op::no_scratch, ($g));
    };
    ($ty:ty => $f:path, smooth_radius = $radius:path) => {
        $crate::differentiable!(@impl $ty => $f, $radius, plain, $crate::op::no_scratch, none);
    };
    ($ty:ty => $f:path, scratch = $len:path) => {
        $crate::differentiable!(@impl $ty => $f, $crate::op::always_smooth, scratch, $len, none);
    };
    ($ty:ty => $f:path, smooth_radius = $radius:path, scratch = $len:path) => {
        $crate::differentiable!(@impl $ty => $f, $radius, scratch, $len, none);
    };
    // The lane form's generated adjoint and batch methods, when there is one.
    (@lanes_reverse $ty:ty, none) => {};
    (@lanes_reverse $ty:ty, ($g:path)) => {
        #[::std::autodiff::autodiff_reverse(diffsim_generated_lanes_vjp, Const, Duplicated, Duplicated, Duplicated)]
        fn diffsim_lanes_reverse_wrapper(op: &$ty, x: &[f64], p: &[f64], y: &mut [f64]) {
            $g(op, x, p, y)
        }
    };
    (@lanes_forward $ty:ty, none) => {};
    (@lanes_forward $ty:ty, ($g:path)) => {
        #[track_caller]
        fn forward_each(&self, xs: &[f64], ps: &[f64], ys: &mut [f64]) {
            use $crate::op::Operator as _;
            let sizes = [self.n_in(), self.n_params(), self.n_out()];
            let count = $crate::op::forward_each_count(self, xs, ps, ys);
            $crate::op::count::record(::std::stringify!($ty), $crate::op::count::Method::Forward);
            $crate::op::lanes::forward_each(sizes, count, xs, ps, ys, |x, p, y| $g(self, x, p, y));
        }
    };
    (@lanes_vjp $ty:ty, none) => {};
    (@lanes_vjp $ty:ty, ($g:path)) => {
        #[inline(never)]
        #[track_caller]
        fn vjp_each(&self, xs: &[f64], ps: &[f64], dys: &mut [f64], dxs: &mut [f64], dps: &mut [f64]) {
            use $crate::op::Operator as _;
            let sizes = [self.n_in(), self.n_params(), self.n_out()];
            let count = $crate::op::vjp_each_count(self, xs, ps, dys, dxs, dps);
            $crate::op::count::record(::std::stringify!($ty), $crate::op::count::Method::Vjp);
            $crate::op::lanes::vjp_each(sizes, count, xs, ps, dys, dxs, dps, |x, dx, p, dp, y, dy| {
                diffsim_generated_lanes_vjp(self, x, dx, p, dp, y, dy)
            });
        }
    };
    // The user's function, with or without its scratch argument.
    (@call plain $f:path, $op:ident, $x:ident, $p:ident, $y:ident, $s:ident) => {{
        let _ = $s;
        $f($op, $x, $p, $y)
    }};
    (@call scratch $f:path, $op:ident, $x:ident, $p:ident, $y:ident, $s:ident) => {
        $f($op, $x, $p, $y, $s)
    };
    (@impl $ty:ty => $f:path, $radius:path, $mode:ident, $len:path, $lanes:tt) => {
        #[allow(clippy::too_many_arguments)]
        const _: () = {
            $crate::differentiable!(@lanes_reverse $ty, $lanes);

            // Both wrappers take the scratch (empty for a plain function), so
            // that one generated signature serves both forms.
            #[::std::autodiff::autodiff_reverse(diffsim_generated_vjp, Const, Duplicated, Duplicated, Duplicated, Duplicated)]
            fn diffsim_reverse_wrapper(op: &$ty, x: &[f64], p: &[f64], y: &mut [f64], s: &mut [f64]) {
                $crate::differentiable!(@call $mode $f, op, x, p, y, s)
            }

            #[::std::autodiff::autodiff_forward(diffsim_generated_jvp, Const, Dual, Dual, Dual, Dual)]
            fn diffsim_forward_wrapper(op: &$ty, x: &[f64], p: &[f64], y: &mut [f64], s: &mut [f64]) {
                $crate::differentiable!(@call $mode $f, op, x, p, y, s)
            }

            impl $crate::op::Forward for $ty {
                #[track_caller]
                fn forward(&self, x: &[f64], p: &[f64], y: &mut [f64]) {
                    $crate::op::validate_forward(self, ::std::stringify!($ty), x, p, y);
                    $crate::op::count::record(::std::stringify!($ty), $crate::op::count::Method::Forward);
                    $crate::op::with_scratch($len(self), |s| $crate::differentiable!(@call $mode $f, self, x, p, y, s))
                }

                fn smooth_radius(&self, x: &[f64], p: &[f64], dx: &[f64], dp: &[f64]) -> f64 {
                    $radius(self, x, p, dx, dp)
                }

                $crate::differentiable!(@lanes_forward $ty, $lanes);
            }

            impl $crate::op::Vjp for $ty {
                #[inline(never)]
                #[track_caller]
                fn vjp(&self, x: &[f64], p: &[f64], dy: &mut [f64], dx: &mut [f64], dp: &mut [f64]) {
                    $crate::op::validate_vjp(self, ::std::stringify!($ty), x, p, dy, dx, dp);
                    $crate::op::count::record(::std::stringify!($ty), $crate::op::count::Method::Vjp);
                    // The primal output goes to scratch. `Duplicated`, not
                    // `DuplicatedOnly`: with the latter, a function that reads
                    // back what it wrote to `y` got a wrong derivative (docs/pitfalls.md). The scratch's shadow starts at zero
                    // (Enzyme adds into shadows).
                    let (n, m) = ($crate::op::Operator::n_out(self), $len(self));
                    $crate::op::with_scratch(n + 2 * m, |buf| {
                        let (y, rest) = buf.split_at_mut(n);
                        let (s, ds) = rest.split_at_mut(m);
                        ds.fill(0.0);
                        diffsim_generated_vjp(self, x, dx, p, dp, y, dy, s, ds);
                    });
                }

                $crate::differentiable!(@lanes_vjp $ty, $lanes);
            }

            impl $crate::op::Jvp for $ty {
                #[inline(never)]
                #[track_caller]
                fn jvp(&self, x: &[f64], p: &[f64], tx: &[f64], tp: &[f64], y: &mut [f64], ty: &mut [f64]) {
                    $crate::op::validate_jvp(self, ::std::stringify!($ty), x, p, tx, tp, y, ty);
                    $crate::op::count::record(::std::stringify!($ty), $crate::op::count::Method::Jvp);
                    let m = $len(self);
                    $crate::op::with_scratch(2 * m, |buf| {
                        let (s, ts) = buf.split_at_mut(m);
                        ts.fill(0.0);
                        diffsim_generated_jvp(self, x, tx, p, tp, y, ty, s, ts);
                    });
                }
            }
        };
    };
}

/// The scratch length of a function without scratch: 0.
#[doc(hidden)]
pub fn no_scratch<O: ?Sized>(_: &O) -> usize {
    0
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
/// unspecified). Generated reverse passes write their primal output there,
/// and functions made with `scratch = len` get their scratch (and its
/// shadow) from it.
#[doc(hidden)]
pub fn with_scratch<R>(n: usize, f: impl FnOnce(&mut [f64]) -> R) -> R {
    if n == 0 {
        // Nothing to lend, so the buffer stays free (the forward of a
        // function without scratch runs user code, which may itself call
        // generated derivatives).
        return f(&mut []);
    }
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
