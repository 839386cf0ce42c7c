//! Layers and networks with hand-written VJPs and JVPs.

use rand::Rng;
use serde::{Deserialize, Serialize};

use diffsim_solvers::nn::{self as kernel, Activation, Conv1d, Conv2d};
use diffsim_solvers::real::Real;

use crate::op::{Forward, Jvp, Operator, Vjp, validate_forward, validate_jvp, validate_vjp};

/// One layer. Feature maps are channel-major (`[c][len]`, `[c][ny][nx]`);
/// parameters are the weights then the biases.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum Layer {
    /// `y = W·x + b`, `W` of `n_out × n_in`.
    Dense {
        /// Inputs.
        n_in: usize,
        /// Outputs.
        n_out: usize,
    },
    /// A 1D convolution, same length in and out.
    Conv1d(Conv1d),
    /// A 2D convolution, same size in and out.
    Conv2d(Conv2d),
    /// `y = f(x)` on `n` values.
    Act {
        /// The function.
        f: Activation,
        /// Values.
        n: usize,
    },
    /// Average pooling by 2 along positions: `c × len → c × len/2`.
    AvgPool1d {
        /// Channels.
        c: usize,
        /// Positions in (even).
        len: usize,
    },
    /// Nearest upsampling by 2: `c × len → c × 2·len`.
    Upsample1d {
        /// Channels.
        c: usize,
        /// Positions in.
        len: usize,
    },
    /// Average pooling by 2×2: `c × ny × nx → c × ny/2 × nx/2`.
    AvgPool2d {
        /// Channels.
        c: usize,
        /// Columns in (even).
        nx: usize,
        /// Rows in (even).
        ny: usize,
    },
    /// Nearest upsampling by 2×2.
    Upsample2d {
        /// Channels.
        c: usize,
        /// Columns in.
        nx: usize,
        /// Rows in.
        ny: usize,
    },
    /// `y[k] = x[from[k]]`, or 0 where `from[k]` is [`Layer::ZERO`]: a fixed
    /// selection (crop, pad, permute, reshape), e.g. a MAC state's faces to
    /// image channels and back ([`crate::nn::presets::mac_to_channels`]).
    Gather {
        /// Inputs.
        n_in: usize,
        /// The input index of each output.
        from: Vec<usize>,
    },
    /// `y = x + f(x)` with `f` the inner net (same size in and out).
    Residual(Net),
    /// `y = [x, f(x)]`: the input's channels followed by the inner net's
    /// (a U-Net's skip connection).
    Skip(Net),
}

/// How weights are drawn (biases start at zero).
#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum Init {
    /// Glorot/Xavier uniform, `±√(6/(fan_in + fan_out))` (for tanh, sigmoid).
    Glorot,
    /// He/Kaiming normal, `σ = √(2/fan_in)` (for relu-like activations).
    He,
    /// LeCun normal, `σ = √(1/fan_in)` (benchmark P3's initialisation).
    LeCun,
}

/// A network that cannot be built. Pointer-free on purpose (docs/pitfalls.md).
#[derive(Clone, Copy, Debug, PartialEq, Eq, thiserror::Error)]
pub enum NetError {
    /// No layers.
    #[error("a network needs at least one layer")]
    Empty,
    /// A layer's output does not fit the next one's input.
    #[error("layer {at} outputs {out} values but layer {} takes {next_in}", at + 1)]
    Mismatch {
        /// The layer.
        at: usize,
        /// Its output size.
        out: usize,
        /// The next layer's input size.
        next_in: usize,
    },
    /// A convolution with an even or zero kernel, or a zero size.
    #[error("layer {at}: kernels must be odd and sizes positive")]
    Kernel {
        /// The layer.
        at: usize,
    },
    /// Pooling over an odd length.
    #[error("layer {at}: pooling needs even sizes")]
    OddPool {
        /// The layer.
        at: usize,
    },
    /// A residual block whose inner net changes the size.
    #[error("layer {at}: a residual block's inner net must keep the size")]
    Residual {
        /// The layer.
        at: usize,
    },
    /// A gather that selects nothing or reads past its input.
    #[error("layer {at}: a gather needs outputs, each reading an input index below n_in (or Layer::ZERO)")]
    Gather {
        /// The layer.
        at: usize,
    },
}

