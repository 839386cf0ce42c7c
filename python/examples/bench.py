"""What calling diffsim from JAX costs (docs/python.md).

1. The worked example (examples/sol_jax.py: P3's training, network in JAX,
   16 unrolled diffsim steps) against the same program in pure JAX, time
   per iteration, interleaved rounds.
2. The fixed cost of one call from a jitted JAX function into diffsim,
   through XLA's FFI (the default) and through ``jax.pure_callback``: an
   empty callback; diffsim's P2 smoke step called directly from NumPy and
   from JAX at 64² and 128², forward and forward + VJP; the difference is
   the call's overhead.

    python examples/bench.py [--iterations 40] [--rounds 7] [--json]
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
    ap.add_argument("--rounds", type=int, default=7, help="interleaved rounds of the example")
    ap.add_argument("--json", action="store_true")
    a = ap.parse_args()
    out = {}
    spec = importlib.util.spec_from_file_location("sol_jax", pathlib.Path(__file__).with_name("sol_jax.py"))
    sol = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(sol)
    # Interleaved: one round of each, several times, medians.
    mixed, plain = [], []
    for _ in range(a.rounds):
        mixed.append(sol.train("diffsim", a.iterations)[1])
        plain.append(sol.train("jax", a.iterations)[1])
    out["example_diffsim_ms"] = 1e3 * float(np.median(mixed))
    out["example_jax_ms"] = 1e3 * float(np.median(plain))
    # Each round's ratio (the two runs of a round share the machine's load).
    ratios = np.asarray(mixed) / np.asarray(plain)
    out["example_ratio_median"] = float(np.median(ratios))
    out["example_ratio_min"], out["example_ratio_max"] = float(ratios.min()), float(ratios.max())
    out["example_rounds_diffsim_faster"] = int((ratios < 1).sum())

    noop = jax.jit(lambda x: jax.pure_callback(lambda v: np.asarray(v), jax.ShapeDtypeStruct(x.shape, x.dtype), x))
    x = jnp.zeros(1000)
    out["empty_callback_us"] = median_us(lambda: noop(x).block_until_ready(), 2000)
    # The fixed cost of an FFI call: a 32-cell Burgers step (nanoseconds of
    # work) against a trivial jitted JAX function.
    tiny, trivial = jax.jit(djax.burgers_step(32, 0.05, 0.01)), jax.jit(lambda v: v + 1.0)
    u = jnp.asarray(np.sin(np.arange(32) * 0.2))
    out["ffi_tiny_step_us"] = median_us(lambda: tiny(u).block_until_ready(), 5000)
    out["jax_trivial_us"] = median_us(lambda: trivial(u).block_until_ready(), 5000)
    for n in (64, 128):
        op = diffsim.smoke_step(n)
        x0 = np.random.default_rng(0).random(op.n_in) * 0.1
        xj = jnp.asarray(x0)
        reps = 200 if n == 64 else 60
        out[f"p2_{n}_values"] = op.n_in
        out[f"p2_{n}_direct_forward_us"] = median_us(lambda: op.forward(x0), reps)
        out[f"p2_{n}_direct_both_us"] = median_us(lambda: (op.forward(x0), op.vjp(x0, None, x0)), reps)
        for via in ("ffi", "callback"):
            f = djax.operator(op, via)
            empty = jnp.zeros((0,))

            def step(x, f=f):
                return f(x, empty)

            def fwd_vjp(x, step=step):
                y, back = jax.vjp(step, x)
                return y, back(x)[0]

            fwd, both = jax.jit(step), jax.jit(fwd_vjp)
            out[f"p2_{n}_{via}_forward_us"] = median_us(lambda: fwd(xj).block_until_ready(), reps)
            out[f"p2_{n}_{via}_both_us"] = median_us(lambda: jax.block_until_ready(both(xj)), reps)
    if a.json:
        print(json.dumps(out))
        return
    print(f"example (P3, 16 steps, batch 32): diffsim solver {out['example_diffsim_ms']:.2f} ms, pure JAX {out['example_jax_ms']:.2f} ms per iteration")
    print(
        f"  ratio diffsim/JAX per round: median {out['example_ratio_median']:.3f} (min {out['example_ratio_min']:.3f}, max {out['example_ratio_max']:.3f});"
        f" diffsim faster in {out['example_rounds_diffsim_faster']} of {a.rounds} rounds"
    )
    print(f"an empty jax.pure_callback: {out['empty_callback_us']:.1f} µs")
    print(f"a jitted FFI call of a 32-cell step: {out['ffi_tiny_step_us']:.2f} µs; a trivial jitted JAX function: {out['jax_trivial_us']:.2f} µs")
    for n in (64, 128):
        f, b = out[f"p2_{n}_direct_forward_us"], out[f"p2_{n}_direct_both_us"]
        line = f"P2 step {n}² ({out[f'p2_{n}_values']} values): direct forward {f:.0f} µs, forward + VJP {b:.0f} µs"
        for via in ("ffi", "callback"):
            fj, bj = out[f"p2_{n}_{via}_forward_us"], out[f"p2_{n}_{via}_both_us"]
            line += f"; via {via} {fj:.0f} (+{fj - f:.0f}) / {bj:.0f} (+{bj - b:.0f})"
        print(line)


if __name__ == "__main__":
    main()
