//! Explicit stencil steps: Enzyme differentiates the pointwise kernel, the
//! framework applies the transpose of the stencil's shifts.
//!
//! A three-point step on a periodic 1D grid, `y[i] = k(x[i−1], x[i], x[i+1], p)`,
//! is written as a plain *map* over three shifted views of the state:
//!
//! ```text
//! fn map(op: &Op, l: &[f64], c: &[f64], r: &[f64], p: &[f64], out: &mut [f64])
//!     // out[i] = k(l[i], c[i], r[i], p) for every i
//! ```
//!
//! Differentiating the whole step makes Enzyme scatter each cell's adjoint
//! into three neighbours of one array: a loop-carried memory dependence that
//! neither vectorises nor forwards stores well (measured ≈ 7× the
//! hand-written adjoint on P1). Differentiating the map instead gives three
//! *separate* adjoint arrays `dl, dc, dr`, written elementwise (vectorised);
//! the framework then gathers `dx[j] += dc[j] + dl[j+1] + dr[j−1]`, chunk by
//! chunk so that the scratch stays in L1. On x86-64 with AVX2 the chunk loop
//! (and the generated code inlined into it) is compiled for AVX2, chosen at
//! run time.
//!
//! [`stencil3!`](crate::stencil3) generates [`Forward`](super::Forward),
//! [`Vjp`](super::Vjp) and [`Jvp`](super::Jvp) for an operator type from its
//! map.
//!
//! **Cell form** (faster, for operators without run-time parameters): the
//! step given as a scalar *cell function* `fn(op: &Op, l, c, r) -> f64`,
//! `stencil3!(cell: Op => cell)`. Enzyme differentiates the scalar
//! function (reverse mode with `Active` arguments, seed 1: the Jacobian row
//! `(∂k/∂l, ∂k/∂c, ∂k/∂r)` of one cell; forward mode with `Dual` arguments
//! for the JVP); the framework's loop gathers each cell's adjoint from the
//! entries of three rows ([`vjp3_rows`]). The generated code is inlined into that
//! loop and vectorised, and nothing else runs: no primal recomputation, no
//! reversed loop, no accumulation into zeroed arrays. On P1 (size M) this
//! took the Enzyme gradient from ≈ 1.7× to ≈ 1.2× the hand-written one.

/// Cells per chunk of the VJP: four scratch arrays of this many `f64` (16 KiB)
/// stay in L1.
pub const CHUNK: usize = 512;

use super::Real;