impl Layer {
    /// The index of [`Layer::Gather`] that yields 0.
    pub const ZERO: usize = usize::MAX;

    /// Input size.
    pub fn n_in(&self) -> usize {
        match self {
            Layer::Dense { n_in, .. } => *n_in,
            Layer::Conv1d(s) => s.c_in * s.len,
            Layer::Conv2d(s) => s.c_in * s.nx * s.ny,
            Layer::Act { n, .. } => *n,
            Layer::AvgPool1d { c, len } | Layer::Upsample1d { c, len } => c * len,
            Layer::AvgPool2d { c, nx, ny } | Layer::Upsample2d { c, nx, ny } => c * nx * ny,
            Layer::Gather { n_in, .. } => *n_in,
            Layer::Residual(net) | Layer::Skip(net) => net.n_in(),
        }
    }

    /// Output size.
    pub fn n_out(&self) -> usize {
        match self {
            Layer::Dense { n_out, .. } => *n_out,
            Layer::Conv1d(s) => s.c_out * s.len,
            Layer::Conv2d(s) => s.c_out * s.nx * s.ny,
            Layer::Act { n, .. } => *n,
            Layer::AvgPool1d { c, len } => c * (len / 2),
            Layer::Upsample1d { c, len } => c * 2 * len,
            Layer::AvgPool2d { c, nx, ny } => c * (nx / 2) * (ny / 2),
            Layer::Upsample2d { c, nx, ny } => c * 4 * nx * ny,
            Layer::Gather { from, .. } => from.len(),
            Layer::Residual(net) => net.n_out(),
            Layer::Skip(net) => net.n_in() + net.n_out(),
        }
    }

    /// Number of parameters.
    pub fn n_params(&self) -> usize {
        match self {
            Layer::Dense { n_in, n_out } => n_out * (n_in + 1),
            Layer::Conv1d(s) => s.n_weights() + s.c_out,
            Layer::Conv2d(s) => s.n_weights() + s.c_out,
            Layer::Residual(net) | Layer::Skip(net) => net.n_params(),
            _ => 0,
        }
    }

    fn check(&self, at: usize) -> Result<(), NetError> {
        let bad_kernel = |k: usize, sizes: &[usize]| k % 2 == 0 || sizes.contains(&0);
        match self {
            Layer::Dense { n_in, n_out } if *n_in == 0 || *n_out == 0 => Err(NetError::Kernel { at }),
            Layer::Conv1d(s) if bad_kernel(s.k, &[s.c_in, s.c_out, s.len]) => Err(NetError::Kernel { at }),
            Layer::Conv2d(s) if bad_kernel(s.k, &[s.c_in, s.c_out, s.nx, s.ny]) => Err(NetError::Kernel { at }),
            Layer::AvgPool1d { len, .. } if len % 2 != 0 => Err(NetError::OddPool { at }),
            Layer::AvgPool2d { nx, ny, .. } if nx % 2 != 0 || ny % 2 != 0 => Err(NetError::OddPool { at }),
            Layer::Residual(net) if net.n_in() != net.n_out() => Err(NetError::Residual { at }),
            Layer::Gather { n_in, from } if from.is_empty() || from.iter().any(|&k| k != Layer::ZERO && k >= *n_in) => Err(NetError::Gather { at }),
            _ => Ok(()),
        }
    }

