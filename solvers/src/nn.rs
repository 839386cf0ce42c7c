//! Neural-network kernels on slices: dense layers, 1D and 2D convolutions
//! (zero or periodic padding), pooling, upsampling and activations, each
//! with its hand-written adjoint. Plain functions; the framework wraps them
//! as operators.
//!
//! Layouts: weights row-major `[out][in]` (dense) and `[c_out][c_in][k]`
//! (1D) / `[c_out][c_in][k][k]` (2D, rows = y); feature maps channel-major,
//! `[c][len]` or `[c][ny][nx]`. Adjoints **add** into their outputs.

use std::simd::f64x8;

/// How a convolution reads beyond the edges.
#[derive(Clone, Copy, Debug, PartialEq, Eq, serde::Serialize, serde::Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum Padding {
    /// Zeros outside.
    Zero,
    /// The signal wraps around.
    Periodic,
}

/// `y = W·x + b` (overwrites `y`); `w` is `n_out × n_in`.
pub fn dense(n_in: usize, w: &[f64], b: &[f64], x: &[f64], y: &mut [f64]) {
    for (o, (yo, bo)) in y.iter_mut().zip(b).enumerate() {
        let row = &w[o * n_in..(o + 1) * n_in];
        *yo = bo + dot(row, x);
    }
}

/// Adjoint of [`dense`]: `gx += Wᵀ·gy`, `gw += gy·xᵀ`, `gb += gy`.
pub fn dense_adjoint(n_in: usize, w: &[f64], x: &[f64], gy: &[f64], gx: &mut [f64], gw: &mut [f64], gb: &mut [f64]) {
    for (o, &g) in gy.iter().enumerate() {
        gb[o] += g;
        let row = &w[o * n_in..(o + 1) * n_in];
        let grow = &mut gw[o * n_in..(o + 1) * n_in];
        for ((gxi, gwi), (&wi, &xi)) in gx.iter_mut().zip(grow.iter_mut()).zip(row.iter().zip(x)) {
            *gxi += g * wi;
            *gwi += g * xi;
        }
    }
}

#[inline(always)]
fn dot(a: &[f64], b: &[f64]) -> f64 {
    // Four partial sums: vectorises and shortens the dependency chain.
    let mut s = [0.0; 4];
    let (ca, cb) = (a.chunks_exact(4), b.chunks_exact(4));
    let (ra, rb) = (ca.remainder(), cb.remainder());
    for (x, y) in ca.zip(cb) {
        for k in 0..4 {
            s[k] += x[k] * y[k];
        }
    }
    let mut t = (s[0] + s[1]) + (s[2] + s[3]);
    for (x, y) in ra.iter().zip(rb) {
        t += x * y;
    }
    t
}

/// Shape of a 1D convolution: `c_in → c_out` channels, odd kernel `k`,
/// `len` positions in and out ("same" padding).
#[derive(Clone, Copy, Debug, PartialEq, Eq, serde::Serialize, serde::Deserialize)]
pub struct Conv1d {
    /// Input channels.
    pub c_in: usize,
    /// Output channels.
    pub c_out: usize,
    /// Kernel width (odd).
    pub k: usize,
    /// Positions.
    pub len: usize,
    /// Edge rule.
    pub padding: Padding,
}

impl Conv1d {
    /// Number of weights (`c_out·c_in·k`; the biases are `c_out` more).
    pub fn n_weights(&self) -> usize {
        self.c_out * self.c_in * self.k
    }

    /// Source position of output `i` under tap `t`, if it reads inside (or wraps).
    #[inline(always)]
    fn src(&self, i: usize, t: usize) -> Option<usize> {
        let j = i as isize + t as isize - (self.k / 2) as isize;
        let n = self.len as isize;
        match self.padding {
            Padding::Periodic => Some(j.rem_euclid(n) as usize),
            Padding::Zero => (0..n).contains(&j).then_some(j as usize),
        }
    }

    /// For tap `t`, the output range `[lo, hi)` whose source lies inside
    /// without wrapping, and the source offset.
    #[inline(always)]
    fn interior(&self, t: usize) -> (usize, usize, isize) {
        let off = t as isize - (self.k / 2) as isize;
        let n = self.len as isize;
        // Empty (lo = hi) when the kernel is wider than the signal.
        let lo = (-off).clamp(0, n);
        let hi = (n - off).min(n).max(lo);
        (lo as usize, hi as usize, off)
    }
}