/// Implements [`Forward`](crate::op::Forward), [`Vjp`](crate::op::Vjp) and
/// [`Jvp`](crate::op::Jvp) for a periodic three-point stencil operator `Op`
/// from its pointwise map `fn(&Op, l, c, r, p, out)` (see the
/// [module docs](crate::op::stencil)). `Op` implements
/// [`Operator`](crate::op::Operator) with `n_in == n_out ≥ 3` and is plain
/// data. An optional `smooth_radius = g` names the operator's
/// [`Forward::smooth_radius`](crate::op::Forward::smooth_radius).
/// `stencil3!(f32: Op => map32)` does the same in single precision
/// (`Forward<f32>` etc., from a map on `f32` slices).
///
/// `stencil3!(cell: Op => k)` (and `cell f32:`) takes the scalar cell
/// function `fn(&Op, l, c, r) -> f64` instead: faster derivatives, for an
/// operator without run-time parameters (`n_params() == 0`, its constants
/// live in `Op`). `stencil3!(cell: Op => k, smooth_radius = g, parallel)`
/// also splits each forward and VJP step over two of rayon's threads on
/// grids of at least [`PAR_MIN_CELLS`] cells ([`forward3_par`],
/// [`vjp3_rows_par`]; `Op` must be `Sync`).
#[macro_export]
macro_rules! stencil3 {
    (@impl $r:ty, $ty:ty => $f:path, $radius:path) => {
        #[allow(clippy::too_many_arguments)]
        const _: () = {
            #[::std::autodiff::autodiff_reverse(diffsim_map_vjp, Const, Duplicated, Duplicated, Duplicated, Duplicated, Duplicated)]
            fn diffsim_map_reverse(op: &$ty, l: &[$r], c: &[$r], r: &[$r], p: &[$r], out: &mut [$r]) {
                $f(op, l, c, r, p, out)
            }

            #[::std::autodiff::autodiff_forward(diffsim_map_jvp, Const, Dual, Dual, Dual, Dual, Dual)]
            fn diffsim_map_forward(op: &$ty, l: &[$r], c: &[$r], r: &[$r], p: &[$r], out: &mut [$r]) {
                $f(op, l, c, r, p, out)
            }

            impl $crate::op::Forward<$r> for $ty {
                #[track_caller]
                fn forward(&self, x: &[$r], p: &[$r], y: &mut [$r]) {
                    $crate::op::validate_forward(self, ::std::stringify!($ty), x, p, y);
                    $crate::op::stencil::enter(self, ::std::stringify!($ty), $crate::op::count::Method::Forward);
                    $crate::op::stencil::forward3(x, y, |l, c, r, out| $f(self, l, c, r, p, out));
                }

                fn smooth_radius(&self, x: &[$r], p: &[$r], dx: &[$r], dp: &[$r]) -> f64 {
                    $radius(self, x, p, dx, dp)
                }
            }

            impl $crate::op::Vjp<$r> for $ty {
                #[inline(never)]
                #[track_caller]
                fn vjp(&self, x: &[$r], p: &[$r], dy: &mut [$r], dx: &mut [$r], dp: &mut [$r]) {
                    $crate::op::validate_vjp(self, ::std::stringify!($ty), x, p, dy, dx, dp);
                    $crate::op::stencil::enter(self, ::std::stringify!($ty), $crate::op::count::Method::Vjp);
                    $crate::op::stencil::vjp3::<true, $r, _>(x, dy, dx, dp, |l, dl, c, dc, r, dr, dp, y, g| {
                        diffsim_map_vjp(self, l, dl, c, dc, r, dr, p, dp, y, g)
                    });
                }

                #[inline(never)]
                #[track_caller]
                fn vjp_overwrite(&self, x: &[$r], p: &[$r], dy: &mut [$r], dx: &mut [$r], dp: &mut [$r]) {
                    $crate::op::validate_vjp(self, ::std::stringify!($ty), x, p, dy, dx, dp);
                    $crate::op::stencil::enter(self, ::std::stringify!($ty), $crate::op::count::Method::Vjp);
                    $crate::op::stencil::vjp3::<false, $r, _>(x, dy, dx, dp, |l, dl, c, dc, r, dr, dp, y, g| {
                        diffsim_map_vjp(self, l, dl, c, dc, r, dr, p, dp, y, g)
                    });
                }
            }

            impl $crate::op::Jvp<$r> for $ty {
                #[inline(never)]
                #[track_caller]
                fn jvp(&self, x: &[$r], p: &[$r], tx: &[$r], tp: &[$r], y: &mut [$r], ty: &mut [$r]) {
                    $crate::op::validate_jvp(self, ::std::stringify!($ty), x, p, tx, tp, y, ty);
                    $crate::op::stencil::enter(self, ::std::stringify!($ty), $crate::op::count::Method::Jvp);
                    $crate::op::stencil::jvp3(x, tx, y, ty, |l, tl, c, tc, r, tr, out, tout| {
                        diffsim_map_jvp(self, l, tl, c, tc, r, tr, p, tp, out, tout)
                    });
                }
            }
        };
    };
    (@cell $r:ty, $ty:ty => $f:path, $radius:path, $forward:ident, $rows:ident) => {
        #[allow(clippy::too_many_arguments)]
        const _: () = {
            #[::std::autodiff::autodiff_reverse(diffsim_cell_vjp, Const, Active, Active, Active, Active)]
            fn diffsim_cell_reverse(op: &$ty, l: $r, c: $r, r: $r) -> $r {
                $f(op, l, c, r)
            }

            #[::std::autodiff::autodiff_forward(diffsim_cell_jvp, Const, Dual, Dual, Dual, Dual)]
            fn diffsim_cell_forward(op: &$ty, l: $r, c: $r, r: $r) -> $r {
                $f(op, l, c, r)
            }

            impl $crate::op::Forward<$r> for $ty {
                #[track_caller]
                fn forward(&self, x: &[$r], p: &[$r], y: &mut [$r]) {
                    $crate::op::validate_forward(self, ::std::stringify!($ty), x, p, y);
                    $crate::op::stencil::enter_cell(self, ::std::stringify!($ty), $crate::op::count::Method::Forward);
                    $crate::op::stencil::$forward(x, y, |l, c, r, out| {
                        for (((o, &l), &c), &r) in out.iter_mut().zip(l).zip(c).zip(r) {
                            *o = $f(self, l, c, r);
                        }
                    });
                }

                fn smooth_radius(&self, x: &[$r], p: &[$r], dx: &[$r], dp: &[$r]) -> f64 {
                    $radius(self, x, p, dx, dp)
                }
            }

            impl $crate::op::Vjp<$r> for $ty {
                #[inline(never)]
                #[track_caller]
                fn vjp(&self, x: &[$r], p: &[$r], dy: &mut [$r], dx: &mut [$r], dp: &mut [$r]) {
                    $crate::op::validate_vjp(self, ::std::stringify!($ty), x, p, dy, dx, dp);
                    $crate::op::stencil::enter_cell(self, ::std::stringify!($ty), $crate::op::count::Method::Vjp);
                    $crate::op::stencil::$rows::<true, $r, _>(x, dy, dx, |l, c, r| {
                        let (_, jl, jc, jr) = diffsim_cell_vjp(self, l, c, r, 1.0);
                        (jl, jc, jr)
                    });
                    // The seed is consumed (the `Vjp::vjp` contract).
                    dy.fill(0.0);
                }

                #[inline(never)]
                #[track_caller]
                fn vjp_overwrite(&self, x: &[$r], p: &[$r], dy: &mut [$r], dx: &mut [$r], dp: &mut [$r]) {
                    $crate::op::validate_vjp(self, ::std::stringify!($ty), x, p, dy, dx, dp);
                    $crate::op::stencil::enter_cell(self, ::std::stringify!($ty), $crate::op::count::Method::Vjp);
                    $crate::op::stencil::$rows::<false, $r, _>(x, dy, dx, |l, c, r| {
                        let (_, jl, jc, jr) = diffsim_cell_vjp(self, l, c, r, 1.0);
                        (jl, jc, jr)
                    });
                }
            }

            impl $crate::op::Jvp<$r> for $ty {
                #[inline(never)]
                #[track_caller]
                fn jvp(&self, x: &[$r], p: &[$r], tx: &[$r], tp: &[$r], y: &mut [$r], ty: &mut [$r]) {
                    $crate::op::validate_jvp(self, ::std::stringify!($ty), x, p, tx, tp, y, ty);
                    $crate::op::stencil::enter_cell(self, ::std::stringify!($ty), $crate::op::count::Method::Jvp);
                    $crate::op::stencil::jvp3(x, tx, y, ty, |l, tl, c, tc, r, tr, out, tout| {
                        let m = out.len();
                        let (l, tl, c, tc, r, tr, tout) = (&l[..m], &tl[..m], &c[..m], &tc[..m], &r[..m], &tr[..m], &mut tout[..m]);
                        for i in 0..m {
                            let (v, t) = diffsim_cell_jvp(self, l[i], tl[i], c[i], tc[i], r[i], tr[i]);
                            out[i] = v;
                            tout[i] = t;
                        }
                    });
                }
            }
        };
    };
    (cell: $ty:ty => $f:path) => {
        $crate::stencil3!(@cell f64, $ty => $f, $crate::op::always_smooth, forward3, vjp3_rows);
    };
    (cell: $ty:ty => $f:path, smooth_radius = $radius:path) => {
        $crate::stencil3!(@cell f64, $ty => $f, $radius, forward3, vjp3_rows);
    };
    (cell: $ty:ty => $f:path, smooth_radius = $radius:path, parallel) => {
        $crate::stencil3!(@cell f64, $ty => $f, $radius, forward3_par, vjp3_rows_par);
    };
    (cell f32: $ty:ty => $f:path, smooth_radius = $radius:path) => {
        $crate::stencil3!(@cell f32, $ty => $f, $radius, forward3, vjp3_rows);
    };
    ($ty:ty => $f:path) => {
        $crate::stencil3!($ty => $f, smooth_radius = $crate::op::always_smooth);
    };
    ($ty:ty => $f:path, smooth_radius = $radius:path) => {
        $crate::stencil3!(@impl f64, $ty => $f, $radius);
    };
    (f32: $ty:ty => $f:path) => {
        $crate::stencil3!(@impl f32, $ty => $f, $crate::op::always_smooth);
    };
    (f32: $ty:ty => $f:path, smooth_radius = $radius:path) => {
        $crate::stencil3!(@impl f32, $ty => $f, $radius);
    };
}