    /// `y = layer(x)` (overwrites `y`).
    fn forward<R: Real>(&self, x: &[R], p: &[R], y: &mut [R]) {
        match self {
            Layer::Dense { n_in, n_out } => {
                let (w, b) = p.split_at(n_in * n_out);
                kernel::dense(*n_in, w, b, x, y);
            }
            Layer::Conv1d(s) => {
                let (w, b) = p.split_at(s.n_weights());
                kernel::conv1d(s, w, b, x, y);
            }
            Layer::Conv2d(s) => {
                let (w, b) = p.split_at(s.n_weights());
                kernel::conv2d(s, w, b, x, y);
            }
            Layer::Act { f, .. } => kernel::activate(*f, x, y),
            Layer::AvgPool1d { c, len } => kernel::avg_pool1d(*c, *len, x, y),
            Layer::Upsample1d { c, len } => kernel::upsample1d(*c, *len, x, y),
            Layer::AvgPool2d { c, nx, ny } => kernel::avg_pool2d(*c, *nx, *ny, x, y),
            Layer::Upsample2d { c, nx, ny } => kernel::upsample2d(*c, *nx, *ny, x, y),
            Layer::Gather { from, .. } => {
                for (y, &k) in y.iter_mut().zip(from) {
                    *y = if k == Layer::ZERO { R::zero() } else { x[k] };
                }
            }
            Layer::Residual(net) => {
                net.forward_into(x, p, y);
                for (y, x) in y.iter_mut().zip(x) {
                    *y += *x;
                }
            }
            Layer::Skip(net) => {
                let (a, b) = y.split_at_mut(x.len());
                a.copy_from_slice(x);
                net.forward_into(x, p, b);
            }
        }
    }

    /// `gx += J_xᵀ·gy`, `gp += J_pᵀ·gy` (`gy` is read only); `y` is the
    /// layer's output where the caller kept it (an activation whose
    /// derivative follows from its output then skips recomputing it).
    fn backprop<R: Real>(&self, x: &[R], y: Option<&[R]>, p: &[R], gy: &[R], gx: &mut [R], gp: &mut [R]) {
        match self {
            Layer::Dense { n_in, n_out } => {
                let (w, _) = p.split_at(n_in * n_out);
                let (gw, gb) = gp.split_at_mut(n_in * n_out);
                kernel::dense_adjoint(*n_in, w, x, gy, gx, gw, gb);
            }
            Layer::Conv1d(s) => {
                let (w, _) = p.split_at(s.n_weights());
                let (gw, gb) = gp.split_at_mut(s.n_weights());
                kernel::conv1d_adjoint(s, w, x, gy, gx, gw, gb);
            }
            Layer::Conv2d(s) => {
                let (w, _) = p.split_at(s.n_weights());
                let (gw, gb) = gp.split_at_mut(s.n_weights());
                kernel::conv2d_adjoint(s, w, x, gy, gx, gw, gb);
            }
            Layer::Act { f, .. } => match y {
                Some(y) if f.df_from_output(R::zero()).is_some() => kernel::activate_adjoint_from_output(*f, y, gy, gx),
                _ => kernel::activate_adjoint(*f, x, gy, gx),
            },
            Layer::AvgPool1d { c, len } => kernel::avg_pool1d_adjoint(*c, *len, gy, gx),
            Layer::Upsample1d { c, len } => kernel::upsample1d_adjoint(*c, *len, gy, gx),
            Layer::AvgPool2d { c, nx, ny } => kernel::avg_pool2d_adjoint(*c, *nx, *ny, gy, gx),
            Layer::Upsample2d { c, nx, ny } => kernel::upsample2d_adjoint(*c, *nx, *ny, gy, gx),
            Layer::Gather { from, .. } => {
                for (&g, &k) in gy.iter().zip(from) {
                    if k != Layer::ZERO {
                        gx[k] += g;
                    }
                }
            }
            Layer::Residual(net) => {
                for (gx, g) in gx.iter_mut().zip(gy) {
                    *gx += *g;
                }
                net.backprop(x, p, gy, gx, gp);
            }
            Layer::Skip(net) => {
                let (ga, gb) = gy.split_at(x.len());
                for (gx, g) in gx.iter_mut().zip(ga) {
                    *gx += *g;
                }
                net.backprop(x, p, gb, gx, gp);
            }
        }
    }