/// `y[o][i] = b[o] + Σ_c Σ_t w[o][c][t]·x[c][i + t − k/2]` (overwrites `y`).
///
/// The input is padded once (wrapped or zeros), then each block of four
/// output channels × eight positions is summed in registers over `c` and
/// `t` (with the widest vector instructions the CPU has); the sums run in
/// the order of [`conv1d_simple`], so the results are the same.
pub fn conv1d(s: &Conv1d, w: &[f64], b: &[f64], x: &[f64], y: &mut [f64]) {
    assert!(w.len() >= s.n_weights() && b.len() >= s.c_out && x.len() >= s.c_in * s.len && y.len() >= s.c_out * s.len, "conv1d: lengths");
    let xp = pad(s, s.c_in, x);
    let taps = Taps { base: 0, q: (s.c_in * s.k) as isize, r: s.k as isize, t: 1 };
    correlate(s.len, s.k, s.c_out, s.c_in, w, taps, Some(b), &xp, y, false);
}

/// Adjoint of [`conv1d`]: `gx += ∂/∂x`, `gw += ∂/∂w`, `gb += ∂/∂b` of
/// `⟨gy, y⟩`. The input gradient is a correlation of the padded `gy` with
/// the flipped, transposed kernel (the forward kernel again); the weight
/// gradient is a dot product per weight over the positions.
pub fn conv1d_adjoint(s: &Conv1d, w: &[f64], x: &[f64], gy: &[f64], gx: &mut [f64], gw: &mut [f64], gb: &mut [f64]) {
    let (n, k) = (s.len, s.k);
    assert!(w.len() >= s.n_weights() && gw.len() >= s.n_weights() && gb.len() >= s.c_out, "conv1d_adjoint: lengths");
    assert!(x.len() >= s.c_in * n && gx.len() >= s.c_in * n && gy.len() >= s.c_out * n, "conv1d_adjoint: lengths");
    for o in 0..s.c_out {
        gb[o] += gy[o * n..(o + 1) * n].iter().sum::<f64>();
    }
    // gx[c][m] += Σ_o Σ_t w[o][c][k−1−t]·gyp[o][m + t].
    let gyp = pad(s, s.c_out, gy);
    let taps = Taps { base: (k - 1) as isize, q: k as isize, r: (s.c_in * k) as isize, t: -1 };
    correlate(n, k, s.c_in, s.c_out, w, taps, None, &gyp, gx, true);
    // gw[o][c][t] += Σ_i gy[o][i]·xp[c][i + t].
    let xp = pad(s, s.c_in, x);
    weight_gradient(s, gy, &xp, gw);
}

/// Where weight `(q, r, t)` of a correlation sits: `base + q·q + r·r + t·t`.
#[derive(Clone, Copy)]
struct Taps {
    base: isize,
    q: isize,
    r: isize,
    t: isize,
}

impl Taps {
    #[inline(always)]
    fn at(&self, q: usize, r: usize, t: usize) -> usize {
        (self.base + q as isize * self.q + r as isize * self.r + t as isize * self.t) as usize
    }
}

/// The `c` channels of `x` (`len` each) padded by `k/2` on both sides,
/// wrapped or with zeros: rows of `len + k − 1`.
fn pad(s: &Conv1d, c: usize, x: &[f64]) -> Vec<f64> {
    let (n, h) = (s.len, s.k / 2);
    let np = n + s.k - 1;
    let mut xp = vec![0.0; c * np];
    for ch in 0..c {
        let (row, src) = (&mut xp[ch * np..(ch + 1) * np], &x[ch * n..(ch + 1) * n]);
        row[h..h + n].copy_from_slice(src);
        if s.padding == Padding::Periodic {
            for j in 0..h {
                // Left pad: positions −h..0; right pad: n..n+h (mod n).
                row[j] = src[(j + n - h % n) % n];
                row[h + n + j] = src[j % n];
            }
        }
    }
    xp
}

crate::simd_dispatch! {
    /// `out[q][i] (= or +=) bias[q] + Σ_r Σ_t W(q, r, t)·inp[r][i + t]` for
    /// `q < nq`, `r < nr`, `t < k`, `i < n`, with `inp` rows of `n + k − 1`.
    #[allow(clippy::too_many_arguments)]
    fn correlate(n: usize, k: usize, nq: usize, nr: usize, w: &[f64], taps: Taps, bias: Option<&[f64]>, inp: &[f64], out: &mut [f64], add: bool) => correlate_body
}

#[inline(always)]
#[allow(clippy::too_many_arguments)]
fn correlate_body(n: usize, k: usize, nq: usize, nr: usize, w: &[f64], taps: Taps, bias: Option<&[f64]>, inp: &[f64], out: &mut [f64], add: bool) {
    // The kernel width as a constant for the common sizes, so that the
    // taps unroll and the accumulators stay in registers.
    match k {
        3 => correlate_k::<3>(n, nq, nr, w, taps, bias, inp, out, add),
        5 => correlate_k::<5>(n, nq, nr, w, taps, bias, inp, out, add),
        7 => correlate_k::<7>(n, nq, nr, w, taps, bias, inp, out, add),
        _ => correlate_scalar(n, k, 0..nq, 0, nr, w, taps, bias, inp, out, add),
    }
}