/// Entry of every generated stencil method: the stencil check and the call
/// count.
#[doc(hidden)]
#[track_caller]
pub fn enter<O: super::Operator + ?Sized>(op: &O, name: &'static str, method: super::count::Method) {
    check_stencil(op, name);
    super::count::record(name, method);
}

/// Panics unless `op` maps a grid of at least 3 cells to itself.
#[doc(hidden)]
#[track_caller]
pub fn check_stencil<O: super::Operator + ?Sized>(op: &O, name: &str) {
    if op.n_in() != op.n_out() || op.n_in() < 3 {
        panic!("{name}: a three-point stencil needs n_in == n_out ≥ 3 (got {} → {})", op.n_in(), op.n_out());
    }
}

/// [`enter`] for the cell form, which also panics if the operator declares
/// run-time parameters (the cell function has none: they would be ignored
/// and their gradient silently zero).
#[doc(hidden)]
#[track_caller]
pub fn enter_cell<O: super::Operator + ?Sized>(op: &O, name: &'static str, method: super::count::Method) {
    enter(op, name, method);
    if op.n_params() != 0 {
        panic!("{name}: a cell-form stencil (`stencil3!(cell: …)`) has no run-time parameters (n_params() = {}); use the map form", op.n_params());
    }
}

/// The map of a forward step.
#[doc(hidden)]
pub trait MapForward<R>: FnMut(&[R], &[R], &[R], &mut [R]) {}
impl<R, F: FnMut(&[R], &[R], &[R], &mut [R])> MapForward<R> for F {}