    /// [`Layer::forward`] on `xs`, samples one after another; each row as
    /// `forward` computes it.
    fn forward_batch<R: Real>(&self, xs: &[R], p: &[R], ys: &mut [R]) {
        match self {
            Layer::Dense { n_in, n_out } => {
                let (w, b) = p.split_at(n_in * n_out);
                kernel::dense_batch(*n_in, w, b, xs, ys);
            }
            Layer::Residual(net) => {
                net.forward_into(xs, p, ys);
                for (y, x) in ys.iter_mut().zip(xs) {
                    *y += *x;
                }
            }
            // Value by value: the batch is one long slice.
            Layer::Act { f, .. } => kernel::activate(*f, xs, ys),
            // One sample at a time, convolutions included: their blocked
            // kernels keep a sample's maps in L1, and laying the batch's
            // maps end to end in one long row took 1.1–2.1× as long
            // (docs/networks.md).
            _ => {
                for (x, y) in xs.chunks_exact(self.n_in()).zip(ys.chunks_exact_mut(self.n_out())) {
                    self.forward(x, p, y);
                }
            }
        }
    }

    /// [`Layer::backprop`] over a batch: `gxs` per sample, `gp` summed over
    /// the samples in their order (the dense layer's in one blocked pass,
    /// [`kernel::dense_batch_adjoint`]).
    fn backprop_batch<R: Real>(&self, xs: &[R], ys: Option<&[R]>, p: &[R], gys: &[R], gxs: &mut [R], gp: &mut [R]) {
        let (n_in, n_out) = (self.n_in(), self.n_out());
        match self {
            Layer::Dense { n_in, n_out } => {
                let (w, _) = p.split_at(n_in * n_out);
                let (gw, gb) = gp.split_at_mut(n_in * n_out);
                kernel::dense_batch_adjoint(*n_in, w, xs, gys, gxs, gw, gb);
            }
            Layer::Residual(net) => {
                for (gx, g) in gxs.iter_mut().zip(gys) {
                    *gx += *g;
                }
                net.backprop(xs, p, gys, gxs, gp);
            }
            // Value by value, as `backprop` does a sample's.
            Layer::Act { .. } => self.backprop(xs, ys, p, gys, gxs, gp),
            _ => {
                for (s, (x, gx)) in xs.chunks_exact(n_in).zip(gxs.chunks_exact_mut(n_in)).enumerate() {
                    let y = ys.map(|ys| &ys[s * n_out..(s + 1) * n_out]);
                    self.backprop(x, y, p, &gys[s * n_out..(s + 1) * n_out], gx, gp);
                }
            }
        }
    }

    /// `y = layer(x)`, `ty = J_x·tx + J_p·tp` (overwrites both).
    fn tangent<R: Real>(&self, x: &[R], p: &[R], tx: &[R], tp: &[R], y: &mut [R], ty: &mut [R]) {
        match self {
            Layer::Dense { .. } | Layer::Conv1d(_) | Layer::Conv2d(_) => {
                // Bilinear in (x, p): ty = layer(x; tp) + layer(tx; p without bias).
                self.forward(x, p, y);
                self.forward(x, tp, ty);
                let mut q = p.to_vec();
                let nw = self.n_params() - self.n_out_channels();
                q[nw..].fill(R::zero());
                let mut t = vec![R::zero(); ty.len()];
                self.forward(tx, &q, &mut t);
                for (a, b) in ty.iter_mut().zip(&t) {
                    *a += *b;
                }
            }
            Layer::Act { f, .. } => {
                for (((y, ty), &x), &t) in y.iter_mut().zip(ty.iter_mut()).zip(x).zip(tx) {
                    *y = f.f(x);
                    *ty = f.df(x) * t;
                }
            }
            Layer::AvgPool1d { .. } | Layer::Upsample1d { .. } | Layer::AvgPool2d { .. } | Layer::Upsample2d { .. } | Layer::Gather { .. } => {
                self.forward(x, p, y);
                self.forward(tx, p, ty);
            }
            Layer::Residual(net) => {
                net.tangent(x, p, tx, tp, y, ty);
                for ((y, ty), (x, t)) in y.iter_mut().zip(ty.iter_mut()).zip(x.iter().zip(tx)) {
                    *y += *x;
                    *ty += *t;
                }
            }
            Layer::Skip(net) => {
                let n = x.len();
                y[..n].copy_from_slice(x);
                ty[..n].copy_from_slice(tx);
                let (_, yb) = y.split_at_mut(n);
                let (_, tyb) = ty.split_at_mut(n);
                net.tangent(x, p, tx, tp, yb, tyb);
            }
        }
    }