#[inline(always)]
#[allow(clippy::too_many_arguments)]
fn correlate_k<const K: usize>(n: usize, nq: usize, nr: usize, w: &[f64], taps: Taps, bias: Option<&[f64]>, inp: &[f64], out: &mut [f64], add: bool) {
    let mut q0 = 0;
    while q0 + 4 <= nq {
        correlate_rows::<K, 4>(n, nr, w, taps, bias, inp, out, add, q0);
        q0 += 4;
    }
    while q0 < nq {
        correlate_rows::<K, 1>(n, nr, w, taps, bias, inp, out, add, q0);
        q0 += 1;
    }
}

/// Rows `q0..q0 + Q`: 32 positions at a time (4 × 8 lanes), then 8, then
/// the tail one by one.
#[inline(always)]
#[allow(clippy::too_many_arguments)]
fn correlate_rows<const K: usize, const Q: usize>(
    n: usize,
    nr: usize,
    w: &[f64],
    taps: Taps,
    bias: Option<&[f64]>,
    inp: &[f64],
    out: &mut [f64],
    add: bool,
    q0: usize,
) {
    let mut i0 = 0;
    while i0 + 32 <= n {
        correlate_tile::<K, Q, 4>(n, nr, w, taps, bias, inp, out, add, q0, i0);
        i0 += 32;
    }
    while i0 + 8 <= n {
        correlate_tile::<K, Q, 1>(n, nr, w, taps, bias, inp, out, add, q0, i0);
        i0 += 8;
    }
    correlate_scalar(n, K, q0..q0 + Q, i0, nr, w, taps, bias, inp, out, add);
}

/// `Q` rows × `P`·8 positions from `(q0, i0)`, summed in registers over
/// `r` and `t` (in that order, as the plain loops). `P` is 1 or 4; the
/// position chunks are written out so that the accumulators are plain
/// vector values (a loop over them left them on the stack).
#[inline(always)]
#[allow(clippy::too_many_arguments)]
fn correlate_tile<const K: usize, const Q: usize, const P: usize>(
    n: usize,
    nr: usize,
    w: &[f64],
    taps: Taps,
    bias: Option<&[f64]>,
    inp: &[f64],
    out: &mut [f64],
    add: bool,
    q0: usize,
    i0: usize,
) {
    let np = n + K - 1;
    let zero = f64x8::splat(0.0);
    let mut acc = [[zero; 4]; Q];
    for (q, aq) in acc.iter_mut().enumerate() {
        let b = f64x8::splat(bias.map_or(0.0, |b| b[q0 + q]));
        for p in 0..P {
            let at = (q0 + q) * n + i0 + 8 * p;
            let start = if add { f64x8::from_slice(&out[at..at + 8]) } else { zero };
            aq[p] = start + b;
        }
    }
    for r in 0..nr {
        let mut wl = [[0.0f64; K]; Q];
        for (q, wq) in wl.iter_mut().enumerate() {
            for (t, v) in wq.iter_mut().enumerate() {
                *v = w[taps.at(q0 + q, r, t)];
            }
        }
        let row = &inp[r * np + i0..r * np + i0 + 8 * P + K - 1];
        for t in 0..K {
            if P == 4 {
                let x0 = f64x8::from_slice(&row[t..t + 8]);
                let x1 = f64x8::from_slice(&row[t + 8..t + 16]);
                let x2 = f64x8::from_slice(&row[t + 16..t + 24]);
                let x3 = f64x8::from_slice(&row[t + 24..t + 32]);
                for q in 0..Q {
                    let wq = f64x8::splat(wl[q][t]);
                    acc[q][0] += wq * x0;
                    acc[q][1] += wq * x1;
                    acc[q][2] += wq * x2;
                    acc[q][3] += wq * x3;
                }
            } else {
                let x0 = f64x8::from_slice(&row[t..t + 8]);
                for q in 0..Q {
                    acc[q][0] += f64x8::splat(wl[q][t]) * x0;
                }
            }
        }
    }
    for (q, aq) in acc.iter().enumerate() {
        for p in 0..P {
            let at = (q0 + q) * n + i0 + 8 * p;
            aq[p].copy_to_slice(&mut out[at..at + 8]);
        }
    }
}

