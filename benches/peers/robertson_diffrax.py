"""Robertson's kinetics with JAX/Diffrax: the loss ½ Σ_i ‖u(t_i) − d_i‖² at
t = 0.4, 4, 40 (d: ODEPACK's published solution) and its gradient with
respect to the log-rates p = ln k, at p off the published rates by
(0.3, −0.4, 0.3) (where a fit starts): the peer of `diffsim bench
robertson` beside diffsol (scripts/bench-robertson).

Kvaerno5 (an ESDIRK, L-stable, order 5) with a PID step-size controller
at RTOL (ATOL the same), saving at the three times; the gradient by
jax.grad through diffeqsolve (RecursiveCheckpointAdjoint: the discrete
adjoint of the steps taken), float64, jit. Prints one JSON line:
{"peer", "rtol", "grad_s", "loss", "gradient"}.

Usage: robertson_diffrax.py RTOL REPS
"""
import json
import sys
import time

import jax

jax.config.update("jax_enable_x64", True)
import jax.numpy as jnp  # noqa: E402
import diffrax  # noqa: E402

TIMES = jnp.array([0.4, 4.0, 40.0])
DATA = jnp.array([[9.851726e-01, 3.386406e-05, 1.479357e-02],
                  [9.055142e-01, 2.240418e-05, 9.446344e-02],
                  [7.158050e-01, 9.184616e-06, 2.841858e-01]])


def rates(t, u, p):
    k1, k2, k3 = jnp.exp(p[0]), jnp.exp(p[1]), jnp.exp(p[2])
    a, b, c = u[0], u[1], u[2]
    return jnp.stack([-k1 * a + k3 * b * c, k1 * a - k3 * b * c - k2 * b * b, k2 * b * b])


def main():
    try:
        rtol, reps = float(sys.argv[1]), int(sys.argv[2])
        assert 0 < rtol < 1 and reps >= 1
    except (IndexError, ValueError, AssertionError):
        sys.exit("usage: robertson_diffrax.py RTOL REPS (RTOL in (0, 1), REPS >= 1)")
    controller = diffrax.PIDController(rtol=rtol, atol=rtol)

    def loss(p):
        sol = diffrax.diffeqsolve(diffrax.ODETerm(rates), diffrax.Kvaerno5(), t0=0.0, t1=40.0, dt0=1e-6,
                                  y0=jnp.array([1.0, 0.0, 0.0]), args=p, saveat=diffrax.SaveAt(ts=TIMES),
                                  stepsize_controller=controller, max_steps=1_000_000)
        return 0.5 * jnp.sum((sol.ys - DATA) ** 2)

    grad = jax.jit(jax.value_and_grad(loss))
    p = jnp.log(jnp.array([0.04, 3.0e7, 1.0e4])) + jnp.array([0.3, -0.4, 0.3])
    value, g = grad(p)
    jax.block_until_ready(g)
    times = []
    for _ in range(reps):
        start = time.perf_counter()
        value, g = grad(p)
        jax.block_until_ready(g)
        times.append(time.perf_counter() - start)
    times.sort()
    if not (jnp.isfinite(value) and jnp.all(jnp.isfinite(g))):
        sys.exit(f"robertson_diffrax: the loss or gradient is not finite at rtol {rtol:e}")
    print(json.dumps({"peer": f"diffrax {diffrax.__version__} Kvaerno5 (JAX {jax.__version__})", "rtol": rtol,
                      "grad_s": times[reps // 2], "loss": float(value), "gradient": [float(v) for v in g]}))


if __name__ == "__main__":
    main()
