//! The pressure projection of a fully periodic MAC grid by FFT, in any
//! dimension: on a box that wraps on every axis (and holds no obstacle) the
//! pressure matrix is diagonal in Fourier space, so the projection onto
//! discretely divergence-free velocities is one multiplication per mode,
//! with no iteration and no tolerance (as JAX-CFD and Exponax project).
//!
//! The discrete operators are those of the CG projection ([`crate::smoke`],
//! 2D and 3D): the divergence of cell `c` is `Σ_a (u_a[c + e_a] −
//! u_a[c])` (face `c` of axis `a` lies between cells `c − e_a` and `c`), the
//! gradient on face `c` is `p[c] − p[c − e_a]`, and the projection is `u ←
//! u − G·p` with `D·G·p = D·u`. In Fourier space, with `θ_a = 2π·k_a/n_a`,
//! the divergence of component `a` multiplies by `e^{iθ_a} − 1`, the
//! gradient by `1 − e^{−iθ_a}`, and `D·G` by `−Σ_a 4·sin²(θ_a/2)`; the mean
//! (mode 0) is left as it is. The map is an orthogonal projection, so it is
//! its own adjoint: [`FftProjection::project_adjoint`] only moves the
//! periodic copies' adjoints to their faces first.
//!
//! Two real components travel in one complex transform (`u + i·v`; in 3D
//! `w` alone in a second), split and joined again by the symmetry of real
//! signals' spectra.

use std::sync::Arc;

use rustfft::num_complex::Complex;
use rustfft::{Fft, FftPlanner};

/// Plans, symbols and buffers of the projection on a periodic box of `n`
/// cells per axis.
pub struct FftProjection<const D: usize> {
    n: [usize; D],
    /// The transforms (behind non-generic functions).
    transforms: Transforms,
    /// `e^{iθ} − 1` per axis and wavenumber index.
    div: [Vec<Complex<f64>>; D],
    /// One complex field per pair of components, and the projected spectra.
    spectra: Vec<Vec<Complex<f64>>>,
    projected: Vec<Vec<Complex<f64>>>,
}

/// The forward and inverse transforms along each axis of a box, with their
/// buffers. Every rustfft call sits in a non-generic function of this
/// crate (built without the autodiff flag): rustfft's generic code
/// instantiated in a crate built with it crashes rustc (its type trees of
/// rustfft's AVX vector types), as faer's does.
struct Transforms {
    n: Vec<usize>,
    forward: Vec<Arc<dyn Fft<f64>>>,
    inverse: Vec<Arc<dyn Fft<f64>>>,
    /// A field with one axis made contiguous, and the transforms' scratch.
    lines: Vec<Complex<f64>>,
    scratch: Vec<Complex<f64>>,
}

impl Transforms {
    /// The plans of a box of `n` cells per axis.
    #[inline(never)]
    fn new(n: &[usize]) -> Self {
        let mut planner = FftPlanner::<f64>::new();
        let forward: Vec<_> = n.iter().map(|&m| planner.plan_fft_forward(m)).collect();
        let inverse: Vec<_> = n.iter().map(|&m| planner.plan_fft_inverse(m)).collect();
        let scratch_len = forward.iter().chain(&inverse).map(|f| f.get_inplace_scratch_len()).max().unwrap_or(0);
        let cells = n.iter().product();
        Self { n: n.to_vec(), forward, inverse, lines: vec![Complex::default(); cells], scratch: vec![Complex::default(); scratch_len] }
    }

    /// The transform of `field` (x fastest), forward or inverse
    /// (unnormalised), one axis at a time.
    #[inline(never)]
    fn apply(&mut self, field: &mut [Complex<f64>], forward: bool) {
        let cells = self.lines.len();
        for a in 0..self.n.len() {
            let plan = if forward { &self.forward[a] } else { &self.inverse[a] };
            let m = self.n[a];
            if a == 0 {
                plan.process_with_scratch(field, &mut self.scratch);
                continue;
            }
            // Gather the lines along `a` contiguously, transform, scatter back:
            // each block of the field is an `m × inner` matrix whose columns
            // are the lines, transposed tile by tile so that both sides stay
            // in cache (a row at a time wrote one value per cache line, at a
            // power-of-two stride: half the projection's time at 256²).
            let inner: usize = self.n[..a].iter().product();
            let lines = &mut self.lines;
            let (block, blocks) = (inner * m, cells / (inner * m));
            for b in 0..blocks {
                transpose(&field[b * block..(b + 1) * block], &mut lines[b * block..(b + 1) * block], m, inner);
            }
            plan.process_with_scratch(lines, &mut self.scratch);
            for b in 0..blocks {
                transpose(&lines[b * block..(b + 1) * block], &mut field[b * block..(b + 1) * block], inner, m);
            }
        }
    }
}