/// Rows `qs` of [`correlate`] from position `i0` on, one value at a time.
#[inline(always)]
#[allow(clippy::too_many_arguments)]
fn correlate_scalar(
    n: usize,
    k: usize,
    qs: std::ops::Range<usize>,
    i0: usize,
    nr: usize,
    w: &[f64],
    taps: Taps,
    bias: Option<&[f64]>,
    inp: &[f64],
    out: &mut [f64],
    add: bool,
) {
    let np = n + k - 1;
    for q in qs {
        for i in i0..n {
            let mut a = if add { out[q * n + i] } else { 0.0 } + bias.map_or(0.0, |b| b[q]);
            for r in 0..nr {
                for t in 0..k {
                    a += w[taps.at(q, r, t)] * inp[r * np + i + t];
                }
            }
            out[q * n + i] = a;
        }
    }
}

crate::simd_dispatch! {
    /// `gw[o][c][t] += Σ_i gy[o][i]·xp[c][i + t]`.
    fn weight_gradient(s: &Conv1d, gy: &[f64], xp: &[f64], gw: &mut [f64]) => weight_gradient_body
}

#[inline(always)]
fn weight_gradient_body(s: &Conv1d, gy: &[f64], xp: &[f64], gw: &mut [f64]) {
    match s.k {
        3 => weight_gradient_k::<3>(s, gy, xp, gw),
        5 => weight_gradient_k::<5>(s, gy, xp, gw),
        7 => weight_gradient_k::<7>(s, gy, xp, gw),
        _ => weight_gradient_scalar(s, 0..s.c_out, gy, xp, gw),
    }
}

/// Eight output channels per vector: `gy` transposed to `[i][o]`, then per
/// input channel all `K` taps of eight (or 32) output channels summed over
/// the positions in registers, and added into `gw` at the end.
#[inline(always)]
fn weight_gradient_k<const K: usize>(s: &Conv1d, gy: &[f64], xp: &[f64], gw: &mut [f64]) {
    let (n, co) = (s.len, s.c_out);
    let np = n + K - 1;
    let full = co - co % 8;
    let mut gyt = vec![0.0; n * full];
    for o in 0..full {
        for i in 0..n {
            gyt[i * full + o] = gy[o * n + i];
        }
    }
    let mut o0 = 0;
    while o0 + 32 <= full {
        weight_gradient_tile::<K, 4>(s, &gyt, full, o0, xp, np, gw);
        o0 += 32;
    }
    while o0 + 8 <= full {
        weight_gradient_tile::<K, 1>(s, &gyt, full, o0, xp, np, gw);
        o0 += 8;
    }
    weight_gradient_scalar(s, full..co, gy, xp, gw);
}

#[inline(always)]
fn weight_gradient_tile<const K: usize, const V: usize>(s: &Conv1d, gyt: &[f64], stride: usize, o0: usize, xp: &[f64], np: usize, gw: &mut [f64]) {
    let (n, ci) = (s.len, s.c_in);
    let zero = f64x8::splat(0.0);
    for c in 0..ci {
        let row = &xp[c * np..(c + 1) * np];
        let mut acc = [[zero; 4]; K];
        for i in 0..n {
            let g = &gyt[i * stride + o0..i * stride + o0 + 8 * V];
            if V == 4 {
                let g0 = f64x8::from_slice(&g[0..8]);
                let g1 = f64x8::from_slice(&g[8..16]);
                let g2 = f64x8::from_slice(&g[16..24]);
                let g3 = f64x8::from_slice(&g[24..32]);
                for t in 0..K {
                    let xv = f64x8::splat(row[i + t]);
                    acc[t][0] += g0 * xv;
                    acc[t][1] += g1 * xv;
                    acc[t][2] += g2 * xv;
                    acc[t][3] += g3 * xv;
                }
            } else {
                let g0 = f64x8::from_slice(&g[0..8]);
                for t in 0..K {
                    acc[t][0] += g0 * f64x8::splat(row[i + t]);
                }
            }
        }
        for (t, at) in acc.iter().enumerate() {
            for v in 0..V {
                for (l, &val) in at[v].as_array().iter().enumerate() {
                    gw[((o0 + 8 * v + l) * ci + c) * K + t] += val;
                }
            }
        }
    }
}

/// Output channels `os` of [`weight_gradient`], one weight at a time.
#[inline(always)]
fn weight_gradient_scalar(s: &Conv1d, os: std::ops::Range<usize>, gy: &[f64], xp: &[f64], gw: &mut [f64]) {
    let (n, k) = (s.len, s.k);
    let np = n + k - 1;
    for o in os {
        let g = &gy[o * n..(o + 1) * n];
        for c in 0..s.c_in {
            let row = &xp[c * np..(c + 1) * np];
            for t in 0..k {
                gw[(o * s.c_in + c) * k + t] += dot(g, &row[t..t + n]);
            }
        }
    }
}