    /// Biases of a dense or convolution layer (their count).
    fn n_out_channels(&self) -> usize {
        match self {
            Layer::Dense { n_out, .. } => *n_out,
            Layer::Conv1d(s) => s.c_out,
            Layer::Conv2d(s) => s.c_out,
            _ => 0,
        }
    }

    /// Distance along the tangent `tx` to the nearest kink of a relu-like
    /// activation (to first order), `∞` for smooth layers.
    fn radius<R: Real>(&self, x: &[R], p: &[R], tx: &[R], tp: &[R]) -> f64 {
        match self {
            Layer::Act { f, .. } if f.kinked() => {
                x.iter().zip(tx).filter(|(_, t)| !t.is_zero()).map(|(x, t)| (x.as_f64() / t.as_f64()).abs()).fold(f64::INFINITY, f64::min)
            }
            Layer::Residual(net) | Layer::Skip(net) => net.radius(x, p, tx, tp),
            _ => f64::INFINITY,
        }
    }

    /// Names and shapes of the parameter tensors, in order.
    fn names(&self, prefix: &str, out: &mut Vec<(String, Vec<usize>)>) {
        match self {
            Layer::Dense { n_in, n_out } => {
                out.push((format!("{prefix}dense.weight"), vec![*n_out, *n_in]));
                out.push((format!("{prefix}dense.bias"), vec![*n_out]));
            }
            Layer::Conv1d(s) => {
                out.push((format!("{prefix}conv1d.weight"), vec![s.c_out, s.c_in, s.k]));
                out.push((format!("{prefix}conv1d.bias"), vec![s.c_out]));
            }
            Layer::Conv2d(s) => {
                out.push((format!("{prefix}conv2d.weight"), vec![s.c_out, s.c_in, s.k, s.k]));
                out.push((format!("{prefix}conv2d.bias"), vec![s.c_out]));
            }
            Layer::Residual(net) => net.names_into(&format!("{prefix}residual."), out),
            Layer::Skip(net) => net.names_into(&format!("{prefix}skip."), out),
            _ => {}
        }
    }

    /// Draws the layer's weights (biases zero).
    fn init(&self, rng: &mut impl Rng, init: Init, p: &mut [f64]) {
        let (fan_in, fan_out, nw) = match self {
            Layer::Dense { n_in, n_out } => (*n_in, *n_out, n_in * n_out),
            Layer::Conv1d(s) => (s.c_in * s.k, s.c_out * s.k, s.n_weights()),
            Layer::Conv2d(s) => (s.c_in * s.k * s.k, s.c_out * s.k * s.k, s.n_weights()),
            Layer::Residual(net) | Layer::Skip(net) => return net.init_into(rng, init, p),
            _ => return,
        };
        p.fill(0.0);
        for w in &mut p[..nw] {
            *w = match init {
                Init::Glorot => {
                    let a = (6.0 / (fan_in + fan_out) as f64).sqrt();
                    rng.random_range(-a..a)
                }
                Init::He => (2.0 / fan_in as f64).sqrt() * normal(rng),
                Init::LeCun => (1.0 / fan_in as f64).sqrt() * normal(rng),
            };
        }
    }
}