/// `to = fromᵀ` for `from` a `rows × cols` matrix (row-major), by tiles
/// of 8 × 8 (eight lines a power of two apart share a cache set; more
/// would evict each other).
fn transpose(from: &[Complex<f64>], to: &mut [Complex<f64>], rows: usize, cols: usize) {
    const TILE: usize = 8;
    assert!(from.len() == rows * cols && to.len() == rows * cols);
    for r0 in (0..rows).step_by(TILE) {
        let r1 = (r0 + TILE).min(rows);
        for c0 in (0..cols).step_by(TILE) {
            for c in c0..(c0 + TILE).min(cols) {
                let out = &mut to[c * rows + r0..c * rows + r1];
                for (k, o) in out.iter_mut().enumerate() {
                    *o = from[(r0 + k) * cols + c];
                }
            }
        }
    }
}

impl<const D: usize> std::fmt::Debug for FftProjection<D> {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("FftProjection").field("n", &self.n).finish()
    }
}

impl<const D: usize> FftProjection<D> {
    /// The projection of a box of `n` cells per axis, periodic on every axis.
    ///
    /// # Panics
    /// If an axis has fewer than 2 cells.
    pub fn new(n: [usize; D]) -> Self {
        assert!(n.iter().all(|&m| m >= 2), "fft projection: every axis needs at least 2 cells, got {n:?}");
        let div = n.map(|m| {
            (0..m)
                .map(|k| {
                    let t = 2.0 * std::f64::consts::PI * k as f64 / m as f64;
                    Complex::new(t.cos() - 1.0, t.sin())
                })
                .collect()
        });
        let cells: usize = n.iter().product();
        let pairs = D.div_ceil(2);
        Self {
            n,
            transforms: Transforms::new(&n),
            div,
            spectra: vec![vec![Complex::default(); cells]; pairs],
            projected: vec![vec![Complex::default(); cells]; pairs],
        }
    }

    /// Cells per axis.
    pub fn dims(&self) -> [usize; D] {
        self.n
    }

    /// Length of the face array of `axis` (one more face along it: the copy).
    pub fn face_len(&self, axis: usize) -> usize {
        (0..D).map(|a| self.n[a] + (a == axis) as usize).product()
    }

    /// Projects the velocity `vel` (the face arrays of each axis, with the
    /// periodic copies: face `n_a` of axis `a` is a copy of face 0, not
    /// read, written as the copy) onto the discretely divergence-free
    /// fields, in place.
    ///
    /// # Panics
    /// If an array's length is not [`Self::face_len`].
    pub fn project(&mut self, vel: [&mut [f64]; D]) {
        for (a, v) in vel.iter().enumerate() {
            assert_eq!(v.len(), self.face_len(a), "fft projection: length of the velocity of axis {a}");
        }
        self.load(&vel);
        for p in 0..self.spectra.len() {
            self.transform(p, true);
        }
        self.multiply();
        for p in 0..self.spectra.len() {
            std::mem::swap(&mut self.spectra[p], &mut self.projected[p]);
            self.transform(p, false);
        }
        self.store(vel);
    }

