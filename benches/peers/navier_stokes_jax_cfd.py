"""JAX-CFD's periodic Navier-Stokes step, the peer of diffsim's
`PeriodicNavierStokes` (docs/navier-stokes.md, `scripts/bench-navier-stokes`).

The 2D Taylor-Green vortex on [0, 2π]², periodic, N² cells on a staggered
grid, float64: JAX-CFD's `semi_implicit_navier_stokes` with its defaults
(van Leer advection, explicit diffusion, the pressure solved by fast
diagonalisation, that is by FFT, forward Euler), jit-compiled. Times one
step and the gradient of L = ½‖u_T‖² with respect to the initial velocity
through T steps (`jax.grad` of the `lax.scan` rollout), each the best of
repeats over `budget` seconds, and checks the decay against exp(−2νt).

Usage: python navier_stokes_jax_cfd.py N STEPS NU DT BUDGET_SECONDS
Prints one JSON line: forward_step_s, grad_per_step_s, loss, decay_error.
"""

import json
import sys
import time

import jax

jax.config.update("jax_enable_x64", True)
import jax.numpy as jnp  # noqa: E402
import jax_cfd.base as cfd  # noqa: E402

n, steps, nu, dt, budget = int(sys.argv[1]), int(sys.argv[2]), float(sys.argv[3]), float(sys.argv[4]), float(sys.argv[5])
grid = cfd.grids.Grid((n, n), domain=((0, 2 * jnp.pi), (0, 2 * jnp.pi)))
bc = cfd.boundaries.periodic_boundary_conditions(2)


def taylor_green():
    """u = sin x cos y, v = −cos x sin y on the staggered faces."""
    x_u, y_u = grid.mesh(grid.cell_faces[0])
    x_v, y_v = grid.mesh(grid.cell_faces[1])
    u = cfd.grids.GridVariable(cfd.grids.GridArray(jnp.sin(x_u) * jnp.cos(y_u), grid.cell_faces[0], grid), bc)
    v = cfd.grids.GridVariable(cfd.grids.GridArray(-jnp.cos(x_v) * jnp.sin(y_v), grid.cell_faces[1], grid), bc)
    return (u, v)


step = cfd.equations.semi_implicit_navier_stokes(density=1.0, viscosity=nu, dt=dt, grid=grid)
v0 = taylor_green()
data0 = tuple(c.array.data for c in v0)


def wrap(data):
    return tuple(cfd.grids.GridVariable(cfd.grids.GridArray(d, c.array.offset, grid), bc) for d, c in zip(data, v0))


@jax.jit
def one(data):
    return tuple(c.array.data for c in step(wrap(data)))


def rollout(data):
    def body(d, _):
        return tuple(c.array.data for c in step(wrap(d))), None

    final, _ = jax.lax.scan(body, data, None, length=steps)
    return final


@jax.jit
def loss(data):
    final = rollout(data)
    return 0.5 * sum(jnp.sum(f * f) for f in final)


grad = jax.jit(jax.grad(loss))


def best(f):
    jax.block_until_ready(f())
    t_end, best_t = time.perf_counter() + budget, float("inf")
    while time.perf_counter() < t_end:
        t = time.perf_counter()
        jax.block_until_ready(f())
        best_t = min(best_t, time.perf_counter() - t)
    return best_t


forward = best(lambda: one(data0))
gradient = best(lambda: grad(data0))
final = jax.jit(rollout)(data0)
decay = jnp.exp(-2 * nu * dt * steps)
err = max(float(jnp.max(jnp.abs(f - d * decay))) for f, d in zip(final, data0))
print(json.dumps({"forward_step_s": forward, "grad_per_step_s": gradient / steps, "loss": float(loss(data0)), "decay_error": err}))
