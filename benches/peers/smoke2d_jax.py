"""Peer and reference for P2 (smoke2d) in JAX, float64, CPU.

Spec: docs/benchmarks.md, problem P2 (the exact conventions there).
Arrays are indexed [j, i] (y, x); the flat smoke index is j*N + i.
The pressure solve is jax.scipy.sparse.linalg.cg, whose gradient is the
transposed (here: same) solve, as the spec asks.
"""
import json, sys, time
import numpy as np
import jax
jax.config.update("jax_enable_x64", True)
import jax.numpy as jnp
from jax.scipy.sparse.linalg import cg

def bilin(f, px, py, ox, oy):
    ny, nx = f.shape
    gx = jnp.clip(px - ox, 0.0, nx - 1.0); gy = jnp.clip(py - oy, 0.0, ny - 1.0)
    i0 = jnp.minimum(jnp.floor(gx).astype(jnp.int32), nx - 2)
    j0 = jnp.minimum(jnp.floor(gy).astype(jnp.int32), ny - 2)
    fx = gx - i0; fy = gy - j0
    return (f[j0, i0] * (1 - fx) * (1 - fy) + f[j0, i0 + 1] * fx * (1 - fy)
            + f[j0 + 1, i0] * (1 - fx) * fy + f[j0 + 1, i0 + 1] * fx * fy)

def neg_lap(p):
    out = jnp.zeros_like(p)
    d = p[:, 1:] - p[:, :-1]; out = out.at[:, 1:].add(d).at[:, :-1].add(-d)
    d = p[1:, :] - p[:-1, :]; out = out.at[1:, :].add(d).at[:-1, :].add(-d)
    return out

def make(n, steps, maxiter=2000):
    jj, ii = np.mgrid[0:n, 0:n]; cx = ii + 0.5; cy = jj + 0.5
    uj, ui = np.mgrid[0:n, 0:n + 1]; ux = ui.astype(float); uy = uj + 0.5
    vj, vi = np.mgrid[0:n + 1, 0:n]; vx = vi + 0.5; vy = vj.astype(float)
    s0 = jnp.asarray((((cx - n / 2) ** 2 + (cy - n / 4) ** 2) <= (n / 8) ** 2).astype(float))
    target = jnp.asarray((((cx - n / 2) ** 2 + (cy - 3 * n / 4) ** 2) <= (n / 8) ** 2).astype(float))

    def step(carry, _):
        s, u, v = carry
        uc = 0.5 * (u[:, 1:] + u[:, :-1]); vc = 0.5 * (v[1:, :] + v[:-1, :])
        s2 = bilin(s, cx - uc, cy - vc, 0.5, 0.5)
        vpad = jnp.pad(v, ((0, 0), (1, 1)), mode="edge")
        vu = 0.25 * (vpad[:-1, :-1] + vpad[:-1, 1:] + vpad[1:, :-1] + vpad[1:, 1:])
        u2 = bilin(u, ux - u, uy - vu, 0.0, 0.5)
        upad = jnp.pad(u, ((1, 1), (0, 0)), mode="edge")
        uv = 0.25 * (upad[:-1, :-1] + upad[:-1, 1:] + upad[1:, :-1] + upad[1:, 1:])
        v2 = bilin(v, vx - uv, vy - v, 0.5, 0.0)
        u2 = u2.at[:, 0].set(0.0).at[:, n].set(0.0)
        v2 = v2.at[0, :].set(0.0).at[n, :].set(0.0)
        v2 = v2.at[1:n, :].add(0.1 * 0.5 * (s2[:-1, :] + s2[1:, :]))
        div = (u2[:, 1:] - u2[:, :-1]) + (v2[1:, :] - v2[:-1, :])
        p, _ = cg(neg_lap, -div, tol=1e-8, atol=0.0, maxiter=maxiter)
        u2 = u2.at[:, 1:n].add(-(p[:, 1:] - p[:, :-1]))
        v2 = v2.at[1:n, :].add(-(p[1:, :] - p[:-1, :]))
        return (s2, u2, v2), None

    def loss(s_init):
        u = jnp.zeros((n, n + 1)); v = jnp.zeros((n + 1, n))
        (s, _, _), _ = jax.lax.scan(step, (s_init, u, v), None, length=steps)
        return 0.5 * jnp.sum((s - target) ** 2)
    return loss, s0

def timeit(f, arg, repeats=5):
    jax.block_until_ready(f(arg)); ts = []
    for _ in range(repeats):
        t = time.perf_counter(); jax.block_until_ready(f(arg)); ts.append(time.perf_counter() - t)
    return float(np.median(ts))

if __name__ == "__main__":
    sizes = [(64, 20), (128, 20)]
    if len(sys.argv) > 1:
        sizes = [tuple(int(x) for x in a.split("x")) for a in sys.argv[1:]]
    for n, steps in sizes:
        loss, s0 = make(n, steps)
        f = jax.jit(loss); g = jax.jit(jax.value_and_grad(loss))
        tf = timeit(f, s0); tg = timeit(g, s0)
        val, grad = g(s0); gf = np.asarray(grad).reshape(-1)
        print(json.dumps({"peer": "jax", "problem": "P2", "n": n, "steps": steps, "forward_s": tf, "grad_s": tg,
                          "ratio": tg / tf, "loss": float(val), "grad_l2": float(np.linalg.norm(gf)),
                          "grad_0": float(gf[0]), "grad_n2": float(gf[n * n // 2]),
                          "grad_argmax": int(np.argmax(np.abs(gf))), "grad_max": float(gf[np.argmax(np.abs(gf))])}))