/// The map's forward-mode pass.
#[doc(hidden)]
pub trait MapJvp<R>: FnMut(&[R], &[R], &[R], &[R], &[R], &[R], &mut [R], &mut [R]) {}
impl<R, F: FnMut(&[R], &[R], &[R], &[R], &[R], &[R], &mut [R], &mut [R])> MapJvp<R> for F {}

/// `y[i] = k(x[i−1], x[i], x[i+1])` on a periodic grid, through the map `f`.
#[doc(hidden)]
#[inline]
pub fn forward3<R: Real, F: MapForward<R>>(x: &[R], y: &mut [R], f: F) {
    dispatch_generic!(forward3_body, [R: Real, F: MapForward<R>], x: &[R], y: &mut [R], f: F)
}

#[inline(always)]
fn forward3_body<R: Real>(x: &[R], y: &mut [R], mut f: impl MapForward<R>) {
    let n = x.len();
    f(&x[..n - 2], &x[1..n - 1], &x[2..], &mut y[1..n - 1]);
    forward3_ends(x, y, &mut f);
}

/// The two end cells of [`forward3`], whose neighbours wrap around.
#[inline(always)]
fn forward3_ends<R: Real>(x: &[R], y: &mut [R], f: &mut impl MapForward<R>) {
    let n = x.len();
    for (i, il, ir) in [(0, n - 1, 1), (n - 1, n - 2, 0)] {
        let mut out = [R::zero()];
        f(&[x[il]], &[x[i]], &[x[ir]], &mut out);
        y[i] = out[0];
    }
}

/// Grids at least this large split a step over two threads in
/// [`forward3_par`] and [`vjp3_rows_par`]. A `rayon::join` per step costs about 2 µs; P1's
/// forward on two threads against one (AVX2, 2 cores, best of 15 runs):
/// 1.12× at 4096 cells, 1.19× at 8192, 1.45× at 16384, 1.89× at 65536
/// (medians inside `diffsim bench p1` at 16384: 1.0–1.46×, depending on how
/// busy the machine is).
pub const PAR_MIN_CELLS: usize = 16384;
// The split paths handle the four cells next to the ends apart.
const _: () = assert!(PAR_MIN_CELLS >= 8);