    /// Adjoint of [`Self::project`] on the velocity's adjoint, in place: the
    /// copies' adjoints added to their faces (and zeroed), then the same
    /// projection (it is symmetric), the copies left at zero.
    ///
    /// # Panics
    /// As [`Self::project`].
    pub fn project_adjoint(&mut self, mut g: [&mut [f64]; D]) {
        for (a, v) in g.iter_mut().enumerate() {
            assert_eq!(v.len(), self.face_len(a), "fft projection: length of the adjoint of axis {a}");
            self.for_copies(a, |face, copy| {
                v[face] += v[copy];
                v[copy] = 0.0;
            });
        }
        self.project(g.each_mut().map(|v| &mut **v));
        for (a, v) in g.iter_mut().enumerate() {
            self.for_copies(a, |_, copy| v[copy] = 0.0);
        }
    }

    /// Calls `f(face 0, its copy)` for every copy of axis `a`'s face array.
    pub(crate) fn for_copies(&self, a: usize, f: impl FnMut(usize, usize)) {
        for_copies(self.n, a, f)
    }

    /// The own faces of each component into the pairs' complex fields (the
    /// cell layout: face `c` of axis `a` at index `c`).
    fn load(&mut self, vel: &[&mut [f64]; D]) {
        for (a, v) in vel.iter().enumerate() {
            let ext: [usize; D] = std::array::from_fn(|b| self.n[b] + (a == b) as usize);
            let (buffer, imaginary) = (&mut self.spectra[a / 2], a % 2 == 1);
            let (inner, outer): (usize, usize) = (ext[..a].iter().product(), ext[a + 1..].iter().product());
            let (len, na) = (inner * self.n[a], inner * ext[a]);
            for o in 0..outer {
                let (from, to) = (&v[o * na..o * na + len], &mut buffer[o * len..(o + 1) * len]);
                for (z, &x) in to.iter_mut().zip(from) {
                    if imaginary {
                        z.im = x;
                    } else {
                        *z = Complex::new(x, 0.0);
                    }
                }
            }
        }
    }

    /// The pairs' fields back into the components, copies refreshed.
    fn store(&mut self, mut vel: [&mut [f64]; D]) {
        let scale = 1.0 / self.n.iter().product::<usize>() as f64;
        for (a, v) in vel.iter_mut().enumerate() {
            let ext: [usize; D] = std::array::from_fn(|b| self.n[b] + (a == b) as usize);
            let (buffer, imaginary) = (&self.spectra[a / 2], a % 2 == 1);
            let (inner, outer): (usize, usize) = (ext[..a].iter().product(), ext[a + 1..].iter().product());
            let (len, na) = (inner * self.n[a], inner * ext[a]);
            for o in 0..outer {
                let (from, to) = (&buffer[o * len..(o + 1) * len], &mut v[o * na..o * na + len]);
                for (x, z) in to.iter_mut().zip(from) {
                    *x = scale * if imaginary { z.im } else { z.re };
                }
                // The copies: the last layer along `a` repeats the first.
                for i in 0..inner {
                    v[o * na + len + i] = v[o * na + i];
                }
            }
        }
    }

    /// The `D`-dimensional transform of pair `p`'s field, forward or inverse
    /// (unnormalised).
    fn transform(&mut self, p: usize, forward: bool) {
        self.transforms.apply(&mut self.spectra[p], forward);
    }

    /// The projection mode by mode: each component's spectrum split out of
    /// its pair (`U(k) = (Z(k) + conj Z(−k))/2`, `V(k) = (Z(k) − conj
    /// Z(−k))/2i`), `p = D·U / (D·G)`, `U −= G·p`, joined again.
    fn multiply(&mut self) {
        let cells = self.spectra[0].len();
        let mut q = [0usize; D];
        for c in 0..cells {
            // The mirrored mode −k, and the symbols.
            let mut mirror = 0;
            let mut stride = 1;
            let mut laplacian = 0.0;
            for a in 0..D {
                let m = self.n[a];
                mirror += ((m - q[a]) % m) * stride;
                stride *= m;
                laplacian += 2.0 * self.div[a][q[a]].re;
            }
            let mut u = [Complex::default(); D];
            for (a, ua) in u.iter_mut().enumerate() {
                let z = &self.spectra[a / 2];
                let (zk, zm) = (z[c], z[mirror].conj());
                let paired = a % 2 == 0 && a + 1 < D;
                *ua = if a % 2 == 1 {
                    (zk - zm) * Complex::new(0.0, -0.5)
                } else if paired {
                    (zk + zm) * 0.5
                } else {
                    zk
                };
            }
            if laplacian != 0.0 {
                let mut du = Complex::default();
                for a in 0..D {
                    du += self.div[a][q[a]] * u[a];
                }
                let pressure = du / laplacian;
                for a in 0..D {
                    // G = 1 − e^{−iθ} = −conj(e^{iθ} − 1).
                    u[a] += self.div[a][q[a]].conj() * pressure;
                }
            }
            for p in 0..self.projected.len() {
                let re = u[2 * p];
                self.projected[p][c] = if 2 * p + 1 < D { re + u[2 * p + 1] * Complex::new(0.0, 1.0) } else { re };
            }
            // The next mode, x fastest.
            for a in 0..D {
                q[a] += 1;
                if q[a] < self.n[a] {
                    break;
                }
                q[a] = 0;
            }
        }
    }
}

