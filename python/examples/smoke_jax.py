"""A JAX program around P2's 2D smoke solver, where the solver is the work.

A control θ (a smoke source on every cell, a stand-in for a network's
output) acts between the steps of P2's solver (64², buoyant smoke, pressure
projection; docs/benchmarks.md): ``x ← step(x); s ← s + θ``, and the
loss after T steps is P2's. The gradient with respect to θ runs through
every step. ``--solver diffsim`` takes the step from diffsim
(``diffsim.jax.smoke_step``: XLA FFI calls, Enzyme's step adjoint, the
implicit adjoint of the pressure solve); ``--solver jax`` the same step in
JAX (the peer's code, benches/peers/smoke2d_jax.py, CG by
``jax.scipy.sparse.linalg.cg``).

    python examples/smoke_jax.py [--n 64] [--steps 20] [--iterations 5] [--json]
"""

from __future__ import annotations

import argparse
import json
import time

import jax

jax.config.update("jax_enable_x64", True)

import jax.numpy as jnp  # noqa: E402
import numpy as np  # noqa: E402
from jax.scipy.sparse.linalg import cg  # noqa: E402

import diffsim  # noqa: E402
import diffsim.jax as djax  # noqa: E402


def jax_step(n: int):
    """P2's step on the packed state (smoke, u, v), in JAX (the peer's)."""
    jj, ii = np.mgrid[0:n, 0:n]
    cx, cy = ii + 0.5, jj + 0.5
    uj, ui = np.mgrid[0:n, 0 : n + 1]
    ux, uy = ui.astype(float), uj + 0.5
    vj, vi = np.mgrid[0 : n + 1, 0:n]
    vx, vy = vi + 0.5, vj.astype(float)

    def bilin(f, px, py, ox, oy):
        ny, nx = f.shape
        gx = jnp.clip(px - ox, 0.0, nx - 1.0)
        gy = jnp.clip(py - oy, 0.0, ny - 1.0)
        i0 = jnp.minimum(jnp.floor(gx).astype(jnp.int32), nx - 2)
        j0 = jnp.minimum(jnp.floor(gy).astype(jnp.int32), ny - 2)
        fx, fy = gx - i0, gy - j0
        return f[j0, i0] * (1 - fx) * (1 - fy) + f[j0, i0 + 1] * fx * (1 - fy) + f[j0 + 1, i0] * (1 - fx) * fy + f[j0 + 1, i0 + 1] * fx * fy

    def neg_lap(p):
        out = jnp.zeros_like(p)
        d = p[:, 1:] - p[:, :-1]
        out = out.at[:, 1:].add(d).at[:, :-1].add(-d)
        d = p[1:, :] - p[:-1, :]
        return out.at[1:, :].add(d).at[:-1, :].add(-d)

    def step(x):
        s = x[: n * n].reshape(n, n)
        u = x[n * n : n * n + n * (n + 1)].reshape(n, n + 1)
        v = x[n * n + n * (n + 1) :].reshape(n + 1, n)
        uc, vc = 0.5 * (u[:, 1:] + u[:, :-1]), 0.5 * (v[1:, :] + v[:-1, :])
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
        p, _ = cg(neg_lap, -div, tol=1e-8, atol=0.0, maxiter=2000)
        u2 = u2.at[:, 1:n].add(-(p[:, 1:] - p[:, :-1]))
        v2 = v2.at[1:n, :].add(-(p[1:, :] - p[:-1, :]))
        return jnp.concatenate([s2.ravel(), u2.ravel(), v2.ravel()])

    return step


def make(solver: str, n: int, steps: int):
    """``value_and_grad`` of the loss with respect to θ, jitted, and the
    starting θ and state."""
    problem = diffsim.p2_problem(n, steps)
    x0, target = jnp.asarray(problem["x0"]), jnp.asarray(problem["target"])
    step = djax.smoke_step(n) if solver == "diffsim" else jax_step(n)

    def loss(theta):
        def body(x, _):
            x = step(x)
            return x.at[: n * n].add(theta), None

        x, _ = jax.lax.scan(body, x0, None, length=steps)
        return 0.5 * jnp.sum((x[: n * n] - target) ** 2)

    return jax.jit(jax.value_and_grad(loss)), jnp.full(n * n, 1e-3)


def timed(f, theta, iterations):
    jax.block_until_ready(f(theta))
    ts = []
    for _ in range(iterations):
        t = time.perf_counter()
        jax.block_until_ready(f(theta))
        ts.append(time.perf_counter() - t)
    return float(np.median(ts))


def main():
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--n", type=int, default=64)
    ap.add_argument("--steps", type=int, default=20)
    ap.add_argument("--iterations", type=int, default=5)
    ap.add_argument("--json", action="store_true")
    a = ap.parse_args()
    out = {"n": a.n, "steps": a.steps}
    values = {}
    for solver in ("diffsim", "jax"):
        f, theta = make(solver, a.n, a.steps)
        out[f"{solver}_s"] = timed(f, theta, a.iterations)
        values[solver] = f(theta)
    (lv, gv), (lj, gj) = values["diffsim"], values["jax"]
    out["loss_rel_diff"] = float(abs(lv - lj) / abs(lj))
    out["grad_rel_diff"] = float(jnp.linalg.norm(gv - gj) / jnp.linalg.norm(gj))
    if a.json:
        print(json.dumps(out))
    else:
        print(
            f"P2 {a.n}², {a.steps} steps, a control between the steps: value and gradient in {1e3 * out['diffsim_s']:.1f} ms "
            f"with diffsim's step, {1e3 * out['jax_s']:.1f} ms with JAX's ({out['jax_s'] / out['diffsim_s']:.1f}×); "
            f"loss and gradient differ by {out['loss_rel_diff']:.1e} and {out['grad_rel_diff']:.1e} (relative)"
        )


if __name__ == "__main__":
    main()
