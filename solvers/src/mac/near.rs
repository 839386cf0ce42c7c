//! Traces shorter than a cell on a box periodic on every axis: the
//! Navier–Stokes step's advection at Courant numbers below 1 (its
//! sub-steps keep them at 0.9 or less).
//!
//! A point traced back by less than a cell along each axis lands between
//! its own sample and one neighbour per axis, the lower one where the
//! displacement is positive: the multilinear sample is a blend of the
//! `3^D` samples around the point with a choice per axis, the same value
//! as [`super::sample`]'s (to rounding) without its floor, wrap and index
//! arithmetic per point. On lattices padded with one layer of periodic
//! copies on every side, each neighbour is a fixed offset from the point,
//! so the loops along x read memory in order and vectorise; nothing
//! gathers. [`crate::smoke::advect_velocity_near`] is this path, where
//! [`crate::smoke::near_applies`] (every face of the scaled velocity below
//! one cell in magnitude, no limiter); [`advect_velocity_adjoint`] is its
//! hand-written adjoint.

/// A lattice of `n` own samples per axis padded with one layer of copies
/// on every side: `n[a] + 2` per axis, axis 0 fastest. Every lattice of a
/// box periodic on every axis (centres and faces alike: the copies of the
/// faces are not own samples) has this shape.
#[derive(Clone, Copy, Debug)]
pub(crate) struct Padded<const D: usize> {
    pub n: [usize; D],
    pub stride: [usize; D],
    pub len: usize,
}

impl<const D: usize> Padded<D> {
    #[inline(always)]
    pub fn new(n: [usize; D]) -> Self {
        let (mut stride, mut len) = ([1; D], 1);
        each_axis!(D, a => {
            stride[a] = len;
            len *= n[a] + 2;
        });
        Self { n, stride, len }
    }

    /// Rows of own samples (along x): the product of `n` over axes 1…
    #[inline(always)]
    pub fn rows(&self) -> usize {
        let mut r = 1;
        each_axis!(D, a => {
            if a >= 1 {
                r *= self.n[a];
            }
        });
        r
    }

    /// The own coordinates of row `r` (axis 0 at 0).
    #[inline(always)]
    pub fn row(&self, r: usize) -> [usize; D] {
        let (mut q, mut rest) = ([0; D], r);
        each_axis!(D, a => {
            if a >= 1 {
                q[a] = rest % self.n[a];
                rest /= self.n[a];
            }
        });
        q
    }

    /// Where own row `r` starts in a lattice array of strides `stride` and
    /// in the padded one.
    #[inline(always)]
    pub fn starts(&self, r: usize, stride: [usize; D]) -> (usize, usize) {
        let q = self.row(r);
        let mut s = 0;
        each_axis!(D, a => {
            s += q[a] * stride[a];
        });
        (s, self.index(q))
    }

    /// Padded index of own sample `q`.
    #[inline(always)]
    pub fn index(&self, q: [usize; D]) -> usize {
        let mut c = 0;
        each_axis!(D, a => {
            c += (q[a] + 1) * self.stride[a];
        });
        c
    }
}

/// One value of an unchecked read (the callers check the lengths once).
#[inline(always)]
fn at(f: &[f64], i: usize) -> f64 {
    debug_assert!(i < f.len());
    // SAFETY: every caller asserts that its arrays hold the padded
    // lattice, and its indices stay inside it by construction.
    unsafe { *f.get_unchecked(i) }
}

