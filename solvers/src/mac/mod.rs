//! The staggered (MAC) grid in any dimension `D` (2 or 3): where its
//! values live, how a point between them is sampled and how that sample is
//! differentiated, and which faces make up the velocity at each point.
//! Written once for every dimension: the 2D and 3D smoke of [`crate::smoke`]
//! trace and sample through these rules (instantiated as `Mac<2>` and `Mac<3>`, each differentiated by Enzyme on
//! its own).
//!
//! Conventions: `n[0] × … × n[D−1]` unit cells, axis 0 (x) fastest in memory,
//! axis `D − 1` slowest (y in 2D, z in 3D); a "slab" is one layer along that
//! slowest axis (a row in 2D). Four kinds of lattice ([`At`]):
//! - the cell centres (`x_a = i_a + ½` on every axis): `Π n` values;
//! - the faces normal to axis `b` (`x_b = i_b`, `x_a = i_a + ½` on the
//!   others): the cells with one more along `b`.
//!
//! Each axis follows [`crate::grid`]'s rules: it wraps (periodic) or is
//! bounded (samples clamp to it). On a wrapping axis face `n` is a copy of
//! face `0`: operators never read it and write it as the copy.

// Loops over the axes index several per-axis arrays at once.
#![allow(clippy::needless_range_loop)]

/// Runs `$body` once per `$k` in the listed constants below `$m`, each
/// copy with `$k` a constant: a small loop written out (the mechanism of
/// [`each_axis`] and [`each_corner`]).
macro_rules! unrolled {
    ($m:expr, $k:ident => $body:block; $($i:literal)*) => {{
        // A running value the last copy updates is not read again.
        #[allow(unused_assignments, unconditional_panic, clippy::identity_op, clippy::absurd_extreme_comparisons)]
        {
            let m: usize = $m;
            $(
                if $i < m {
                    let $k: usize = $i;
                    $body
                }
            )*
        }
    }};
}
pub(crate) use unrolled;

/// Runs `$body` once per axis `0..D` (`D` at most 3), with `$a` a
/// constant in each copy: the loop written out. In code Enzyme
/// differentiates, an index into a small array (`n[a]`, `stride[a]`) by a
/// loop variable left as a run-time value types the array as integers at
/// every offset, which clashes with the floating-point fields that follow it
/// in memory (docs/pitfalls.md); a constant index does not.
macro_rules! each_axis {
    ($d:expr, $a:ident => $body:block) => {
        $crate::mac::unrolled!($d, $a => $body; 0 1 2)
    };
}
pub(crate) use each_axis;

/// Runs `$body` with `$a` the constant equal to `$axis` (a run-time axis
/// below 3), for the same reason as [`each_axis`].
macro_rules! on_axis {
    ($axis:expr, $a:ident => $body:block) => {
        match $axis {
            0 => {
                let $a: usize = 0;
                $body
            }
            1 => {
                let $a: usize = 1;
                $body
            }
            _ => {
                let $a: usize = 2;
                $body
            }
        }
    };
}
pub(crate) use on_axis;

/// Runs `$body` for `$k` = 0, 1, … while `$k < $m` (at most 8: the corners
/// of a cell in 3D), each copy with `$k` a constant: the small loops of
/// the multilinear sample written out, for the reason of [`each_axis`].
macro_rules! each_corner {
    ($m:expr, $k:ident => $body:block) => {
        $crate::mac::unrolled!($m, $k => $body; 0 1 2 3 4 5 6 7)
    };
}
#[allow(unused_imports)]
pub(crate) use each_corner;

pub(crate) mod advect;
pub mod central;
pub mod fft;
pub(crate) mod near;
pub mod periodic;

use crate::grid::{beside, next, own_faces, passes, position};