/// A standard normal sample (Box–Muller).
pub fn normal(rng: &mut impl Rng) -> f64 {
    let u1: f64 = 1.0 - rng.random::<f64>();
    let u2: f64 = rng.random();
    (-2.0 * u1.ln()).sqrt() * (std::f64::consts::TAU * u2).cos()
}

/// A sequence of layers: an operator from the first layer's input to the
/// last layer's output with the layers' parameters concatenated. Plain data
/// (`Send + Sync`), serialisable as its list of layers.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(try_from = "Vec<Layer>", into = "Vec<Layer>")]
pub struct Net {
    layers: Vec<Layer>,
    /// Where each layer's parameters start (one more entry: the total).
    offsets: Vec<usize>,
}

impl TryFrom<Vec<Layer>> for Net {
    type Error = NetError;
    fn try_from(layers: Vec<Layer>) -> Result<Self, NetError> {
        Net::new(layers)
    }
}

impl From<Net> for Vec<Layer> {
    fn from(net: Net) -> Self {
        net.layers
    }
}

impl Net {
    /// The network of `layers`, checked: sizes chain, kernels are odd,
    /// pooled sizes even.
    pub fn new(layers: Vec<Layer>) -> Result<Self, NetError> {
        if layers.is_empty() {
            return Err(NetError::Empty);
        }
        for (at, l) in layers.iter().enumerate() {
            l.check(at)?;
        }
        for (at, w) in layers.windows(2).enumerate() {
            if w[0].n_out() != w[1].n_in() {
                return Err(NetError::Mismatch { at, out: w[0].n_out(), next_in: w[1].n_in() });
            }
        }
        let mut offsets = vec![0];
        for l in &layers {
            offsets.push(offsets.last().copied().unwrap_or(0) + l.n_params());
        }
        Ok(Self { layers, offsets })
    }

    /// The layers.
    pub fn layers(&self) -> &[Layer] {
        &self.layers
    }

    fn range(&self, k: usize) -> std::ops::Range<usize> {
        self.offsets[k]..self.offsets[k + 1]
    }

    /// Names and shapes of the parameter tensors, in the order of `p`.
    pub fn param_names(&self) -> Vec<(String, Vec<usize>)> {
        let mut out = Vec::new();
        self.names_into("", &mut out);
        out
    }

    fn names_into(&self, prefix: &str, out: &mut Vec<(String, Vec<usize>)>) {
        for (k, l) in self.layers.iter().enumerate() {
            l.names(&format!("{prefix}{k}."), out);
        }
    }

    /// Fresh parameters: weights drawn by `init`, biases zero.
    pub fn init(&self, rng: &mut impl Rng, init: Init) -> Vec<f64> {
        let mut p = vec![0.0; self.n_params()];
        self.init_into(rng, init, &mut p);
        p
    }

    fn init_into(&self, rng: &mut impl Rng, init: Init, p: &mut [f64]) {
        for (k, l) in self.layers.iter().enumerate() {
            l.init(rng, init, &mut p[self.range(k)]);
        }
    }

    /// Where a batch's forward pass splits into two halves of the samples,
    /// one a thread (each sample's values are the same either way): from
    /// [`NET_PAR_MIN_WORK`] samples × parameters, with two threads or more.
    fn halves(&self, batch: usize) -> Option<usize> {
        let work = batch.saturating_mul(self.n_params().max(1));
        (batch >= 2 && work >= NET_PAR_MIN_WORK && rayon::current_num_threads() > 1).then_some(batch / 2)
    }

