"""Peer benchmark P2 (smoke2d) in PhiFlow 3 on its JAX backend, CPU.

Spec: docs/benchmarks.md, problem P2. Buoyant smoke on a closed N x N box,
staggered velocity, semi-Lagrangian advection, pressure projection by CG to a
relative tolerance of 1e-8 (capped at 2000 iterations, never reached). Times one forward rollout and one gradient of the final
density loss with respect to the initial smoke, after jit warm-up.
"""
import json, sys, time
import numpy as np
from phi.jax.flow import *
from phi import math as pm

def run(n, steps, cg_iters):
    box = Box(x=n, y=n)
    # Converged solves: relative tolerance 1e-8, no absolute floor; cg_iters is only a cap.
    solve = Solve('CG', 1e-8, 0, max_iterations=cg_iters)
    v0 = StaggeredGrid(0, 0, box, x=n, y=n)
    target = CenteredGrid(Noise(scale=n / 4, smoothness=2.0), 0, box, x=n, y=n)
    s0 = CenteredGrid(Sphere(x=n / 2, y=n / 4, radius=n / 8), 0, box, x=n, y=n)

    def loss(smoke):
        v = v0
        for _ in range(steps):
            smoke = advect.semi_lagrangian(smoke, v, 1.0)
            buoy = resample(smoke * (0, 0.1), to=v)
            v = advect.semi_lagrangian(v, v, 1.0) + buoy
            v, _ = fluid.make_incompressible(v, (), solve)
        return pm.l2_loss(smoke - target)

    f = jit_compile(loss)
    g = jit_compile(pm.gradient(loss, 'smoke', get_output=True))
    def timed(fn, repeats=5):
        r = fn(s0); pm.wrap(0)
        ts = []
        for _ in range(repeats):
            t = time.perf_counter(); r = fn(s0)
            leaf = r[1] if isinstance(r, tuple) else r
            while isinstance(leaf, (tuple, list)):
                leaf = leaf[0]
            float(pm.sum(leaf.values if isinstance(leaf, Field) else leaf))
            ts.append(time.perf_counter() - t)
        return float(np.median(ts)), r
    tf, _ = timed(f)
    tg, r = timed(g)
    print(json.dumps({"peer": "phiflow-jax", "problem": "P2", "n": n, "steps": steps, "cg_iters": cg_iters,
                      "forward_s": tf, "grad_s": tg, "ratio": tg / tf}))

if __name__ == "__main__":
    sizes = [(64, 20, 2000), (128, 20, 2000)]
    if len(sys.argv) > 1:
        sizes = [tuple(int(v) for v in a.split("x")) for a in sys.argv[1:]]
    for n, steps, it in sizes:
        run(n, steps, it)
