"""Peer benchmark P1 (burgers1d) in JAX, float64, CPU.

Spec: docs/benchmarks.md, problem P1. Prints one JSON line per size with
forward and gradient times (median of repeats, after jit warm-up), the loss and
a gradient checksum, so the project's numbers can be compared side by side.
"""
import json, sys, time
import jax
jax.config.update("jax_enable_x64", True)
import jax.numpy as jnp
import numpy as np

NU = 0.01

def setup(n):
    dx = 2 * np.pi / n
    x = np.arange(n) * dx
    dt = min(0.25 * dx, 0.25 * dx * dx / NU)
    u0 = np.sin(x) + 0.5 * np.sin(2 * x + 0.3)
    target = 0.8 * np.sin(x - 0.4)
    return dx, dt, jnp.asarray(u0), jnp.asarray(target)

def make_loss(n, steps):
    dx, dt, _, target = setup(n)
    def step(u, _):
        l = jnp.roll(u, 1)
        r = jnp.roll(u, -1)
        adv = jnp.where(u > 0, u * (u - l) / dx, u * (r - u) / dx)
        dif = NU * (r - 2 * u + l) / (dx * dx)
        return u + dt * (dif - adv), None
    def loss(u0):
        u, _ = jax.lax.scan(step, u0, None, length=steps)
        return 0.5 * dx * jnp.sum((u - target) ** 2)
    return loss

def timeit(f, arg, repeats):
    jax.block_until_ready(f(arg))
    ts = []
    for _ in range(repeats):
        t = time.perf_counter(); jax.block_until_ready(f(arg)); ts.append(time.perf_counter() - t)
    return float(np.median(ts))

def main():
    sizes = [(256, 256), (2048, 2048), (16384, 1000)]
    if len(sys.argv) > 1:
        sizes = [tuple(int(v) for v in a.split("x")) for a in sys.argv[1:]]
    for n, steps in sizes:
        _, _, u0, _ = setup(n)
        loss = make_loss(n, steps)
        f = jax.jit(loss)
        g = jax.jit(jax.value_and_grad(loss))
        tf = timeit(f, u0, 7)
        tg = timeit(g, u0, 7)
        val, grad = g(u0)
        print(json.dumps({"peer": "jax", "problem": "P1", "n": n, "steps": steps,
                          "forward_s": tf, "grad_s": tg, "ratio": tg / tf,
                          "loss": float(val), "grad_l2": float(jnp.linalg.norm(grad)),
                          "grad_0": float(grad[0]), "grad_n2": float(grad[n // 2])}))

if __name__ == "__main__":
    main()
