"""Shared pieces of the Python tests: P1 written entirely in JAX (the
scheme of benches/peers/burgers1d_jax.py), to compare diffsim against."""

import jax

jax.config.update("jax_enable_x64", True)

import jax.numpy as jnp  # noqa: E402
import numpy as np  # noqa: E402
import pytest  # noqa: E402

NU = 0.01


def jax_p1_loss(n, steps):
    """P1's loss u0 -> ½·dx·Σ (u_T − u*)² in plain JAX."""
    dx = 2 * np.pi / n
    x = np.arange(n) * dx
    dt = min(0.25 * dx, 0.25 * dx * dx / NU)
    target = jnp.asarray(0.8 * np.sin(x - 0.4))

    def step(u, _):
        left, right = jnp.roll(u, 1), jnp.roll(u, -1)
        adv = jnp.where(u > 0, u * (u - left) / dx, u * (right - u) / dx)
        dif = NU * (right - 2 * u + left) / (dx * dx)
        return u + dt * (dif - adv), None

    def loss(u0):
        u, _ = jax.lax.scan(step, u0, None, length=steps)
        return 0.5 * dx * jnp.sum((u - target) ** 2)

    return loss


@pytest.fixture
def scenes():
    """The repository's scene folders."""
    import pathlib

    root = pathlib.Path(__file__).resolve().parents[2]
    return root


def jax_oscillators(kind):
    """diffsim.oscillators(kind) in plain JAX: (x0 (4), u (steps)) -> s_T by
    RK4, the coupled oscillators of src/problems/oscillators.rs."""
    steps, dt, linear, cubic, control = (24, 0.5, 0.2, 0.0, 1.0) if kind == "linear" else (96, 0.125, 0.0, 1.0, 3.0)

    def rhs(s, u):
        d = s[0] - s[1]
        f = cubic * d**3
        return jnp.stack([s[2], s[3], -s[0] - linear * d - f, -s[1] + linear * d + f + control * u])

    def step(s, u):
        k1 = rhs(s, u)
        k2 = rhs(s + 0.5 * dt * k1, u)
        k3 = rhs(s + 0.5 * dt * k2, u)
        k4 = rhs(s + dt * k3, u)
        return s + dt / 6 * (k1 + 2 * k2 + 2 * k3 + k4), None

    def run(x0, u):
        assert u.shape == (steps,)
        s, _ = jax.lax.scan(step, x0, u)
        return s

    return run