/// Fills the layer of copies of the padded lattice `f` from its own
/// samples: axis by axis, each layer copying whole layers of the axes
/// before it (their copies included), so edges and corners are right.
#[inline(always)]
pub(crate) fn fill_copies<const D: usize>(pad: &Padded<D>, f: &mut [f64]) {
    assert!(f.len() >= pad.len, "near: padded lattice length");
    each_axis!(D, a => {
        // Positions of the later axes over their own samples.
        let mut outer = 1;
        each_axis!(D, b => {
            if b > a {
                outer *= pad.n[b];
            }
        });
        let (st, m) = (pad.stride[a], pad.n[a]);
        for o in 0..outer {
            let mut base = 0;
            let mut rest = o;
            each_axis!(D, b => {
                if b > a {
                    base += (rest % pad.n[b] + 1) * pad.stride[b];
                    rest /= pad.n[b];
                }
            });
            for j in 0..st {
                f[base + j] = f[base + m * st + j];
                f[base + (m + 1) * st + j] = f[base + st + j];
            }
        }
    });
}

/// The own samples of the lattice array `src` (strides `src_stride`, the
/// lattice's own samples `pad.n`) times `scale` into the padded `dst`, its
/// copies filled.
#[inline(always)]
pub(crate) fn pad_from<const D: usize>(pad: &Padded<D>, src_stride: [usize; D], src: &[f64], scale: f64, dst: &mut [f64]) {
    assert!(dst.len() >= pad.len, "near: padded lattice length");
    let n0 = pad.n[0];
    for r in 0..pad.rows() {
        let (s, d) = pad.starts(r, src_stride);
        for i in 0..n0 {
            dst[d + i] = scale * src[s + i];
        }
    }
    fill_copies(pad, dst);
}

/// `c·(1 − |s|) + o·|s|` with `o` the lower neighbour where `s > 0` (the
/// point traced back below its own sample), else the upper one.
///
/// At `s = 0` exactly the sample is the own value and the blend has a kink:
/// its slope is `lower − own` from above and `own − upper` from below.
/// There it is written as `own + s·(lower − upper)/2`, the same value with
/// the mean of the two slopes, so that the derivative Enzyme takes (and
/// [`blend_ds`]) is the one central differences see. A flow at rest along
/// an axis (the 3D Taylor–Green vortex's `w = 0`) traces every point
/// exactly onto a lattice plane; with a one-sided slope its gradient was
/// off by 2 % against finite differences in Mosaic's fd_check.
#[inline(always)]
fn blend(s: f64, lower: f64, own: f64, upper: f64) -> f64 {
    let w = s.abs();
    let o = if s > 0.0 { lower } else { upper };
    let traced = own * (1.0 - w) + o * w;
    if s == 0.0 { own + s * (0.5 * (lower - upper)) } else { traced }
}

/// The velocity at the own samples of the faces normal to axis `a`, from
/// the padded components `vel` (each padded, scaled to cells per step),
/// into `disp` (`D` padded arrays, one per component, own samples
/// written): the component normal to the faces is the face's own, the
/// others the mean of the four nearest faces (as [`super::Mac::taps`]).
#[inline(always)]
pub(crate) fn displacement<const D: usize>(pad: &Padded<D>, a: usize, vel: [&[f64]; D], disp: &mut [f64]) {
    let p = pad.len;
    assert!(disp.len() >= D * p, "near: displacement length");
    each_axis!(D, b => {
        assert!(vel[b].len() >= p, "near: padded velocity length");
    });
    let st = pad.stride;
    let n0 = pad.n[0];
    each_axis!(D, b => {
        let (v, d) = (vel[b], &mut disp[b * p..(b + 1) * p]);
        for r in 0..pad.rows() {
            let c0 = pad.index(pad.row(r));
            if b == a {
                for c in c0..c0 + n0 {
                    put(d, c, at(v, c));
                }
            } else {
                let (sa, sb) = (st[a], st[b]);
                for c in c0..c0 + n0 {
                    put(d, c, 0.25 * ((at(v, c - sa) + at(v, c)) + (at(v, c - sa + sb) + at(v, c + sb))));
                }
            }
        }
    });
}

/// One unchecked write (the callers check the lengths once).
#[inline(always)]
fn put(f: &mut [f64], i: usize, v: f64) {
    debug_assert!(i < f.len());
    // SAFETY: as in [`at`].
    unsafe { *f.get_unchecked_mut(i) = v }
}