    /// The inputs of layers `1..L` (the outputs of all but the last layer)
    /// for a batch of samples, one after another (one sample is a batch of
    /// one), on the calling thread. (The VJP's forward pass stays on one
    /// thread: split in halves, it took longer, 221 against 154 µs on the
    /// linear HIG network's batch of 256, the idle workers competing with
    /// the backward pass for two cores.)
    fn hidden<R: Real>(&self, xs: &[R], p: &[R]) -> Vec<Vec<R>> {
        let batch = xs.len() / self.n_in();
        let last = self.layers.len() - 1;
        let mut outs: Vec<Vec<R>> = Vec::with_capacity(last);
        for (k, l) in self.layers[..last].iter().enumerate() {
            let mut y = vec![R::zero(); batch * l.n_out()];
            l.forward_batch(outs.last().map_or(xs, |v| v), &p[self.range(k)], &mut y);
            outs.push(y);
        }
        outs
    }

    fn forward_into<R: Real>(&self, xs: &[R], p: &[R], ys: &mut [R]) {
        let Some(mid) = self.halves(xs.len() / self.n_in()) else {
            return self.forward_here(xs, p, ys);
        };
        let (xa, xb) = xs.split_at(mid * self.n_in());
        let (ya, yb) = ys.split_at_mut(mid * self.n_out());
        rayon::join(|| self.forward_here(xa, p, ya), || self.forward_here(xb, p, yb));
    }

    /// [`Net::forward_into`] on the calling thread.
    fn forward_here<R: Real>(&self, xs: &[R], p: &[R], ys: &mut [R]) {
        let hidden = self.hidden(xs, p);
        let last = self.layers.len() - 1;
        self.layers[last].forward_batch(hidden.last().map_or(xs, |v| v), &p[self.range(last)], ys);
    }

    fn backprop<R: Real>(&self, xs: &[R], p: &[R], gys: &[R], gxs: &mut [R], gp: &mut [R]) {
        let batch = xs.len() / self.n_in();
        let outs = self.hidden(xs, p);
        let mut g = gys.to_vec();
        for k in (0..self.layers.len()).rev() {
            let input: &[R] = if k == 0 { xs } else { &outs[k - 1] };
            let output = outs.get(k).map(|v| v.as_slice());
            if k == 0 {
                self.layers[0].backprop_batch(input, output, &p[self.range(0)], &g, gxs, &mut gp[self.range(0)]);
            } else {
                let mut gin = vec![R::zero(); batch * self.layers[k].n_in()];
                self.layers[k].backprop_batch(input, output, &p[self.range(k)], &g, &mut gin, &mut gp[self.range(k)]);
                g = gin;
            }
        }
    }

    fn tangent<R: Real>(&self, x: &[R], p: &[R], tx: &[R], tp: &[R], y: &mut [R], ty: &mut [R]) {
        let (mut cur, mut tcur) = (x.to_vec(), tx.to_vec());
        let last = self.layers.len() - 1;
        for (k, l) in self.layers.iter().enumerate() {
            let r = self.range(k);
            if k == last {
                l.tangent(&cur, &p[r.clone()], &tcur, &tp[r], y, ty);
            } else {
                let (mut a, mut b) = (vec![R::zero(); l.n_out()], vec![R::zero(); l.n_out()]);
                l.tangent(&cur, &p[r.clone()], &tcur, &tp[r], &mut a, &mut b);
                (cur, tcur) = (a, b);
            }
        }
    }

    fn radius<R: Real>(&self, x: &[R], p: &[R], tx: &[R], tp: &[R]) -> f64 {
        let mut r = f64::INFINITY;
        let (mut cur, mut tcur) = (x.to_vec(), tx.to_vec());
        for (k, l) in self.layers.iter().enumerate() {
            let range = self.range(k);
            r = r.min(l.radius(&cur, &p[range.clone()], &tcur, &tp[range.clone()]));
            let (mut a, mut b) = (vec![R::zero(); l.n_out()], vec![R::zero(); l.n_out()]);
            l.tangent(&cur, &p[range.clone()], &tcur, &tp[range], &mut a, &mut b);
            (cur, tcur) = (a, b);
        }
        r
    }
}

