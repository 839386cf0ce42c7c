//! The grid of the fluid solvers in any dimension: [`MacGrid<D>`].

use std::ops::Range;

use crate::boundary::Boundary;
use crate::mac::{Bounded, Mac};

/// The staggered (MAC) grid of a fluid in `D` dimensions (2 or 3): `n[0] ×
/// … × n[D−1]` unit cells, the kind of each side, and the two settings of
/// the explicit smoke step ([`super::advect_buoyancy`]: buoyancy and time
/// step). Written once: P2 is `MacGrid::<2>::p2(n)`, P4
/// `MacGrid::<3>::p4(n)`.
///
/// The packed state is `[s, u₀, …, u_{D−1}]`: the smoke at the cell centres
/// (`Π n` values), then each velocity component at the faces normal to its
/// axis (the cells with one more along that axis), each array x fastest
/// and its slowest axis last ([`crate::mac`]'s conventions). On a periodic
/// axis face `n` is a copy of face `0`: operators never read it and write
/// it as the copy, so the state keeps one layout whatever the boundary.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct MacGrid<const D: usize> {
    /// Cells along each axis (x first; y is up).
    pub n: [usize; D],
    /// Buoyancy of the explicit step: `u₁ += buoyancy · (smoke averaged to
    /// the y-face)` (0: none; a scene adds buoyancy as its own effect).
    pub buoyancy: f64,
    /// Time step of the explicit step's advection, in cells per unit speed
    /// (P2 and P4: 1).
    pub dt: f64,
    /// The sides (closed for P2 and P4). Check with [`Boundary::validate`]
    /// before simulating.
    pub boundary: Boundary<D>,
}

impl MacGrid<2> {
    /// The P2 setting: an `n²` closed box, buoyancy 0.1, unit time step.
    pub fn p2(n: usize) -> Self {
        Self { n: [n, n], buoyancy: 0.1, dt: 1.0, boundary: Boundary::CLOSED }
    }
}

impl MacGrid<3> {
    /// The P4 setting: an `n³` closed box, buoyancy 0.1, unit time step.
    pub fn p4(n: usize) -> Self {
        Self { n: [n, n, n], buoyancy: 0.1, dt: 1.0, boundary: Boundary::<3>::CLOSED }
    }
}

impl<const D: usize> MacGrid<D> {
    /// A closed box of `n` cells, unit time step, without buoyancy.
    pub fn new(n: [usize; D]) -> Self {
        Self { n, buoyancy: 0.0, dt: 1.0, boundary: Boundary::CLOSED }
    }

    /// The same grid with other sides.
    pub fn with_boundary(self, boundary: Boundary<D>) -> Self {
        Self { boundary, ..self }
    }

    /// The same grid with another time step of the explicit step.
    pub fn with_dt(self, dt: f64) -> Self {
        Self { dt, ..self }
    }

    /// The cells along each axis, `n` read entry by entry. Code Enzyme
    /// differentiates takes `n` this way: a copy of the whole array field
    /// reaches Enzyme typed as integers at every offset past it, which
    /// clashes with the floating-point fields that follow it in the struct
    /// (docs/pitfalls.md).
    #[inline(always)]
    pub fn cells(&self) -> [usize; D] {
        crate::mac::axes_of(&self.n)
    }

    /// Whether every side is closed (P2's and P4's box).
    pub fn is_closed(&self) -> bool {
        self.boundary == Boundary::CLOSED
    }

    /// Whether every axis has the same number of cells.
    pub fn is_cube(&self) -> bool {
        self.n.iter().all(|&m| m == self.n[0])
    }

    /// The fewest cells along an axis.
    pub fn min_cells(&self) -> usize {
        self.cells().into_iter().min().unwrap_or(0)
    }

    /// The index rules of this grid's MAC lattices, its axes wrapping where
    /// the sides are periodic.
    pub fn mac(&self) -> Mac<D, [bool; D]> {
        Mac { n: self.cells(), wrap: self.boundary.wraps() }
    }

