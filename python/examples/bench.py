"""What calling diffsim from JAX costs (docs/python.md).

1. The worked example (examples/sol_jax.py: P3's training, network in JAX,
   16 unrolled diffsim steps) against the same program in pure JAX, time
   per iteration, interleaved rounds.
2. The fixed cost of one call from a jitted JAX function into diffsim
   (``jax.pure_callback``): an empty callback; diffsim's P2 smoke step
   called directly from NumPy and through JAX at 64² and 128², forward and
   forward + VJP; the difference is the call's overhead.

    python examples/bench.py [--iterations 40] [--json]
"""

from __future__ import annotations

import argparse
import importlib.util
import json
import pathlib
import time

import jax

jax.config.update("jax_enable_x64", True)

import jax.numpy as jnp  # noqa: E402
import numpy as np  # noqa: E402

import diffsim  # noqa: E402
import diffsim.jax as djax  # noqa: E402


def median_us(f, repeats):
    f()
    ts = []
    for _ in range(repeats):
        t = time.perf_counter()
        f()
        ts.append(time.perf_counter() - t)
    return 1e6 * float(np.median(ts))


def main():
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--iterations", type=int, default=40)
    ap.add_argument("--json", action="store_true")
    a = ap.parse_args()
    out = {}
    spec = importlib.util.spec_from_file_location("sol_jax", pathlib.Path(__file__).with_name("sol_jax.py"))
    sol = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(sol)
    # Interleaved: one round of each, several times, medians.
    mixed, plain = [], []
    for _ in range(3):
        mixed.append(sol.train("diffsim", a.iterations)[1])
        plain.append(sol.train("jax", a.iterations)[1])
    out["example_diffsim_ms"] = 1e3 * float(np.median(mixed))
    out["example_jax_ms"] = 1e3 * float(np.median(plain))

    noop = jax.jit(lambda x: jax.pure_callback(lambda v: np.asarray(v), jax.ShapeDtypeStruct(x.shape, x.dtype), x))
    x = jnp.zeros(1000)
    out["empty_callback_us"] = median_us(lambda: noop(x).block_until_ready(), 2000)
    for n in (64, 128):
        op = diffsim.smoke_step(n)
        step = djax.smoke_step(n)
        x0 = np.random.default_rng(0).random(op.n_in) * 0.1
        xj = jnp.asarray(x0)
        fwd = jax.jit(step)
        def fwd_vjp(x):
            y, back = jax.vjp(step, x)
            return y, back(x)[0]

        both = jax.jit(fwd_vjp)
        reps = 200 if n == 64 else 60
        out[f"p2_{n}_values"] = op.n_in
        out[f"p2_{n}_direct_forward_us"] = median_us(lambda: op.forward(x0), reps)
        out[f"p2_{n}_jax_forward_us"] = median_us(lambda: fwd(xj).block_until_ready(), reps)
        out[f"p2_{n}_direct_both_us"] = median_us(lambda: (op.forward(x0), op.vjp(x0, None, x0)), reps)
        out[f"p2_{n}_jax_both_us"] = median_us(lambda: jax.block_until_ready(both(xj)), reps)
    if a.json:
        print(json.dumps(out))
        return
    print(f"example (P3, 16 steps, batch 32): diffsim solver {out['example_diffsim_ms']:.2f} ms, pure JAX {out['example_jax_ms']:.2f} ms per iteration")
    print(f"an empty jax.pure_callback: {out['empty_callback_us']:.1f} µs")
    for n in (64, 128):
        f, fj = out[f"p2_{n}_direct_forward_us"], out[f"p2_{n}_jax_forward_us"]
        b, bj = out[f"p2_{n}_direct_both_us"], out[f"p2_{n}_jax_both_us"]
        print(f"P2 step {n}² ({out[f'p2_{n}_values']} values): forward {f:.0f} µs direct, {fj:.0f} µs from JAX (+{fj - f:.0f}); forward + VJP {b:.0f} / {bj:.0f} µs (+{bj - b:.0f})")


if __name__ == "__main__":
    main()