/// Whether a step on `n` cells is split over two threads: at least
/// [`PAR_MIN_CELLS`] cells and more than one thread in the current rayon
/// pool.
#[doc(hidden)]
pub fn split_pays(n: usize) -> bool {
    n >= PAR_MIN_CELLS && rayon::current_num_threads() >= 2
}

/// Runs `f(part, start)` on the two halves of `out[from..to]` (split at
/// `out.len() / 2`) with `rayon::join`; `start` is the index in `out` of the
/// half's first element.
#[doc(hidden)]
pub fn join_halves<R: Send>(out: &mut [R], from: usize, to: usize, f: impl Fn(&mut [R], usize) + Sync) {
    let mid = out.len() / 2;
    let (lo, hi) = out.split_at_mut(mid);
    rayon::join(|| f(&mut lo[from..], from), || f(&mut hi[..to - mid], mid));
}

/// [`forward3`] with the interior split in two halves run by
/// `rayon::join` when the grid has at least [`PAR_MIN_CELLS`] cells and the
/// current rayon pool more than one thread. Every cell is computed by the
/// same code as in [`forward3`], so the result is the same bit for bit.
#[doc(hidden)]
pub fn forward3_par<R: Real, F: Fn(&[R], &[R], &[R], &mut [R]) + Sync>(x: &[R], y: &mut [R], f: F) {
    let n = x.len();
    if !split_pays(n) {
        return forward3(x, y, &f);
    }
    join_halves(y, 1, n - 1, |part, s| map_range(x, s, part, &f));
    forward3_ends(x, y, &mut &f);
}

/// `out[i] = k(x[s+i−1], x[s+i], x[s+i+1])` for the cells `s..s+out.len()`
/// (`1 ≤ s`, `s + out.len() ≤ n − 1`), vectorised like [`forward3`].
#[inline]
fn map_range<R: Real, F: Fn(&[R], &[R], &[R], &mut [R])>(x: &[R], s: usize, out: &mut [R], f: F) {
    dispatch_generic!(map_range_body, [R: Real, F: Fn(&[R], &[R], &[R], &mut [R])], x: &[R], s: usize, out: &mut [R], f: F)
}

#[inline(always)]
fn map_range_body<R: Real>(x: &[R], s: usize, out: &mut [R], f: impl Fn(&[R], &[R], &[R], &mut [R])) {
    let m = out.len();
    f(&x[s - 1..s - 1 + m], &x[s..s + m], &x[s + 1..s + 1 + m], out);
}

/// Tangent of [`forward3`]: the map's JVP over the shifted views of the
/// state and of the tangent.
#[doc(hidden)]
#[inline]
pub fn jvp3<R: Real, F: MapJvp<R>>(x: &[R], t: &[R], y: &mut [R], ty: &mut [R], f: F) {
    dispatch_generic!(jvp3_body, [R: Real, F: MapJvp<R>], x: &[R], t: &[R], y: &mut [R], ty: &mut [R], f: F)
}

#[inline(always)]
fn jvp3_body<R: Real>(x: &[R], t: &[R], y: &mut [R], ty: &mut [R], mut f: impl MapJvp<R>) {
    let n = x.len();
    f(&x[..n - 2], &t[..n - 2], &x[1..n - 1], &t[1..n - 1], &x[2..], &t[2..], &mut y[1..n - 1], &mut ty[1..n - 1]);
    for (i, il, ir) in [(0, n - 1, 1), (n - 1, n - 2, 0)] {
        let (mut out, mut tout) = ([R::zero()], [R::zero()]);
        f(&[x[il]], &[t[il]], &[x[i]], &[t[i]], &[x[ir]], &[t[ir]], &mut out, &mut tout);
        y[i] = out[0];
        ty[i] = tout[0];
    }
}