/// [`conv1d`] as plain loops without run-time dispatch (what Enzyme
/// differentiates for the generated-versus-hand comparison; the same sums in
/// the same order, so the same results).
pub fn conv1d_simple(s: &Conv1d, w: &[f64], b: &[f64], x: &[f64], y: &mut [f64]) {
    let (n, k) = (s.len, s.k);
    for o in 0..s.c_out {
        let yo = &mut y[o * n..(o + 1) * n];
        yo.fill(b[o]);
        for c in 0..s.c_in {
            let xc = &x[c * n..(c + 1) * n];
            for t in 0..k {
                let wt = w[(o * s.c_in + c) * k + t];
                // Interior: a shifted axpy that vectorises; edges apart.
                let (lo, hi, off) = s.interior(t);
                if hi > lo {
                    let src = &xc[(lo as isize + off) as usize..(hi as isize + off) as usize];
                    for (yi, xi) in yo[lo..hi].iter_mut().zip(src) {
                        *yi += wt * xi;
                    }
                }
                for i in (0..lo).chain(hi..n) {
                    if let Some(j) = s.src(i, t) {
                        yo[i] += wt * xc[j];
                    }
                }
            }
        }
    }
}

/// [`conv1d_adjoint`] as plain loops (the reference for the blocked one).
pub fn conv1d_adjoint_simple(s: &Conv1d, w: &[f64], x: &[f64], gy: &[f64], gx: &mut [f64], gw: &mut [f64], gb: &mut [f64]) {
    let (n, k) = (s.len, s.k);
    for o in 0..s.c_out {
        let go = &gy[o * n..(o + 1) * n];
        gb[o] += go.iter().sum::<f64>();
        for c in 0..s.c_in {
            let xc = &x[c * n..(c + 1) * n];
            let gxc = &mut gx[c * n..(c + 1) * n];
            for t in 0..k {
                let wi = (o * s.c_in + c) * k + t;
                let wt = w[wi];
                let (lo, hi, off) = s.interior(t);
                let mut acc = 0.0;
                if hi > lo {
                    let range = (lo as isize + off) as usize..(hi as isize + off) as usize;
                    acc = dot(&go[lo..hi], &xc[range.clone()]);
                    for (gxi, gi) in gxc[range].iter_mut().zip(&go[lo..hi]) {
                        *gxi += wt * gi;
                    }
                }
                for i in (0..lo).chain(hi..n) {
                    if let Some(j) = s.src(i, t) {
                        acc += go[i] * xc[j];
                        gxc[j] += wt * go[i];
                    }
                }
                gw[wi] += acc;
            }
        }
    }
}

/// Shape of a 2D convolution: `c_in → c_out`, odd square kernel `k`, an
/// `nx × ny` map in and out.
#[derive(Clone, Copy, Debug, PartialEq, Eq, serde::Serialize, serde::Deserialize)]
pub struct Conv2d {
    /// Input channels.
    pub c_in: usize,
    /// Output channels.
    pub c_out: usize,
    /// Kernel width (odd).
    pub k: usize,
    /// Columns.
    pub nx: usize,
    /// Rows.
    pub ny: usize,
    /// Edge rule (both axes).
    pub padding: Padding,
}

impl Conv2d {
    /// Number of weights (`c_out·c_in·k²`).
    pub fn n_weights(&self) -> usize {
        self.c_out * self.c_in * self.k * self.k
    }

    /// The input row read by output row `j` under kernel row `t`.
    #[inline(always)]
    fn src_row(&self, j: usize, t: usize) -> Option<usize> {
        wrap(j, t, self.k, self.ny, self.padding)
    }
}

#[inline(always)]
fn wrap(i: usize, t: usize, k: usize, n: usize, padding: Padding) -> Option<usize> {
    let j = i as isize + t as isize - (k / 2) as isize;
    match padding {
        Padding::Periodic => Some(j.rem_euclid(n as isize) as usize),
        Padding::Zero => (0..n as isize).contains(&j).then_some(j as usize),
    }
}