/// Which axes of a grid wrap: [`Bounded`] (none, known when compiling: the
/// closed boxes of P2 and P4, whose loops then carry no test), [`Wrapping`]
/// (all: the periodic box of Navier–Stokes) or `[bool; D]` (known at run
/// time: any boundary).
pub trait Wraps<const D: usize>: Copy + Send + Sync {
    /// Whether each axis wraps.
    fn wraps(self) -> [bool; D];
}

/// No axis wraps (every side bounded).
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq)]
pub struct Bounded;

impl<const D: usize> Wraps<D> for Bounded {
    #[inline(always)]
    fn wraps(self) -> [bool; D] {
        [false; D]
    }
}

/// Every axis wraps (a fully periodic box, known when compiling).
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq)]
pub struct Wrapping;

impl<const D: usize> Wraps<D> for Wrapping {
    #[inline(always)]
    fn wraps(self) -> [bool; D] {
        [true; D]
    }
}

impl<const D: usize> Wraps<D> for [bool; D] {
    #[inline(always)]
    fn wraps(self) -> [bool; D] {
        self
    }
}

/// A copy of `n` read entry by entry. Code Enzyme differentiates copies a
/// `[usize; D]` field of a struct this way: a copy of the whole array
/// reaches Enzyme typed as integers at every offset past it, which clashes
/// with the floating-point fields that follow it in the struct
/// (docs/pitfalls.md).
#[inline(always)]
pub fn axes_of<const D: usize>(n: &[usize; D]) -> [usize; D] {
    let mut c = [1; D];
    each_axis!(D, a => {
        c[a] = n[a];
    });
    c
}

/// The lattices of a MAC grid.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum At {
    /// Cell centres (a scalar such as smoke).
    Centre,
    /// Faces normal to this axis (the velocity component along it).
    Face(usize),
}

impl At {
    /// The axis the lattice's faces are normal to (`usize::MAX` at the
    /// centres, so that it equals no axis).
    #[inline(always)]
    pub fn axis(self) -> usize {
        match self {
            At::Centre => usize::MAX,
            At::Face(a) => a,
        }
    }
}

/// A lattice of samples in an array: sample `q` at index `Σ q[a]·stride[a]`
/// and at the point `q + o`; `n[a]` samples along axis `a` hold their own
/// value (on a wrapping axis: per period).
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Lattice<const D: usize> {
    /// Distance in the array between neighbours along each axis (1 along x).
    pub stride: [usize; D],
    /// Samples per axis that hold their own value.
    pub n: [usize; D],
    /// Position of sample `0`.
    pub o: [f64; D],
    /// Length of the array (with the copies on wrapping axes).
    pub len: usize,
}

impl<const D: usize> Lattice<D> {
    /// Index of sample `q` in the array.
    #[inline(always)]
    pub fn index(&self, q: [usize; D]) -> usize {
        let mut c = 0;
        each_axis!(D, a => {
            c += q[a] * self.stride[a];
        });
        c
    }

    /// Number of rows (lines along x) in one slab (layer along the slowest
    /// axis) that hold their own values.
    #[inline(always)]
    pub fn rows_per_slab(&self) -> usize {
        let mut r = 1;
        each_axis!(D, a => {
            if a >= 1 && a + 1 < D {
                r *= self.n[a];
            }
        });
        r
    }

    /// Every point holding its own value, slab by slab, row by row, x
    /// fastest (for code Enzyme does not differentiate: the differentiated
    /// loops are written out).
    pub fn points(&self) -> impl Iterator<Item = [usize; D]> + '_ {
        (0..self.n[D - 1]).flat_map(move |k| {
            (0..self.rows_per_slab()).flat_map(move |r| {
                let q = self.row_start(k, r);
                (0..self.n[0]).map(move |i| {
                    let mut q = q;
                    q[0] = i;
                    q
                })
            })
        })
    }

    /// Point `(0, row r, …)` of slab `k`: the first sample of row `r` of
    /// that slab (rows counted x-line by x-line through the middle axes).
    #[inline(always)]
    pub fn row_start(&self, k: usize, r: usize) -> [usize; D] {
        // Started from a splat of a value known only at run time: a zeroed
        // array is a memset, whose type Enzyme cannot deduce, and
        // `std::array::from_fn` reaches Enzyme as a call it cannot type
        // (docs/pitfalls.md).
        let mut q = [k; D];
        q[0] = 0;
        let mut rest = r;
        each_axis!(D, a => {
            if a >= 1 && a + 1 < D {
                q[a] = rest % self.n[a];
                rest /= self.n[a];
            }
        });
        q
    }
}