/// The own samples of a lattice traced back by `sign ×` the displacement
/// `disp` ([`displacement`]: `D` padded arrays, every value below one in
/// magnitude): `out[c] = f(c − sign·disp(c))` at each own sample's padded
/// index `c`, `f` and `out` padded (`out`'s copies left as they were).
#[inline(always)]
#[allow(unconditional_panic)]
pub(crate) fn trace<const D: usize>(pad: &Padded<D>, disp: &[f64], sign: f64, f: &[f64], out: &mut [f64]) {
    let p = pad.len;
    assert!(f.len() >= p && out.len() >= p && disp.len() >= D * p, "near: padded lattice length");
    let st = pad.stride;
    // The `3^(D−1)` rows around a row, from the corner row (−1 along each
    // later axis): offsets along axis 1 then 2.
    let rows_around = if D == 3 { 9 } else { 3 };
    let mut off = [0usize; 9];
    super::unrolled!(rows_around, k => {
        let mut o = 0;
        if D >= 2 {
            o += (k % 3) * st[1];
        }
        if D >= 3 {
            o += (k / 3) * st[2];
        }
        off[k] = o;
    }; 0 1 2 3 4 5 6 7 8);
    let mut corner = 1;
    each_axis!(D, b => {
        if b >= 1 {
            corner += st[b];
        }
    });
    let n0 = pad.n[0];
    for r in 0..pad.rows() {
        let c0 = pad.index(pad.row(r));
        for c in c0..c0 + n0 {
            // The displacement at the point, in cells.
            let mut s = [0.0; D];
            each_axis!(D, b => {
                s[b] = sign * at(disp, b * p + c);
            });
            // Blended along x on each row around, then along each later axis.
            let lo = c - corner;
            let mut t = [0.0; 9];
            super::unrolled!(rows_around, k => {
                let q = lo + off[k];
                t[k] = blend(s[0], at(f, q), at(f, q + 1), at(f, q + 2));
            }; 0 1 2 3 4 5 6 7 8);
            if D >= 2 {
                super::unrolled!(rows_around / 3, k => {
                    t[k] = blend(s[1], t[3 * k], t[3 * k + 1], t[3 * k + 2]);
                }; 0 1 2);
            }
            if D >= 3 {
                t[0] = blend(s[2], t[0], t[1], t[2]);
            }
            put(out, c, t[0]);
        }
    }
}

/// The own samples of the padded `f` (each `g(padded index)`) written into
/// the lattice array `o` (strides `o_stride`), its periodic copies left.
#[inline(always)]
fn unpad<const D: usize>(pad: &Padded<D>, o_stride: [usize; D], o: &mut [f64], g: impl Fn(usize) -> f64) {
    let n0 = pad.n[0];
    for r in 0..pad.rows() {
        let (s, d) = pad.starts(r, o_stride);
        for i in 0..n0 {
            o[s + i] = g(d + i);
        }
    }
}

/// Scratch of [`advect_velocity`]: each component padded twice (scaled
/// and as it is), the displacement on one lattice (`D` padded arrays), and
/// two padded lattices for the traces.
pub(crate) fn scratch_len<const D: usize>(n: [usize; D]) -> usize {
    (3 * D + 2) * Padded::new(n).len
}

/// Whether every face of the packed velocity `vel` times `dt` is below one
/// cell in magnitude (so is every mean of faces): the traces stay within
/// the samples around their point. False for NaN.
#[inline(always)]
pub(crate) fn below_a_cell(dt: f64, vel: &[f64]) -> bool {
    // Eight running maxima and sums side by side (they vectorise; a sum
    // carries any NaN or infinity to the end), by comparisons, not
    // `f64::max` (docs/pitfalls.md).
    let (mut m, mut sum) = ([0.0f64; 8], [0.0f64; 8]);
    let mut chunks = vel.chunks_exact(8);
    for c in &mut chunks {
        for l in 0..8 {
            let s = (dt * c[l]).abs();
            m[l] = if s > m[l] { s } else { m[l] };
            sum[l] += s;
        }
    }
    for (l, &v) in chunks.remainder().iter().enumerate() {
        let s = (dt * v).abs();
        m[l] = if s > m[l] { s } else { m[l] };
        sum[l] += s;
    }
    let (mut top, mut total) = (0.0, 0.0);
    for l in 0..8 {
        top = if m[l] > top { m[l] } else { top };
        total += sum[l];
    }
    total.is_finite() && top < 1.0
}