/// The map's reverse pass: `f(l, dl, c, dc, r, dr, dp, y, g)` adds the
/// adjoints of its three inputs into `dl, dc, dr` (and of the parameters into
/// `dp`) and consumes the seed `g`.
#[doc(hidden)]
pub trait MapVjp<R>: FnMut(&[R], &mut [R], &[R], &mut [R], &[R], &mut [R], &mut [R], &mut [R], &mut [R]) {}
impl<R, F: FnMut(&[R], &mut [R], &[R], &mut [R], &[R], &mut [R], &mut [R], &mut [R], &mut [R])> MapVjp<R> for F {}

/// `dx += Jᵀ·g` (`ADD`) or `dx = Jᵀ·g`, and `dp += J_pᵀ·g`, for a periodic
/// three-point stencil, from the reverse pass of its map; consumes `g`.
#[doc(hidden)]
#[inline]
pub fn vjp3<const ADD: bool, R: Real, F: MapVjp<R>>(x: &[R], g: &mut [R], dx: &mut [R], dp: &mut [R], f: F) {
    if ADD {
        dispatch_generic!(vjp3_add, [R: Real, F: MapVjp<R>], x: &[R], g: &mut [R], dx: &mut [R], dp: &mut [R], f: F)
    } else {
        dispatch_generic!(vjp3_overwrite, [R: Real, F: MapVjp<R>], x: &[R], g: &mut [R], dx: &mut [R], dp: &mut [R], f: F)
    }
}

#[inline(always)]
fn vjp3_add<R: Real>(x: &[R], g: &mut [R], dx: &mut [R], dp: &mut [R], f: impl MapVjp<R>) {
    vjp3_body::<true, R>(x, g, dx, dp, f)
}

#[inline(always)]
fn vjp3_overwrite<R: Real>(x: &[R], g: &mut [R], dx: &mut [R], dp: &mut [R], f: impl MapVjp<R>) {
    vjp3_body::<false, R>(x, g, dx, dp, f)
}

/// `dx += Jᵀ·g` (`ADD`) or `dx = Jᵀ·g` for a periodic three-point stencil
/// from its Jacobian rows: `f(l, c, r)` returns `(∂k/∂l, ∂k/∂c, ∂k/∂r)` of
/// the cell function at one cell, and `dx[j] (+)= g[j]·∂_c k_j +
/// g[j+1]·∂_l k_{j+1} + g[j−1]·∂_r k_{j−1}` is gathered in one pass; `g` is
/// left unchanged.
#[doc(hidden)]
#[inline]
pub fn vjp3_rows<const ADD: bool, R: Real, F: FnMut(R, R, R) -> (R, R, R)>(x: &[R], g: &[R], dx: &mut [R], f: F) {
    if ADD {
        dispatch_generic!(vjp3_rows_add, [R: Real, F: FnMut(R, R, R) -> (R, R, R)], x: &[R], g: &[R], dx: &mut [R], f: F)
    } else {
        dispatch_generic!(vjp3_rows_overwrite, [R: Real, F: FnMut(R, R, R) -> (R, R, R)], x: &[R], g: &[R], dx: &mut [R], f: F)
    }
}

#[inline(always)]
fn vjp3_rows_add<R: Real>(x: &[R], g: &[R], dx: &mut [R], f: impl FnMut(R, R, R) -> (R, R, R)) {
    vjp3_rows_body::<true, R>(x, g, dx, f)
}

#[inline(always)]
fn vjp3_rows_overwrite<R: Real>(x: &[R], g: &[R], dx: &mut [R], f: impl FnMut(R, R, R) -> (R, R, R)) {
    vjp3_rows_body::<false, R>(x, g, dx, f)
}

#[inline(always)]
fn vjp3_rows_body<const ADD: bool, R: Real>(x: &[R], g: &[R], dx: &mut [R], mut f: impl FnMut(R, R, R) -> (R, R, R)) {
    let n = x.len();
    // Gather form: dx[j] takes the centre entry of row j, the left entry of
    // row j + 1 and the right entry of row j − 1, each row evaluated where
    // it is needed. After inlining, the compiler keeps only the arithmetic
    // of the entry each call uses (the left and right entries of a typical
    // row are much cheaper than the centre one), so this costs about one row
    // per cell and needs no scratch: measured 1.6× faster than scaling whole
    // rows into a buffer and gathering from it (docs/p1.md).
    if n < 5 {
        for (j, d) in dx.iter_mut().enumerate() {
            put::<ADD, R>(d, gather_at(x, g, j, &mut f));
        }
        return;
    }
    gather_ends::<ADD, R>(x, g, dx, &mut f);
    rows_range_body::<ADD, R>(x, g, &mut dx[2..n - 2], 2, f);
}