/// Index rules of the MAC grid of a box of `n` cells whose axes wrap as
/// `wrap` says, written once for the forward operators and their adjoints.
#[derive(Clone, Copy, Debug)]
pub struct Mac<const D: usize, W: Wraps<D> = Bounded> {
    /// Cells per axis.
    pub n: [usize; D],
    /// The axes that wrap.
    pub wrap: W,
}

impl<const D: usize> Mac<D, Bounded> {
    /// The closed box of `n` cells per axis.
    pub fn bounded(n: [usize; D]) -> Self {
        Self { n, wrap: Bounded }
    }
}

impl<const D: usize, W: Wraps<D>> Mac<D, W> {
    const DIMENSION: () = assert!(D == 2 || D == 3, "a MAC grid has 2 or 3 axes");

    /// Which axes wrap.
    #[inline(always)]
    pub fn wraps(self) -> [bool; D] {
        self.wrap.wraps()
    }

    /// The cell after `k` along `axis`.
    #[inline(always)]
    fn next(self, axis: usize, k: usize) -> usize {
        if self.wraps()[axis] { next::<true>(self.n[axis], k) } else { next::<false>(self.n[axis], k) }
    }

    /// The two cells beside face `k` of `axis`.
    #[inline(always)]
    fn beside(self, axis: usize, k: usize) -> (usize, usize) {
        if self.wraps()[axis] { beside::<true>(self.n[axis], k) } else { beside::<false>(self.n[axis], k) }
    }

    /// The lattice of `at`: strides, own samples, origin and array length.
    #[inline(always)]
    pub fn lattice(self, at: At) -> Lattice<D> {
        #[allow(clippy::let_unit_value)]
        let () = Self::DIMENSION;
        let (face, w) = (at.axis(), self.wraps());
        // Splats of non-zero constants, filled in (see `row_start`).
        let mut lat = Lattice { stride: [1; D], n: self.n, o: [0.5; D], len: 1 };
        each_axis!(D, b => {
            lat.stride[b] = lat.len;
            if b == face {
                // One more face than cells along the face's axis.
                lat.len *= self.n[b] + 1;
                lat.n[b] = if w[b] { own_faces::<true>(self.n[b]) } else { own_faces::<false>(self.n[b]) };
                lat.o[b] = 0.0;
            } else {
                lat.len *= self.n[b];
            }
        });
        lat
    }

    /// Index of point `q` in the array of the faces normal to `b`.
    #[inline(always)]
    fn face_index(self, b: usize, q: [usize; D]) -> usize {
        let (mut c, mut s) = (0, 1);
        each_axis!(D, a => {
            c += q[a] * s;
            s *= self.n[a] + (a == b) as usize;
        });
        c
    }

    /// The faces of component `b` whose mean is the velocity `b` at point
    /// `q` of the lattice `at`: at a centre, the two faces of the cell along
    /// `b` (each twice); on faces of axis `b`, the face itself (four times);
    /// on faces of another axis `a`, the faces of the two cells beside `q`
    /// along `a` (the edge-extended copy on a bounded axis) at `q` and at the
    /// next position along `b` (the four nearest faces).
    #[inline(always)]
    pub fn taps(self, at: At, b: usize, q: [usize; D]) -> [usize; 4] {
        let a = at.axis();
        if a == b {
            return [self.face_index(b, q); 4];
        }
        let (b0, b1) = (q[b], self.next(b, q[b]));
        // The other varying axis: `a` on a face lattice; at a centre another
        // axis, left fixed.
        let (axis, (a0, a1)) = if a < D { (a, self.beside(a, q[a])) } else { ((b + 1) % D, (q[(b + 1) % D], q[(b + 1) % D])) };
        let at_ = |x: usize, y: usize| {
            let mut p = q;
            p[axis] = x;
            p[b] = y;
            self.face_index(b, p)
        };
        [at_(a0, b0), at_(a1, b0), at_(a0, b1), at_(a1, b1)]
    }