/// The packed velocity `vel` (components `comps`, lattice strides
/// `strides`) of the box of `n` cells periodic on every axis advected by
/// itself over `dt` cells per unit speed, semi-Lagrangian or (with
/// `maccormack`) MacCormack without the limiter, into `out`'s components
/// (own samples; the periodic copies are the caller's). Every face of
/// `dt·vel` below one cell ([`below_a_cell`]); `scratch` holds
/// [`scratch_len`] values.
#[inline(always)]
pub(crate) fn advect_velocity<const D: usize>(
    n: [usize; D],
    strides: [[usize; D]; D],
    maccormack: bool,
    dt: f64,
    comps: [&[f64]; D],
    outs: [&mut [f64]; D],
    scratch: &mut [f64],
) {
    let pad = Padded::new(n);
    let p = pad.len;
    assert!(scratch.len() >= scratch_len(n), "near: advection scratch");
    let (scaled, rest) = scratch.split_at_mut(D * p);
    let (fields, rest) = rest.split_at_mut(D * p);
    let (disp, rest) = rest.split_at_mut(D * p);
    let (hat, rest) = rest.split_at_mut(p);
    let tilde = &mut rest[..p];
    each_axis!(D, a => {
        pad_from(&pad, strides[a], comps[a], dt, &mut scaled[a * p..(a + 1) * p]);
        pad_from(&pad, strides[a], comps[a], 1.0, &mut fields[a * p..(a + 1) * p]);
    });
    // Filled one constant index at a time (as `MacGrid::components`).
    let mut v = [&scaled[..0]; D];
    each_axis!(D, a => {
        v[a] = &scaled[a * p..(a + 1) * p];
    });
    each_axis!(D, a => {
        let f = &fields[a * p..(a + 1) * p];
        displacement(&pad, a, v, disp);
        trace(&pad, disp, 1.0, f, hat);
        if maccormack {
            fill_copies(&pad, hat);
            trace(&pad, disp, -1.0, hat, tilde);
            let (hat, tilde) = (&*hat, &*tilde);
            unpad(&pad, strides[a], outs[a], |c| hat[c] + 0.5 * (f[c] - tilde[c]));
        } else {
            let hat = &*hat;
            unpad(&pad, strides[a], outs[a], |c| hat[c]);
        }
    });
}

/// `d/ds` of [`blend`]: `sign(s)·(o − own)`, and at `s = 0` the mean of
/// the two sides, `(lower − upper)/2`.
#[inline(always)]
fn blend_ds(s: f64, lower: f64, own: f64, upper: f64) -> f64 {
    if s > 0.0 {
        lower - own
    } else if s < 0.0 {
        own - upper
    } else {
        0.5 * (lower - upper)
    }
}

/// The weights [`blend`] gives the lower, own and upper samples.
#[inline(always)]
fn weights(s: f64) -> [f64; 3] {
    let w = s.abs();
    if s > 0.0 { [w, 1.0 - w, 0.0] } else { [0.0, 1.0 - w, w] }
}