/// `y[o][j][i] = b[o] + Σ_c Σ_{ty,tx} w[o][c][ty][tx]·x[c][j+ty−k/2][i+tx−k/2]`.
pub fn conv2d(s: &Conv2d, w: &[f64], b: &[f64], x: &[f64], y: &mut [f64]) {
    let (nx, ny, k) = (s.nx, s.ny, s.k);
    let row = Conv1d { c_in: 1, c_out: 1, k, len: nx, padding: s.padding };
    for o in 0..s.c_out {
        y[o * nx * ny..(o + 1) * nx * ny].fill(b[o]);
        for c in 0..s.c_in {
            for j in 0..ny {
                for ty in 0..k {
                    let Some(js) = s.src_row(j, ty) else { continue };
                    let xrow = &x[(c * ny + js) * nx..(c * ny + js + 1) * nx];
                    let yrow = &mut y[(o * ny + j) * nx..(o * ny + j + 1) * nx];
                    for tx in 0..k {
                        let wt = w[((o * s.c_in + c) * k + ty) * k + tx];
                        let (lo, hi, off) = row.interior(tx);
                        if hi > lo {
                            let src = &xrow[(lo as isize + off) as usize..(hi as isize + off) as usize];
                            for (yi, xi) in yrow[lo..hi].iter_mut().zip(src) {
                                *yi += wt * xi;
                            }
                        }
                        for i in (0..lo).chain(hi..nx) {
                            if let Some(is) = row.src(i, tx) {
                                yrow[i] += wt * xrow[is];
                            }
                        }
                    }
                }
            }
        }
    }
}

/// Adjoint of [`conv2d`] (adds into `gx`, `gw`, `gb`).
pub fn conv2d_adjoint(s: &Conv2d, w: &[f64], x: &[f64], gy: &[f64], gx: &mut [f64], gw: &mut [f64], gb: &mut [f64]) {
    let (nx, ny, k) = (s.nx, s.ny, s.k);
    let row = Conv1d { c_in: 1, c_out: 1, k, len: nx, padding: s.padding };
    for o in 0..s.c_out {
        gb[o] += gy[o * nx * ny..(o + 1) * nx * ny].iter().sum::<f64>();
        for c in 0..s.c_in {
            for j in 0..ny {
                for ty in 0..k {
                    let Some(js) = s.src_row(j, ty) else { continue };
                    let xrow = &x[(c * ny + js) * nx..(c * ny + js + 1) * nx];
                    let grow = &gy[(o * ny + j) * nx..(o * ny + j + 1) * nx];
                    let gxrow = &mut gx[(c * ny + js) * nx..(c * ny + js + 1) * nx];
                    for tx in 0..k {
                        let wi = ((o * s.c_in + c) * k + ty) * k + tx;
                        let wt = w[wi];
                        let (lo, hi, off) = row.interior(tx);
                        let mut acc = 0.0;
                        if hi > lo {
                            let range = (lo as isize + off) as usize..(hi as isize + off) as usize;
                            acc = dot(&grow[lo..hi], &xrow[range.clone()]);
                            for (gxi, gi) in gxrow[range].iter_mut().zip(&grow[lo..hi]) {
                                *gxi += wt * gi;
                            }
                        }
                        for i in (0..lo).chain(hi..nx) {
                            if let Some(is) = row.src(i, tx) {
                                acc += grow[i] * xrow[is];
                                gxrow[is] += wt * grow[i];
                            }
                        }
                        gw[wi] += acc;
                    }
                }
            }
        }
    }
}

/// Pointwise activation functions.
#[derive(Clone, Copy, Debug, PartialEq, Eq, serde::Serialize, serde::Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum Activation {
    /// `max(x, 0)`.
    Relu,
    /// `x` for `x > 0`, else `0.01·x`.
    LeakyRelu,
    /// `tanh x`.
    Tanh,
    /// `1/(1 + e^{−x})`.
    Sigmoid,
    /// `x·Φ(x)` with the tanh approximation (as in GPT-2 and JAX's default).
    Gelu,
    /// `x·sigmoid(x)`.
    Swish,
}

const GELU_C: f64 = 0.797_884_560_802_865_4; // √(2/π)

impl Activation {
    /// `f(x)`.
    #[inline(always)]
    pub fn f(self, x: f64) -> f64 {
        match self {
            Activation::Relu => x.max(0.0),
            Activation::LeakyRelu => {
                if x > 0.0 {
                    x
                } else {
                    0.01 * x
                }
            }
            Activation::Tanh => x.tanh(),
            Activation::Sigmoid => 1.0 / (1.0 + (-x).exp()),
            Activation::Gelu => 0.5 * x * (1.0 + (GELU_C * (x + 0.044715 * x * x * x)).tanh()),
            Activation::Swish => x / (1.0 + (-x).exp()),
        }
    }

    /// `f′(x)`.
    #[inline(always)]
    pub fn df(self, x: f64) -> f64 {
        match self {
            Activation::Relu => {
                if x > 0.0 {
                    1.0
                } else {
                    0.0
                }
            }
            Activation::LeakyRelu => {
                if x > 0.0 {
                    1.0
                } else {
                    0.01
                }
            }
            Activation::Tanh => {
                let t = x.tanh();
                1.0 - t * t
            }
            Activation::Sigmoid => {
                let s = 1.0 / (1.0 + (-x).exp());
                s * (1.0 - s)
            }
            Activation::Gelu => {
                let u = GELU_C * (x + 0.044715 * x * x * x);
                let t = u.tanh();
                0.5 * (1.0 + t) + 0.5 * x * (1.0 - t * t) * GELU_C * (1.0 + 3.0 * 0.044715 * x * x)
            }
            Activation::Swish => {
                let s = 1.0 / (1.0 + (-x).exp());
                s + x * s * (1.0 - s)
            }
        }
    }