    /// Velocity component `b` at point `q` of the lattice `at`: the face's
    /// own value, the mean of the cell's two faces at a centre, of four
    /// faces elsewhere.
    #[inline(always)]
    fn component(self, at: At, b: usize, f: &[f64], q: [usize; D]) -> f64 {
        let t = self.taps(at, b, q);
        if at.axis() == b {
            f[t[0]]
        } else if at == At::Centre {
            0.5 * (f[t[0]] + f[t[2]])
        } else {
            0.25 * ((f[t[0]] + f[t[1]]) + (f[t[2]] + f[t[3]]))
        }
    }

    /// Adds `g·∂(component b)/∂f` into `gf`.
    #[inline(always)]
    fn component_adjoint(self, at: At, b: usize, gf: &mut [f64], q: [usize; D], g: f64) {
        let t = self.taps(at, b, q);
        if at.axis() == b {
            gf[t[0]] += g;
        } else if at == At::Centre {
            gf[t[0]] += 0.5 * g;
            gf[t[2]] += 0.5 * g;
        } else {
            for c in t {
                gf[c] += 0.25 * g;
            }
        }
    }

    /// The velocity at point `q` of the lattice `at` (`vel` the components'
    /// face arrays).
    #[inline(always)]
    pub fn velocity(self, at: At, vel: [&[f64]; D], q: [usize; D]) -> [f64; D] {
        // A splat of the first component, the others filled in (see `row_start`).
        let mut v = [self.component(at, 0, vel[0], q); D];
        each_axis!(D, b => {
            if b >= 1 {
                v[b] = self.component(at, b, vel[b], q);
            }
        });
        v
    }

    /// Adds `gᵀ·∂(velocity)/∂vel` into `gvel`.
    #[inline(always)]
    pub fn velocity_adjoint(self, at: At, gvel: &mut [&mut [f64]; D], q: [usize; D], g: [f64; D]) {
        each_axis!(D, b => {
            self.component_adjoint(at, b, gvel[b], q, g[b]);
        });
    }

    /// The point `q` of lattice `lat` traced back over `dt` along the
    /// velocity `v` there.
    #[inline(always)]
    pub fn back(lat: &Lattice<D>, q: [usize; D], v: [f64; D], dt: f64) -> [f64; D] {
        let mut p = v;
        each_axis!(D, a => {
            p[a] = q[a] as f64 + lat.o[a] - dt * v[a];
        });
        p
    }
}

/// The `2^D` samples around `p` (axis 0 fastest: bit `a` of the corner's
/// number says upper along axis `a`; the first `2^D` entries are used, the
/// others hold the lattice's length) and the fractions along each axis.
#[inline(always)]
pub fn corners<const D: usize>(wrap: [bool; D], lat: &Lattice<D>, p: [f64; D]) -> ([usize; 8], [f64; D]) {
    // Arrays started from splats of run-time values (see `Lattice::row_start`).
    let (mut lo, mut hi, mut fr) = ([lat.len; D], [lat.len; D], p);
    each_axis!(D, a => {
        let (i0, i1, f) = position(wrap[a], lat.n[a], p[a] - lat.o[a]);
        lo[a] = i0 * lat.stride[a];
        hi[a] = i1 * lat.stride[a];
        fr[a] = f;
    });
    let mut c = [lat.len; 8];
    each_corner!(1 << D, k => {
        let mut index = if k & 1 == 1 { hi[0] } else { lo[0] };
        each_axis!(D, a => {
            if a >= 1 {
                index += if (k >> a) & 1 == 1 { hi[a] } else { lo[a] };
            }
        });
        c[k] = index;
    });
    (c, fr)
}