    /// The index rules with no axis wrapping (for a box with no periodic
    /// side: its loops then carry no test).
    pub fn bounded(&self) -> Mac<D, Bounded> {
        Mac::bounded(self.cells())
    }

    /// Number of cells (smoke values).
    pub fn n_s(&self) -> usize {
        self.n.iter().product()
    }

    /// Extents of the array of faces normal to `axis`: the cells with one
    /// more along that axis.
    pub fn face_dims(&self, axis: usize) -> [usize; D] {
        let mut e = self.cells();
        e[axis] += 1;
        e
    }

    /// Number of faces normal to `axis`.
    pub fn n_face(&self, axis: usize) -> usize {
        self.face_dims(axis).iter().product()
    }

    /// Number of velocities (every face of every axis).
    pub fn n_vel(&self) -> usize {
        (0..D).map(|a| self.n_face(a)).sum()
    }

    /// Length of the packed state `[s, u₀, …]`.
    pub fn n_state(&self) -> usize {
        self.n_s() + self.n_vel()
    }

    /// Where the faces normal to `axis` lie in the packed velocity `[u₀, …,
    /// u_{D−1}]` (add [`MacGrid::n_s`] for the packed state). Code Enzyme
    /// differentiates writes each component through one such slice of the
    /// packed velocity (an array of mutable slices trips its reverse pass).
    #[inline(always)]
    pub fn face_range(&self, axis: usize) -> Range<usize> {
        let mut start = 0;
        for a in 0..axis {
            start += self.n_face(a);
        }
        start..start + self.n_face(axis)
    }

    /// Splits a packed velocity `[u₀, …, u_{D−1}]` into its components.
    #[inline(always)]
    pub fn components<'a>(&self, vel: &'a [f64]) -> [&'a [f64]; D] {
        // Filled from a splat of an empty slice (no array constructor Enzyme
        // cannot type; a splat of `vel` itself stored its length, an
        // argument Enzyme could not type, when `vel` was the differentiated
        // function's own argument), one constant index at a time
        // (docs/pitfalls.md).
        let mut parts = [&vel[..0]; D];
        let mut start = 0;
        crate::mac::each_axis!(D, a => {
            let len = self.n_face(a);
            parts[a] = &vel[start..start + len];
            start += len;
        });
        parts
    }

    /// Splits a packed velocity into its components, mutably.
    #[inline(always)]
    pub fn components_mut<'a>(&self, vel: &'a mut [f64]) -> [&'a mut [f64]; D] {
        let mut parts: [&'a mut [f64]; D] = [(); D].map(|_| <&mut [f64]>::default());
        let mut rest = vel;
        for (a, part) in parts.iter_mut().enumerate() {
            let (f, r) = std::mem::take(&mut rest).split_at_mut(self.n_face(a));
            *part = f;
            rest = r;
        }
        parts
    }

    /// Splits a packed state `[s, u₀, …]` into the smoke and the velocity
    /// components.
    #[inline(always)]
    pub fn split<'a>(&self, x: &'a [f64]) -> (&'a [f64], [&'a [f64]; D]) {
        let (s, vel) = x.split_at(self.n_s());
        (s, self.components(vel))
    }

    /// Splits a packed state `[s, u₀, …]`, mutably.
    #[inline(always)]
    pub fn split_mut<'a>(&self, x: &'a mut [f64]) -> (&'a mut [f64], [&'a mut [f64]; D]) {
        let (s, vel) = x.split_at_mut(self.n_s());
        (s, self.components_mut(vel))
    }

    /// Values per slab (layer along the slowest axis, a row in 2D) of the
    /// cells and of each face array: `[cells, faces₀, …]`, the faces normal
    /// to the slowest axis counted per slab of cells.
    fn slab_sizes(&self) -> (usize, [usize; D]) {
        let cells = self.n_s() / self.n[D - 1];
        let mut faces = [cells; D];
        for (a, f) in faces.iter_mut().enumerate() {
            if a + 1 < D {
                *f = cells / self.n[a] * (self.n[a] + 1);
            }
        }
        (cells, faces)
    }

    /// Lengths of slabs `ks` (along the slowest axis) of `[s, u₀, …]`:
    /// `ks.len()` slabs of each field, and for the last component also its
    /// last face slab when `ks` reaches the end. Over `0..n[D−1]`, the packed
    /// state's parts.
    pub fn slab_lens(&self, ks: Range<usize>) -> (usize, [usize; D]) {
        let (cells, mut faces) = self.slab_sizes();
        let m = ks.len();
        for (a, f) in faces.iter_mut().enumerate() {
            *f *= m + (a + 1 == D && ks.end == self.n[D - 1]) as usize;
        }
        (m * cells, faces)
    }

    /// Slabs `ks` of each field of the packed state as `(start, length)`,
    /// the smoke first: the pieces an operator on a range of slabs reads
    /// and writes (each contiguous).
    pub fn slab_pieces(&self, ks: Range<usize>) -> Vec<(usize, usize)> {
        let (lc, lf) = self.slab_lens(ks.clone());
        let (sc, sf) = self.slab_starts(ks.start);
        std::iter::once((sc, lc)).chain(sf.into_iter().zip(lf)).collect()
    }

    /// Total length of slabs `ks` of every field.
    pub fn slabs_len(&self, ks: Range<usize>) -> usize {
        let (lc, lf) = self.slab_lens(ks);
        lc + lf.iter().sum::<usize>()
    }

    /// Where slab `k` of each field starts in the packed state.
    pub fn slab_starts(&self, k: usize) -> (usize, [usize; D]) {
        let (cells, faces) = self.slab_sizes();
        let mut starts = [0; D];
        let mut offset = self.n_s();
        for a in 0..D {
            starts[a] = offset + k * faces[a];
            offset += self.n_face(a);
        }
        (k * cells, starts)
    }
}

