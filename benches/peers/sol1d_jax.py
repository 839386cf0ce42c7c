"""Peer benchmark P3 (sol1d): one training iteration through an unrolled
coarse Burgers solver with a 1D conv network correcting each step, JAX on CPU.

Spec: docs/benchmarks.md, problem P3. Prints one JSON line: median seconds
per iteration (loss + gradient + Adam update, jit-compiled), for float64 and
float32.
"""
import json, sys, time
import numpy as np
import jax
jax.config.update("jax_enable_x64", True)
import jax.numpy as jnp

N, NU, DT, BATCH, UNROLL, CH, K = 32, 0.01, 0.05, 32, 16, 32, 5
DX = 2 * np.pi / N

def step(u):
    l = jnp.roll(u, 1, axis=-1); r = jnp.roll(u, -1, axis=-1)
    adv = jnp.where(u > 0, u * (u - l) / DX, u * (r - u) / DX)
    dif = NU * (r - 2 * u + l) / (DX * DX)
    return u + DT * (dif - adv)

def conv(x, w, b):
    # x: (B, Cin, N) periodic; w: (Cout, Cin, K)
    pad = K // 2
    xp = jnp.concatenate([x[..., -pad:], x, x[..., :pad]], axis=-1)
    y = jax.lax.conv_general_dilated(xp, w, (1,), "VALID", dimension_numbers=("NCH", "OIH", "NCH"))
    return y + b[None, :, None]

def net(p, u):
    h = jnp.tanh(conv(u[:, None, :], p["w1"], p["b1"]))
    h = jnp.tanh(conv(h, p["w2"], p["b2"]))
    return conv(h, p["w3"], p["b3"])[:, 0, :]

def init(key, dtype):
    k1, k2, k3 = jax.random.split(key, 3)
    def w(k, co, ci):
        return (jax.random.normal(k, (co, ci, K)) * np.sqrt(1.0 / (ci * K))).astype(dtype)
    return {"w1": w(k1, CH, 1), "b1": jnp.zeros(CH, dtype), "w2": w(k2, CH, CH), "b2": jnp.zeros(CH, dtype),
            "w3": w(k3, 1, CH), "b3": jnp.zeros(1, dtype)}

def loss(p, u0, refs):
    def body(u, ref):
        v = step(u); v = v + net(p, v)
        return v, jnp.mean((v - ref) ** 2)
    _, ls = jax.lax.scan(body, u0, refs)
    return jnp.mean(ls)

def adam_update(p, g, m, v, t, lr=1e-3, b1=0.9, b2=0.999, eps=1e-8):
    m = jax.tree_util.tree_map(lambda m, g: b1 * m + (1 - b1) * g, m, g)
    v = jax.tree_util.tree_map(lambda v, g: b2 * v + (1 - b2) * g * g, v, g)
    mh = jax.tree_util.tree_map(lambda m: m / (1 - b1 ** t), m)
    vh = jax.tree_util.tree_map(lambda v: v / (1 - b2 ** t), v)
    p = jax.tree_util.tree_map(lambda p, a, b: p - lr * a / (jnp.sqrt(b) + eps), p, mh, vh)
    return p, m, v

@jax.jit
def train_step(p, m, v, t, u0, refs):
    l, g = jax.value_and_grad(loss)(p, u0, refs)
    p, m, v = adam_update(p, g, m, v, t)
    return p, m, v, l

def run(dtype):
    rng = np.random.default_rng(0)
    x = np.arange(N) * DX
    def sample(b):
        a = rng.uniform(-1, 1, (b, 3)); ph = rng.uniform(0, 2 * np.pi, (b, 3))
        return sum(a[:, k:k + 1] * np.sin((k + 1) * x[None, :] + ph[:, k:k + 1]) for k in range(3))
    u0 = jnp.asarray(sample(BATCH), dtype)
    refs = jnp.asarray(np.stack([sample(BATCH) * 0.5 for _ in range(UNROLL)]), dtype)
    p = init(jax.random.PRNGKey(0), dtype)
    m = jax.tree_util.tree_map(jnp.zeros_like, p); v = jax.tree_util.tree_map(jnp.zeros_like, p)
    p, m, v, l = train_step(p, m, v, 1.0, u0, refs); l.block_until_ready()
    ts = []
    for i in range(30):
        t0 = time.perf_counter()
        p, m, v, l = train_step(p, m, v, float(i + 2), u0, refs); l.block_until_ready()
        ts.append(time.perf_counter() - t0)
    nparams = sum(int(np.prod(a.shape)) for a in jax.tree_util.tree_leaves(p))
    return float(np.median(ts)), nparams

if __name__ == "__main__":
    for name, dt in (("float64", jnp.float64), ("float32", jnp.float32)):
        s, npar = run(dt)
        print(json.dumps({"peer": "jax", "problem": "P3", "dtype": name, "s_per_iter": s, "params": npar,
                          "batch": BATCH, "unroll": UNROLL, "n": N}))