/// Samples × parameters from which a network's batch forward pass runs in
/// two halves on two threads ([`Net::forward_batch`]): below, handing half
/// to a thread (a few microseconds) costs more than it saves.
pub const NET_PAR_MIN_WORK: usize = 1 << 17;

impl Operator for Net {
    fn n_in(&self) -> usize {
        self.layers[0].n_in()
    }
    fn n_out(&self) -> usize {
        self.layers[self.layers.len() - 1].n_out()
    }
    fn n_params(&self) -> usize {
        self.offsets[self.layers.len()]
    }
}

impl<R: Real> Forward<R> for Net {
    fn forward(&self, x: &[R], p: &[R], y: &mut [R]) {
        validate_forward(self, "Net", x, p, y);
        crate::op::count::record("Net", crate::op::count::Method::Forward);
        self.forward_into(x, p, y);
    }

    /// One pass per layer over the whole batch (dense layers as one
    /// blocked product); each sample's output as [`Forward::forward`]'s.
    fn forward_batch(&self, xs: &[R], p: &[R], ys: &mut [R]) {
        validate_batch(self, xs, p, ys.len(), xs.len());
        crate::op::count::record("Net", crate::op::count::Method::Forward);
        self.forward_into(xs, p, ys);
    }

    /// Kinks of relu-like activations, to first order along the tangent.
    fn smooth_radius(&self, x: &[R], p: &[R], dx: &[R], dp: &[R]) -> f64 {
        // Half the first-order distance: the pre-activations are not exactly linear along the tangent.
        0.5 * self.radius(x, p, dx, dp)
    }
}

impl<R: Real> Vjp<R> for Net {
    fn vjp(&self, x: &[R], p: &[R], dy: &mut [R], dx: &mut [R], dp: &mut [R]) {
        validate_vjp(self, "Net", x, p, dy, dx, dp);
        crate::op::count::record("Net", crate::op::count::Method::Vjp);
        self.backprop(x, p, dy, dx, dp);
        dy.fill(R::zero());
    }

    /// The batch's backward pass layer by layer; the dense layers' weight
    /// gradients summed over the samples in one blocked pass, in sample
    /// order (equal, bit for bit, to adding per-sample gradients in order).
    fn vjp_batch(&self, xs: &[R], p: &[R], dys: &mut [R], dxs: &mut [R], dp: &mut [R]) {
        validate_batch(self, xs, p, dys.len(), dxs.len());
        assert_eq!(dp.len(), self.n_params(), "Net: vjp_batch's dp has {} values, not {}", dp.len(), self.n_params());
        crate::op::count::record("Net", crate::op::count::Method::Vjp);
        self.backprop(xs, p, dys, dxs, dp);
        dys.fill(R::zero());
    }
}

/// Checks a batch call's sizes: whole samples in `xs`, `n_out` values per
/// sample in `ys`, `n_in` per sample in `dxs`, `n_params` parameters.
fn validate_batch<R: Real>(net: &Net, xs: &[R], p: &[R], ys: usize, dxs: usize) {
    let (n_in, n_out) = (net.n_in(), net.n_out());
    let batch = xs.len() / n_in;
    assert!(
        xs.len().is_multiple_of(n_in) && ys == batch * n_out && dxs == xs.len() && p.len() == net.n_params(),
        "Net: a batch of {} inputs ({n_in} per sample) with {ys} outputs ({n_out} per sample), {dxs} input values and {} parameters ({} expected)",
        xs.len(),
        p.len(),
        net.n_params()
    );
}

impl<R: Real> Jvp<R> for Net {
    fn jvp(&self, x: &[R], p: &[R], tx: &[R], tp: &[R], y: &mut [R], ty: &mut [R]) {
        validate_jvp(self, "Net", x, p, tx, tp, y, ty);
        crate::op::count::record("Net", crate::op::count::Method::Jvp);
        self.tangent(x, p, tx, tp, y, ty);
    }
}
