//! Neural-network kernels on slices: dense layers, 1D and 2D convolutions
//! (zero or periodic padding), pooling, upsampling and activations, each
//! with its hand-written adjoint. Plain functions; the framework wraps them
//! as operators.
//!
//! Layouts: weights row-major `[out][in]` (dense) and `[c_out][c_in][k]`
//! (1D) / `[c_out][c_in][k][k]` (2D, rows = y); feature maps channel-major,
//! `[c][len]` or `[c][ny][nx]`. Adjoints **add** into their outputs.
//!
//! Every kernel is generic over the element type ([`Real`]: `f64` or
//! `f32`); the hot ones (the blocked 1D convolution, tanh) are compiled in
//! this crate for each type with run-time choice of vector instructions.

pub use crate::real::Real;

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
pub fn dense<R: Real>(n_in: usize, w: &[R], b: &[R], x: &[R], y: &mut [R]) {
    for (o, (yo, bo)) in y.iter_mut().zip(b).enumerate() {
        let row = &w[o * n_in..(o + 1) * n_in];
        *yo = *bo + dot(row, x);
    }
}

/// Adjoint of [`dense`]: `gx += Wᵀ·gy`, `gw += gy·xᵀ`, `gb += gy`.
pub fn dense_adjoint<R: Real>(n_in: usize, w: &[R], x: &[R], gy: &[R], gx: &mut [R], gw: &mut [R], gb: &mut [R]) {
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

/// [`dense`] for a batch: `ys` row `s` = `W·xs_s + b`, the samples' rows
/// one after another (`xs` is `batch × n_in`, `ys` `batch × n_out`). Each
/// row is computed exactly as [`dense`] computes it, so a sample's output
/// does not depend on the batch it is in.
pub fn dense_batch<R: Real>(n_in: usize, w: &[R], b: &[R], xs: &[R], ys: &mut [R]) {
    let n_out = b.len();
    assert_eq!(xs.len() / n_in.max(1), ys.len() / n_out.max(1), "dense_batch: rows of xs and ys differ");
    let batch = ys.len() / n_out.max(1);
    if split_pays(batch, n_in, n_out) {
        // Two halves of the batch on two threads: each row as one thread
        // would compute it.
        let mid = batch / 2;
        let ((xa, xb), (ya, yb)) = (xs.split_at(mid * n_in), ys.split_at_mut(mid * n_out));
        rayon::join(|| R::dense_batch_kernel(n_in, w, b, xa, ya), || R::dense_batch_kernel(n_in, w, b, xb, yb));
    } else {
        R::dense_batch_kernel(n_in, w, b, xs, ys);
    }
}

/// Batches of a dense layer with at least this many multiply-adds
/// ([`dense_batch`], [`dense_batch_adjoint`]) split over two of rayon's
/// threads: waking a parked thread costs a few microseconds, this work
/// about fifteen (at 8–10 GMAC/s on one core; measured on an AMD EPYC with
/// AVX-512, 20 → 20 over 256 samples took as long on two threads as on one,
/// and 20 → 96 over 512 took 0.6 of its one-thread time).
pub const DENSE_PAR_MIN_WORK: usize = 1 << 17;

/// Whether a dense layer's batch pass splits over two threads.
fn split_pays(batch: usize, n_in: usize, n_out: usize) -> bool {
    batch >= 2 && batch.saturating_mul(n_in).saturating_mul(n_out) >= DENSE_PAR_MIN_WORK && rayon::current_num_threads() > 1
}

/// Samples a dense kernel takes side by side, one to a vector lane: the
/// layers of small networks (20 wide, 4 in) leave vectors over a row's
/// values mostly empty, vectors over samples are always full.
const DENSE_BLOCK: usize = 8;

/// Copies `m` rows of `width` values from `rows` (`rows[l·width + i]`) into
/// lane `l` of `lanes` (`lanes[i·DENSE_BLOCK + l]`).
#[inline(always)]
fn to_lanes<R: Real>(width: usize, m: usize, rows: &[R], lanes: &mut [R]) {
    for l in 0..m {
        for (i, &v) in rows[l * width..(l + 1) * width].iter().enumerate() {
            lanes[i * DENSE_BLOCK + l] = v;
        }
    }
}

/// The inverse of [`to_lanes`] for the first `m` lanes.
#[inline(always)]
fn from_lanes<R: Real>(width: usize, m: usize, lanes: &[R], rows: &mut [R]) {
    for l in 0..m {
        for (i, v) in rows[l * width..(l + 1) * width].iter_mut().enumerate() {
            *v = lanes[i * DENSE_BLOCK + l];
        }
    }
}

/// The `DENSE_BLOCK` values of `v` from `at` as an array (a copy in
/// registers: the compiler then need not fear that stores alias them).
#[inline(always)]
fn lanes<R: Real>(v: &[R], at: usize) -> [R; DENSE_BLOCK] {
    let mut out = [R::zero(); DENSE_BLOCK];
    out.copy_from_slice(&v[at..at + DENSE_BLOCK]);
    out
}

/// [`dense_batch`]'s loop, compiled once per vector width ([`Real`]'s hook):
/// [`DENSE_BLOCK`] samples at a time, one to a lane, each output summed in
/// the order of [`dense`]'s `dot` (four partial sums over the quadruples of
/// inputs, added pairwise, then the remaining inputs one by one), so that
/// every lane computes its sample's row bit for bit as [`dense`] does.
#[inline(always)]
fn dense_batch_body<R: Real>(n_in: usize, w: &[R], b: &[R], xs: &[R], ys: &mut [R]) {
    const L: usize = DENSE_BLOCK;
    let n_out = b.len();
    if n_out == 0 {
        return;
    }
    let batch = ys.len() / n_out;
    let quads = n_in / 4 * 4;
    let mut xt = vec![R::zero(); n_in * L];
    let mut first = 0;
    while first < batch {
        let m = (batch - first).min(L);
        to_lanes(n_in, m, &xs[first * n_in..(first + m) * n_in], &mut xt);
        for (o, &bo) in b.iter().enumerate() {
            let row = &w[o * n_in..(o + 1) * n_in];
            let (mut s0, mut s1, mut s2, mut s3) = ([R::zero(); L], [R::zero(); L], [R::zero(); L], [R::zero(); L]);
            for k in (0..quads).step_by(4) {
                let (w0, w1, w2, w3) = (row[k], row[k + 1], row[k + 2], row[k + 3]);
                let (x0, x1, x2, x3) = (lanes(&xt, k * L), lanes(&xt, (k + 1) * L), lanes(&xt, (k + 2) * L), lanes(&xt, (k + 3) * L));
                for l in 0..L {
                    s0[l] += w0 * x0[l];
                    s1[l] += w1 * x1[l];
                    s2[l] += w2 * x2[l];
                    s3[l] += w3 * x3[l];
                }
            }
            let mut t = [R::zero(); L];
            for l in 0..L {
                t[l] = (s0[l] + s1[l]) + (s2[l] + s3[l]);
            }
            for (i, &wi) in row.iter().enumerate().skip(quads) {
                let x = lanes(&xt, i * L);
                for l in 0..L {
                    t[l] += wi * x[l];
                }
            }
            for l in 0..m {
                ys[(first + l) * n_out + o] = bo + t[l];
            }
        }
        first += m;
    }
}

/// Adjoint of [`dense_batch`]: `gxs_s += Wᵀ·gy_s` for every sample, and
/// the parameters' gradients summed over the batch, `gw += Σ_s gy_s·x_sᵀ`,
/// `gb += Σ_s gy_s`. The sums run in sample order (each element added to
/// in the order of the samples), so they equal, bit for bit, the
/// per-sample gradients of [`dense_adjoint`] added one after another, for
/// any batch size, and no per-sample gradient is formed.
pub fn dense_batch_adjoint<R: Real>(n_in: usize, w: &[R], xs: &[R], gys: &[R], gxs: &mut [R], gw: &mut [R], gb: &mut [R]) {
    let n_out = gb.len();
    let batch = gys.len() / n_out.max(1);
    assert!(xs.len() == batch * n_in && gxs.len() == batch * n_in && gw.len() == n_out * n_in, "dense_batch_adjoint: sizes do not match");
    if !split_pays(batch, n_in, n_out) || n_out < 2 {
        R::dense_batch_adjoint_kernel(n_in, w, xs, gys, gxs, gw, gb);
        return;
    }
    // Two threads, each with half the samples' input gradients and half the
    // weight rows' gradients: every element is added to in the same order,
    // so the result is the same bit for bit.
    let (mid, half) = (batch / 2, n_out / 2);
    let (gxa, gxb) = gxs.split_at_mut(mid * n_in);
    let ((gwa, gwb), (gba, gbb)) = (gw.split_at_mut(half * n_in), gb.split_at_mut(half));
    rayon::join(
        || {
            R::dense_input_gradient_kernel(n_in, w, &gys[..mid * n_out], gxa);
            R::dense_weight_gradient_kernel(n_in, n_out, 0, xs, gys, gwa, gba);
        },
        || {
            R::dense_input_gradient_kernel(n_in, w, &gys[mid * n_out..], gxb);
            R::dense_weight_gradient_kernel(n_in, n_out, half, xs, gys, gwb, gbb);
        },
    );
}

/// `gxs_s += Wᵀ·gy_s` for the samples of `gys` (`n_out = w.len() / n_in`
/// values each): [`DENSE_BLOCK`] samples at a time, one to a lane, each
/// input's gradient added to over the outputs in order, as
/// [`dense_adjoint`] adds to it.
#[inline(always)]
fn dense_input_gradient_body<R: Real>(n_in: usize, w: &[R], gys: &[R], gxs: &mut [R]) {
    const L: usize = DENSE_BLOCK;
    let n_out = w.len() / n_in.max(1);
    if n_in == 0 || n_out == 0 {
        return;
    }
    let batch = gys.len() / n_out;
    let (mut gxt, mut gyt) = (vec![R::zero(); n_in * L], vec![R::zero(); n_out * L]);
    let mut first = 0;
    while first < batch {
        let m = (batch - first).min(L);
        to_lanes(n_in, m, &gxs[first * n_in..(first + m) * n_in], &mut gxt);
        to_lanes(n_out, m, &gys[first * n_out..(first + m) * n_out], &mut gyt);
        // Four inputs at a time (four independent sums), then the rest one
        // by one.
        let quads = n_in / 4 * 4;
        for i in (0..quads).step_by(4) {
            input_gradient_lanes::<R, 4>(n_in, n_out, i, w, &gyt, &mut gxt);
        }
        for i in quads..n_in {
            input_gradient_lanes::<R, 1>(n_in, n_out, i, w, &gyt, &mut gxt);
        }
        from_lanes(n_in, m, &gxt, &mut gxs[first * n_in..(first + m) * n_in]);
        first += m;
    }
}

/// Inputs `i..i + Q` of a block's input gradients (`gxt`, in lanes), their
/// lanes held in registers while the outputs pass in order.
#[inline(always)]
fn input_gradient_lanes<R: Real, const Q: usize>(n_in: usize, n_out: usize, i: usize, w: &[R], gyt: &[R], gxt: &mut [R]) {
    const L: usize = DENSE_BLOCK;
    let mut gx: [[R; L]; Q] = std::array::from_fn(|q| lanes(gxt, (i + q) * L));
    for o in 0..n_out {
        let (g, row) = (lanes(gyt, o * L), &w[o * n_in + i..o * n_in + i + Q]);
        for (q, gx) in gx.iter_mut().enumerate() {
            for l in 0..L {
                gx[l] += g[l] * row[q];
            }
        }
    }
    for (q, gx) in gx.iter().enumerate() {
        gxt[(i + q) * L..(i + q + 1) * L].copy_from_slice(gx);
    }
}

/// `gw_o += Σ_s gy_s[o]·x_s` and `gb_o += Σ_s gy_s[o]` for the rows `first..`
/// that `gw` (`n_in` values a row) and `gb` hold, the samples taken in
/// order: a row's gradient held in whole vectors (the inputs copied once
/// into rows padded to [`DENSE_BLOCK`] values) while the samples pass.
#[inline(always)]
fn dense_weight_gradient_body<R: Real>(n_in: usize, n_out: usize, first: usize, xs: &[R], gys: &[R], gw: &mut [R], gb: &mut [R]) {
    const L: usize = DENSE_BLOCK;
    for (k, gbo) in gb.iter_mut().enumerate() {
        for gy in gys.chunks_exact(n_out.max(1)) {
            *gbo += gy[first + k];
        }
    }
    if n_in == 0 || n_out == 0 {
        return;
    }
    let width = n_in.div_ceil(L) * L;
    let mut xp = vec![R::zero(); gys.len() / n_out * width];
    for (x, p) in xs.chunks_exact(n_in).zip(xp.chunks_exact_mut(width)) {
        p[..n_in].copy_from_slice(x);
    }
    // Four rows at a time (four independent sums sharing each sample's
    // inputs), then the rest of the rows one by one.
    let rows = gw.len() / n_in;
    let quads = rows / 4 * 4;
    for k in (0..quads).step_by(4) {
        weight_gradient_rows::<R, 4>(n_in, n_out, first, k, &xp, gys, gw);
    }
    for k in quads..rows {
        weight_gradient_rows::<R, 1>(n_in, n_out, first, k, &xp, gys, gw);
    }
}

/// Rows `k..k + Q` of `gw` (the layer's rows `first + k..`): `L` values of
/// each held in registers while the samples pass in order (`xp`: the
/// inputs in rows padded to whole vectors).
#[inline(always)]
fn weight_gradient_rows<R: Real, const Q: usize>(n_in: usize, n_out: usize, first: usize, k: usize, xp: &[R], gys: &[R], gw: &mut [R]) {
    const L: usize = DENSE_BLOCK;
    let (o, width) = (first + k, n_in.div_ceil(L) * L);
    for c in (0..width).step_by(L) {
        let valid = (n_in - c).min(L);
        let mut acc = [[R::zero(); L]; Q];
        for (q, acc) in acc.iter_mut().enumerate() {
            acc[..valid].copy_from_slice(&gw[(k + q) * n_in + c..(k + q) * n_in + c + valid]);
        }
        for (s, gy) in gys.chunks_exact(n_out).enumerate() {
            let (g, x) = (&gy[o..o + Q], lanes(xp, s * width + c));
            for (q, acc) in acc.iter_mut().enumerate() {
                for l in 0..L {
                    acc[l] += g[q] * x[l];
                }
            }
        }
        for (q, acc) in acc.iter().enumerate() {
            gw[(k + q) * n_in + c..(k + q) * n_in + c + valid].copy_from_slice(&acc[..valid]);
        }
    }
}

/// [`dense_batch_adjoint`]'s loops, compiled once per vector width
/// ([`Real`]'s hook): the input gradients, then the weights' (the two
/// touch different values, so the order between them changes nothing).
#[inline(always)]
fn dense_batch_adjoint_body<R: Real>(n_in: usize, w: &[R], xs: &[R], gys: &[R], gxs: &mut [R], gw: &mut [R], gb: &mut [R]) {
    dense_input_gradient_body(n_in, w, gys, gxs);
    dense_weight_gradient_body(n_in, gb.len(), 0, xs, gys, gw, gb);
}

#[inline(always)]
fn dot<R: Real>(a: &[R], b: &[R]) -> R {
    // Four partial sums: vectorises and shortens the dependency chain.
    // (Four scalars, not an array: Enzyme cannot type the memset that
    // zeroes a generic array.)
    let z = R::zero();
    let (mut s0, mut s1, mut s2, mut s3) = (z, z, z, z);
    let (ca, cb) = (a.chunks_exact(4), b.chunks_exact(4));
    let (ra, rb) = (ca.remainder(), cb.remainder());
    for (x, y) in ca.zip(cb) {
        s0 += x[0] * y[0];
        s1 += x[1] * y[1];
        s2 += x[2] * y[2];
        s3 += x[3] * y[3];
    }
    let mut t = (s0 + s1) + (s2 + s3);
    for (x, y) in ra.iter().zip(rb) {
        t += *x * *y;
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
        tap_source(i, t, self.k, self.len, self.padding)
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

    /// Tap `t` along one row (`x`, `y` of `len` values): `y[i] += w·x[src(i, t)]`
    /// for every `i` with a source; the interior as a shifted axpy that
    /// vectorises, the edges apart.
    #[inline(always)]
    fn tap<R: Real>(&self, t: usize, w: R, x: &[R], y: &mut [R]) {
        let (lo, hi, off) = self.interior(t);
        if hi > lo {
            let src = &x[(lo as isize + off) as usize..(hi as isize + off) as usize];
            for (yi, xi) in y[lo..hi].iter_mut().zip(src) {
                *yi += w * *xi;
            }
        }
        for i in (0..lo).chain(hi..self.len) {
            if let Some(j) = self.src(i, t) {
                y[i] += w * x[j];
            }
        }
    }

    /// Adjoint of [`Self::tap`] for the seed `g`: `gx[src(i, t)] += w·g[i]`,
    /// and returns `Σ_i g[i]·x[src(i, t)]`, the gradient of the tap's weight.
    #[inline(always)]
    fn tap_adjoint<R: Real>(&self, t: usize, w: R, x: &[R], g: &[R], gx: &mut [R]) -> R {
        let (lo, hi, off) = self.interior(t);
        let mut acc = R::zero();
        if hi > lo {
            let range = (lo as isize + off) as usize..(hi as isize + off) as usize;
            acc = dot(&g[lo..hi], &x[range.clone()]);
            for (gxi, gi) in gx[range].iter_mut().zip(&g[lo..hi]) {
                *gxi += w * *gi;
            }
        }
        for i in (0..lo).chain(hi..self.len) {
            if let Some(j) = self.src(i, t) {
                acc += g[i] * x[j];
                gx[j] += w * g[i];
            }
        }
        acc
    }
}

/// `y[o][i] = b[o] + Σ_c Σ_t w[o][c][t]·x[c][i + t − k/2]` (overwrites `y`).
///
/// The input is padded once (wrapped or zeros), then each block of four
/// output channels × 32 positions is summed in vector registers over `c`
/// and `t` (with the widest vector instructions the CPU has); the sums run
/// in the order of [`conv1d_simple`], so the results are the same.
pub fn conv1d<R: Real>(s: &Conv1d, w: &[R], b: &[R], x: &[R], y: &mut [R]) {
    assert!(w.len() >= s.n_weights() && b.len() >= s.c_out && x.len() >= s.c_in * s.len && y.len() >= s.c_out * s.len, "conv1d: lengths");
    let xp = pad(s, s.c_in, x);
    let taps = Taps { base: 0, q: (s.c_in * s.k) as isize, r: s.k as isize, t: 1, inp: s.len + s.k - 1, out: s.len };
    R::correlate(s.len, s.k, s.c_out, s.c_in, w, taps, Some(b), &xp, y, false);
}

/// Adjoint of [`conv1d`]: `gx += ∂/∂x`, `gw += ∂/∂w`, `gb += ∂/∂b` of
/// `⟨gy, y⟩`. The input gradient is a correlation of the padded `gy` with
/// the flipped, transposed kernel (the forward kernel again); the weight
/// gradient is a dot product per weight over the positions.
pub fn conv1d_adjoint<R: Real>(s: &Conv1d, w: &[R], x: &[R], gy: &[R], gx: &mut [R], gw: &mut [R], gb: &mut [R]) {
    let (n, k) = (s.len, s.k);
    assert!(w.len() >= s.n_weights() && gw.len() >= s.n_weights() && gb.len() >= s.c_out, "conv1d_adjoint: lengths");
    assert!(x.len() >= s.c_in * n && gx.len() >= s.c_in * n && gy.len() >= s.c_out * n, "conv1d_adjoint: lengths");
    for o in 0..s.c_out {
        gb[o] += gy[o * n..(o + 1) * n].iter().copied().sum::<R>();
    }
    // gx[c][m] += Σ_o Σ_t w[o][c][k−1−t]·gyp[o][m + t].
    let gyp = pad(s, s.c_out, gy);
    let taps = Taps { base: (k - 1) as isize, q: k as isize, r: (s.c_in * k) as isize, t: -1, inp: n + k - 1, out: n };
    R::correlate(n, k, s.c_in, s.c_out, w, taps, None, &gyp, gx, true);
    // gw[o][c][t] += Σ_i gy[o][i]·xp[c][i + t].
    let xp = pad(s, s.c_in, x);
    let wg = WeightGrad { n, k, c_in: s.c_in, c_out: s.c_out, gy: n, xp: n + k - 1, gw_o: s.c_in * k, gw_c: k, gw_base: 0 };
    R::weight_gradient(&wg, gy, &xp, gw);
}

/// Where weight `(q, r, t)` of a correlation sits (`base + q·q + r·r +
/// t·t`) and how far apart the rows of its input (`inp`, per `r`) and output
/// (`out`, per `q`) are (an argument of [`Real`]'s kernel hooks; not for use
/// outside).
#[doc(hidden)]
#[derive(Clone, Copy, Debug)]
pub struct Taps {
    base: isize,
    q: isize,
    r: isize,
    t: isize,
    inp: usize,
    out: usize,
}

/// The shape of a weight gradient `gw[o][c][t] += Σ_i gy[o][i]·xp[c][i + t]`
/// for `i < n`, `t < k`: rows of `gy` `gy` apart, of `xp` `xp` apart, and
/// weight `(o, c, t)` at `gw_base + o·gw_o + c·gw_c + t` (an argument of
/// [`Real`]'s kernel hooks; not for use outside).
#[doc(hidden)]
#[derive(Clone, Copy, Debug)]
pub struct WeightGrad {
    n: usize,
    k: usize,
    c_in: usize,
    c_out: usize,
    gy: usize,
    xp: usize,
    gw_o: usize,
    gw_c: usize,
    gw_base: usize,
}

impl WeightGrad {
    #[inline(always)]
    fn at(&self, o: usize, c: usize, t: usize) -> usize {
        self.gw_base + o * self.gw_o + c * self.gw_c + t
    }
}

impl Taps {
    #[inline(always)]
    fn at(&self, q: usize, r: usize, t: usize) -> usize {
        (self.base + q as isize * self.q + r as isize * self.r + t as isize * self.t) as usize
    }

    /// Panics unless every weight `(q, r, t)` with `q < nq`, `r < nr`,
    /// `t < k` lies inside `w` (the tiles then read without checks).
    fn check(&self, nq: usize, nr: usize, k: usize, len: usize) {
        if nq == 0 || nr == 0 || k == 0 {
            return;
        }
        let corner = |q: usize, r: usize, t: usize| self.base + q as isize * self.q + r as isize * self.r + t as isize * self.t;
        let (mut lo, mut hi) = (isize::MAX, isize::MIN);
        for q in [0, nq - 1] {
            for r in [0, nr - 1] {
                for t in [0, k - 1] {
                    lo = lo.min(corner(q, r, t));
                    hi = hi.max(corner(q, r, t));
                }
            }
        }
        assert!(lo >= 0 && (hi as usize) < len, "correlate: weights out of range");
    }
}

/// The `c` channels of `x` (`len` each) padded by `k/2` on both sides,
/// wrapped or with zeros: rows of `len + k − 1`.
fn pad<R: Real>(s: &Conv1d, c: usize, x: &[R]) -> Vec<R> {
    let (n, h) = (s.len, s.k / 2);
    let np = n + s.k - 1;
    let mut xp = vec![R::zero(); c * np];
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

/// The kernels [`Real`] dispatches to, compiled here once per type (with
/// run-time choice of the vector instructions).
macro_rules! kernels_for {
    ($t:ty, $correlate:ident, $weight_gradient:ident, $tanh:ident, $dense:ident, $dense_adjoint:ident, $dense_gx:ident, $dense_gw:ident) => {
        crate::simd_dispatch! {
            #[allow(clippy::too_many_arguments)]
            pub(crate) fn $correlate(n: usize, k: usize, nq: usize, nr: usize, w: &[$t], taps: Taps, bias: Option<&[$t]>, inp: &[$t], out: &mut [$t], add: bool) => correlate_body::<$t>
        }
        crate::simd_dispatch! {
            pub(crate) fn $weight_gradient(s: &WeightGrad, gy: &[$t], xp: &[$t], gw: &mut [$t]) => weight_gradient_body::<$t>
        }
        crate::simd_dispatch! {
            pub(crate) fn $tanh(x: &[$t], y: &mut [$t]) => tanh_slice_body::<$t>
        }
        crate::simd_dispatch! {
            pub(crate) fn $dense(n_in: usize, w: &[$t], b: &[$t], xs: &[$t], ys: &mut [$t]) => dense_batch_body::<$t>
        }
        crate::simd_dispatch! {
            pub(crate) fn $dense_gx(n_in: usize, w: &[$t], gys: &[$t], gxs: &mut [$t]) => dense_input_gradient_body::<$t>
        }
        crate::simd_dispatch! {
            #[allow(clippy::too_many_arguments)]
            pub(crate) fn $dense_gw(n_in: usize, n_out: usize, first: usize, xs: &[$t], gys: &[$t], gw: &mut [$t], gb: &mut [$t]) => dense_weight_gradient_body::<$t>
        }
        crate::simd_dispatch! {
            #[allow(clippy::too_many_arguments)]
            pub(crate) fn $dense_adjoint(n_in: usize, w: &[$t], xs: &[$t], gys: &[$t], gxs: &mut [$t], gw: &mut [$t], gb: &mut [$t]) => dense_batch_adjoint_body::<$t>
        }
    };
}
kernels_for!(f64, correlate_f64, weight_gradient_f64, tanh_slice_f64, dense_batch_f64, dense_batch_adjoint_f64, dense_gx_f64, dense_gw_f64);
kernels_for!(f32, correlate_f32, weight_gradient_f32, tanh_slice_f32, dense_batch_f32, dense_batch_adjoint_f32, dense_gx_f32, dense_gw_f32);

/// `out[q][i] (= or +=) bias[q] + Σ_r Σ_t W(q, r, t)·inp[r][i + t]` for
/// `q < nq`, `r < nr`, `t < k`, `i < n`, with input rows `taps.inp` and
/// output rows `taps.out` apart.
#[inline(always)]
#[allow(clippy::too_many_arguments)]
fn correlate_body<R: Real>(n: usize, k: usize, nq: usize, nr: usize, w: &[R], taps: Taps, bias: Option<&[R]>, inp: &[R], out: &mut [R], add: bool) {
    // The kernel width as a constant for the common sizes, so that the
    // taps unroll and the accumulators stay in registers.
    taps.check(nq, nr, k, w.len());
    match k {
        3 => correlate_k::<R, 3>(n, nq, nr, w, taps, bias, inp, out, add),
        5 => correlate_k::<R, 5>(n, nq, nr, w, taps, bias, inp, out, add),
        7 => correlate_k::<R, 7>(n, nq, nr, w, taps, bias, inp, out, add),
        _ => correlate_scalar(n, k, 0..nq, 0, nr, w, taps, bias, inp, out, add),
    }
}

#[inline(always)]
#[allow(clippy::too_many_arguments)]
fn correlate_k<R: Real, const K: usize>(n: usize, nq: usize, nr: usize, w: &[R], taps: Taps, bias: Option<&[R]>, inp: &[R], out: &mut [R], add: bool) {
    let mut q0 = 0;
    // f32: eight rows × two vectors of sixteen (sixteen accumulators, one
    // register file's half); f64: four rows × four vectors of eight.
    while R::LANES == 16 && q0 + 8 <= nq {
        correlate_rows::<R, K, 8>(n, nr, w, taps, bias, inp, out, add, q0);
        q0 += 8;
    }
    while q0 + 4 <= nq {
        correlate_rows::<R, K, 4>(n, nr, w, taps, bias, inp, out, add, q0);
        q0 += 4;
    }
    while q0 < nq {
        correlate_rows::<R, K, 1>(n, nr, w, taps, bias, inp, out, add, q0);
        q0 += 1;
    }
}

/// Rows `q0..q0 + Q`: four vectors of positions at a time (32 `f64`, 64
/// `f32`; only for `Q ≤ 4`), then two, then one, then the tail one by one.
#[inline(always)]
#[allow(clippy::too_many_arguments)]
fn correlate_rows<R: Real, const K: usize, const Q: usize>(
    n: usize,
    nr: usize,
    w: &[R],
    taps: Taps,
    bias: Option<&[R]>,
    inp: &[R],
    out: &mut [R],
    add: bool,
    q0: usize,
) {
    let l = R::LANES;
    let mut i0 = 0;
    // At most sixteen accumulators: four vectors for up to four rows.
    while Q <= 4 && i0 + 4 * l <= n {
        correlate_tile::<R, K, Q, 4>(nr, w, taps, bias, inp, out, add, q0, i0);
        i0 += 4 * l;
    }
    while i0 + 2 * l <= n {
        correlate_tile::<R, K, Q, 2>(nr, w, taps, bias, inp, out, add, q0, i0);
        i0 += 2 * l;
    }
    if i0 + l <= n {
        correlate_tile::<R, K, Q, 1>(nr, w, taps, bias, inp, out, add, q0, i0);
        i0 += l;
    }
    correlate_scalar(n, K, q0..q0 + Q, i0, nr, w, taps, bias, inp, out, add);
}

/// `Q` rows × `P` vectors of positions from `(q0, i0)`, summed in registers
/// over `r` and `t` (in that order, as the plain loops). The loops over `P`
/// and `Q` have constant bounds and unroll, so the accumulators are plain
/// vector registers.
#[inline(always)]
#[allow(clippy::too_many_arguments)]
fn correlate_tile<R: Real, const K: usize, const Q: usize, const P: usize>(
    nr: usize,
    w: &[R],
    taps: Taps,
    bias: Option<&[R]>,
    inp: &[R],
    out: &mut [R],
    add: bool,
    q0: usize,
    i0: usize,
) {
    let (l, np, no) = (R::LANES, taps.inp, taps.out);
    let zero = R::splat(R::zero());
    let mut acc = [[zero; P]; Q];
    for (q, aq) in acc.iter_mut().enumerate() {
        let b = R::splat(bias.map_or(R::zero(), |b| b[q0 + q]));
        for (p, a) in aq.iter_mut().enumerate() {
            let at = (q0 + q) * no + i0 + l * p;
            let start = if add { R::load(&out[at..at + l]) } else { zero };
            *a = start + b;
        }
    }
    for r in 0..nr {
        let row = &inp[r * np + i0..r * np + i0 + l * P + K - 1];
        for t in 0..K {
            let xs: [R::V; P] = std::array::from_fn(|p| R::load(&row[t + l * p..t + l * (p + 1)]));
            for (q, aq) in acc.iter_mut().enumerate() {
                // SAFETY: `Taps::check` in `correlate_body` bounds every
                // (q, r, t) read here (q0 + q < nq, r < nr, t < K).
                let wq = R::splat(unsafe { *w.get_unchecked(taps.at(q0 + q, r, t)) });
                for (a, x) in aq.iter_mut().zip(&xs) {
                    *a += wq * *x;
                }
            }
        }
    }
    for (q, aq) in acc.iter().enumerate() {
        for (p, a) in aq.iter().enumerate() {
            let at = (q0 + q) * no + i0 + l * p;
            R::store(*a, &mut out[at..at + l]);
        }
    }
}

/// Rows `qs` of the correlation from position `i0` on, one value at a time.
#[inline(always)]
#[allow(clippy::too_many_arguments)]
fn correlate_scalar<R: Real>(
    n: usize,
    k: usize,
    qs: std::ops::Range<usize>,
    i0: usize,
    nr: usize,
    w: &[R],
    taps: Taps,
    bias: Option<&[R]>,
    inp: &[R],
    out: &mut [R],
    add: bool,
) {
    let (np, no) = (taps.inp, taps.out);
    for q in qs {
        for i in i0..n {
            let mut a = if add { out[q * no + i] } else { R::zero() } + bias.map_or(R::zero(), |b| b[q]);
            for r in 0..nr {
                for t in 0..k {
                    a += w[taps.at(q, r, t)] * inp[r * np + i + t];
                }
            }
            out[q * no + i] = a;
        }
    }
}

/// `gw[o][c][t] += Σ_i gy[o][i]·xp[c][i + t]` (shape and strides in `s`).
#[inline(always)]
fn weight_gradient_body<R: Real>(s: &WeightGrad, gy: &[R], xp: &[R], gw: &mut [R]) {
    match s.k {
        3 => weight_gradient_k::<R, 3>(s, gy, xp, gw),
        5 => weight_gradient_k::<R, 5>(s, gy, xp, gw),
        7 => weight_gradient_k::<R, 7>(s, gy, xp, gw),
        _ => weight_gradient_scalar(s, 0..s.c_out, gy, xp, gw),
    }
}

/// One vector of output channels at a time: `gy` transposed to `[i][o]`,
/// then per input channel all `K` taps of four (two, one) vectors of output
/// channels summed over the positions in registers, and added into `gw` at
/// the end.
#[inline(always)]
fn weight_gradient_k<R: Real, const K: usize>(s: &WeightGrad, gy: &[R], xp: &[R], gw: &mut [R]) {
    let (n, co, l) = (s.n, s.c_out, R::LANES);
    let full = co - co % l;
    let mut gyt = vec![R::zero(); n * full];
    for o in 0..full {
        for i in 0..n {
            gyt[i * full + o] = gy[o * s.gy + i];
        }
    }
    let mut o0 = 0;
    while o0 + 4 * l <= full {
        weight_gradient_tile::<R, K, 4>(s, &gyt, full, o0, xp, gw);
        o0 += 4 * l;
    }
    if o0 + 2 * l <= full {
        weight_gradient_tile::<R, K, 2>(s, &gyt, full, o0, xp, gw);
        o0 += 2 * l;
    }
    if o0 + l <= full {
        weight_gradient_tile::<R, K, 1>(s, &gyt, full, o0, xp, gw);
    }
    weight_gradient_scalar(s, full..co, gy, xp, gw);
}

#[inline(always)]
fn weight_gradient_tile<R: Real, const K: usize, const V: usize>(s: &WeightGrad, gyt: &[R], stride: usize, o0: usize, xp: &[R], gw: &mut [R]) {
    let (n, ci, l) = (s.n, s.c_in, R::LANES);
    let zero = R::splat(R::zero());
    let mut lanes = [R::zero(); 16];
    for c in 0..ci {
        let row = &xp[c * s.xp..c * s.xp + n + K - 1];
        let mut acc = [[zero; V]; K];
        for i in 0..n {
            let g = &gyt[i * stride + o0..i * stride + o0 + l * V];
            let gs: [R::V; V] = std::array::from_fn(|v| R::load(&g[l * v..l * (v + 1)]));
            for (t, at) in acc.iter_mut().enumerate() {
                let xv = R::splat(row[i + t]);
                for (a, g) in at.iter_mut().zip(&gs) {
                    *a += *g * xv;
                }
            }
        }
        for (t, at) in acc.iter().enumerate() {
            for (v, a) in at.iter().enumerate() {
                R::store(*a, &mut lanes[..l]);
                for (j, &val) in lanes[..l].iter().enumerate() {
                    gw[s.at(o0 + l * v + j, c, t)] += val;
                }
            }
        }
    }
}

/// Output channels `os` of the weight gradient, one weight at a time.
#[inline(always)]
fn weight_gradient_scalar<R: Real>(s: &WeightGrad, os: std::ops::Range<usize>, gy: &[R], xp: &[R], gw: &mut [R]) {
    let (n, k) = (s.n, s.k);
    for o in os {
        let g = &gy[o * s.gy..o * s.gy + n];
        for c in 0..s.c_in {
            let row = &xp[c * s.xp..c * s.xp + n + k - 1];
            for t in 0..k {
                gw[s.at(o, c, t)] += dot(g, &row[t..t + n]);
            }
        }
    }
}

/// [`conv1d`] as plain loops without run-time dispatch (what Enzyme
/// differentiates for the generated-versus-hand comparison; the same sums in
/// the same order, so the same results).
pub fn conv1d_simple<R: Real>(s: &Conv1d, w: &[R], b: &[R], x: &[R], y: &mut [R]) {
    let (n, k) = (s.len, s.k);
    for o in 0..s.c_out {
        let yo = &mut y[o * n..(o + 1) * n];
        yo.fill(b[o]);
        for c in 0..s.c_in {
            let xc = &x[c * n..(c + 1) * n];
            for t in 0..k {
                s.tap(t, w[(o * s.c_in + c) * k + t], xc, yo);
            }
        }
    }
}

/// [`conv1d_adjoint`] as plain loops (the reference for the blocked one).
pub fn conv1d_adjoint_simple<R: Real>(s: &Conv1d, w: &[R], x: &[R], gy: &[R], gx: &mut [R], gw: &mut [R], gb: &mut [R]) {
    let (n, k) = (s.len, s.k);
    for o in 0..s.c_out {
        let go = &gy[o * n..(o + 1) * n];
        gb[o] += go.iter().copied().sum::<R>();
        for c in 0..s.c_in {
            let xc = &x[c * n..(c + 1) * n];
            let gxc = &mut gx[c * n..(c + 1) * n];
            for t in 0..k {
                let wi = (o * s.c_in + c) * k + t;
                gw[wi] += s.tap_adjoint(t, w[wi], xc, go, gxc);
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
        tap_source(j, t, self.k, self.ny, self.padding)
    }
}

/// The input position that output `i` reads under tap `t` of a kernel of
/// width `k`, on a signal of `n` values.
#[inline(always)]
fn tap_source(i: usize, t: usize, k: usize, n: usize, padding: Padding) -> Option<usize> {
    wrap_index(i as isize + t as isize - (k / 2) as isize, n, padding)
}

/// `y[o][j][i] = b[o] + Σ_c Σ_{ty,tx} w[o][c][ty][tx]·x[c][j+ty−k/2][i+tx−k/2]`
/// (overwrites `y`).
///
/// The input is padded once to `(ny + k − 1) × (nx + k − 1)` per channel
/// and read as one long row (`ny` padded rows back to back): for each kernel
/// row `ty` the sum over channels and `tx` is then the 1D blocked
/// correlation of [`conv1d`] over `ny·(nx + k − 1)` positions shifted by
/// `ty` rows, whose outputs in the `k − 1` padding columns of each row are
/// computed and dropped. The sums run in another order than
/// [`conv2d_simple`] (equal to rounding, tested).
pub fn conv2d<R: Real>(s: &Conv2d, w: &[R], b: &[R], x: &[R], y: &mut [R]) {
    let (nx, ny, k) = (s.nx, s.ny, s.k);
    assert!(w.len() >= s.n_weights() && b.len() >= s.c_out && x.len() >= s.c_in * nx * ny && y.len() >= s.c_out * nx * ny, "conv2d: lengths");
    let g = Grid2::new(s);
    let xp = g.pad(s, s.c_in, x);
    let mut yp = vec![R::zero(); s.c_out * g.len];
    for ty in 0..k {
        let taps = Taps { base: (ty * k) as isize, q: (s.c_in * k * k) as isize, r: (k * k) as isize, t: 1, inp: g.stride, out: g.len };
        R::correlate(g.len, k, s.c_out, s.c_in, w, taps, (ty == 0).then_some(b), &xp[ty * g.npx..], &mut yp, ty > 0);
    }
    for o in 0..s.c_out {
        for j in 0..ny {
            y[(o * ny + j) * nx..(o * ny + j + 1) * nx].copy_from_slice(&yp[o * g.len + j * g.npx..o * g.len + j * g.npx + nx]);
        }
    }
}

/// Adjoint of [`conv2d`] (adds into `gx`, `gw`, `gb`): the input gradient
/// is the forward kernel on the padded `gy` with the flipped, transposed
/// weights, the weight gradient the 1D one over the long rows, both in the
/// layout of [`conv2d`].
pub fn conv2d_adjoint<R: Real>(s: &Conv2d, w: &[R], x: &[R], gy: &[R], gx: &mut [R], gw: &mut [R], gb: &mut [R]) {
    let (nx, ny, k) = (s.nx, s.ny, s.k);
    assert!(w.len() >= s.n_weights() && gw.len() >= s.n_weights() && gb.len() >= s.c_out, "conv2d_adjoint: lengths");
    assert!(x.len() >= s.c_in * nx * ny && gx.len() >= s.c_in * nx * ny && gy.len() >= s.c_out * nx * ny, "conv2d_adjoint: lengths");
    let g = Grid2::new(s);
    for o in 0..s.c_out {
        gb[o] += gy[o * nx * ny..(o + 1) * nx * ny].iter().copied().sum::<R>();
    }
    // gx[c][m] = Σ_o Σ_{ty,tx} w[o][c][k−1−ty][k−1−tx]·gyp[o][m + ty·npx + tx].
    let gyp = g.pad(s, s.c_out, gy);
    let mut gxp = vec![R::zero(); s.c_in * g.len];
    for ty in 0..k {
        let base = ((k - 1 - ty) * k + k - 1) as isize;
        let taps = Taps { base, q: (k * k) as isize, r: (s.c_in * k * k) as isize, t: -1, inp: g.stride, out: g.len };
        R::correlate(g.len, k, s.c_in, s.c_out, w, taps, None, &gyp[ty * g.npx..], &mut gxp, ty > 0);
    }
    for c in 0..s.c_in {
        for j in 0..ny {
            let src = &gxp[c * g.len + j * g.npx..c * g.len + j * g.npx + nx];
            for (a, &v) in gx[(c * ny + j) * nx..(c * ny + j + 1) * nx].iter_mut().zip(src) {
                *a += v;
            }
        }
    }
    // gw[o][c][ty][tx] = Σ_m gyz[o][m]·xp[c][m + ty·npx + tx], gyz = gy with
    // zeros in the padding columns (so that those positions add nothing).
    let mut gyz = vec![R::zero(); s.c_out * g.len];
    for o in 0..s.c_out {
        for j in 0..ny {
            gyz[o * g.len + j * g.npx..o * g.len + j * g.npx + nx].copy_from_slice(&gy[(o * ny + j) * nx..(o * ny + j + 1) * nx]);
        }
    }
    let xp = g.pad(s, s.c_in, x);
    for ty in 0..k {
        let wg = WeightGrad { n: g.len, k, c_in: s.c_in, c_out: s.c_out, gy: g.len, xp: g.stride, gw_o: s.c_in * k * k, gw_c: k * k, gw_base: ty * k };
        R::weight_gradient(&wg, &gyz, &xp[ty * g.npx..], gw);
    }
}

/// The padded layout of [`conv2d`]: rows of `npx = nx + k − 1`, `len =
/// ny·npx` output positions per channel (the padding columns included),
/// `stride` between padded channels (`(ny + k − 1)·npx` and `k` to spare,
/// so that the long rows shifted by `ty` rows and `tx` columns stay inside).
struct Grid2 {
    npx: usize,
    len: usize,
    stride: usize,
}

impl Grid2 {
    fn new(s: &Conv2d) -> Self {
        let npx = s.nx + s.k - 1;
        Self { npx, len: s.ny * npx, stride: (s.ny + s.k - 1) * npx + s.k }
    }

    /// `c` channels of `x` padded by `k/2` on every side (wrapped or zeros).
    fn pad<R: Real>(&self, s: &Conv2d, c: usize, x: &[R]) -> Vec<R> {
        let (nx, ny, h) = (s.nx, s.ny, (s.k / 2) as isize);
        let mut xp = vec![R::zero(); c * self.stride];
        for ch in 0..c {
            for py in 0..ny + s.k - 1 {
                let Some(j) = wrap_index(py as isize - h, ny, s.padding) else { continue };
                let dst = &mut xp[ch * self.stride + py * self.npx..ch * self.stride + (py + 1) * self.npx];
                let src = &x[(ch * ny + j) * nx..(ch * ny + j + 1) * nx];
                for (px, d) in dst.iter_mut().enumerate() {
                    if let Some(i) = wrap_index(px as isize - h, nx, s.padding) {
                        *d = src[i];
                    }
                }
            }
        }
        xp
    }
}

/// Index `i` of a signal of `n` values: wrapped, or `None` outside for zero
/// padding.
#[inline(always)]
fn wrap_index(i: isize, n: usize, padding: Padding) -> Option<usize> {
    match padding {
        Padding::Periodic => Some(i.rem_euclid(n as isize) as usize),
        Padding::Zero => (0..n as isize).contains(&i).then_some(i as usize),
    }
}

/// [`conv2d`] as plain loops (the reference for the blocked one).
pub fn conv2d_simple<R: Real>(s: &Conv2d, w: &[R], b: &[R], x: &[R], y: &mut [R]) {
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
                        row.tap(tx, w[((o * s.c_in + c) * k + ty) * k + tx], xrow, yrow);
                    }
                }
            }
        }
    }
}

