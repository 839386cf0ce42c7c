"""The implicit heat benchmark of `diffsim bench implicit-heat`, in JAX.

Backward-Euler heat conduction on an n x n grid of unit cells, insulated
sides, a conductivity exp(theta) per cell (a face takes the mean of its two
cells'), dt = 0.1: each step solves (I + dt A(theta)) y = x by CG
(jax.scipy.sparse.linalg.cg, relative tolerance 1e-10) inside
lax.custom_linear_solve(symmetric=True), so JAX differentiates by the
implicit rule (a transposed solve), as diffsim does. Loss 1/2 |x_T - x*|^2,
gradient with respect to the initial state and every conductivity; float64,
jit. The same initial state, conductivities and target as the Rust bench.

Usage: python implicit_heat_jax.py N STEPS BUDGET_SECONDS [zero|rhs] [none|jacobi]  -> one JSON line
(rhs: CG starts from the right-hand side, as `diffsim bench implicit-heat
--start rhs`; jacobi: CG preconditioned by the matrix's diagonal, as
`--preconditioner jacobi`).
"""
import json
import statistics
import sys
import time

import jax

jax.config.update("jax_enable_x64", True)
import jax.numpy as jnp  # noqa: E402
from jax.scipy.sparse.linalg import cg  # noqa: E402

n, steps, budget = int(sys.argv[1]), int(sys.argv[2]), float(sys.argv[3])
start = sys.argv[4] if len(sys.argv) > 4 else "zero"
precond = sys.argv[5] if len(sys.argv) > 5 else "none"
dt, tol = 0.1, 1e-10


def wave(a, b):
    k = jnp.arange(n * n)
    i, j = k % n, k // n
    return (a * jnp.sin(0.37 * i) * jnp.cos(0.23 * j) + b).reshape(n, n)


x0, theta, target = wave(1.0, 0.5), wave(0.5, 0.0), wave(0.2, 0.5)


def matvec_of(theta):
    kappa = jnp.exp(theta)
    cx = dt * 0.5 * (kappa[:, 1:] + kappa[:, :-1])  # faces between columns i, i+1
    cy = dt * 0.5 * (kappa[1:, :] + kappa[:-1, :])  # faces between rows j, j+1

    def matvec(v):
        fx = cx * (v[:, :-1] - v[:, 1:])
        fy = cy * (v[:-1, :] - v[1:, :])
        out = v
        out = out.at[:, :-1].add(fx).at[:, 1:].add(-fx)
        out = out.at[:-1, :].add(fy).at[1:, :].add(-fy)
        return out

    return matvec


def diagonal_of(theta):
    kappa = jnp.exp(theta)
    cx = dt * 0.5 * (kappa[:, 1:] + kappa[:, :-1])
    cy = dt * 0.5 * (kappa[1:, :] + kappa[:-1, :])
    d = jnp.ones_like(theta)
    return d.at[:, :-1].add(cx).at[:, 1:].add(cx).at[:-1, :].add(cy).at[1:, :].add(cy)


def solver(theta):
    m = None
    if precond == "jacobi":
        d = jax.lax.stop_gradient(diagonal_of(theta))
        m = lambda r: r / d  # noqa: E731

    def solve(matvec, b):
        return cg(matvec, b, x0=b if start == "rhs" else None, tol=tol, atol=0.0, maxiter=10_000, M=m)[0]

    return solve


def loss(x0, theta):
    matvec = matvec_of(theta)
    solve = solver(theta)

    def step(x, _):
        return jax.lax.custom_linear_solve(matvec, x, solve, symmetric=True), None

    x, _ = jax.lax.scan(step, x0, None, length=steps)
    return 0.5 * jnp.sum((x - target) ** 2)


forward = jax.jit(loss)
gradient = jax.jit(jax.value_and_grad(loss, argnums=(0, 1)))


def median_time(f):
    jax.block_until_ready(f())  # compile
    times, start = [], time.perf_counter()
    while len(times) < 3 or time.perf_counter() - start < budget:
        t0 = time.perf_counter()
        jax.block_until_ready(f())
        times.append(time.perf_counter() - t0)
        if len(times) >= 1000:
            break
    return statistics.median(times)


value = float(forward(x0, theta))
v2, (gx, gt) = gradient(x0, theta)
forward_s = median_time(lambda: forward(x0, theta))
grad_s = median_time(lambda: gradient(x0, theta))
print(json.dumps({"peer": "jax", "jax": jax.__version__, "n": n, "steps": steps, "tolerance": tol, "start": start, "preconditioner": precond, "loss": value,
                  "grad_norm": float(jnp.sqrt(jnp.sum(gx ** 2) + jnp.sum(gt ** 2))),
                  "forward_s": forward_s, "grad_s": grad_s, "grad_over_forward": grad_s / forward_s}))
