"""Peer and reference for P4 (smoke3d) in JAX, float64, CPU.

Spec: docs/benchmarks.md, problem P4 (P2's conventions in 3D).
Arrays are indexed [k, j, i] (z, y, x); the flat smoke index is (k*N + j)*N + i.
The pressure solve is jax.scipy.sparse.linalg.cg, whose gradient is the
transposed (here: same) solve, as the spec asks.
Usage: python smoke3d_jax.py [NxT ...]   (default 32x10 48x10)
"""
import json, sys, time
import numpy as np
import jax
jax.config.update("jax_enable_x64", True)
import jax.numpy as jnp
from jax.scipy.sparse.linalg import cg


def trilin(f, px, py, pz, ox, oy, oz):
    nz, ny, nx = f.shape
    gx = jnp.clip(px - ox, 0.0, nx - 1.0)
    gy = jnp.clip(py - oy, 0.0, ny - 1.0)
    gz = jnp.clip(pz - oz, 0.0, nz - 1.0)
    i0 = jnp.minimum(jnp.floor(gx).astype(jnp.int32), nx - 2)
    j0 = jnp.minimum(jnp.floor(gy).astype(jnp.int32), ny - 2)
    k0 = jnp.minimum(jnp.floor(gz).astype(jnp.int32), nz - 2)
    fx = gx - i0; fy = gy - j0; fz = gz - k0
    out = 0.0
    for dk, wz in ((0, 1 - fz), (1, fz)):
        for dj, wy in ((0, 1 - fy), (1, fy)):
            for di, wx in ((0, 1 - fx), (1, fx)):
                out = out + f[k0 + dk, j0 + dj, i0 + di] * wx * wy * wz
    return out


def neg_lap(p):
    out = jnp.zeros_like(p)
    d = p[:, :, 1:] - p[:, :, :-1]; out = out.at[:, :, 1:].add(d).at[:, :, :-1].add(-d)
    d = p[:, 1:, :] - p[:, :-1, :]; out = out.at[:, 1:, :].add(d).at[:, :-1, :].add(-d)
    d = p[1:, :, :] - p[:-1, :, :]; out = out.at[1:, :, :].add(d).at[:-1, :, :].add(-d)
    return out


def mean4(a, ax1, ax2):
    """Mean of the four neighbours along axes ax1, ax2 after extending `a` by
    one layer on each side along ax1 (edge copy); ax2 is the face axis of `a`."""
    pad = [(0, 0)] * 3; pad[ax1] = (1, 1)
    e = jnp.pad(a, pad, mode="edge")
    def sl(x, ax, lo):
        idx = [slice(None)] * 3
        idx[ax] = slice(0, x.shape[ax] - 1) if lo else slice(1, x.shape[ax])
        return x[tuple(idx)]
    return 0.25 * (sl(sl(e, ax1, True), ax2, True) + sl(sl(e, ax1, True), ax2, False)
                   + sl(sl(e, ax1, False), ax2, True) + sl(sl(e, ax1, False), ax2, False))


