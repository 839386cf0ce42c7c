//! Ready-made networks: a plain convolution stack (benchmark P3's network),
//! a multilayer perceptron, a small residual network, U-Nets, and
//! the gathers that put a 2D MAC velocity into image channels and back.

use diffsim_solvers::nn::{Activation, Conv1d, Conv2d, Padding};

use super::{Layer, Net, NetError};

fn conv1d(c_in: usize, c_out: usize, k: usize, len: usize, padding: Padding) -> Layer {
    Layer::Conv1d(Conv1d { c_in, c_out, k, len, padding })
}

fn conv2d(c_in: usize, c_out: usize, k: usize, nx: usize, ny: usize, padding: Padding) -> Layer {
    Layer::Conv2d(Conv2d { c_in, c_out, k, nx, ny, padding })
}

/// 1D convolutions through `channels` (e.g. `[1, 32, 32, 1]`), kernel `k`,
/// the activation between them and none after the last. P3's network is
/// `conv_stack_1d(32, &[1, 32, 32, 1], 5, Periodic, Tanh)` (5505 parameters).
pub fn conv_stack_1d(len: usize, channels: &[usize], k: usize, padding: Padding, act: Activation) -> Result<Net, NetError> {
    let mut layers = Vec::new();
    for (i, w) in channels.windows(2).enumerate() {
        layers.push(conv1d(w[0], w[1], k, len, padding));
        if i + 2 < channels.len() {
            layers.push(Layer::Act { f: act, n: w[1] * len });
        }
    }
    Net::new(layers)
}

/// Dense layers through `sizes` (e.g. `[4, 20, 20, 24]`) with the
/// activation between them and none after the last.
pub fn mlp(sizes: &[usize], act: Activation) -> Result<Net, NetError> {
    let mut layers = Vec::new();
    for (i, w) in sizes.windows(2).enumerate() {
        layers.push(Layer::Dense { n_in: w[0], n_out: w[1] });
        if i + 2 < sizes.len() {
            layers.push(Layer::Act { f: act, n: w[1] });
        }
    }
    Net::new(layers)
}

/// A small 1D residual network: a convolution to `width` channels, `blocks`
/// residual blocks (conv, act, conv), the activation, a convolution to
/// `c_out`.
#[allow(clippy::too_many_arguments)]
pub fn resnet_1d(len: usize, c_in: usize, c_out: usize, width: usize, blocks: usize, k: usize, padding: Padding, act: Activation) -> Result<Net, NetError> {
    let n = width * len;
    let mut layers = vec![conv1d(c_in, width, k, len, padding), Layer::Act { f: act, n }];
    for _ in 0..blocks {
        let inner = Net::new(vec![conv1d(width, width, k, len, padding), Layer::Act { f: act, n }, conv1d(width, width, k, len, padding)])?;
        layers.push(Layer::Residual(inner));
        layers.push(Layer::Act { f: act, n });
    }
    layers.push(conv1d(width, c_out, k, len, padding));
    Net::new(layers)
}

/// A small 1D U-Net with one level: conv to `width`, then a skip
/// connection around (pool, conv to `2·width`, act, conv back to `width`,
/// act, upsample), then on the `2·width` concatenated channels a conv to
/// `width`, act, and a conv to `c_out`. `len` must be even.
pub fn unet_1d(len: usize, c_in: usize, c_out: usize, width: usize, k: usize, padding: Padding, act: Activation) -> Result<Net, NetError> {
    let h = len / 2;
    let down = Net::new(vec![
        Layer::AvgPool1d { c: width, len },
        conv1d(width, 2 * width, k, h, padding),
        Layer::Act { f: act, n: 2 * width * h },
        conv1d(2 * width, width, k, h, padding),
        Layer::Act { f: act, n: width * h },
        Layer::Upsample1d { c: width, len: h },
    ])?;
    Net::new(vec![
        conv1d(c_in, width, k, len, padding),
        Layer::Act { f: act, n: width * len },
        Layer::Skip(down),
        conv1d(2 * width, width, k, len, padding),
        Layer::Act { f: act, n: width * len },
        conv1d(width, c_out, k, len, padding),
    ])
}

/// The 2D counterpart of [`unet_1d`] on an `nx × ny` map (both even).
#[allow(clippy::too_many_arguments)]
pub fn unet_2d(nx: usize, ny: usize, c_in: usize, c_out: usize, width: usize, k: usize, padding: Padding, act: Activation) -> Result<Net, NetError> {
    let (hx, hy) = (nx / 2, ny / 2);
    let down = Net::new(vec![
        Layer::AvgPool2d { c: width, nx, ny },
        conv2d(width, 2 * width, k, hx, hy, padding),
        Layer::Act { f: act, n: 2 * width * hx * hy },
        conv2d(2 * width, width, k, hx, hy, padding),
        Layer::Act { f: act, n: width * hx * hy },
        Layer::Upsample2d { c: width, nx: hx, ny: hy },
    ])?;
    Net::new(vec![
        conv2d(c_in, width, k, nx, ny, padding),
        Layer::Act { f: act, n: width * nx * ny },
        Layer::Skip(down),
        conv2d(2 * width, width, k, nx, ny, padding),
        Layer::Act { f: act, n: width * nx * ny },
        conv2d(width, c_out, k, nx, ny, padding),
    ])
}

