"""diffsim's periodic Navier-Stokes step through its Python package, the
side of `scripts/bench-navier-stokes` that JAX-CFD is measured against
(benches/peers/navier_stokes_jax_cfd.py: the same Taylor-Green vortex,
grid, viscosity, time step and loss).

`diffsim.navier_stokes_step([N, N], scheme="maccormack")` (its default):
MacCormack advection (second order, unlimited) and explicit viscosity
differentiated by Enzyme, the projection by FFT, the
call split into stable sub-steps. Times one step and the gradient of
L = ½‖u_T‖² (the faces' own values, not the periodic copies) with respect
to the initial velocity through T steps (T forwards storing the states,
then T VJPs), each the best of repeats over `budget` seconds.

Usage: python navier_stokes_diffsim.py N STEPS NU DT BUDGET_SECONDS
Prints one JSON line: forward_step_s, grad_per_step_s, loss, decay_error.
"""

import json
import sys
import time

import numpy as np

import diffsim

# The generated adjoints' buffers reused, not mapped afresh per call.
diffsim.keep_freed_memory()
n, steps, nu, dt, budget = int(sys.argv[1]), int(sys.argv[2]), float(sys.argv[3]), float(sys.argv[4]), float(sys.argv[5])
op = diffsim.navier_stokes_step([n, n], scheme="maccormack")
h = 2 * np.pi / n
xu, yu = np.meshgrid(np.arange(n + 1) * h, (np.arange(n) + 0.5) * h)
xv, yv = np.meshgrid((np.arange(n) + 0.5) * h, np.arange(n + 1) * h)
x0 = np.concatenate([(np.sin(xu) * np.cos(yu)).ravel(), (-np.cos(xv) * np.sin(yv)).ravel()])
p = np.array([nu, dt])
# The own faces: u without its last column (the copy of the first), v
# without its last row.
own = np.concatenate([np.pad(np.ones((n, n)), ((0, 0), (0, 1))).ravel(), np.pad(np.ones((n, n)), ((0, 1), (0, 0))).ravel()])


def gradient():
    states = [x0]
    for _ in range(steps):
        states.append(op.forward(states[-1], p))
    g = states[-1] * own
    loss = 0.5 * float(np.sum(g * states[-1]))
    for x in reversed(states[:-1]):
        g, _ = op.vjp(x, p, g)
    return loss, g


def best(f):
    f()
    t_end, best_t = time.perf_counter() + budget, float("inf")
    while time.perf_counter() < t_end:
        t = time.perf_counter()
        f()
        best_t = min(best_t, time.perf_counter() - t)
    return best_t


forward = best(lambda: op.forward(x0, p))
grad = best(gradient)
loss, _ = gradient()
x = x0
for _ in range(steps):
    x = op.forward(x, p)
err = float(np.max(np.abs(x - x0 * np.exp(-2 * nu * dt * steps))))
print(json.dumps({"forward_step_s": forward, "grad_per_step_s": grad / steps, "loss": loss, "decay_error": err}))