/// Adjoint of [`fill_copies`]: each copy's value added into the sample it
/// copies and zeroed, axis by axis in reverse order.
#[inline(always)]
pub(crate) fn fill_copies_adjoint<const D: usize>(pad: &Padded<D>, g: &mut [f64]) {
    assert!(g.len() >= pad.len, "near: padded lattice length");
    for a in (0..D).rev() {
        let mut outer = 1;
        for b in a + 1..D {
            outer *= pad.n[b];
        }
        let (st, m) = (pad.stride[a], pad.n[a]);
        for o in 0..outer {
            let (mut base, mut rest) = (0, o);
            for b in a + 1..D {
                base += (rest % pad.n[b] + 1) * pad.stride[b];
                rest /= pad.n[b];
            }
            for j in 0..st {
                let lower = std::mem::take(&mut g[base + j]);
                g[base + m * st + j] += lower;
                let upper = std::mem::take(&mut g[base + (m + 1) * st + j]);
                g[base + st + j] += upper;
            }
        }
    }
}

/// Adjoint of [`displacement`]: the displacement's adjoint `gdisp` (`D`
/// padded arrays, own samples read) added into the padded components'
/// `gvel` (copies included: fold them with [`fill_copies_adjoint`]).
pub(crate) fn displacement_adjoint<const D: usize>(pad: &Padded<D>, a: usize, gdisp: &[f64], gvel: &mut [Vec<f64>]) {
    let (p, st, n0) = (pad.len, pad.stride, pad.n[0]);
    for (b, gv) in gvel.iter_mut().enumerate() {
        let gd = &gdisp[b * p..(b + 1) * p];
        for r in 0..pad.rows() {
            let c0 = pad.index(pad.row(r));
            for c in c0..c0 + n0 {
                if b == a {
                    gv[c] += gd[c];
                } else {
                    for t in [c - st[a], c, c - st[a] + st[b], c + st[b]] {
                        gv[t] += 0.25 * gd[c];
                    }
                }
            }
        }
    }
}

/// Adjoint of [`trace`] (hand-written): adds `Jᵀ·g` (`g` padded, read at
/// the own samples) into the padded `gf` (the traced field's, copies
/// included: fold them with [`fill_copies_adjoint`]) and `gdisp` (the
/// displacement's, `D` padded arrays).
#[allow(clippy::too_many_arguments)]
pub(crate) fn trace_adjoint<const D: usize>(pad: &Padded<D>, disp: &[f64], sign: f64, f: &[f64], g: &[f64], gf: &mut [f64], gdisp: &mut [f64]) {
    let (p, st) = (pad.len, pad.stride);
    let n0 = pad.n[0];
    let rows_around = 3usize.pow(D as u32 - 1);
    let mut corner = 1;
    for b in 1..D {
        corner += st[b];
    }
    let mut off = [0usize; 9];
    for (k, o) in off.iter_mut().enumerate().take(rows_around) {
        *o = if D >= 2 { (k % 3) * st[1] } else { 0 } + if D >= 3 { (k / 3) * st[2] } else { 0 };
    }
    for r in 0..pad.rows() {
        let c0 = pad.index(pad.row(r));
        for i in 0..n0 {
            let c = c0 + i;
            let gc = g[c];
            let mut s = [0.0; D];
            for b in 0..D {
                s[b] = sign * disp[b * p + c];
            }
            let lo = c - corner;
            let mut w = [[0.0; 3]; D];
            for b in 0..D {
                w[b] = weights(s[b]);
            }
            // The field: each of the 3^D samples times its weight.
            for k in 0..rows_around {
                let mut wr = gc;
                if D >= 2 {
                    wr *= w[1][k % 3];
                }
                if D >= 3 {
                    wr *= w[2][k / 3];
                }
                for d in 0..3 {
                    gf[lo + off[k] + d] += wr * w[0][d];
                }
            }
            // The velocity: d(value)/d(s_b), the other axes blended.
            for b in 0..D {
                let mut t = [0.0; 9];
                for k in 0..rows_around {
                    let p = lo + off[k];
                    t[k] = if b == 0 { blend_ds(s[0], f[p], f[p + 1], f[p + 2]) } else { blend(s[0], f[p], f[p + 1], f[p + 2]) };
                }
                let mut m = rows_around;
                for e in 1..D {
                    m /= 3;
                    for k in 0..m {
                        let (l, o, u) = (t[3 * k], t[3 * k + 1], t[3 * k + 2]);
                        t[k] = if e == b { blend_ds(s[e], l, o, u) } else { blend(s[e], l, o, u) };
                    }
                }
                gdisp[b * p + c] += sign * gc * t[0];
            }
        }
    }
}

