"""Shared pieces of the Python tests: P1 written entirely in JAX (the
scheme of ../shared/peers/burgers1d_jax.py), to compare diffsim against."""

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