    /// Whether `f` has a kink at 0 (for the gradient checks' smoothness radius).
    pub fn kinked(self) -> bool {
        matches!(self, Activation::Relu | Activation::LeakyRelu)
    }
}

/// Average pooling by 2 along positions, per channel: `c × len → c × len/2`.
pub fn avg_pool1d(c: usize, len: usize, x: &[f64], y: &mut [f64]) {
    let h = len / 2;
    for ch in 0..c {
        for i in 0..h {
            y[ch * h + i] = 0.5 * (x[ch * len + 2 * i] + x[ch * len + 2 * i + 1]);
        }
    }
}

/// Adjoint of [`avg_pool1d`] (adds into `gx`).
pub fn avg_pool1d_adjoint(c: usize, len: usize, gy: &[f64], gx: &mut [f64]) {
    let h = len / 2;
    for ch in 0..c {
        for i in 0..h {
            let g = 0.5 * gy[ch * h + i];
            gx[ch * len + 2 * i] += g;
            gx[ch * len + 2 * i + 1] += g;
        }
    }
}

/// Nearest-neighbour upsampling by 2: `c × len → c × 2·len`.
pub fn upsample1d(c: usize, len: usize, x: &[f64], y: &mut [f64]) {
    for ch in 0..c {
        for i in 0..len {
            let v = x[ch * len + i];
            y[ch * 2 * len + 2 * i] = v;
            y[ch * 2 * len + 2 * i + 1] = v;
        }
    }
}

/// Adjoint of [`upsample1d`] (adds into `gx`).
pub fn upsample1d_adjoint(c: usize, len: usize, gy: &[f64], gx: &mut [f64]) {
    for ch in 0..c {
        for i in 0..len {
            gx[ch * len + i] += gy[ch * 2 * len + 2 * i] + gy[ch * 2 * len + 2 * i + 1];
        }
    }
}

/// Average pooling by 2×2: `c × ny × nx → c × ny/2 × nx/2`.
pub fn avg_pool2d(c: usize, nx: usize, ny: usize, x: &[f64], y: &mut [f64]) {
    let (hx, hy) = (nx / 2, ny / 2);
    for ch in 0..c {
        for j in 0..hy {
            for i in 0..hx {
                let at = |dj: usize, di: usize| x[(ch * ny + 2 * j + dj) * nx + 2 * i + di];
                y[(ch * hy + j) * hx + i] = 0.25 * (at(0, 0) + at(0, 1) + at(1, 0) + at(1, 1));
            }
        }
    }
}

/// Adjoint of [`avg_pool2d`] (adds into `gx`).
pub fn avg_pool2d_adjoint(c: usize, nx: usize, ny: usize, gy: &[f64], gx: &mut [f64]) {
    let (hx, hy) = (nx / 2, ny / 2);
    for ch in 0..c {
        for j in 0..hy {
            for i in 0..hx {
                let g = 0.25 * gy[(ch * hy + j) * hx + i];
                for dj in 0..2 {
                    for di in 0..2 {
                        gx[(ch * ny + 2 * j + dj) * nx + 2 * i + di] += g;
                    }
                }
            }
        }
    }
}

/// Nearest-neighbour upsampling by 2×2: `c × ny × nx → c × 2ny × 2nx`.
pub fn upsample2d(c: usize, nx: usize, ny: usize, x: &[f64], y: &mut [f64]) {
    let (ux, uy) = (2 * nx, 2 * ny);
    for ch in 0..c {
        for j in 0..uy {
            for i in 0..ux {
                y[(ch * uy + j) * ux + i] = x[(ch * ny + j / 2) * nx + i / 2];
            }
        }
    }
}

/// Adjoint of [`upsample2d`] (adds into `gx`).
pub fn upsample2d_adjoint(c: usize, nx: usize, ny: usize, gy: &[f64], gx: &mut [f64]) {
    let (ux, uy) = (2 * nx, 2 * ny);
    for ch in 0..c {
        for j in 0..uy {
            for i in 0..ux {
                gx[(ch * ny + j / 2) * nx + i / 2] += gy[(ch * uy + j) * ux + i];
            }
        }
    }
}