/// Calls `f(face 0, its copy)` for every periodic copy in the array of the
/// faces normal to `a` of a box of `n` cells (face `n_a` along `a` copies
/// face 0).
pub(crate) fn for_copies<const D: usize>(n: [usize; D], a: usize, mut f: impl FnMut(usize, usize)) {
    let ext: [usize; D] = std::array::from_fn(|b| n[b] + (a == b) as usize);
    let stride: usize = ext[..a].iter().product();
    let outer: usize = ext[a + 1..].iter().product();
    for o in 0..outer {
        for i in 0..stride {
            let face = o * stride * ext[a] + i;
            f(face, face + n[a] * stride);
        }
    }
}

/// Moves a periodic field of `n` samples per axis (x fastest) by `shift`
/// samples along `axis` in place, by the Fourier shift theorem: each mode
/// `k` (signed, `|k| < m/2` on an axis of `m` samples) multiplied by
/// `e^{2πi·k·shift/m}`, so that a band-limited field is moved exactly. The
/// Nyquist mode of an even `m` (real, a sign per sample) keeps its real
/// part, `cos(π·shift)`: a half-sample shift drops it. Linear in the field;
/// its transpose is the shift by `−shift` (the Nyquist factor is even).
/// Every rustfft call is in this non-generic function (see [`Transforms`]).
///
/// # Panics
/// If `field` does not have `Π n` values or `axis` is not an axis.
#[inline(never)]
pub fn shift_along(n: &[usize], axis: usize, shift: f64, field: &mut [f64]) {
    let cells: usize = n.iter().product();
    assert!(axis < n.len() && field.len() == cells, "shift_along: {} values for {n:?}, axis {axis}", field.len());
    let m = n[axis];
    let mut planner = FftPlanner::<f64>::new();
    let (forward, inverse) = (planner.plan_fft_forward(m), planner.plan_fft_inverse(m));
    let mut scratch = vec![Complex::default(); forward.get_inplace_scratch_len().max(inverse.get_inplace_scratch_len())];
    // The shift per mode, with the inverse transform's 1/m.
    let t = 2.0 * std::f64::consts::PI * shift / m as f64;
    let factor: Vec<Complex<f64>> = (0..m)
        .map(|k| {
            let c = if 2 * k == m {
                Complex::new((std::f64::consts::PI * shift).cos(), 0.0)
            } else {
                let signed = if 2 * k < m { k as f64 } else { k as f64 - m as f64 };
                Complex::from_polar(1.0, t * signed)
            };
            c / m as f64
        })
        .collect();
    let inner: usize = n[..axis].iter().product();
    let (block, blocks) = (inner * m, cells / (inner * m));
    let mut line = vec![Complex::default(); m];
    for b in 0..blocks {
        for i in 0..inner {
            for (k, l) in line.iter_mut().enumerate() {
                *l = Complex::new(field[b * block + k * inner + i], 0.0);
            }
            forward.process_with_scratch(&mut line, &mut scratch);
            for (l, f) in line.iter_mut().zip(&factor) {
                *l *= f;
            }
            inverse.process_with_scratch(&mut line, &mut scratch);
            for (k, l) in line.iter().enumerate() {
                field[b * block + k * inner + i] = l.re;
            }
        }
    }
}