/// `*d += v` when `ADD`, else `*d = v`.
#[inline(always)]
fn put<const ADD: bool, R: Real>(d: &mut R, v: R) {
    if ADD { *d += v } else { *d = v }
}

/// The gather of [`vjp3_rows`] at the four cells next to the ends (`n ≥
/// 5`), whose neighbours wrap around.
#[inline(always)]
fn gather_ends<const ADD: bool, R: Real>(x: &[R], g: &[R], dx: &mut [R], f: &mut impl FnMut(R, R, R) -> (R, R, R)) {
    let n = x.len();
    for j in [0, 1, n - 2, n - 1] {
        put::<ADD, R>(&mut dx[j], gather_at(x, g, j, f));
    }
}

/// The gather of [`vjp3_rows`] at one cell `j` (neighbours periodic).
#[inline(always)]
fn gather_at<R: Real>(x: &[R], g: &[R], j: usize, f: &mut impl FnMut(R, R, R) -> (R, R, R)) -> R {
    let n = x.len();
    let m = |k: isize| (j as isize + k).rem_euclid(n as isize) as usize;
    let (_, jc, _) = f(x[m(-1)], x[j], x[m(1)]);
    let (jl, _, _) = f(x[j], x[m(1)], x[m(2)]);
    let (_, _, jr) = f(x[m(-2)], x[m(-1)], x[j]);
    g[j] * jc + g[m(1)] * jl + g[m(-1)] * jr
}

/// The gather of [`vjp3_rows`] for the cells `s..s + out.len()`, all at
/// least two cells from either end (`2 ≤ s`, `s + out.len() ≤ n − 2`):
/// five shifted views of the state, three of the seed.
#[inline(always)]
fn rows_range_body<const ADD: bool, R: Real>(x: &[R], g: &[R], out: &mut [R], s: usize, mut f: impl FnMut(R, R, R) -> (R, R, R)) {
    let m = out.len();
    let (xm2, xm1, x0, xp1, xp2) = (&x[s - 2..s - 2 + m], &x[s - 1..s - 1 + m], &x[s..s + m], &x[s + 1..s + 1 + m], &x[s + 2..s + 2 + m]);
    let (gm1, g0, gp1) = (&g[s - 1..s - 1 + m], &g[s..s + m], &g[s + 1..s + 1 + m]);
    for (i, d) in out.iter_mut().enumerate() {
        let (_, jc, _) = f(xm1[i], x0[i], xp1[i]);
        let (jl, _, _) = f(x0[i], xp1[i], xp2[i]);
        let (_, _, jr) = f(xm2[i], xm1[i], x0[i]);
        put::<ADD, R>(d, g0[i] * jc + gp1[i] * jl + gm1[i] * jr);
    }
}

/// [`vjp3_rows`] with the cells split in two halves run by `rayon::join`
/// when the grid has at least [`PAR_MIN_CELLS`] cells and the current rayon
/// pool more than one thread; the same code per cell, so the same result
/// bit for bit.
#[doc(hidden)]
pub fn vjp3_rows_par<const ADD: bool, R: Real, F: Fn(R, R, R) -> (R, R, R) + Sync>(x: &[R], g: &[R], dx: &mut [R], f: F) {
    let n = x.len();
    if !split_pays(n) {
        return vjp3_rows::<ADD, R, _>(x, g, dx, &f);
    }
    gather_ends::<ADD, R>(x, g, dx, &mut &f);
    join_halves(dx, 2, n - 2, |part, s| rows_range::<ADD, R, _>(x, g, part, s, &f));
}