def make(n, steps, maxiter=2000):
    kk, jj, ii = np.mgrid[0:n, 0:n, 0:n]; cx = ii + 0.5; cy = jj + 0.5; cz = kk + 0.5
    uk, uj, ui = np.mgrid[0:n, 0:n, 0:n + 1]; ux = ui.astype(float); uy = uj + 0.5; uz = uk + 0.5
    vk, vj, vi = np.mgrid[0:n, 0:n + 1, 0:n]; vx = vi + 0.5; vy = vj.astype(float); vz = vk + 0.5
    wk, wj, wi = np.mgrid[0:n + 1, 0:n, 0:n]; wx = wi + 0.5; wy = wj + 0.5; wz = wk.astype(float)
    r2 = (n / 8) ** 2
    s0 = jnp.asarray((((cx - n / 2) ** 2 + (cy - n / 4) ** 2 + (cz - n / 2) ** 2) <= r2).astype(float))
    target = jnp.asarray((((cx - n / 2) ** 2 + (cy - 3 * n / 4) ** 2 + (cz - n / 2) ** 2) <= r2).astype(float))

    def step(carry, _):
        s, u, v, w = carry
        uc = 0.5 * (u[:, :, 1:] + u[:, :, :-1])
        vc = 0.5 * (v[:, 1:, :] + v[:, :-1, :])
        wc = 0.5 * (w[1:, :, :] + w[:-1, :, :])
        s2 = trilin(s, cx - uc, cy - vc, cz - wc, 0.5, 0.5, 0.5)
        # x-faces: v and w extended in x, averaged over their own face axis.
        v_u = mean4(v, 2, 1); w_u = mean4(w, 2, 0)
        u2 = trilin(u, ux - u, uy - v_u, uz - w_u, 0.0, 0.5, 0.5)
        # y-faces: u and w extended in y.
        u_v = mean4(u, 1, 2); w_v = mean4(w, 1, 0)
        v2 = trilin(v, vx - u_v, vy - v, vz - w_v, 0.5, 0.0, 0.5)
        # z-faces: u and v extended in z.
        u_w = mean4(u, 0, 2); v_w = mean4(v, 0, 1)
        w2 = trilin(w, wx - u_w, wy - v_w, wz - w, 0.5, 0.5, 0.0)
        u2 = u2.at[:, :, 0].set(0.0).at[:, :, n].set(0.0)
        v2 = v2.at[:, 0, :].set(0.0).at[:, n, :].set(0.0)
        w2 = w2.at[0, :, :].set(0.0).at[n, :, :].set(0.0)
        v2 = v2.at[:, 1:n, :].add(0.1 * 0.5 * (s2[:, :-1, :] + s2[:, 1:, :]))
        div = (u2[:, :, 1:] - u2[:, :, :-1]) + (v2[:, 1:, :] - v2[:, :-1, :]) + (w2[1:, :, :] - w2[:-1, :, :])
        p, _ = cg(neg_lap, -div, tol=1e-8, atol=0.0, maxiter=maxiter)
        u2 = u2.at[:, :, 1:n].add(-(p[:, :, 1:] - p[:, :, :-1]))
        v2 = v2.at[:, 1:n, :].add(-(p[:, 1:, :] - p[:, :-1, :]))
        w2 = w2.at[1:n, :, :].add(-(p[1:, :, :] - p[:-1, :, :]))
        return (s2, u2, v2, w2), None

    def loss(s_init):
        u = jnp.zeros((n, n, n + 1)); v = jnp.zeros((n, n + 1, n)); w = jnp.zeros((n + 1, n, n))
        (s, _, _, _), _ = jax.lax.scan(step, (s_init, u, v, w), None, length=steps)
        return 0.5 * jnp.sum((s - target) ** 2)
    return loss, s0


def timeit(f, arg, repeats=3):
    jax.block_until_ready(f(arg)); ts = []
    for _ in range(repeats):
        t = time.perf_counter(); jax.block_until_ready(f(arg)); ts.append(time.perf_counter() - t)
    return float(np.median(ts))


if __name__ == "__main__":
    sizes = [(32, 10), (48, 10)]
    if len(sys.argv) > 1:
        sizes = [tuple(int(x) for x in a.split("x")) for a in sys.argv[1:]]
    for n, steps in sizes:
        loss, s0 = make(n, steps)
        f = jax.jit(loss); g = jax.jit(jax.value_and_grad(loss))
        tf = timeit(f, s0); tg = timeit(g, s0)
        val, grad = g(s0); gf = np.asarray(grad).reshape(-1)
        mid = (n // 2 * n + n // 2) * n + n // 2
        print(json.dumps({"peer": "jax", "problem": "P4", "n": n, "steps": steps, "forward_s": tf, "grad_s": tg,
                          "ratio": tg / tf, "loss": float(val), "grad_l2": float(np.linalg.norm(gf)),
                          "grad_0": float(gf[0]), "grad_mid": float(gf[mid]),
                          "grad_argmax": int(np.argmax(np.abs(gf))), "grad_max": float(gf[np.argmax(np.abs(gf))])}))