/// A U-Net of `levels` resolutions on an `nx × ny` map (both divisible by
/// `2^(levels−1)`), `filters` channels at every level, in the classic
/// shape of PhiFlow's `u_net` (the SIP paper's network: 4 levels, 16
/// filters): a double convolution (`k × k` conv, act, conv, act) to
/// `filters`; per coarser level a 2 × 2 average pool and a double
/// convolution, the way back an upsample, the finer level's features
/// concatenated (a skip) and a double convolution from `2·filters`; a 1 × 1
/// convolution to `c_out`. (PhiFlow pools by maximum and may normalise
/// batches; diffsim pools by average and has no batch normalisation.)
#[allow(clippy::too_many_arguments)]
pub fn unet_2d_levels(
    nx: usize,
    ny: usize,
    c_in: usize,
    c_out: usize,
    filters: usize,
    levels: usize,
    k: usize,
    padding: Padding,
    act: Activation,
) -> Result<Net, NetError> {
    let f = filters;
    let double = |c_in: usize, nx: usize, ny: usize| {
        vec![
            conv2d(c_in, f, k, nx, ny, padding),
            Layer::Act { f: act, n: f * nx * ny },
            conv2d(f, f, k, nx, ny, padding),
            Layer::Act { f: act, n: f * nx * ny },
        ]
    };
    // The levels below resolution (nx, ny), inside out: pool, double conv,
    // [the next level as a skip, double conv from 2f], upsample.
    let mut inner: Option<Net> = None;
    for level in (1..levels.max(1)).rev() {
        let (hx, hy) = (nx >> level, ny >> level);
        let mut layers = vec![Layer::AvgPool2d { c: f, nx: 2 * hx, ny: 2 * hy }];
        layers.extend(double(f, hx, hy));
        if let Some(net) = inner.take() {
            layers.push(Layer::Skip(net));
            layers.extend(double(2 * f, hx, hy));
        }
        layers.push(Layer::Upsample2d { c: f, nx: hx, ny: hy });
        inner = Some(Net::new(layers)?);
    }
    let mut layers = double(c_in, nx, ny);
    if let Some(net) = inner {
        layers.push(Layer::Skip(net));
        layers.extend(double(2 * f, nx, ny));
    }
    layers.push(conv2d(f, c_out, 1, nx, ny, padding));
    Net::new(layers)
}

/// A [`Layer::Gather`] from a packed MAC state `[s, u, v]` of an `nx × ny`
/// box ([`diffsim_solvers::smoke`]'s layout) to two `ny × nx` image
/// channels: `u` on each cell's left face, `v` on its bottom face (the
/// smoke and the last face of each row and column are left out).
pub fn mac_to_channels(nx: usize, ny: usize) -> Layer {
    let (ns, nu) = (nx * ny, ny * (nx + 1));
    let mut from = Vec::with_capacity(2 * ns);
    from.extend((0..ns).map(|c| ns + (c / nx) * (nx + 1) + c % nx));
    from.extend((0..ns).map(|c| ns + nu + c));
    Layer::Gather { n_in: ns + nu + (ny + 1) * nx, from }
}

/// The inverse placement of [`mac_to_channels`]: two `ny × nx` channels to
/// a packed MAC state, zero smoke and zero on each row's last x-face and the
/// top row of y-faces. With `keep`, only the state entries where `keep` is
/// true receive a value (a correction then leaves boundary and obstacle
/// faces alone).
pub fn channels_to_mac(nx: usize, ny: usize, keep: Option<&[bool]>) -> Layer {
    let (ns, nu, nv) = (nx * ny, ny * (nx + 1), (ny + 1) * nx);
    let mut from = vec![Layer::ZERO; ns + nu + nv];
    for j in 0..ny {
        for i in 0..nx {
            from[ns + j * (nx + 1) + i] = j * nx + i;
            from[ns + nu + j * nx + i] = ns + j * nx + i;
        }
    }
    if let Some(keep) = keep {
        for (f, &k) in from.iter_mut().zip(keep) {
            if !k {
                *f = Layer::ZERO;
            }
        }
    }
    Layer::Gather { n_in: 2 * ns, from }
}

/// A 2D convolution stack on a MAC state: [`mac_to_channels`], convolutions
/// of kernel `k` through `channels` (first 2, last 2) with `act` between,
/// zero padding (the walls), [`channels_to_mac`] (writing only where `keep`
/// says, when given).
pub fn mac_conv_stack(nx: usize, ny: usize, channels: &[usize], k: usize, act: Activation, keep: Option<&[bool]>) -> Result<Net, NetError> {
    let mut layers = vec![mac_to_channels(nx, ny)];
    for (w, pair) in channels.windows(2).enumerate() {
        layers.push(conv2d(pair[0], pair[1], k, nx, ny, Padding::Zero));
        if w + 2 < channels.len() {
            layers.push(Layer::Act { f: act, n: pair[1] * nx * ny });
        }
    }
    layers.push(channels_to_mac(nx, ny, keep));
    Net::new(layers)
}