/// Multilinear (bilinear, trilinear) sample of the lattice `f` at `p`;
/// outside it, positions are clamped to its edge per axis (the rule of P2
/// and P4) or wrap on the axes marked in `wrap`. Blended one axis at a
/// time, x first.
#[inline(always)]
pub fn sample<const D: usize>(wrap: [bool; D], f: &[f64], lat: &Lattice<D>, p: [f64; D]) -> f64 {
    let (c, fr) = corners(wrap, lat, p);
    let mut v = [f[c[0]]; 8];
    each_corner!(1 << D, k => {
        v[k] = f[c[k]];
    });
    let mut m = 1 << D;
    each_axis!(D, a => {
        m /= 2;
        each_corner!(m, k => {
            v[k] = v[2 * k] * (1.0 - fr[a]) + v[2 * k + 1] * fr[a];
        });
    });
    v[0]
}

/// The smallest and largest of the `2^D` samples [`sample`] blends at `p`
/// (MacCormack's limiter clamps to them).
#[inline(always)]
pub fn sample_range<const D: usize>(wrap: [bool; D], f: &[f64], lat: &Lattice<D>, p: [f64; D]) -> (f64, f64) {
    let (c, _) = corners(wrap, lat, p);
    let mut lo = f[c[0]];
    let mut hi = lo;
    // Comparisons, not `f64::min`/`max`: LLVM turns those into
    // `llvm.minimumnum`/`maximumnum`, which Enzyme cannot type
    // (docs/pitfalls.md).
    each_corner!(1 << D, k => {
        let v = f[c[k]];
        if v < lo {
            lo = v;
        }
        if v > hi {
            hi = v;
        }
    });
    (lo, hi)
}

/// Adjoint of [`sample`]: adds `g·∂value/∂f` into `gf` and returns
/// `g·∂value/∂p`. The clamp passes derivatives as
/// [`crate::grid::axis_passes`] says (where the position is inside the
/// lattice's range, edges included, as Enzyme's derivative of `f64::clamp`
/// does); a wrap always passes them.
#[inline(always)]
pub fn sample_adjoint<const D: usize>(wrap: [bool; D], f: &[f64], gf: &mut [f64], lat: &Lattice<D>, p: [f64; D], g: f64) -> [f64; D] {
    let (c, fr) = corners(wrap, lat, p);
    for k in 0..1 << D {
        let mut w = g;
        for a in 0..D {
            w *= if (k >> a) & 1 == 1 { fr[a] } else { 1.0 - fr[a] };
        }
        gf[c[k]] += w;
    }
    let v: [f64; 8] = std::array::from_fn(|k| if k < 1 << D { f[c[k]] } else { 0.0 });
    std::array::from_fn(|a| {
        // Differences along `a` (corner `m` of the others: bit `a` of the
        // corner's number removed), blended over the other axes in order.
        let low = |m: usize| (m & ((1 << a) - 1)) | ((m >> a) << (a + 1));
        let mut e: [f64; 4] = std::array::from_fn(|m| if m < 1 << (D - 1) { v[low(m) | 1 << a] - v[low(m)] } else { 0.0 });
        let mut m = 1 << (D - 1);
        for b in 0..D {
            if b == a {
                continue;
            }
            m /= 2;
            for k in 0..m {
                e[k] = e[2 * k] * (1.0 - fr[b]) + e[2 * k + 1] * fr[b];
            }
        }
        g * e[0] * passes(wrap[a], lat.n[a], p[a] - lat.o[a])
    })
}

#[cfg(test)]
mod tests;
