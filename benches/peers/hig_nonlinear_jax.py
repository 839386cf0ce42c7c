"""Peer for the HIG comparison on the *nonlinear* coupled oscillators, in JAX
on CPU, written the way benches/peers/hig_oscillators_jax.py writes the
linear one (same structure, same timing), with the published nonlinear setup
of Schnell, Holl & Thuerey (ICLR 2022, tum-pbs/half-inverse-gradients,
Nonlinear_oscillators/):

Physics: two oscillators, x' = v, v' = -x + (x_{i+-1} - x_i)^3 (cubic
coupling of strength 1, free ends) + 3 * control on the last one, RK4, 96
steps of dt 0.125. Network 4 -> 20 -> 20 -> 20 -> 96 (ReLU), input the start
state, output the control per step; 4096 samples from U[0,1); the target is
the start state. Loss per sample: squared distance of the end state to the
start state. HIG: batch 128, SGD lr 1, singular values at or below 1e-6 * max
dropped, others raised to -1/2. Adam: batch 512, lr 3e-4. float32 like the
published code. Prints one JSON line: final training loss per optimizer,
seconds per update (the update steps alone) and the budget.

Usage: python hig_nonlinear_jax.py [BUDGET_SECONDS]
"""
import json, sys, time
import numpy as np
import jax
import jax.numpy as jnp

NX, NT, DT, N = 2, 96, 0.125, 4096
HIG_BATCH, ADAM_BATCH, TRUNC, ADAM_LR = 128, 512, 1e-6, 3e-4
BUDGET = float(sys.argv[1]) if len(sys.argv) > 1 else 30.0


def f(s, c):
    x1, x2, v1, v2 = s[:, 0], s[:, 1], s[:, 2], s[:, 3]
    d = x2 - x1
    return jnp.stack([v1, v2, -x1 + d ** 3, -x2 - d ** 3 + 3.0 * c], axis=1)


def solver(x0, control):
    def body(x, c):
        k1 = f(x, c); k2 = f(x + 0.5 * DT * k1, c); k3 = f(x + 0.5 * DT * k2, c); k4 = f(x + DT * k3, c)
        return x + DT * (k1 + 2 * k2 + 2 * k3 + k4) / 6, None
    x, _ = jax.lax.scan(body, x0, control.T)
    return x


sizes = [2 * NX, 20, 20, 20, NT]


def init(key):
    ps = []
    for a, b in zip(sizes[:-1], sizes[1:]):
        key, k = jax.random.split(key)
        lim = np.sqrt(6.0 / (a + b))
        ps.append((jax.random.uniform(k, (a, b), jnp.float32, -lim, lim), jnp.zeros(b, jnp.float32)))
    return ps


def net(ps, x):
    h = x
    for i, (w, b) in enumerate(ps):
        h = h @ w + b
        if i < len(ps) - 1:
            h = jax.nn.relu(h)
    return h


def predict(ps, x):
    return solver(x, net(ps, x))


def loss(ps, x):
    return jnp.sum((predict(ps, x) - x) ** 2) / x.shape[0]


from jax.flatten_util import ravel_pytree


@jax.jit
def hig_step(ps, x):
    theta, unravel = ravel_pytree(ps)
    pred = lambda t: predict(unravel(t), x).reshape(-1)
    J = jax.jacrev(pred)(theta)                       # (batch*4, params)
    y = predict(ps, x)
    g = (2.0 * (y - x) / x.shape[0]).reshape(-1)      # d loss / d y
    U, S, Vt = jnp.linalg.svd(J, full_matrices=False)
    keep = S > TRUNC * S.max()
    sinv = jnp.where(keep, 1.0 / jnp.sqrt(jnp.where(keep, S, 1.0)), 0.0)
    upd = Vt.T @ (sinv * (U.T @ g))
    return unravel(theta - 1.0 * upd)


@jax.jit
def adam_step(ps, m, v, t, x):
    g = jax.grad(loss)(ps, x)
    m = jax.tree_util.tree_map(lambda m, g: 0.9 * m + 0.1 * g, m, g)
    v = jax.tree_util.tree_map(lambda v, g: 0.999 * v + 0.001 * g * g, v, g)
    ps = jax.tree_util.tree_map(lambda p, m, v: p - ADAM_LR * (m / (1 - 0.9 ** t)) / (jnp.sqrt(v / (1 - 0.999 ** t)) + 1e-8), ps, m, v)
    return ps, m, v


full_loss = jax.jit(loss)


def run(mode):
    rng = np.random.default_rng(0)
    X = jnp.asarray(rng.random((N, 2 * NX)), jnp.float32)
    ps = init(jax.random.PRNGKey(1))
    bs = HIG_BATCH if mode == "hig" else ADAM_BATCH
    m = jax.tree_util.tree_map(jnp.zeros_like, ps); v = jax.tree_util.tree_map(jnp.zeros_like, ps)
    # warm-up compile outside the budget
    if mode == "hig":
        jax.block_until_ready(hig_step(ps, X[:bs]))
    else:
        jax.block_until_ready(adam_step(ps, m, v, 1.0, X[:bs]))
    t0 = time.perf_counter(); t = 0; curve = [(0.0, float(full_loss(ps, X)))]
    updates = 0; step_s = 0.0
    while time.perf_counter() - t0 < BUDGET:
        ts = time.perf_counter()
        for b in range(N // bs):
            xb = X[b * bs:(b + 1) * bs]
            if mode == "hig":
                ps = hig_step(ps, xb)
            else:
                t += 1; ps, m, v = adam_step(ps, m, v, float(t), xb)
        jax.block_until_ready(ps)
        step_s += time.perf_counter() - ts; updates += N // bs
        curve.append((time.perf_counter() - t0, float(full_loss(ps, X))))
    return curve, step_s / max(updates, 1)


if __name__ == "__main__":
    res = {}
    for mode in ("hig", "adam"):
        c, per_update = run(mode)
        res[mode] = c[-1][1]
        res[mode + "_s_per_update"] = per_update
        res[mode + "_epochs"] = len(c) - 1
    res["budget_s"] = BUDGET
    print(json.dumps(res))
