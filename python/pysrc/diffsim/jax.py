"""diffsim operators inside JAX programs.

``operator(op)`` turns a :class:`diffsim.Operator` into a JAX function
``(x, p) -> y`` with a custom VJP: diffsim computes the forward and the
gradient through ``jax.pure_callback`` (host callbacks on NumPy arrays;
JAX's FFI is not used). It works under ``jax.jit``, ``jax.grad`` and
``jax.vmap`` (``vmap_method="broadcast_all"``: a batch reaches diffsim as a
leading axis and runs in parallel there). Forward-mode (``jax.jvp``) is not
wired: use ``Operator.jvp`` directly.

Needs ``jax`` with float64 enabled (``jax.config.update("jax_enable_x64",
True)``; this module turns it on when imported).
"""

from __future__ import annotations

import os
from typing import Callable

import jax
import jax.numpy as jnp
import numpy as np

from . import _diffsim

jax.config.update("jax_enable_x64", True)

__all__ = ["operator", "p1_loss", "scene_loss", "smoke_step", "burgers_step"]


def _batched_p(x: np.ndarray, p: np.ndarray, n_params: int) -> np.ndarray:
    """``p`` broadcast to ``x``'s batch axes (``[..., n_params]``)."""
    batch = x.shape[:-1]
    if p.ndim == 1:
        return np.broadcast_to(p, batch + (n_params,))
    # p batched by vmap over the leading axes: extend to x's native batch axes.
    extra = len(batch) - (p.ndim - 1)
    return np.broadcast_to(p.reshape(p.shape[:-1] + (1,) * extra + p.shape[-1:]), batch + (n_params,))


def operator(op: _diffsim.Operator) -> Callable[[jax.Array, jax.Array], jax.Array]:
    """``op`` as a JAX function ``f(x, p) -> y`` (``y``: ``x``'s batch axes
    and ``n_out``) whose VJP is diffsim's. ``p`` has ``op.n_params`` values
    (an empty array when there are none)."""
    n_in, n_out, n_params = op.n_in, op.n_out, op.n_params
    if n_in == 0:
        raise _diffsim.DiffsimError("an operator without inputs cannot be a JAX function of x")

    def params(x, p):
        # No parameters: nothing to pass (the common case, and the fastest).
        return None if n_params == 0 else np.ascontiguousarray(_batched_p(x, np.asarray(p, dtype=np.float64), n_params))

    def forward_host(x, p):
        x = np.asarray(x, dtype=np.float64)
        return op.forward(x, params(x, p))

    def vjp_host(x, p, dy):
        x = np.asarray(x, dtype=np.float64)
        return op.vjp(x, params(x, p), np.asarray(dy, dtype=np.float64))

    @jax.custom_vjp
    def f(x, p):
        out = jax.ShapeDtypeStruct(x.shape[:-1] + (n_out,), jnp.float64)
        return jax.pure_callback(forward_host, out, x, p, vmap_method="broadcast_all")

    def f_fwd(x, p):
        return f(x, p), (x, p)

    def f_bwd(res, dy):
        x, p = res
        shapes = (jax.ShapeDtypeStruct(x.shape, jnp.float64), jax.ShapeDtypeStruct(x.shape[:-1] + (n_params,), jnp.float64))
        dx, dp = jax.pure_callback(vjp_host, shapes, x, p, dy, vmap_method="broadcast_all")
        # A shared p: its gradient is the sum over x's batch axes.
        if p.ndim == 1:
            dp = dp.sum(axis=tuple(range(dp.ndim - 1)))
        return dx, dp.reshape(p.shape)

    f.defvjp(f_fwd, f_bwd)
    f.__doc__ = f"{op!r} as a JAX function (x, p) -> y."
    return f


def _of_x(op: _diffsim.Operator, squeeze: bool) -> Callable[[jax.Array], jax.Array]:
    f = operator(op)
    empty = jnp.zeros((0,), dtype=jnp.float64)

    def g(x):
        y = f(x, empty)
        return y[..., 0] if squeeze else y

    g.operator = op
    return g


def p1_loss(n: int, steps: int) -> Callable[[jax.Array], jax.Array]:
    """P1 (``../shared/benchmarks.md``): ``u0 -> L`` for ``u0`` of ``n``
    cells, ``steps`` steps of viscous Burgers, ``L = ½·dx·Σ (u_T − u*)²``;
    forward and gradient by diffsim. ``u0`` may have batch axes."""
    return _of_x(_diffsim.p1_loss(n, steps), squeeze=True)


def scene_loss(path: str | os.PathLike[str]) -> Callable[[jax.Array], jax.Array]:
    """The loss of the scene file at ``path`` (its ``[loss]`` table) as a
    function of its packed initial state; ``.x0`` is the scene's own
    initial state and ``.scene`` the :class:`diffsim.SceneFile`."""
    scene = _diffsim.SceneFile(path)
    g = _of_x(scene.loss_operator(), squeeze=True)
    g.x0 = jnp.asarray(scene.x0)
    g.scene = scene
    return g


def smoke_step(n: int) -> Callable[[jax.Array], jax.Array]:
    """One step of P2's 2D smoke solver on ``n × n`` cells: packed state in,
    packed state out (``n·n`` smoke values, then the face velocities)."""
    return _of_x(_diffsim.smoke_step(n), squeeze=False)


def burgers_step(n: int, dt: float, nu: float, length: float = 2 * np.pi) -> Callable[[jax.Array], jax.Array]:
    """One step of P1's Burgers scheme: ``u -> u_next``."""
    return _of_x(_diffsim.burgers_step(n, dt, nu, length), squeeze=False)