/// `y[i] = f(x[i])` (overwrites `y`); tanh by [`tanh_slice`], the others
/// element by element.
pub fn activate(f: Activation, x: &[f64], y: &mut [f64]) {
    match f {
        Activation::Tanh => tanh_slice(x, y),
        _ => {
            for (y, &x) in y.iter_mut().zip(x) {
                *y = f.f(x);
            }
        }
    }
}

/// Adjoint of [`activate`]: `gx[i] += gy[i]·f′(x[i])` (tanh: `1 − tanh²`
/// from [`tanh_slice`], so that it is the derivative of what the forward
/// computed).
pub fn activate_adjoint(f: Activation, x: &[f64], gy: &[f64], gx: &mut [f64]) {
    match f {
        Activation::Tanh => {
            let mut t = vec![0.0; x.len()];
            tanh_slice(x, &mut t);
            for ((gx, &g), &t) in gx.iter_mut().zip(gy).zip(&t) {
                *gx += g * (1.0 - t * t);
            }
        }
        _ => {
            for ((gx, &g), &x) in gx.iter_mut().zip(gy).zip(x) {
                *gx += g * f.df(x);
            }
        }
    }
}

crate::simd_dispatch! {
    /// `y[i] = tanh(x[i])` in vector instructions, to within a few units in
    /// the last place (relative error below 1.5e-15, tested against
    /// `f64::tanh`; a NaN stays NaN): `e/(e + 2)` with `e = e^{2|x|} − 1` by
    /// range reduction and a polynomial ([`tanh_fast`]; `|x|` capped at 20,
    /// where tanh is 1 in double precision). Branch-free, so that the loop
    /// vectorises; the libm call it replaces dominated small networks.
    pub fn tanh_slice(x: &[f64], y: &mut [f64]) => tanh_slice_body
}

#[inline(always)]
fn tanh_slice_body(x: &[f64], y: &mut [f64]) {
    for (y, &x) in y.iter_mut().zip(x) {
        *y = tanh_fast(x);
    }
}

/// One value of [`tanh_slice`]: `sign(x)·e/(e + 2)` with `e = expm1(2|x|)`,
/// free of cancellation for every `x`.
#[inline(always)]
pub fn tanh_fast(x: f64) -> f64 {
    // (A comparison, not `min`: `f64::min` would turn a NaN into 20.)
    let a = if x.abs() > 20.0 { 20.0 } else { x.abs() };
    let e = expm1_fast(2.0 * a);
    let t = e / (e + 2.0);
    if x < 0.0 { -t } else { t }
}

/// `1/k!` for `k = 0..=13` (every `k!` here is exact in `f64`).
const INV_FACTORIAL: [f64; 14] = {
    let mut t = [1.0; 14];
    let mut f = 1.0;
    let mut k = 1;
    while k < 14 {
        f *= k as f64;
        t[k] = 1.0 / f;
        k += 1;
    }
    t
};

/// `e^z − 1` for `0 ≤ z ≤ 40`: `z = n·ln2 + r`, `|r| ≤ ln2/2`,
/// `e^r − 1 = r·q(r)` with `q` the Taylor polynomial of degree 12
/// (Estrin's scheme: a short dependency chain), then
/// `2^n·(e^r − 1) + (2^n − 1)` (`2^n` from the exponent bits; for `n = 0`
/// simply `e^r − 1`, accurate for tiny `z`).
#[inline(always)]
fn expm1_fast(z: f64) -> f64 {
    const SHIFT: f64 = 6755399441055744.0; // 1.5·2^52: adding it rounds to an integer
    const LN2_HI: f64 = 0.693_147_180_369_123_816_49;
    const LN2_LO: f64 = 1.908_214_929_270_587_7e-10;
    let kd = z * std::f64::consts::LOG2_E + SHIFT;
    let ki = kd.to_bits();
    let n = kd - SHIFT;
    let r = (z - n * LN2_HI) - n * LN2_LO;
    // q(r) = Σ_{j=0}^{12} r^j/(j+1)!, c_j = INV_FACTORIAL[j + 1].
    let c = |j: usize| INV_FACTORIAL[j + 1];
    let (r2, r4) = (r * r, (r * r) * (r * r));
    let r8 = r4 * r4;
    let q03 = (c(0) + c(1) * r) + (c(2) + c(3) * r) * r2;
    let q47 = (c(4) + c(5) * r) + (c(6) + c(7) * r) * r2;
    let q812 = ((c(8) + c(9) * r) + (c(10) + c(11) * r) * r2) + c(12) * r4;
    let q = (q03 + q47 * r4) + q812 * r8;
    let scale = f64::from_bits((ki.wrapping_sub(SHIFT.to_bits()).wrapping_add(1023)) << 52);
    scale * (r * q) + (scale - 1.0)
}
