"""Peer for the published SIP-heat update (Holl, Koltun & Thuerey, ICLR 2022;
docs/sip.md) in JAX on CPU: one update of the 4-level U-Net on a batch of
128 observations, SIP and Adam, float32 like the published code.

The network is diffsim's `presets::unet_2d_levels(64, 64, 1, 1, 16, 4, 3,
Zero, Relu)` written in JAX: per level a double 3x3 convolution (zero
padding, ReLU after each) to 16 channels; going down a 2x2 average pool,
going up a nearest 2x upsample and the finer level's features concatenated
before its input (skip: [x, f(x)]), then a double convolution from 32
channels; a 1x1 convolution to one channel. He initialisation. The
prediction is shifted to the observation's mean (diffsim's MeanMatched).

Physics: periodic diffusion on 64x64 to nu*t = 8 in Fourier space,
y = P(x) = F^-1[exp(-|k|^2 nu t) F x]; the SIP update's local inverse is
the damped inverse g / (g^2 + eps) (eps 1e-3) of the same multiplier.
SIP: x_target = x - eta * (P^-1(P(x)) - P^-1(y*)), the proxy loss
mean ||N(y*) - stop_gradient(x_target)||^2 / 2, Adam (lr 1e-3) on it.
Adam: the physics loss mean ||P(N(y*)) - y*||^2 / 2 through P, Adam 1e-3.

Prints one JSON line: seconds per update of each (median of the timed
updates after a warm-up), the batch and the parameter count.
Usage: python sip_heat_unet_jax.py [UPDATES]   (default 5)
"""
import json, sys, time
import numpy as np
import jax
import jax.numpy as jnp

N, B, F, LEVELS, NU_T, EPS, ETA, LR = 64, 128, 16, 4, 8.0, 1e-3, 1.0, 1e-3
UPDATES = int(sys.argv[1]) if len(sys.argv) > 1 else 5

k = 2 * np.pi * np.fft.fftfreq(N, d=1.0 / N) / N  # wavenumbers of a unit-spaced periodic grid
K2 = k[None, :] ** 2 + k[:, None] ** 2
G = jnp.asarray(np.exp(-K2 * NU_T), jnp.float32)
GINV = G / (G * G + EPS)

def physics(x):  # x: (B, N, N)
    return jnp.real(jnp.fft.ifft2(jnp.fft.fft2(x) * G))

def inverse(y):
    return jnp.real(jnp.fft.ifft2(jnp.fft.fft2(y) * GINV))

def conv_params(key, c_in, c_out, ksz):
    std = np.sqrt(2.0 / (c_in * ksz * ksz))
    return (jax.random.normal(key, (ksz, ksz, c_in, c_out), jnp.float32) * std, jnp.zeros(c_out, jnp.float32))

def init(key):
    ps = {}
    def double(name, c_in):
        nonlocal key
        key, a, b = jax.random.split(key, 3)
        ps[name + "a"], ps[name + "b"] = conv_params(a, c_in, F, 3), conv_params(b, F, F, 3)
    double("top_in", 1)
    for level in range(1, LEVELS):
        double(f"l{level}_in", F)
        if level < LEVELS - 1:
            double(f"l{level}_out", 2 * F)
    double("top_out", 2 * F)
    key, c = jax.random.split(key)
    ps["last"] = conv_params(c, F, 1, 1)
    return ps

def conv(p, x):
    w, b = p
    return jax.lax.conv_general_dilated(x, w, (1, 1), "SAME", dimension_numbers=("NHWC", "HWIO", "NHWC")) + b

def double(ps, name, x):
    return jax.nn.relu(conv(ps[name + "b"], jax.nn.relu(conv(ps[name + "a"], x))))

def pool(x):
    b, h, w, c = x.shape
    return x.reshape(b, h // 2, 2, w // 2, 2, c).mean(axis=(2, 4))

def upsample(x):
    return jnp.repeat(jnp.repeat(x, 2, axis=1), 2, axis=2)

def level(ps, lv, x):  # the inner net of level lv: pool, double, [skip, double], upsample
    h = double(ps, f"l{lv}_in", pool(x))
    if lv < LEVELS - 1:
        h = double(ps, f"l{lv}_out", jnp.concatenate([h, level(ps, lv + 1, h)], axis=-1))
    return upsample(h)

def net(ps, y):  # y: (B, N, N) -> x: (B, N, N)
    h = double(ps, "top_in", y[..., None])
    h = double(ps, "top_out", jnp.concatenate([h, level(ps, 1, h)], axis=-1))
    x = conv(ps["last"], h)[..., 0]
    return x - x.mean(axis=(1, 2), keepdims=True) + y.mean(axis=(1, 2), keepdims=True)

def adam(ps, g, m, v, t):
    m = jax.tree.map(lambda m, g: 0.9 * m + 0.1 * g, m, g)
    v = jax.tree.map(lambda v, g: 0.999 * v + 0.001 * g * g, v, g)
    mh, vh = 1 - 0.9 ** t, 1 - 0.999 ** t
    ps = jax.tree.map(lambda p, m, v: p - LR * (m / mh) / (jnp.sqrt(v / vh) + 1e-8), ps, m, v)
    return ps, m, v

@jax.jit
def sip_step(ps, m, v, t, y):
    x = net(ps, y)
    target = jax.lax.stop_gradient(x - ETA * (inverse(physics(x)) - inverse(y)))
    def proxy(ps):
        return 0.5 * jnp.mean(jnp.sum((net(ps, y) - target) ** 2, axis=(1, 2)))
    loss, g = jax.value_and_grad(proxy)(ps)
    ps, m, v = adam(ps, g, m, v, t)
    return ps, m, v, loss

@jax.jit
def adam_step(ps, m, v, t, y):
    def physics_loss(ps):
        return 0.5 * jnp.mean(jnp.sum((physics(net(ps, y)) - y) ** 2, axis=(1, 2)))
    loss, g = jax.value_and_grad(physics_loss)(ps)
    ps, m, v = adam(ps, g, m, v, t)
    return ps, m, v, loss

def timed(step):
    ps = init(jax.random.PRNGKey(1))
    m = jax.tree.map(jnp.zeros_like, ps)
    v = jax.tree.map(jnp.zeros_like, ps)
    y = physics(jax.random.uniform(jax.random.PRNGKey(2), (B, N, N), jnp.float32))
    ps, m, v, loss = step(ps, m, v, 1.0, y)  # compile
    loss.block_until_ready()
    times = []
    for t in range(2, UPDATES + 2):
        start = time.perf_counter()
        ps, m, v, loss = step(ps, m, v, float(t), y)
        loss.block_until_ready()
        times.append(time.perf_counter() - start)
    return float(np.median(times)), sum(int(np.prod(p.shape)) for p in jax.tree.leaves(ps))

sip_s, params = timed(sip_step)
adam_s, _ = timed(adam_step)
print(json.dumps({"sip_s_per_update": sip_s, "adam_s_per_update": adam_s, "batch": B, "params": params, "updates": UPDATES}))