/// [`rows_range_body`] compiled for the widest vectors the CPU has.
#[inline]
fn rows_range<const ADD: bool, R: Real, F: Fn(R, R, R) -> (R, R, R)>(x: &[R], g: &[R], out: &mut [R], s: usize, f: F) {
    if ADD {
        dispatch_generic!(rows_range_add, [R: Real, F: Fn(R, R, R) -> (R, R, R)], x: &[R], g: &[R], out: &mut [R], s: usize, f: F)
    } else {
        dispatch_generic!(rows_range_overwrite, [R: Real, F: Fn(R, R, R) -> (R, R, R)], x: &[R], g: &[R], out: &mut [R], s: usize, f: F)
    }
}

#[inline(always)]
fn rows_range_add<R: Real>(x: &[R], g: &[R], out: &mut [R], s: usize, f: impl Fn(R, R, R) -> (R, R, R)) {
    rows_range_body::<true, R>(x, g, out, s, f)
}

#[inline(always)]
fn rows_range_overwrite<R: Real>(x: &[R], g: &[R], out: &mut [R], s: usize, f: impl Fn(R, R, R) -> (R, R, R)) {
    rows_range_body::<false, R>(x, g, out, s, f)
}

/// Adds `src` into `dst` and zeroes `src` (one pass).
#[inline(always)]
fn drain_into<R: Real>(dst: &mut [R], src: &mut [R]) {
    for (d, s) in dst.iter_mut().zip(src.iter_mut()) {
        *d += *s;
        *s = R::zero();
    }
}

#[inline(always)]
fn vjp3_body<const ADD: bool, R: Real>(x: &[R], g: &mut [R], dx: &mut [R], dp: &mut [R], mut f: impl MapVjp<R>) {
    let n = x.len();
    let mut buf = [R::zero(); 4 * CHUNK];
    let (dl, rest) = buf.split_at_mut(CHUNK);
    let (dc, rest) = rest.split_at_mut(CHUNK);
    let (dr, y) = rest.split_at_mut(CHUNK);
    if !ADD {
        // Written only by accumulation below (the wrap-around cells).
        dx[0] = R::zero();
        dx[n - 1] = R::zero();
    }
    // Interior cells 1..n−1 in chunks: the views are plain shifts of x.
    let mut carry = R::zero(); // dr of the previous chunk's last cell, owed to dx[s]
    let mut s = 1;
    while s < n - 1 {
        let e = (s + CHUNK).min(n - 1);
        let m = e - s;
        f(&x[s - 1..e - 1], &mut dl[..m], &x[s..e], &mut dc[..m], &x[s + 1..e + 1], &mut dr[..m], dp, &mut y[..m], &mut g[s..e]);
        // The transpose of the shifts: gathers, each vectorised.
        if ADD {
            drain_into(&mut dx[s - 1..e - 1], &mut dl[..m]);
            drain_into(&mut dx[s..e], &mut dc[..m]);
            drain_into(&mut dx[s + 1..e + 1], &mut dr[..m]);
        } else {
            // dx[s+i] = dc[i] + dl[i+1] + dr[i−1], with the chunk's edges
            // patched from its neighbours.
            let out = &mut dx[s..e];
            out[0] = dc[0] + carry + if m > 1 { dl[1] } else { R::zero() };
            if m > 1 {
                for (((o, &c), &l), &r) in out[1..m - 1].iter_mut().zip(&dc[1..m - 1]).zip(&dl[2..m]).zip(&dr[..m - 2]) {
                    *o = c + l + r;
                }
                out[m - 1] = dc[m - 1] + dr[m - 2];
            }
            dx[s - 1] += dl[0];
            carry = dr[m - 1];
            dl[..m].fill(R::zero());
            dc[..m].fill(R::zero());
            dr[..m].fill(R::zero());
        }
        s = e;
    }
    if !ADD {
        dx[n - 1] += carry;
    }
    // The two boundary cells wrap around.
    for (i, il, ir) in [(0, n - 1, 1), (n - 1, n - 2, 0)] {
        let z = R::zero();
        let (mut a, mut b, mut c, mut yy, mut gi) = ([z], [z], [z], [z], [g[i]]);
        f(&[x[il]], &mut a, &[x[i]], &mut b, &[x[ir]], &mut c, dp, &mut yy, &mut gi);
        dx[il] += a[0];
        dx[i] += b[0];
        dx[ir] += c[0];
        g[i] = R::zero();
    }
}