/// Adjoint of [`advect_velocity`] (hand-written, the reference for
/// Enzyme's): adds `Jᵀ·g` (`g` the output's components, own samples read)
/// into the velocity's components `gcomps` (own samples; its copies are
/// not inputs that matter: [`advect_velocity`] reads only own samples) and
/// returns the derivative with respect to `dt`.
#[allow(clippy::too_many_arguments)]
pub fn advect_velocity_adjoint<const D: usize>(
    n: [usize; D],
    strides: [[usize; D]; D],
    maccormack: bool,
    dt: f64,
    comps: [&[f64]; D],
    g: [&[f64]; D],
    gcomps: [&mut [f64]; D],
) -> f64 {
    let pad = Padded::new(n);
    let p = pad.len;
    let mut scaled = vec![vec![0.0; p]; D];
    let mut fields = vec![vec![0.0; p]; D];
    for a in 0..D {
        pad_from(&pad, strides[a], comps[a], dt, &mut scaled[a]);
        pad_from(&pad, strides[a], comps[a], 1.0, &mut fields[a]);
    }
    let v: [&[f64]; D] = std::array::from_fn(|a| scaled[a].as_slice());
    let mut gscaled = vec![vec![0.0; p]; D];
    let mut gfields = vec![vec![0.0; p]; D];
    let (mut hat, mut ghat, mut gtilde, mut gp) = (vec![0.0; p], vec![0.0; p], vec![0.0; p], vec![0.0; p]);
    let (mut disp, mut gdisp) = (vec![0.0; D * p], vec![0.0; D * p]);
    for a in 0..D {
        // The output's adjoint, padded (own samples only).
        gp.fill(0.0);
        for r in 0..pad.rows() {
            let (s, d) = pad.starts(r, strides[a]);
            gp[d..d + n[0]].copy_from_slice(&g[a][s..s + n[0]]);
        }
        let f = &fields[a];
        displacement(&pad, a, v, &mut disp);
        gdisp.fill(0.0);
        if maccormack {
            trace(&pad, &disp, 1.0, f, &mut hat);
            fill_copies(&pad, &mut hat);
            // out = hat + ½(f − tilde), tilde = trace₋(hat).
            ghat.copy_from_slice(&gp);
            for (t, &x) in gtilde.iter_mut().zip(&gp) {
                *t = -0.5 * x;
            }
            for (y, &x) in gfields[a].iter_mut().zip(&gp) {
                *y += 0.5 * x;
            }
            trace_adjoint(&pad, &disp, -1.0, &hat, &gtilde, &mut ghat, &mut gdisp);
            fill_copies_adjoint(&pad, &mut ghat);
            trace_adjoint(&pad, &disp, 1.0, f, &ghat, &mut gfields[a], &mut gdisp);
        } else {
            trace_adjoint(&pad, &disp, 1.0, f, &gp, &mut gfields[a], &mut gdisp);
        }
        displacement_adjoint(&pad, a, &gdisp, &mut gscaled);
    }
    let mut gdt = 0.0;
    for (a, gc) in gcomps.into_iter().enumerate() {
        fill_copies_adjoint(&pad, &mut gscaled[a]);
        fill_copies_adjoint(&pad, &mut gfields[a]);
        for r in 0..pad.rows() {
            let (s, d) = pad.starts(r, strides[a]);
            for i in 0..n[0] {
                gc[s + i] += dt * gscaled[a][d + i] + gfields[a][d + i];
                gdt += comps[a][s + i] * gscaled[a][d + i];
            }
        }
    }
    gdt
}
