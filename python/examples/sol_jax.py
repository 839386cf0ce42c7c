"""Solver in the loop with the network in JAX and the solver in diffsim.

P3's setup (docs/benchmarks.md): a 1D conv network (1 → 32 → 32 → 1
channels, kernel 5, periodic, tanh) corrects each step of the coarse
Burgers solver (32 cells, dt 0.05, ν 0.01), trained through 16 unrolled
steps on batches of 32 with Adam. The step is diffsim's
(``diffsim.jax.burgers_step``: forward and VJP by diffsim, a batch in one
call); everything else is JAX, under one ``jax.jit``. With ``--solver jax``
the same program runs with the step written in JAX (the peer
``benches/peers/sol1d_jax.py``), for the side-by-side time.

    python examples/sol_jax.py [--iterations 200] [--solver diffsim|jax] [--json]
"""

from __future__ import annotations

import argparse
import json
import time

import jax

jax.config.update("jax_enable_x64", True)

import jax.numpy as jnp  # noqa: E402
import numpy as np  # noqa: E402

import diffsim.jax as djax  # noqa: E402

N, NU, DT, BATCH, UNROLL, CH, K = 32, 0.01, 0.05, 32, 16, 32, 5
DX = 2 * np.pi / N


def jax_step(u):
    """P1's scheme in JAX (the peer's)."""
    left, right = jnp.roll(u, 1, axis=-1), jnp.roll(u, -1, axis=-1)
    adv = jnp.where(u > 0, u * (u - left) / DX, u * (right - u) / DX)
    dif = NU * (right - 2 * u + left) / (DX * DX)
    return u + DT * (dif - adv)


def conv(x, w, b):
    pad = K // 2
    xp = jnp.concatenate([x[..., -pad:], x, x[..., :pad]], axis=-1)
    y = jax.lax.conv_general_dilated(xp, w, (1,), "VALID", dimension_numbers=("NCH", "OIH", "NCH"))
    return y + b[None, :, None]


def net(p, u):
    h = jnp.tanh(conv(u[:, None, :], p["w1"], p["b1"]))
    h = jnp.tanh(conv(h, p["w2"], p["b2"]))
    return conv(h, p["w3"], p["b3"])[:, 0, :]


def init(key):
    k1, k2, k3 = jax.random.split(key, 3)

    def w(k, co, ci):
        return jax.random.normal(k, (co, ci, K)) * np.sqrt(1.0 / (ci * K))

    return {"w1": w(k1, CH, 1), "b1": jnp.zeros(CH), "w2": w(k2, CH, CH), "b2": jnp.zeros(CH), "w3": w(k3, 1, CH), "b3": jnp.zeros(1)}


def make_train_step(step):
    def loss(p, u0, refs):
        def body(u, ref):
            v = step(u)
            v = v + net(p, v)
            return v, jnp.mean((v - ref) ** 2)

        _, ls = jax.lax.scan(body, u0, refs)
        return jnp.mean(ls)

    @jax.jit
    def train_step(p, m, v, t, u0, refs, lr=1e-3, b1=0.9, b2=0.999, eps=1e-8):
        value, g = jax.value_and_grad(loss)(p, u0, refs)
        m = jax.tree_util.tree_map(lambda m, g: b1 * m + (1 - b1) * g, m, g)
        v = jax.tree_util.tree_map(lambda v, g: b2 * v + (1 - b2) * g * g, v, g)
        p = jax.tree_util.tree_map(lambda p, m, v: p - lr * (m / (1 - b1**t)) / (jnp.sqrt(v / (1 - b2**t)) + eps), p, m, v)
        return p, m, v, value

    return train_step


def data(rng, batch):
    x = np.arange(N) * DX
    a = rng.uniform(-1, 1, (batch, 3))
    ph = rng.uniform(0, 2 * np.pi, (batch, 3))
    return sum(a[:, k : k + 1] * np.sin((k + 1) * x[None, :] + ph[:, k : k + 1]) for k in range(3))


def train(solver: str, iterations: int, batch: int = BATCH, unroll: int = UNROLL, seed: int = 0):
    """Trains for ``iterations`` updates; returns (losses, median seconds per
    iteration after the first, compiled one)."""
    step = djax.burgers_step(N, DT, NU) if solver == "diffsim" else jax_step
    train_step = make_train_step(step)
    rng = np.random.default_rng(seed)
    u0 = jnp.asarray(data(rng, batch))
    refs = jnp.asarray(np.stack([data(rng, batch) * 0.5 for _ in range(unroll)]))
    p = init(jax.random.PRNGKey(seed))
    m = jax.tree_util.tree_map(jnp.zeros_like, p)
    v = jax.tree_util.tree_map(jnp.zeros_like, p)
    losses, times = [], []
    for i in range(iterations):
        t0 = time.perf_counter()
        p, m, v, value = train_step(p, m, v, float(i + 1), u0, refs)
        value.block_until_ready()
        times.append(time.perf_counter() - t0)
        losses.append(float(value))
    return losses, float(np.median(times[1:])) if len(times) > 1 else times[0]


def main():
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--iterations", type=int, default=200)
    ap.add_argument("--solver", choices=["diffsim", "jax"], default="diffsim")
    ap.add_argument("--json", action="store_true")
    a = ap.parse_args()
    losses, s = train(a.solver, a.iterations)
    if a.json:
        print(json.dumps({"example": "sol_jax", "solver": a.solver, "iterations": a.iterations, "s_per_iter": s, "loss_first": losses[0], "loss_last": losses[-1]}))
    else:
        print(f"{a.solver} solver, JAX network: {a.iterations} iterations, {1e3 * s:.2f} ms each (median); loss {losses[0]:.4e} -> {losses[-1]:.4e}")


if __name__ == "__main__":
    main()