#[cfg(test)]
#[allow(clippy::needless_range_loop)]
mod tests {
    use super::*;

    fn check_layout<const D: usize>(n: [usize; D]) {
        let g = MacGrid::new(n);
        let x: Vec<f64> = (0..g.n_state()).map(|i| i as f64).collect();
        let (s, vel) = g.split(&x);
        assert_eq!(s.len(), g.n_s());
        let mut start = g.n_s();
        for a in 0..D {
            assert_eq!(vel[a].len(), g.n_face(a));
            assert_eq!(vel[a][0], start as f64);
            start += g.n_face(a);
        }
        assert_eq!(start, g.n_state());
        let mut y = x.clone();
        let (_, vm) = g.split_mut(&mut y);
        for a in 0..D {
            assert_eq!(vm[a].len(), g.n_face(a));
        }
        // Slabs: the whole range is the packed state; a slab's parts start
        // where slab_starts says and add up over the slabs.
        let last = n[D - 1];
        let (cs, fs) = g.slab_lens(0..last);
        assert_eq!(cs, g.n_s());
        for a in 0..D {
            assert_eq!(fs[a], g.n_face(a));
        }
        for k in 0..last {
            let (c0, f0) = g.slab_starts(k);
            let (c1, f1) = g.slab_starts(k + 1);
            let (cl, fl) = g.slab_lens(k..k + 1);
            assert_eq!(c1 - c0, cl);
            for a in 0..D {
                if a + 1 < D || k + 1 < last {
                    assert_eq!(f1[a] - f0[a], fl[a], "axis {a} slab {k}");
                }
            }
        }
    }

    #[test]
    fn layout_2d_and_3d() {
        check_layout([5, 3]);
        check_layout([4, 3, 2]);
        assert_eq!(MacGrid::<2>::p2(8).n_state(), 64 + 2 * 72);
        assert_eq!(MacGrid::<3>::p4(4).n_state(), 64 + 3 * 80);
    }
}
