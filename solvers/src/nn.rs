//! Neural-network kernels on slices: dense layers, 1D and 2D convolutions
//! (zero or periodic padding), pooling, upsampling and activations, each
//! with its hand-written adjoint. Plain functions; the framework wraps them
//! as operators.
//!
//! Layouts: weights row-major `[out][in]` (dense) and `[c_out][c_in][k]`
//! (1D) / `[c_out][c_in][k][k]` (2D, rows = y); feature maps channel-major,
//! `[c][len]` or `[c][ny][nx]`. Adjoints **add** into their outputs.

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
        let lo = (-off).max(0) as usize;
        let hi = (self.len as isize - off.max(0)).max(lo as isize) as usize;
        (lo, hi, off)
    }
}

/// `y[o][i] = b[o] + Σ_c Σ_t w[o][c][t]·x[c][i + t − k/2]` (overwrites `y`).
pub fn conv1d(s: &Conv1d, w: &[f64], b: &[f64], x: &[f64], y: &mut [f64]) {
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
                let src = &xc[(lo as isize + off) as usize..(hi as isize + off) as usize];
                for (yi, xi) in yo[lo..hi].iter_mut().zip(src) {
                    *yi += wt * xi;
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

/// Adjoint of [`conv1d`]: `gx += ∂/∂x`, `gw += ∂/∂w`, `gb += ∂/∂b` of `⟨gy, y⟩`.
pub fn conv1d_adjoint(s: &Conv1d, w: &[f64], x: &[f64], gy: &[f64], gx: &mut [f64], gw: &mut [f64], gb: &mut [f64]) {
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
                let range = (lo as isize + off) as usize..(hi as isize + off) as usize;
                let mut acc = dot(&go[lo..hi], &xc[range.clone()]);
                for (gxi, gi) in gxc[range].iter_mut().zip(&go[lo..hi]) {
                    *gxi += wt * gi;
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
                        let src = &xrow[(lo as isize + off) as usize..(hi as isize + off) as usize];
                        for (yi, xi) in yrow[lo..hi].iter_mut().zip(src) {
                            *yi += wt * xi;
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
                        let range = (lo as isize + off) as usize..(hi as isize + off) as usize;
                        let mut acc = dot(&grow[lo..hi], &xrow[range.clone()]);
                        for (gxi, gi) in gxrow[range].iter_mut().zip(&grow[lo..hi]) {
                            *gxi += wt * gi;
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
