"""diffsim operators inside JAX programs.

``operator(op)`` turns a :class:`diffsim.Operator` into a JAX function
``(x, p) -> y`` with a custom VJP: diffsim computes the forward and the
gradient, called from compiled JAX code through XLA's FFI
(``jax.ffi.ffi_call`` into the custom-call targets ``diffsim_forward`` and
``diffsim_vjp``, with XLA's buffers: no Python and no copies in between).
``operator(op, via="callback")`` uses ``jax.pure_callback`` instead (host
callbacks on NumPy arrays). It works under ``jax.jit``, ``jax.grad`` and
``jax.vmap`` (``vmap_method="broadcast_all"``: a batch reaches diffsim as a
leading axis and runs in parallel there). Forward-mode (``jax.jvp``) is not
wired: use ``Operator.jvp`` directly.

Needs ``jax`` with float64 enabled (``jax.config.update("jax_enable_x64",
True)``; this module turns it on when imported).
"""

from __future__ import annotations

import ctypes
import os
from typing import Callable

import jax
import jax.numpy as jnp
import numpy as np

from . import _diffsim

jax.config.update("jax_enable_x64", True)

# The FFI targets, registered once per process.
_HANDLER = ctypes.CFUNCTYPE(ctypes.c_void_p, ctypes.c_void_p)
_TARGETS = [_HANDLER(address) for _, address in _diffsim.ffi_targets()]
for (_name, _), _fn in zip(_diffsim.ffi_targets(), _TARGETS):
    jax.ffi.register_ffi_target(_name, jax.ffi.pycapsule(_fn), platform="cpu")

__all__ = ["operator", "p1_loss", "scene_loss", "smoke_step", "burgers_step"]


def _batched_p(x: np.ndarray, p: np.ndarray, n_params: int) -> np.ndarray:
    """``p`` broadcast to ``x``'s batch axes (``[..., n_params]``)."""
    batch = x.shape[:-1]
    if p.ndim == 1:
        return np.broadcast_to(p, batch + (n_params,))
    # p batched by vmap over the leading axes: extend to x's native batch axes.
    extra = len(batch) - (p.ndim - 1)
    return np.broadcast_to(p.reshape(p.shape[:-1] + (1,) * extra + p.shape[-1:]), batch + (n_params,))


def operator(op: _diffsim.Operator, via: str = "ffi") -> Callable[[jax.Array, jax.Array], jax.Array]:
    """``op`` as a JAX function ``f(x, p) -> y`` (``y``: ``x``'s batch axes
    and ``n_out``) whose VJP is diffsim's. ``p`` has ``op.n_params`` values
    (an empty array when there are none). ``via``: ``"ffi"`` (XLA's FFI,
    the default) or ``"callback"`` (``jax.pure_callback``)."""
    n_in, n_out, n_params = op.n_in, op.n_out, op.n_params
    if n_in == 0:
        raise _diffsim.DiffsimError("an operator without inputs cannot be a JAX function of x")
    if via not in ("ffi", "callback"):
        raise _diffsim.DiffsimError(f"via must be 'ffi' or 'callback', got {via!r}")

    def check(x, p):
        # Shapes are known when JAX traces: refuse mistakes here, in words.
        if x.ndim < 1 or x.shape[-1] != n_in:
            raise _diffsim.DiffsimError(f"x has shape {tuple(x.shape)}; its last axis must have length {n_in}")
        if p.ndim != 1 or p.shape[0] != n_params:
            raise _diffsim.DiffsimError(f"p has shape {tuple(p.shape)}; this operator has {n_params} parameters")

    if via == "ffi":
        op_id = np.int64(op.ffi_id())

        def call_forward(x, p):
            out = jax.ShapeDtypeStruct(x.shape[:-1] + (n_out,), jnp.float64)
            return jax.ffi.ffi_call("diffsim_forward", out, vmap_method="broadcast_all")(x, p, op_id=op_id)

        def call_vjp(x, p, dy):
            shapes = (jax.ShapeDtypeStruct(x.shape, jnp.float64), jax.ShapeDtypeStruct(x.shape[:-1] + (n_params,), jnp.float64))
            return jax.ffi.ffi_call("diffsim_vjp", shapes, vmap_method="broadcast_all")(x, p, dy, op_id=op_id)

    else:

        def params(x, p):
            # No parameters: nothing to pass (the common case, and the fastest).
            return None if n_params == 0 else np.ascontiguousarray(_batched_p(x, np.asarray(p, dtype=np.float64), n_params))

        def forward_host(x, p):
            x = np.asarray(x, dtype=np.float64)
            return op.forward(x, params(x, p))

        def vjp_host(x, p, dy):
            x = np.asarray(x, dtype=np.float64)
            return op.vjp(x, params(x, p), np.asarray(dy, dtype=np.float64))

        def call_forward(x, p):
            out = jax.ShapeDtypeStruct(x.shape[:-1] + (n_out,), jnp.float64)
            return jax.pure_callback(forward_host, out, x, p, vmap_method="broadcast_all")

        def call_vjp(x, p, dy):
            shapes = (jax.ShapeDtypeStruct(x.shape, jnp.float64), jax.ShapeDtypeStruct(x.shape[:-1] + (n_params,), jnp.float64))
            return jax.pure_callback(vjp_host, shapes, x, p, dy, vmap_method="broadcast_all")

    @jax.custom_vjp
    def f(x, p):
        check(x, p)
        return call_forward(jnp.asarray(x, jnp.float64), jnp.asarray(p, jnp.float64))

    def f_fwd(x, p):
        return f(x, p), (x, p)

    def f_bwd(res, dy):
        x, p = res
        dx, dp = call_vjp(x, p, dy)
        # A shared p: its gradient is the sum over x's batch axes.
        if p.ndim == 1:
            dp = dp.sum(axis=tuple(range(dp.ndim - 1)))
        return dx, dp.reshape(p.shape)

    f.defvjp(f_fwd, f_bwd)
    f.__doc__ = f"{op!r} as a JAX function (x, p) -> y."
    return f


def _of_x(op: _diffsim.Operator, squeeze: bool, via: str = "ffi") -> Callable[[jax.Array], jax.Array]:
    f = operator(op, via)
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