/// [`conv2d_adjoint`] as plain loops (the reference for the blocked one).
pub fn conv2d_adjoint_simple<R: Real>(s: &Conv2d, w: &[R], x: &[R], gy: &[R], gx: &mut [R], gw: &mut [R], gb: &mut [R]) {
    let (nx, ny, k) = (s.nx, s.ny, s.k);
    let row = Conv1d { c_in: 1, c_out: 1, k, len: nx, padding: s.padding };
    for o in 0..s.c_out {
        gb[o] += gy[o * nx * ny..(o + 1) * nx * ny].iter().copied().sum::<R>();
        for c in 0..s.c_in {
            for j in 0..ny {
                for ty in 0..k {
                    let Some(js) = s.src_row(j, ty) else { continue };
                    let xrow = &x[(c * ny + js) * nx..(c * ny + js + 1) * nx];
                    let grow = &gy[(o * ny + j) * nx..(o * ny + j + 1) * nx];
                    let gxrow = &mut gx[(c * ny + js) * nx..(c * ny + js + 1) * nx];
                    for tx in 0..k {
                        let wi = ((o * s.c_in + c) * k + ty) * k + tx;
                        gw[wi] += row.tap_adjoint(tx, w[wi], xrow, grow, gxrow);
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
    /// `f(x)` (tanh by [`Real::tanh_fast`], as in [`activate`]).
    #[inline(always)]
    pub fn f<R: Real>(self, x: R) -> R {
        let (zero, one, c) = (R::zero(), R::one(), R::of);
        match self {
            Activation::Relu => x.max(zero),
            Activation::LeakyRelu => {
                if x > zero {
                    x
                } else {
                    c(0.01) * x
                }
            }
            Activation::Tanh => x.tanh_fast(),
            Activation::Sigmoid => one / (one + (-x).exp()),
            Activation::Gelu => c(0.5) * x * (one + (c(GELU_C) * (x + c(0.044715) * x * x * x)).tanh()),
            Activation::Swish => x / (one + (-x).exp()),
        }
    }

    /// `f′(x)`.
    #[inline(always)]
    pub fn df<R: Real>(self, x: R) -> R {
        let (zero, one, c) = (R::zero(), R::one(), R::of);
        match self {
            Activation::Relu => {
                if x > zero {
                    one
                } else {
                    zero
                }
            }
            Activation::LeakyRelu => {
                if x > zero {
                    one
                } else {
                    c(0.01)
                }
            }
            Activation::Tanh => {
                let t = x.tanh_fast();
                one - t * t
            }
            Activation::Sigmoid => {
                let s = one / (one + (-x).exp());
                s * (one - s)
            }
            Activation::Gelu => {
                let u = c(GELU_C) * (x + c(0.044715) * x * x * x);
                let t = u.tanh();
                c(0.5) * (one + t) + c(0.5) * x * (one - t * t) * c(GELU_C) * (one + c(3.0 * 0.044715) * x * x)
            }
            Activation::Swish => {
                let s = one / (one + (-x).exp());
                s + x * s * (one - s)
            }
        }
    }

    /// `f′` from the output `y = f(x)` where that is cheaper than from `x`
    /// (tanh: `1 − y²`; sigmoid: `y·(1 − y)`), else `None`.
    #[inline(always)]
    pub fn df_from_output<R: Real>(self, y: R) -> Option<R> {
        match self {
            Activation::Tanh => Some(R::one() - y * y),
            Activation::Sigmoid => Some(y * (R::one() - y)),
            _ => None,
        }
    }

    /// Whether `f` has a kink at 0 (for the gradient checks' smoothness radius).
    pub fn kinked(self) -> bool {
        matches!(self, Activation::Relu | Activation::LeakyRelu)
    }
}

/// Average pooling by 2 along positions, per channel: `c × len → c × len/2`.
pub fn avg_pool1d<R: Real>(c: usize, len: usize, x: &[R], y: &mut [R]) {
    let h = len / 2;
    for ch in 0..c {
        for i in 0..h {
            y[ch * h + i] = R::of(0.5) * (x[ch * len + 2 * i] + x[ch * len + 2 * i + 1]);
        }
    }
}

/// Adjoint of [`avg_pool1d`] (adds into `gx`).
pub fn avg_pool1d_adjoint<R: Real>(c: usize, len: usize, gy: &[R], gx: &mut [R]) {
    let h = len / 2;
    for ch in 0..c {
        for i in 0..h {
            let g = R::of(0.5) * gy[ch * h + i];
            gx[ch * len + 2 * i] += g;
            gx[ch * len + 2 * i + 1] += g;
        }
    }
}

/// Nearest-neighbour upsampling by 2: `c × len → c × 2·len`.
pub fn upsample1d<R: Real>(c: usize, len: usize, x: &[R], y: &mut [R]) {
    for ch in 0..c {
        for i in 0..len {
            let v = x[ch * len + i];
            y[ch * 2 * len + 2 * i] = v;
            y[ch * 2 * len + 2 * i + 1] = v;
        }
    }
}

/// Adjoint of [`upsample1d`] (adds into `gx`).
pub fn upsample1d_adjoint<R: Real>(c: usize, len: usize, gy: &[R], gx: &mut [R]) {
    for ch in 0..c {
        for i in 0..len {
            gx[ch * len + i] += gy[ch * 2 * len + 2 * i] + gy[ch * 2 * len + 2 * i + 1];
        }
    }
}

/// Average pooling by 2×2: `c × ny × nx → c × ny/2 × nx/2`.
pub fn avg_pool2d<R: Real>(c: usize, nx: usize, ny: usize, x: &[R], y: &mut [R]) {
    let (hx, hy) = (nx / 2, ny / 2);
    for ch in 0..c {
        for j in 0..hy {
            for i in 0..hx {
                let at = |dj: usize, di: usize| x[(ch * ny + 2 * j + dj) * nx + 2 * i + di];
                y[(ch * hy + j) * hx + i] = R::of(0.25) * (at(0, 0) + at(0, 1) + at(1, 0) + at(1, 1));
            }
        }
    }
}

/// Adjoint of [`avg_pool2d`] (adds into `gx`).
pub fn avg_pool2d_adjoint<R: Real>(c: usize, nx: usize, ny: usize, gy: &[R], gx: &mut [R]) {
    let (hx, hy) = (nx / 2, ny / 2);
    for ch in 0..c {
        for j in 0..hy {
            for i in 0..hx {
                let g = R::of(0.25) * gy[(ch * hy + j) * hx + i];
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
pub fn upsample2d<R: Real>(c: usize, nx: usize, ny: usize, x: &[R], y: &mut [R]) {
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
pub fn upsample2d_adjoint<R: Real>(c: usize, nx: usize, ny: usize, gy: &[R], gx: &mut [R]) {
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
pub fn activate<R: Real>(f: Activation, x: &[R], y: &mut [R]) {
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
pub fn activate_adjoint<R: Real>(f: Activation, x: &[R], gy: &[R], gx: &mut [R]) {
    match f {
        Activation::Tanh => {
            let mut t = vec![R::zero(); x.len()];
            tanh_slice(x, &mut t);
            activate_adjoint_from_output(f, &t, gy, gx);
        }
        _ => {
            for ((gx, &g), &x) in gx.iter_mut().zip(gy).zip(x) {
                *gx += g * f.df(x);
            }
        }
    }
}

/// [`activate_adjoint`] from the forward's output `y = f(x)` instead of
/// `x`, for the activations whose derivative is a function of the output
/// ([`Activation::df_from_output`]; panics for the others).
pub fn activate_adjoint_from_output<R: Real>(f: Activation, y: &[R], gy: &[R], gx: &mut [R]) {
    assert!(f.df_from_output(R::zero()).is_some(), "activate_adjoint_from_output: {f:?} needs its input");
    for ((gx, &g), &y) in gx.iter_mut().zip(gy).zip(y) {
        *gx += g * f.df_from_output(y).unwrap_or(R::zero());
    }
}

/// `y[i] = tanh(x[i])` in vector instructions ([`Real::tanh_fast`]: `f64`
/// to a relative error below 1.5e-15, `f32` within a few units in the last
/// place, both tested against the library tanh; a NaN stays NaN). The libm
/// call it replaces dominated small networks.
pub fn tanh_slice<R: Real>(x: &[R], y: &mut [R]) {
    R::tanh_slice(x, y)
}

#[inline(always)]
fn tanh_slice_body<R: Real>(x: &[R], y: &mut [R]) {
    for (y, &x) in y.iter_mut().zip(x) {
        *y = x.tanh_fast();
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn values(n: usize, seed: u64) -> Vec<f64> {
        (0..n).map(|i| ((i as f64 + 1.0) * 0.618 + seed as f64 * 0.37).sin()).collect()
    }

    /// `dense` against `W·x + b` written out; its adjoint against the
    /// transposed products written out.
    #[test]
    fn dense_and_its_adjoint_follow_their_formulas() {
        let (n_in, n_out) = (3, 2);
        let (w, b, x, gy) = (values(6, 1), values(2, 2), values(3, 3), values(2, 4));
        let mut y = vec![0.0; 2];
        dense(n_in, &w, &b, &x, &mut y);
        for o in 0..n_out {
            let direct = b[o] + w[o * 3] * x[0] + w[o * 3 + 1] * x[1] + w[o * 3 + 2] * x[2];
            assert!((y[o] - direct).abs() < 1e-15);
        }
        let (mut gx, mut gw, mut gb) = (vec![1.0; 3], vec![0.0; 6], vec![0.0; 2]);
        dense_adjoint(n_in, &w, &x, &gy, &mut gx, &mut gw, &mut gb);
        for i in 0..n_in {
            assert!((gx[i] - (1.0 + w[i] * gy[0] + w[3 + i] * gy[1])).abs() < 1e-15, "gx[{i}] adds to what was there");
            for o in 0..n_out {
                assert_eq!(gw[o * 3 + i], gy[o] * x[i]);
            }
        }
        assert_eq!(gb, gy);
    }

    /// The batched dense layer: rows as `dense`'s, and its adjoint's sums
    /// equal to the per-sample adjoints added in sample order, bit for bit,
    /// across block boundaries (batch sizes around [`DENSE_BLOCK`]), for
    /// rows shorter than, not a multiple of and longer than a vector, and
    /// adding to gradients that were not zero.
    #[test]
    fn batched_dense_equals_per_sample_passes() {
        batched_dense_case(5, 7);
        batched_dense_case(3, 2);
        batched_dense_case(20, 24);
        batched_dense_case(16, 1);
    }

    fn batched_dense_case(n_in: usize, n_out: usize) {
        // The last two split over two threads (at least DENSE_PAR_MIN_WORK
        // multiply-adds), in a pool of two whatever the machine.
        let pool = rayon::ThreadPoolBuilder::new().num_threads(2).build().unwrap();
        let big = DENSE_PAR_MIN_WORK / (n_in * n_out) + 1;
        for batch in [1, 3, DENSE_BLOCK, DENSE_BLOCK + 1, 3 * DENSE_BLOCK + 2, big, big + 1] {
            assert_eq!(pool.install(|| split_pays(batch, n_in, n_out)), batch >= big);
            let (w, b) = (values(n_in * n_out, 1), values(n_out, 2));
            let (xs, gys) = (values(batch * n_in, 3), values(batch * n_out, 4));
            let mut ys = vec![0.0; batch * n_out];
            pool.install(|| dense_batch(n_in, &w, &b, &xs, &mut ys));
            let (mut gxs, mut gw, mut gb) = (values(batch * n_in, 5), values(n_in * n_out, 6), values(n_out, 7));
            let (gxs0, mut sw, mut sb) = (gxs.clone(), gw.clone(), gb.clone());
            pool.install(|| dense_batch_adjoint(n_in, &w, &xs, &gys, &mut gxs, &mut gw, &mut gb));
            for s in 0..batch {
                let (x, gy) = (&xs[s * n_in..(s + 1) * n_in], &gys[s * n_out..(s + 1) * n_out]);
                let mut y = vec![0.0; n_out];
                dense(n_in, &w, &b, x, &mut y);
                assert_eq!(&ys[s * n_out..(s + 1) * n_out], &y[..], "{n_in} -> {n_out}, batch {batch}");
                let mut gx = gxs0[s * n_in..(s + 1) * n_in].to_vec();
                let (mut gws, mut gbs) = (vec![0.0; n_in * n_out], vec![0.0; n_out]);
                dense_adjoint(n_in, &w, x, gy, &mut gx, &mut gws, &mut gbs);
                assert_eq!(&gxs[s * n_in..(s + 1) * n_in], &gx[..], "{n_in} -> {n_out}, batch {batch}");
                sw.iter_mut().zip(&gws).for_each(|(a, b)| *a += b);
                sb.iter_mut().zip(&gbs).for_each(|(a, b)| *a += b);
            }
            assert_eq!(gw, sw, "{n_in} -> {n_out}, batch {batch}");
            assert_eq!(gb, sb, "{n_in} -> {n_out}, batch {batch}");
        }
    }
}
